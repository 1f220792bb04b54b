//! Conforming interface surfaces of a phase image: every interface between two phases
//! (grain|pore, binder|pore, grain|binder, ...) and between a phase and the outside of the
//! image, as welded triangles tagged with the pair of phases they separate.
//!
//! The construction extends the marching tetrahedra of the `stl` exporter
//! ([`crate::stl::phase_surface`]) to many labels. Every cube of eight voxel centres (the
//! image padded by one layer of the *exterior*, label [`EXTERIOR`]) is split into the same
//! six tetrahedra around its main diagonal. In a tetrahedron with
//! - one label: nothing;
//! - two labels: the marching-tetrahedra triangle or quad through the midpoints of the
//!   edges that change label, exactly the `stl` surface;
//! - three or four labels: on each of its four faces the curves that separate the labels
//!   (two labels on a face: the segment between the midpoints of the two changing edges;
//!   three labels: three segments from those midpoints to the face centroid), each coned to
//!   the tetrahedron's centroid.
//!
//! The face curves depend only on the face's three labels, so neighbouring tetrahedra agree
//! on them and the label regions partition space: each interface is a 2-manifold whose only
//! boundary is the junction lines where three or more phases meet, and a closed interface
//! (a sphere of grain in pore) is watertight. Vertices are midpoints, face centroids and
//! tetrahedron centroids of voxel centres, all on a lattice of 1/12 voxel, so shared
//! vertices are welded exactly (integer keys, no tolerance).
//!
//! Orientation: for the pair (a, b) with a < b (the exterior is -1, lowest), the normal
//! (right-hand rule) points out of phase b into phase a, so a grain's surface against the
//! pore (label 0) and the image box against the exterior point outwards.
//!
//! Smoothing (optional) is Taubin's lambda|mu filter (G. Taubin, "A signal processing
//! approach to fair surface design", SIGGRAPH 1995, pp. 351-358): alternating steps
//! x += lambda L(x) and x += mu L(x) with the umbrella Laplacian L(x)_i = mean of the
//! neighbours - x_i, lambda = 0.6307, mu = -0.6732 (pass band k_PB = 1/lambda + 1/mu = 0.1,
//! the paper's example), which removes the voxel staircase without the shrinkage of plain
//! Laplacian smoothing. Vertices on junction lines (touching two or more interfaces) and
//! on the image box (interfaces with the exterior) stay fixed, so interfaces stay conforming
//! and the box stays a box.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

/// The label of the outside of the image in interface pairs.
pub const EXTERIOR: i32 = -1;

/// Taubin's shrinking and inflating factors (pass band 0.1).
pub const TAUBIN_LAMBDA: f64 = 0.6307;
pub const TAUBIN_MU: f64 = -0.6732;

/// Lattice units per voxel (midpoints: 1/2, face centroids: 1/3, centroids: 1/4).
const UNITS: i64 = 12;
/// Bits per axis of a packed lattice key.
const KEY_BITS: u32 = 21;

/// Cube corners by bit (x = bit 0, y = bit 1, z = bit 2); six tetrahedra around the 0-7
/// diagonal (the `stl` exporter's split).
const TETS: [[usize; 4]; 6] = [
    [0, 1, 3, 7],
    [0, 3, 2, 7],
    [0, 2, 6, 7],
    [0, 6, 4, 7],
    [0, 4, 5, 7],
    [0, 5, 1, 7],
];

/// Bytes per triangle and per point of an [`InterfaceMesh`] while it is built (triangle
/// nodes, interface id, point coordinates, the welding table at its load factor).
pub const BYTES_PER_TRIANGLE: u64 = 12 + 2;
pub const BYTES_PER_POINT: u64 = 24 + 32;
/// Extra bytes per point while smoothing (second coordinate buffer, neighbour lists).
pub const SMOOTH_BYTES_PER_POINT: u64 = 24 + 4 + 6 * 4 + 1;
/// Extra bytes per point while decimating (interface and local-index tables, locks, f32
/// positions, the new triangles at two per point, meshoptimizer's working tables).
pub const DECIMATE_BYTES_PER_POINT: u64 = 4 + 4 + 1 + 12 + 2 * 14 + 64;

