//! Geometric multigrid for one velocity component's Laplacian block (7-point, variable
//! coefficients, walls folded into the diagonal), used as a fixed symmetric positive definite
//! preconditioner inside MINRES.
//!
//! Coarsening aggregates 2x2x2 blocks of the component's (periodic) index grid; the coarse
//! operator is the Galerkin product P^T A P with piecewise-constant P restricted to active
//! unknowns, which is again a 7-point stencil. This needs no coarse geometry, so thin pore
//! throats that a re-voxelized coarse image would close keep their coupling. The smoother is
//! red-black Gauss-Seidel, forward before and backward after the coarse correction, so that
//! the V-cycle is symmetric (MINRES needs a symmetric preconditioner).

use crate::mac::{active_bit, DiagValue, Dims, FLUID};
use rayon::prelude::*;

/// A 7-point symmetric operator on a periodic grid.
pub trait Op7: Sync {
    fn dims(&self) -> Dims;
    fn active(&self, i: usize) -> bool;
    fn diag(&self, i: usize, nb: &[usize; 6]) -> f32;
    /// Coupling weight w >= 0 between active i and j = i + e_b (A_ij = -w); 0 if j is inactive.
    fn link(&self, i: usize, j: usize, b: usize) -> f32;
    /// `(sum_j w_ij x_j, A_ii)` at the active point `i`, with `x_j = read(j)`: the two halves
    /// of a Gauss-Seidel update or a residual, in one pass over the neighbours so that an
    /// operator can share its coefficient lookups between them. `x` is zero at inactive points
    /// (every level's iterate is written at active points only), which an operator may use.
    #[inline]
    fn row_parts<R: Fn(usize) -> f32>(&self, read: R, i: usize, nb: &[usize; 6]) -> (f32, f32) {
        let d = self.dims();
        let mut s = 0.0;
        for b in 0..3 {
            if d.n[b] == 1 {
                continue;
            }
            let (jm, jp) = (nb[2 * b], nb[2 * b + 1]);
            s += self.link(i, jp, b) * read(jp) + self.link(jm, i, b) * read(jm);
        }
        (s, self.diag(i, nb))
    }
    /// The Gauss-Seidel value `(r + sum_j w_ij x_j) / A_ii` at the active point `i`.
    #[inline]
    fn relax<R: Fn(usize) -> f32>(&self, read: R, r: f32, i: usize, nb: &[usize; 6]) -> f32 {
        let (s, d) = self.row_parts(read, i, nb);
        (r + s) / d
    }
    /// `r / A_ii` at the active point `i`.
    #[inline]
    fn solve_diag(&self, r: f32, i: usize, nb: &[usize; 6]) -> f32 {
        r / self.diag(i, nb)
    }
}

/// `1 / d` for the whole-number fine diagonals `d = 0..=12` of [`crate::mac::diagonals`]: a
/// multiplication in place of the division that otherwise limits the fine sweeps.
pub(crate) const INV_DIAG: [f32; 13] = [
    0.0,
    1.0,
    1.0 / 2.0,
    1.0 / 3.0,
    1.0 / 4.0,
    1.0 / 5.0,
    1.0 / 6.0,
    1.0 / 7.0,
    1.0 / 8.0,
    1.0 / 9.0,
    1.0 / 10.0,
    1.0 / 11.0,
    1.0 / 12.0,
];

/// The finest level: the wall rule of [`crate::mac`] evaluated from the mask, nothing stored.
pub struct FineOp<'a, D: DiagValue = u8> {
    pub dims: Dims,
    pub mask: &'a [u8],
    /// This component's block of [`crate::mac::diagonals`] (or of
    /// [`crate::mac::composite_diagonals`]).
    pub diag: &'a [D],
    pub axis: usize,
}

