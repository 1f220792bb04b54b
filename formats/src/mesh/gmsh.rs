//! Gmsh MSH 4.1 ASCII (`.msh`) of a voxel mesh: one volume entity and one named physical
//! group (dimension 3) per phase, 8-node hexahedra (element type 5).
//!
//! Layout per the Gmsh reference manual, "MSH file format" (version 4.1): `$MeshFormat`
//! (`4.1 0 8`), `$PhysicalNames` (`dim tag "name"`), `$Entities` (no points, curves or
//! surfaces; each volume: tag, bounding box, one physical tag, no bounding surfaces),
//! `$Nodes` (blocks per entity: `dim tag parametric count`, the tags, then the coordinates),
//! `$Elements` (blocks per entity: `dim tag type count`, then `tag node...`). Gmsh's
//! hexahedron node order is VTK's. Node tags are point index + 1; a node shared by several
//! phases is listed once, in the block of the first selected phase that touches it.
//! Physical tag and entity tag of a phase = its label + 1 (tags must be positive).

use super::VoxelHexMesh;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::Path;

/// Bytes beyond the mesh itself: one owner byte per grid corner.
pub fn memory_bytes(dims: [usize; 3]) -> u64 {
    ((dims[0] + 1) * (dims[1] + 1) * (dims[2] + 1)) as u64
}

/// Writes the file at `path` (a plain file; the caller makes it atomic). `phases`: the
/// selected (id, name) in output order; `comment` goes into a `$Comments` section.
pub fn write_msh(
    path: &Path,
    mesh: &VoxelHexMesh,
    phases: &[(u8, String)],
    comment: &str,
) -> io::Result<()> {
    use std::fmt::Write as _;
    let mut w = BufWriter::with_capacity(1 << 20, File::create(path)?);
    // Which phase block lists each point: the first selected phase (in order) touching it.
    let mut rank_of = [u8::MAX; 256];
    for (r, (id, _)) in phases.iter().enumerate() {
        rank_of[*id as usize] = r as u8;
    }
    const NONE: u8 = u8::MAX;
    let corners = memory_bytes(mesh.dims) as usize;
    let mut owner = vec![NONE; corners];
    let mut counts = vec![0usize; phases.len()];
    let [nx, ny, _] = mesh.dims;
    for (v, _) in mesh.cells() {
        let r = rank_of[mesh.label(v) as usize];
        counts[r as usize] += 1;
        let (x, y, z) = (v % nx, (v / nx) % ny, v / (nx * ny));
        for c in super::HEX_CORNERS {
            let k = mesh.corner_index([x + c[0], y + c[1], z + c[2]]);
            owner[k] = owner[k].min(r);
        }
    }
    let populated: Vec<usize> = (0..phases.len()).filter(|&r| counts[r] > 0).collect();
    let tag = |r: usize| phases[r].0 as usize + 1;
    let mut s = String::from("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Comments\n");
    for line in comment.lines() {
        s.push_str(line);
        s.push('\n');
    }
    s.push_str("$EndComments\n$PhysicalNames\n");
    let _ = writeln!(s, "{}", populated.len());
    for &r in &populated {
        let _ = writeln!(
            s,
            "3 {} \"{}\"",
            tag(r),
            phases[r].1.replace(['"', '\n'], "'")
        );
    }
    s.push_str("$EndPhysicalNames\n$Entities\n");
    let _ = writeln!(s, "0 0 0 {}", populated.len());
    let lo = mesh.origin;
    let hi = mesh.position(mesh.dims);
    for &r in &populated {
        let _ = writeln!(
            s,
            "{} {:e} {:e} {:e} {:e} {:e} {:e} 1 {} 0",
            tag(r),
            lo[0],
            lo[1],
            lo[2],
            hi[0],
            hi[1],
            hi[2],
            tag(r)
        );
    }
    s.push_str("$EndEntities\n$Nodes\n");
    let np = mesh.point_count();
    let _ = writeln!(s, "{} {np} {} {np}", populated.len(), np.min(1));
    w.write_all(s.as_bytes())?;
    // Point index and corner of each point, in point order, for one pass per block.
    for &r in &populated {
        let owner = &owner;
        let mine = move || {
            mesh.point_corners()
                .enumerate()
                .filter(move |(_, c)| owner[mesh.corner_index(*c)] == r as u8)
        };
        let count = mine().count();
        w.write_all(format!("3 {} 0 {count}\n", tag(r)).as_bytes())?;
        let mut line = String::new();
        for (k, _) in mine() {
            line.clear();
            let _ = writeln!(line, "{}", k + 1);
            w.write_all(line.as_bytes())?;
        }
        for (_, c) in mine() {
            let p = mesh.position(c);
            line.clear();
            let _ = writeln!(line, "{:e} {:e} {:e}", p[0], p[1], p[2]);
            w.write_all(line.as_bytes())?;
        }
    }
    let ne = mesh.cell_count();
    w.write_all(
        format!(
            "$EndNodes\n$Elements\n{} {ne} {} {ne}\n",
            populated.len(),
            ne.min(1)
        )
        .as_bytes(),
    )?;
    let mut element = 0usize;
    let mut line = String::new();
    for &r in &populated {
        let id = phases[r].0;
        w.write_all(format!("3 {} 5 {}\n", tag(r), counts[r]).as_bytes())?;
        for (_, nodes) in mesh.cells().filter(|(v, _)| mesh.label(*v) == id) {
            element += 1;
            line.clear();
            let _ = write!(line, "{element}");
            for n in nodes {
                let _ = write!(line, " {}", n as u64 + 1);
            }
            line.push('\n');
            w.write_all(line.as_bytes())?;
        }
    }
    w.write_all(b"$EndElements\n")?;
    w.flush()
}

