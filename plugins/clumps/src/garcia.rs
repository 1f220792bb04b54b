//! Garcia's cluster-of-overlapping-spheres algorithm (paper, section 2.1, Algorithm 1) with
//! the paper's three accelerations:
//! 1. candidate radii from an exact Euclidean distance transform ([`crate::edt`]);
//! 2. candidate centres restricted to an approximation of the medial surface;
//! 3. a lazy max-heap of potential coverage.
//!
//! Everything here works in voxel units on a boolean mask; [`clump_metrics`] turns the
//! selected spheres into physical volume and inertia.
//!
//! Conventions. A candidate sphere is centred on a mask voxel centre `c` with radius
//! `R = sqrt(d2(c))`, the distance to the nearest background voxel centre (the radius at
//! which Garcia's growing sphere "hits the boundary of the particle"). It covers the mask
//! voxels whose centres lie strictly inside it; by construction these are all grain voxels.
//! The exported clump uses the same radii, so coverage is measured on the exported geometry.

use crate::edt::squared_edt;
use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};

/// Options of one run of Algorithm 1.
#[derive(Clone, Copy, Debug)]
pub struct GarciaOptions {
    /// Target covered fraction of the grain's voxels (paper: alpha = 0.9).
    pub alpha: f64,
    /// Restrict candidate centres to the medial surface (acceleration 2).
    pub medial: bool,
    /// Lazy max-heap (acceleration 3); `false` re-evaluates every connected candidate at
    /// every step (the reference greedy).
    pub lazy: bool,
    /// Give up (error) beyond this many spheres.
    pub max_spheres: usize,
    /// Radii reach the nearest background voxel *cube* instead of its centre, so every
    /// sphere lies inside the union of the mask's voxels (see [`strict_d2`]).
    pub strict: bool,
}

impl Default for GarciaOptions {
    fn default() -> Self {
        GarciaOptions {
            alpha: 0.9,
            medial: true,
            lazy: true,
            max_spheres: 5000,
            strict: false,
        }
    }
}

/// A selected sphere in voxel units: centre index `[x, y, z]`, the lattice ball it covers
/// (`|v|^2 < d2`) and its radius `r` (`sqrt(d2)`, or the strict radius, whose open ball holds
/// the same lattice points).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VoxSphere {
    pub center: [usize; 3],
    pub d2: u32,
    pub r: f64,
}

impl VoxSphere {
    pub fn radius(&self) -> f64 {
        self.r
    }
}

#[derive(Clone, Debug)]
pub struct GarciaResult {
    pub spheres: Vec<VoxSphere>,
    /// Mask voxels whose centres lie inside the cluster.
    pub covered: usize,
    /// Mask voxels.
    pub total: usize,
    /// Candidate centres considered (after the medial-surface restriction).
    pub candidates: usize,
    /// Potential-coverage evaluations (the cost the lazy heap saves).
    pub evaluations: u64,
}

impl GarciaResult {
    pub fn coverage(&self) -> f64 {
        if self.total == 0 {
            0.0
        } else {
            self.covered as f64 / self.total as f64
        }
    }
}

/// Why Algorithm 1 stopped short of alpha.
#[derive(Clone, Debug)]
pub struct GarciaFailure {
    pub message: String,
    pub partial: GarciaResult,
}

#[derive(Clone, Copy)]
struct Cand {
    x: i32,
    y: i32,
    z: i32,
    d2: u32,
    r: f64,
    idx: u32,
}

/// Rows `(dy, dz, w)` of the lattice ball `dx^2 + dy^2 + dz^2 < d2`: the row at offset
/// `(dy, dz)` spans `dx in [-w, w]`.
fn ball_rows(d2: u32) -> BallRows {
    let lim = d2 as i64 - 1;
    let r = (lim.max(0) as f64).sqrt() as i64 + 1;
    let mut rows = Vec::new();
    let mut count = 0u64;
    for dz in -r..=r {
        for dy in -r..=r {
            let rem = lim - dy * dy - dz * dz;
            if rem < 0 {
                continue;
            }
            let mut w = (rem as f64).sqrt() as i64;
            while w * w > rem {
                w -= 1;
            }
            while (w + 1) * (w + 1) <= rem {
                w += 1;
            }
            rows.push((dy as i32, dz as i32, w as i32));
            count += (2 * w + 1) as u64;
        }
    }
    (rows, count)
}