impl<D: DiagValue> Op7 for FineOp<'_, D> {
    fn dims(&self) -> Dims {
        self.dims
    }
    #[inline]
    fn active(&self, i: usize) -> bool {
        self.mask[i] & active_bit(self.axis) != 0
    }
    #[inline]
    fn diag(&self, i: usize, _nb: &[usize; 6]) -> f32 {
        self.diag[i].value()
    }
    #[inline]
    fn link(&self, i: usize, j: usize, _b: usize) -> f32 {
        let bit = active_bit(self.axis);
        if self.mask[i] & self.mask[j] & bit != 0 {
            1.0
        } else {
            0.0
        }
    }
    /// Unit links, and `x` is zero at inactive faces: the off-diagonal sum is the plain sum of
    /// the six neighbours, without their six mask tests (the same value: `1 * x_j + 0` is
    /// exact). This is the innermost loop of the whole solve.
    #[inline]
    fn row_parts<R: Fn(usize) -> f32>(&self, read: R, i: usize, nb: &[usize; 6]) -> (f32, f32) {
        let n = self.dims.n;
        let mut s = 0.0;
        for b in 0..3 {
            if n[b] == 1 {
                continue;
            }
            s += read(nb[2 * b + 1]) + read(nb[2 * b]);
        }
        (s, self.diag[i].value())
    }
    #[inline]
    fn relax<R: Fn(usize) -> f32>(&self, read: R, r: f32, i: usize, nb: &[usize; 6]) -> f32 {
        let (s, _) = self.row_parts(read, i, nb);
        self.diag[i].divide(r + s)
    }
    #[inline]
    fn solve_diag(&self, r: f32, i: usize, _nb: &[usize; 6]) -> f32 {
        self.diag[i].divide(r)
    }
}

/// A coarse level: stored stencil and the level's solution and right-hand side.
pub struct Coarse {
    pub dims: Dims,
    pub diag: Vec<f32>,
    /// Weight of the link from i to i + e_b.
    pub link: [Vec<f32>; 3],
    pub x: Vec<f32>,
    pub b: Vec<f32>,
}

impl Op7 for Coarse {
    fn dims(&self) -> Dims {
        self.dims
    }
    #[inline]
    fn active(&self, i: usize) -> bool {
        self.diag[i] > 0.0
    }
    #[inline]
    fn diag(&self, i: usize, _nb: &[usize; 6]) -> f32 {
        self.diag[i]
    }
    #[inline]
    fn link(&self, i: usize, _j: usize, b: usize) -> f32 {
        self.link[b][i]
    }
}

fn coarse_dims(d: Dims) -> Dims {
    Dims::new(d.n.map(|n| n.div_ceil(2)))
}

#[inline]
fn parent(fine: [usize; 3], c: Dims) -> usize {
    c.index(fine[0] / 2, fine[1] / 2, fine[2] / 2)
}

/// Galerkin coarse operator P^T A P with P = 1 on the active fine unknowns of each 2x2x2 block.
fn galerkin<O: Op7>(op: &O) -> Coarse {
    let f = op.dims();
    let c = coarse_dims(f);
    let slab = c.slab();
    let mut diag = vec![0f32; c.len()];
    let mut lx = vec![0f32; c.len()];
    let mut ly = vec![0f32; c.len()];
    let mut lz = vec![0f32; c.len()];
    diag.par_chunks_mut(slab)
        .zip(lx.par_chunks_mut(slab))
        .zip(ly.par_chunks_mut(slab))
        .zip(lz.par_chunks_mut(slab))
        .enumerate()
        .for_each(|(cz, (((d, ax), ay), az))| {
            for cy in 0..c.n[1] {
                for cx in 0..c.n[0] {
                    let ci = c.index(cx, cy, cz);
                    let l = ci - cz * slab;
                    let mut dd = 0.0f64;
                    let mut links = [0.0f64; 3];
                    let mut any = false;
                    for fz in 2 * cz..(2 * cz + 2).min(f.n[2]) {
                        for fy in 2 * cy..(2 * cy + 2).min(f.n[1]) {
                            for fx in 2 * cx..(2 * cx + 2).min(f.n[0]) {
                                let i = f.index(fx, fy, fz);
                                if !op.active(i) {
                                    continue;
                                }
                                any = true;
                                let nb = f.neighbours(fx, fy, fz);
                                dd += op.diag(i, &nb) as f64;
                                for b in 0..3 {
                                    if f.n[b] == 1 {
                                        continue;
                                    }
                                    let j = nb[2 * b + 1];
                                    let w = op.link(i, j, b) as f64;
                                    if w == 0.0 {
                                        continue;
                                    }
                                    if parent(f.coords(j), c) == ci {
                                        dd -= 2.0 * w;
                                    } else {
                                        links[b] += w;
                                    }
                                }
                            }
                        }
                    }
                    if any {
                        // Positive for a full-rank P; the floor guards round-off only.
                        d[l] = (dd as f32).max(f32::MIN_POSITIVE);
                        ax[l] = links[0] as f32;
                        ay[l] = links[1] as f32;
                        az[l] = links[2] as f32;
                    }
                }
            }
        });
    let n = c.len();
    Coarse {
        dims: c,
        diag,
        link: [lx, ly, lz],
        x: vec![0.0; n],
        b: vec![0.0; n],
    }
}

