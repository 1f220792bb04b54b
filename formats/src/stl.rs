//! Binary STL surfaces: the spheres of a packing or clump library as icospheres, or the
//! boundary of one phase of a phase image by marching tetrahedra.
//!
//! Marching tetrahedra (not cubes) because splitting every cube of voxel centres into the
//! same six tetrahedra around its main diagonal has no ambiguous cases: the surface is a
//! closed 2-manifold (every edge in exactly two triangles) for any labelling, which 3-D
//! printing slicers and meshers require. With 0/1 values every vertex sits on the midpoint
//! of a tetrahedron edge.

use crate::volume::VolumeRef;
use grainpipe_core::fsutil::{atomic_write, check_interrupt};
use grainpipe_core::registry::{ExportOption, ExportOptions};
use grainpipe_core::{Artifact, ArtifactKind, Exporter, PhaseImage, Provenance};
use std::path::Path;

pub type Triangle = [[f64; 3]; 3];

/// The unit icosphere: an icosahedron whose faces are split in four `subdivisions` times,
/// new vertices pushed onto the sphere (20 * 4^s triangles, outward winding).
pub fn icosphere(subdivisions: u32) -> Vec<Triangle> {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let v: Vec<[f64; 3]> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|p| unit(*p))
    .collect();
    const F: [[usize; 3]; 20] = [
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    let mut tris: Vec<Triangle> = F.iter().map(|f| [v[f[0]], v[f[1]], v[f[2]]]).collect();
    for _ in 0..subdivisions {
        let mut next = Vec::with_capacity(tris.len() * 4);
        for [a, b, c] in tris {
            let ab = unit(mid(a, b));
            let bc = unit(mid(b, c));
            let ca = unit(mid(c, a));
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        tris = next;
    }
    tris
}

fn mid(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|k| 0.5 * (a[k] + b[k]))
}

