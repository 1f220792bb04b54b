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

use crate::mac::{active_bit, Dims};
use rayon::prelude::*;

/// A 7-point symmetric operator on a periodic grid.
pub trait Op7: Sync {
    fn dims(&self) -> Dims;
    fn active(&self, i: usize) -> bool;
    fn diag(&self, i: usize, nb: &[usize; 6]) -> f32;
    /// Coupling weight w >= 0 between active i and j = i + e_b (A_ij = -w); 0 if j is inactive.
    fn link(&self, i: usize, j: usize, b: usize) -> f32;
}

/// The finest level: the wall rule of [`crate::mac`] evaluated from the mask, nothing stored.
pub struct FineOp<'a> {
    pub dims: Dims,
    pub mask: &'a [u8],
    /// This component's block of [`crate::mac::diagonals`].
    pub diag: &'a [u8],
    pub axis: usize,
}

impl Op7 for FineOp<'_> {
    fn dims(&self) -> Dims {
        self.dims
    }
    #[inline]
    fn active(&self, i: usize) -> bool {
        self.mask[i] & active_bit(self.axis) != 0
    }
    #[inline]
    fn diag(&self, i: usize, _nb: &[usize; 6]) -> f32 {
        self.diag[i] as f32
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

/// (A x)_i at an active point.
#[inline]
fn apply_at<O: Op7>(op: &O, x: &[f32], i: usize, nb: &[usize; 6]) -> f32 {
    op.diag(i, nb) * x[i] - offdiag_sum(op, x, i, nb)
}

/// sum_j w_ij x_j over the six neighbours.
#[inline]
fn offdiag_sum<O: Op7>(op: &O, x: &[f32], i: usize, nb: &[usize; 6]) -> f32 {
    let d = op.dims();
    let mut s = 0.0;
    for b in 0..3 {
        if d.n[b] == 1 {
            continue;
        }
        let (jm, jp) = (nb[2 * b], nb[2 * b + 1]);
        s += op.link(i, jp, b) * x[jp] + op.link(jm, i, b) * x[jm];
    }
    s
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

/// Points on the last layer of an axis with an odd number (> 1) of layers: there the
/// periodic neighbour has the same red-black colour, so they are updated after the parallel
/// phase, sequentially in a fixed order.
#[inline]
fn on_seam(d: Dims, c: [usize; 3]) -> bool {
    (0..3).any(|a| d.n[a] > 1 && d.n[a] % 2 == 1 && c[a] == d.n[a] - 1)
}

/// The seam points of one colour in index order, enumerated plane by plane.
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
    let update = |xs: &Shared, fx: usize, fy: usize, fz: usize| {
        let i = d.index(fx, fy, fz);
        if !op.active(i) {
            return;
        }
        let nb = d.neighbours(fx, fy, fz);
        let mut s = 0.0;
        for b in 0..3 {
            if d.n[b] == 1 {
                continue;
            }
            let (jm, jp) = (nb[2 * b], nb[2 * b + 1]);
            // SAFETY: neighbours have the other colour or sit on the seam, which is not
            // written in the parallel phase; the seam phase is sequential.
            unsafe {
                s += op.link(i, jp, b) * xs.read(jp) + op.link(jm, i, b) * xs.read(jm);
            }
        }
        let v = (rhs[i] + s) / op.diag(i, &nb);
        unsafe { xs.write(i, v) };
    };
    let xs = Shared(x.as_mut_ptr(), x.len());
    let seam = |xs: &Shared| {
        let mut pts = seam_points(d, colour);
        if seam_first {
            pts.reverse();
        }
        for p in pts {
            update(xs, p[0], p[1], p[2]);
        }
    };
    let any_seam = (0..3).any(|a| d.n[a] > 1 && d.n[a] % 2 == 1);
    if seam_first && any_seam {
        seam(&xs);
    }
    (0..d.n[2]).into_par_iter().for_each(|z| {
        for y in 0..d.n[1] {
            let start = (colour + y + z) % 2;
            for xx in (start..d.n[0]).step_by(2) {
                if !on_seam(d, [xx, y, z]) {
                    update(&xs, xx, y, z);
                }
            }
        }
    });
    if !seam_first && any_seam {
        seam(&xs);
    }
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
fn restrict<O: Op7>(op: &O, x: &[f32], rhs: &[f32], coarse: &mut Coarse) {
    let f = op.dims();
    let c = coarse.dims;
    let slab = c.slab();
    let active = &coarse.diag;
    coarse
        .b
        .par_chunks_mut(slab)
        .enumerate()
        .for_each(|(cz, bs)| {
            for cy in 0..c.n[1] {
                for cx in 0..c.n[0] {
                    let ci = c.index(cx, cy, cz);
                    let mut r = 0.0f64;
                    if active[ci] > 0.0 {
                        for fz in 2 * cz..(2 * cz + 2).min(f.n[2]) {
                            for fy in 2 * cy..(2 * cy + 2).min(f.n[1]) {
                                for fx in 2 * cx..(2 * cx + 2).min(f.n[0]) {
                                    let i = f.index(fx, fy, fz);
                                    if op.active(i) {
                                        let nb = f.neighbours(fx, fy, fz);
                                        r += (rhs[i] - apply_at(op, x, i, &nb)) as f64;
                                    }
                                }
                            }
                        }
                    }
                    bs[ci - cz * slab] = r as f32;
                }
            }
        });
}

/// x += scale * P x_c on the active points.
fn prolong<O: Op7>(op: &O, x: &mut [f32], xc: &[f32], c: Dims, scale: f32) {
    let f = op.dims();
    let slab = f.slab();
    x.par_chunks_mut(slab).enumerate().for_each(|(z, xs)| {
        for y in 0..f.n[1] {
            for xx in 0..f.n[0] {
                let i = f.index(xx, y, z);
                if op.active(i) {
                    xs[i - z * slab] += scale * xc[parent([xx, y, z], c)];
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
            sweeps: 1,
            over_correction: 1.5,
            coarsest_sweeps: 20,
        }
    }
}

/// The hierarchy of one velocity component.
pub struct Hierarchy<'a> {
    pub fine: FineOp<'a>,
    pub levels: Vec<Coarse>,
    pub settings: CycleSettings,
}

/// Stop coarsening at this many unknowns.
const COARSEST: usize = 64;

impl<'a> Hierarchy<'a> {
    pub fn new(
        dims: Dims,
        mask: &'a [u8],
        diag: &'a [u8],
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
        let mut levels: Vec<Coarse> = Vec::new();
        loop {
            let d = levels.last().map_or(dims, |l| l.dims);
            if d.len() <= COARSEST || coarse_dims(d) == d {
                break;
            }
            let next = match levels.last() {
                None => galerkin(&fine),
                Some(l) => galerkin(l),
            };
            levels.push(next);
        }
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
        z.par_iter_mut().for_each(|v| *v = 0.0);
        let s = self.settings;
        if self.levels.is_empty() {
            for _ in 0..s.coarsest_sweeps {
                smooth_forward(&self.fine, z, r, 1);
                smooth_backward(&self.fine, z, r, 1);
            }
            return;
        }
        smooth_forward(&self.fine, z, r, s.sweeps);
        restrict(&self.fine, z, r, &mut self.levels[0]);
        cycle_level(&mut self.levels, 0, s);
        let c = &self.levels[0];
        prolong(&self.fine, z, &c.x, c.dims, s.over_correction);
        smooth_backward(&self.fine, z, r, s.sweeps);
    }
}

fn cycle_level(levels: &mut [Coarse], l: usize, s: CycleSettings) {
    let (head, tail) = levels.split_at_mut(l + 1);
    let lev = &mut head[l];
    let mut x = std::mem::take(&mut lev.x);
    x.par_iter_mut().for_each(|v| *v = 0.0);
    if tail.is_empty() {
        for _ in 0..s.coarsest_sweeps {
            smooth_forward(lev, &mut x, &lev.b, 1);
            smooth_backward(lev, &mut x, &lev.b, 1);
        }
        lev.x = x;
        return;
    }
    smooth_forward(lev, &mut x, &lev.b, s.sweeps);
    restrict(lev, &x, &lev.b, &mut tail[0]);
    cycle_level(levels, l + 1, s);
    let (head, tail) = levels.split_at_mut(l + 1);
    let lev = &mut head[l];
    prolong(lev, &mut x, &tail[0].x, tail[0].dims, s.over_correction);
    smooth_backward(lev, &mut x, &lev.b, s.sweeps);
    lev.x = x;
}
