//! Rasterizing unions of spheres onto a voxel grid, block by block.
//!
//! Every sphere is binned once into the blocks of `BLOCK^3` voxels that lie within its
//! radius plus a `reach`; a block then sorts its spheres by a lower bound of their signed
//! distance to any point of the block, so a voxel visits only the spheres that can matter and
//! stops at the first one whose bound exceeds what it still needs. The cost follows the
//! spheres near each voxel, not the largest sphere of the packing (a cell list sized by the
//! largest sphere makes clump packings of many small spheres slow), and memory is the bins
//! (8 bytes per sphere-block pair) plus whatever the caller stores per voxel.
//!
//! Work is split into slabs of `BLOCK` z-planes, each a contiguous piece of the voxel array,
//! so writes never race and the result does not depend on the thread count.

use crate::model::{Grid, WorldSphere};
use rayon::prelude::*;

/// Voxels per block edge.
pub const BLOCK: usize = 8;

/// Candidates between two questions to a search's `give_up`.
const GIVE_UP_EVERY: usize = 4;

/// A sphere as seen from one block: its (periodically shifted) centre, radius, and a lower
/// bound of `|x - centre| - radius` over the block's voxels (whole voxels, not only centres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    pub center: [f64; 3],
    pub radius: f64,
    pub lower_bound: f64,
    /// Index into the sphere list the raster was built from.
    pub sphere: u32,
    /// The body the sphere belongs to.
    pub body: u32,
}

impl Candidate {
    /// Signed distance from `p` to this sphere's surface (negative inside).
    #[inline]
    pub fn distance(&self, p: [f64; 3]) -> f64 {
        let d = [0, 1, 2].map(|a| p[a] - self.center[a]);
        (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() - self.radius
    }
}

/// One (sphere, periodic image) entry of a block.
#[derive(Clone, Copy, Debug)]
struct Entry {
    sphere: u32,
    shift: [i8; 3],
}

/// Spheres binned into blocks of a grid.
pub struct SphereRaster {
    grid: Grid,
    blocks: [usize; 3],
    spheres: Vec<WorldSphere>,
    /// CSR offsets into `entries`, one range per block (x fastest).
    start: Vec<usize>,
    entries: Vec<Entry>,
    reach: f64,
}

/// Why a raster cannot be built.
#[derive(Debug, Clone, PartialEq)]
pub enum RasterError {
    /// A sphere reaches further than 127 periodic images.
    TooManyImages { sphere: usize },
    /// The bins would exceed the given entry budget.
    TooManyEntries { entries: u64, limit: u64 },
}

impl std::fmt::Display for RasterError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RasterError::TooManyImages { sphere } => write!(
                f,
                "sphere {sphere} reaches over more than 127 periodic images of the cell"
            ),
            RasterError::TooManyEntries { entries, limit } => write!(
                f,
                "{entries} sphere-block pairs exceed the budget of {limit}: a smaller reach \
                 or a coarser grid is needed"
            ),
        }
    }
}

impl std::error::Error for RasterError {}

/// Distance from `x` to the interval `[lo, hi]`.
#[inline]
fn interval_gap(x: f64, lo: f64, hi: f64) -> f64 {
    if x < lo {
        lo - x
    } else if x > hi {
        x - hi
    } else {
        0.0
    }
}

impl SphereRaster {
    /// Bins `spheres` (world coordinates; periodic axes of `grid` wrap) into the blocks each
    /// reaches within `reach` of its surface. Spheres whose reach leaves a non-periodic grid
    /// are clipped to it.
    pub fn new(grid: &Grid, spheres: &[WorldSphere], reach: f64) -> Result<Self, RasterError> {
        Self::with_budget(grid, spheres, reach, u64::MAX)
    }

