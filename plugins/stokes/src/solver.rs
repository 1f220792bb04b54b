//! Permeability of a periodic voxel pore space in voxel units (h = 1, mu = 1, f = 1): the
//! load cases, free of framework types.

use crate::mac::{
    build_mask, composite_walls, diagonals, dot, DiagValue, Dims, Percolation, Stokes, FLUID,
};
use crate::minres::{minres, MinresError};
use crate::multigrid::{
    conductance_table, encode_conductance, CycleSettings, DarcyHierarchy, DarcyOp, Hierarchy,
};
use rayon::prelude::*;

/// Settings of a solve.
#[derive(Clone, Copy, Debug)]
pub struct SolverSettings {
    /// Stop when the preconditioned residual fell by this factor.
    pub tolerance: f64,
    pub max_iterations: usize,
    pub cycle: CycleSettings,
}

/// One load case f = e_axis.
#[derive(Clone, Debug)]
pub struct LoadCase {
    pub axis: usize,
    /// <u>_Y per component in voxel units (eq. (3.7)); column `axis` of kappa / h^2.
    pub mean_velocity: [f64; 3],
    pub iterations: usize,
    /// Final relative preconditioned residual (MINRES estimate).
    pub residual: f64,
    /// ||b - K x|| / ||b|| recomputed from the solution.
    pub true_residual: f64,
    /// ||div u||_2 / ||u||_2 over the pore space (voxel units).
    pub mass_error: f64,
    pub history: Vec<(usize, f64)>,
    /// Why the case was not solved (non-percolating direction), if so.
    pub note: Option<String>,
    /// The solution [u_x | u_y | u_z | p] when kept.
    pub solution: Option<Vec<f32>>,
}

/// Why a solve failed.
#[derive(Clone, Debug)]
pub enum SolveError {
    NotConverged {
        axis: usize,
        iterations: usize,
        residual: f64,
    },
    Breakdown {
        axis: usize,
        cause: MinresError,
    },
    NoSolid,
}

impl std::fmt::Display for SolveError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = |a: &usize| ["x", "y", "z"][*a];
        match self {
            SolveError::NotConverged {
                axis,
                iterations,
                residual,
            } => write!(
                f,
                "load case {}: MINRES did not reach the tolerance in {iterations} iterations \
                 (relative residual {residual:.3e}); raise max_iterations or loosen tolerance",
                name(axis)
            ),
            SolveError::Breakdown { axis, cause } => {
                write!(f, "load case {}: {cause}", name(axis))
            }
            SolveError::NoSolid => write!(
                f,
                "the pore space percolates along an axis without meeting any solid: the \
                 permeability of a cell with a solid-free channel of periodic layers is unbounded"
            ),
        }
    }
}

/// Bytes per voxel the solve holds at its peak: six 4-block f32 MINRES vectors (the solution
/// included; the right-hand side is the first Lanczos vector), the mask, the three diagonal
/// bytes, the three conductance bytes of the Darcy pressure operator, and the coarse levels of
/// three velocity hierarchies and the pressure hierarchy (24 bytes per coarse unknown, 1/7 of
/// the fine count summed over levels): 116.7 bytes.
pub const BYTES_PER_VOXEL: f64 = 6.0 * 16.0 + 1.0 + 3.0 + 3.0 + 4.0 * 24.0 / 7.0;
/// Extra bytes per voxel for the velocity and pressure fields (f32, 4 components).
pub const FIELD_BYTES_PER_VOXEL: f64 = 16.0;
/// The percolation analysis (u32 component and i32x3 image shift per voxel) runs before the
/// solver vectors exist.
pub const LABEL_BYTES_PER_VOXEL: f64 = 16.0 + 1.0 + 1.0;

/// The result of all load cases.
#[derive(Clone, Debug)]
pub struct Permeability {
    pub percolation: Percolation,
    /// kappa / h^2, kappa[i][j] = <u_i> under f = e_j (eq. (3.8) with mu = 1).
    pub kappa: [[f64; 3]; 3],
    pub cases: Vec<LoadCase>,
    /// Porosity of the image (all fluid voxels) and of the kept pore space.
    pub porosity: f64,
    pub connected_porosity: f64,
}