/// (A x)_i at an active point (`x` zero at inactive points, see [`Op7::row_parts`]).
#[inline]
fn apply_at<O: Op7>(op: &O, x: &[f32], i: usize, nb: &[usize; 6]) -> f32 {
    let (s, d) = op.row_parts(|j| x[j], i, nb);
    d * x[i] - s
}

/// Points per parallel task at least: below this, coarse levels run on one thread, where
/// scheduling cost more than the work (per-point updates are independent within a phase, so
/// the split changes no result).
const MIN_POINTS: usize = 1 << 15;

/// z-slabs per parallel task so that a task holds at least [`MIN_POINTS`] points.
#[inline]
fn min_slabs(d: Dims) -> usize {
    MIN_POINTS.div_ceil(d.slab().max(1))
}

/// A slice written from several threads at indices that no other thread reads or writes in
/// the same phase (one colour of a red-black sweep).
struct Shared(*mut f32, usize);
unsafe impl Sync for Shared {}
impl Shared {
    /// # Safety
    /// Callers write index `i` from one thread only, and no thread reads it in that phase.
    #[inline]
    unsafe fn write(&self, i: usize, v: f32) {
        debug_assert!(i < self.1);
        *self.0.add(i) = v;
    }
    #[inline]
    unsafe fn read(&self, i: usize) -> f32 {
        debug_assert!(i < self.1);
        *self.0.add(i)
    }
}

/// The seam: points on the last layer of an axis with an odd number (> 1) of layers, where
/// the periodic neighbour has the same red-black colour; they are updated after the parallel
/// phase, sequentially in a fixed order. Returns those of one colour in index order, plane by
/// plane.
fn seam_points(d: Dims, colour: usize) -> Vec<[usize; 3]> {
    let odd = |a: usize| d.n[a] > 1 && d.n[a] % 2 == 1;
    let mut pts = Vec::new();
    for z in 0..d.n[2] {
        for y in 0..d.n[1] {
            let whole = (odd(2) && z == d.n[2] - 1) || (odd(1) && y == d.n[1] - 1);
            if whole {
                for x in 0..d.n[0] {
                    if (x + y + z) % 2 == colour {
                        pts.push([x, y, z]);
                    }
                }
            } else if odd(0) && (d.n[0] - 1 + y + z) % 2 == colour {
                pts.push([d.n[0] - 1, y, z]);
            }
        }
    }
    pts
}

