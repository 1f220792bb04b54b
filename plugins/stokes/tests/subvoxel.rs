//! Sub-voxel walls (`permeability_composite`) against the label staircase.

mod common;

use grainpipe_stokes::mac::Dims;
use grainpipe_stokes::solver::{permeability_composite, Permeability};
use std::f64::consts::PI;

fn solve_composite(dims: Dims, phi: &[f32], axes: &[usize], tol: f64) -> Permeability {
    permeability_composite::<(), _>(dims, phi, axes, common::settings(tol), None, |_, _, _| Ok(()))
        .unwrap()
        .unwrap_or_else(|e| panic!("{e}"))
}

/// Fluid fraction of every voxel around a ball of radius `a` centred at `c` (voxel units),
/// by `m^3` sub-samples in the voxels the sphere may cross.
fn ball_fractions(dims: Dims, c: [f64; 3], a: f64, m: usize) -> Vec<f32> {
    (0..dims.len())
        .map(|i| {
            let p = dims.coords(i).map(|v| v as f64 + 0.5);
            let r = (0..3).map(|k| (p[k] - c[k]).powi(2)).sum::<f64>().sqrt();
            if r > a + 0.87 {
                return 1.0;
            }
            if r < a - 0.87 {
                return 0.0;
            }
            let mut fluid = 0usize;
            for z in 0..m {
                for y in 0..m {
                    for x in 0..m {
                        let q = [x, y, z].map(|t| (t as f64 + 0.5) / m as f64 - 0.5);
                        let d2: f64 = (0..3).map(|k| (p[k] + q[k] - c[k]).powi(2)).sum();
                        fluid += (d2 > a * a) as usize;
                    }
                }
            }
            (fluid as f64 / (m * m * m) as f64) as f32
        })
        .collect()
}

#[test]
fn explore_zick_homsy() {
    let cases: [(f64, f64); 5] = [
        (0.064, 2.810),
        (0.125, 4.292),
        (0.216, 7.442),
        (0.343, 15.4),
        (0.45, 28.1),
    ];
    for vpd in [10.0, 20.0] {
        for (c, k_ref) in cases {
            let d_over_l = 2.0 * (3.0 * c / (4.0 * PI)).cbrt();
            let n = (vpd / d_over_l).round() as usize;
            let dims = Dims::new([n, n, n]);
            let nf = n as f64;
            let a = 0.5 * d_over_l * nf;
            let phi = ball_fractions(dims, [nf / 2.0; 3], a, 16);
            let labels: Vec<bool> = phi.iter().map(|&f| f >= 0.5).collect();
            let centre: Vec<bool> = (0..dims.len())
                .map(|i| {
                    let p = dims.coords(i).map(|v| v as f64 + 0.5 - nf / 2.0);
                    p.iter().map(|v| v * v).sum::<f64>() > a * a
                })
                .collect();
            let matched = common::centred_body(dims, c, true);
            let kk = |k: f64| nf.powi(3) / (6.0 * PI * a * k) / k_ref - 1.0;
            let t = std::time::Instant::now();
            let rl = common::solve(dims, &centre, &[0], 1e-5);
            let tl = t.elapsed().as_secs_f64();
            let rm = common::solve(dims, &matched, &[0], 1e-5);
            let rh = common::solve(dims, &labels, &[0], 1e-5);
            let t = std::time::Instant::now();
            let rc = solve_composite(dims, &phi, &[0], 1e-5);
            let tc = t.elapsed().as_secs_f64();
            println!(
                "vpd {vpd} c {c} n {n}: centre {:+.2}% ({} it {tl:.2}s) matched {:+.2}% half {:+.2}% composite {:+.2}% ({} it {tc:.2}s)",
                100.0 * kk(rl.kappa[0][0]),
                rl.cases[0].iterations,
                100.0 * kk(rm.kappa[0][0]),
                100.0 * kk(rh.kappa[0][0]),
                100.0 * kk(rc.kappa[0][0]),
                rc.cases[0].iterations
            );
        }
    }
}

/// Fluid fraction of voxel rows for plates normal to y with fluid in (y0, y0 + gap).
fn slit(ny: usize, y0: f64, gap: f64) -> (Dims, Vec<f32>) {
    let d = Dims::new([4, ny, 3]);
    let f = (0..d.len())
        .map(|i| {
            let y = d.coords(i)[1] as f64;
            ((y + 1.0).min(y0 + gap) - y.max(y0)).clamp(0.0, 1.0) as f32
        })
        .collect();
    (d, f)
}

#[test]
fn explore_channel() {
    for gap in [4.3f64, 6.5, 8.7, 10.25, 12.6, 16.4, 20.5] {
        let ny = gap.ceil() as usize + 4;
        let (d, phi) = slit(ny, 1.8, gap);
        let exact = gap.powi(3) / 12.0 / ny as f64;
        let labels: Vec<bool> = phi.iter().map(|&f| f >= 0.5).collect();
        let rl = common::solve(d, &labels, &[0], 1e-7);
        let rc = solve_composite(d, &phi, &[0], 1e-7);
        println!(
            "gap {gap}: labels {:+.3}% composite {:+.4}%",
            100.0 * (rl.kappa[0][0] / exact - 1.0),
            100.0 * (rc.kappa[0][0] / exact - 1.0)
        );
    }
}

/// A periodic slit along the direction (1, s) in an n x (s n) x 1 box (s = 1, 2): fluid where
/// the line coordinate t = s x - y (mod s n) lies in (t0, t0 + w); fractions by m^2 samples.
fn tilted_slit(n: usize, s: usize, t0: f64, w: f64, m: usize) -> (Dims, Vec<f32>) {
    let d = Dims::new([n, s * n, 1]);
    let per = (s * n) as f64;
    let f = (0..d.len())
        .map(|i| {
            let c = d.coords(i);
            let mut k = 0;
            for a in 0..m {
                for b in 0..m {
                    let x = c[0] as f64 + (a as f64 + 0.5) / m as f64;
                    let y = c[1] as f64 + (b as f64 + 0.5) / m as f64;
                    let t = (s as f64 * x - y - t0).rem_euclid(per);
                    k += (t < w) as usize;
                }
            }
            (k as f64 / (m * m) as f64) as f32
        })
        .collect();
    (d, f)
}

#[test]
fn explore_tilted() {
    for s in [1usize, 2] {
        for n in [12usize, 18, 24, 36] {
            let per = (s * n) as f64;
            let w = 0.55 * per;
            let (d, phi) = tilted_slit(n, s, 0.3, w, 64);
            // gap normal to the plates: the line t = s x - y has |grad t| = sqrt(1 + s^2)
            let g = w / ((1 + s * s) as f64).sqrt();
            let porosity = w / per;
            // unit force along x: component along the plates (1, s)/sqrt(1+s^2)
            let c2 = 1.0 / (1 + s * s) as f64;
            let exact = porosity * g * g / 12.0 * c2;
            let labels: Vec<bool> = phi.iter().map(|&f| f >= 0.5).collect();
            let rl = common::solve(d, &labels, &[0], 1e-7);
            let rc = solve_composite(d, &phi, &[0], 1e-7);
            println!(
                "s {s} n {n} gap {g:.2}: labels {:+.3}% composite {:+.3}% ({} / {} it)",
                100.0 * (rl.kappa[0][0] / exact - 1.0),
                100.0 * (rc.kappa[0][0] / exact - 1.0),
                rl.cases[0].iterations,
                rc.cases[0].iterations
            );
        }
    }
}