/// The covered-voxel bitset, one run of 64-bit words per (y, z) row.
struct Bits {
    words: usize,
    ny: usize,
    data: Vec<u64>,
}

impl Bits {
    fn new(dims: [usize; 3]) -> Self {
        let words = dims[0].div_ceil(64);
        Bits {
            words,
            ny: dims[1],
            data: vec![0; words * dims[1] * dims[2]],
        }
    }
    #[inline]
    fn row(&self, y: i32, z: i32) -> usize {
        (y as usize + self.ny * z as usize) * self.words
    }
    /// Number of set bits in `[x0, x1]` of the row starting at word `base`.
    #[inline]
    fn count(&self, base: usize, x0: usize, x1: usize) -> u32 {
        let (w0, w1) = (x0 / 64, x1 / 64);
        let lo = !0u64 << (x0 % 64);
        let hi = !0u64 >> (63 - x1 % 64);
        if w0 == w1 {
            return (self.data[base + w0] & lo & hi).count_ones();
        }
        let mut c = (self.data[base + w0] & lo).count_ones();
        for w in w0 + 1..w1 {
            c += self.data[base + w].count_ones();
        }
        c + (self.data[base + w1] & hi).count_ones()
    }
    #[inline]
    fn set(&mut self, base: usize, x0: usize, x1: usize) {
        let (w0, w1) = (x0 / 64, x1 / 64);
        let lo = !0u64 << (x0 % 64);
        let hi = !0u64 >> (63 - x1 % 64);
        if w0 == w1 {
            self.data[base + w0] |= lo & hi;
            return;
        }
        self.data[base + w0] |= lo;
        for w in w0 + 1..w1 {
            self.data[base + w] = !0;
        }
        self.data[base + w1] |= hi;
    }
}

/// Rows of a lattice ball and its point count.
type BallRows = (Vec<(i32, i32, i32)>, u64);

struct Balls {
    cache: HashMap<u32, BallRows>,
}

impl Balls {
    fn get(&mut self, d2: u32) -> &BallRows {
        self.cache.entry(d2).or_insert_with(|| ball_rows(d2))
    }
}

/// Voxels not yet covered inside candidate `c`'s ball (its potential coverage).
fn potential(c: &Cand, balls: &mut Balls, bits: &Bits) -> u64 {
    let (rows, count) = balls.get(c.d2);
    let mut covered = 0u64;
    for &(dy, dz, w) in rows {
        let base = bits.row(c.y + dy, c.z + dz);
        covered += bits.count(base, (c.x - w) as usize, (c.x + w) as usize) as u64;
    }
    count - covered
}

fn cover(c: &Cand, balls: &mut Balls, bits: &mut Bits) {
    let (rows, _) = balls.get(c.d2);
    for &(dy, dz, w) in rows {
        let base = bits.row(c.y + dy, c.z + dz);
        bits.set(base, (c.x - w) as usize, (c.x + w) as usize);
    }
}

/// `M[t] = max |v + e_t|^2` over lattice points `|v|^2 < d2`, for the neighbour offsets
/// `e_0 = (1,0,0)`, `e_1 = (1,1,0)`, `e_2 = (1,1,1)` (every 26-neighbour offset is one of
/// these up to axis permutations and sign flips, under which the lattice ball is symmetric).
/// The ball of `p` lies inside the ball of a neighbour `q = p + e` iff `d2(q) > M`.
fn containment_table(d2: u32) -> [u64; 3] {
    let (rows, _) = ball_rows(d2);
    let mut m = [0u64; 3];
    for (dy, dz, w) in rows {
        let (w, dy, dz) = (w as i64, dy as i64, dz as i64);
        let x = (w + 1) * (w + 1);
        m[0] = m[0].max((x + dy * dy + dz * dz) as u64);
        m[1] = m[1].max((x + (dy + 1) * (dy + 1) + dz * dz) as u64);
        m[2] = m[2].max((x + (dy + 1) * (dy + 1) + (dz + 1) * (dz + 1)) as u64);
    }
    m
}

