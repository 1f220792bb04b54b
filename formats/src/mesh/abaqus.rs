//! Abaqus input deck (`.inp`) of a voxel mesh: C3D8 bricks, one element set, placeholder
//! material and solid section per phase, node sets on the six faces of the image box, and
//! for periodic axes node sets of periodic node pairs.
//!
//! Keywords per the Abaqus Keywords Reference: `*NODE` (label, x, y, z), `*ELEMENT,
//! TYPE=C3D8, ELSET=...` (label and eight nodes: the lower face counter-clockwise, then the
//! upper face, the same order as VTK's hexahedron), `*NSET` (at most 16 labels per data
//! line), `*MATERIAL`, `*SOLID SECTION, ELSET=..., MATERIAL=...`. Lines starting `**` are
//! comments. Node labels are point index + 1 (corner order, x fastest); element labels run
//! over the phases in the order selected.
//!
//! Periodic pairs: for each periodic axis, `PERIODIC_<A>_LO` holds the nodes on the lower
//! face whose translate by the box length is a node on the upper face, `PERIODIC_<A>_HI`
//! those translates. Abaqus sorts node sets by label, and both sets sort in the same
//! (other-axes) order, so the i-th node of `_LO` pairs with the i-th of `_HI`: `*EQUATION`
//! on the two sets ties every pair.

use super::VoxelHexMesh;
use std::collections::HashSet;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::Path;

/// Face node set names in [`grainpipe_core::FACE_NAMES`] order.
pub const FACE_SETS: [&str; 6] = ["XMIN", "XMAX", "YMIN", "YMAX", "ZMIN", "ZMAX"];

/// Abaqus labels for the phases: letters, digits and `_` only, starting with a letter, at
/// most 80 characters, unique ignoring case (Abaqus compares labels case-insensitively).
pub fn set_names(phases: &[(u8, String)]) -> Vec<String> {
    let mut seen = HashSet::new();
    phases
        .iter()
        .map(|(id, name)| {
            let mut t: String = name
                .chars()
                .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
                .collect();
            if !t.starts_with(|c: char| c.is_ascii_alphabetic()) {
                t = format!("PHASE{id}_{t}");
            }
            t.truncate(70);
            if !seen.insert(t.to_ascii_uppercase()) {
                t = format!("{t}_{id}");
                seen.insert(t.to_ascii_uppercase());
            }
            t
        })
        .collect()
}

fn write_set(w: &mut impl Write, keyword: &str, labels: &[u64]) -> io::Result<()> {
    w.write_all(format!("{keyword}\n").as_bytes())?;
    for line in labels.chunks(16) {
        let t: Vec<String> = line.iter().map(|l| l.to_string()).collect();
        w.write_all(t.join(", ").as_bytes())?;
        w.write_all(b"\n")?;
    }
    Ok(())
}

/// Writes the deck at `path` (a plain file; the caller makes it atomic). `phases` are the
/// selected (id, name) in output order; `comments` become `**` lines at the top.
pub fn write_inp(
    path: &Path,
    mesh: &VoxelHexMesh,
    phases: &[(u8, String)],
    periodic: [bool; 3],
    comments: &[String],
) -> io::Result<()> {
    let mut w = BufWriter::with_capacity(1 << 20, File::create(path)?);
    for c in comments {
        for line in c.lines() {
            w.write_all(format!("** {line}\n").as_bytes())?;
        }
    }
    let names = set_names(phases);
    w.write_all(
        b"** C3D8 voxel mesh, lengths in m. Element set, material and section per phase;\n\
          ** node sets XMIN..ZMAX on the faces of the image box; for periodic axes node sets\n\
          ** PERIODIC_<axis>_LO/_HI: the i-th node of _LO pairs with the i-th of _HI.\n\
          *HEADING\ngrainpipe voxel mesh\n*NODE\n",
    )?;
    let mut line = String::new();
    for (k, c) in mesh.point_corners().enumerate() {
        use std::fmt::Write as _;
        line.clear();
        let p = mesh.position(c);
        let _ = writeln!(line, "{}, {:e}, {:e}, {:e}", k + 1, p[0], p[1], p[2]);
        w.write_all(line.as_bytes())?;
    }
    let mut element = 0u64;
    let mut populated = Vec::new();
    for ((id, name), set) in phases.iter().zip(&names) {
        let mut cells = mesh
            .cells()
            .filter(|(v, _)| mesh.label(*v) == *id)
            .peekable();
        if cells.peek().is_none() {
            w.write_all(format!("** phase {name} ({id}) has no voxels: no elements\n").as_bytes())?;
            continue;
        }
        populated.push((id, name, set));
        w.write_all(format!("*ELEMENT, TYPE=C3D8, ELSET={set}\n").as_bytes())?;
        for (_, nodes) in cells {
            use std::fmt::Write as _;
            element += 1;
            line.clear();
            let _ = write!(line, "{element}");
            for n in nodes {
                let _ = write!(line, ", {}", n as u64 + 1);
            }
            line.push('\n');
            w.write_all(line.as_bytes())?;
        }
    }
    let dims = mesh.dims;
    for (f, set) in FACE_SETS.iter().enumerate() {
        let (axis, at) = (f / 2, if f % 2 == 0 { 0 } else { dims[f / 2] });
        let labels: Vec<u64> = mesh
            .point_corners()
            .enumerate()
            .filter(|(_, c)| c[axis] == at)
            .map(|(k, _)| k as u64 + 1)
            .collect();
        write_set(&mut w, &format!("*NSET, NSET={set}"), &labels)?;
    }
    for axis in (0..3).filter(|&a| periodic[a]) {
        let (lo, hi): (Vec<u64>, Vec<u64>) = mesh
            .point_corners()
            .enumerate()
            .filter(|(_, c)| c[axis] == 0)
            .filter_map(|(k, c)| {
                let mut up = c;
                up[axis] = dims[axis];
                mesh.point_at(up).map(|p| (k as u64 + 1, p as u64 + 1))
            })
            .unzip();
        let a = ["X", "Y", "Z"][axis];
        write_set(&mut w, &format!("*NSET, NSET=PERIODIC_{a}_LO"), &lo)?;
        write_set(&mut w, &format!("*NSET, NSET=PERIODIC_{a}_HI"), &hi)?;
    }
    for (id, name, set) in populated {
        w.write_all(
            format!(
                "*MATERIAL, NAME={set}\n\
                 ** placeholder for phase `{name}` (label {id}): add its behaviour, e.g.\n\
                 ** *ELASTIC\n** <E [Pa]>, <nu>\n\
                 *SOLID SECTION, ELSET={set}, MATERIAL={set}\n,\n"
            )
            .as_bytes(),
        )?;
    }
    w.flush()
}
