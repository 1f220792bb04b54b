//! Stage-level checks of the brick fillers against geometry (exact tangency, face planes),
//! the paper's goals and the Kolmogorov-Smirnov statistics of the drawn radii.

// Loops over axes index several per-axis arrays at once.
#![allow(clippy::needless_range_loop)]

use grainpipe_bricks::{
    BrickParams, Curved, CurvedParams, Method1, Method1Params, Method2, Method2Params,
};
use grainpipe_core::distributions::{ks_critical_value, ks_distance, SizeDistribution};
use grainpipe_core::engine::run_quietly;
use grainpipe_core::pipeline::PipelineDoc;
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{
    ColumnData, ContactGraph, Outputs, Packing, Registry, RunContext, StageError, Table, TypedStage,
};
use std::f64::consts::PI;

/// Geometric tolerance of the filler is 1e-9 mean radii (exact tangency is accepted); we
/// allow 1e-8 for round-off accumulated through reflections and translations.
const OVERLAP_TOL: f64 = 1e-8;

/// Preflight and run, and, as the engine does, hold every output to its announcement.
fn run<T: TypedStage>(stage: &T, p: &T::Params) -> Result<Outputs, StageError> {
    let rep = SilentReporter;
    let pf = stage.preflight(p, &Default::default())?;
    let o = stage.run(p, &pf.plan, &Default::default(), &RunContext::new(7, &rep))?;
    for (port, meta) in &pf.outputs {
        meta.check(&o[port])
            .unwrap_or_else(|e| panic!("{port}: {e}"));
    }
    Ok(o)
}

fn parts(o: &Outputs) -> (&Packing, &ContactGraph, &Table) {
    (
        o["packing"].as_packing().unwrap(),
        o["contacts"].as_contact_graph().unwrap(),
        o["report"].as_table().unwrap(),
    )
}

fn val(t: &Table, name: &str) -> f64 {
    match &t.column(name).unwrap_or_else(|| panic!("{name}")).data {
        ColumnData::F64(v) => v[0],
        ColumnData::I64(v) => v[0] as f64,
        ColumnData::Str(_) => panic!(),
    }
}

fn spheres(p: &Packing) -> Vec<([f64; 3], f64)> {
    p.world_spheres()
        .iter()
        .map(|s| (s.center, s.radius))
        .collect()
}

fn gap(a: &([f64; 3], f64), b: &([f64; 3], f64)) -> f64 {
    let d: f64 = (0..3).map(|k| (a.0[k] - b.0[k]).powi(2)).sum();
    d.sqrt() - a.1 - b.1
}

/// Brute force over all pairs: no overlap beyond the tolerance, every recorded contact has
/// the recorded gap and is within the contact distance, and no touching pair is missing.
fn check_pairs(p: &Packing, g: &ContactGraph, rmean: f64, contact_parameter: f64) {
    let s = spheres(p);
    // The graph carries each sphere's own centre and radius, so it can be glyphed alone.
    assert_eq!(g.positions.len(), s.len());
    for (k, (c, r)) in s.iter().enumerate() {
        assert_eq!((g.positions[k], g.radii[k]), (*c, *r), "body {k}");
    }
    let max_gap = contact_parameter * rmean;
    let mut expected = 0usize;
    for i in 0..s.len() {
        for j in i + 1..s.len() {
            let d = gap(&s[i], &s[j]);
            assert!(
                d > -OVERLAP_TOL * rmean,
                "spheres {i} and {j} overlap by {}",
                -d
            );
            if d <= max_gap {
                expected += 1;
            }
        }
    }
    for c in &g.contacts {
        let d = gap(&s[c.i], &s[c.j]);
        assert!((d - c.gap).abs() <= 1e-12 * rmean, "recorded gap differs");
        assert!(
            d <= max_gap,
            "contact {}-{} has gap {d} > {max_gap}",
            c.i,
            c.j
        );
    }
    assert_eq!(g.contacts.len(), expected, "contact list incomplete");
    assert_eq!(g.positions.len(), s.len());
}

