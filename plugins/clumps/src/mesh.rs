//! Closed triangle meshes (STL ASCII/binary, OBJ) and their voxelization by ray parity.

use crate::shape::{VoxelizeError, Voxelized};
use std::collections::HashMap;
use std::path::Path;

#[derive(Clone, Debug, Default)]
pub struct Mesh {
    pub vertices: Vec<[f64; 3]>,
    pub triangles: Vec<[usize; 3]>,
}

fn parse_f(s: &str, path: &Path, line: usize) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| format!("{}:{line}: bad number `{s}`", path.display()))
}

impl Mesh {
    /// Reads `.stl` (ASCII or binary) or `.obj` by extension.
    pub fn read(path: &Path) -> Result<Mesh, String> {
        let bytes =
            std::fs::read(path).map_err(|e| format!("{}: cannot read: {e}", path.display()))?;
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        match ext.as_str() {
            "stl" => Self::parse_stl(&bytes, path),
            "obj" => Self::parse_obj(&String::from_utf8_lossy(&bytes), path),
            _ => Err(format!(
                "{}: unknown mesh format (expected .stl or .obj)",
                path.display()
            )),
        }
    }

    fn from_soup(soup: Vec<[[f64; 3]; 3]>) -> Mesh {
        // STL repeats vertices per facet: weld exact duplicates so edges can be matched.
        let mut m = Mesh::default();
        let mut index: HashMap<[u64; 3], usize> = HashMap::new();
        for t in soup {
            let ids = t.map(|p| {
                *index.entry(p.map(f64::to_bits)).or_insert_with(|| {
                    m.vertices.push(p);
                    m.vertices.len() - 1
                })
            });
            m.triangles.push(ids);
        }
        m
    }

    pub fn parse_stl(bytes: &[u8], path: &Path) -> Result<Mesh, String> {
        // Binary STL: 80-byte header, u32 count, 50 bytes per facet. Some binary files
        // start with "solid", so the size check decides.
        if bytes.len() >= 84 {
            let n = u32::from_le_bytes(bytes[80..84].try_into().expect("4 bytes")) as usize;
            if bytes.len() == 84 + 50 * n {
                let mut soup = Vec::with_capacity(n);
                for k in 0..n {
                    let b = &bytes[84 + 50 * k..];
                    let f = |o: usize| {
                        f32::from_le_bytes(b[o..o + 4].try_into().expect("4 bytes")) as f64
                    };
                    soup.push([0, 1, 2].map(|v| [0, 1, 2].map(|a| f(12 + 12 * v + 4 * a))));
                }
                return Ok(Self::from_soup(soup));
            }
        }
        let text = String::from_utf8_lossy(bytes);
        if !text.trim_start().starts_with("solid") {
            return Err(format!(
                "{}: neither binary STL (size {} does not match its facet count) nor ASCII STL",
                path.display(),
                bytes.len()
            ));
        }
        let mut soup = Vec::new();
        let mut cur: Vec<[f64; 3]> = Vec::new();
        for (ln, line) in text.lines().enumerate() {
            let t: Vec<&str> = line.split_whitespace().collect();
            match t.first() {
                Some(&"vertex") => {
                    if t.len() != 4 {
                        return Err(format!("{}:{}: `vertex x y z`", path.display(), ln + 1));
                    }
                    cur.push([
                        parse_f(t[1], path, ln + 1)?,
                        parse_f(t[2], path, ln + 1)?,
                        parse_f(t[3], path, ln + 1)?,
                    ]);
                }
                Some(&"endfacet") => {
                    if cur.len() != 3 {
                        return Err(format!(
                            "{}:{}: a facet has {} vertices, expected 3",
                            path.display(),
                            ln + 1,
                            cur.len()
                        ));
                    }
                    soup.push([cur[0], cur[1], cur[2]]);
                    cur.clear();
                }
                _ => {}
            }
        }
        if soup.is_empty() {
            return Err(format!("{}: no facets", path.display()));
        }
        Ok(Self::from_soup(soup))
    }

    pub fn parse_obj(text: &str, path: &Path) -> Result<Mesh, String> {
        let mut m = Mesh::default();
        for (ln, line) in text.lines().enumerate() {
            let t: Vec<&str> = line.split_whitespace().collect();
            match t.first() {
                Some(&"v") => {
                    if t.len() < 4 {
                        return Err(format!("{}:{}: `v x y z`", path.display(), ln + 1));
                    }
                    m.vertices.push([
                        parse_f(t[1], path, ln + 1)?,
                        parse_f(t[2], path, ln + 1)?,
                        parse_f(t[3], path, ln + 1)?,
                    ]);
                }
                Some(&"f") => {
                    let mut ids = Vec::new();
                    for tok in &t[1..] {
                        let s = tok.split('/').next().unwrap_or("");
                        let i: i64 = s.parse().map_err(|_| {
                            format!("{}:{}: bad face index `{tok}`", path.display(), ln + 1)
                        })?;
                        // OBJ indices are 1-based; negative ones count back from the end.
                        let k = if i > 0 {
                            i - 1
                        } else {
                            m.vertices.len() as i64 + i
                        };
                        if k < 0 || k >= m.vertices.len() as i64 {
                            return Err(format!(
                                "{}:{}: face index {i} out of range",
                                path.display(),
                                ln + 1
                            ));
                        }
                        ids.push(k as usize);
                    }
                    if ids.len() < 3 {
                        return Err(format!(
                            "{}:{}: face with < 3 vertices",
                            path.display(),
                            ln + 1
                        ));
                    }
                    for k in 1..ids.len() - 1 {
                        m.triangles.push([ids[0], ids[k], ids[k + 1]]);
                    }
                }
                _ => {}
            }
        }
        if m.triangles.is_empty() {
            return Err(format!("{}: no faces", path.display()));
        }
        Ok(m)
    }