/// One colour of Gauss-Seidel: parallel over interior points, then the seam in order
/// (`reverse` runs the seam backwards, so a backward sweep is the adjoint of a forward one).
fn gs_colour<O: Op7>(op: &O, x: &mut [f32], rhs: &[f32], colour: usize, seam_first: bool) {
    let d = op.dims();
    // `update(i, nb)` relaxes the active point `i` with neighbours `nb` (-x, +x, -y, +y, -z, +z).
    let update = |xs: &Shared, i: usize, nb: &[usize; 6]| {
        // SAFETY: neighbours have the other colour or sit on the seam, which is not written
        // in the parallel phase; the seam phase is sequential.
        let v = op.relax(|j| unsafe { xs.read(j) }, rhs[i], i, nb);
        unsafe { xs.write(i, v) };
    };
    let xs = Shared(x.as_mut_ptr(), x.len());
    let seam = |xs: &Shared| {
        let mut pts = seam_points(d, colour);
        if seam_first {
            pts.reverse();
        }
        for p in pts {
            let i = d.index(p[0], p[1], p[2]);
            if op.active(i) {
                update(xs, i, &d.neighbours(p[0], p[1], p[2]));
            }
        }
    };
    let odd = |a: usize| d.n[a] > 1 && d.n[a] % 2 == 1;
    let any_seam = (0..3).any(odd);
    if seam_first && any_seam {
        seam(&xs);
    }
    let [nx, ny, nz] = d.n;
    // Seam rows (last y or z layer of an odd axis) and the last x of an odd x axis are left to
    // the sequential seam phase (see `seam_points`); the neighbour indices are formed per row
    // (the same values as `Dims::neighbours`, without its per-point wrap tests).
    let x_end = if odd(0) { nx - 1 } else { nx };
    (0..nz)
        .into_par_iter()
        .with_min_len(min_slabs(d))
        .for_each(|z| {
            let zm = if z == 0 { nz - 1 } else { z - 1 };
            let zp = if z + 1 == nz { 0 } else { z + 1 };
            for y in 0..ny {
                if (odd(2) && z == nz - 1) || (odd(1) && y == ny - 1) {
                    continue;
                }
                let ym = if y == 0 { ny - 1 } else { y - 1 };
                let yp = if y + 1 == ny { 0 } else { y + 1 };
                let row = d.index(0, y, z);
                let (rym, ryp) = (d.index(0, ym, z), d.index(0, yp, z));
                let (rzm, rzp) = (d.index(0, y, zm), d.index(0, y, zp));
                let start = (colour + y + z) % 2;
                for xx in (start..x_end).step_by(2) {
                    let i = row + xx;
                    if !op.active(i) {
                        continue;
                    }
                    let xm = if xx == 0 { nx - 1 } else { xx - 1 };
                    let xp = if xx + 1 == nx { 0 } else { xx + 1 };
                    let nb = [row + xm, row + xp, rym + xx, ryp + xx, rzm + xx, rzp + xx];
                    update(&xs, i, &nb);
                }
            }
        });
    if !seam_first && any_seam {
        seam(&xs);
    }
}

/// Whether red-black colouring is consistent across the periodic wrap (no axis with an odd
/// number > 1 of layers), so that a colour's neighbours all have the other colour.
#[inline]
fn no_seam(d: Dims) -> bool {
    (0..3).all(|a| d.n[a] == 1 || d.n[a] % 2 == 0)
}

/// x <- 0 followed by the first colour-0 half-sweep, in one pass: from x = 0 the colour-0
/// update reads only zeros, so it is x_i = rhs_i / A_ii (colour 1 stays 0). Saves the zeroing
/// pass and the neighbour reads of the first half-sweep; the values are those of the
/// two-pass form (seam points, whose same-colour neighbours are updated first, go through the
/// sequential seam phase as before).
fn first_half_sweep<O: Op7>(op: &O, x: &mut [f32], rhs: &[f32]) {
    let d = op.dims();
    let [nx, ny, nz] = d.n;
    let odd = |a: usize| d.n[a] > 1 && d.n[a] % 2 == 1;
    let slab = d.slab();
    x.par_chunks_mut(slab)
        .with_min_len(min_slabs(d))
        .enumerate()
        .for_each(|(z, xs)| {
            let zm = if z == 0 { nz - 1 } else { z - 1 };
            let zp = if z + 1 == nz { 0 } else { z + 1 };
            for y in 0..ny {
                let ym = if y == 0 { ny - 1 } else { y - 1 };
                let yp = if y + 1 == ny { 0 } else { y + 1 };
                let row = d.index(0, y, z);
                let (rym, ryp) = (d.index(0, ym, z), d.index(0, yp, z));
                let (rzm, rzp) = (d.index(0, y, zm), d.index(0, y, zp));
                let seam_row = (odd(2) && z == nz - 1) || (odd(1) && y == ny - 1);
                let out = &mut xs[y * nx..(y + 1) * nx];
                out.iter_mut().for_each(|v| *v = 0.0);
                if seam_row {
                    continue;
                }
                let x_end = if odd(0) { nx - 1 } else { nx };
                for xx in ((y + z) % 2..x_end).step_by(2) {
                    let i = row + xx;
                    if !op.active(i) {
                        continue;
                    }
                    let xm = if xx == 0 { nx - 1 } else { xx - 1 };
                    let xp = if xx + 1 == nx { 0 } else { xx + 1 };
                    let nb = [row + xm, row + xp, rym + xx, ryp + xx, rzm + xx, rzp + xx];
                    out[xx] = op.solve_diag(rhs[i], i, &nb);
                }
            }
        });
    if !no_seam(d) {
        // Seam points of colour 0 in their sequential order, as `gs_colour` does.
        let xs = Shared(x.as_mut_ptr(), x.len());
        for p in seam_points(d, 0) {
            let i = d.index(p[0], p[1], p[2]);
            if op.active(i) {
                let nb = d.neighbours(p[0], p[1], p[2]);
                // SAFETY: sequential phase.
                let v = op.relax(|j| unsafe { xs.read(j) }, rhs[i], i, &nb);
                unsafe { xs.write(i, v) };
            }
        }
    }
}