#[test]
fn registry_is_consistent() {
    let mut r = Registry::new();
    grainpipe_bricks::register(&mut r);
    r.check_consistency().unwrap();
    assert!(r.stage("bricks.method1").is_some());
    assert!(r.stage("bricks.method2").is_some());
    assert!(r.stage("bricks.curved").is_some());
    // One declaration of the shared parameters, flattened into each stage with its own
    // defaults (the paper's examples 1A, 2 and 3A).
    let default = |id: &str, name: &str| {
        let info = r.stage(id).unwrap().stage.info().clone();
        info.params
            .iter()
            .find(|p| p.name == name)
            .map(|p| p.default.clone())
    };
    assert_eq!(default("bricks.method1", "face_goal"), Some(0.8.into()));
    assert_eq!(default("bricks.method2", "face_goal"), Some(1.0.into()));
    assert_eq!(default("bricks.curved", "face_goal"), Some(0.4.into()));
    assert_eq!(
        default("bricks.method2", "require_goals"),
        Some(false.into())
    );
    assert_eq!(default("bricks.curved", "brick_numbers"), None);
    // Params arrive as JSON from YAML: units in strings, typos refused with the key named.
    let st = &r.stage("bricks.method2").unwrap().stage;
    let v = st
        .normalize_params(&serde_json::json!({
            "radius": {"kind": "weibull", "scale": "15.7 um", "shape": 3.55},
            "brick_sides": [1, 1, 0.12], "brick_numbers": [6, 6, 1]
        }))
        .unwrap();
    assert!((v["radius"]["scale"].as_f64().unwrap() - 15.7e-6).abs() < 1e-18);
    let e = st
        .normalize_params(&serde_json::json!({"face_gaol": 1.0}))
        .unwrap_err();
    assert!(
        matches!(e, StageError::UnknownParam { ref key, ref suggestion }
            if key == "face_gaol" && suggestion.as_deref() == Some("face_goal")),
        "{e}"
    );
}

#[test]
fn preflight_names_the_bad_parameter() {
    let e = Method1
        .preflight(
            &Method1Params {
                common: BrickParams {
                    face_goal: 1.5,
                    ..BrickParams::method1_defaults()
                },
                ..Default::default()
            },
            &Default::default(),
        )
        .unwrap_err();
    assert!(matches!(e, StageError::InvalidParam { ref key, .. } if key == "face_goal"));
    let e = Method1
        .preflight(
            &Method1Params {
                common: BrickParams {
                    radius: SizeDistribution::Weibull {
                        scale: grainpipe_core::units::Q::new(15.7e-6),
                        shape: -1.0,
                        min: None,
                        max: None,
                    },
                    ..BrickParams::method1_defaults()
                },
                ..Default::default()
            },
            &Default::default(),
        )
        .unwrap_err();
    assert!(matches!(e, StageError::InvalidParam { ref key, .. } if key == "radius.shape"));
    // A brick of 3 mean radii cannot hold two corner spheres of radius r_mean with room.
    let e = Method1
        .preflight(
            &Method1Params {
                common: BrickParams {
                    std_length: 3.0,
                    ..BrickParams::method1_defaults()
                },
                ..Default::default()
            },
            &Default::default(),
        )
        .unwrap_err();
    assert!(matches!(e, StageError::InvalidParam { ref key, .. } if key == "brick_sides"));
}

#[test]
fn method1_example_1a_meets_goals_without_overlap() {
    let p = Method1Params::default(); // Example 1A: 15 r_mean cube, 2 x 2 x 1 bricks
    let o = run(&Method1, &p).unwrap();
    let (pk, g, t) = parts(&o);
    let rmean = val(t, "mean_radius_target");
    // Paper eq. (2.3)-(2.4): mean radius 14.137 um.
    assert!((rmean / 14.1367e-6 - 1.0).abs() < 1e-4);
    check_pairs(pk, g, rmean, p.common.contact_parameter);
    let n_unit = val(t, "spheres_unit_brick") as usize;
    assert_eq!(
        pk.bodies.len(),
        4 * n_unit,
        "reflection copies every sphere"
    );
    // Goals: recompute the body fraction of the unit brick independently.
    let l = 15.0 * rmean;
    let unit: f64 = spheres(pk)[..n_unit]
        .iter()
        .map(|s| 4.0 / 3.0 * PI * s.1.powi(3))
        .sum::<f64>()
        / l.powi(3);
    assert!(unit >= 0.55, "body fraction {unit}");
    assert!((unit - val(t, "body_fraction")).abs() < 1e-12);
    assert!(val(t, "face_fraction_min") >= 0.8);
    assert_eq!(val(t, "goals_reached"), 1.0);
    // Every sphere lies inside the total domain, and the face lists are exactly the spheres
    // within the contact distance of each face (the paper's ListXmin .. ListZmax).
    let size = pk.domain.max;
    let tol = p.common.contact_parameter * rmean;
    for (i, s) in spheres(pk).iter().enumerate() {
        for a in 0..3 {
            assert!(
                s.0[a] - s.1 > -OVERLAP_TOL * rmean && s.0[a] + s.1 < size[a] + OVERLAP_TOL * rmean
            );
        }
        for f in 0..6 {
            let a = f / 2;
            let d = if f % 2 == 0 {
                s.0[a] - s.1
            } else {
                size[a] - s.0[a] - s.1
            };
            assert_eq!(g.faces[f].contains(&i), d <= tol, "face {f} sphere {i}");
        }
    }
    // Face spheres touch their own mirror image across the shared faces x = L and y = L.
    let s = spheres(pk);
    let mirrored = g
        .contacts
        .iter()
        .filter(|c| {
            c.gap.abs() < OVERLAP_TOL * rmean
                && (s[c.i].1 - s[c.j].1).abs() < 1e-15
                && ((s[c.i].0[0] + s[c.j].0[0] - 2.0 * l).abs() < 1e-9 * l
                    || (s[c.i].0[1] + s[c.j].0[1] - 2.0 * l).abs() < 1e-9 * l)
        })
        .count();
    assert!(mirrored > 0, "no mirror contacts across the shared faces");
}

