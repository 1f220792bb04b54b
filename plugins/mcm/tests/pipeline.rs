//! pipelines/mcm.yaml through the engine with a registry holding this crate and the formats.

use grainpipe_core::engine::{execute, plan, PlanOptions, RunOptions, SilentObserver};
use grainpipe_core::pipeline::PipelineDoc;
use grainpipe_core::Registry;
use std::path::Path;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_mcm::register(&mut r);
    r
}

#[test]
fn registry_is_consistent() {
    registry().check_consistency().unwrap();
}

#[test]
fn mcm_pipeline_runs_and_exports() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut doc = PipelineDoc::load(&root.join("pipelines/mcm.yaml")).unwrap();
    let out = tempfile::tempdir().unwrap();
    doc.redirect_exports(out.path());
    let reg = registry();
    let p = plan(&doc, &reg, &PlanOptions::default()).unwrap();
    let res = execute(
        &doc,
        &p,
        &RunOptions { cache_dir: None },
        &mut SilentObserver,
    )
    .unwrap();
    let classic = res.outputs["classic"]["packing"].as_packing().unwrap();
    assert_eq!(classic.bodies.len(), 300);
    // 300 equal spheres in a cube sized for 60 %: exact up to rounding.
    assert!((classic.volume_fraction() - 0.6).abs() < 1e-9);
    let stacked = res.outputs["stacked"]["packing"].as_packing().unwrap();
    // Two layers of (560 um)^2 x 280 um at 50 %.
    let v = 0.5 * 560e-6 * 560e-6 * 560e-6;
    assert!((stacked.solid_volume() / v - 1.0).abs() < 1e-9);
    for f in [
        "classic.vtp",
        "classic.h5",
        "classic_report.csv",
        "classic_orientation.csv",
        "stacked.vtp",
        "stacked.h5",
        "stacked_report.csv",
    ] {
        let path = out.path().join("mcm").join(f);
        assert!(
            path.metadata().map(|m| m.len() > 0).unwrap_or(false),
            "{f} missing"
        );
    }
}
