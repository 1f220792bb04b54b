//! Connected components of one phase of a voxel image, with periodic axes and percolation.
//!
//! Connectivity is by faces (6 neighbours). Voxels are stored x fastest
//! (`i = x + nx * (y + ny * z)`).
//!
//! Method: the image is cut into slabs of z planes, labelled in parallel by the classic
//! two-pass union-find labelling inside each slab; the slab labels are then joined across
//! slab boundaries and across the faces of periodic axes by a second union-find over labels
//! only. That second union-find carries, for every label, the periodic image (an integer
//! shift in periods along x, y, z) its voxels sit in relative to its root's copy. Joining two
//! labels of one set across a periodic face whose shifts disagree closes a loop that winds
//! around the torus: the component is connected to its own periodic image displaced by the
//! disagreement, i.e. it is infinite along every axis where that displacement is non-zero.
//! A component that merely crosses a periodic face (so that it looks cut in two in the
//! image) closes no such loop and does not percolate.
//!
//! Percolation along a non-periodic axis: one component touches both faces of the image
//! normal to that axis. Along a periodic axis: one component connects to its own periodic
//! image along that axis (winding).
//!
//! Components are numbered in the raster order of their first voxel, so the result does not
//! depend on the number of threads or slabs.

use rayon::prelude::*;

/// Marks voxels outside the phase in [`Labeling::ids`].
pub const NONE: u32 = u32::MAX;

/// One connected component.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Component {
    pub voxels: u64,
    /// Touches the lower / upper face of the image normal to x, y, z.
    pub touches: [[bool; 2]; 3],
    /// Connected to its own periodic image displaced along x, y, z (periodic axes only).
    pub winds: [bool; 3],
    /// Spans the domain along x, y, z (see the module documentation).
    pub percolates: [bool; 3],
}

/// The components of one phase.
#[derive(Clone, Debug)]
pub struct Labeling {
    /// Component index per voxel, [`NONE`] outside the phase.
    pub ids: Vec<u32>,
    /// In the raster order of their first voxel.
    pub components: Vec<Component>,
}

impl Labeling {
    /// Voxels of the phase.
    pub fn voxels(&self) -> u64 {
        self.components.iter().map(|c| c.voxels).sum()
    }
    /// Voxels of the largest component (0 without components).
    pub fn largest(&self) -> u64 {
        self.components.iter().map(|c| c.voxels).max().unwrap_or(0)
    }
    /// Whether some component percolates along each axis.
    pub fn percolates(&self) -> [bool; 3] {
        [0, 1, 2].map(|a| self.components.iter().any(|c| c.percolates[a]))
    }
    /// Voxels in components that percolate along at least one of the axes `along`.
    pub fn percolating_voxels(&self, along: [bool; 3]) -> u64 {
        self.components
            .iter()
            .filter(|c| (0..3).any(|a| along[a] && c.percolates[a]))
            .map(|c| c.voxels)
            .sum()
    }
}

/// Local union-find with path halving; the root of a set is its smallest label, which is
/// the label created first in raster order.
fn find(parent: &mut [u32], mut l: u32) -> u32 {
    while parent[l as usize] != l {
        let g = parent[parent[l as usize] as usize];
        parent[l as usize] = g;
        l = g;
    }
    l
}

fn union_min(parent: &mut [u32], a: u32, b: u32) -> u32 {
    let (ra, rb) = (find(parent, a), find(parent, b));
    let (lo, hi) = if ra < rb { (ra, rb) } else { (rb, ra) };
    parent[hi as usize] = lo;
    lo
}