    /// Like [`SphereRaster::new`], refusing more than `max_entries` sphere-block pairs.
    pub fn with_budget(
        grid: &Grid,
        spheres: &[WorldSphere],
        reach: f64,
        max_entries: u64,
    ) -> Result<Self, RasterError> {
        let blocks = grid.dims.map(|n| n.div_ceil(BLOCK));
        let extent = grid.extent();
        let block_len = [0, 1, 2].map(|a| BLOCK as f64 * grid.spacing[a]);
        // Spheres are stored with centres wrapped into the cell on periodic axes.
        let wrapped: Vec<WorldSphere> = spheres
            .iter()
            .map(|s| {
                let mut s = *s;
                s.center = std::array::from_fn(|a| {
                    if grid.periodic[a] {
                        grid.origin[a] + (s.center[a] - grid.origin[a]).rem_euclid(extent[a])
                    } else {
                        s.center[a]
                    }
                });
                s
            })
            .collect();
        let nblocks = blocks[0] * blocks[1] * blocks[2];
        // Per axis, the (block, periodic image) pairs a sphere's reach overlaps: voxel ranges
        // are wrapped image by image, since blocks need not tile the cell exactly.
        let axis_blocks =
            |s: &WorldSphere, a: usize, i: usize| -> Result<Vec<(usize, i8)>, RasterError> {
                let n = grid.dims[a] as i64;
                let r = s.radius + reach;
                let lo = ((s.center[a] - r - grid.origin[a]) / grid.spacing[a]).floor() as i64;
                let hi = ((s.center[a] + r - grid.origin[a]) / grid.spacing[a]).floor() as i64;
                let (kmin, kmax) = if grid.periodic[a] {
                    (lo.div_euclid(n), hi.div_euclid(n))
                } else {
                    (0, 0)
                };
                if kmin < -127 || kmax > 127 {
                    return Err(RasterError::TooManyImages { sphere: i });
                }
                let mut out = Vec::new();
                for k in kmin..=kmax {
                    let vlo = (lo - k * n).max(0);
                    let vhi = (hi - k * n).min(n - 1);
                    if vlo > vhi {
                        continue;
                    }
                    for b in vlo / BLOCK as i64..=vhi / BLOCK as i64 {
                        out.push((b as usize, k as i8));
                    }
                }
                Ok(out)
            };
        // Visits every (block, shift) whose block box is within reach of the sphere.
        let visit = |i: usize, f: &mut dyn FnMut(usize, [i8; 3])| -> Result<(), RasterError> {
            let s = &wrapped[i];
            let per_axis = [
                axis_blocks(s, 0, i)?,
                axis_blocks(s, 1, i)?,
                axis_blocks(s, 2, i)?,
            ];
            for &(bz, kz) in &per_axis[2] {
                for &(by, ky) in &per_axis[1] {
                    for &(bx, kx) in &per_axis[0] {
                        let idx = [bx, by, bz];
                        let shift = [kx, ky, kz];
                        let mut gap2 = 0.0;
                        for a in 0..3 {
                            // The sphere seen from this block sits at centre - k * extent.
                            let c = s.center[a] - shift[a] as f64 * extent[a];
                            let lo = grid.origin[a] + idx[a] as f64 * block_len[a];
                            let hi = (lo + block_len[a]).min(grid.origin[a] + extent[a]);
                            let g = interval_gap(c, lo, hi);
                            gap2 += g * g;
                        }
                        if gap2.sqrt() - s.radius <= reach {
                            f(bx + blocks[0] * (by + blocks[1] * bz), shift);
                        }
                    }
                }
            }
            Ok(())
        };
        let mut count = vec![0usize; nblocks + 1];
        let mut total: u64 = 0;
        for i in 0..wrapped.len() {
            visit(i, &mut |b, _| {
                count[b + 1] += 1;
                total += 1;
            })?;
            if total > max_entries {
                return Err(RasterError::TooManyEntries {
                    entries: total,
                    limit: max_entries,
                });
            }
        }
        for b in 0..nblocks {
            count[b + 1] += count[b];
        }
        let start = count.clone();
        let mut fill = count;
        let mut entries = vec![
            Entry {
                sphere: 0,
                shift: [0; 3]
            };
            total as usize
        ];
        for i in 0..wrapped.len() {
            visit(i, &mut |b, shift| {
                entries[fill[b]] = Entry {
                    sphere: i as u32,
                    shift,
                };
                fill[b] += 1;
            })?;
        }
        Ok(SphereRaster {
            grid: grid.clone(),
            blocks,
            spheres: wrapped,
            start,
            entries,
            reach,
        })
    }