/// Candidate centres: every grain voxel, or (medial) only the discrete centres of maximal
/// balls: voxels whose lattice ball is not contained in the lattice ball of a 26-neighbour.
/// These sit on the ridges (saddle and ridge points) of the distance map, the paper's
/// approximation of the medial surface (section 2.1, item 2). The containment test is exact
/// on the lattice, so every grain voxel stays coverable: a removed ball lies inside a
/// neighbour's ball, and so on up to a kept one (d2 grows strictly along the chain).
fn candidates(
    mask: &[bool],
    d2: &[u32],
    radius: &dyn Fn(usize) -> f64,
    dims: [usize; 3],
    medial: bool,
) -> Vec<Cand> {
    let [nx, ny, nz] = dims;
    let mut out = Vec::new();
    let mut offs = Vec::new();
    for dz in -1i64..=1 {
        for dy in -1i64..=1 {
            for dx in -1i64..=1 {
                let t = (dx * dx + dy * dy + dz * dz) as usize;
                if t > 0 {
                    offs.push((dx, dy, dz, t - 1));
                }
            }
        }
    }
    let maxd2 = d2.iter().copied().max().unwrap_or(0) as usize;
    let mut tables: Vec<Option<[u64; 3]>> = vec![None; maxd2 + 1];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let i = x + nx * (y + ny * z);
                if !mask[i] {
                    continue;
                }
                if medial {
                    let m = *tables[d2[i] as usize].get_or_insert_with(|| containment_table(d2[i]));
                    let contained = offs.iter().any(|&(dx, dy, dz, t)| {
                        let (qx, qy, qz) = (x as i64 + dx, y as i64 + dy, z as i64 + dz);
                        if qx < 0
                            || qy < 0
                            || qz < 0
                            || qx >= nx as i64
                            || qy >= ny as i64
                            || qz >= nz as i64
                        {
                            return false;
                        }
                        let q = qx as usize + nx * (qy as usize + ny * qz as usize);
                        d2[q] as u64 > m[t]
                    });
                    if contained {
                        continue;
                    }
                }
                out.push(Cand {
                    x: x as i32,
                    y: y as i32,
                    z: z as i32,
                    d2: d2[i],
                    r: radius(i),
                    idx: i as u32,
                });
            }
        }
    }
    out
}

fn overlaps(a: &Cand, b: &Cand) -> bool {
    let d =
        ((a.x - b.x) as f64).powi(2) + ((a.y - b.y) as f64).powi(2) + ((a.z - b.z) as f64).powi(2);
    let rs = a.r + b.r;
    d < rs * rs
}

type Key = (u64, u32, Reverse<u32>);

fn key(pot: u64, c: &Cand) -> Key {
    // Ties in potential coverage go to the larger sphere, then to the lower voxel index, so
    // the lazy and the naive greedy are the same deterministic function.
    (pot, c.d2, Reverse(c.idx))
}

