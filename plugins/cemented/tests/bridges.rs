//! binder.bridges: rasterised bridge and disk areas against exact circle-polygon
//! intersection areas, the stage's grid and labels, determinism across thread counts.

#![allow(clippy::needless_range_loop)] // axis loops index several vectors

use grainpipe_cemented::bridges::{find_bridges, rasterize, Bridges, BridgesParams};
use grainpipe_cemented::common::{Particles, LARGE, MATRIX, SMALL, VOID};
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::units::Q;
use grainpipe_core::{
    Artifact, Body, BodyAttribute, Domain, Grid, InputMetas, Inputs, Packing, RunContext,
    TypedStage,
};
use std::f64::consts::PI;
use std::sync::Arc;

/// Signed area of (circle of radius r at the origin) intersected with triangle (0, a, b):
/// the segment a-b is cut where it crosses the circle; inner pieces add triangles, outer
/// pieces circular sectors.
fn tri_circle(a: [f64; 2], b: [f64; 2], r: f64) -> f64 {
    let d = [b[0] - a[0], b[1] - a[1]];
    let (qa, qb, qc) = (
        d[0] * d[0] + d[1] * d[1],
        2.0 * (a[0] * d[0] + a[1] * d[1]),
        a[0] * a[0] + a[1] * a[1] - r * r,
    );
    let mut ts = vec![0.0, 1.0];
    let disc = qb * qb - 4.0 * qa * qc;
    if disc > 0.0 {
        for t in [
            (-qb - disc.sqrt()) / (2.0 * qa),
            (-qb + disc.sqrt()) / (2.0 * qa),
        ] {
            if t > 0.0 && t < 1.0 {
                ts.push(t);
            }
        }
    }
    ts.sort_by(f64::total_cmp);
    let at = |t: f64| [a[0] + t * d[0], a[1] + t * d[1]];
    let mut area = 0.0;
    for w in ts.windows(2) {
        let (p, q) = (at(w[0]), at(w[1]));
        let m = at(0.5 * (w[0] + w[1]));
        let cr = p[0] * q[1] - p[1] * q[0];
        if m[0] * m[0] + m[1] * m[1] <= r * r {
            area += 0.5 * cr;
        } else {
            area += 0.5 * r * r * cr.atan2(p[0] * q[0] + p[1] * q[1]);
        }
    }
    area
}

/// Area of a convex polygon (counter-clockwise) intersected with a circle.
fn polygon_circle(poly: &[[f64; 2]], c: [f64; 2], r: f64) -> f64 {
    (0..poly.len())
        .map(|k| {
            let a = poly[k];
            let b = poly[(k + 1) % poly.len()];
            tri_circle([a[0] - c[0], a[1] - c[1]], [b[0] - c[0], b[1] - c[1]], r)
        })
        .sum()
}

fn no_poll(_: u64, _: u64) -> Result<(), ()> {
    Ok(())
}

fn two_disks(r1: f64, r2: f64, d: f64) -> Packing {
    let mut p = Packing::new(Domain::boxed(
        [-8e-3, -8e-3, -2e-3],
        [8e-3, 8e-3, 2e-3],
        [false; 3],
    ));
    p.bodies = vec![
        Body::sphere([-0.5 * d, 0.0, 0.0], r1),
        Body::sphere([0.5 * d, 0.0, 0.0], r2),
    ];
    p.attributes.insert(
        "class".into(),
        BodyAttribute {
            unit: String::new(),
            values: vec![1.0, 2.0],
        },
    );
    p.attributes.insert(
        "disk".into(),
        BodyAttribute {
            unit: String::new(),
            values: vec![1.0, 1.0],
        },
    );
    p
}

fn run_stage(
    p: &BridgesParams,
    pk: &Packing,
) -> (grainpipe_core::PhaseImage, grainpipe_core::Table) {
    let mut metas = InputMetas::new();
    metas.insert(
        "packing".into(),
        grainpipe_core::ArtifactMeta::packing(pk.domain.min, pk.domain.max, pk.domain.periodic),
    );
    let pf = Bridges.preflight(p, &metas).unwrap();
    let mut inputs = Inputs::new();
    inputs.insert("packing".into(), Arc::new(Artifact::Packing(pk.clone())));
    let ctx = RunContext::new(0, &SilentReporter);
    let out = Bridges.run(p, &pf.plan, &inputs, &ctx).unwrap();
    let img = out["image"].as_phase_image().unwrap().clone();
    if let Some(g) = &pf.plan.grid {
        assert_eq!(g, &img.grid, "announced grid");
    }
    (img, out["report"].as_table().unwrap().clone())
}

