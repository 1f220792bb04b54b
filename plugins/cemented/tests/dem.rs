//! dem.compact: force and torque balance recomputed from the final geometry, wall stress = P,
//! packing fraction of frictional bidisperse disks, determinism across thread counts.

#![allow(clippy::needless_range_loop)] // axis loops index several vectors

use grainpipe_cemented::common::{cross, dot, sub, Particles};
use grainpipe_cemented::dem::{compact, CompactParams, DemResult};
use grainpipe_cemented::poisson::{to_packing, two_step_sample, PoissonDiskParams};

fn sample(dim: u32, gamma: f64, size_in_rl: f64, seed: u64) -> Particles {
    let p = PoissonDiskParams {
        dimension: dim,
        gamma,
        theta: 1.4,
        size: grainpipe_core::units::Q::new(size_in_rl * 1e-3),
        ..Default::default()
    };
    let spec = p.spec().unwrap();
    // A fixed gap (no calibration needed for a DEM test).
    let s = two_step_sample(&spec, 0.1e-3, seed).unwrap();
    Particles::from_packing(&to_packing(&spec, &s), "packing").unwrap()
}

fn run(parts: &Particles, half: f64) -> DemResult {
    let spec = CompactParams::default().spec().unwrap();
    let h = [half, half, if parts.dim == 2 { 1.0 } else { half }];
    compact(parts, [0.0; 3], h, &spec, |_, _| Ok(())).unwrap()
}

#[test]
fn compacted_disks_are_in_equilibrium_at_the_confining_pressure() {
    let parts = sample(2, 2.5, 12.0, 1);
    let res = run(&parts, 6e-3);
    let p = CompactParams::default();
    let pressure = p.pressure.si();
    let kn = p.stiffness_ratio * pressure;
    assert!((res.kn - kn).abs() < 1e-9 * kn);
    let n = parts.len();
    let mut f = vec![[0.0f64; 3]; n];
    let mut t = vec![[0.0f64; 3]; n];
    let mut mean_fn = 0.0;
    let mut dash = 0.0;
    for &(i, j, fc) in &res.contact_forces {
        let d = sub(res.pos[j], res.pos[i]);
        let dist = dot(d, d).sqrt();
        let nrm = d.map(|c| c / dist);
        let overlap = parts.radius[i] + parts.radius[j] - dist;
        assert!(overlap > 0.0, "a force without overlap");
        // Normal part = k_n overlap + dashpot; the dashpot is checked on average below.
        let fnm = dot(fc, nrm);
        dash += (fnm - kn * overlap).abs();
        assert!(
            (fnm - kn * overlap).abs() <= 0.1 * kn * overlap,
            "{fnm} vs {}",
            kn * overlap
        );
        // Coulomb cone.
        let ft = [0, 1, 2].map(|k| fc[k] - fnm * nrm[k]);
        assert!(dot(ft, ft).sqrt() <= 0.3 * fnm * (1.0 + 1e-9));
        mean_fn += fnm;
        for k in 0..3 {
            f[j][k] += fc[k];
            f[i][k] -= fc[k];
        }
        let tj = cross(nrm.map(|c| -c * parts.radius[j]), fc);
        let ti = cross(nrm.map(|c| c * parts.radius[i]), fc.map(|c| -c));
        for k in 0..3 {
            t[j][k] += tj[k];
            t[i][k] += ti[k];
        }
    }
    // At rest: dashpot forces below 1e-3 of the elastic ones on average (stage criterion).
    assert!(dash / mean_fn <= 1e-3 * (1.0 + 1e-9), "{}", dash / mean_fn);
    mean_fn /= res.contact_forces.len() as f64;
    // Wall forces from the geometry, and wall stresses.
    let mut wall = [0.0f64; 2];
    for i in 0..n {
        for a in 0..2 {
            let lo = res.pos[i][a] - (-res.half[a]) - parts.radius[i];
            let hi = res.half[a] - res.pos[i][a] - parts.radius[i];
            if lo < 0.0 {
                f[i][a] += -kn * lo;
                wall[a] += -kn * lo;
            }
            if hi < 0.0 {
                f[i][a] -= -kn * hi;
                wall[a] += -kn * hi;
            }
        }
    }
    for a in 0..2 {
        let sigma = 0.5 * wall[a] / (2.0 * res.half[1 - a]);
        assert!(
            (sigma - pressure).abs() <= 0.011 * pressure,
            "axis {a}: {sigma} vs {pressure}"
        );
    }
    // Force balance: mean |net force| below 1e-3 of the mean contact force (the stage's
    // criterion) plus the dashpot part (also below 1e-3 by the criterion), and no particle
    // above 5 %.
    let nets: Vec<f64> = f.iter().map(|v| dot(*v, *v).sqrt() / mean_fn).collect();
    let touching: Vec<f64> = nets.iter().cloned().filter(|&x| x > 0.0).collect();
    let mean_net = touching.iter().sum::<f64>() / touching.len() as f64;
    let worst = nets.iter().cloned().fold(0.0, f64::max);
    let worst_t = t
        .iter()
        .zip(&parts.radius)
        .map(|(v, r)| dot(*v, *v).sqrt() / (mean_fn * r))
        .fold(0.0, f64::max);
    eprintln!(
        "2D DEM: n = {n}, steps = {}, mean net/mean fn = {mean_net:.2e}, worst = {worst:.2e}, worst torque = {worst_t:.2e}",
        res.steps
    );
    assert!(mean_net <= 2.1e-3, "{mean_net}");
    assert!(worst <= 0.05, "{worst}");
    assert!(worst_t <= 0.05, "{worst_t}");
    // Packing fraction of frictional (mu = 0.3) bidisperse disks between walls.
    let solid: f64 = parts
        .radius
        .iter()
        .map(|r| std::f64::consts::PI * r * r)
        .sum();
    let phi = solid / (4.0 * res.half[0] * res.half[1]);
    eprintln!("packing fraction {phi:.4}, contacts {}", res.n_contacts);
    assert!(phi > 0.78 && phi < 0.88, "{phi}");
}