/// Labels the voxels `i` with `inside(i)` of slab `ids` (whole z planes starting at plane
/// `z0`) with local labels 0..n in raster order of their first voxel; returns n.
fn label_slab(
    ids: &mut [u32],
    dims: [usize; 3],
    z0: usize,
    inside: &(impl Fn(usize) -> bool + Sync),
) -> u32 {
    let [nx, ny, _] = dims;
    let plane = nx * ny;
    let base = z0 * plane;
    let mut parent: Vec<u32> = Vec::new();
    for j in 0..ids.len() {
        let i = base + j;
        if !inside(i) {
            ids[j] = NONE;
            continue;
        }
        let x = j % nx;
        let y = (j / nx) % ny;
        let mut l = NONE;
        let back = [
            (x > 0).then(|| j - 1),
            (y > 0).then(|| j - nx),
            (j >= plane).then(|| j - plane),
        ];
        for n in back.into_iter().flatten() {
            let m = ids[n];
            if m != NONE {
                l = if l == NONE {
                    m
                } else {
                    union_min(&mut parent, l, m)
                };
            }
        }
        if l == NONE {
            l = parent.len() as u32;
            parent.push(l);
        }
        ids[j] = l;
    }
    // Compact the roots in label order (= raster order of first voxels).
    let mut compact = vec![NONE; parent.len()];
    let mut n = 0u32;
    for l in 0..parent.len() as u32 {
        let r = find(&mut parent, l);
        if compact[r as usize] == NONE {
            compact[r as usize] = n;
            n += 1;
        }
        compact[l as usize] = compact[r as usize];
    }
    for v in ids.iter_mut() {
        if *v != NONE {
            *v = compact[*v as usize];
        }
    }
    n
}

/// Whether a label touches the lower / upper face of the image normal to x, y, z.
type Touches = [[bool; 2]; 3];

/// Union-find over labels carrying the periodic shift of each label relative to its parent.
struct Winding {
    parent: Vec<u32>,
    shift: Vec<[i32; 3]>,
    size: Vec<u64>,
    winds: Vec<[bool; 3]>,
}

impl Winding {
    fn new(n: usize) -> Self {
        Winding {
            parent: (0..n as u32).collect(),
            shift: vec![[0; 3]; n],
            size: vec![1; n],
            winds: vec![[false; 3]; n],
        }
    }

    /// Root of `l` and the shift of `l`'s copy relative to the root's copy.
    fn find(&mut self, l: u32) -> (u32, [i32; 3]) {
        // Two passes: find the root summing shifts, then point the path at the root.
        let mut r = l;
        let mut total = [0i32; 3];
        while self.parent[r as usize] != r {
            let s = self.shift[r as usize];
            total = [0, 1, 2].map(|a| total[a] + s[a]);
            r = self.parent[r as usize];
        }
        let mut cur = l;
        let mut rest = total;
        while self.parent[cur as usize] != cur {
            let next = self.parent[cur as usize];
            let s = self.shift[cur as usize];
            self.parent[cur as usize] = r;
            self.shift[cur as usize] = rest;
            rest = [0, 1, 2].map(|a| rest[a] - s[a]);
            cur = next;
        }
        (r, total)
    }

    /// Records that label `a`'s voxels touch label `b`'s voxels in the periodic image
    /// displaced by `d` (in periods) from `a`'s.
    fn join(&mut self, a: u32, b: u32, d: [i32; 3]) {
        let (ra, sa) = self.find(a);
        let (rb, sb) = self.find(b);
        // Where b's copy sits relative to ra's copy through this contact, minus where it
        // sits through the set it belongs to.
        let w: [i32; 3] = [0, 1, 2].map(|k| sa[k] + d[k] - sb[k]);
        if ra == rb {
            let winds = &mut self.winds[ra as usize];
            *winds = [0, 1, 2].map(|k| winds[k] || w[k] != 0);
            return;
        }
        // Hang the smaller set under the larger; rb's copy is displaced by w from ra's.
        let (root, child, s) = if self.size[ra as usize] >= self.size[rb as usize] {
            (ra, rb, w)
        } else {
            (rb, ra, w.map(|v| -v))
        };
        self.parent[child as usize] = root;
        self.shift[child as usize] = s;
        self.size[root as usize] += self.size[child as usize];
        let cw = self.winds[child as usize];
        let winds = &mut self.winds[root as usize];
        *winds = [0, 1, 2].map(|k| winds[k] || cw[k]);
    }
}