/// A multiplicative hash for the packed lattice keys (SipHash is 3x slower here and the
/// keys are not adversarial).
#[derive(Default)]
struct KeyHasher(u64);
impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ b as u64).wrapping_mul(0x100000001b3);
        }
    }
    fn write_u64(&mut self, k: u64) {
        self.0 = (k ^ (k >> 29)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }
}
type KeyMap = HashMap<u64, u32, BuildHasherDefault<KeyHasher>>;

/// The interface surfaces: welded points [m], triangles grouped by interface (in interface
/// order), and the interface table.
#[derive(Clone, Debug, Default)]
pub struct InterfaceMesh {
    pub points: Vec<[f64; 3]>,
    pub triangles: Vec<[u32; 3]>,
    /// Interface index (into `pairs`) of each triangle.
    pub interface: Vec<u16>,
    /// The (a, b) phase pairs, a < b, sorted; [`EXTERIOR`] for the outside of the image.
    pub pairs: Vec<[i32; 2]>,
}

impl InterfaceMesh {
    /// Triangles of interface `k` (a contiguous run).
    pub fn interface_triangles(&self, k: usize) -> &[[u32; 3]] {
        let lo = self.interface.partition_point(|&i| (i as usize) < k);
        let hi = self.interface.partition_point(|&i| (i as usize) <= k);
        &self.triangles[lo..hi]
    }

    /// Number of triangles per interface.
    pub fn counts(&self) -> Vec<usize> {
        (0..self.pairs.len())
            .map(|k| self.interface_triangles(k).len())
            .collect()
    }

    /// The corners of a triangle [m].
    pub fn corners(&self, t: [u32; 3]) -> [[f64; 3]; 3] {
        t.map(|i| self.points[i as usize])
    }
}

fn pack(p: [i64; 3]) -> u64 {
    (p[0] as u64) | ((p[1] as u64) << KEY_BITS) | ((p[2] as u64) << (2 * KEY_BITS))
}

/// Welds lattice points into indices.
struct Welder {
    map: KeyMap,
    lattice: Vec<[i64; 3]>,
}

impl Welder {
    fn index(&mut self, p: [i64; 3]) -> u32 {
        let n = self.lattice.len() as u32;
        let k = *self.map.entry(pack(p)).or_insert(n);
        if k == n {
            self.lattice.push(p);
        }
        k
    }
}

fn avg<const N: usize>(ps: [[i64; 3]; N]) -> [i64; 3] {
    std::array::from_fn(|k| ps.iter().map(|p| p[k]).sum::<i64>() / N as i64)
}

