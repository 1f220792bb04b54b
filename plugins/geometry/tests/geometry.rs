//! Validation of packing.rsa and voxelize.packing against analytic references.

use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::units::Q;
use grainpipe_core::{Artifact, Inputs, Packing, Registry, RunContext, StageError, TypedStage};
use grainpipe_geometry::rsa::{Rsa, RsaParams};
use grainpipe_geometry::voxelize::{Voxelize, VoxelizeParams};
use std::f64::consts::PI;
use std::sync::Arc;

fn run_rsa(p: &RsaParams, seed: u64) -> Result<Packing, StageError> {
    let ctx = RunContext::new(seed, &SilentReporter);
    let out = Rsa.run(p, &(), &Inputs::new(), &ctx)?;
    Ok(out["packing"].as_packing().unwrap().clone())
}

fn voxelize(packing: &Packing, p: &VoxelizeParams) -> (grainpipe_core::PhaseImage, f64) {
    let ctx = RunContext::new(0, &SilentReporter);
    let mut inputs = Inputs::new();
    inputs.insert(
        "packing".into(),
        Arc::new(Artifact::Packing(packing.clone())),
    );
    let out = Voxelize.run(p, &None, &inputs, &ctx).unwrap();
    let cov = out["report"]
        .as_table()
        .unwrap()
        .f64_column("coverage_fraction")
        .unwrap()[0];
    (out["image"].as_phase_image().unwrap().clone(), cov)
}

/// Largest overlap over all pairs, brute force with minimum images (independent of the cell list).
fn max_overlap(p: &Packing) -> f64 {
    let size = p.domain.size();
    let mut worst = f64::NEG_INFINITY;
    let s = p.world_spheres();
    for i in 0..s.len() {
        for j in i + 1..s.len() {
            let d2: f64 = (0..3)
                .map(|a| {
                    let mut d = s[j].center[a] - s[i].center[a];
                    if p.domain.periodic[a] {
                        d -= size[a] * (d / size[a]).round();
                    }
                    d * d
                })
                .sum();
            worst = worst.max(s[i].radius + s[j].radius - d2.sqrt());
        }
    }
    worst
}

#[test]
fn rsa_reaches_target_without_overlap() {
    let p = RsaParams {
        radius: SizeDistribution::Uniform {
            min: Q::new(15e-6),
            max: Q::new(30e-6),
        },
        volume_fraction: 0.30,
        ..Default::default()
    };
    let packing = run_rsa(&p, 7).unwrap();
    let phi = packing.volume_fraction();
    // Radii are drawn until the target is reached, so the overshoot is at most one sphere.
    let one_sphere = 4.0 / 3.0 * PI * (30e-6f64).powi(3) / packing.domain.volume();
    assert!(phi >= 0.30 && phi < 0.30 + one_sphere, "phi = {phi}");
    // Overlap tolerance: zero up to round-off of the centre coordinates (1e-18 m).
    assert!(
        max_overlap(&packing) <= 1e-18,
        "overlap {}",
        max_overlap(&packing)
    );
    // Every centre lies in the periodic box.
    for b in &packing.bodies {
        assert!(b.position.iter().all(|&x| (0.0..500e-6).contains(&x)));
    }
}

#[test]
fn rsa_non_periodic_keeps_spheres_inside() {
    let p = RsaParams {
        periodic: [false, false, true],
        volume_fraction: 0.2,
        ..Default::default()
    };
    let packing = run_rsa(&p, 3).unwrap();
    for b in &packing.bodies {
        for a in 0..2 {
            assert!(b.position[a] >= 25e-6 && b.position[a] <= 500e-6 - 25e-6);
        }
    }
    assert!(max_overlap(&packing) <= 1e-18);
}

#[test]
fn rsa_same_seed_same_packing_different_seed_different() {
    let p = RsaParams::default();
    let a = run_rsa(&p, 11).unwrap();
    let b = run_rsa(&p, 11).unwrap();
    let c = run_rsa(&p, 12).unwrap();
    assert_eq!(a, b);
    assert_ne!(a.bodies[0].position, c.bodies[0].position);
}

#[test]
fn rsa_refuses_monodisperse_fraction_above_jamming_limit() {
    let p = RsaParams {
        volume_fraction: 0.45,
        ..Default::default()
    };
    match Rsa.preflight(&p, &Default::default()) {
        Err(StageError::InvalidParam { key, message }) => {
            assert_eq!(key, "volume_fraction");
            assert!(message.contains("0.38278"), "{message}");
        }
        other => panic!("expected a parameter error, got {other:?}"),
    }
}

