//! pipelines/clumps.yaml through the engine with a registry holding this crate and the
//! formats crate: every real grain of data/sand-grains becomes a connected clump at
//! alpha = 0.9, and the exports are written.

use grainpipe_core::testing::{run_pipeline, workspace_root};
use grainpipe_core::{ColumnData, Registry};

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_clumps::register(&mut r);
    r
}

#[test]
fn registry_is_consistent() {
    registry().check_consistency().unwrap();
}

#[test]
fn real_grains_become_connected_clumps_at_alpha_0_9() {
    let root = workspace_root(env!("CARGO_MANIFEST_DIR"));
    let out = tempfile::tempdir().unwrap();
    let res = run_pipeline(&registry(), &root, "clumps.yaml", &[], out.path()).unwrap();
    let report = res.outputs["clumps"]["report"].as_table().unwrap().clone();
    let cov = report.f64_column("coverage").unwrap();
    let ColumnData::I64(spheres) = &report.column("spheres").unwrap().data else {
        panic!()
    };
    let ColumnData::I64(conn) = &report.column("connected").unwrap().data else {
        panic!()
    };
    let ColumnData::Str(src) = &report.column("source").unwrap().data else {
        panic!()
    };
    // All 30 files of data/sand-grains (README: 30 grains), none dropped.
    assert_eq!(cov.len(), 30);
    for k in 0..cov.len() {
        println!("{}: {} spheres, coverage {:.4}", src[k], spheres[k], cov[k]);
        assert!(cov[k] >= 0.9, "{}: coverage {}", src[k], cov[k]);
        assert_eq!(conn[k], 1, "{} not connected", src[k]);
    }
    let mean = spheres.iter().sum::<i64>() as f64 / spheres.len() as f64;
    println!("mean spheres per grain: {mean:.1}");
    // The grains were rescaled to median d_eq = 140 um: the summary's D50 must say so
    // (the median of 30 values is the mean of the 15th and 16th: exact up to voxelization,
    // 2 % = 3 voxel-volume fractions of a 35-voxel grain's d_eq).
    let summary = res.outputs["grains"]["summary"].as_table().unwrap();
    let d50 = summary.f64_column("d_eq").unwrap()[1];
    assert!((d50 / 140e-6 - 1.0).abs() < 0.02, "D50 = {d50}");
    for f in [
        "library.h5",
        "library.json",
        "library.csv",
        "library.vtp",
        "report.csv",
        "grains.h5",
    ] {
        assert!(
            out.path().join("clumps").join(f).is_file(),
            "{f} not written"
        );
    }
    let lib =
        grainpipe_formats::read_h5_clump_library(&out.path().join("clumps/library.h5")).unwrap();
    assert_eq!(lib.clumps.len(), 20);
}

#[test]
fn preflight_refuses_impossible_parameters_and_missing_inputs() {
    use grainpipe_core::model::ArtifactMeta;
    use grainpipe_core::stage::InputMetas;
    use grainpipe_core::{ArtifactKind, StageError};
    let reg = registry();
    let pf = |id: &str, params: serde_json::Value, inputs: &InputMetas| {
        reg.stage(id).unwrap().stage.preflight(&params, inputs)
    };
    let mut series = InputMetas::new();
    series.insert("grains".into(), ArtifactMeta::of(ArtifactKind::Collection));
    assert!(pf("clumps.garcia", serde_json::json!({}), &series).is_ok());
    for (id, params, key) in [
        ("clumps.garcia", serde_json::json!({"alpha": 1.5}), "alpha"),
        (
            "clumps.library",
            serde_json::json!({"sampling": "halton"}),
            "sampling",
        ),
        (
            "clumps.library",
            serde_json::json!({"scale": -1.0}),
            "scale",
        ),
        (
            "grains.synthetic",
            serde_json::json!({"length_to_thickness": 0.5}),
            "length_to_thickness",
        ),
        (
            "grains.from_harmonics",
            serde_json::json!({"directory": "/nonexistent"}),
            "directory",
        ),
        ("grains.from_meshes", serde_json::json!({}), "files"),
    ] {
        match pf(id, params, &series) {
            Err(StageError::InvalidParam { key: k, .. }) => assert_eq!(k, key, "{id}"),
            other => panic!("{id}: expected InvalidParam {key}, got {other:?}"),
        }
    }
    assert!(matches!(
        pf(
            "grains.from_labels",
            serde_json::json!({}),
            &InputMetas::new()
        ),
        Err(StageError::InvalidInput { .. })
    ));
}

