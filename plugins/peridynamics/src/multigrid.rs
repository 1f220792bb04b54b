//! Aggregation multigrid preconditioner (a W-cycle by default) for the linearised bond-based
//! operator.
//!
//! Why: Jacobi-preconditioned CG needs iterations growing about linearly with the grid edge
//! (600 at 256^2, 1112 at 512^2), because the condition number of the lattice operator grows
//! like N^2 and the diagonal does nothing against it. A multigrid V-cycle removes the smooth
//! error on coarse grids, so the iteration count stays bounded when the grid is refined.
//!
//! Construction (all on the regular grid, no bond list):
//! - Aggregates are the 2 x 2 (x 2) blocks of the grid; the prolongation P copies a coarse
//!   value to every free DOF of its block (piecewise constant, zero on prescribed DOFs and
//!   on nodes without material). Voids, free sides, Dirichlet rows and excluded floating
//!   clusters are therefore handled by the masks alone.
//! - Coarse operators are Galerkin products A_c = P^T A P. The fine operator is the
//!   linearised eq. (6): each bond contributes B = c V / |xi|^3 xi xi^T (scaled units) as
//!   K_ii += B, K_ij -= B, so P^T K P is summed bond by bond into a block stencil on the
//!   coarse grid (offset range ceil(R/2) for a fine range R: 5 x 5 blocks after the 28-
//!   neighbour fine stencil, 3 x 3 further down). Galerkin coarse operators of an SPD fine
//!   operator are SPD on the aggregates that hold a free DOF, which keeps thin matrix
//!   bridges and interfaces represented exactly (a re-discretised phase image would lose
//!   them on coarse grids).
//! - Smoother: block Jacobi (the nc x nc diagonal block of each node) with weight
//!   omega = 1.2 / lambda_max(D^-1 A), lambda_max from a power iteration at set-up; the same
//!   number of sweeps before and after the coarse correction keeps the V-cycle symmetric
//!   positive definite, as PCG needs.
//! - Coarsest grid (at most 1024 DOFs): dense Cholesky in f64.
//! - The coarse correction is scaled by `overcorrection` (piecewise-constant prolongation
//!   makes the coarse operators too stiff: a linear field interpolated piecewise constant
//!   stores more energy than the field itself, so the plain correction is too short).
//!
//! Everything is a fixed linear operator evaluated with row-ordered loops: the same numbers
//! for any thread count.

use crate::lattice::{bond_k_pub, Lattice, Vec3};
use rayon::prelude::*;

/// Options of the V-cycle.
#[derive(Clone, Copy, Debug)]
pub struct MgOptions {
    /// Block-Jacobi sweeps before and after the coarse correction on the fine grid.
    pub fine_sweeps: usize,
    /// Sweeps on the assembled coarse grids.
    pub coarse_sweeps: usize,
    /// Scale of the coarse correction.
    pub overcorrection: f32,
    /// Coarse-grid solves per visit below level 1 (1 = V-cycle, 2 = W-cycle): the second
    /// pass on the remaining coarse residual costs little (a coarse level has a quarter of
    /// the nodes) and keeps the iteration count from creeping up with the number of levels.
    pub cycle: usize,
}

impl Default for MgOptions {
    fn default() -> Self {
        MgOptions {
            fine_sweeps: 1,
            coarse_sweeps: 1,
            overcorrection: 1.5,
            cycle: 2,
        }
    }
}

/// Geometry of an assembled level: padded by its stencil range on the active axes.
#[derive(Clone, Debug)]
struct Geom {
    dims: [usize; 3],
    pad: [usize; 3],
    pdims: [usize; 3],
}

impl Geom {
    fn new(dims: [usize; 3], range: usize) -> Geom {
        let pad = [0, 1, 2].map(|a| if dims[a] > 1 { range } else { 0 });
        let pdims = [0, 1, 2].map(|a| dims[a] + 2 * pad[a]);
        Geom { dims, pad, pdims }
    }
    fn len(&self) -> usize {
        self.pdims.iter().product()
    }
    fn pidx(&self, c: [usize; 3]) -> usize {
        (c[0] + self.pad[0])
            + self.pdims[0] * ((c[1] + self.pad[1]) + self.pdims[1] * (c[2] + self.pad[2]))
    }
    /// Unpadded (y, z) of padded row `row`, or None for a padding row.
    fn row_yz(&self, row: usize) -> Option<(usize, usize)> {
        let py = row % self.pdims[1];
        let pz = row / self.pdims[1];
        if py < self.pad[1]
            || py >= self.pad[1] + self.dims[1]
            || pz < self.pad[2]
            || pz >= self.pad[2] + self.dims[2]
        {
            return None;
        }
        Some((py - self.pad[1], pz - self.pad[2]))
    }
}