fn sub(a: [i64; 3], b: [i64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|k| (a[k] - b[k]) as f64)
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

/// A triangle of a tetrahedron with the labels on its two sides and a tetrahedron vertex on
/// each side (lattice coordinates): (triangle, label, its vertex, other label, its vertex).
type Piece = ([[i64; 3]; 3], i32, [i64; 3], i32, [i64; 3]);

/// The interface surfaces of the labels of a `dims` grid (x fastest). `keep(a, b)` says
/// which interfaces (a < b, [`EXTERIOR`] = -1) are kept. `origin`, `spacing`: the grid's.
pub fn interfaces(
    dims: [usize; 3],
    origin: [f64; 3],
    spacing: [f64; 3],
    labels: &[u8],
    keep: impl Fn(i32, i32) -> bool,
) -> Result<InterfaceMesh, String> {
    let [nx, ny, nz] = dims.map(|d| d as i64);
    if labels.len() != (nx * ny * nz) as usize {
        return Err(format!("{} labels for {nx}x{ny}x{nz} voxels", labels.len()));
    }
    let limit = (1i64 << KEY_BITS) / UNITS - 2;
    if nx.max(ny).max(nz) > limit {
        return Err(format!(
            "{nx}x{ny}x{nz} voxels: the surface mesh numbers at most {limit} voxels per axis"
        ));
    }
    let label = |x: i64, y: i64, z: i64| -> i32 {
        if x < 0 || y < 0 || z < 0 || x >= nx || y >= ny || z >= nz {
            EXTERIOR
        } else {
            labels[(x + nx * (y + ny * z)) as usize] as i32
        }
    };
    // Interface index of each kept pair, assigned in order of appearance, renumbered at the
    // end so the table is sorted.
    let mut pair_slot: HashMap<(i32, i32), u16> = HashMap::new();
    let mut pairs: Vec<[i32; 2]> = Vec::new();
    let mut welder = Welder {
        map: KeyMap::default(),
        lattice: Vec::new(),
    };
    let mut tris: Vec<[u32; 3]> = Vec::new();
    let mut iface: Vec<u16> = Vec::new();
    let mut refused: Option<String> = None;
    // Lattice position of voxel centre (x, y, z): UNITS * (index + 1), all non-negative.
    for z in -1..nz {
        for y in -1..ny {
            for x in -1..nx {
                let corner = |b: usize| {
                    [
                        x + (b & 1) as i64,
                        y + ((b >> 1) & 1) as i64,
                        z + ((b >> 2) & 1) as i64,
                    ]
                };
                let lab: [i32; 8] = std::array::from_fn(|b| {
                    let c = corner(b);
                    label(c[0], c[1], c[2])
                });
                if lab.iter().all(|&l| l == lab[0]) {
                    continue;
                }
                let pos = |b: usize| corner(b).map(|c| UNITS * (c + 1));
                for tet in TETS {
                    let l = tet.map(|b| lab[b]);
                    let p = tet.map(pos);
                    let mut distinct = l.to_vec();
                    distinct.sort_unstable();
                    distinct.dedup();
                    if distinct.len() == 1 {
                        continue;
                    }
                    let mut out: Vec<Piece> = Vec::new();
                    let m = |i: usize, j: usize| avg([p[i], p[j]]);
                    if distinct.len() == 2 {
                        let hi = distinct[1];
                        let (inn, outs): (Vec<usize>, Vec<usize>) =
                            (0..4).partition(|&i| l[i] == hi);
                        let lo = distinct[0];
                        let ci = p[inn[0]];
                        let co = p[outs[0]];
                        match (inn.len(), outs.len()) {
                            (1, 3) => out.push((
                                [m(inn[0], outs[0]), m(inn[0], outs[1]), m(inn[0], outs[2])],
                                hi,
                                ci,
                                lo,
                                co,
                            )),
                            (3, 1) => out.push((
                                [m(outs[0], inn[0]), m(outs[0], inn[1]), m(outs[0], inn[2])],
                                hi,
                                ci,
                                lo,
                                co,
                            )),
                            _ => {
                                let (i0, i1, o0, o1) = (inn[0], inn[1], outs[0], outs[1]);
                                let (a, b, c, d) = (m(i0, o0), m(i0, o1), m(i1, o1), m(i1, o0));
                                out.push(([a, b, c], hi, ci, lo, co));
                                out.push(([a, c, d], hi, ci, lo, co));
                            }
                        }
                    } else {
                        let centre = avg(p);
                        for skip in 0..4 {
                            let f: Vec<usize> = (0..4).filter(|&i| i != skip).collect();
                            let (i, j, k) = (f[0], f[1], f[2]);
                            let (a, b, c) = (l[i], l[j], l[k]);
                            if a == b && b == c {
                                continue;
                            }
                            if a != b && b != c && a != c {
                                let fc = avg([p[i], p[j], p[k]]);
                                for (u, v) in [(i, j), (j, k), (k, i)] {
                                    out.push(([m(u, v), fc, centre], l[u], p[u], l[v], p[v]));
                                }
                            } else {
                                // The odd vertex r and the two alike, q1 and q2.
                                let (r, q1, q2) = if a == b {
                                    (k, i, j)
                                } else if a == c {
                                    (j, i, k)
                                } else {
                                    (i, j, k)
                                };
                                out.push(([m(r, q1), m(r, q2), centre], l[r], p[r], l[q1], p[q1]));
                            }
                        }
                    }
                    for (t, la, pa, lb, pb) in out {
                        // Orient out of the higher label into the lower.
                        let (hi, lo, p_hi, p_lo) = if la > lb {
                            (la, lb, pa, pb)
                        } else {
                            (lb, la, pb, pa)
                        };
                        if !keep(lo, hi) {
                            continue;
                        }
                        let n = cross(sub(t[1], t[0]), sub(t[2], t[0]));
                        let t = if dot(n, sub(p_lo, p_hi)) >= 0.0 {
                            t
                        } else {
                            [t[0], t[2], t[1]]
                        };
                        let slot = match pair_slot.get(&(lo, hi)) {
                            Some(&s) => s,
                            None => {
                                if pairs.len() >= u16::MAX as usize {
                                    refused.get_or_insert_with(|| {
                                        "more than 65535 interfaces".to_string()
                                    });
                                    continue;
                                }
                                let s = pairs.len() as u16;
                                pair_slot.insert((lo, hi), s);
                                pairs.push([lo, hi]);
                                s
                            }
                        };
                        tris.push(t.map(|q| welder.index(q)));
                        iface.push(slot);
                    }
                }
            }
        }
    }
    if let Some(e) = refused {
        return Err(e);
    }
    drop(welder.map);
    // Sort the table and group the triangles by interface (a counting sort).
    let mut order: Vec<usize> = (0..pairs.len()).collect();
    order.sort_by_key(|&s| pairs[s]);
    let mut rank = vec![0u16; pairs.len()];
    for (r, &s) in order.iter().enumerate() {
        rank[s] = r as u16;
    }
    let mut start = vec![0usize; pairs.len() + 1];
    for &s in &iface {
        start[rank[s as usize] as usize + 1] += 1;
    }
    for k in 0..pairs.len() {
        start[k + 1] += start[k];
    }
    let mut triangles = vec![[0u32; 3]; tris.len()];
    let mut interface = vec![0u16; tris.len()];
    for (t, &s) in tris.iter().zip(&iface) {
        let r = rank[s as usize] as usize;
        triangles[start[r]] = *t;
        interface[start[r]] = r as u16;
        start[r] += 1;
    }
    drop(tris);
    let points = welder
        .lattice
        .iter()
        .map(|q| {
            // Voxel centre index c = q / UNITS - 1 lies at origin + (c + 0.5) * spacing.
            [0, 1, 2].map(|k| origin[k] + (q[k] as f64 / UNITS as f64 - 0.5) * spacing[k])
        })
        .collect();
    Ok(InterfaceMesh {
        points,
        triangles,
        interface,
        pairs: order.iter().map(|&s| pairs[s]).collect(),
    })
}

/// Taubin lambda|mu smoothing, `iterations` pairs of steps (see the module doc). Vertices
/// on two or more interfaces or on an interface with the exterior stay fixed.
pub fn taubin_smooth(mesh: &mut InterfaceMesh, iterations: u32) {
    if iterations == 0 || mesh.triangles.is_empty() {
        return;
    }
    let n = mesh.points.len();
    const FREE: u32 = u32::MAX;
    const PINNED: u32 = u32::MAX - 1;
    // The one interface of each vertex, PINNED when it has several or touches the outside.
    let mut owner = vec![FREE; n];
    for (t, &k) in mesh.triangles.iter().zip(&mesh.interface) {
        let outside = mesh.pairs[k as usize][0] == EXTERIOR;
        for &v in t {
            let o = &mut owner[v as usize];
            *o = if outside || (*o != FREE && *o != k as u32) {
                PINNED
            } else {
                k as u32
            };
        }
    }
    // Neighbour lists (CSR) from the triangle edges, each edge once per direction.
    let mut edges: Vec<(u32, u32)> = Vec::with_capacity(3 * mesh.triangles.len());
    for t in &mesh.triangles {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            if owner[a as usize] != PINNED {
                edges.push((a, b));
            }
            if owner[b as usize] != PINNED {
                edges.push((b, a));
            }
        }
    }
    edges.sort_unstable();
    edges.dedup();
    let mut start = vec![0u32; n + 1];
    for &(a, _) in &edges {
        start[a as usize + 1] += 1;
    }
    for k in 0..n {
        start[k + 1] += start[k];
    }
    let nbr: Vec<u32> = edges.iter().map(|e| e.1).collect();
    drop(edges);
    let mut next = mesh.points.clone();
    for _ in 0..iterations {
        for factor in [TAUBIN_LAMBDA, TAUBIN_MU] {
            let pts = &mesh.points;
            for (v, q) in next.iter_mut().enumerate() {
                let (lo, hi) = (start[v] as usize, start[v + 1] as usize);
                if owner[v] == PINNED || hi == lo {
                    *q = pts[v];
                    continue;
                }
                let mut s = [0.0; 3];
                for &w in &nbr[lo..hi] {
                    let p = pts[w as usize];
                    for k in 0..3 {
                        s[k] += p[k];
                    }
                }
                let c = (hi - lo) as f64;
                *q = [0, 1, 2].map(|k| pts[v][k] + factor * (s[k] / c - pts[v][k]));
            }
            std::mem::swap(&mut mesh.points, &mut next);
        }
    }
}

