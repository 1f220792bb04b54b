//! packing.poisson_disk: no overlaps (brute force over all pairs, periodic images included),
//! theta within 5 % of the target, determinism, preflight refusals.

#![allow(clippy::needless_range_loop)] // axis loops index several vectors

use grainpipe_cemented::common::{measure, SMALL};
use grainpipe_cemented::poisson::{PoissonDisk, PoissonDiskParams};
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::units::Q;
use grainpipe_core::{InputMetas, Inputs, Packing, RunContext, StageError, Table, TypedStage};

fn run(p: &PoissonDiskParams, seed: u64) -> Result<(Packing, Table), StageError> {
    let pf = PoissonDisk.preflight(p, &InputMetas::new())?;
    let ctx = RunContext::new(seed, &SilentReporter);
    let out = PoissonDisk.run(p, &pf.plan, &Inputs::new(), &ctx)?;
    Ok((
        out["packing"].as_packing().unwrap().clone(),
        out["report"].as_table().unwrap().clone(),
    ))
}

fn params(
    dimension: u32,
    gamma: f64,
    theta: f64,
    size_in_rl: f64,
    periodic: bool,
) -> PoissonDiskParams {
    PoissonDiskParams {
        dimension,
        gamma,
        theta,
        periodic,
        size: Q::new(size_in_rl * 1e-3),
        ..Default::default()
    }
}

/// Largest overlap (r_i + r_j - distance, over the smaller radius) over all pairs and, on
/// periodic axes, all images within one period; independent of the stage's cell list.
fn worst_overlap(p: &Packing) -> f64 {
    let size = p.domain.size();
    let shifts: Vec<[f64; 3]> = {
        let mut v = Vec::new();
        let r = |a: usize| if p.domain.periodic[a] { -1..=1 } else { 0..=0 };
        for i in r(0) {
            for j in r(1) {
                for k in r(2) {
                    v.push([i as f64 * size[0], j as f64 * size[1], k as f64 * size[2]]);
                }
            }
        }
        v
    };
    let s = p.world_spheres();
    let mut worst = f64::NEG_INFINITY;
    for i in 0..s.len() {
        for j in i..s.len() {
            for sh in &shifts {
                if i == j && sh.iter().all(|&x| x == 0.0) {
                    continue;
                }
                let d = (0..3)
                    .map(|a| (s[j].center[a] + sh[a] - s[i].center[a]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                let o = (s[i].radius + s[j].radius - d) / s[i].radius.min(s[j].radius);
                worst = worst.max(o);
            }
        }
    }
    worst
}

/// theta recomputed from the bodies (independent of the report).
fn theta_of(p: &Packing, dim: usize) -> f64 {
    let class = &p.attributes["class"].values;
    let (mut l, mut s) = (0.0, 0.0);
    for (b, &c) in p.world_spheres().iter().zip(class) {
        if c == SMALL as f64 {
            s += measure(dim, b.radius);
        } else {
            l += measure(dim, b.radius);
        }
    }
    l / s
}

#[test]
fn walled_2d_sample_has_no_overlaps_and_hits_theta() {
    let p = params(2, 5.0, 1.4, 16.0, false);
    let (pk, rep) = run(&p, 7).unwrap();
    let worst = worst_overlap(&pk);
    assert!(worst <= 1e-9, "overlap {worst}");
    // Inside the walls.
    let h = 8e-3;
    for b in pk.world_spheres() {
        for a in 0..2 {
            assert!(b.center[a].abs() + b.radius <= h * (1.0 + 1e-12));
        }
    }
    let th = theta_of(&pk, 2);
    assert!((th - 1.4).abs() / 1.4 < 0.05, "theta {th}");
    let reported = rep.f64_column("theta").unwrap()[0];
    assert!((reported - th).abs() < 1e-12 * th);
    let rho = rep.f64_column("rho_particles").unwrap()[0];
    eprintln!(
        "2D walled: n = {}, theta = {th:.4}, rho_p = {rho:.4}, gap = {:e}",
        pk.bodies.len(),
        rep.f64_column("large_gap").unwrap()[0]
    );
    assert!(rho > 0.6 && rho < 0.9, "FPDS is nearly dense: {rho}");
}

#[test]
fn periodic_2d_sample_has_no_overlaps_with_images() {
    let p = params(2, 2.5, 2.2, 14.0, true);
    let (pk, _) = run(&p, 3).unwrap();
    let worst = worst_overlap(&pk);
    assert!(worst <= 1e-9, "overlap {worst}");
    let th = theta_of(&pk, 2);
    assert!((th - 2.2).abs() / 2.2 < 0.05, "theta {th}");
}

#[test]
fn sphere_sample_3d_has_no_overlaps_and_hits_theta() {
    let p = params(3, 2.0, 2.0, 12.0, false);
    let (pk, _) = run(&p, 11).unwrap();
    assert!(worst_overlap(&pk) <= 1e-9);
    let th = theta_of(&pk, 3);
    assert!((th - 2.0).abs() / 2.0 < 0.05, "theta {th}");
}

#[test]
fn same_seed_same_sample_other_seed_other_sample() {
    let p = params(2, 3.33, 1.6, 12.0, false);
    let (a, _) = run(&p, 5).unwrap();
    let (b, _) = run(&p, 5).unwrap();
    let (c, _) = run(&p, 6).unwrap();
    assert_eq!(a, b);
    assert_ne!(a, c);
}

#[test]
fn preflight_refuses_absurd_input_naming_the_key() {
    let key = |p: PoissonDiskParams| match PoissonDisk.preflight(&p, &InputMetas::new()) {
        Err(StageError::InvalidParam { key, .. }) => key,
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("accepted"),
    };
    assert_eq!(key(params(2, 5.0, 100.0, 20.0, false)), "theta");
    assert_eq!(key(params(2, 0.5, 1.4, 20.0, false)), "gamma");
    assert_eq!(key(params(2, 5.0, 1.4, 3.0, false)), "size");
    assert_eq!(key(params(4, 5.0, 1.4, 20.0, false)), "dimension");
    let mut p = params(2, 5.0, 1.4, 20.0, false);
    p.large_gap = Some(Q::new(10e-3));
    assert_eq!(key(p), "large_gap");
    let mut p = params(2, 5.0, 1.4, 20000.0, false);
    p.max_particles = 1000;
    assert_eq!(key(p), "size");
    // Issue 35: 10^9 calibrations kept bisecting a collapsed interval.
    let mut p = params(2, 5.0, 1.4, 20.0, false);
    p.max_calibrations = 1_000_000_000;
    assert_eq!(key(p), "max_calibrations");
}