/// Issue 36: a 25 mm radius in a 400 um periodic box ran and reported a volume fraction of
/// 1 022 653. A sphere wider than the period is refused at preflight, naming both lengths.
#[test]
fn rsa_refuses_a_sphere_wider_than_the_periodic_box() {
    let p = RsaParams {
        size: [Q::new(400e-6); 3],
        radius: SizeDistribution::Fixed {
            value: Q::new(25e-3),
        },
        ..Default::default()
    };
    match Rsa.preflight(&p, &Default::default()) {
        Err(StageError::InvalidParam { key, message }) => {
            assert_eq!(key, "radius");
            assert!(
                message.contains("(50 mm across) is wider than the periodic box along x (400 um)"),
                "{message}"
            );
        }
        other => panic!("expected a parameter error, got {other:?}"),
    }
}

#[test]
fn rsa_jams_loudly_on_unreachable_polydisperse_target() {
    // A narrow polydisperse law behaves like monodisperse spheres: 0.55 is far beyond
    // the ~0.38 RSA saturation, so a sphere must run out of attempts.
    let p = RsaParams {
        size: [Q::new(300e-6); 3],
        radius: SizeDistribution::Uniform {
            min: Q::new(24e-6),
            max: Q::new(26e-6),
        },
        volume_fraction: 0.55,
        max_attempts_per_sphere: 2_000,
        ..Default::default()
    };
    match run_rsa(&p, 1) {
        Err(StageError::Failed(m)) => {
            assert!(
                m.contains("jammed") && m.contains("volume fraction reached"),
                "{m}"
            );
        }
        other => panic!("expected failure, got {:?}", other.map(|p| p.bodies.len())),
    }
}

#[test]
fn voxelized_single_sphere_matches_analytic_volume() {
    let mut packing = Packing::new(grainpipe_core::Domain::boxed(
        [0.0; 3], [1e-3; 3], [true; 3],
    ));
    packing.bodies.push(grainpipe_core::Body::sphere(
        [0.5e-3, 0.5e-3, 0.5e-3],
        0.3e-3,
    ));
    let p = VoxelizeParams {
        voxels_per_diameter: 20.0,
        ..Default::default()
    };
    let (img, cov) = voxelize(&packing, &p);
    let exact = 4.0 / 3.0 * PI * 0.3f64.powi(3);
    // A single sphere centred on a voxel centre is the worst case of the lattice-point count
    // (Gauss's sphere problem): at ~10 voxels radius the majority-vote image deviates by a few
    // percent, which averages out over the random positions of a packing (see the RSA test
    // below). The sub-voxel coverage (4^3 samples in each cut voxel) is the accurate measure.
    assert!(
        (img.fraction(1) - exact).abs() / exact < 0.03,
        "image {}",
        img.fraction(1)
    );
    assert!((cov - exact).abs() / exact < 0.005, "coverage {cov}");
}

#[test]
fn periodic_wrap_counts_a_sphere_across_the_corner() {
    // A sphere centred on the box corner is split into 8 pieces by the periodic boundary.
    let mut packing = Packing::new(grainpipe_core::Domain::boxed(
        [0.0; 3], [1e-3; 3], [true; 3],
    ));
    packing
        .bodies
        .push(grainpipe_core::Body::sphere([0.0, 0.0, 0.0], 0.3e-3));
    let p = VoxelizeParams {
        voxels_per_diameter: 20.0,
        ..Default::default()
    };
    let (_, cov) = voxelize(&packing, &p);
    let exact = 4.0 / 3.0 * PI * 0.3f64.powi(3);
    // Same sampling tolerance as for the centred sphere: the eight pieces must add up.
    assert!(
        (cov - exact).abs() / exact < 0.005,
        "coverage {cov} vs {exact}"
    );
}

/// The acceptance test of the foundation issue: an RSA packing voxelized at 20 voxels per
/// diameter matches the analytic sphere volume fraction within 0.5 %.
#[test]
fn rsa_packing_voxelized_at_20_voxels_per_diameter_within_half_percent() {
    let p = RsaParams {
        size: [Q::new(400e-6); 3],
        volume_fraction: 0.30,
        ..Default::default()
    };
    let packing = run_rsa(&p, 42).unwrap();
    let analytic = packing.volume_fraction();
    let (img, _) = voxelize(
        &packing,
        &VoxelizeParams {
            voxels_per_diameter: 20.0,
            ..Default::default()
        },
    );
    let rel = (img.fraction(1) - analytic).abs() / analytic;
    assert!(
        rel < 0.005,
        "image {} analytic {analytic} rel {rel}",
        img.fraction(1)
    );
}

#[test]
fn voxelization_does_not_depend_on_thread_count() {
    let packing = run_rsa(
        &RsaParams {
            size: [Q::new(300e-6); 3],
            ..Default::default()
        },
        5,
    )
    .unwrap();
    let p = VoxelizeParams {
        voxels_per_diameter: 8.0,
        ..Default::default()
    };
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let a = one.install(|| voxelize(&packing, &p));
    let b = two.install(|| voxelize(&packing, &p));
    assert_eq!(a.0.labels, b.0.labels);
    assert_eq!(a.1.to_bits(), b.1.to_bits());
}