/// Solves the load cases `axes` on the label pore space `is_fluid` (walls on the voxel
/// faces, [`diagonals`]); the solutions of the axes in `keep_solutions` are kept.
/// `monitor(case index, iteration, residual)` may cancel.
pub fn permeability<E, M>(
    dims: Dims,
    is_fluid: Vec<bool>,
    axes: &[usize],
    settings: SolverSettings,
    keep_solutions: &[usize],
    monitor: M,
) -> Result<Result<Permeability, SolveError>, E>
where
    M: FnMut(usize, usize, f64) -> Result<(), E>,
{
    let n = dims.len();
    let (mask, perc) = build_mask(dims, &is_fluid);
    let porosity = is_fluid.iter().filter(|&&f| f).count() as f64 / n as f64;
    drop(is_fluid);
    let connected = perc.kept as f64 / n as f64;
    let diag = diagonals(dims, &mask);
    solve_cases(
        dims,
        &mask,
        perc,
        (porosity, connected),
        &diag,
        None,
        axes,
        settings,
        keep_solutions,
        monitor,
    )
}

/// [`permeability`] with sub-voxel walls: `fluid_fraction` is the fluid volume fraction of
/// every voxel (1 = fluid, 0 = solid). Voxels at least half fluid carry the pressure and
/// the velocity unknowns (the label topology of the fractions), and the wall distances of
/// the velocity faces next to the solid come from the fractions ([`composite_diagonals`]),
/// so that a wall anywhere inside a voxel is seen where it is instead of on a voxel face.
/// With fractions in {0, 1} the result is that of [`permeability`] on the same pore space.
/// Porosity is the mean fluid fraction; the connected porosity scales it by the kept share
/// of the pore voxels.
pub fn permeability_composite<E, M>(
    dims: Dims,
    fluid_fraction: &[f32],
    axes: &[usize],
    settings: SolverSettings,
    keep_solutions: &[usize],
    monitor: M,
) -> Result<Result<Permeability, SolveError>, E>
where
    M: FnMut(usize, usize, f64) -> Result<(), E>,
{
    let n = dims.len();
    assert_eq!(fluid_fraction.len(), n);
    let is_fluid: Vec<bool> = fluid_fraction.par_iter().map(|&f| f >= 0.5).collect();
    let (mask, perc) = build_mask(dims, &is_fluid);
    drop(is_fluid);
    let porosity = sum_chunked(fluid_fraction) / n as f64;
    let pore_voxels = perc.kept + perc.isolated;
    let connected = if pore_voxels > 0 {
        porosity * perc.kept as f64 / pore_voxels as f64
    } else {
        0.0
    };
    let (diag, force) = composite_walls(dims, &mask, fluid_fraction);
    solve_cases(
        dims,
        &mask,
        perc,
        (porosity, connected),
        &diag,
        Some(&force),
        axes,
        settings,
        keep_solutions,
        monitor,
    )
}