/// Forward smoothing from x = 0 (the start of every V-cycle level).
fn smooth_forward_from_zero<O: Op7>(op: &O, x: &mut [f32], rhs: &[f32], sweeps: usize) {
    if sweeps == 0 {
        x.par_iter_mut()
            .with_min_len(MIN_POINTS)
            .for_each(|v| *v = 0.0);
        return;
    }
    first_half_sweep(op, x, rhs);
    gs_colour(op, x, rhs, 1, false);
    smooth_forward(op, x, rhs, sweeps - 1);
}

fn smooth_forward<O: Op7>(op: &O, x: &mut [f32], rhs: &[f32], sweeps: usize) {
    for _ in 0..sweeps {
        gs_colour(op, x, rhs, 0, false);
        gs_colour(op, x, rhs, 1, false);
    }
}

fn smooth_backward<O: Op7>(op: &O, x: &mut [f32], rhs: &[f32], sweeps: usize) {
    for _ in 0..sweeps {
        gs_colour(op, x, rhs, 1, true);
        gs_colour(op, x, rhs, 0, true);
    }
}

/// b_c = P^T (rhs - A x), the residual summed over each block's active points.
/// `colour0_only`: right after a forward red-black sweep (its last half-sweep colour 1, no
/// seam) the residual at colour-1 points is zero up to round-off (they were just relaxed and
/// their colour-0 neighbours have not moved since), so only colour-0 points are summed: half
/// the operator evaluations of the restriction.
fn restrict<O: Op7>(op: &O, x: &[f32], rhs: &[f32], coarse: &mut Coarse, colour0_only: bool) {
    let f = op.dims();
    let c = coarse.dims;
    let slab = c.slab();
    let [nx, ny, nz] = f.n;
    let step = if colour0_only { 2 } else { 1 };
    // Fine rows in order, each point adding to its parent's row accumulator: per parent the
    // children are summed in the order (z, y, x) as before (the same f64 sums), with the
    // neighbour indices formed per row. An inactive parent has no active children.
    coarse
        .b
        .par_chunks_mut(slab)
        .with_min_len(min_slabs(c))
        .enumerate()
        .for_each_init(
            || vec![0f64; c.n[0]],
            |acc, (cz, bs)| {
                for cy in 0..c.n[1] {
                    acc.iter_mut().for_each(|v| *v = 0.0);
                    for fz in 2 * cz..(2 * cz + 2).min(nz) {
                        let zm = if fz == 0 { nz - 1 } else { fz - 1 };
                        let zp = if fz + 1 == nz { 0 } else { fz + 1 };
                        for fy in 2 * cy..(2 * cy + 2).min(ny) {
                            let ym = if fy == 0 { ny - 1 } else { fy - 1 };
                            let yp = if fy + 1 == ny { 0 } else { fy + 1 };
                            let row = f.index(0, fy, fz);
                            let (rym, ryp) = (f.index(0, ym, fz), f.index(0, yp, fz));
                            let (rzm, rzp) = (f.index(0, fy, zm), f.index(0, fy, zp));
                            let start = if colour0_only { (fy + fz) % 2 } else { 0 };
                            for fx in (start..nx).step_by(step) {
                                let i = row + fx;
                                if !op.active(i) {
                                    continue;
                                }
                                let xm = if fx == 0 { nx - 1 } else { fx - 1 };
                                let xp = if fx + 1 == nx { 0 } else { fx + 1 };
                                let nb =
                                    [row + xm, row + xp, rym + fx, ryp + fx, rzm + fx, rzp + fx];
                                acc[fx / 2] += (rhs[i] - apply_at(op, x, i, &nb)) as f64;
                            }
                        }
                    }
                    let out = &mut bs[cy * c.n[0]..(cy + 1) * c.n[0]];
                    for (o, &a) in out.iter_mut().zip(acc.iter()) {
                        *o = a as f32;
                    }
                }
            },
        );
}