#[test]
fn method1_example_1b_ks_distance_is_bounded() {
    // Example 1B: 30 r_mean cube. Drawn radii are the target law conditioned on acceptance.
    // If a fraction q of draws is rejected, the accepted law F_a satisfies
    // |F_a - F| <= q / (1 - q) for any acceptance rule (0 <= acceptance <= 1), so the sample
    // KS distance is below q/(1-q) plus the sampling bound 1.95/sqrt(n) (alpha = 0.001).
    let p = Method1Params {
        common: BrickParams {
            std_length: 30.0,
            contact_parameter: 0.1,
            ..BrickParams::method1_defaults()
        },
        ..Default::default()
    };
    let o = run(&Method1, &p).unwrap();
    let (_, _, t) = parts(&o);
    let q = val(t, "rejected_draws") / val(t, "draws");
    let n = val(t, "ks_samples") as usize;
    let ks = val(t, "ks_distance");
    let bound = q / (1.0 - q) + ks_critical_value(n, 0.001);
    assert!(ks < bound, "KS {ks} >= bound {bound} (q {q}, n {n})");
    // The paper's Table 1: N = 3075 spheres in the unit cube; ours within 15 %.
    let nu = val(t, "spheres_unit_brick");
    assert!((nu / 3075.0 - 1.0).abs() < 0.15, "N = {nu}");
    assert_eq!(val(t, "goals_reached"), 1.0);
}

#[test]
fn method2_tiles_seamlessly() {
    let p = Method2Params {
        common: BrickParams {
            std_length: 15.0,
            ..BrickParams::method2_defaults()
        },
        ..Default::default()
    };
    let o = run(&Method2, &p).unwrap();
    let (pk, g, t) = parts(&o);
    let rmean = val(t, "mean_radius_target");
    check_pairs(pk, g, rmean, p.common.contact_parameter);
    let s = spheres(pk);
    let size = pk.domain.max;
    let key = |i: usize, drop: usize| {
        let c = s[i].0;
        let mut k: Vec<i64> = (0..3)
            .filter(|&a| a != drop)
            .map(|a| (c[a] / rmean * 1e6).round() as i64)
            .collect();
        k.push((s[i].1 / rmean * 1e9).round() as i64);
        k
    };
    for a in 0..3 {
        assert!(!g.faces[2 * a].is_empty());
        // Sphere centres lie on the face planes (Method 2).
        for &i in &g.faces[2 * a] {
            assert!(s[i].0[a].abs() < 1e-12 * size[a]);
        }
        for &i in &g.faces[2 * a + 1] {
            assert!((s[i].0[a] - size[a]).abs() < 1e-9 * size[a]);
        }
        // Opposite faces carry identical sphere sets (same in-plane centres and radii).
        let mut lo: Vec<_> = g.faces[2 * a].iter().map(|&i| key(i, a)).collect();
        let mut hi: Vec<_> = g.faces[2 * a + 1].iter().map(|&i| key(i, a)).collect();
        lo.sort();
        hi.sort();
        assert_eq!(lo, hi, "faces {} / {} differ", 2 * a, 2 * a + 1);
    }
    // Saturated fill (the paper's goals 1.0 / 0.9 are beyond reach): the report says so.
    assert_eq!(val(t, "goals_reached"), 0.0);
    assert!(val(t, "body_fraction") > 0.5 && val(t, "body_fraction") < 0.9);
}

