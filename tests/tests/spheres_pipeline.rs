//! pipelines/spheres.yaml end to end: the exported files hold what the stages computed, the
//! voxelized fraction matches the analytic one, and thread count does not change results.

use grainpipe_tests::run_pipeline;

#[test]
fn exported_image_matches_analytic_volume_fraction() {
    let dir = tempfile::tempdir().unwrap();
    let r = run_pipeline("spheres.yaml", &[], dir.path()).unwrap();
    let packing = r.outputs["pack"]["packing"].as_packing().unwrap().clone();
    let analytic = packing.volume_fraction();
    // Read the exported VTI back (independent of the in-memory image).
    let img = grainpipe_formats::read_vti(&dir.path().join("spheres/image.vti"), None)
        .unwrap()
        .into_phase_image()
        .unwrap();
    assert_eq!(img.grid.dims, [160, 160, 160]);
    let phi = img.fraction(1);
    // Foundation acceptance: within 0.5 % of the analytic fraction at 20 voxels per diameter.
    assert!(
        (phi - analytic).abs() / analytic < 0.005,
        "image {phi} analytic {analytic}"
    );
    // The HDF5 packing round-trips exactly (f64 positions are stored as f64).
    let back = grainpipe_formats::read_h5(&dir.path().join("spheres/packing.h5")).unwrap();
    assert_eq!(back.as_packing().unwrap().bodies, packing.bodies);
    // The report written to CSV agrees with the image read back.
    let t = grainpipe_formats::read_table_csv(&dir.path().join("spheres/voxelize.csv")).unwrap();
    let reported = t.f64_column("image_fraction").unwrap()[0];
    assert!(
        (reported - phi).abs() < 1e-12,
        "csv {reported} vs image {phi}"
    );
}

#[test]
fn results_do_not_depend_on_thread_count() {
    let overrides = [
        "pack.size=[200 um, 200 um, 200 um]",
        "voxels.voxels_per_diameter=8",
    ];
    let run = |threads: usize| {
        let dir = tempfile::tempdir().unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let r = pool.install(|| run_pipeline("spheres.yaml", &overrides, dir.path()).unwrap());
        (
            r.outputs["pack"]["packing"].clone(),
            r.outputs["voxels"]["image"].clone(),
            r.outputs["voxels"]["report"].clone(),
        )
    };
    assert_eq!(run(1), run(2));
}

#[test]
fn preflight_knows_the_voxel_grid_before_anything_runs() {
    // Equal spheres fix the mean diameter, so the grid at 20 voxels per diameter is known at
    // preflight: 400 um / (50 um / 20) = 160 voxels per axis, periodic like the packing. The
    // run is checked against this announcement by the engine.
    let doc = grainpipe_core::pipeline::PipelineDoc::load(
        &grainpipe_tests::repo_root().join("pipelines/spheres.yaml"),
    )
    .unwrap();
    let plan = grainpipe_core::engine::plan(
        &doc,
        &grainpipe_cli::builtin_registry(),
        &Default::default(),
    )
    .unwrap();
    let (i, _) = doc.step("voxels").unwrap();
    let grid = plan.steps[i].as_ref().unwrap().preflight.outputs["image"]
        .grid
        .clone()
        .expect("grid announced");
    assert_eq!(grid.dims, [160; 3]);
    assert_eq!(grid.periodic, [true; 3]);
    assert!((grid.spacing[0] - 2.5e-6).abs() < 1e-18);
    // Polydisperse radii only estimate the diameter: no grid is promised then.
    let mut poly = doc.clone();
    poly.apply_override("pack.radius={kind: uniform, min: 20 um, max: 30 um}")
        .unwrap();
    let plan = grainpipe_core::engine::plan(
        &poly,
        &grainpipe_cli::builtin_registry(),
        &Default::default(),
    )
    .unwrap();
    assert!(plan.steps[i].as_ref().unwrap().preflight.outputs["image"]
        .grid
        .is_none());
}
