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