fn unit(a: [f64; 3]) -> [f64; 3] {
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    a.map(|x| x / n)
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Volume enclosed by a closed, outward-wound triangle surface (divergence theorem).
pub fn enclosed_volume(tris: &[Triangle]) -> f64 {
    tris.iter()
        .map(|[a, b, c]| dot(*a, cross(*b, *c)) / 6.0)
        .sum()
}

/// Spheres (centre, radius) as icospheres.
pub fn sphere_surfaces(spheres: &[([f64; 3], f64)], subdivisions: u32) -> Vec<Triangle> {
    let unit = icosphere(subdivisions);
    let mut out = Vec::with_capacity(unit.len() * spheres.len());
    for (c, r) in spheres {
        out.extend(
            unit.iter()
                .map(|t| t.map(|p| [0, 1, 2].map(|k| c[k] + r * p[k]))),
        );
    }
    out
}

/// Cube corners by bit (x = bit 0, y = bit 1, z = bit 2); six tetrahedra around the 0-7
/// diagonal, the same in every cube, so neighbouring cubes split shared faces alike.
const TETS: [[usize; 4]; 6] = [
    [0, 1, 3, 7],
    [0, 3, 2, 7],
    [0, 2, 6, 7],
    [0, 6, 4, 7],
    [0, 4, 5, 7],
    [0, 5, 1, 7],
];

/// The boundary of `phase` in `img`: marching tetrahedra over the voxel centres, the image
/// padded by one layer outside the phase so the surface closes at the image faces. Vertices
/// are midpoints between voxel centres; coordinates in metres.
pub fn phase_surface(img: &PhaseImage, phase: u8) -> Vec<Triangle> {
    let mut out = Vec::new();
    for z in -1..img.grid.dims[2] as i64 {
        phase_surface_slab(img, phase, z, &mut out);
    }
    out
}

/// The triangles of [`phase_surface`] in the layer of cubes between voxel centres `z` and
/// `z + 1` (`z` from -1 to nz - 1), appended to `out`: what a streaming export holds at a time.
pub fn phase_surface_slab(img: &PhaseImage, phase: u8, z: i64, out: &mut Vec<Triangle>) {
    let g = &img.grid;
    let [nx, ny, nz] = g.dims.map(|d| d as i64);
    let inside = |x: i64, y: i64, z: i64| {
        x >= 0
            && y >= 0
            && z >= 0
            && x < nx
            && y < ny
            && z < nz
            && img.labels[g.index(x as usize, y as usize, z as usize)] == phase
    };
    // Positions in half-voxel units from the lower grid corner: voxel centre (x) is 2x + 1,
    // so every midpoint is an integer point and shared vertices are bit-identical.
    let world = |p: [i64; 3]| [0, 1, 2].map(|k| g.origin[k] + 0.5 * p[k] as f64 * g.spacing[k]);
    for y in -1..ny {
        for x in -1..nx {
            let corner = |b: usize| {
                [
                    x + (b & 1) as i64,
                    y + ((b >> 1) & 1) as i64,
                    z + ((b >> 2) & 1) as i64,
                ]
            };
            let ins: [bool; 8] = std::array::from_fn(|b| {
                let c = corner(b);
                inside(c[0], c[1], c[2])
            });
            if ins.iter().all(|&i| i) || ins.iter().all(|&i| !i) {
                continue;
            }
            let pos = |b: usize| corner(b).map(|c| 2 * c + 1);
            for tet in TETS {
                let (inn, outs): (Vec<usize>, Vec<usize>) = tet.iter().partition(|&&b| ins[b]);
                if inn.is_empty() || outs.is_empty() {
                    continue;
                }
                let m = |a: usize, b: usize| {
                    let (p, q) = (pos(a), pos(b));
                    [0, 1, 2].map(|k| (p[k] + q[k]) / 2)
                };
                let polys: Vec<[[i64; 3]; 3]> = match (inn.len(), outs.len()) {
                    (1, 3) => {
                        vec![[m(inn[0], outs[0]), m(inn[0], outs[1]), m(inn[0], outs[2])]]
                    }
                    (3, 1) => {
                        vec![[m(outs[0], inn[0]), m(outs[0], inn[1]), m(outs[0], inn[2])]]
                    }
                    _ => {
                        // Quad a-b-c-d around the tetrahedron, split along a-c.
                        let (i0, i1, o0, o1) = (inn[0], inn[1], outs[0], outs[1]);
                        let (a, b, c, d) = (m(i0, o0), m(i0, o1), m(i1, o1), m(i1, o0));
                        vec![[a, b, c], [a, c, d]]
                    }
                };
                let ci = centroid(inn.iter().map(|&b| pos(b)));
                let co = centroid(outs.iter().map(|&b| pos(b)));
                for p in polys {
                    let t = p.map(world);
                    let n = cross(sub(t[1], t[0]), sub(t[2], t[0]));
                    // Normals point from the phase outwards.
                    let outward = dot(n, sub(world_f(g, co), world_f(g, ci))) >= 0.0;
                    out.push(if outward { t } else { [t[0], t[2], t[1]] });
                }
            }
        }
    }
}

fn centroid(ps: impl Iterator<Item = [i64; 3]>) -> [f64; 3] {
    let mut s = [0.0; 3];
    let mut n = 0.0;
    for p in ps {
        for k in 0..3 {
            s[k] += p[k] as f64;
        }
        n += 1.0;
    }
    s.map(|x| x / n)
}

fn world_f(g: &grainpipe_core::Grid, p: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|k| g.origin[k] + 0.5 * p[k] * g.spacing[k])
}

/// The 80-byte header of a binary STL (never starting with "solid", which makes some readers
/// take the file for ASCII STL).
fn stl_header(header: &str) -> Vec<u8> {
    let mut h = header.as_bytes().to_vec();
    if h.starts_with(b"solid") {
        h.insert(0, b' ');
    }
    h.resize(80, b' ');
    h
}

/// One triangle as its 50 bytes of binary STL (normal, three vertices, attribute 0).
fn put_triangle(b: &mut Vec<u8>, t: &Triangle, scale: f64) {
    let nrm = unit(cross(sub(t[1], t[0]), sub(t[2], t[0])));
    let nrm = if nrm.iter().all(|x| x.is_finite()) {
        nrm
    } else {
        [0.0; 3]
    };
    for x in nrm {
        b.extend_from_slice(&(x as f32).to_le_bytes());
    }
    for p in t {
        for x in p {
            b.extend_from_slice(&((x * scale) as f32).to_le_bytes());
        }
    }
    b.extend_from_slice(&0u16.to_le_bytes());
}

/// Binary STL bytes; `scale` converts metres to the file's length unit.
pub fn stl_bytes(tris: &[Triangle], scale: f64, header: &str) -> Result<Vec<u8>, String> {
    let n = u32::try_from(tris.len())
        .map_err(|_| format!("{} triangles exceed what binary STL counts", tris.len()))?;
    let mut b = Vec::with_capacity(84 + 50 * tris.len());
    b.extend_from_slice(&stl_header(header));
    b.extend_from_slice(&n.to_le_bytes());
    for t in tris {
        put_triangle(&mut b, t, scale);
    }
    Ok(b)
}