/// Runs Algorithm 1 on `mask` (x fastest, dims `[nx, ny, nz]`, voxels assumed cubic).
pub fn garcia(
    mask: &[bool],
    dims: [usize; 3],
    opts: &GarciaOptions,
) -> Result<GarciaResult, GarciaFailure> {
    let (d2, strict_r2) = if opts.strict {
        let (ball, r2) = strict_d2(mask, dims);
        (ball, Some(r2))
    } else {
        (squared_edt(mask, dims), None)
    };
    let radius = |i: usize| match &strict_r2 {
        Some(r2) => r2[i].sqrt(),
        None => (d2[i] as f64).sqrt(),
    };
    let cands = candidates(mask, &d2, &radius, dims, opts.medial);
    let total = mask.iter().filter(|&&b| b).count();
    let mut res = GarciaResult {
        spheres: Vec::new(),
        covered: 0,
        total,
        candidates: cands.len(),
        evaluations: 0,
    };
    if total == 0 {
        return Err(GarciaFailure {
            message: "the grain mask is empty".into(),
            partial: res,
        });
    }
    let mut balls = Balls {
        cache: HashMap::new(),
    };
    let mut bits = Bits::new(dims);
    let target = opts.alpha * total as f64;

    // Algorithm 1, line 2: the largest sphere first.
    let first = (0..cands.len())
        .max_by_key(|&k| (cands[k].d2, Reverse(cands[k].idx)))
        .expect("a non-empty mask has a candidate");
    let mut unconnected: Vec<usize> = (0..cands.len()).filter(|&k| k != first).collect();
    let mut heap: BinaryHeap<(Key, usize)> = BinaryHeap::new();
    let mut connected: Vec<usize> = Vec::new();

    let select = |k: usize,
                  pot: u64,
                  res: &mut GarciaResult,
                  bits: &mut Bits,
                  balls: &mut Balls,
                  unconnected: &mut Vec<usize>,
                  heap: &mut BinaryHeap<(Key, usize)>,
                  connected: &mut Vec<usize>| {
        let c = cands[k];
        cover(&c, balls, bits);
        res.covered += pot as usize;
        res.spheres.push(VoxSphere {
            center: [c.x as usize, c.y as usize, c.z as usize],
            d2: c.d2,
            r: c.r,
        });
        // Candidates overlapping the new sphere become connected to the cluster; their full
        // ball count is a valid upper bound of their potential coverage.
        unconnected.retain(|&j| {
            if overlaps(&c, &cands[j]) {
                if opts.lazy {
                    let ub = balls.get(cands[j].d2).1;
                    heap.push((key(ub, &cands[j]), j));
                } else {
                    connected.push(j);
                }
                false
            } else {
                true
            }
        });
    };
    let pot0 = {
        res.evaluations += 1;
        potential(&cands[first], &mut balls, &bits)
    };
    select(
        first,
        pot0,
        &mut res,
        &mut bits,
        &mut balls,
        &mut unconnected,
        &mut heap,
        &mut connected,
    );

    // Algorithm 1, lines 3-6.
    while (res.covered as f64) < target {
        if res.spheres.len() >= opts.max_spheres {
            let cov = res.coverage();
            return Err(GarciaFailure {
                message: format!(
                    "reached max_spheres = {} with coverage {:.4} < alpha = {}",
                    opts.max_spheres, cov, opts.alpha
                ),
                partial: res,
            });
        }
        let chosen = if opts.lazy {
            // Acceleration 3: stale keys are upper bounds (coverage only shrinks as the
            // cluster grows), so a refreshed top that still beats the next stale key is the
            // true maximum.
            let mut chosen = None;
            while let Some((_, k)) = heap.pop() {
                res.evaluations += 1;
                let p = potential(&cands[k], &mut balls, &bits);
                if p == 0 {
                    continue; // never useful again
                }
                let kk = key(p, &cands[k]);
                if heap.peek().is_none_or(|(next, _)| kk >= *next) {
                    chosen = Some((k, p));
                    break;
                }
                heap.push((kk, k));
            }
            chosen
        } else {
            let mut best: Option<(Key, usize, usize)> = None;
            let mut j = 0;
            while j < connected.len() {
                let k = connected[j];
                res.evaluations += 1;
                let p = potential(&cands[k], &mut balls, &bits);
                if p == 0 {
                    connected.swap_remove(j);
                    continue;
                }
                let kk = key(p, &cands[k]);
                if best.as_ref().is_none_or(|b| kk > b.0) {
                    best = Some((kk, k, j));
                }
                j += 1;
            }
            best.map(|(kk, k, j)| {
                connected.swap_remove(j);
                (k, kk.0)
            })
        };
        let Some((k, p)) = chosen else {
            let cov = res.coverage();
            return Err(GarciaFailure {
                message: format!(
                    "no candidate sphere connected to the cluster adds coverage: stopped at \
                     coverage {cov:.4} < alpha = {} with {} spheres (the mask has parts \
                     the connected cluster cannot reach)",
                    opts.alpha,
                    res.spheres.len()
                ),
                partial: res,
            });
        };
        select(
            k,
            p,
            &mut res,
            &mut bits,
            &mut balls,
            &mut unconnected,
            &mut heap,
            &mut connected,
        );
    }
    Ok(res)
}

