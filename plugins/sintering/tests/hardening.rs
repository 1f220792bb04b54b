//! Issue 17 regressions for `sintering.laser`: preflight bounds the work and memory that
//! passes, history and dt drive; max_steps counts multirate sub-cycles; results outside the
//! model's range of validity are reported.

use grainpipe_core::model::{
    ArtifactKind, ArtifactMeta, Body, Contact, ContactGraph, Domain, Packing,
};
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::units::Q;
use grainpipe_core::{InputMetas, RunContext, StageError, TypedStage};
use grainpipe_sintering::params::LaserParams;
use grainpipe_sintering::{simulate, validity_warning, LaserSintering};

/// A square lattice of touching spheres, two layers, with small spheres on every third top
/// sphere (their tiny heat capacity makes them stiff, so multirate sub-cycles them).
fn decorated_bed() -> (Packing, ContactGraph) {
    let (n, r, rs) = (8usize, 14.14e-6, 2e-6);
    let mut bodies = Vec::new();
    let mut contacts = Vec::new();
    let idx = |x: usize, y: usize, z: usize| x + n * (y + n * z);
    for z in 0..2 {
        for y in 0..n {
            for x in 0..n {
                let c = [
                    r + 2.0 * r * x as f64,
                    r + 2.0 * r * y as f64,
                    r + 2.0 * r * z as f64,
                ];
                bodies.push(Body::sphere(c, r));
                for (dx, dy, dz) in [(1, 0, 0), (0, 1, 0), (0, 0, 1)] {
                    if x + dx < n && y + dy < n && z + dz < 2 {
                        contacts.push(Contact {
                            i: idx(x, y, z),
                            j: idx(x + dx, y + dy, z + dz),
                            gap: 0.0,
                        });
                    }
                }
            }
        }
    }
    let mut top: Vec<usize> = (0..n * n).map(|k| k + n * n).collect();
    for k in (0..n * n).step_by(3) {
        let i = k + n * n;
        let c = bodies[i].position;
        let j = bodies.len();
        bodies.push(Body::sphere([c[0], c[1], c[2] + r + rs], rs));
        contacts.push(Contact { i, j, gap: 0.0 });
        top.push(j);
    }
    let side = 2.0 * r * n as f64;
    let mut p = Packing::new(Domain::boxed(
        [0.0; 3],
        [side, side, 4.0 * r + 2.0 * rs],
        [false; 3],
    ));
    p.bodies = bodies;
    let mut g = ContactGraph {
        contacts,
        ..Default::default()
    };
    g.faces[5] = top;
    (p, g)
}

fn metas(count: u64) -> InputMetas {
    let mut m = InputMetas::new();
    m.insert(
        "packing".into(),
        ArtifactMeta::packing([0.0; 3], [1e-3; 3], [false; 3]).with_count(count, None),
    );
    m.insert(
        "contacts".into(),
        ArtifactMeta::of(ArtifactKind::ContactGraph).with_count(count, None),
    );
    m
}

#[test]
fn a_billion_passes_are_refused_in_preflight_without_allocating_the_path() {
    let p = LaserParams {
        passes: 1_000_000_000,
        ..Default::default()
    };
    let e = LaserSintering
        .preflight(&p, &metas(1000))
        .expect_err("refused");
    match e {
        StageError::InvalidParam { key, message } => {
            assert_eq!(key, "passes");
            assert!(message.contains("max_steps"), "{message}");
        }
        other => panic!("{other}"),
    }
}

