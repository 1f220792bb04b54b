//! Test geometries and a shorthand for the solver in voxel units.
#![allow(dead_code)]

use grainpipe_stokes::mac::Dims;
use grainpipe_stokes::multigrid::CycleSettings;
use grainpipe_stokes::solver::{permeability, Permeability, SolverSettings};

pub fn settings(tol: f64) -> SolverSettings {
    SolverSettings {
        tolerance: tol,
        max_iterations: 1000,
        cycle: CycleSettings::default(),
    }
}

/// Solves the listed load cases; panics on failure.
pub fn solve(dims: Dims, fluid: &[bool], axes: &[usize], tol: f64) -> Permeability {
    permeability::<(), _>(dims, fluid.to_vec(), axes, settings(tol), &[], |_, _, _| {
        Ok(())
    })
    .unwrap()
    .unwrap_or_else(|e| panic!("{e}"))
}

/// A centred body (ball when `dim3`, else a cylinder along z) voxelized so that its voxel
/// volume is the closest whole-shell approximation of `fraction` (volume-matched, so the
/// comparison measures the flow and not the voxelized volume). Returns the fluid mask.
pub fn centred_body(dims: Dims, fraction: f64, dim3: bool) -> Vec<bool> {
    let n = dims.len();
    let c = dims.n.map(|v| v as f64 / 2.0);
    let d2: Vec<f64> = (0..n)
        .map(|i| {
            let p = dims.coords(i);
            let q: Vec<f64> = (0..if dim3 { 3 } else { 2 })
                .map(|a| p[a] as f64 + 0.5 - c[a])
                .collect();
            q.iter().map(|v| v * v).sum()
        })
        .collect();
    let mut sorted = d2.clone();
    sorted.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let target = fraction * n as f64;
    // Cut only between distinct distances, so symmetric shells stay whole.
    let mut best = (f64::INFINITY, 0.0);
    let mut k = 0;
    while k < n {
        let mut e = k;
        while e < n && sorted[e] == sorted[k] {
            e += 1;
        }
        let err = (e as f64 - target).abs();
        if err < best.0 {
            best = (err, sorted[k]);
        }
        k = e;
    }
    d2.iter().map(|&v| v > best.1).collect()
}