/// x += scale * P x_c on the active points. `colour0_only`: the backward sweep that follows
/// starts with colour 1, whose update does not read its own old value, so (without a seam)
/// the correction at colour-1 points would be overwritten unread: skipping it changes no value.
fn prolong<O: Op7>(op: &O, x: &mut [f32], xc: &[f32], c: Dims, scale: f32, colour0_only: bool) {
    let f = op.dims();
    let slab = f.slab();
    let step = if colour0_only { 2 } else { 1 };
    x.par_chunks_mut(slab)
        .with_min_len(min_slabs(f))
        .enumerate()
        .for_each(|(z, xs)| {
            for y in 0..f.n[1] {
                let start = if colour0_only { (y + z) % 2 } else { 0 };
                let row = f.index(0, y, z);
                let crow = c.index(0, y / 2, z / 2);
                for xx in (start..f.n[0]).step_by(step) {
                    let i = row + xx;
                    if op.active(i) {
                        xs[i - z * slab] += scale * xc[crow + xx / 2];
                    }
                }
            }
        });
}

/// Settings of the V-cycle.
#[derive(Clone, Copy, Debug)]
pub struct CycleSettings {
    /// Red-black Gauss-Seidel sweeps before and after the coarse correction.
    pub sweeps: usize,
    /// Scale of the coarse correction: piecewise-constant prolongation underestimates smooth
    /// errors, which a factor above 1 compensates (Braess 1995; Notay's AGMG).
    pub over_correction: f32,
    /// Symmetric Gauss-Seidel sweeps on the coarsest level.
    pub coarsest_sweeps: usize,
}

impl Default for CycleSettings {
    fn default() -> Self {
        CycleSettings {
            // 2 against 1: 38 vs 61 MINRES iterations at 96^3 (porosity 0.65) for about 1.55x
            // the cost per iteration: 5-13 % less CPU per solve, and fewer iterations means
            // fewer of the per-iteration reductions and fork-joins that limit two threads.
            sweeps: 2,
            // 1.8 against 1.5: 53 vs 58 and 64 vs 74 MINRES iterations on the random packings
            // of `examples/random_spheres` (64^3, porosity 0.65; 96^3, porosity 0.48). The
            // V-cycle stays SPD for any scale >= 0 (GS is an A-norm contraction and the coarse
            // correction is A-positive semidefinite), so only its quality depends on it.
            over_correction: 1.8,
            coarsest_sweeps: 20,
        }
    }
}

/// The hierarchy of one velocity component.
pub struct Hierarchy<'a, D: DiagValue = u8> {
    pub fine: FineOp<'a, D>,
    pub levels: Vec<Coarse>,
    pub settings: CycleSettings,
}

/// Stop coarsening at this many unknowns.
const COARSEST: usize = 64;

impl<'a, D: DiagValue> Hierarchy<'a, D> {
    pub fn new(
        dims: Dims,
        mask: &'a [u8],
        diag: &'a [D],
        axis: usize,
        settings: CycleSettings,
    ) -> Self {
        let n = dims.len();
        let fine = FineOp {
            dims,
            mask,
            diag: &diag[axis * n..(axis + 1) * n],
            axis,
        };
        let levels = build_levels(&fine);
        Hierarchy {
            fine,
            levels,
            settings,
        }
    }