#[test]
fn same_numbers_on_one_and_two_threads() {
    let parts = sample(2, 2.0, 12.0, 4);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let a = one.install(|| run(&parts, 6e-3));
    let b = two.install(|| run(&parts, 6e-3));
    assert_eq!(a.pos, b.pos);
    assert_eq!(a.half, b.half);
    assert_eq!(a.steps, b.steps);
}

#[test]
fn spheres_compact_in_3d() {
    let parts = sample(3, 1.43, 11.0, 2);
    let res = run(&parts, 5.5e-3);
    let pressure = CompactParams::default().pressure.si();
    for a in 0..3 {
        assert!((res.wall_stress[a] - pressure).abs() <= 0.01 * pressure);
    }
    let solid: f64 = parts
        .radius
        .iter()
        .map(|r| 4.0 / 3.0 * std::f64::consts::PI * r.powi(3))
        .sum();
    let phi = solid / (8.0 * res.half[0] * res.half[1] * res.half[2]);
    eprintln!(
        "3D DEM: n = {}, steps = {}, phi = {phi:.4}",
        parts.len(),
        res.steps
    );
    // Frictional spheres pack near 0.60-0.64 in bulk; a box of four diameters is dominated
    // by the looser wall layers.
    assert!(phi > 0.50 && phi < 0.66, "{phi}");
}

/// Issue 35: a pressure of 1e300 Pa (k_n = 1e304) went on to 10^6 steps with an infinite force
/// ratio. Pressures no grain survives and stiffness ratios whose forces lose their digits are
/// refused, naming the key.
#[test]
fn absurd_pressure_and_stiffness_are_refused() {
    for (p, key) in [
        (
            CompactParams {
                pressure: grainpipe_core::units::Q::new(1e300),
                ..Default::default()
            },
            "pressure",
        ),
        (
            CompactParams {
                stiffness_ratio: 1e12,
                ..Default::default()
            },
            "stiffness_ratio",
        ),
    ] {
        match p.spec() {
            Err(grainpipe_core::StageError::InvalidParam { key: k, message }) => {
                assert_eq!(k, key, "{message}")
            }
            other => panic!("{key}: {:?}", other.map(|_| ())),
        }
    }
    // The paper's values pass.
    CompactParams::default().spec().unwrap();
}