/// Writes interface surfaces (see [`super::surface`]) at `path`: one surface entity and one
/// named physical group (dimension 2) per interface, `names[k]` = `"<a>|<b>"`, tag = k + 1
/// (the `interface` id of the `.vtu`); 3-node triangles (element type 2) whose normals
/// point out of phase b into phase a; `$ElementData` views `phase_a` and `phase_b` with the
/// labels (-1 = exterior). A node shared by several interfaces is listed once, in the block
/// of the first interface that touches it.
pub fn write_surface_msh(
    path: &Path,
    mesh: &super::surface::InterfaceMesh,
    names: &[String],
    comment: &str,
) -> io::Result<()> {
    use std::fmt::Write as _;
    let mut w = BufWriter::with_capacity(1 << 20, File::create(path)?);
    let np = mesh.points.len();
    let ni = mesh.pairs.len();
    let mut owner = vec![u16::MAX; np];
    for (t, &k) in mesh.triangles.iter().zip(&mesh.interface) {
        for &v in t {
            owner[v as usize] = owner[v as usize].min(k);
        }
    }
    let mut s = String::from("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Comments\n");
    for line in comment.lines() {
        s.push_str(line);
        s.push('\n');
    }
    s.push_str("$EndComments\n$PhysicalNames\n");
    let _ = writeln!(s, "{ni}");
    for (k, name) in names.iter().enumerate() {
        let _ = writeln!(s, "2 {} \"{}\"", k + 1, name.replace(['"', '\n'], "'"));
    }
    s.push_str("$EndPhysicalNames\n$Entities\n");
    let _ = writeln!(s, "0 0 {ni} 0");
    for k in 0..ni {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for t in mesh.interface_triangles(k) {
            for &v in t {
                let p = mesh.points[v as usize];
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
            }
        }
        let _ = writeln!(
            s,
            "{} {:e} {:e} {:e} {:e} {:e} {:e} 1 {} 0",
            k + 1,
            lo[0],
            lo[1],
            lo[2],
            hi[0],
            hi[1],
            hi[2],
            k + 1
        );
    }
    s.push_str("$EndEntities\n$Nodes\n");
    let _ = writeln!(s, "{ni} {np} {} {np}", np.min(1));
    w.write_all(s.as_bytes())?;
    // Points grouped by owning interface (a counting sort), in point order within each.
    let mut start = vec![0usize; ni + 1];
    for &o in &owner {
        start[o as usize + 1] += 1;
    }
    for k in 0..ni {
        start[k + 1] += start[k];
    }
    let mut grouped = vec![0u32; np];
    let mut fill = start.clone();
    for (v, &o) in owner.iter().enumerate() {
        grouped[fill[o as usize]] = v as u32;
        fill[o as usize] += 1;
    }
    drop(owner);
    let mut line = String::new();
    for k in 0..ni {
        let mine = &grouped[start[k]..start[k + 1]];
        w.write_all(format!("2 {} 0 {}\n", k + 1, mine.len()).as_bytes())?;
        for &v in mine {
            line.clear();
            let _ = writeln!(line, "{}", v + 1);
            w.write_all(line.as_bytes())?;
        }
        for &v in mine {
            let p = mesh.points[v as usize];
            line.clear();
            let _ = writeln!(line, "{:e} {:e} {:e}", p[0], p[1], p[2]);
            w.write_all(line.as_bytes())?;
        }
    }
    let ne = mesh.triangles.len();
    w.write_all(format!("$EndNodes\n$Elements\n{ni} {ne} {} {ne}\n", ne.min(1)).as_bytes())?;
    let mut element = 0usize;
    for k in 0..ni {
        let tris = mesh.interface_triangles(k);
        w.write_all(format!("2 {} 2 {}\n", k + 1, tris.len()).as_bytes())?;
        for t in tris {
            element += 1;
            line.clear();
            let _ = writeln!(line, "{element} {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
            w.write_all(line.as_bytes())?;
        }
    }
    w.write_all(b"$EndElements\n")?;
    for (side, name) in [(0, "phase_a"), (1, "phase_b")] {
        w.write_all(format!("$ElementData\n1\n\"{name}\"\n1\n0\n3\n0\n1\n{ne}\n").as_bytes())?;
        for (e, &k) in mesh.interface.iter().enumerate() {
            line.clear();
            let _ = writeln!(line, "{} {}", e + 1, mesh.pairs[k as usize][side]);
            w.write_all(line.as_bytes())?;
        }
        w.write_all(b"$EndElementData\n")?;
    }
    w.flush()
}