/// The load cases on a built mask and velocity diagonals (whole-number label diagonals or
/// the real ones of the sub-voxel walls).
#[allow(clippy::too_many_arguments)]
fn solve_cases<D: DiagValue, E, M>(
    dims: Dims,
    mask: &[u8],
    perc: Percolation,
    (porosity, connected): (f64, f64),
    diag: &[D],
    force: Option<&[f32]>,
    axes: &[usize],
    settings: SolverSettings,
    keep_solutions: &[usize],
    mut monitor: M,
) -> Result<Result<Permeability, SolveError>, E>
where
    M: FnMut(usize, usize, f64) -> Result<(), E>,
{
    let n = dims.len();
    let op = Stokes {
        dims,
        mask,
        diag,
        force,
    };
    let mut kappa = [[0.0; 3]; 3];
    let any_solve = axes.iter().any(|&a| perc.percolates[a]);
    if any_solve && perc.kept == n {
        return Ok(Err(SolveError::NoSolid));
    }
    let mut hier: Vec<Hierarchy<D>> = if any_solve {
        (0..3)
            .map(|a| Hierarchy::new(dims, mask, diag, a, settings.cycle))
            .collect()
    } else {
        Vec::new()
    };
    // The solution vector, shared by the load cases (MINRES starts from zero); before them it
    // is the scratch space of `conductances`, so the setup adds no transient allocation to
    // the peak (freed heap memory is not always returned to the system).
    let mut x = vec![0f32; 4 * n];
    let w = if any_solve {
        let (ones, wa) = x[..2 * n].split_at_mut(n);
        conductances(dims, mask, diag, &mut hier, ones, wa)
    } else {
        Vec::new()
    };
    let mut darcy = if any_solve {
        Some(DarcyHierarchy::new(
            DarcyOp {
                dims,
                mask,
                w: &w,
                table: conductance_table(),
                delta: DARCY_DELTA,
            },
            settings.cycle,
        ))
    } else {
        None
    };
    // The cases whose solutions are kept run last, so the last one's vector can outlive the
    // others (the earlier kept ones are copied: 16 B per voxel each).
    let mut order: Vec<(usize, usize)> = axes.iter().copied().enumerate().collect();
    order.sort_by_key(|&(_, a)| keep_solutions.contains(&a));
    let last_kept = order
        .iter()
        .rev()
        .find(|&&(_, a)| keep_solutions.contains(&a))
        .map(|&(k, _)| k);
    let mut results: Vec<Option<LoadCase>> = vec![None; axes.len()];
    for (case_index, axis) in order {
        if !perc.percolates[axis] {
            results[case_index] = Some(LoadCase {
                axis,
                mean_velocity: [0.0; 3],
                iterations: 0,
                residual: 0.0,
                true_residual: 0.0,
                mass_error: 0.0,
                history: vec![],
                note: Some(format!(
                    "the pore space does not percolate along {}: no pore component connects \
                     to its periodic image, so kappa = 0 in that direction (not solved)",
                    ["x", "y", "z"][axis]
                )),
                solution: None,
            });
            continue;
        }
        if x.is_empty() {
            // Only if an axis is listed twice and its first solution was kept.
            x = vec![0f32; 4 * n];
        }
        let mut b = vec![0f32; 4 * n];
        let bit = crate::mac::active_bit(axis);
        b[axis * n..(axis + 1) * n]
            .par_iter_mut()
            .zip(mask.par_iter())
            .enumerate()
            .for_each(|(l, (v, &m))| {
                if m & bit != 0 {
                    *v = force.map_or(1.0, |w| w[axis * n + l]);
                }
            });
        let precond = |v: &[f32], z: &mut [f32]| {
            // The four V-cycles are independent: run as concurrent tasks, the sequential
            // coarse levels and the fork-join ends of one overlap with the parallel sweeps of
            // another (each V-cycle's result does not depend on how it is scheduled).
            let (vu, vp) = v.split_at(3 * n);
            let (zu, zp) = z.split_at_mut(3 * n);
            rayon::scope(|s| {
                if let Some(dh) = darcy.as_mut() {
                    s.spawn(move |_| dh.vcycle(vp, zp));
                } else {
                    zp.iter_mut().for_each(|v| *v = 0.0);
                }
                for ((h, vc), zc) in hier.iter_mut().zip(vu.chunks(n)).zip(zu.chunks_mut(n)) {
                    s.spawn(move |_| h.vcycle(vc, zc));
                }
            });
            // Pressure block: S^{-1} ~ M_p^{-1} + (B W B^T)^{-1} (Cahouet & Chabard 1988 for
            // A = sigma I - Lap, where S^{-1} = I + sigma L_p^{-1} exactly in a periodic cell),
            // with the wall resistance of the pore space in place of sigma: W = diag(A^{-1} 1)
            // (see `conductances`). In a one-voxel channel (A = 8 + L along it) this is the
            // exact S^{-1} = I + 8 L^{-1}; in open pores W is large and the mass-matrix term
            // dominates. The identity alone lets the Darcy-like pressure modes across narrow
            // throats converge slowly (iterations growing with resolution).
            z[3 * n..]
                .par_iter_mut()
                .zip(v[3 * n..].par_iter())
                .zip(mask.par_iter())
                .for_each(|((zz, &vv), &m)| *zz = if m & FLUID != 0 { vv + *zz } else { 0.0 });
        };
        let active_faces = mask.iter().filter(|&&m| m & bit != 0).count();
        let bnorm = match force {
            None => (active_faces as f64).sqrt(),
            Some(_) => dot(&b, &b).sqrt(),
        };
        let res = minres(
            &op,
            b,
            &mut x,
            settings.tolerance,
            settings.max_iterations,
            precond,
            |it, r| monitor(case_index, it, r),
        )?;
        let res = match res {
            Ok(r) => r,
            Err(cause) => return Ok(Err(SolveError::Breakdown { axis, cause })),
        };
        if !res.converged {
            return Ok(Err(SolveError::NotConverged {
                axis,
                iterations: res.iterations,
                residual: res.relative_residual,
            }));
        }
        let mut mean = [0.0; 3];
        for (a, m) in mean.iter_mut().enumerate() {
            *m = match force {
                // Weights (2 + w) / 3: between the point values (the nodal sum) and the
                // trapezoid rule of the profile through u = 0 at the wall (the dual-cell
                // extent w), which err in opposite directions on a parabola (h^2/24 and
                // -h^2/12 of its curvature): exact for plane Poiseuille flow with uniform
                // spacing, and measured closer for walls at any distance.
                Some(w) => sum_weighted(&x[a * n..(a + 1) * n], &w[a * n..(a + 1) * n]) / n as f64,
                None => sum_chunked(&x[a * n..(a + 1) * n]) / n as f64,
            };
            kappa[a][axis] = *m;
        }
        let (rv, rp) = op.residual_sq(&x, axis);
        let true_residual = (rv + rp).sqrt() / bnorm;
        // The pressure rows of the residual are -div u (their right-hand side is 0).
        let unorm = dot(&x[..3 * n], &x[..3 * n]).sqrt();
        let mass_error = if unorm > 0.0 { rp.sqrt() / unorm } else { 0.0 };
        results[case_index] = Some(LoadCase {
            axis,
            mean_velocity: mean,
            iterations: res.iterations,
            residual: res.relative_residual,
            true_residual,
            mass_error,
            history: res.history,
            note: None,
            // The last kept case runs last, so `x` is not needed after it.
            solution: if last_kept == Some(case_index) {
                Some(std::mem::take(&mut x))
            } else if keep_solutions.contains(&axis) {
                Some(x.clone())
            } else {
                None
            },
        });
    }
    drop(hier);
    let cases: Vec<LoadCase> = results.into_iter().flatten().collect();
    Ok(Ok(Permeability {
        percolation: perc,
        kappa,
        cases,
        porosity,
        connected_porosity: connected,
    }))
}