/// An assembled coarse level: a block stencil over a box of offsets.
struct Level {
    g: Geom,
    /// Stencil range (offsets in [-range, range] on active axes).
    range: usize,
    /// Linear offsets of the box (row-major, x fastest).
    offsets: Vec<isize>,
    /// Blocks: [(node * noff + o) * nc * nc + a * nc + b].
    a: Vec<f32>,
    /// Inverse diagonal blocks per padded node (zero rows/columns for inactive DOFs).
    dinv: Vec<f32>,
    omega: f32,
}

/// Dense Cholesky factor of the coarsest operator over its active DOFs.
struct Dense {
    /// Active DOF indices (node * nc + a) of the coarsest level.
    dofs: Vec<usize>,
    /// Lower factor, row-major n x n.
    l: Vec<f64>,
    /// DOFs whose pivot vanished (rank deficiency): solved as zero.
    dead: Vec<bool>,
}

/// The multigrid hierarchy.
pub struct Multigrid {
    nc: usize,
    /// Fine-level inverse diagonal blocks per padded lattice node.
    fine_dinv: Vec<f32>,
    fine_omega: f32,
    levels: Vec<Level>,
    dense: Dense,
    opt: MgOptions,
}

fn box_offsets(g: &Geom, range: usize) -> (Vec<isize>, Vec<[isize; 3]>) {
    let r = range as isize;
    let rz = if g.dims[2] > 1 { r } else { 0 };
    let ry = if g.dims[1] > 1 { r } else { 0 };
    let rx = if g.dims[0] > 1 { r } else { 0 };
    let mut lin = Vec::new();
    let mut vecs = Vec::new();
    for oz in -rz..=rz {
        for oy in -ry..=ry {
            for ox in -rx..=rx {
                lin.push(ox + g.pdims[0] as isize * (oy + g.pdims[1] as isize * oz));
                vecs.push([ox, oy, oz]);
            }
        }
    }
    (lin, vecs)
}

/// Index of offset vector v in the box of `range` (same order as `box_offsets`).
fn box_index(dims: [usize; 3], range: usize, v: [isize; 3]) -> usize {
    let w = [0, 1, 2].map(|a| if dims[a] > 1 { 2 * range + 1 } else { 1 });
    let c = [0, 1, 2].map(|a| {
        if dims[a] > 1 {
            (v[a] + range as isize) as usize
        } else {
            0
        }
    });
    c[0] + w[0] * (c[1] + w[1] * c[2])
}

/// Inverse of the symmetric nc x nc block `m` restricted to the DOFs with a positive
/// diagonal (others get zero rows and columns).
fn block_inverse(m: &[f64], nc: usize) -> Vec<f32> {
    let act: Vec<bool> = (0..nc).map(|a| m[a * nc + a] > 0.0).collect();
    let mut w = vec![0f64; nc * nc];
    for a in 0..nc {
        for b in 0..nc {
            w[a * nc + b] = if act[a] && act[b] {
                m[a * nc + b]
            } else if a == b {
                1.0
            } else {
                0.0
            };
        }
    }
    // Gauss-Jordan on a 2 x 2 or 3 x 3 SPD block.
    let mut inv = vec![0f64; nc * nc];
    for a in 0..nc {
        inv[a * nc + a] = 1.0;
    }
    for p in 0..nc {
        let piv = w[p * nc + p];
        if piv.abs() < 1e-300 {
            return vec![0.0; nc * nc];
        }
        for c in 0..nc {
            w[p * nc + c] /= piv;
            inv[p * nc + c] /= piv;
        }
        for r in 0..nc {
            if r != p {
                let f = w[r * nc + p];
                for c in 0..nc {
                    w[r * nc + c] -= f * w[p * nc + c];
                    inv[r * nc + c] -= f * inv[p * nc + c];
                }
            }
        }
    }
    (0..nc * nc)
        .map(|k| {
            let (a, b) = (k / nc, k % nc);
            if act[a] && act[b] {
                inv[k] as f32
            } else {
                0.0
            }
        })
        .collect()
}