    /// Bytes held by the coarse levels.
    pub fn bytes(&self) -> usize {
        self.levels.iter().map(|l| l.dims.len() * 24).sum()
    }

    /// z <- M^{-1} r by one symmetric V-cycle from z = 0.
    pub fn vcycle(&mut self, r: &[f32], z: &mut [f32]) {
        vcycle_op(&self.fine, &mut self.levels, self.settings, r, z);
    }

    /// out <- A x on the active faces (0 elsewhere), for `x` zero on the inactive faces.
    pub fn apply(&self, x: &[f32], out: &mut [f32]) {
        apply_op(&self.fine, x, out);
    }
}

/// The Galerkin levels below `fine`, down to [`COARSEST`] unknowns.
fn build_levels<O: Op7>(fine: &O) -> Vec<Coarse> {
    let mut levels: Vec<Coarse> = Vec::new();
    loop {
        let d = levels.last().map_or(fine.dims(), |l| l.dims);
        if d.len() <= COARSEST || coarse_dims(d) == d {
            break;
        }
        let next = match levels.last() {
            None => galerkin(fine),
            Some(l) => galerkin(l),
        };
        levels.push(next);
    }
    levels
}

/// out <- A x on the active points of `op` (0 elsewhere).
fn apply_op<O: Op7>(op: &O, x: &[f32], out: &mut [f32]) {
    let d = op.dims();
    let slab = d.slab();
    out.par_chunks_mut(slab).enumerate().for_each(|(z, o)| {
        for y in 0..d.n[1] {
            for xx in 0..d.n[0] {
                let i = d.index(xx, y, z);
                o[i - z * slab] = if op.active(i) {
                    apply_at(op, x, i, &d.neighbours(xx, y, z))
                } else {
                    0.0
                };
            }
        }
    });
}

/// z <- M^{-1} r by one symmetric V-cycle from z = 0 on `fine` and its Galerkin `levels`.
fn vcycle_op<O: Op7>(fine: &O, levels: &mut [Coarse], s: CycleSettings, r: &[f32], z: &mut [f32]) {
    if levels.is_empty() {
        z.par_iter_mut()
            .with_min_len(MIN_POINTS)
            .for_each(|v| *v = 0.0);
        for _ in 0..s.coarsest_sweeps {
            smooth_forward(fine, z, r, 1);
            smooth_backward(fine, z, r, 1);
        }
        return;
    }
    let half = s.sweeps > 0 && no_seam(fine.dims());
    smooth_forward_from_zero(fine, z, r, s.sweeps);
    restrict(fine, z, r, &mut levels[0], half);
    cycle_level(levels, 0, s);
    let c = &levels[0];
    prolong(fine, z, &c.x, c.dims, s.over_correction, half);
    smooth_backward(fine, z, r, s.sweeps);
}

/// Face conductances are stored in one byte on a logarithmic scale (steps of 2^(1/16), 4.4 %,
/// from the Jacobi floor 1/12 up to about 5e3 voxel units): the Schur approximation needs
/// them only to within a bounded factor, and three bytes per voxel keep the solve under 120.
pub fn encode_conductance(w: f32) -> u8 {
    if w > 0.0 {
        (1.0 + (16.0 * (12.0 * w).log2()).round()).clamp(1.0, 255.0) as u8
    } else {
        0
    }
}

/// The inverse of [`encode_conductance`], as a table (code 0: inactive face).
pub fn conductance_table() -> [f32; 256] {
    let mut t = [0f32; 256];
    for (q, v) in t.iter_mut().enumerate().skip(1) {
        *v = ((q as f64 - 1.0) / 16.0).exp2() as f32 / 12.0;
    }
    t
}

