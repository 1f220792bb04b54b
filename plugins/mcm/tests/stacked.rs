mod common;
use common::*;
use grainpipe_mcm::stages::{Classic, Stacked};
use serde_json::json;

/// An integer column of the stage's report, one value per layer.
fn report_i64(out: &grainpipe_core::Outputs, name: &str) -> Vec<i64> {
    match &out["report"].as_table().unwrap().column(name).unwrap().data {
        grainpipe_core::ColumnData::I64(v) => v.clone(),
        _ => panic!("report column `{name}` is not an integer column"),
    }
}

/// Every centroid lies in its own layer of thickness `t` (the soft box of Remark 4).
fn assert_centroids_in_layers(p: &grainpipe_core::Packing, t: f64, what: &str) {
    for b in &p.bodies {
        let z = b.position[2];
        assert!(
            z >= b.layer as f64 * t && z <= (b.layer + 1) as f64 * t,
            "{what}: centroid z = {z} outside layer {}",
            b.layer
        );
    }
}

fn spheres(layers: usize, seed: u64) -> grainpipe_core::Outputs {
    run(
        &Stacked,
        json!({"layers": layers, "layer_size": ["400 um", "400 um"], "layer_thickness": "200 um",
               "volume_fraction": 0.45, "min_gap": "2 um",
               "radius": {"kind": "uniform", "min": "35 um", "max": "60 um"}}),
        None,
        seed,
    )
    .unwrap()
}

#[test]
fn layers_are_frozen_filled_exactly_and_overlap_free() {
    let one = spheres(1, 5);
    let two = spheres(2, 5);
    let (p1, p2) = (packing(&one), packing(&two));
    // Layer 0 is generated identically in both runs; in the two-layer run it is frozen while
    // layer 1 is packed on it (layer 1 never got stuck, so no grain of layer 0 was released),
    // so its bodies must be bit-identical.
    assert_eq!(report_i64(&two, "released"), vec![0, 0]);
    let l0: Vec<_> = p2.bodies.iter().filter(|b| b.layer == 0).cloned().collect();
    assert_eq!(l0, p1.bodies);
    let t = 200e-6;
    let per_layer = 0.45 * 400e-6 * 400e-6 * t;
    assert_centroids_in_layers(p2, t, "two layers");
    for layer in 0..2u32 {
        let bodies: Vec<_> = p2.bodies.iter().filter(|b| b.layer == layer).collect();
        assert!(!bodies.is_empty());
        // Remark 1: the grains of each layer are rescaled to exactly eta V_layer.
        let v: f64 = bodies.iter().map(|b| p2.body_volume(b)).sum();
        assert!(
            (v / per_layer - 1.0).abs() < 1e-9,
            "layer {layer}: {}",
            v / per_layer
        );
    }
    let rep = two["report"].as_table().unwrap();
    for f in rep.f64_column("fraction").unwrap() {
        assert!((f - 0.45).abs() < 1e-9);
    }
    let g = min_surface_gap(p2);
    assert!(g >= 2e-6 - 1e-12, "gap {g}");
}

fn nzz(out: &grainpipe_core::Outputs) -> f64 {
    out["orientation"].as_tensor().unwrap().values[8]
}

#[test]
fn stacked_packings_of_rods_lie_flat_classic_ones_do_not() {
    let lib = rods();
    let (mut s, mut c) = (0.0, 0.0);
    let seeds = [1u64, 2, 3, 4, 5, 6];
    for &seed in &seeds {
        let st = run(
            &Stacked,
            json!({"layers": 2, "layer_size": ["600 um", "600 um"], "layer_thickness": "200 um",
                   "volume_fraction": 0.45, "beta": 8.0, "min_gap": 0.0}),
            Some(&lib),
            seed,
        )
        .unwrap();
        let cl = run(
            &Classic,
            json!({"count": 120, "volume_fraction": 0.45}),
            Some(&lib),
            seed,
        )
        .unwrap();
        println!(
            "seed {seed}: stacked nzz {:.3}, classic nzz {:.3}, {} grains",
            nzz(&st),
            nzz(&cl),
            packing(&st).bodies.len()
        );
        s += nzz(&st);
        c += nzz(&cl);
        // The tensor's trace is 1 (unit axes).
        let t = &st["orientation"].as_tensor().unwrap().values;
        assert!((t[0] + t[4] + t[8] - 1.0).abs() < 1e-9);
    }
    s /= seeds.len() as f64;
    c /= seeds.len() as f64;
    // Isotropic axes: <n_z^2> = 1/3 with standard deviation sqrt(4/45 / N): N = 720 classic
    // axes (120 x 6) -> 0.011, N ~ 425 stacked axes -> 0.015. Classic must be isotropic within
    // 0.04 (3.6 sd); stacked must lie 0.05 (3.4 sd) below 1/3 and 0.05 below classic.
    // Measured: stacked 0.251, classic 0.336.
    assert!((c - 1.0 / 3.0).abs() < 0.04, "classic nzz = {c}");
    assert!(s < 1.0 / 3.0 - 0.05, "stacked nzz = {s}");
    assert!(c - s > 0.05, "classic {c} vs stacked {s}");
}

#[test]
fn same_seed_same_stacked_packing_under_1_and_2_threads() {
    let go = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| packing(&spheres(2, 9)).clone())
    };
    assert_eq!(go(1), go(2));
}