    /// Edges used by other than exactly two triangles (0 for a closed manifold surface).
    pub fn open_edges(&self) -> usize {
        let mut count: HashMap<(usize, usize), u32> = HashMap::new();
        for t in &self.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *count.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
        count.values().filter(|&&c| c != 2).count()
    }

    /// Enclosed volume (divergence theorem) and area.
    pub fn volume_area(&self) -> (f64, f64) {
        let mut v = 0.0;
        let mut a = 0.0;
        for t in &self.triangles {
            let [p, q, r] = t.map(|i| self.vertices[i]);
            v += (p[0] * (q[1] * r[2] - q[2] * r[1]) - p[1] * (q[0] * r[2] - q[2] * r[0])
                + p[2] * (q[0] * r[1] - q[1] * r[0]))
                / 6.0;
            let u = [0, 1, 2].map(|k| q[k] - p[k]);
            let w = [0, 1, 2].map(|k| r[k] - p[k]);
            let c = [
                u[1] * w[2] - u[2] * w[1],
                u[2] * w[0] - u[0] * w[2],
                u[0] * w[1] - u[1] * w[0],
            ];
            a += 0.5 * (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
        }
        (v.abs(), a)
    }

    pub fn scale(&mut self, s: f64) {
        for v in &mut self.vertices {
            *v = v.map(|c| c * s);
        }
    }

    /// Voxel mask at voxel size `h`: a voxel is inside when a ray from its centre along +x
    /// crosses the surface an odd number of times (ray parity, exact for closed surfaces).
    /// Each (y, z) row gathers its crossings from the triangles over it, so the cost is
    /// O(rows under each triangle + voxels). One empty layer is left around.
    pub fn voxelize(&self, h: f64) -> Result<Voxelized, VoxelizeError> {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for v in &self.vertices {
            for a in 0..3 {
                lo[a] = lo[a].min(v[a]);
                hi[a] = hi[a].max(v[a]);
            }
        }
        let start = lo.map(|v| ((v / h).floor() - 1.0) * h);
        let dims = [0, 1, 2].map(|a| (((hi[a] - start[a]) / h).ceil() as usize) + 1);
        let n = dims[0] * dims[1] * dims[2];
        if n > 400_000_000 {
            return Err(VoxelizeError::TooManyVoxels { what: "mesh", dims });
        }
        // A tiny irrational shift of the ray keeps it off vertices and edges that sit
        // exactly on voxel-centre rows (a parity count is only exact off them).
        let (ey, ez) = (0.618_033_988_7e-7 * h, 0.414_213_562_3e-7 * h);
        let mut crossings: Vec<Vec<f64>> = vec![Vec::new(); dims[1] * dims[2]];
        for t in &self.triangles {
            let [p, q, r] = t.map(|i| self.vertices[i]);
            let ymin = p[1].min(q[1]).min(r[1]);
            let ymax = p[1].max(q[1]).max(r[1]);
            let zmin = p[2].min(q[2]).min(r[2]);
            let zmax = p[2].max(q[2]).max(r[2]);
            let jy0 = (((ymin - start[1]) / h - 0.5).floor().max(0.0)) as usize;
            let jy1 = ((((ymax - start[1]) / h - 0.5).ceil()) as usize).min(dims[1] - 1);
            let jz0 = (((zmin - start[2]) / h - 0.5).floor().max(0.0)) as usize;
            let jz1 = ((((zmax - start[2]) / h - 0.5).ceil()) as usize).min(dims[2] - 1);
            for jz in jz0..=jz1 {
                let zc = start[2] + (jz as f64 + 0.5) * h + ez;
                for jy in jy0..=jy1 {
                    let yc = start[1] + (jy as f64 + 0.5) * h + ey;
                    // Barycentric coordinates of (yc, zc) in the projected triangle.
                    let d = (q[1] - p[1]) * (r[2] - p[2]) - (r[1] - p[1]) * (q[2] - p[2]);
                    if d == 0.0 {
                        continue; // parallel to the ray
                    }
                    let b1 = ((yc - p[1]) * (r[2] - p[2]) - (r[1] - p[1]) * (zc - p[2])) / d;
                    let b2 = ((q[1] - p[1]) * (zc - p[2]) - (yc - p[1]) * (q[2] - p[2])) / d;
                    let b0 = 1.0 - b1 - b2;
                    if b0 < 0.0 || b1 < 0.0 || b2 < 0.0 {
                        continue;
                    }
                    let x = b0 * p[0] + b1 * q[0] + b2 * r[0];
                    crossings[jy + dims[1] * jz].push(x);
                }
            }
        }
        let mut mask = vec![false; n];
        let mut odd_rows = 0;
        for jz in 0..dims[2] {
            for jy in 0..dims[1] {
                let c = &mut crossings[jy + dims[1] * jz];
                if c.is_empty() {
                    continue;
                }
                c.sort_by(f64::total_cmp);
                if c.len() % 2 == 1 {
                    odd_rows += 1;
                    continue;
                }
                for pair in c.chunks(2) {
                    // Voxel centres x with pair[0] < x < pair[1].
                    let a = ((pair[0] - start[0]) / h - 0.5).floor() as i64 + 1;
                    let b = ((pair[1] - start[0]) / h - 0.5).ceil() as i64 - 1;
                    for jx in a.max(0)..=b.min(dims[0] as i64 - 1) {
                        mask[jx as usize + dims[0] * (jy + dims[1] * jz)] = true;
                    }
                }
            }
        }
        if odd_rows > 0 {
            return Err(VoxelizeError::OpenSurface(odd_rows));
        }
        Ok((dims, start, mask))
    }
}