#[test]
fn history_of_every_step_is_in_the_memory_estimate() {
    // dt 1 ns over the default 3.5 ms: 3.5 million history rows.
    let p = LaserParams {
        history_interval: Q::new(0.0),
        dt: Some(Q::new(1e-9)),
        integrator: grainpipe_sintering::params::Integrator::Implicit,
        ..Default::default()
    };
    match LaserSintering.preflight(&p, &metas(100)) {
        Ok(pf) => assert!(
            pf.memory_bytes >= 3_000_000 * 100,
            "estimate {} B ignores the history",
            pf.memory_bytes
        ),
        // On a machine with little memory the same estimate refuses the run, naming the key.
        Err(StageError::InvalidParam { key, .. }) => assert_eq!(key, "history_interval"),
        Err(e) => panic!("{e}"),
    }
    // Without a dt the rows are bounded by max_steps: a smaller limit, a smaller estimate.
    let bounded = LaserParams {
        history_interval: Q::new(0.0),
        max_steps: 1000,
        ..Default::default()
    };
    let pf = LaserSintering.preflight(&bounded, &metas(100)).unwrap();
    assert!(pf.memory_bytes < 50_000_000, "{}", pf.memory_bytes);
}

#[test]
fn max_steps_counts_multirate_sub_cycles() {
    let (pk, g) = decorated_bed();
    let ctx = RunContext::new(3, &SilentReporter);
    let base = LaserParams {
        raster_length: Q::new(150e-6),
        passes: 2,
        cooldown: Q::new(50e-6),
        snapshot_interval: Q::new(0.0),
        history_interval: Q::new(0.0),
        bonded_conductance: Q::new(1.0),
        ..Default::default()
    };
    let full = simulate(&base, &pk, &g, &ctx).unwrap();
    let global_steps = full.history.rows() as u64 - 1;
    assert!(
        full.steps > global_steps,
        "sub-cycles must count as work: {} work steps, {global_steps} global steps",
        full.steps
    );
    // A limit the global steps fit under but the real work does not: refused.
    let limited = LaserParams {
        max_steps: global_steps + 1,
        ..base
    };
    let Err(e) = simulate(&limited, &pk, &g, &ctx) else {
        panic!("the limit bounds the work")
    };
    assert!(e.to_string().contains("max_steps"), "{e}");
}

#[test]
fn absurd_power_is_reported_outside_the_range_of_validity() {
    let (pk, g) = decorated_bed();
    let ctx = RunContext::new(3, &SilentReporter);
    let p = LaserParams {
        power: Q::new(1e300),
        raster_length: Q::new(100e-6),
        passes: 1,
        cooldown: Q::new(10e-6),
        snapshot_interval: Q::new(0.0),
        refuse_invalid: true,
        ..Default::default()
    };
    let Err(e) = simulate(&p, &pk, &g, &ctx) else {
        panic!("refused")
    };
    let text = e.to_string();
    assert!(
        text.contains("RANGE OF VALIDITY") || text.contains("non-finite"),
        "{text}"
    );
    // The check itself: 19,800 K (the old demo's peak) is far above boiling, 2000 K is not.
    let d = LaserParams::default();
    assert!(validity_warning(&d, 19_800.0, &[19_800.0, 300.0])
        .unwrap()
        .contains("1 of 2"));
    assert!(validity_warning(&d, 2000.0, &[2000.0]).is_none());
    assert!(validity_warning(&d, f64::INFINITY, &[f64::INFINITY]).is_some());
}

#[test]
fn absorptivity_scales_the_absorbed_energy() {
    let (pk, g) = decorated_bed();
    let ctx = RunContext::new(3, &SilentReporter);
    let base = LaserParams {
        raster_length: Q::new(100e-6),
        passes: 1,
        cooldown: Q::new(0.0),
        snapshot_interval: Q::new(0.0),
        ..Default::default()
    };
    let laser = |p: &LaserParams| {
        let r = simulate(p, &pk, &g, &ctx).unwrap();
        *r.history
            .f64_column("laser_energy")
            .unwrap()
            .last()
            .unwrap()
    };
    let full = laser(&base);
    let third = laser(&LaserParams {
        absorptivity: 0.35,
        ..base.clone()
    });
    assert!(
        full > 0.0 && (third / full - 0.35).abs() < 1e-9,
        "{third} / {full}"
    );
    let e = LaserSintering
        .preflight(
            &LaserParams {
                absorptivity: 1.5,
                ..base
            },
            &metas(10),
        )
        .expect_err("refused");
    assert!(
        matches!(e, StageError::InvalidParam { ref key, .. } if key == "absorptivity"),
        "{e}"
    );
}