/// Connected components (6-connectivity) of the voxels `i` with `inside(i)` on a grid of
/// `dims` voxels; `periodic` axes wrap.
///
/// Memory: 4 bytes per voxel (the ids) plus a few words per provisional label.
pub fn label_components(
    dims: [usize; 3],
    periodic: [bool; 3],
    inside: impl Fn(usize) -> bool + Sync,
) -> Labeling {
    let [nx, ny, nz] = dims;
    let plane = nx * ny;
    let n = plane * nz;
    assert!(
        (n as u64) < NONE as u64,
        "{n} voxels: more than the u32 labels can number"
    );
    let mut ids = vec![NONE; n];
    if n == 0 {
        return Labeling {
            ids,
            components: Vec::new(),
        };
    }
    // Slabs of whole z planes; a few per thread so that uneven slabs balance.
    let slabs = (rayon::current_num_threads() * 4).clamp(1, nz);
    let zs = nz.div_ceil(slabs);
    let counts: Vec<u32> = ids
        .par_chunks_mut(zs * plane)
        .enumerate()
        .map(|(s, chunk)| label_slab(chunk, dims, s * zs, &inside))
        .collect();
    let mut offsets = Vec::with_capacity(counts.len());
    let mut total = 0u64;
    for &c in &counts {
        offsets.push(total as u32);
        total += c as u64;
    }
    let total = total as usize;
    // Global labels; and per label its voxel count and the image faces it touches. Each
    // slab's labels are a contiguous range, so each slab fills its own part.
    let per_slab: Vec<(Vec<u64>, Vec<Touches>)> = ids
        .par_chunks_mut(zs * plane)
        .enumerate()
        .map(|(s, chunk)| {
            let off = offsets[s];
            let c = counts[s] as usize;
            let mut vox = vec![0u64; c];
            let mut touch = vec![[[false; 2]; 3]; c];
            for (j, v) in chunk.iter_mut().enumerate() {
                if *v == NONE {
                    continue;
                }
                let l = *v as usize;
                vox[l] += 1;
                let i = s * zs * plane + j;
                let xyz = [i % nx, (i / nx) % ny, i / plane];
                for a in 0..3 {
                    touch[l][a][0] |= xyz[a] == 0;
                    touch[l][a][1] |= xyz[a] + 1 == dims[a];
                }
                *v += off;
            }
            (vox, touch)
        })
        .collect();
    let mut voxels = Vec::with_capacity(total);
    let mut touches = Vec::with_capacity(total);
    for (v, t) in per_slab {
        voxels.extend(v);
        touches.extend(t);
    }
    let mut uf = Winding::new(total);
    // Across slab boundaries (same periodic image).
    for s in 1..counts.len() {
        let z = s * zs;
        for k in 0..plane {
            let (a, b) = (ids[(z - 1) * plane + k], ids[z * plane + k]);
            if a != NONE && b != NONE {
                uf.join(a, b, [0; 3]);
            }
        }
    }
    // Across the faces of periodic axes: the voxel at index n-1 touches the voxel at index 0
    // of the next image along that axis.
    for a in 0..3 {
        if !periodic[a] {
            continue;
        }
        let mut d = [0; 3];
        d[a] = 1;
        let (u, v) = ([1, 2, 0][a], [2, 0, 1][a]);
        for p in 0..dims[u] {
            for q in 0..dims[v] {
                let mut lo = [0; 3];
                lo[u] = p;
                lo[v] = q;
                let mut hi = lo;
                hi[a] = dims[a] - 1;
                let at = |c: [usize; 3]| c[0] + nx * (c[1] + ny * c[2]);
                let (l_hi, l_lo) = (ids[at(hi)], ids[at(lo)]);
                if l_hi != NONE && l_lo != NONE {
                    uf.join(l_hi, l_lo, d);
                }
            }
        }
    }
    // Number the sets by their smallest label (raster order of the first voxel).
    let mut number = vec![NONE; total];
    let mut final_of = vec![0u32; total];
    let mut components: Vec<Component> = Vec::new();
    for l in 0..total as u32 {
        let (r, _) = uf.find(l);
        if number[r as usize] == NONE {
            number[r as usize] = components.len() as u32;
            components.push(Component {
                voxels: 0,
                touches: [[false; 2]; 3],
                winds: uf.winds[r as usize],
                percolates: [false; 3],
            });
        }
        let c = number[r as usize];
        final_of[l as usize] = c;
        let comp = &mut components[c as usize];
        comp.voxels += voxels[l as usize];
        for (mine, its) in comp.touches.iter_mut().zip(&touches[l as usize]) {
            *mine = [mine[0] || its[0], mine[1] || its[1]];
        }
    }
    for c in &mut components {
        c.percolates = [0, 1, 2].map(|a| {
            if periodic[a] {
                c.winds[a]
            } else {
                c.touches[a][0] && c.touches[a][1]
            }
        });
    }
    ids.par_iter_mut().for_each(|v| {
        if *v != NONE {
            *v = final_of[*v as usize];
        }
    });
    Labeling { ids, components }
}