#[test]
fn free_surface_layers_with_the_papers_gap_pack_without_overlap() {
    // The paper's setting (50 %, 8 um gap, 280 um layers, D50 = 140 um) with a free surface
    // above each new layer: x-y periodic only.
    let out = run(
        &Stacked,
        json!({"layers": 2, "layer_size": ["560 um", "560 um"], "layer_thickness": "280 um",
               "volume_fraction": 0.5, "min_gap": "8 um", "periodic_z": false,
               "radius": {"kind": "lognormal", "median": "70 um", "sigma": 0.2, "min": "40 um", "max": "120 um"}}),
        None,
        3,
    )
    .unwrap();
    let p = packing(&out);
    assert_eq!(p.domain.periodic, [true, true, false]);
    let g = min_surface_gap(p);
    assert!(g >= 8e-6 - 1e-12, "gap {g}");
    let t = 280e-6;
    assert_centroids_in_layers(p, t, "free surface");
    // Remark 1: 0.5 of each layer's volume, exactly.
    let v = 0.5 * 560e-6 * 560e-6 * 2.0 * t;
    assert!((p.solid_volume() / v - 1.0).abs() < 1e-9);
}

/// Issue 20: `min_gap: 300 um` (more than half the 560 um cell) was accepted at preflight and
/// failed after 8-15 minutes.
#[test]
fn a_gap_larger_than_half_the_cell_is_refused_at_preflight() {
    for (gap, key) in [(300e-6, "min_gap"), (8.0, "min_gap"), (150e-6, "min_gap")] {
        let t0 = std::time::Instant::now();
        match run(&Stacked, json!({"min_gap": gap}), None, 1) {
            Err(grainpipe_core::StageError::InvalidParam { key: k, message }) => {
                assert_eq!(k, key, "{message}");
                assert!(message.contains("um"), "{message}");
            }
            other => panic!(
                "min_gap {gap}: expected InvalidParam, got {:?}",
                other.map(|_| ())
            ),
        }
        assert!(t0.elapsed().as_secs_f64() < 2.0);
    }
}

/// Issue 20: `layer_thickness: 100 um` with grains wider than the layer failed after 76 s
/// naming "grains 5 and 5" (a grain touching its own z image). Spheres from `radius` are
/// refused at preflight; clumps (sizes known only when drawn) before anything is placed,
/// naming the grain's thinnest width and what to change.
#[test]
fn grains_thicker_than_a_periodic_layer_are_refused_fast() {
    let e = run(
        &Stacked,
        json!({"layer_thickness": "100 um", "radius": {"kind": "fixed", "value": "70 um"}}),
        None,
        1,
    )
    .unwrap_err();
    let grainpipe_core::StageError::InvalidParam { key, message } = &e else {
        panic!("{e}")
    };
    assert_eq!(key, "layer_thickness", "{message}");
    // Rods of radius 40-50 um (thinnest width 80-100 um) in 90 um layers with a 2 um gap: the
    // 45 and 50 um rods cannot lie flat in the layer.
    let t0 = std::time::Instant::now();
    let e = run(
        &Stacked,
        json!({"layer_thickness": "90 um", "layer_size": ["600 um", "600 um"], "min_gap": "2 um"}),
        Some(&rods()),
        1,
    )
    .unwrap_err();
    assert!(t0.elapsed().as_secs_f64() < 2.0);
    let grainpipe_core::StageError::InvalidParam { key, message } = &e else {
        panic!("{e}")
    };
    assert_eq!(key, "layer_thickness");
    // The 50 um rod is 100 um thick at its thinnest (within the sampling slack).
    assert!(message.contains("thick at its thinnest"), "{message}");
    // The same rods in a free-surface layer are not concerned.
    let p: grainpipe_mcm::stages::StackedParams = serde_json::from_value(
        json!({"layer_thickness": "90 um", "layer_size": ["600 um", "600 um"], "min_gap": "2 um", "periodic_z": false, "layers": 1, "volume_fraction": 0.3}),
    )
    .unwrap();
    grainpipe_core::TypedStage::preflight(&Stacked, &p, &grainpipe_core::InputMetas::new())
        .unwrap();
}

/// Issue 20: a layer contracted between the rigid top of the layer below and, with
/// `periodic_z`, the rigid bottom of layer 0's image above jammed long before its own jamming
/// density. Spheres at 50 % with the paper's 8 um gap in 280 um layers (the gap pads a 40 um
/// sphere's volume by a third) got stuck on the first try of every layer above the first; at
/// the first stuck step the earlier grains within reach are released (each kept in its own
/// layer's soft box) and the layer packs on its first try. The packing stays valid: gap over
/// every periodic image, centroids in their layers, exact volumes.
#[test]
fn a_jammed_layer_releases_the_grains_it_touches_and_stays_layered() {
    let mut released = 0;
    for seed in 0..3 {
        let out = run(
            &Stacked,
            json!({"layers": 3, "layer_size": ["560 um", "560 um"], "layer_thickness": "280 um",
                   "volume_fraction": 0.5, "min_gap": "8 um",
                   "radius": {"kind": "lognormal", "median": "70 um", "sigma": 0.4, "min": "40 um", "max": "130 um"}}),
            None,
            seed,
        )
        .unwrap();
        let per_layer = report_i64(&out, "released");
        released += per_layer.iter().sum::<i64>();
        assert_eq!(per_layer[0], 0, "layer 0 has no earlier layer to release");
        let p = packing(&out);
        let g = min_surface_gap(p);
        assert!(g >= 8e-6 - 1e-12, "seed {seed}: gap {g}");
        let t = 280e-6;
        assert_centroids_in_layers(p, t, &format!("seed {seed}"));
        let v = 0.5 * 560e-6 * 560e-6 * 3.0 * t;
        assert!((p.solid_volume() / v - 1.0).abs() < 1e-9);
    }
    assert!(
        released > 0,
        "no layer jammed: the case no longer tests the release"
    );
}
