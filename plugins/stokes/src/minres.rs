//! Preconditioned MINRES (Paige & Saunders 1975; the form of Elman, Silvester & Wathen 2014,
//! Algorithm 4.1) for the symmetric indefinite Stokes system, with six stored vectors: the
//! product K z is never stored but recomputed inside the Lanczos update, and the new search
//! direction is formed before the next preconditioner application so that z can be reused.
//!
//! Vectors are f32 (memory); all scalars and reductions are f64, reduced in fixed chunks so
//! that the iterates do not depend on the number of threads.

use crate::mac::{dot, DiagValue, Stokes, CHUNK};
use rayon::prelude::*;

/// Outcome of a solve.
#[derive(Clone, Debug)]
pub struct MinresResult {
    pub iterations: usize,
    /// Final preconditioned residual relative to the initial one.
    pub relative_residual: f64,
    pub converged: bool,
    /// (iteration, relative preconditioned residual) after every iteration.
    pub history: Vec<(usize, f64)>,
}

/// Why a solve stopped without converging.
#[derive(Clone, Debug, PartialEq)]
pub enum MinresError {
    /// The preconditioner is not positive definite (<z, v> <= 0).
    IndefinitePreconditioner { iteration: usize, value: f64 },
    /// A non-finite number appeared.
    NotFinite { iteration: usize },
    /// The residual fell by less than [`STAGNATION_GAIN`] over the last half of the run
    /// (at least [`STAGNATION_WINDOW`] iterations): the tolerance is out of reach.
    Stagnated { iteration: usize, residual: f64 },
}

/// The smallest tolerance accepted. The vectors are f32: the recurrence residual keeps
/// falling below 1e-7 (1.2e-10 after 3000 iterations on spheres) while the velocity no longer
/// changes, so a smaller tolerance only runs out the iteration limit (1e-300 ran all 10^5).
pub const MIN_TOLERANCE: f64 = 1e-9;

/// The fewest iterations a stagnation is judged over.
pub const STAGNATION_WINDOW: usize = 1000;
/// The residual must fall at least by this factor over a window to count as progress.
pub const STAGNATION_GAIN: f64 = 0.99;

/// Whether `history` (iteration, residual) has stalled: over its last half, and at least
/// [`STAGNATION_WINDOW`] iterations, the residual fell by less than 1 %. MINRES residuals do
/// not increase but can plateau on indefinite systems before falling again; a plateau as long
/// as all the progress made before it is taken as final.
pub fn stagnated(history: &[(usize, f64)]) -> bool {
    let n = history.len();
    if n < 2 * STAGNATION_WINDOW {
        return false;
    }
    let (then, now) = (history[n / 2].1, history[n - 1].1);
    now > STAGNATION_GAIN * then
}

impl std::fmt::Display for MinresError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MinresError::IndefinitePreconditioner { iteration, value } => write!(
                f,
                "the multigrid preconditioner lost positive definiteness at iteration \
                 {iteration} (<z, r> = {value:.3e}); lower over_correction"
            ),
            MinresError::NotFinite { iteration } => {
                write!(f, "non-finite values at iteration {iteration}")
            }
            MinresError::Stagnated {
                iteration,
                residual,
            } => write!(
                f,
                "MINRES stagnated: the relative residual stayed at {residual:.3e} over the last \
                 {} iterations (iteration {iteration}); the tolerance is out of reach of this \
                 solve, loosen it to about {:.0e}",
                iteration / 2,
                10.0 * residual
            ),
        }
    }
}