/// A binary STL written as its triangles come: the count is filled in at the end, so the
/// surface is never held in memory (a 333^3 image's boundary is several GB of triangles).
struct StlStream {
    file: std::io::BufWriter<std::fs::File>,
    path: std::path::PathBuf,
    scale: f64,
    count: u64,
    buf: Vec<u8>,
}

impl StlStream {
    fn create(path: &Path, header: &str, scale: f64) -> Result<Self, String> {
        use std::io::Write;
        let at = |e: std::io::Error| format!("{}: {e}", path.display());
        let mut file =
            std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(path).map_err(at)?);
        file.write_all(&stl_header(header)).map_err(at)?;
        file.write_all(&0u32.to_le_bytes()).map_err(at)?;
        Ok(StlStream {
            file,
            path: path.to_path_buf(),
            scale,
            count: 0,
            buf: Vec::with_capacity(50),
        })
    }

    fn push(&mut self, t: &Triangle) -> Result<(), String> {
        use std::io::Write;
        self.buf.clear();
        put_triangle(&mut self.buf, t, self.scale);
        self.count += 1;
        self.file
            .write_all(&self.buf)
            .map_err(|e| format!("{}: {e}", self.path.display()))
    }

    /// Writes the triangle count into the header; fails when binary STL cannot count them.
    fn finish(self) -> Result<(), String> {
        use std::io::{Seek, SeekFrom, Write};
        let at = |e: std::io::Error| format!("{}: {e}", self.path.display());
        let n = u32::try_from(self.count)
            .map_err(|_| format!("{} triangles exceed what binary STL counts", self.count))?;
        let mut f = self.file.into_inner().map_err(|e| at(e.into_error()))?;
        f.seek(SeekFrom::Start(80)).map_err(at)?;
        f.write_all(&n.to_le_bytes()).map_err(at)?;
        f.flush().map_err(at)
    }
}

/// Peak memory of an STL export [bytes]: the triangles of one layer of cubes of an image
/// (at most 12 per cube), or one icosphere, plus the write buffer.
fn stl_export_bytes(meta: &grainpipe_core::ArtifactMeta) -> u64 {
    let layer = meta.grid.as_ref().map_or(0u64, |g| {
        let per_cube = 12 * std::mem::size_of::<Triangle>() as u64;
        (g.dims[0] as u64 + 1)
            .saturating_mul(g.dims[1] as u64 + 1)
            .saturating_mul(per_cube)
    });
    let sphere = 20 * 4u64.pow(6) * std::mem::size_of::<Triangle>() as u64;
    layer.max(sphere).saturating_add(2 << 20)
}

/// Reads binary STL triangles back (coordinates in the file's unit).
pub fn read_stl(bytes: &[u8]) -> Result<Vec<Triangle>, String> {
    if bytes.len() < 84 {
        return Err("shorter than a binary STL header".into());
    }
    let n = u32::from_le_bytes(bytes[80..84].try_into().expect("4 bytes")) as usize;
    if bytes.len() != 84 + 50 * n {
        return Err(format!("{} bytes for {n} triangles", bytes.len()));
    }
    let f = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes")) as f64;
    Ok((0..n)
        .map(|i| {
            let o = 84 + 50 * i + 12;
            std::array::from_fn(|v| std::array::from_fn(|k| f(o + 12 * v + 4 * k)))
        })
        .collect())
}

fn scale_of(v: &serde_json::Value) -> Result<f64, String> {
    match v.as_str() {
        Some("m") => Ok(1.0),
        Some("mm") => Ok(1e3),
        Some("um") => Ok(1e6),
        _ => Err(format!(
            "{v} is not a length unit of the file; write `mm` (what CAD and slicers assume), \
             `um` or `m`"
        )),
    }
}

fn subdivisions(v: &serde_json::Value) -> Result<u32, String> {
    v.as_u64()
        .filter(|&s| s <= 6)
        .map(|s| s as u32)
        .ok_or_else(|| format!("{v}: give 0..=6 (20 * 4^s triangles per sphere; 2 gives 320)"))
}

fn phase_of(v: &serde_json::Value) -> Result<u8, String> {
    v.as_u64()
        .and_then(|p| u8::try_from(p).ok())
        .ok_or_else(|| format!("{v}: give a phase label 0..=255"))
}

/// The `stl` exporter.
pub struct StlExporter;