    /// Heap bytes of a raster of `spheres` spheres of radius up to `radius` with `reach` on
    /// a grid of `dims` voxels of `spacing`, for memory estimates: the wrapped spheres, the
    /// block offsets (two `usize` per block), 8 B per sphere-block pair (a sphere's reach
    /// spans at most `2 (radius + reach) / (BLOCK h) + 2` blocks per axis, capped at the grid),
    /// and per worker thread one block's candidates (48 B each), counted at twice the
    /// average pairs per block (at most every sphere).
    pub fn memory_bytes(
        dims: [usize; 3],
        spacing: [f64; 3],
        spheres: u64,
        radius: f64,
        reach: f64,
    ) -> u64 {
        let blocks = dims.map(|n| n.div_ceil(BLOCK) as u64);
        let nblocks = blocks[0] * blocks[1] * blocks[2];
        let per_sphere: u64 = (0..3)
            .map(|a| {
                let span = 2.0 * (radius + reach) / (BLOCK as f64 * spacing[a]);
                let k = if span.is_finite() {
                    span as u64 + 2
                } else {
                    blocks[a]
                };
                k.min(blocks[a]).max(1)
            })
            .product();
        let pairs = spheres.saturating_mul(per_sphere);
        let cands = (2 * pairs / nblocks.max(1)).min(spheres);
        let threads = rayon::current_num_threads() as u64;
        spheres * std::mem::size_of::<WorldSphere>() as u64
            + 16 * (nblocks + 1)
            + 8 * pairs
            + threads * 48 * cands
    }

    /// Sphere-block pairs stored (8 bytes each).
    pub fn entries(&self) -> usize {
        self.entries.len()
    }

    /// The reach the raster was built with: spheres further than this from every point of a
    /// block are not among its candidates.
    pub fn reach(&self) -> f64 {
        self.reach
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// Candidates of block `b` (x fastest), sorted by lower bound (ties by sphere index).
    fn candidates(&self, b: [usize; 3], out: &mut Vec<Candidate>) {
        let g = &self.grid;
        let extent = g.extent();
        let lo: [f64; 3] =
            std::array::from_fn(|a| g.origin[a] + (b[a] * BLOCK) as f64 * g.spacing[a]);
        let hi: [f64; 3] = std::array::from_fn(|a| {
            g.origin[a] + (((b[a] + 1) * BLOCK).min(g.dims[a])) as f64 * g.spacing[a]
        });
        let id = b[0] + self.blocks[0] * (b[1] + self.blocks[1] * b[2]);
        out.clear();
        for e in &self.entries[self.start[id]..self.start[id + 1]] {
            let s = &self.spheres[e.sphere as usize];
            let center: [f64; 3] =
                std::array::from_fn(|a| s.center[a] - e.shift[a] as f64 * extent[a]);
            let gap2: f64 = (0..3)
                .map(|a| interval_gap(center[a], lo[a], hi[a]).powi(2))
                .sum();
            out.push(Candidate {
                center,
                radius: s.radius,
                lower_bound: gap2.sqrt() - s.radius,
                sphere: e.sphere,
                body: s.body as u32,
            });
        }
        out.sort_by(|x, y| {
            x.lower_bound
                .total_cmp(&y.lower_bound)
                .then(x.sphere.cmp(&y.sphere))
        });
    }

    /// Calls `visit(acc, candidates, voxel (x, y, z), centre, value)` for every voxel, where
    /// `value` is that voxel's entry of `values` (one per voxel, x fastest). Slabs of
    /// [`BLOCK`] z-planes run in parallel, each with its own accumulator from `init`; the
    /// accumulators come back in slab order. `progress(done, total)` is called after each
    /// slab and may stop the scan by returning an error.
    pub fn scan<T, A, E, I, V, P>(
        &self,
        values: &mut [T],
        init: I,
        visit: V,
        progress: P,
    ) -> Result<Vec<A>, E>
    where
        T: Send,
        A: Send,
        E: Send,
        I: Fn() -> A + Sync,
        V: Fn(&mut A, &[Candidate], [usize; 3], [f64; 3], &mut T) + Sync,
        P: Fn(u64, u64) -> Result<(), E> + Sync,
    {
        let g = &self.grid;
        let [nx, ny, nz] = g.dims;
        assert_eq!(values.len(), nx * ny * nz, "one value per voxel");
        let slabs = self.blocks[2] as u64;
        let done = std::sync::atomic::AtomicU64::new(0);
        values
            .par_chunks_mut(nx * ny * BLOCK)
            .enumerate()
            .map(|(bz, slab)| {
                let mut acc = init();
                let mut cands = Vec::new();
                for by in 0..self.blocks[1] {
                    for bx in 0..self.blocks[0] {
                        self.candidates([bx, by, bz], &mut cands);
                        for z in bz * BLOCK..((bz + 1) * BLOCK).min(nz) {
                            for y in by * BLOCK..((by + 1) * BLOCK).min(ny) {
                                for x in bx * BLOCK..((bx + 1) * BLOCK).min(nx) {
                                    let local = x + nx * (y + ny * (z - bz * BLOCK));
                                    let p = g.voxel_center(x, y, z);
                                    visit(&mut acc, &cands, [x, y, z], p, &mut slab[local]);
                                }
                            }
                        }
                    }
                }
                let finished = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                progress(finished, slabs)?;
                Ok(acc)
            })
            .collect()
    }
}

/// The smallest signed distance from `p` to the candidates' surfaces, exact when it lies in
/// `[below, above]`; the search stops early with some value `< below` (inside for sure) or
/// `> above` (nothing within `above`). Returns `f64::INFINITY` when no candidate is closer
/// than `above`.
#[inline]
pub fn min_distance(cands: &[Candidate], p: [f64; 3], below: f64, above: f64) -> f64 {
    let mut best = f64::INFINITY;
    for c in cands {
        if c.lower_bound > best.min(above) {
            break;
        }
        let d = c.distance(p);
        if d < best {
            best = d;
            if best < below {
                break;
            }
        }
    }
    best
}

/// What a search for the smallest distances counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Over {
    /// Every sphere (and every periodic image of it) on its own.
    Spheres,
    /// Every body once, at the smallest distance of its spheres (the exact outward distance
    /// to a clump, eq. 2.12-2.13 of Donval et al. 2025). Periodic images of one body are one
    /// body here, which matters only in cells smaller than a body plus the window.
    Bodies,
}