#[test]
fn rasterised_bridge_and_disk_areas_match_exact_areas() {
    // r1 = 1 mm (large), r2 = 0.6 mm (small), centres 2.8 mm apart: a gap of 1.2 mm.
    let (r1, r2, d, eta) = (1e-3, 0.6e-3, 2.8e-3, 0.8);
    let pk = two_disks(r1, r2, d);
    let p = BridgesParams {
        eta,
        max_gap: Some(Q::new(1.5e-3)),
        crop_size: Some(Q::new(6e-3)),
        resolution: 600,
        ..Default::default()
    };
    let (img, rep) = run_stage(&p, &pk);
    assert_eq!(img.grid.dims, [600, 600, 1]);
    assert_eq!(
        rep.f64_column("bridges").map(|v| v[0]),
        None,
        "bridges is an integer column"
    );
    let px = img.grid.spacing[0] * img.grid.spacing[1];
    let area = |l: u8| img.labels.iter().filter(|&&x| x == l).count() as f64 * px;
    // Trapezoid from (-d/2, +-eta r1 / 2) to (d/2, +-eta r2 / 2), counter-clockwise.
    let (h1, h2) = (0.5 * eta * r1, 0.5 * eta * r2);
    let trap = [
        [-0.5 * d, -h1],
        [0.5 * d, -h2],
        [0.5 * d, h2],
        [-0.5 * d, h1],
    ];
    let trap_area = d * (h1 + h2);
    let exact_matrix = trap_area
        - polygon_circle(&trap, [-0.5 * d, 0.0], r1)
        - polygon_circle(&trap, [0.5 * d, 0.0], r2);
    let m = area(MATRIX);
    eprintln!("matrix {m:.6e} exact {exact_matrix:.6e} trapezoid {trap_area:.6e}");
    // Tolerance: boundary voxels of a 10 um grid with 3x3 sub-samples, about 0.2 % here.
    assert!(
        (m - exact_matrix).abs() <= 0.01 * exact_matrix,
        "{m} vs {exact_matrix}"
    );
    assert!((area(LARGE) - PI * r1 * r1).abs() <= 0.003 * PI * r1 * r1);
    assert!((area(SMALL) - PI * r2 * r2).abs() <= 0.003 * PI * r2 * r2);
    let total = 36e-6;
    assert!((area(VOID) + area(LARGE) + area(SMALL) + m - total).abs() < 1e-12);
}

#[test]
fn pairs_beyond_the_gap_get_no_bridge_and_bridges_join_close_pairs() {
    let pk = two_disks(1e-3, 1e-3, 2.5e-3);
    let parts = Particles::from_packing(&pk, "packing").unwrap();
    assert_eq!(
        find_bridges(&parts, &pk.domain, 0.4, 0.49e-3, no_poll)
            .unwrap()
            .len(),
        0
    );
    let b = find_bridges(&parts, &pk.domain, 0.4, 0.5e-3 + 1e-12, no_poll).unwrap();
    assert_eq!(b.len(), 1);
    assert!((b[0].ha - 0.2e-3).abs() < 1e-15 && (b[0].hb - 0.2e-3).abs() < 1e-15);
    // A point on the axis in the gap is matrix, one beyond the half-width is not.
    assert!(b[0].contains([0.0, 0.19e-3, 0.0]));
    assert!(!b[0].contains([0.0, 0.21e-3, 0.0]));
}

#[test]
fn labels_do_not_depend_on_the_thread_count() {
    let pk = two_disks(1e-3, 0.7e-3, 2.2e-3);
    let parts = Particles::from_packing(&pk, "packing").unwrap();
    let bridges = find_bridges(&parts, &pk.domain, 0.6, 1e-3, no_poll).unwrap();
    let grid = Grid::tiling(
        [-4e-3, -4e-3, -2.5e-6],
        [4e-3, 4e-3, 2.5e-6],
        [false; 3],
        5e-6,
    );
    let ctx = RunContext::new(0, &SilentReporter);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let a = one.install(|| rasterize(&parts, &bridges, &grid, 2, &ctx).unwrap());
    let b = two.install(|| rasterize(&parts, &bridges, &grid, 2, &ctx).unwrap());
    assert_eq!(a, b);
}