/// Strict radii: for every mask voxel the squared distance `R^2` from its centre to the
/// nearest background voxel cube (voxels outside the array count as background), and the
/// lattice ball of the open sphere of radius R, as the `d2` of `|v|^2 < d2`. The nearest
/// point of a cube to a voxel centre is a corner, edge midpoint, face centre or the centre
/// of that cube, all on the half-voxel lattice, so an exact EDT on a doubled grid (a point
/// is background when it belongs to a background cube) gives R exactly. The sphere of
/// radius R then lies inside the union of the mask's voxels: the mask's continuous surface.
pub fn strict_d2(mask: &[bool], dims: [usize; 3]) -> (Vec<u32>, Vec<f64>) {
    // Doubled coordinates Q = 2 x + 2: Q = 0 and Q = 2 n + 2 are the centres of the
    // (background) voxels just outside the array.
    let d = dims.map(|n| 2 * n + 3);
    let inside = |x: i64, y: i64, z: i64| {
        x >= 0
            && y >= 0
            && z >= 0
            && (x as usize) < dims[0]
            && (y as usize) < dims[1]
            && (z as usize) < dims[2]
            && mask[x as usize + dims[0] * (y as usize + dims[1] * z as usize)]
    };
    // Voxels whose closed cube holds the point at doubled coordinate q: one when q is even
    // (a centre plane), the two on either side when odd (a face plane).
    let span = |q: usize| -> (i64, i64) {
        let v = q as i64 - 2;
        if v % 2 == 0 {
            (v / 2, v / 2)
        } else {
            ((v - 1).div_euclid(2), (v + 1).div_euclid(2))
        }
    };
    let mut fine = vec![false; d[0] * d[1] * d[2]];
    for qz in 0..d[2] {
        let (z0, z1) = span(qz);
        for qy in 0..d[1] {
            let (y0, y1) = span(qy);
            for qx in 0..d[0] {
                let (x0, x1) = span(qx);
                let mut all = true;
                'cubes: for z in z0..=z1 {
                    for y in y0..=y1 {
                        for x in x0..=x1 {
                            if !inside(x, y, z) {
                                all = false;
                                break 'cubes;
                            }
                        }
                    }
                }
                fine[qx + d[0] * (qy + d[1] * qz)] = all;
            }
        }
    }
    let e = squared_edt(&fine, d);
    let mut ball = vec![0u32; mask.len()];
    let mut r2 = vec![0.0; mask.len()];
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let i = x + dims[0] * (y + dims[1] * z);
                if !mask[i] {
                    continue;
                }
                let q = (2 * x + 2) + d[0] * ((2 * y + 2) + d[1] * (2 * z + 2));
                // Half-voxel units: R^2 = e / 4; lattice points with |v|^2 < e / 4 are those
                // with |v|^2 < ceil(e / 4).
                r2[i] = e[q] as f64 / 4.0;
                ball[i] = e[q].div_ceil(4);
            }
        }
    }
    (ball, r2)
}

/// True when the spheres' overlap graph (`|ci - cj| < Ri + Rj`) is connected.
pub fn is_connected(spheres: &[VoxSphere]) -> bool {
    if spheres.is_empty() {
        return true;
    }
    let n = spheres.len();
    let mut seen = vec![false; n];
    let mut stack = vec![0];
    seen[0] = true;
    while let Some(i) = stack.pop() {
        for j in 0..n {
            if seen[j] {
                continue;
            }
            let (a, b) = (&spheres[i], &spheres[j]);
            let d: f64 = (0..3)
                .map(|k| (a.center[k] as f64 - b.center[k] as f64).powi(2))
                .sum();
            let rs = a.radius() + b.radius();
            if d < rs * rs {
                seen[j] = true;
                stack.push(j);
            }
        }
    }
    seen.iter().all(|&s| s)
}

/// Volume, centroid and inertia (about the centroid, per unit density) of a solid, in voxel
/// units.
#[derive(Clone, Copy, Debug, Default)]
pub struct MassProps {
    pub volume: f64,
    pub centroid: [f64; 3],
    /// Inertia tensor about the centroid, row-major.
    pub inertia: [[f64; 3]; 3],
}