impl Level {
    fn noff(&self) -> usize {
        self.offsets.len()
    }
    /// y = A x (interleaved padded vectors).
    fn apply(&self, nc: usize, x: &[f32], y: &mut [f32]) {
        let px = self.g.pdims[0];
        let noff = self.noff();
        let nc2 = nc * nc;
        y.par_chunks_mut(px * nc).enumerate().for_each(|(row, yr)| {
            yr.fill(0.0);
            if self.g.row_yz(row).is_none() {
                return;
            }
            for xi in self.g.pad[0]..self.g.pad[0] + self.g.dims[0] {
                let i = row * px + xi;
                let blk = &self.a[i * noff * nc2..(i + 1) * noff * nc2];
                let mut acc = [0f32; 3];
                for (o, &d) in self.offsets.iter().enumerate() {
                    let j = (i as isize + d) as usize;
                    let b = &blk[o * nc2..(o + 1) * nc2];
                    let xj = &x[j * nc..j * nc + nc];
                    for a in 0..nc {
                        let mut s = 0.0;
                        for c in 0..nc {
                            s += b[a * nc + c] * xj[c];
                        }
                        acc[a] += s;
                    }
                }
                yr[xi * nc..xi * nc + nc].copy_from_slice(&acc[..nc]);
            }
        });
    }
    /// x += omega D^-1 t.
    fn jacobi(&self, nc: usize, t: &[f32], x: &mut [f32]) {
        let nc2 = nc * nc;
        let w = self.omega;
        x.par_chunks_mut(nc)
            .zip(t.par_chunks(nc))
            .zip(self.dinv.par_chunks(nc2))
            .for_each(|((x, t), d)| {
                for a in 0..nc {
                    let mut s = 0.0;
                    for c in 0..nc {
                        s += d[a * nc + c] * t[c];
                    }
                    x[a] += w * s;
                }
            });
    }
}