/// Solves K x = b from x = 0, taking `b` over as the first Lanczos vector (so the right-hand
/// side costs no extra vector). `precond(v, z)` applies the SPD preconditioner z = P^{-1} v;
/// `monitor(iteration, relative residual)` may stop the solve by returning an error.
pub fn minres<D: DiagValue, P, M, E>(
    op: &Stokes<D>,
    b: Vec<f32>,
    x: &mut [f32],
    tol: f64,
    max_iterations: usize,
    mut precond: P,
    mut monitor: M,
) -> Result<Result<MinresResult, MinresError>, E>
where
    P: FnMut(&[f32], &mut [f32]),
    M: FnMut(usize, f64) -> Result<(), E>,
{
    let n = op.len();
    x.par_iter_mut().for_each(|v| *v = 0.0);
    let mut v_prev = vec![0f32; n];
    let mut v_cur = b;
    let mut z = vec![0f32; n];
    let mut w_prev = vec![0f32; n];
    let mut w_cur = vec![0f32; n];
    precond(&v_cur, &mut z);
    let g2 = dot(&z, &v_cur);
    if g2.is_nan() || g2 <= 0.0 {
        if g2 == 0.0 {
            return Ok(Ok(MinresResult {
                iterations: 0,
                relative_residual: 0.0,
                converged: true,
                history: vec![],
            }));
        }
        return Ok(Err(MinresError::IndefinitePreconditioner {
            iteration: 0,
            value: g2,
        }));
    }
    let gamma1 = g2.sqrt();
    let mut gamma = gamma1;
    let mut gamma_prev = 1.0;
    let mut eta = gamma1;
    let (mut s_prev, mut s) = (0.0f64, 0.0f64);
    let (mut c_prev, mut c) = (1.0f64, 1.0f64);
    let mut history = Vec::new();
    let mut rel = 1.0;
    // The search directions are stored unnormalised, w_j = a1_j * (true w_j), and the solution
    // update x += c eta w_j of iteration j is applied in iteration j + 1's pass over w (it reads
    // w_j anyway): one pass over x, w_{j-1}, w_j and z per iteration instead of two (the
    // normalisation of w alone wrote a whole vector). `pending` is c eta / a1 of the update
    // still owed to x; `a1_cur`, `a1_prev` the normalisations of w_cur, w_prev.
    let mut pending = 0.0f64;
    let (mut a1_cur, mut a1_prev) = (1.0f64, 1.0f64);
    let flush = |x: &mut [f32], w: &[f32], coef: f64| {
        let coef = coef as f32;
        x.par_chunks_mut(CHUNK)
            .zip(w.par_chunks(CHUNK))
            .for_each(|(xx, ww)| {
                for k in 0..xx.len() {
                    xx[k] += coef * ww[k];
                }
            });
    };
    for it in 1..=max_iterations {
        // z_j = P^{-1} v_j / gamma_j: the 1/gamma is folded into the two passes that read z.
        let zs = 1.0 / gamma;
        // v_{j+1} = K z_j - (delta / gamma_j) v_j - (gamma_j / gamma_{j-1}) v_{j-1}, with
        // delta = <K z_j, z_j> accumulated while K z_j is formed.
        let delta = op.apply_shift_quad(&z, &mut v_prev, gamma / gamma_prev, zs);
        {
            let a = (delta / gamma) as f32;
            v_prev
                .par_chunks_mut(CHUNK)
                .zip(v_cur.par_chunks(CHUNK))
                .for_each(|(vp, vc)| {
                    for k in 0..vp.len() {
                        vp[k] -= a * vc[k];
                    }
                });
        }
        std::mem::swap(&mut v_prev, &mut v_cur);
        let a0 = c * delta - c_prev * s * gamma;
        let a2 = s * delta + c_prev * c * gamma;
        let a3 = s_prev * gamma;
        // w_{j+1} = z_j - a3 w_{j-1} - a2 w_j (true directions), written over w_{j-1}, with
        // the owed x += pending * w_j on the way.
        {
            let (zs, a2, a3, px) = (
                zs as f32,
                (a2 / a1_cur) as f32,
                (a3 / a1_prev) as f32,
                pending as f32,
            );
            w_prev
                .par_chunks_mut(CHUNK)
                .zip(w_cur.par_chunks(CHUNK))
                .zip(z.par_chunks(CHUNK))
                .zip(x.par_chunks_mut(CHUNK))
                .for_each(|(((wp, wc), zz), xx)| {
                    for k in 0..wp.len() {
                        xx[k] += px * wc[k];
                        wp[k] = zs * zz[k] - a3 * wp[k] - a2 * wc[k];
                    }
                });
        }
        std::mem::swap(&mut w_prev, &mut w_cur);
        precond(&v_cur, &mut z);
        let g2 = dot(&z, &v_cur);
        if g2 < 0.0 {
            return Ok(Err(MinresError::IndefinitePreconditioner {
                iteration: it,
                value: g2,
            }));
        }
        let gamma_next = g2.sqrt();
        let a1 = (a0 * a0 + gamma_next * gamma_next).sqrt();
        if !a1.is_finite() || a1 == 0.0 {
            return Ok(Err(MinresError::NotFinite { iteration: it }));
        }
        let c_next = a0 / a1;
        let s_next = gamma_next / a1;
        a1_prev = a1_cur;
        a1_cur = a1;
        pending = c_next * eta / a1;
        eta *= -s_next;
        gamma_prev = gamma;
        gamma = gamma_next;
        c_prev = c;
        c = c_next;
        s_prev = s;
        s = s_next;
        rel = eta.abs() / gamma1;
        if !rel.is_finite() {
            return Ok(Err(MinresError::NotFinite { iteration: it }));
        }
        history.push((it, rel));
        if let Err(e) = monitor(it, rel) {
            flush(x, &w_cur, pending);
            return Err(e);
        }
        if rel <= tol || gamma == 0.0 {
            flush(x, &w_cur, pending);
            return Ok(Ok(MinresResult {
                iterations: it,
                relative_residual: rel,
                converged: true,
                history,
            }));
        }
        if stagnated(&history) {
            return Ok(Err(MinresError::Stagnated {
                iteration: it,
                residual: rel,
            }));
        }
    }
    flush(x, &w_cur, pending);
    Ok(Ok(MinresResult {
        iterations: max_iterations,
        relative_residual: rel,
        converged: false,
        history,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn history(residual: impl Fn(usize) -> f64, n: usize) -> Vec<(usize, f64)> {
        (1..=n).map(|i| (i, residual(i))).collect()
    }

    #[test]
    fn a_plateau_as_long_as_the_progress_before_it_is_stagnation() {
        // Falls to 1e-8 in 500 iterations, then flat for 1500: stalled.
        let h = history(|i| 10f64.powf(-8.0 * (i.min(500) as f64) / 500.0), 2000);
        assert!(stagnated(&h));
        // Still falling by 1 % per 100 iterations: progress.
        let h = history(|i| 0.9999f64.powi(i as i32), 4000);
        assert!(!stagnated(&h));
        // Too short to judge.
        let h = history(|_| 1.0, 2 * STAGNATION_WINDOW - 1);
        assert!(!stagnated(&h));
        // A plateau shorter than the run before it, then a fall (indefinite systems): not
        // stagnation at any point.
        let r = |i: usize| match i {
            0..=1500 => 1e-3 * 0.995f64.powi(i as i32),
            1501..=2200 => 1e-3 * 0.995f64.powi(1500),
            _ => 1e-3 * 0.995f64.powi(1500) * 0.99f64.powi((i - 2200) as i32),
        };
        let h = history(r, 3000);
        assert!((2 * STAGNATION_WINDOW..=3000).all(|n| !stagnated(&h[..n])));
    }
}
