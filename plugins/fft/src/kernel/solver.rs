//! Linear solvers on the displacement (or temperature) fluctuation: preconditioned conjugate
//! gradients (Zeman et al. 2010, Brisard & Dormieux 2010, in the displacement form of
//! Schneider 2021) and the basic fixed-point scheme (Moulinec & Suquet 1994), both
//! preconditioned by the reference-medium Green operator `P = K0^{-1}` applied by FFT.
//!
//! Residual measure (Schneider 2021): `sqrt(r . P r) / sqrt(N E : C0 : E)`, the reference
//! energy norm of the strain correction `Gamma0 : sigma` relative to that of the macroscopic
//! strain. For the basic scheme it is the norm of the strain increment, for CG the same
//! quantity at the current iterate; it does not depend on the scaling of `C0` or on the
//! resolution. Every reduction is accumulated in f64 over fixed chunks, so results do not
//! depend on the thread count.

use rayon::prelude::*;
use std::fmt;

use crate::real::Real;

/// A linear cell problem `K u = f` with a preconditioner, on fields of `len()` scalars.
pub trait CellProblem<T: Real> {
    /// Number of unknowns (scalars).
    fn unknowns(&self) -> usize;
    /// `out = B^T C (E + B u)` with `E` the macroscopic load (`None`: zero).
    fn apply(&mut self, u: &[T], load: Option<&[f64]>, out: &mut [T]);
    /// `out = K p` (no load) and `p . out`; override where the dot product rides on the
    /// sweep that writes `out`.
    fn apply_dot(&mut self, p: &[T], out: &mut [T]) -> f64 {
        self.apply(p, None, out);
        dot(p, out)
    }
    /// `z = K0^{-1} r` (zero on the null space of `K0`).
    fn precondition(&mut self, r: &[T], z: &mut [T]);
    /// `r -= alpha q` first if `step` is `Some((alpha, q))`, then `z = K0^{-1} r`; returns
    /// `r . z` (accumulated in f64 in an order that does not depend on the thread count).
    /// Override where the update and the dot product ride on the preconditioner's sweeps.
    fn precondition_dot(&mut self, step: Option<(f64, &[T])>, r: &mut [T], z: &mut [T]) -> f64 {
        if let Some((alpha, q)) = step {
            axpy(-alpha, q, r);
        }
        self.precondition(r, z);
        dot(r, z)
    }
    /// `N E : C0 : E`, the reference energy of the load over the cell.
    fn load_energy(&self, load: &[f64]) -> f64;
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Method {
    Cg,
    FixedPoint,
}

#[derive(Clone, Debug)]
pub struct SolveOptions {
    pub method: Method,
    pub tolerance: f64,
    pub max_iterations: usize,
    /// Stagnation: the best residual has not dropped by 1 % over this many iterations.
    pub stagnation_window: usize,
}

#[derive(Clone, Debug, PartialEq)]
pub enum SolveError {
    NotConverged {
        iterations: usize,
        residual: f64,
    },
    Stagnated {
        iterations: usize,
        residual: f64,
        window: usize,
    },
    Diverged {
        iterations: usize,
        residual: f64,
    },
    Indefinite {
        iterations: usize,
        residual: f64,
        curvature: f64,
    },
    /// The load's reference energy or the first residual is not a finite positive number:
    /// the moduli or the load overflow (or underflow) double precision.
    OutOfRange {
        scale: f64,
        residual: f64,
    },
    Cancelled,
}

impl fmt::Display for SolveError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SolveError::NotConverged {
                iterations,
                residual,
            } => write!(
                f,
                "not converged after {iterations} iterations (max_iterations): residual \
                 {residual:.3e}; raise max_iterations, loosen tolerance, or use solver: cg \
                 with discretization: staggered"
            ),
            SolveError::Stagnated {
                iterations,
                residual,
                window,
            } => write!(
                f,
                "stagnated: the residual {residual:.3e} did not drop by 1 % over the last \
                 {window} iterations (iteration {iterations}); the scheme cannot reach the \
                 tolerance on this image (pores with the spectral or rotated discretization, \
                 or f32 round-off): use discretization: staggered or hex8, solver: cg, \
                 precision: f64"
            ),
            SolveError::Diverged {
                iterations,
                residual,
            } => write!(
                f,
                "diverged at iteration {iterations}: residual {residual:.3e}"
            ),
            SolveError::Indefinite {
                iterations,
                residual,
                curvature,
            } => write!(
                f,
                "loss of positive definiteness at iteration {iterations} (curvature \
                 {curvature:.3e}): residual {residual:.3e}; the discretized operator is not \
                 positive on the search direction (hourglass or pore modes)"
            ),
            SolveError::OutOfRange { scale, residual } => write!(
                f,
                "the problem is out of floating-point range before the first iteration (load \
                 energy scale {scale:.3e}, residual {residual:.3e}): the moduli or \
                 conductivities overflow or underflow; check their units"
            ),
            SolveError::Cancelled => write!(f, "cancelled"),
        }
    }
}