#[test]
fn preflight_refuses_a_crop_outside_the_box_and_bad_eta() {
    let pk = two_disks(1e-3, 1e-3, 2.5e-3);
    let mut metas = InputMetas::new();
    metas.insert(
        "packing".into(),
        grainpipe_core::ArtifactMeta::packing(pk.domain.min, pk.domain.max, pk.domain.periodic),
    );
    let key = |p: BridgesParams| match Bridges.preflight(&p, &metas) {
        Err(grainpipe_core::StageError::InvalidParam { key, .. }) => key,
        other => panic!("{:?}", other.map(|_| ())),
    };
    assert_eq!(
        key(BridgesParams {
            crop_size: Some(Q::new(20e-3)),
            ..Default::default()
        }),
        "crop_size"
    );
    assert_eq!(
        key(BridgesParams {
            eta: 0.0,
            ..Default::default()
        }),
        "eta"
    );
    assert_eq!(
        key(BridgesParams {
            crop_size: Some(Q::new(10e-3)),
            voxel_size: Some(Q::new(1e-9)),
            ..Default::default()
        }),
        "voxel_size"
    );
    // Issue 35: `max_gap: 1` (1 m) searched for minutes, ignoring Ctrl-C. Wider than half the
    // box (8 mm here) is refused before running; wider than the largest particle (2 mm) when
    // the particles are known.
    assert_eq!(
        key(BridgesParams {
            max_gap: Some(Q::new(1.0)),
            ..Default::default()
        }),
        "max_gap"
    );
    let p = BridgesParams {
        max_gap: Some(Q::new(3e-3)),
        crop_size: Some(Q::new(10e-3)),
        ..Default::default()
    };
    let pf = Bridges.preflight(&p, &metas).unwrap();
    let mut inputs = Inputs::new();
    inputs.insert("packing".into(), Arc::new(Artifact::Packing(pk.clone())));
    let ctx = RunContext::new(0, &SilentReporter);
    match Bridges.run(&p, &pf.plan, &inputs, &ctx) {
        Err(grainpipe_core::StageError::InvalidParam { key, message }) => {
            assert_eq!(key, "max_gap");
            assert!(
                message.contains("largest particle (2 mm across)"),
                "{message}"
            );
        }
        other => panic!("{:?}", other.map(|_| ())),
    }
}

/// Issue 34, item 1: the particle ids (1 + packing index) of two overlapping disks of one
/// class, against a brute-force point-in-disk test at the voxel centres (one sub-sample per
/// voxel): a voxel inside one disk only carries that disk's id, one in the lens either
/// disk's, matrix and void carry 0; both particles keep their identity although the labels
/// merge them into one region.
#[test]
fn particle_ids_follow_the_packing() {
    let (r, d) = (1e-3, 1.8e-3);
    let mut pk = two_disks(r, r, d);
    pk.attributes.get_mut("class").unwrap().values = vec![1.0, 1.0];
    let parts = Particles::from_packing(&pk, "packing").unwrap();
    let bridges = find_bridges(&parts, &pk.domain, 0.6, 1e-3, no_poll).unwrap();
    let grid = Grid::tiling(
        [-3e-3, -2e-3, -2.5e-5],
        [3e-3, 2e-3, 2.5e-5],
        [false; 3],
        5e-5,
    );
    let ctx = RunContext::new(0, &SilentReporter);
    let (labels, ids, _) = rasterize(&parts, &bridges, &grid, 1, &ctx).unwrap();
    let centres = [[-0.5 * d, 0.0], [0.5 * d, 0.0]];
    let mut seen = [0usize; 3];
    for (v, (&l, &id)) in labels.iter().zip(&ids).enumerate() {
        let [nx, _, _] = grid.dims;
        let q = [
            grid.origin[0] + ((v % nx) as f64 + 0.5) * grid.spacing[0],
            grid.origin[1] + ((v / nx) as f64 + 0.5) * grid.spacing[1],
        ];
        let inside: Vec<u32> = (0..2)
            .filter(|&k| {
                let c = centres[k];
                (q[0] - c[0]).powi(2) + (q[1] - c[1]).powi(2) < r * r
            })
            .map(|k| k as u32 + 1)
            .collect();
        if l == LARGE {
            assert!(
                inside.contains(&id),
                "voxel {v}: id {id}, inside {inside:?}"
            );
            seen[id as usize] += 1;
        } else {
            assert_eq!(id, 0, "voxel {v} of label {l}");
            seen[0] += 1;
        }
    }
    assert!(seen.iter().all(|&n| n > 100), "{seen:?}");
}