#[test]
fn declared_parameters_match_the_params_structs() {
    let mut r = Registry::new();
    grainpipe_geometry::register(&mut r);
    r.check_consistency().unwrap();
}

fn grid(n: usize, box_len: f64, periodic: bool) -> grainpipe_core::Grid {
    grainpipe_core::Grid {
        dims: [n; 3],
        spacing: [box_len / n as f64; 3],
        origin: [0.0; 3],
        periodic: [periodic; 3],
    }
}

fn one_sphere(center: [f64; 3], radius: f64) -> Vec<grainpipe_core::WorldSphere> {
    vec![grainpipe_core::WorldSphere {
        center,
        radius,
        body: 0,
    }]
}

#[test]
fn stamped_clumps_are_identical_at_one_and_two_threads() {
    // Clumps of heavily overlapping spheres of mixed sizes, many across the periodic faces,
    // at a supersampling whose 27 sub-samples do not fill a 64-bit mask word.
    let mut spheres = Vec::new();
    for c in 0..30u64 {
        let f = |k: u64| ((c * 2654435761 + k * 40503) % 1000) as f64 / 1000.0;
        for s in 0..12u64 {
            let g = |k: u64| ((c * 7919 + s * 104729 + k * 1299709) % 1000) as f64 / 1000.0;
            spheres.push(grainpipe_core::WorldSphere {
                center: [0, 1, 2].map(|a| f(a as u64) + 0.06 * (g(a as u64) - 0.5)),
                radius: 0.01 + 0.04 * g(3),
                body: c as usize,
            });
        }
    }
    let g = grid(50, 1.0, true);
    let ctx = RunContext::new(0, &SilentReporter);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                grainpipe_geometry::voxelize::voxelize(&g, &spheres, [true; 3], 3, &ctx).unwrap()
            })
    };
    let (a, b) = (run(1), run(2));
    assert_eq!(a.0, b.0);
    assert_eq!(a.1.to_bits(), b.1.to_bits());
    assert!(a.0.contains(&0) && a.0.contains(&1));
}

#[test]
fn voxel_volume_of_one_sphere_converges_to_four_thirds_pi_r_cubed() {
    // Off-lattice centre (no symmetry helps the count). Tolerances on the sub-voxel
    // coverage (4^3 samples in cut voxels) at 8, 16 and 32 voxels per diameter: the
    // surface-sampling error falls about as (voxels per diameter)^-2 .. ^-1.5.
    let r = 0.3;
    let exact = 4.0 / 3.0 * PI * r * r * r;
    let mut errors = Vec::new();
    for (vpd, tol) in [(8usize, 0.02), (16, 0.006), (32, 0.002)] {
        let n = (vpd as f64 / (2.0 * r)).round() as usize;
        let g = grid(n, 1.0, true);
        let ctx = RunContext::new(0, &SilentReporter);
        let (labels, cov) = grainpipe_geometry::voxelize::voxelize(
            &g,
            &one_sphere([0.5123, 0.4871, 0.5037], r),
            [true; 3],
            4,
            &ctx,
        )
        .unwrap();
        let rel = (cov - exact).abs() / exact;
        assert!(
            rel < tol,
            "{vpd} voxels per diameter: coverage {cov} vs {exact}"
        );
        // The majority-vote image is within a few times the coverage error.
        let img = labels.iter().filter(|&&l| l == 1).count() as f64 / labels.len() as f64;
        assert!(
            (img - exact).abs() / exact < 4.0 * tol,
            "{vpd}: image {img}"
        );
        errors.push(rel);
    }
    assert!(errors[2] < errors[0], "{errors:?}");
}

#[test]
fn periodic_sphere_across_the_corner_is_the_centred_sphere_rolled() {
    // Dyadic coordinates make every voxel-centre distance exact, so the sphere centred near
    // the corner must be the sphere centred near the middle, shifted by 16 voxels on each
    // axis, voxel for voxel: no piece of it is lost at the faces.
    let n = 32;
    let g = grid(n, 1.0, true);
    let ctx = RunContext::new(0, &SilentReporter);
    let d = 3.0 / 64.0;
    let vox = |c| {
        grainpipe_geometry::voxelize::voxelize(&g, &one_sphere(c, 0.3), [true; 3], 4, &ctx).unwrap()
    };
    let (corner, cov_corner) = vox([d, 1.0 - d, d]);
    let (middle, cov_middle) = vox([0.5 + d, 0.5 - d, 0.5 + d]);
    let at = |x: usize, y: usize, z: usize| x + n * (y + n * z);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let rolled = at((x + n / 2) % n, (y + n / 2) % n, (z + n / 2) % n);
                assert_eq!(corner[at(x, y, z)], middle[rolled], "voxel {x} {y} {z}");
            }
        }
    }
    assert_eq!(cov_corner, cov_middle);
    let exact = 4.0 / 3.0 * PI * 0.027;
    assert!((cov_corner - exact).abs() / exact < 0.003, "{cov_corner}");
}