/// Regularisation `delta` of the Darcy pressure operator `B W B^T + delta I` (voxel units).
/// It keeps the Galerkin diagonal of a coarse block that covers a whole pore component
/// positive; the pressure parts of the Lanczos vectors have zero mean per component (they are
/// divergences), so it barely acts. Measured: 1e-5 and 1e-3 give the same iterations at 64^3.
pub const DARCY_DELTA: f32 = 1e-5;

/// Face conductances `w_a ~ A_a^{-1} 1` of the three velocity components, encoded by
/// [`encode_conductance`]: the flow a unit body force drives through each face when the
/// pressure is ignored, i.e. the local Darcy permeability of the pore space (in a straight
/// channel its Poiseuille profile). One V-cycle of the velocity multigrid gives it closely
/// enough (Richardson refinements did not change the iteration count: 58 at 64^3 with 0, 2
/// or 5); floored at the Jacobi value `1 / A_ff`, which bounds `A^{-1} 1` from below for this
/// M-matrix.
/// `ones` and `wa` are scratch vectors of one block.
fn conductances<D: DiagValue>(
    dims: Dims,
    mask: &[u8],
    diag: &[D],
    hier: &mut [Hierarchy<D>],
    ones: &mut [f32],
    wa: &mut [f32],
) -> Vec<u8> {
    let n = dims.len();
    let mut w = vec![0u8; 3 * n];
    for (a, h) in hier.iter_mut().enumerate() {
        let bit = crate::mac::active_bit(a);
        ones.par_iter_mut()
            .zip(mask.par_iter())
            .for_each(|(o, &m)| *o = if m & bit != 0 { 1.0 } else { 0.0 });
        h.vcycle(ones, wa);
        w[a * n..(a + 1) * n]
            .par_iter_mut()
            .zip(wa.par_iter())
            .zip(diag[a * n..(a + 1) * n].par_iter())
            .for_each(|((q, &ww), &d)| {
                *q = if d.value() > 0.0 {
                    encode_conductance(ww.max(1.0 / d.value()))
                } else {
                    0
                };
            });
    }
    w
}

/// sum of v (2 + w) / 3 in fixed chunks (see the mean velocity of the sub-voxel walls).
fn sum_weighted(v: &[f32], w: &[f32]) -> f64 {
    v.par_chunks(crate::mac::CHUNK)
        .zip(w.par_chunks(crate::mac::CHUNK))
        .map(|(c, d)| {
            c.iter()
                .zip(d)
                .map(|(&x, &w)| x as f64 * (2.0 + w as f64) / 3.0)
                .sum::<f64>()
        })
        .collect::<Vec<f64>>()
        .iter()
        .sum()
}

fn sum_chunked(v: &[f32]) -> f64 {
    v.par_chunks(crate::mac::CHUNK)
        .map(|c| c.iter().map(|&x| x as f64).sum::<f64>())
        .collect::<Vec<f64>>()
        .iter()
        .sum()
}

/// Relative asymmetry ||K - K^T||_F / ||K||_F of the solved block.
pub fn symmetry_error(k: &[[f64; 3]; 3]) -> f64 {
    let mut num = 0.0;
    let mut den = 0.0;
    for (i, row) in k.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            num += (v - k[j][i]).powi(2);
            den += v.powi(2);
        }
    }
    if den > 0.0 {
        (num / den).sqrt()
    } else {
        0.0
    }
}
