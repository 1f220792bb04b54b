//! conductivity.fft against exact laminate values and Rayleigh's simple-cubic sphere array.
#![allow(clippy::needless_range_loop)]

mod common;
use common::*;
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::units::Q;
use grainpipe_core::{PhaseImage, RunContext};
use grainpipe_fft::common::{Discretization, Solver};
use grainpipe_fft::conductivity::{solve_all, ConductivityParams};

fn conductivity(img: &PhaseImage, k: &[(u8, f64)], d: Discretization, tol: f64) -> [[f64; 3]; 3] {
    let p = ConductivityParams {
        conductivities: k.iter().map(|&(l, v)| (l.to_string(), Q::new(v))).collect(),
        discretization: d,
        solver: Solver::Cg,
        tolerance: tol,
        ..Default::default()
    };
    let kl = grainpipe_fft::common::resolve("conductivities", &p.conductivities, img, 0.0, |q| {
        Ok(q.si())
    })
    .unwrap();
    let rep = SilentReporter;
    let ctx = RunContext::new(1, &rep);
    solve_all::<f64>(&p, img, &kl, None, &ctx).unwrap().0
}

#[test]
fn laminates_give_the_series_and_parallel_means() {
    // Layers of 3, 2, 3 voxels with k = 7.7, 1.0, 0.2 (and a void instead of the last one).
    for void in [false, true] {
        let k3 = if void { 0.0 } else { 0.2 };
        let f = [3.0 / 8.0, 2.0 / 8.0, 3.0 / 8.0];
        let k = [7.7, 1.0, k3];
        let parallel: f64 = (0..3).map(|i| f[i] * k[i]).sum();
        let series = if void {
            0.0
        } else {
            1.0 / (0..3).map(|i| f[i] / k[i]).sum::<f64>()
        };
        for axis in 0..3 {
            let mut dims = [4, 4, 4];
            dims[axis] = 8;
            let img = image(dims, 1e-6, move |x, y, z| {
                let c = [x, y, z][axis];
                if c < 3 {
                    1
                } else if c < 5 {
                    2
                } else {
                    3
                }
            });
            let mats: Vec<(u8, f64)> = vec![(1, 7.7), (2, 1.0), (3, k3)];
            for d in [Discretization::Staggered, Discretization::Hex8] {
                let t = conductivity(&img, &mats, d, 1e-10);
                for i in 0..3 {
                    for j in 0..3 {
                        let want = if i != j {
                            0.0
                        } else if i == axis {
                            series
                        } else {
                            parallel
                        };
                        assert!(
                            (t[i][j] - want).abs() < 1e-8 * parallel,
                            "void {void} axis {axis} {d:?} k[{i}][{j}] = {} want {want}",
                            t[i][j]
                        );
                    }
                }
            }
        }
    }
}

/// Rayleigh (1892) for a simple-cubic array of spheres of conductivity ks in km at volume
/// fraction f, to the order f^(10/3) (McKenzie, McPhedran & Derrick 1978 add higher poles,
/// below 1e-4 relative at f = 0.1):
/// k/km = 1 + 3 f / (T - f - 1.305 f^(10/3) (ks - km) / (ks + 4/3 km)), T = (ks + 2 km)/(ks - km).
fn rayleigh(ks: f64, km: f64, f: f64) -> f64 {
    let t = (ks + 2.0 * km) / (ks - km);
    let c = (ks - km) / (ks + 4.0 / 3.0 * km);
    km * (1.0 + 3.0 * f / (t - f - 1.305 * c * f.powf(10.0 / 3.0)))
}

#[test]
fn simple_cubic_spheres_match_rayleigh() {
    // One sphere per cell at f ~ 0.1, 24^3 voxels: discretization error of the voxelized
    // sphere about 1-2 %; the voxel volume fraction (not the nominal one) enters the formula.
    let n = 24;
    let r = (0.1 * 3.0 / (4.0 * std::f64::consts::PI)).cbrt();
    for (ks, km) in [(0.0, 1.0), (10.0, 1.0)] {
        let img = spheres_image(n, &[[0.5; 3]], r, 2, 1);
        let f = img.fraction(2);
        let want = rayleigh(ks, km, f);
        for d in [Discretization::Staggered, Discretization::Hex8] {
            let t = conductivity(&img, &[(1, km), (2, ks)], d, 1e-8);
            for i in 0..3 {
                let e = (t[i][i] / want - 1.0).abs();
                // Conforming trilinear elements are stiffer (an upper bound for the voxel
                // geometry): 2.5 %; the staggered grid 1.5 %.
                let tol = if d == Discretization::Hex8 {
                    0.025
                } else {
                    0.015
                };
                assert!(
                    e < tol,
                    "ks {ks} {d:?}: k_{i}{i} = {} vs Rayleigh {want} ({e:.3e})",
                    t[i][i]
                );
            }
            // cubic symmetry: equal diagonal, no off-diagonal
            assert!((t[0][0] - t[2][2]).abs() < 1e-6 * want);
            assert!(t[0][1].abs() < 1e-6 * want);
        }
    }
}