/// The `out.len()` smallest signed distances from `p` (ascending) among candidates within
/// `window` of the smallest, counted `over` spheres or bodies; `ids` receives the sphere or
/// body of each entry. Returns how many were found. Candidates further than `beyond` are not
/// looked at when nothing closer was found (the caller does not need them).
/// `give_up(found, bound)` is asked every few candidates with the distances found so far and
/// a lower bound of every distance still to come; when it says so the search stops and
/// returns 0 (the caller knows the answer cannot matter).
#[inline]
pub fn smallest_distances(
    cands: &[Candidate],
    p: [f64; 3],
    over: Over,
    (window, beyond): (f64, f64),
    (out, ids): (&mut [f64], &mut [u32]),
    give_up: impl Fn(&[f64], f64) -> bool,
) -> usize {
    let k = out.len();
    let mut n = 0usize;
    for (seen, c) in cands.iter().enumerate() {
        if seen % GIVE_UP_EVERY == GIVE_UP_EVERY - 1 && give_up(&out[..n], c.lower_bound) {
            return 0;
        }
        let kth = if n == k { out[k - 1] } else { f64::INFINITY };
        let limit = if n == 0 {
            beyond
        } else {
            kth.min(out[0] + window)
        };
        if c.lower_bound > limit {
            break;
        }
        let d = c.distance(p);
        let id = match over {
            Over::Spheres => c.sphere,
            Over::Bodies => c.body,
        };
        let listed = match over {
            Over::Spheres => None,
            Over::Bodies => ids[..n].iter().position(|&b| b == id),
        };
        let mut i = match listed {
            Some(j) if d < out[j] => j,
            Some(_) => continue,
            None if n < k => {
                n += 1;
                n - 1
            }
            None if d < out[k - 1] => k - 1,
            None => continue,
        };
        // Move the entry up to its place in the sorted prefix.
        while i > 0 && out[i - 1] > d {
            out[i] = out[i - 1];
            ids[i] = ids[i - 1];
            i -= 1;
        }
        out[i] = d;
        ids[i] = id;
    }
    // Drop entries outside the window of the smallest (they were kept only while the
    // smallest was not yet known).
    while n > 1 && out[n - 1] > out[0] + window {
        n -= 1;
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: usize, h: f64, periodic: bool) -> Grid {
        Grid {
            dims: [n; 3],
            spacing: [h; 3],
            origin: [0.0; 3],
            periodic: [periodic; 3],
        }
    }

    /// Brute force over every sphere and every periodic image in -1..=1; with `by_body`, the
    /// smallest per body.
    fn brute(g: &Grid, spheres: &[WorldSphere], p: [f64; 3], by_body: bool) -> Vec<f64> {
        let l = g.extent();
        let mut d = Vec::new();
        let mut per_body = std::collections::BTreeMap::new();
        for s in spheres {
            let mut best = f64::INFINITY;
            for k in 0..27 {
                let sh = [k % 3, (k / 3) % 3, k / 9].map(|v| v as f64 - 1.0);
                if (0..3).any(|a| !g.periodic[a] && sh[a] != 0.0) {
                    continue;
                }
                let q: f64 = (0..3)
                    .map(|a| (p[a] - s.center[a] - sh[a] * l[a]).powi(2))
                    .sum();
                best = best.min(q.sqrt() - s.radius);
            }
            d.push(best);
            let e = per_body.entry(s.body).or_insert(f64::INFINITY);
            *e = best.min(*e);
        }
        if by_body {
            d = per_body.into_values().collect();
        }
        d.sort_by(f64::total_cmp);
        d
    }

    fn spheres() -> Vec<WorldSphere> {
        // Deterministic scatter, including spheres across the periodic boundary.
        (0..40)
            .map(|i| {
                let f = |k: u32| {
                    ((i as u32).wrapping_mul(2654435761).wrapping_add(k * 40503) % 1000) as f64
                        / 1000.0
                };
                WorldSphere {
                    center: [f(1) * 1.2 - 0.1, f(2), f(3) * 1.1 - 0.05],
                    radius: 0.02 + 0.08 * f(4),
                    body: i / 3,
                }
            })
            .collect()
    }

    #[test]
    fn min_and_smallest_distances_match_brute_force() {
        for periodic in [true, false] {
            let g = grid(20, 0.05, periodic);
            let sph = spheres();
            let reach = 0.12;
            let r = SphereRaster::new(&g, &sph, reach).unwrap();
            let mut vals = vec![0u8; g.voxel_count()];
            let errs: Vec<usize> = r
                .scan(
                    &mut vals,
                    || 0usize,
                    |bad, cands, _, p, _| {
                        let want = brute(&g, &sph, p, false);
                        let m = min_distance(cands, p, f64::NEG_INFINITY, reach);
                        if want[0] <= reach && (m - want[0]).abs() > 1e-12 {
                            eprintln!("min {p:?} {m} {:?}", &want[..3]);
                            *bad += 1;
                        }
                        let mut out = [0.0; 4];
                        let mut ids = [0u32; 4];
                        let n = smallest_distances(
                            cands,
                            p,
                            Over::Spheres,
                            (0.05, reach),
                            (&mut out, &mut ids),
                            |_, _| false,
                        );
                        let expect: Vec<f64> = want
                            .iter()
                            .copied()
                            .filter(|&d| d <= want[0] + 0.05)
                            .take(4)
                            .collect();
                        if want[0] + 0.05 <= reach
                            && (n != expect.len()
                                || out[..n]
                                    .iter()
                                    .zip(&expect)
                                    .any(|(a, b)| (a - b).abs() > 1e-12))
                        {
                            eprintln!("k {p:?} {:?} {expect:?}", &out[..n]);
                            *bad += 1;
                        }
                        let want = brute(&g, &sph, p, true);
                        let mut bodies = [0u32; 4];
                        let n = smallest_distances(
                            cands,
                            p,
                            Over::Bodies,
                            (0.05, reach),
                            (&mut out, &mut bodies),
                            |_, _| false,
                        );
                        let expect: Vec<f64> = want
                            .iter()
                            .copied()
                            .filter(|&d| d <= want[0] + 0.05)
                            .take(4)
                            .collect();
                        if want[0] + 0.05 <= reach
                            && (n != expect.len()
                                || out[..n]
                                    .iter()
                                    .zip(&expect)
                                    .any(|(a, b)| (a - b).abs() > 1e-12))
                        {
                            eprintln!("bodies {p:?} {:?} {expect:?}", &out[..n]);
                            *bad += 1;
                        }
                    },
                    |_, _| Ok::<(), ()>(()),
                )
                .unwrap();
            assert_eq!(errs.iter().sum::<usize>(), 0, "periodic = {periodic}");
        }
    }

    #[test]
    fn budget_is_enforced() {
        let g = grid(16, 0.05, true);
        let e = SphereRaster::with_budget(&g, &spheres(), 0.1, 10)
            .err()
            .unwrap();
        assert!(matches!(e, RasterError::TooManyEntries { .. }));
    }
}