#[test]
fn same_seed_same_bed_on_any_thread_count() {
    let p = Method2Params {
        common: BrickParams {
            std_length: 15.0,
            brick_sides: [1.0, 1.0, 0.24],
            ..BrickParams::method2_defaults()
        },
        brick_numbers: [3, 3, 1],
    };
    let go = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| run(&Method2, &p).unwrap())
    };
    let (a, b) = (go(1), go(2));
    assert_eq!(a["packing"], b["packing"]);
    assert_eq!(a["contacts"], b["contacts"]);
    assert_eq!(a["report"], b["report"]);
}

#[test]
fn impossible_goal_fails_clearly() {
    // Random packings of unequal spheres stay far below 0.95 (the FCC lattice is 0.74).
    let p = Method1Params {
        common: BrickParams {
            body_goal: 0.95,
            ..BrickParams::method1_defaults()
        },
        ..Default::default()
    };
    let e = run(&Method1, &p).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, StageError::Failed(_)));
    assert!(
        msg.contains("body fraction reached") && msg.contains("draws"),
        "{msg}"
    );
    // The reached fraction is stated and lies below the goal.
    let reached: f64 = msg
        .split("reached ")
        .nth(1)
        .and_then(|t| t.split_whitespace().next())
        .and_then(|x| x.parse().ok())
        .unwrap();
    assert!(reached > 0.5 && reached < 0.95, "{reached}");
}

#[test]
fn curved_example_3a_stays_in_the_domain() {
    let p = CurvedParams::default();
    let o = run(&Curved, &p).unwrap();
    let (pk, g, t) = parts(&o);
    let rmean = val(t, "mean_radius_target");
    check_pairs(pk, g, rmean, p.common.contact_parameter);
    let l = 30.0 * rmean;
    let hr = 0.5 * l;
    // Domain volume: cube minus two hemispheres, 1 - pi/6 of the cube (midpoint rule on 160^3
    // cells, error < 1e-3).
    let v = val(t, "domain_volume_unit") / l.powi(3);
    assert!((v - (1.0 - PI / 6.0)).abs() < 1e-3, "{v}");
    for s in spheres(pk) {
        for a in 0..3 {
            assert!(s.0[a] - s.1 > -OVERLAP_TOL * rmean && s.0[a] + s.1 < l + OVERLAP_TOL * rmean);
        }
        for x in [0.0, l] {
            let d =
                ((s.0[0] - x).powi(2) + (s.0[1] - 0.5 * l).powi(2) + (s.0[2] - 0.5 * l).powi(2))
                    .sqrt();
            assert!(
                d >= hr + s.1 - OVERLAP_TOL * rmean,
                "sphere in a hemisphere"
            );
        }
    }
    assert!(val(t, "body_fraction") >= 0.4);
    for f in ["ymin", "ymax", "zmin", "zmax"] {
        assert!(val(t, &format!("face_fraction_{f}")) >= 0.4);
    }
    // The report's KS distance is the one of the drawn radii (corner spheres have the mean
    // radius and are excluded): recompute it from the packing.
    let drawn: Vec<f64> = spheres(pk)
        .iter()
        .map(|s| s.1)
        .filter(|r| *r != rmean)
        .collect();
    let ks = ks_distance(&drawn, &p.common.radius);
    assert!((ks - val(t, "ks_distance")).abs() < 1e-12, "{ks}");
}