#[test]
fn from_labels_takes_a_field_for_more_than_255_grains() {
    use grainpipe_core::stage::{RunContext, SilentReporter};
    use grainpipe_core::{Artifact, Field, FieldData, Grid, Inputs};
    // Three 4x4x4 cubes with ids 1000, 1001, 1002 inside a 16^3 field (none touches a face).
    let dims = [16, 16, 16];
    let mut v = vec![0.0f64; 4096];
    for (k, x0) in [1usize, 6, 11].into_iter().enumerate() {
        for z in 6..10 {
            for y in 6..10 {
                for x in x0..x0 + 4 {
                    v[x + 16 * (y + 16 * z)] = 1000.0 + k as f64;
                }
            }
        }
    }
    let field = Field {
        grid: Grid {
            dims,
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
        name: "labels".into(),
        unit: "".into(),
        convention: grainpipe_core::ComponentConvention::Plain,
        components: 1,
        data: FieldData::F64(v),
    };
    let mut metas = grainpipe_core::InputMetas::new();
    metas.insert(
        "field".into(),
        grainpipe_core::ArtifactMeta::on_grid(
            grainpipe_core::ArtifactKind::Field,
            field.grid.clone(),
        ),
    );
    let mut inp = Inputs::new();
    inp.insert("field".into(), std::sync::Arc::new(Artifact::Field(field)));
    let reg = registry();
    let st = &reg.stage("grains.from_labels").unwrap().stage;
    let params = serde_json::json!({});
    let (_, prepared) = st.preflight(&params, &metas).unwrap();
    let out = st
        .run(
            &params,
            &prepared,
            &inp,
            &RunContext::new(1, &SilentReporter),
        )
        .unwrap();
    let t = out["stats"].as_table().unwrap();
    // 64 voxels of 1 um^3 each; d_eq = (6 * 64 / pi)^(1/3) um.
    let vol = t.f64_column("volume").unwrap();
    assert_eq!(vol.len(), 3);
    assert!(
        vol.iter().all(|v| (v / 64e-18 - 1.0).abs() < 1e-12),
        "{vol:?}"
    );
    let d = (6.0 * 64.0 / std::f64::consts::PI).cbrt() * 1e-6;
    assert!(t
        .f64_column("d_eq")
        .unwrap()
        .iter()
        .all(|x| (x - d).abs() < 1e-15));
    let ColumnData::Str(src) = &t.column("source").unwrap().data else {
        panic!()
    };
    assert_eq!(src, &["label 1000", "label 1001", "label 1002"]);
}

#[test]
fn from_meshes_stage_scales_by_mesh_unit() {
    use grainpipe_core::stage::{RunContext, SilentReporter};
    use grainpipe_core::Inputs;
    // A 2 x 1 x 0.5 box in mm, voxels of 50 um aligned with its faces: exactly 1 mm^3.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("box.obj");
    std::fs::write(
        &path,
        "v 0 0 0\nv 2 0 0\nv 2 1 0\nv 0 1 0\nv 0 0 0.5\nv 2 0 0.5\nv 2 1 0.5\nv 0 1 0.5\n\
         f 1 4 3 2\nf 5 6 7 8\nf 1 2 6 5\nf 2 3 7 6\nf 3 4 8 7\nf 4 1 5 8\n",
    )
    .unwrap();
    let reg = registry();
    let st = &reg.stage("grains.from_meshes").unwrap().stage;
    let params = serde_json::json!({"files": [path.to_str().unwrap()], "voxel_size": "50 um", "mesh_unit": "1 mm"});
    let (_, prepared) = st.preflight(&params, &Default::default()).unwrap();
    let out = st
        .run(
            &params,
            &prepared,
            &Inputs::new(),
            &RunContext::new(1, &SilentReporter),
        )
        .unwrap();
    let t = out["stats"].as_table().unwrap();
    let v = t.f64_column("volume").unwrap()[0];
    assert!((v / 1e-9 - 1.0).abs() < 1e-9, "{v}");
    // Exact area 7 mm^2: sphericity pi^(1/3) (6 V)^(2/3) / A.
    let s = std::f64::consts::PI.cbrt() * 6f64.powf(2.0 / 3.0) / 7.0;
    assert!((t.f64_column("sphericity").unwrap()[0] - s).abs() < 1e-9);
}

#[test]
fn from_harmonics_maps_sizes_onto_the_requested_law() {
    use grainpipe_core::stage::{RunContext, SilentReporter};
    use grainpipe_core::Inputs;
    let reg = registry();
    let st = &reg.stage("grains.from_harmonics").unwrap().stage;
    let files = [
        "MA107-6-fine-anm-00002.dat",
        "MA107-6-fine-anm-00055.dat",
        "MA107-6-fine-anm-00109.dat",
    ];
    // Uniform law on [100, 160] um, 6 grains cycling through 3 files with random rotations:
    // the k-th smallest natural grain gets quantile (k + 1/2)/6, i.e. 105, 115, ..., 155 um,
    // in the order of the natural sizes (00055 < 00002 < 00109, README table).
    let params = serde_json::json!({
        "files": files, "count": 6, "random_rotation": true, "voxel_size": "4 um",
        "size": {"kind": "uniform", "min": "100 um", "max": "160 um"}
    });
    let (_, prepared) = st.preflight(&params, &Default::default()).unwrap();
    let out = st
        .run(
            &params,
            &prepared,
            &Inputs::new(),
            &RunContext::new(3, &SilentReporter),
        )
        .unwrap();
    let t = out["stats"].as_table().unwrap();
    let d = t.f64_column("d_eq").unwrap();
    // Grain k uses file k % 3; ties between the two copies of a file go to the lower index.
    let expect = [125e-6, 105e-6, 145e-6, 135e-6, 115e-6, 155e-6];
    for k in 0..6 {
        // Voxel volume vs surface volume: within the half-voxel shell, i.e. d_eq within
        // ~ (3 * 0.5 * 4 um / d) / 3 * d = 2 um; 3 um allows for roughness (area > sphere's).
        assert!(
            (d[k] - expect[k]).abs() < 3e-6,
            "grain {k}: {} vs {}",
            d[k],
            expect[k]
        );
    }
}

#[test]
fn preflight_announces_counts_the_parameters_fix() {
    use grainpipe_core::model::ArtifactMeta;
    use grainpipe_core::stage::InputMetas;
    use grainpipe_core::ArtifactKind;
    let reg = registry();
    let pf = |id: &str, params: serde_json::Value, inputs: &InputMetas| {
        reg.stage(id)
            .unwrap()
            .stage
            .preflight(&params, inputs)
            .unwrap()
            .0
    };
    let g = pf(
        "grains.synthetic",
        serde_json::json!({"count": 7, "voxel_size": "40 um"}),
        &InputMetas::new(),
    );
    assert_eq!(g.outputs["grains"].count_bounds, Some([7, 7]));
    assert_eq!(g.outputs["stats"].count_bounds, Some([7, 7]));
    assert_eq!(g.outputs["summary"].count_bounds, Some([4, 4]));
    // The default lognormal law's mean diameter: 140 um x exp(0.25^2 / 2).
    let d = g.outputs["grains"].length_scale.unwrap();
    assert!(
        (d / (140e-6 * (0.03125f64).exp()) - 1.0).abs() < 1e-12,
        "{d}"
    );
    // clumps.garcia: one clump and one report row per grain.
    let mut series = InputMetas::new();
    series.insert("grains".into(), g.outputs["grains"].clone());
    let c = pf("clumps.garcia", serde_json::json!({}), &series);
    assert_eq!(c.outputs["library"].count_bounds, Some([7, 7]));
    assert_eq!(c.outputs["report"].count_bounds, Some([7, 7]));
    // clumps.library: `count` clumps drawn, or all of them kept.
    let mut lib = InputMetas::new();
    lib.insert("library".into(), c.outputs["library"].clone());
    let l = pf("clumps.library", serde_json::json!({"count": 3}), &lib);
    for port in ["library", "table", "gallery"] {
        assert_eq!(l.outputs[port].count_bounds, Some([3, 3]), "{port}");
    }
    assert_eq!(l.outputs["gallery"].periodic, Some([false; 3]));
    let all = pf(
        "clumps.library",
        serde_json::json!({"sampling": "all"}),
        &lib,
    );
    assert_eq!(all.outputs["library"].count_bounds, Some([7, 7]));
    let capped = pf(
        "clumps.library",
        serde_json::json!({"sampling": "all", "max_bounding_diameter": "1 mm"}),
        &lib,
    );
    assert_eq!(capped.outputs["library"].count_bounds, Some([1, 7]));
    // grains.from_labels: the count is known only once the labels are read.
    let mut labels = InputMetas::new();
    labels.insert("labels".into(), ArtifactMeta::of(ArtifactKind::PhaseImage));
    let f = pf("grains.from_labels", serde_json::json!({}), &labels);
    assert_eq!(f.outputs["grains"].count_bounds, None);
    assert_eq!(f.outputs["summary"].count_bounds, Some([4, 4]));
}

/// The shipped data directory is found from any working directory, and the value the cache
/// hashes is the directory actually read.
#[test]
fn harmonics_directory_resolves_to_the_shipped_data() {
    let reg = registry();
    let st = &reg.stage("grains.from_harmonics").unwrap().stage;
    let v = st
        .normalize_params(&serde_json::json!({"directory": "data/sand-grains/MA107-6-fine"}))
        .unwrap();
    let dir = std::path::PathBuf::from(v["directory"].as_str().unwrap());
    assert!(dir.is_dir(), "{}", dir.display());
    assert_eq!(v["directory"], st.default_params()["directory"]);
    let spec = st
        .info()
        .params
        .iter()
        .find(|p| p.name == "directory")
        .unwrap();
    assert!(spec.reads_file);
}

/// `shape: equivalent_spheres` (paper, section 4.4) keeps the drawn grains' volumes: every
/// library entry is one sphere whose volume, (4/3) pi r^3, equals the volume of the clump of
/// the same source grain, with the inertia of a solid sphere, (2/5) m r^2.
#[test]
fn equivalent_spheres_keep_the_grains_volume_distribution() {
    let root = workspace_root(env!("CARGO_MANIFEST_DIR"));
    let out = tempfile::tempdir().unwrap();
    let res = run_pipeline(
        &registry(),
        &root,
        "clumps.yaml",
        &["clumps.alpha=0.6", "library.shape=equivalent_spheres"],
        out.path(),
    )
    .unwrap();
    let full = res.outputs["clumps"]["library"].as_clump_library().unwrap();
    let lib = res.outputs["library"]["library"]
        .as_clump_library()
        .unwrap();
    assert_eq!(lib.clumps.len(), 20);
    for c in &lib.clumps {
        let grain = c.source.trim_end_matches(" (equivalent sphere)");
        let original = full
            .clumps
            .iter()
            .find(|o| o.source == grain)
            .unwrap_or_else(|| panic!("no clump from {grain}"));
        assert_eq!(c.spheres.len(), 1);
        let r = c.spheres[0].radius;
        let v_sphere = 4.0 / 3.0 * std::f64::consts::PI * r.powi(3);
        assert!((v_sphere / original.volume - 1.0).abs() < 1e-12);
        assert!((c.volume / original.volume - 1.0).abs() < 1e-12);
        assert_eq!(c.spheres[0].offset, [0.0; 3]);
        assert_eq!(c.bounding_radius, r);
        let inertia = 0.4 * v_sphere * r * r;
        for i in c.principal_inertia {
            assert!((i / inertia - 1.0).abs() < 1e-12);
        }
    }
}