/// Area [m^2] and signed enclosed volume [m^3] (divergence theorem: the sum of
/// a . (b x c) / 6) of a set of triangles.
pub fn area_and_volume(mesh: &InterfaceMesh, tris: &[[u32; 3]]) -> (f64, f64) {
    let mut area = 0.0;
    let mut vol = 0.0;
    for &t in tris {
        let [a, b, c] = mesh.corners(t);
        let ab = [0, 1, 2].map(|k| b[k] - a[k]);
        let ac = [0, 1, 2].map(|k| c[k] - a[k]);
        let n = cross(ab, ac);
        area += 0.5 * dot(n, n).sqrt();
        vol += dot(a, cross(b, c)) / 6.0;
    }
    (area, vol)
}

/// Largest distance [voxels] decimation may move the surface (meshoptimizer's absolute
/// error bound, in voxel units along each axis).
pub const DECIMATE_MAX_ERROR: f32 = 0.5;

/// Decimates each interface to about `fraction` of its triangles with meshoptimizer's
/// edge-collapse simplifier (the `meshopt` crate, bindings to zeux/meshoptimizer's
/// `meshopt_simplifyWithAttributes`): vertices on two or more interfaces and on open borders
/// are locked, so junction lines and welding are kept; collapses that would move the surface
/// by more than [`DECIMATE_MAX_ERROR`] voxels are not made (an interface may keep more than
/// `fraction`). Collapses reuse existing points; points no triangle uses are dropped.
pub fn decimate(mesh: &mut InterfaceMesh, fraction: f64, spacing: [f64; 3]) {
    if fraction >= 1.0 || mesh.triangles.is_empty() {
        return;
    }
    let n = mesh.points.len();
    const NONE: u32 = u32::MAX;
    let mut first = vec![NONE; n];
    let mut shared = vec![false; n];
    for (t, &k) in mesh.triangles.iter().zip(&mesh.interface) {
        for &v in t {
            let f = &mut first[v as usize];
            if *f == NONE {
                *f = k as u32;
            } else if *f != k as u32 {
                shared[v as usize] = true;
            }
        }
    }
    drop(first);
    let mut local = vec![NONE; n];
    let mut triangles = Vec::new();
    let mut interface = Vec::new();
    for k in 0..mesh.pairs.len() {
        let tris = mesh.interface_triangles(k);
        let mut globals: Vec<u32> = Vec::new();
        let mut indices: Vec<u32> = Vec::with_capacity(3 * tris.len());
        for &v in tris.iter().flatten() {
            if local[v as usize] == NONE {
                local[v as usize] = globals.len() as u32;
                globals.push(v);
            }
            indices.push(local[v as usize]);
        }
        // Positions in voxel units from the first point (f32 keeps ~1e-7 of a voxel).
        let p0 = mesh.points[globals[0] as usize];
        let pos: Vec<[f32; 3]> = globals
            .iter()
            .map(|&g| {
                let p = mesh.points[g as usize];
                [0, 1, 2].map(|a| ((p[a] - p0[a]) / spacing[a]) as f32)
            })
            .collect();
        let locks: Vec<bool> = globals.iter().map(|&g| shared[g as usize]).collect();
        let target = 3 * ((fraction * tris.len() as f64).round() as usize).max(1);
        let adapter = meshopt::VertexDataAdapter::new(
            meshopt::typed_to_bytes(&pos),
            std::mem::size_of::<[f32; 3]>(),
            0,
        )
        .expect("tightly packed positions");
        let kept = meshopt::simplify_with_locks(
            &indices,
            &adapter,
            &locks,
            target,
            DECIMATE_MAX_ERROR,
            meshopt::SimplifyOptions::LockBorder | meshopt::SimplifyOptions::ErrorAbsolute,
            None,
        );
        for t in kept.chunks_exact(3) {
            triangles.push([0, 1, 2].map(|c| globals[t[c] as usize]));
            interface.push(k as u16);
        }
        for &g in &globals {
            local[g as usize] = NONE;
        }
    }
    // Drop the points no triangle uses; keep the order of the others.
    let mut renum = vec![NONE; n];
    for &v in triangles.iter().flatten() {
        renum[v as usize] = 0;
    }
    let mut points = Vec::new();
    for (v, r) in renum.iter_mut().enumerate() {
        if *r == 0 {
            *r = points.len() as u32;
            points.push(mesh.points[v]);
        }
    }
    for t in triangles.iter_mut() {
        *t = t.map(|v| renum[v as usize]);
    }
    mesh.points = points;
    mesh.triangles = triangles;
    mesh.interface = interface;
}