impl Exporter for StlExporter {
    fn name(&self) -> &'static str {
        "stl"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["stl"]
    }
    fn accepts(&self, kind: ArtifactKind) -> bool {
        matches!(
            kind,
            ArtifactKind::Packing | ArtifactKind::ClumpLibrary | ArtifactKind::PhaseImage
        )
    }
    fn doc(&self) -> &'static str {
        "Binary STL. A packing (clumps expanded) or a clump library (clump k shifted along x \
         by its index times twice the largest bounding radius): every sphere as an icosphere \
         with vertices on the sphere. A phase image: the closed, watertight boundary of \
         phase `phase` by marching tetrahedra over the voxel centres (vertices midway \
         between voxel centres, the image padded outside). Normals point outwards."
    }
    fn options(&self) -> Vec<ExportOption> {
        vec![
            ExportOption {
                name: "subdivisions",
                doc: "icosphere refinement: 20 * 4^s triangles per sphere (0..=6)",
                default: serde_json::json!(2),
            },
            ExportOption {
                name: "phase",
                doc: "phase label whose boundary an image export writes",
                default: serde_json::json!(1),
            },
            ExportOption {
                name: "length_unit",
                doc: "unit of the coordinates: `mm` (CAD and slicers), `um` or `m`",
                default: serde_json::json!("mm"),
            },
        ]
    }
    fn check_options(&self, o: &ExportOptions) -> Result<(), (String, String)> {
        subdivisions(&o["subdivisions"]).map_err(|m| ("subdivisions".to_string(), m))?;
        phase_of(&o["phase"]).map_err(|m| ("phase".to_string(), m))?;
        scale_of(&o["length_unit"]).map_err(|m| ("length_unit".to_string(), m))?;
        Ok(())
    }
    fn write(
        &self,
        a: &Artifact,
        path: &Path,
        prov: &Provenance,
        o: &ExportOptions,
    ) -> Result<(), String> {
        let get = |k: &str| o.get(k).cloned().unwrap_or(serde_json::Value::Null);
        let s = subdivisions(&get("subdivisions"))?;
        let scale = scale_of(&get("length_unit"))?;
        // Spheres as (centre, radius); an image's surface is written layer by layer.
        let spheres: Vec<([f64; 3], f64)> = match a {
            Artifact::Packing(p) => {
                a.validate()?;
                p.world_spheres()
                    .iter()
                    .map(|w| (w.center, w.radius))
                    .collect()
            }
            Artifact::ClumpLibrary(l) => {
                let pitch = 2.0
                    * l.clumps
                        .iter()
                        .map(|c| c.bounding_radius)
                        .fold(0.0, f64::max);
                l.clumps
                    .iter()
                    .enumerate()
                    .flat_map(|(k, c)| {
                        c.spheres.iter().map(move |sp| {
                            let o = sp.offset;
                            ([o[0] + k as f64 * pitch, o[1], o[2]], sp.radius)
                        })
                    })
                    .collect()
            }
            Artifact::PhaseImage(img) => {
                VolumeRef::Phase(img).validate()?;
                let phase = phase_of(&get("phase"))?;
                if !img.labels.contains(&phase) {
                    return Err(format!(
                        "no voxel has phase {phase}; phases present: {}",
                        img.phases
                            .iter()
                            .map(|p| format!("{} ({})", p.id, p.name))
                            .collect::<Vec<_>>()
                            .join(", ")
                    ));
                }
                Vec::new()
            }
            other => return Err(format!("stl cannot hold a {}", other.kind())),
        };
        let header = format!(
            "grainpipe {} STL",
            prov.entries
                .get("pipeline")
                .map(|s| s.as_str())
                .unwrap_or("")
        );
        atomic_write(path, |tmp| -> Result<(), String> {
            let mut out = StlStream::create(tmp, &header, scale)?;
            if let Artifact::PhaseImage(img) = a {
                let phase = phase_of(&get("phase"))?;
                let mut layer = Vec::new();
                for z in -1..img.grid.dims[2] as i64 {
                    check_interrupt()?;
                    layer.clear();
                    phase_surface_slab(img, phase, z, &mut layer);
                    layer.iter().try_for_each(|t| out.push(t))?;
                }
            } else {
                let unit_sphere = icosphere(s);
                for (k, (c, r)) in spheres.iter().enumerate() {
                    if k % 4096 == 0 {
                        check_interrupt()?;
                    }
                    for t in &unit_sphere {
                        out.push(&t.map(|p| [0, 1, 2].map(|k| c[k] + r * p[k])))?;
                    }
                }
            }
            out.finish()
        })
    }
    fn memory_bytes(&self, meta: &grainpipe_core::ArtifactMeta, _: &ExportOptions) -> u64 {
        stl_export_bytes(meta)
    }
}
