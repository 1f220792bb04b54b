//! pipelines/cemented2d.yaml through the engine (shrunk), the registry's consistency checks,
//! the same numbers on one and two threads for the whole chain, and pipelines/cemented3d.yaml
//! as shipped.

#![allow(clippy::needless_range_loop)] // axis loops index several vectors

use grainpipe_core::testing::{run_pipeline, workspace_root};
use grainpipe_core::Registry;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    // Its `png` (ContactGraph) comes first, as in the CLI: the stress PDF plots (Tables) must
    // reach pdf-png all the same.
    grainpipe_sintering::register(&mut r);
    grainpipe_cemented::register(&mut r);
    // cemented2d.yaml ends with peridynamics.bond_based and analysis.stress_stats.
    grainpipe_peridynamics::register(&mut r);
    r
}

/// Width and height of a PNG, decoding the whole image (so a truncated file fails).
fn png_size(path: &std::path::Path) -> (u32, u32) {
    let file = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut reader = png::Decoder::new(file).read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let rgb = &buf[..info.buffer_size()];
    assert!(rgb.iter().any(|&v| v != 255), "blank image");
    (info.width, info.height)
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
        assert_eq!(
            png_size(&out.path().join("cemented2d/stress_pdf.png")),
            (900, 600)
        );
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

/// pipelines/cemented3d.yaml as shipped (spheres, a 40^3 grid): the sample reaches its
/// theta, the DEM ends in force balance at the confining pressure, and the peridynamic
/// sample carries tension along the load, with the mean stress (volume average) equal to
/// the grip reaction per area.
#[test]
fn shipped_3d_pipeline_runs_and_is_physical() {
    let root = workspace_root(env!("CARGO_MANIFEST_DIR"));
    let out = tempfile::tempdir().unwrap();
    let t = std::time::Instant::now();
    let a = run_pipeline(&registry(), &root, "cemented3d.yaml", &[], out.path()).unwrap();
    println!("cemented3d.yaml: {:.1} s", t.elapsed().as_secs_f64());
    let theta = a.value("pack.report", "theta");
    assert!((theta - 1.32).abs() / 1.32 < 0.05, "theta {theta}");
    for axis in ["x", "y", "z"] {
        let s = a.value("dem.report", &format!("wall_stress_{axis}"));
        assert!((s - 1e5).abs() <= 0.01 * 1e5, "wall stress {axis}: {s}");
    }
    let unbalanced = a.value("dem.report", "unbalanced_force_ratio");
    assert!(unbalanced <= 1e-3, "unbalanced force ratio {unbalanced}");
    let phi = a.value("dem.report", "packing_fraction");
    assert!(phi > 0.55 && phi < 0.75, "packing fraction {phi}");
    let img = a.artifact("bridges.image").as_phase_image().unwrap();
    assert_eq!(img.grid.dims, [40, 40, 40]);
    let sm = a.value("pores.summary", "s_m");
    assert!(sm > 0.0 && sm < 1.0, "S_m {sm}");
    let sigma = a.value("pd.report", "mean_stress");
    let strain = a.value("pd.report", "strain");
    assert!(sigma > 0.0 && strain > 0.0, "mean stress {sigma}");
    let (eff, reaction) = (
        a.value("pd.report", "effective_modulus"),
        a.value("pd.report", "reaction_modulus"),
    );
    assert!(
        (eff / reaction - 1.0).abs() < 0.05,
        "effective modulus {eff} vs grip reaction {reaction}"
    );
    let stats = a.artifact("stress.stats").as_table().unwrap();
    let means = stats.f64_column("mean_stress").unwrap();
    assert!(
        means.len() >= 2 && means.iter().all(|&m| m > 0.0),
        "{means:?}"
    );
    for f in [
        "phases.vti",
        "stress.vti",
        "stress_stats.csv",
        "particles.vtp",
    ] {
        assert!(out.path().join("cemented3d").join(f).is_file(), "{f}");
    }
    assert_eq!(
        png_size(&out.path().join("cemented3d/stress_pdf.png")),
        (900, 600)
    );
}
