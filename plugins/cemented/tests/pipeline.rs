//! pipelines/cemented2d.yaml through the engine (shrunk), the registry's consistency checks,
//! and the same numbers on one and two threads for the whole chain.

#![allow(clippy::needless_range_loop)] // axis loops index several vectors

use grainpipe_core::testing::{run_pipeline, workspace_root};
use grainpipe_core::Registry;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_cemented::register(&mut r);
    // cemented2d.yaml ends with peridynamics.bond_based and analysis.stress_stats.
    grainpipe_peridynamics::register(&mut r);
    r
}

#[test]
fn registry_is_consistent() {
    registry().check_consistency().unwrap();
}

const SMALL: &[&str] = &[
    "pack.size=\"12 mm\"",
    // A 12 r_L box holds ~25 large disks: theta moves in steps of ~4 % with the gap.
    "pack.theta_tolerance=0.05",
    "bridges.crop_size=\"9 mm\"",
    "bridges.resolution=160",
];

#[test]
fn shipped_pipeline_runs_small_and_is_thread_count_independent() {
    let root = workspace_root(env!("CARGO_MANIFEST_DIR"));
    let run = |threads: usize| {
        let out = tempfile::tempdir().unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let res = pool
            .install(|| run_pipeline(&registry(), &root, "cemented2d.yaml", SMALL, out.path()))
            .unwrap();
        assert!(out.path().join("cemented2d/phases.vti").is_file());
        assert!(out.path().join("cemented2d/particles.vtp").is_file());
        assert!(out.path().join("cemented2d/pores_summary.csv").is_file());
        assert!(out.path().join("cemented2d/stress_stats.csv").is_file());
        res
    };
    let a = run(1);
    let theta = a.value("pack.report", "theta");
    assert!((theta - 1.32).abs() / 1.32 < 0.05, "theta {theta}");
    let phi = a.value("dem.report", "packing_fraction");
    assert!(phi > 0.78 && phi < 0.9, "packing fraction {phi}");
    for axis in ["x", "y"] {
        let s = a.value("dem.report", &format!("wall_stress_{axis}"));
        assert!((s - 1e5).abs() <= 0.01 * 1e5, "{s}");
    }
    let sm = a.value("pores.summary", "s_m");
    assert!(sm > 0.0 && sm < 1.0, "S_m {sm}");
    assert!(a.value("pores.summary", "n_pores") > 10.0);
    let img = a.artifact("bridges.image").as_phase_image().unwrap();
    assert_eq!(img.grid.dims, [160, 160, 1]);
    let b = run(2);
    for col in ["pore_mean", "void_cv", "s_m", "z_ls", "z_ss"] {
        assert_eq!(
            a.value("pores.summary", col),
            b.value("pores.summary", col),
            "{col}"
        );
    }
    assert_eq!(
        a.artifact("dem.packing").as_packing().unwrap(),
        b.artifact("dem.packing").as_packing().unwrap()
    );
}