const CHUNK: usize = 1 << 14;

/// Deterministic dot product (fixed chunks, f64 accumulation, ordered final sum).
pub fn dot<T: Real>(a: &[T], b: &[T]) -> f64 {
    a.par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(x, y)| x.iter().zip(y).map(|(p, q)| p.f64() * q.f64()).sum::<f64>())
        .collect::<Vec<f64>>()
        .iter()
        .sum()
}

/// `sum a_i b_i` accumulated in f64 over 8 interleaved partial sums, added in a fixed order at
/// the end. Why not one running sum: that is a chain of dependent additions (~4 cycles each),
/// slower than the loads feeding it; 8 independent ones keep up with them. The order depends
/// only on the length, never on the thread count.
pub fn dot_lanes<T: Real>(a: &[T], b: &[T]) -> f64 {
    assert_eq!(a.len(), b.len());
    let mut acc = [0.0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..8 {
            acc[l] += x[l].f64() * y[l].f64();
        }
    }
    for (l, (x, y)) in ra.iter().zip(rb).enumerate() {
        acc[l] += x.f64() * y.f64();
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}

/// `y += a x`.
fn axpy<T: Real>(a: f64, x: &[T], y: &mut [T]) {
    let a = T::of(a);
    y.par_chunks_mut(CHUNK)
        .zip(x.par_chunks(CHUNK))
        .for_each(|(y, x)| y.iter_mut().zip(x).for_each(|(y, &x)| *y = *y + a * x));
}

/// `u += a p` then `p = z + b p`, in one pass over `u`, `p` and `z`.
///
/// Why together: CG's `u` is not read between its update and the next search direction, so
/// its update waits for this pass instead of riding a pass of its own (two vectors fewer read
/// per iteration). Every element gets the same formulas as in separate passes.
fn update_up<T: Real>(a: f64, b: f64, z: &[T], u: &mut [T], p: &mut [T]) {
    let (a, b) = (T::of(a), T::of(b));
    u.par_chunks_mut(CHUNK)
        .zip(p.par_chunks_mut(CHUNK))
        .zip(z.par_chunks(CHUNK))
        .for_each(|((u, p), z)| {
            for ((u, p), &z) in u.iter_mut().zip(p.iter_mut()).zip(z) {
                *u = *u + a * *p;
                *p = z + b * *p;
            }
        });
}

/// The outcome of one load case: the fluctuation and the residual history.
pub struct Solution<T> {
    pub u: Vec<T>,
    pub history: Vec<f64>,
}

/// Solves `K u = -B^T C E` for one load. `progress(iteration, residual)` returns false to
/// cancel.
pub fn solve<T: Real, P: CellProblem<T>>(
    problem: &mut P,
    load: &[f64],
    opt: &SolveOptions,
    progress: &mut dyn FnMut(usize, f64) -> bool,
) -> Result<Solution<T>, (SolveError, Vec<f64>)> {
    let n = problem.unknowns();
    let scale = problem.load_energy(load).sqrt();
    let mut u = vec![T::zero(); n];
    let mut r = vec![T::zero(); n];
    let mut z = vec![T::zero(); n];
    let mut history = Vec::new();
    let mut watch = Watch::new(opt);
    // r = f - K u with u = 0: f = -B^T C E.
    problem.apply(&u, Some(load), &mut r);
    r.par_iter_mut().for_each(|x| *x = -*x);
    let mut rz = problem.precondition_dot(None, &mut r, &mut z);
    let mut res = rz.max(0.0).sqrt() / scale;
    history.push(res);
    // A zero or infinite scale or a NaN residual would pass the test below as "converged"
    // with garbage (inf) moduli.
    if !(scale > 0.0 && scale.is_finite() && res.is_finite() && rz.is_finite()) {
        return Err((
            SolveError::OutOfRange {
                scale,
                residual: res,
            },
            history,
        ));
    }
    if res <= opt.tolerance {
        return Ok(Solution { u, history });
    }
    match opt.method {
        Method::FixedPoint => {
            // Basic scheme: u <- u + K0^{-1} (f - K u), eq. (3.3) as a fixed point.
            for it in 1..=opt.max_iterations {
                axpy(1.0, &z, &mut u);
                problem.apply(&u, Some(load), &mut r);
                r.par_iter_mut().for_each(|x| *x = -*x);
                rz = problem.precondition_dot(None, &mut r, &mut z);
                res = rz.max(0.0).sqrt() / scale;
                history.push(res);
                if !progress(it, res) {
                    return Err((SolveError::Cancelled, history));
                }
                if res <= opt.tolerance {
                    return Ok(Solution { u, history });
                }
                if let Err(e) = watch.check(it, res) {
                    return Err((e, history));
                }
            }
        }
        Method::Cg => {
            let mut p = z.clone();
            let mut q = vec![T::zero(); n];
            for it in 1..=opt.max_iterations {
                let pq = problem.apply_dot(&p, &mut q);
                // K is positive semi-definite and the load lies in its range, so a search
                // direction of zero curvature means the discrete operator lost definiteness
                // (or round-off dominates): stop instead of dividing by ~0.
                if !(pq > 0.0 && pq.is_finite()) {
                    let pp = dot(&p, &p);
                    return Err((
                        SolveError::Indefinite {
                            iterations: it,
                            residual: res,
                            curvature: pq / pp.max(f64::MIN_POSITIVE),
                        },
                        history,
                    ));
                }
                let alpha = rz / pq;
                // `u += alpha p` is left to `update_up` (or done below on convergence).
                let rz_new = problem.precondition_dot(Some((alpha, &q)), &mut r, &mut z);
                if rz_new < 0.0 {
                    return Err((
                        SolveError::Indefinite {
                            iterations: it,
                            residual: res,
                            curvature: rz_new,
                        },
                        history,
                    ));
                }
                res = rz_new.sqrt() / scale;
                history.push(res);
                if !progress(it, res) {
                    return Err((SolveError::Cancelled, history));
                }
                if res <= opt.tolerance {
                    axpy(alpha, &p, &mut u);
                    return Ok(Solution { u, history });
                }
                if let Err(e) = watch.check(it, res) {
                    return Err((e, history));
                }
                let beta = rz_new / rz;
                rz = rz_new;
                update_up(alpha, beta, &z, &mut u, &mut p);
            }
        }
    }
    Err((
        SolveError::NotConverged {
            iterations: opt.max_iterations,
            residual: res,
        },
        history,
    ))
}

/// `precondition_dot(Some((alpha, q)))` against its definition: `r -= alpha q`, then
/// `z = K0^{-1} r` by `precondition`, then `r . z` (to round-off: only the summation order
/// differs).
#[cfg(test)]
pub fn check_precondition_dot<T: Real, P: CellProblem<T>>(p: &mut P, seed: f64) {
    let n = p.unknowns();
    let r0: Vec<T> = (0..n).map(|i| T::of((i as f64 * seed).sin())).collect();
    let q: Vec<T> = (0..n)
        .map(|i| T::of((i as f64 * 0.29 + seed).cos()))
        .collect();
    let alpha = 0.37;
    let mut r_fused = r0.clone();
    let mut z_fused = vec![T::zero(); n];
    let rz_fused = p.precondition_dot(Some((alpha, &q)), &mut r_fused, &mut z_fused);
    let mut r = r0;
    axpy(-alpha, &q, &mut r);
    let mut z = vec![T::zero(); n];
    p.precondition(&r, &mut z);
    let rz = dot(&r, &z);
    assert_eq!(r, r_fused, "r -= alpha q must be the same per element");
    let zmax = z.iter().fold(0.0f64, |m, v| m.max(v.f64().abs()));
    for (a, b) in z.iter().zip(&z_fused) {
        assert!((a.f64() - b.f64()).abs() <= 1e-12 * zmax);
    }
    assert!(
        (rz - rz_fused).abs() <= 1e-12 * rz.abs(),
        "{rz} vs {rz_fused}"
    );
}

/// Divergence and stagnation watch.
struct Watch {
    first: Option<f64>,
    best: f64,
    best_at: usize,
    window: usize,
}

impl Watch {
    fn new(opt: &SolveOptions) -> Self {
        Watch {
            first: None,
            best: f64::INFINITY,
            best_at: 0,
            window: opt.stagnation_window.max(1),
        }
    }
    fn check(&mut self, it: usize, res: f64) -> Result<(), SolveError> {
        let first = *self.first.get_or_insert(res);
        if !res.is_finite() || res > 1e6 * first.max(1.0) {
            return Err(SolveError::Diverged {
                iterations: it,
                residual: res,
            });
        }
        if res < 0.99 * self.best {
            self.best = res;
            self.best_at = it;
        } else if it - self.best_at >= self.window {
            return Err(SolveError::Stagnated {
                iterations: it,
                residual: self.best,
                window: self.window,
            });
        }
        Ok(())
    }
}