#[test]
fn powderbed_pipeline_builds_the_paper_bed() {
    // pipelines/powderbed.yaml, step `bed` alone (the rest needs other crates' stages and
    // exporters), planned and run by the engine, which checks the announced metadata.
    let root = grainpipe_core::testing::workspace_root(env!("CARGO_MANIFEST_DIR"));
    let mut doc = PipelineDoc::load(&root.join("pipelines/powderbed.yaml")).unwrap();
    doc.steps.retain(|s| s.id == "bed");
    doc.exports.clear();
    assert_eq!(doc.steps[0].uses, "bricks.method2");
    let mut r = Registry::new();
    grainpipe_bricks::register(&mut r);
    let res = run_quietly(&doc, &r).unwrap();
    let pk = res.artifact("bed.packing").as_packing().unwrap();
    let g = res.artifact("bed.contacts").as_contact_graph().unwrap();
    let t = res.table("bed.report");
    // Paper section 5.2: "a domain of size ~ 2545 x 2545 x 50.89 um" = 6 x 30 r_mean and
    // 0.12 x 30 r_mean with r_mean = 14.137 um (4 significant digits quoted).
    let size = pk.domain.max;
    assert!((size[0] / 2545e-6 - 1.0).abs() < 5e-4 && (size[1] - size[0]).abs() < 1e-15);
    assert!((size[2] / 50.89e-6 - 1.0).abs() < 5e-4, "{size:?}");
    // The 36 bricks share their faces: the top and bottom faces carry equal sets.
    assert_eq!(g.faces[4].len(), g.faces[5].len());
    assert_eq!(val(t, "spheres_total") as usize, pk.bodies.len());
    check_pairs(pk, g, val(t, "mean_radius_target"), 0.1);
}

#[test]
fn curved_domain_takes_any_cut_out_ball() {
    // The signed-distance mechanism: no hemispheres, one ball of radius 0.3 L in the centre.
    let rmean = SizeDistribution::default().mean();
    let l = 20.0 * rmean;
    let q = grainpipe_core::units::Q::new;
    let p = CurvedParams {
        common: BrickParams {
            std_length: 20.0,
            ..BrickParams::curved_defaults()
        },
        hemisphere_radii: [0.0, 0.0],
        excluded_spheres: vec![grainpipe_bricks::stages::ExcludedSphere {
            center: [q(0.5 * l), q(0.5 * l), q(0.5 * l)],
            radius: q(0.3 * l),
        }],
        filled_faces: vec!["zmin".into()],
    };
    let o = run(&Curved, &p).unwrap();
    let (pk, g, t) = parts(&o);
    check_pairs(pk, g, rmean, p.common.contact_parameter);
    for s in spheres(pk) {
        let d = ((0..3).map(|a| (s.0[a] - 0.5 * l).powi(2)).sum::<f64>()).sqrt();
        assert!(
            d >= 0.3 * l + s.1 - OVERLAP_TOL * rmean,
            "sphere inside the cut-out ball"
        );
    }
    // Domain volume L^3 - (4/3) pi (0.3 L)^3 (midpoint rule, error < 1e-3 of L^3).
    let v = val(t, "domain_volume_unit") / l.powi(3);
    assert!((v - (1.0 - 4.0 / 3.0 * PI * 0.027)).abs() < 1e-3, "{v}");
    assert!(val(t, "face_fraction_zmin") >= 0.4 && val(t, "body_fraction") >= 0.4);
    assert_eq!(pk.domain.excluded.len(), 1);
}

#[test]
fn a_sample_failing_its_ks_test_is_explained_in_a_warning() {
    // Example 1A rejects large draws that no longer fit, which biases the radii: the
    // report's own KS columns decide whether a warning is due, and the warning must give
    // the reason and the mean shift the report's mean columns show.
    let p = Method1Params::default();
    let log = grainpipe_core::testing::WarningLog::default();
    let pf = Method1.preflight(&p, &Default::default()).unwrap();
    let o = Method1
        .run(&p, &pf.plan, &Default::default(), &RunContext::new(7, &log))
        .unwrap();
    let (_, _, t) = parts(&o);
    let (ks, critical) = (val(t, "ks_distance"), val(t, "ks_critical_0_05"));
    let warnings = log.warnings();
    let ks_warnings: Vec<&String> = warnings
        .iter()
        .filter(|w| w.contains("Kolmogorov-Smirnov"))
        .collect();
    if ks <= critical {
        assert!(ks_warnings.is_empty(), "{warnings:?}");
        return;
    }
    assert_eq!(ks_warnings.len(), 1, "{warnings:?}");
    let w = ks_warnings[0];
    assert!(
        w.contains(&format!("{ks:.3}")) && w.contains(&format!("{critical:.3}")),
        "{w}"
    );
    let rejected = val(t, "rejected_draws");
    assert!(rejected > 0.0 && w.contains("rejected"), "{w}");
    let law_mean = p.common.radius.mean();
    let drawn_mean = val(t, "mean_radius_drawn");
    assert!(
        w.contains(&format!(
            "({:+.1} %)",
            100.0 * (drawn_mean / law_mean - 1.0)
        )),
        "{w}"
    );
}