/// Clump vs mask comparison, in voxel units.
#[derive(Clone, Copy, Debug, Default)]
pub struct ClumpMetrics {
    pub clump: MassProps,
    pub mask: MassProps,
    /// Volume of the symmetric difference clump XOR mask (voxel^3).
    pub symmetric_difference: f64,
    /// Volume of the clump outside the union of the mask's voxels (voxel^3): the sub-voxel
    /// spill of spheres whose radius reaches the nearest background voxel centre.
    pub spill: f64,
}

impl ClumpMetrics {
    /// (V_clump - V_mask) / V_mask.
    /// Share of the clump's volume outside the mask's voxels.
    pub fn spill_fraction(&self) -> f64 {
        if self.clump.volume > 0.0 {
            self.spill / self.clump.volume
        } else {
            0.0
        }
    }
    pub fn volume_error(&self) -> f64 {
        (self.clump.volume - self.mask.volume) / self.mask.volume
    }
    /// Frobenius norm of I_clump - I_mask over that of I_mask (both about their centroids).
    pub fn inertia_error(&self) -> f64 {
        let mut num = 0.0;
        let mut den = 0.0;
        for i in 0..3 {
            for j in 0..3 {
                num += (self.clump.inertia[i][j] - self.mask.inertia[i][j]).powi(2);
                den += self.mask.inertia[i][j].powi(2);
            }
        }
        (num / den).sqrt()
    }
}

#[derive(Default)]
struct Moments {
    n: f64,
    s: [f64; 3],
    ss: [[f64; 3]; 3],
}

impl Moments {
    fn add(&mut self, p: [f64; 3]) {
        self.n += 1.0;
        for i in 0..3 {
            self.s[i] += p[i];
            for j in 0..3 {
                self.ss[i][j] += p[i] * p[j];
            }
        }
    }
    fn props(&self, cell: f64) -> MassProps {
        let vol = self.n * cell.powi(3);
        if self.n == 0.0 {
            return MassProps::default();
        }
        let c = self.s.map(|v| v / self.n);
        // Second moments about the centroid; each sample cell adds its own cell^2/12.
        let mut m = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] = (self.ss[i][j] / self.n - c[i] * c[j]) * vol;
            }
            m[i][i] += vol * cell * cell / 12.0;
        }
        let tr = m[0][0] + m[1][1] + m[2][2];
        let mut inertia = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                inertia[i][j] = if i == j { tr - m[i][i] } else { -m[i][j] };
            }
        }
        MassProps {
            volume: vol,
            centroid: c,
            inertia,
        }
    }
}