/// The pressure-space operator `L_w + delta I` of the Darcy part of the Schur-complement
/// approximation: `(L_w p)_i = sum_f w_f (p_i - p_j)` over the active faces `f` between pore
/// voxels `i` and `j`, with the face conductance `w_f`. Singular per pore component without
/// `delta`, which keeps every Galerkin diagonal positive.
pub struct DarcyOp<'a> {
    pub dims: Dims,
    pub mask: &'a [u8],
    /// [`encode_conductance`] of the face between voxel i and i + e_b, [x | y | z] blocks
    /// (0 when the face is inactive).
    pub w: &'a [u8],
    pub table: [f32; 256],
    pub delta: f32,
}

impl DarcyOp<'_> {
    #[inline]
    fn w(&self, b: usize, i: usize) -> f32 {
        self.table[self.w[b * self.dims.len() + i] as usize]
    }
}

impl Op7 for DarcyOp<'_> {
    fn dims(&self) -> Dims {
        self.dims
    }
    #[inline]
    fn active(&self, i: usize) -> bool {
        self.mask[i] & FLUID != 0
    }
    #[inline]
    fn diag(&self, i: usize, nb: &[usize; 6]) -> f32 {
        let mut d = self.delta;
        for b in 0..3 {
            if self.dims.n[b] == 1 {
                continue;
            }
            d += self.w(b, i) + self.w(b, nb[2 * b]);
        }
        d
    }
    #[inline]
    fn link(&self, i: usize, _j: usize, b: usize) -> f32 {
        self.w(b, i)
    }
    /// The diagonal is the sum of the same conductances the links read: one table lookup
    /// per face instead of two.
    #[inline]
    fn row_parts<R: Fn(usize) -> f32>(&self, read: R, i: usize, nb: &[usize; 6]) -> (f32, f32) {
        let mut s = 0.0;
        let mut d = self.delta;
        for b in 0..3 {
            if self.dims.n[b] == 1 {
                continue;
            }
            let (jm, jp) = (nb[2 * b], nb[2 * b + 1]);
            let (wp, wm) = (self.w(b, i), self.w(b, jm));
            s += wp * read(jp) + wm * read(jm);
            d += wp + wm;
        }
        (s, d)
    }
}

/// Multigrid for [`DarcyOp`]: one symmetric V-cycle approximates `(L_w + delta I)^{-1}`.
pub struct DarcyHierarchy<'a> {
    pub fine: DarcyOp<'a>,
    pub levels: Vec<Coarse>,
    pub settings: CycleSettings,
}

impl<'a> DarcyHierarchy<'a> {
    pub fn new(fine: DarcyOp<'a>, settings: CycleSettings) -> Self {
        let levels = build_levels(&fine);
        DarcyHierarchy {
            fine,
            levels,
            settings,
        }
    }
    pub fn vcycle(&mut self, r: &[f32], z: &mut [f32]) {
        vcycle_op(&self.fine, &mut self.levels, self.settings, r, z);
    }
    pub fn bytes(&self) -> usize {
        self.levels.iter().map(|l| l.dims.len() * 24).sum()
    }
}

fn cycle_level(levels: &mut [Coarse], l: usize, s: CycleSettings) {
    let (head, tail) = levels.split_at_mut(l + 1);
    let lev = &mut head[l];
    let mut x = std::mem::take(&mut lev.x);
    if tail.is_empty() {
        x.par_iter_mut()
            .with_min_len(MIN_POINTS)
            .for_each(|v| *v = 0.0);
        for _ in 0..s.coarsest_sweeps {
            smooth_forward(lev, &mut x, &lev.b, 1);
            smooth_backward(lev, &mut x, &lev.b, 1);
        }
        lev.x = x;
        return;
    }
    let half = s.sweeps > 0 && no_seam(lev.dims);
    smooth_forward_from_zero(lev, &mut x, &lev.b, s.sweeps);
    restrict(lev, &x, &lev.b, &mut tail[0], half);
    cycle_level(levels, l + 1, s);
    let (head, tail) = levels.split_at_mut(l + 1);
    let lev = &mut head[l];
    prolong(
        lev,
        &mut x,
        &tail[0].x,
        tail[0].dims,
        s.over_correction,
        half,
    );
    smooth_backward(lev, &mut x, &lev.b, s.sweeps);
    lev.x = x;
}