/// Deterministic start vector for the power iterations (hash of the index, in [-1, 1]).
fn hash_unit(i: usize) -> f32 {
    let mut z = (i as u64).wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    ((z >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
}

fn norm(v: &[f32]) -> f64 {
    let parts: Vec<f64> = v
        .par_chunks(4096)
        .map(|c| c.iter().map(|&x| x as f64 * x as f64).sum())
        .collect();
    parts.iter().sum::<f64>().sqrt()
}

/// Power-iteration iterations for lambda_max(D^-1 A).
const POWER_ITERATIONS: usize = 12;
/// Smoother weight omega = OMEGA_SCALE / lambda_max (< 2 / lambda_max with margin for the
/// power iteration's underestimate).
const OMEGA_SCALE: f64 = 1.2;
/// Fewer on the fine grid (each costs a force sweep): there the bond form gives the bound
/// lambda_max(D^-1 K) <= 2 (each bond adds (u_j - u_i)^T B (u_j - u_i) <= 2 u_i^T B u_i +
/// 2 u_j^T B u_j, and D collects exactly those B), so omega is capped at FINE_OMEGA_MAX < 1
/// and the smoother stays convergent (omega lambda_max < 2) whatever the estimate.
const FINE_POWER_ITERATIONS: usize = 6;
const FINE_OMEGA_MAX: f64 = 0.95;
/// Coarsen until a level holds at most this many DOFs (then dense Cholesky).
const DENSE_DOFS: usize = 1024;

/// Heap bytes of the dense Cholesky factor of the coarsest level of a fine grid of `dims`
/// nodes with `nc` components, for memory estimates: the levels halve every axis (level 1
/// always) until at most [`DENSE_DOFS`] DOFs remain; the factor is a full m x m f64 matrix of
/// those m DOFs, with their index list and position map (~40 B per DOF).
pub fn dense_bytes(dims: [usize; 3], nc: usize) -> u64 {
    let mut d = dims.map(|n| n.div_ceil(2));
    while d.iter().product::<usize>() * nc > DENSE_DOFS && !d.iter().all(|&n| n <= 1) {
        d = d.map(|n| n.div_ceil(2));
    }
    let m = (d.iter().product::<usize>() * nc) as u64;
    8 * m * m + 40 * m
}

impl Multigrid {
    /// Builds the hierarchy for the free DOFs of `lat` (prescribed components and nodes
    /// without material excluded).
    pub fn new(lat: &Lattice, opt: MgOptions) -> Multigrid {
        let l = &lat.layout;
        let nc = l.ncomp();
        let nc2 = nc * nc;
        let n = l.len();
        let free = |i: usize, a: usize| lat.region[i] != 0 && lat.fixed[i] & (1 << a) == 0;
        // Fine diagonal blocks: sum_j B_ij over the free components.
        let fine_dinv: Vec<f32> = (0..n)
            .into_par_iter()
            .flat_map_iter(|i| {
                let mut m = vec![0f64; nc2];
                if lat.region[i] != 0 {
                    for o in &l.offsets {
                        let j = (i as isize + o.d) as usize;
                        let k = bond_k_pub(lat, i, j);
                        if k == 0.0 {
                            continue;
                        }
                        let g = k as f64 / (o.len as f64).powi(3);
                        for a in 0..nc {
                            for b in 0..nc {
                                if free(i, a) && free(i, b) {
                                    m[a * nc + b] += g * o.xi[a] as f64 * o.xi[b] as f64;
                                }
                            }
                        }
                    }
                }
                block_inverse(&m, nc)
            })
            .collect();
        let mut mg = Multigrid {
            nc,
            fine_dinv,
            fine_omega: 1.0,
            levels: Vec::new(),
            dense: Dense {
                dofs: Vec::new(),
                l: Vec::new(),
                dead: Vec::new(),
            },
            opt,
        };
        let lam0 = mg.fine_lambda(lat);
        mg.fine_omega = (OMEGA_SCALE / lam0).min(FINE_OMEGA_MAX) as f32;

        // Level 1 from the bonds.
        let fdims = l.dims;
        let cdims = fdims.map(|d| d.div_ceil(2));
        let frange = lat.layout.horizon.floor() as usize;
        let range = frange.div_ceil(2);
        let g = Geom::new(cdims, range);
        let (offsets, _) = box_offsets(&g, range);
        let noff = offsets.len();
        let mut a = vec![0f32; g.len() * noff * nc2];
        let px = g.pdims[0];
        a.par_chunks_mut(px * noff * nc2)
            .enumerate()
            .for_each(|(row, ar)| {
                let Some((cy, cz)) = g.row_yz(row) else {
                    return;
                };
                for cx in 0..cdims[0] {
                    let ip = g.pad[0] + cx;
                    let blk = &mut ar[ip * noff * nc2..(ip + 1) * noff * nc2];
                    let mut acc = vec![0f64; noff * nc2];
                    let diag_o = box_index(cdims, range, [0, 0, 0]);
                    for fz in 2 * cz..(2 * cz + 2).min(fdims[2]) {
                        for fy in 2 * cy..(2 * cy + 2).min(fdims[1]) {
                            for fx in 2 * cx..(2 * cx + 2).min(fdims[0]) {
                                let i = l.pidx(fx, fy, fz);
                                if lat.region[i] == 0 {
                                    continue;
                                }
                                for o in &l.offsets {
                                    let j = (i as isize + o.d) as usize;
                                    let k = bond_k_pub(lat, i, j);
                                    if k == 0.0 {
                                        continue;
                                    }
                                    let gk = k as f64 / (o.len as f64).powi(3);
                                    let fj = [fx, fy, fz].map(|c| c as isize);
                                    let jc = [0, 1, 2].map(|q| fj[q] + o.xi[q] as isize);
                                    let v = [0, 1, 2]
                                        .map(|q| jc[q].div_euclid(2) - [cx, cy, cz][q] as isize);
                                    let oj = box_index(cdims, range, v);
                                    for p in 0..nc {
                                        if !free(i, p) {
                                            continue;
                                        }
                                        for q in 0..nc {
                                            let bpq = gk * o.xi[p] as f64 * o.xi[q] as f64;
                                            if free(i, q) {
                                                acc[diag_o * nc2 + p * nc + q] += bpq;
                                            }
                                            if free(j, q) {
                                                acc[oj * nc2 + p * nc + q] -= bpq;
                                            }
                                        }
                                    }
                                }
                            }
                        }
                    }
                    for (b, v) in blk.iter_mut().zip(acc) {
                        *b = v as f32;
                    }
                }
            });
        mg.push_level(g, range, offsets, a);

        // Further levels from the assembled stencils.
        while mg.levels.last().unwrap().g.dims.iter().product::<usize>() * nc > DENSE_DOFS {
            let f = mg.levels.last().unwrap();
            let fd = f.g.dims;
            if fd.iter().all(|&d| d <= 1) {
                break;
            }
            let cd = fd.map(|d| d.div_ceil(2));
            let range = f.range.div_ceil(2);
            let g = Geom::new(cd, range);
            let (offsets, _) = box_offsets(&g, range);
            let (_, fvecs) = box_offsets(&f.g, f.range);
            let noff = offsets.len();
            let fnoff = f.noff();
            let mut a = vec![0f32; g.len() * noff * nc2];
            let px = g.pdims[0];
            a.par_chunks_mut(px * noff * nc2)
                .enumerate()
                .for_each(|(row, ar)| {
                    let Some((cy, cz)) = g.row_yz(row) else {
                        return;
                    };
                    for cx in 0..cd[0] {
                        let ip = g.pad[0] + cx;
                        let blk = &mut ar[ip * noff * nc2..(ip + 1) * noff * nc2];
                        let mut acc = vec![0f64; noff * nc2];
                        for fz in 2 * cz..(2 * cz + 2).min(fd[2]) {
                            for fy in 2 * cy..(2 * cy + 2).min(fd[1]) {
                                for fx in 2 * cx..(2 * cx + 2).min(fd[0]) {
                                    let i = f.g.pidx([fx, fy, fz]);
                                    let fb = &f.a[i * fnoff * nc2..(i + 1) * fnoff * nc2];
                                    for (o, v) in fvecs.iter().enumerate() {
                                        let b = &fb[o * nc2..(o + 1) * nc2];
                                        if b.iter().all(|&x| x == 0.0) {
                                            continue;
                                        }
                                        let jc = [fx, fy, fz].map(|c| c as isize);
                                        let jc = [0, 1, 2].map(|q| jc[q] + v[q]);
                                        let w = [0, 1, 2].map(|q| {
                                            jc[q].div_euclid(2) - [cx, cy, cz][q] as isize
                                        });
                                        let oj = box_index(cd, range, w);
                                        for (t, &x) in b.iter().enumerate() {
                                            acc[oj * nc2 + t] += x as f64;
                                        }
                                    }
                                }
                            }
                        }
                        for (b, v) in blk.iter_mut().zip(acc) {
                            *b = v as f32;
                        }
                    }
                });
            mg.push_level(g, range, offsets, a);
        }
        mg.factor_dense();
        mg
    }

    /// Number of grids including the fine one.
    pub fn depth(&self) -> usize {
        self.levels.len() + 1
    }

    fn push_level(&mut self, g: Geom, range: usize, offsets: Vec<isize>, a: Vec<f32>) {
        let nc = self.nc;
        let nc2 = nc * nc;
        let noff = offsets.len();
        let dims = g.dims;
        let diag_o = box_index(dims, range, [0, 0, 0]);
        let dinv: Vec<f32> = (0..g.len())
            .into_par_iter()
            .flat_map_iter(|i| {
                let b = &a[(i * noff + diag_o) * nc2..(i * noff + diag_o + 1) * nc2];
                let m: Vec<f64> = b.iter().map(|&x| x as f64).collect();
                block_inverse(&m, nc)
            })
            .collect();
        let mut lev = Level {
            g,
            range,
            offsets,
            a,
            dinv,
            omega: 1.0,
        };
        // Power iteration for lambda_max(D^-1 A).
        let n = lev.g.len() * nc;
        let mut v: Vec<f32> = (0..n).map(hash_unit).collect();
        let mut t = vec![0f32; n];
        let mut lam = 1.0;
        for _ in 0..POWER_ITERATIONS {
            let nv = norm(&v);
            if nv == 0.0 {
                break;
            }
            lev.apply(nc, &v, &mut t);
            v.fill(0.0);
            let w = lev.omega;
            lev.omega = 1.0;
            lev.jacobi(nc, &t, &mut v);
            lev.omega = w;
            lam = norm(&v) / nv;
        }
        lev.omega = (OMEGA_SCALE / lam.max(1e-12)) as f32;
        self.levels.push(lev);
    }

    fn factor_dense(&mut self) {
        let nc = self.nc;
        let lev = self.levels.last().unwrap();
        let noff = lev.noff();
        let nc2 = nc * nc;
        let (_, vecs) = box_offsets(&lev.g, lev.range);
        let diag_o = box_index(lev.g.dims, lev.range, [0, 0, 0]);
        let mut dofs = Vec::new();
        for i in 0..lev.g.len() {
            for a in 0..nc {
                if lev.a[(i * noff + diag_o) * nc2 + a * nc + a] > 0.0 {
                    dofs.push(i * nc + a);
                }
            }
        }
        let m = dofs.len();
        let pos: std::collections::HashMap<usize, usize> =
            dofs.iter().enumerate().map(|(k, &d)| (d, k)).collect();
        let mut k = vec![0f64; m * m];
        let d = lev.g.dims;
        let _ = d;
        for (r, &dof) in dofs.iter().enumerate() {
            let (i, a) = (dof / nc, dof % nc);
            for (o, _) in vecs.iter().enumerate() {
                let j = (i as isize + lev.offsets[o]) as usize;
                for b in 0..nc {
                    if let Some(&c) = pos.get(&(j * nc + b)) {
                        k[r * m + c] += lev.a[(i * noff + o) * nc2 + a * nc + b] as f64;
                    }
                }
            }
        }
        // Symmetrise (f32 round-off of the two Galerkin sums).
        for r in 0..m {
            for c in 0..r {
                let s = 0.5 * (k[r * m + c] + k[c * m + r]);
                k[r * m + c] = s;
                k[c * m + r] = s;
            }
        }
        let mut dead = vec![false; m];
        for j in 0..m {
            let mut s = k[j * m + j];
            for p in 0..j {
                s -= k[j * m + p] * k[j * m + p];
            }
            let d0 = k[j * m + j].abs();
            if s <= 1e-10 * d0 || s <= 0.0 {
                dead[j] = true;
                for r in j..m {
                    k[r * m + j] = 0.0;
                }
                continue;
            }
            let sq = s.sqrt();
            k[j * m + j] = sq;
            for r in j + 1..m {
                let mut t = k[r * m + j];
                for p in 0..j {
                    t -= k[r * m + p] * k[j * m + p];
                }
                k[r * m + j] = t / sq;
            }
        }
        self.dense = Dense { dofs, l: k, dead };
    }

    fn dense_solve(&self, r: &[f32], x: &mut [f32]) {
        let d = &self.dense;
        let m = d.dofs.len();
        let mut y: Vec<f64> = d.dofs.iter().map(|&k| r[k] as f64).collect();
        for j in 0..m {
            if d.dead[j] {
                y[j] = 0.0;
                continue;
            }
            let row = &d.l[j * m..j * m + j];
            let s = y[j] - row.iter().zip(&y[..j]).map(|(l, y)| l * y).sum::<f64>();
            y[j] = s / d.l[j * m + j];
        }
        for j in (0..m).rev() {
            if d.dead[j] {
                y[j] = 0.0;
                continue;
            }
            let mut s = y[j];
            for (p, yp) in y.iter().enumerate().skip(j + 1) {
                s -= d.l[p * m + j] * yp;
            }
            y[j] = s / d.l[j * m + j];
        }
        x.fill(0.0);
        for (k, &dof) in d.dofs.iter().enumerate() {
            x[dof] = y[k] as f32;
        }
    }

    /// y = K x on the free DOFs of the fine lattice (zero elsewhere).
    fn fine_apply(&self, lat: &Lattice, x: &Vec3, y: &mut Vec3) {
        lat.forces(x, crate::lattice::ForceLaw::Linear, y, None, false);
        for (a, c) in y.c.iter_mut().enumerate() {
            c.par_iter_mut().enumerate().for_each(|(i, v)| {
                *v = if lat.region[i] != 0 && lat.fixed[i] & (1 << a) == 0 {
                    -*v
                } else {
                    0.0
                };
            });
        }
    }

    /// x += omega D^-1 t on the fine lattice (per node the nc x nc block).
    fn fine_jacobi(&self, t: &Vec3, x: &mut Vec3, omega: f32) {
        let nc = self.nc;
        let d = &self.fine_dinv;
        if nc == 2 {
            let (x0, x1) = x.c.split_at_mut(1);
            x0[0]
                .par_iter_mut()
                .zip(x1[0].par_iter_mut())
                .zip(t.c[0].par_iter().zip(t.c[1].par_iter()))
                .zip(d.par_chunks(4))
                .for_each(|(((x0, x1), (&t0, &t1)), d)| {
                    *x0 += omega * (d[0] * t0 + d[1] * t1);
                    *x1 += omega * (d[2] * t0 + d[3] * t1);
                });
        } else {
            let (x0, rest) = x.c.split_at_mut(1);
            let (x1, x2) = rest.split_at_mut(1);
            x0[0]
                .par_iter_mut()
                .zip(x1[0].par_iter_mut())
                .zip(x2[0].par_iter_mut())
                .zip(
                    t.c[0]
                        .par_iter()
                        .zip(t.c[1].par_iter())
                        .zip(t.c[2].par_iter()),
                )
                .zip(d.par_chunks(9))
                .for_each(|((((x0, x1), x2), ((&t0, &t1), &t2)), d)| {
                    *x0 += omega * (d[0] * t0 + d[1] * t1 + d[2] * t2);
                    *x1 += omega * (d[3] * t0 + d[4] * t1 + d[5] * t2);
                    *x2 += omega * (d[6] * t0 + d[7] * t1 + d[8] * t2);
                });
        }
    }

    fn fine_lambda(&self, lat: &Lattice) -> f64 {
        let l = &lat.layout;
        let mut v: Vec3 = Vec3::zeros(l);
        for (a, c) in v.c.iter_mut().enumerate() {
            for (i, x) in c.iter_mut().enumerate() {
                *x = hash_unit(i * 3 + a);
            }
        }
        let mut t = Vec3::zeros(l);
        let mut lam = 1.0;
        for _ in 0..FINE_POWER_ITERATIONS {
            let nv: f64 = v.c.iter().map(|c| norm(c).powi(2)).sum::<f64>().sqrt();
            if nv == 0.0 {
                break;
            }
            self.fine_apply(lat, &v, &mut t);
            for c in v.c.iter_mut() {
                c.par_iter_mut().for_each(|x| *x = 0.0);
            }
            self.fine_jacobi(&t, &mut v, 1.0);
            lam = v.c.iter().map(|c| norm(c).powi(2)).sum::<f64>().sqrt() / nv;
        }
        lam.max(1e-12)
    }

    /// One V-cycle on assembled level `k` (index into `levels`): x = M_k r.
    fn vcycle(&self, k: usize, r: &[f32], x: &mut [f32]) {
        let nc = self.nc;
        if k + 1 == self.levels.len() {
            self.dense_solve(r, x);
            return;
        }
        let lev = &self.levels[k];
        let next = &self.levels[k + 1];
        let mut t = vec![0f32; r.len()];
        x.fill(0.0);
        let sweeps = self.opt.coarse_sweeps.max(1);
        lev.jacobi(nc, r, x);
        for _ in 1..sweeps {
            self.residual(lev, r, x, &mut t);
            lev.jacobi(nc, &t, x);
        }
        self.residual(lev, r, x, &mut t);
        // Restrict: sum over the 2 x 2 (x 2) block.
        let mut rc = vec![0f32; next.g.len() * nc];
        let mut xc = vec![0f32; rc.len()];
        self.restrict(lev, next, &t, &mut rc);
        self.coarse_solve(k + 1, &rc, &mut xc);
        self.prolong(lev, next, &xc, x);
        for _ in 0..sweeps {
            self.residual(lev, r, x, &mut t);
            lev.jacobi(nc, &t, x);
        }
    }

    /// Approximate solve on assembled level k: `cycle` cycles, each on the residual left by
    /// the previous ones (x1 = M r, x2 = x1 + M (r - A x1): symmetric, 2M - MAM).
    fn coarse_solve(&self, k: usize, r: &[f32], x: &mut [f32]) {
        self.vcycle(k, r, x);
        if k + 1 == self.levels.len() {
            return;
        }
        let lev = &self.levels[k];
        let mut t = vec![0f32; r.len()];
        let mut dx = vec![0f32; r.len()];
        for _ in 1..self.opt.cycle.max(1) {
            self.residual(lev, r, x, &mut t);
            self.vcycle(k, &t, &mut dx);
            x.par_iter_mut()
                .zip(dx.par_iter())
                .for_each(|(x, &d)| *x += d);
        }
    }

    fn residual(&self, lev: &Level, r: &[f32], x: &[f32], t: &mut [f32]) {
        lev.apply(self.nc, x, t);
        t.par_iter_mut()
            .zip(r.par_iter())
            .for_each(|(t, &r)| *t = r - *t);
    }

    fn restrict(&self, f: &Level, c: &Level, t: &[f32], rc: &mut [f32]) {
        let nc = self.nc;
        let fd = f.g.dims;
        let px = c.g.pdims[0];
        rc.par_chunks_mut(px * nc)
            .enumerate()
            .for_each(|(row, rr)| {
                let Some((cy, cz)) = c.g.row_yz(row) else {
                    return;
                };
                for cx in 0..c.g.dims[0] {
                    let o = &mut rr[(c.g.pad[0] + cx) * nc..(c.g.pad[0] + cx + 1) * nc];
                    for fz in 2 * cz..(2 * cz + 2).min(fd[2]) {
                        for fy in 2 * cy..(2 * cy + 2).min(fd[1]) {
                            for fx in 2 * cx..(2 * cx + 2).min(fd[0]) {
                                let i = f.g.pidx([fx, fy, fz]);
                                for a in 0..nc {
                                    o[a] += t[i * nc + a];
                                }
                            }
                        }
                    }
                }
            });
    }

    fn prolong(&self, f: &Level, c: &Level, xc: &[f32], x: &mut [f32]) {
        let nc = self.nc;
        let px = f.g.pdims[0];
        let alpha = self.opt.overcorrection;
        x.par_chunks_mut(px * nc).enumerate().for_each(|(row, xr)| {
            let Some((fy, fz)) = f.g.row_yz(row) else {
                return;
            };
            for fx in 0..f.g.dims[0] {
                let i = f.g.pad[0] + fx;
                let ic = c.g.pidx([fx / 2, fy / 2, fz / 2]);
                let dg = &f.dinv[(row * px + i) * nc * nc..];
                for a in 0..nc {
                    // Inactive DOFs (zero diagonal) stay zero.
                    if dg[a * nc + a] != 0.0 {
                        xr[i * nc + a] += alpha * xc[ic * nc + a];
                    }
                }
            }
        });
    }

    /// z = M r on the fine lattice (r zero on prescribed DOFs).
    pub fn apply(&self, lat: &Lattice, r: &Vec3, z: &mut Vec3) {
        let l = &lat.layout;
        let nc = self.nc;
        let w = self.fine_omega;
        for c in z.c.iter_mut() {
            c.par_iter_mut().for_each(|x| *x = 0.0);
        }
        let mut t = Vec3::zeros(l);
        let sweeps = self.opt.fine_sweeps.max(1);
        self.fine_jacobi(r, z, w);
        let fine_res = |z: &Vec3, t: &mut Vec3| {
            self.fine_apply(lat, z, t);
            for (tc, rc) in t.c.iter_mut().zip(r.c.iter()) {
                tc.par_iter_mut()
                    .zip(rc.par_iter())
                    .for_each(|(t, &r)| *t = r - *t);
            }
        };
        for _ in 1..sweeps {
            fine_res(z, &mut t);
            self.fine_jacobi(&t, z, w);
        }
        fine_res(z, &mut t);
        // Restrict to level 1 (masked: t is zero on prescribed DOFs already).
        let c = &self.levels[0];
        let fd = l.dims;
        let mut rc = vec![0f32; c.g.len() * nc];
        let px = c.g.pdims[0];
        rc.par_chunks_mut(px * nc)
            .enumerate()
            .for_each(|(row, rr)| {
                let Some((cy, cz)) = c.g.row_yz(row) else {
                    return;
                };
                for cx in 0..c.g.dims[0] {
                    let o = &mut rr[(c.g.pad[0] + cx) * nc..(c.g.pad[0] + cx + 1) * nc];
                    for fz in 2 * cz..(2 * cz + 2).min(fd[2]) {
                        for fy in 2 * cy..(2 * cy + 2).min(fd[1]) {
                            for fx in 2 * cx..(2 * cx + 2).min(fd[0]) {
                                let i = l.pidx(fx, fy, fz);
                                for (o, tc) in o.iter_mut().zip(&t.c) {
                                    *o += tc[i];
                                }
                            }
                        }
                    }
                }
            });
        let mut xc = vec![0f32; rc.len()];
        self.coarse_solve(0, &rc, &mut xc);
        let alpha = self.opt.overcorrection;
        let px = l.pdims[0];
        for (a, zc) in z.c.iter_mut().enumerate() {
            zc.par_chunks_mut(px).enumerate().for_each(|(row, zr)| {
                let Some(start) = l.row_start_pub(row) else {
                    return;
                };
                let py = row % l.pdims[1];
                let pz = row / l.pdims[1];
                let (fy, fz) = (py - l.pad[1], pz - l.pad[2]);
                for fx in 0..fd[0] {
                    let i = start + fx;
                    if lat.region[i] == 0 || lat.fixed[i] & (1 << a) != 0 {
                        continue;
                    }
                    let ic = c.g.pidx([fx / 2, fy / 2, fz / 2]);
                    zr[l.pad[0] + fx] += alpha * xc[ic * nc + a];
                }
            });
        }
        for _ in 0..sweeps {
            fine_res(z, &mut t);
            self.fine_jacobi(&t, z, w);
        }
    }
}