/// Volume and inertia of the union of `spheres` and of the mask, by midpoint quadrature on
/// a lattice `sub` times finer than the voxels (the same lattice for both, so the
/// comparison is like with like). The lattice covers the mask array plus one voxel on each
/// side, which holds every sphere (a sphere reaches at most the nearest background centre).
pub fn clump_metrics(
    spheres: &[VoxSphere],
    mask: &[bool],
    dims: [usize; 3],
    sub: usize,
) -> ClumpMetrics {
    let sub = sub.max(1);
    let h = 1.0 / sub as f64;
    // Sample j along an axis sits at voxel coordinate -1.5 + (j + 0.5) h.
    let n = dims.map(|d| (d + 2) * sub);
    let coord = |j: usize| -1.5 + (j as f64 + 0.5) * h;
    let mut inside = vec![false; n[0] * n[1] * n[2]];
    for s in spheres {
        let r = s.radius();
        let c = s.center.map(|v| v as f64);
        let lo = |a: usize| (((c[a] - r + 1.5) / h - 0.5).floor().max(0.0)) as usize;
        let hi = |a: usize| ((((c[a] + r + 1.5) / h - 0.5).ceil()) as usize).min(n[a] - 1);
        for jz in lo(2)..=hi(2) {
            let dz = coord(jz) - c[2];
            for jy in lo(1)..=hi(1) {
                let dy = coord(jy) - c[1];
                let rem = r * r - dy * dy - dz * dz;
                if rem <= 0.0 {
                    continue;
                }
                let w = rem.sqrt();
                // Strictly inside: |x - c| < r.
                let x0 = (((c[0] - w + 1.5) / h - 0.5).floor() as i64 + 1).max(0) as usize;
                let x1f = (c[0] + w + 1.5) / h - 0.5;
                let mut x1 = x1f.ceil() as i64 - 1;
                x1 = x1.min(n[0] as i64 - 1);
                if x1 < x0 as i64 {
                    continue;
                }
                let base = n[0] * (jy + n[1] * jz);
                inside[base + x0..=base + x1 as usize].fill(true);
            }
        }
    }
    let mut mc = Moments::default();
    let mut mm = Moments::default();
    let mut xor = 0.0;
    let mut spill = 0.0;
    for jz in 0..n[2] {
        let vz = jz / sub; // voxel index + 1
        for jy in 0..n[1] {
            let vy = jy / sub;
            for jx in 0..n[0] {
                let vx = jx / sub;
                let in_mask = vx >= 1
                    && vy >= 1
                    && vz >= 1
                    && vx <= dims[0]
                    && vy <= dims[1]
                    && vz <= dims[2]
                    && mask[(vx - 1) + dims[0] * ((vy - 1) + dims[1] * (vz - 1))];
                let in_clump = inside[jx + n[0] * (jy + n[1] * jz)];
                if !in_mask && !in_clump {
                    continue;
                }
                let p = [coord(jx), coord(jy), coord(jz)];
                if in_clump {
                    mc.add(p);
                }
                if in_mask {
                    mm.add(p);
                }
                if in_clump != in_mask {
                    xor += 1.0;
                    if in_clump {
                        spill += 1.0;
                    }
                }
            }
        }
    }
    ClumpMetrics {
        clump: mc.props(h),
        mask: mm.props(h),
        symmetric_difference: xor * h * h * h,
        spill: spill * h * h * h,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ball_rows_count_matches_brute_force() {
        // Lattice points with |p|^2 < d2, counted exhaustively.
        for d2 in [1u32, 2, 5, 17, 50, 101] {
            let r = 12i64;
            let mut brute = 0u64;
            for z in -r..=r {
                for y in -r..=r {
                    for x in -r..=r {
                        if ((x * x + y * y + z * z) as u32) < d2 {
                            brute += 1;
                        }
                    }
                }
            }
            assert_eq!(ball_rows(d2).1, brute, "d2 = {d2}");
        }
    }

    #[test]
    fn containment_table_matches_brute_force() {
        // Ball of p inside ball of q = p + e iff every |v|^2 < d2p has |v - e|^2 < d2q,
        // checked exhaustively for all 26 offsets.
        for d2p in [1u32, 2, 3, 6, 14, 29, 50] {
            let m = containment_table(d2p);
            for e in [
                (1i64, 0i64, 0i64),
                (0, -1, 0),
                (1, -1, 0),
                (0, 1, 1),
                (-1, 1, -1),
                (1, 1, 1),
            ] {
                let t = (e.0 * e.0 + e.1 * e.1 + e.2 * e.2) as usize - 1;
                for d2q in 1..80u64 {
                    let r = 9i64;
                    let mut inside = true;
                    for z in -r..=r {
                        for y in -r..=r {
                            for x in -r..=r {
                                if ((x * x + y * y + z * z) as u32) < d2p {
                                    let w = ((x - e.0).pow(2) + (y - e.1).pow(2) + (z - e.2).pow(2))
                                        as u64;
                                    inside &= w < d2q;
                                }
                            }
                        }
                    }
                    assert_eq!(inside, d2q > m[t], "d2p {d2p} e {e:?} d2q {d2q}");
                }
            }
        }
    }

    #[test]
    fn bitset_counts_ranges() {
        let mut b = Bits::new([150, 1, 1]);
        b.set(0, 3, 130);
        assert_eq!(b.count(0, 0, 149), 128);
        assert_eq!(b.count(0, 60, 70), 11);
        assert_eq!(b.count(0, 0, 2), 0);
        assert_eq!(b.count(0, 130, 140), 1);
    }
}
