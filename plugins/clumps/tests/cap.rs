//! Issue 31, "no silent outliers": a `clumps.library` size cap that drops more than 10 % of
//! the sand volume is refused at preflight (naming the grains and the share, offering the
//! choices) when the grains' sizes are known then, at run time otherwise; `drop_oversize:
//! true` accepts it with a warning; a cap dropping less only warns.

use grainpipe_clumps::clumps::{oversize, Library, MAX_DROPPED_SHARE};
use grainpipe_clumps::grains::FromHarmonics;
use grainpipe_core::engine::{plan, PlanOptions};
use grainpipe_core::pipeline::PipelineDoc;
use grainpipe_core::*;
use std::path::Path;
use std::sync::Arc;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_clumps::register(&mut r);
    r
}

/// The shipped grains at D50 = 140 um (as pipelines/mcm.yaml) through clumps.garcia into
/// clumps.library with the given `with:` text.
fn yaml(library_with: &str) -> String {
    format!(
        "name: cap\nstages:\n  - id: grains\n    use: grains.from_harmonics\n    with: {{ voxel_size: 4 um, d50: 140 um }}\n  - id: clumps\n    use: clumps.garcia\n    in: {{ grains: grains.grains }}\n  - id: library\n    use: clumps.library\n    in: {{ library: clumps.library }}\n    with: {library_with}\n"
    )
}

/// Plans (resolves and preflights) the pipeline: nothing runs.
fn preflight(text: &str) -> Result<(), String> {
    let doc = PipelineDoc::parse(Path::new("cap.yaml"), text.to_string()).map_err(|e| e.message)?;
    plan(&doc, &registry(), &PlanOptions::default())
        .map(|_| ())
        .map_err(|e| {
            std::iter::once(e.message.clone())
                .chain(e.related.iter().map(|r| r.message.clone()))
                .collect::<Vec<_>>()
                .join("\n")
        })
}

/// The grains' announced (name, volume, bounding diameter), as clumps.library sees them.
fn announced() -> Vec<(String, f64, f64)> {
    let p: <FromHarmonics as TypedStage>::Params =
        serde_json::from_value(serde_json::json!({"voxel_size": "4 um", "d50": "140 um"})).unwrap();
    let pf = FromHarmonics.preflight(&p, &InputMetas::new()).unwrap();
    pf.outputs["grains"]
        .item_sizes
        .as_ref()
        .expect("grains.from_harmonics announces the grains' sizes")
        .iter()
        .map(|x| (x.name.clone(), x.volume, x.bounding_diameter))
        .collect()
}

#[test]
fn the_shipped_cap_passes_and_a_tighter_one_is_refused_at_preflight() {
    let items = announced();
    assert_eq!(items.len(), 30);
    // The shipped pipelines' cap (280 um, the paper's layer thickness) drops at most a few
    // per cent of the shipped sand: it passes.
    let o = oversize(&items, 1.0, 280e-6).unwrap();
    eprintln!("280 um: {}", o.describe());
    assert!(o.share <= MAX_DROPPED_SHARE, "{}", o.describe());
    preflight(&yaml("{ sampling: all, max_bounding_diameter: 280 um }")).unwrap();
    // A cap at the 80th percentile of the bounding diameters drops the coarsest fifth of
    // the grains, far more than 10 % of the volume: refused before anything runs, naming the
    // grains (by file) and the share, and offering the three ways out.
    let mut d: Vec<f64> = items.iter().map(|x| x.2).collect();
    d.sort_by(f64::total_cmp);
    let cap = d[24];
    let o = oversize(&items, 1.0, cap).unwrap();
    assert_eq!(o.dropped.len(), 5);
    assert!(o.share > MAX_DROPPED_SHARE, "{}", o.describe());
    let with = format!(
        "{{ sampling: all, max_bounding_diameter: {} um }}",
        cap * 1e6
    );
    let err = preflight(&yaml(&with)).unwrap_err();
    eprintln!("{err}");
    for (name, _, _) in &o.dropped {
        assert!(err.contains(name.as_str()), "{name} not named: {err}");
    }
    let share = format!("{:.1} % of the sand volume", o.share * 100.0);
    assert!(err.contains(&share), "no `{share}` in {err}");
    for choice in [
        "rescale",
        "raise max_bounding_diameter",
        "drop_oversize: true",
    ] {
        assert!(err.contains(choice), "no `{choice}` in {err}");
    }
    // The same cap accepted explicitly.
    let with = format!(
        "{{ sampling: all, max_bounding_diameter: {} um, drop_oversize: true }}",
        cap * 1e6
    );
    preflight(&yaml(&with)).unwrap();
}

#[test]
fn announced_sizes_match_the_clumps_garcia_builds() {
    // The preflight estimate (star-shape table at the target size) against the clumps
    // clumps.garcia builds from the same grains at 4 um (as the shipped pipelines).
    let items = announced();
    let res = grainpipe_core::testing::run_yaml(&registry(), &yaml("{ sampling: all }")).unwrap();
    let lib = res.artifact("clumps.library").as_clump_library().unwrap();
    assert_eq!(lib.clumps.len(), items.len());
    let total: f64 = items.iter().map(|x| x.1).sum();
    let ctotal: f64 = lib.clumps.iter().map(|c| c.volume).sum();
    let (mut dd, mut ds) = (0.0f64, 0.0f64);
    for (c, (name, v, d)) in lib.clumps.iter().zip(&items) {
        assert_eq!(&c.source, name);
        dd = dd.max((2.0 * c.bounding_radius - d).abs());
        ds = ds.max((c.volume / ctotal - v / total).abs());
    }
    eprintln!(
        "largest differences: bounding diameter {:.2} um, volume share {:.3} %",
        dd * 1e6,
        ds * 100.0
    );
    // Bounding diameters within three voxels (measured: 10.8 um; the clump covers alpha =
    // 0.9 of the voxels and leaves thin tips out, the mask samples the star shape at voxel
    // centres); volume shares (what the cap's threshold is on) within 0.5 percentage points
    // (measured 0.07).
    assert!(dd < 12e-6, "bounding diameters differ by up to {dd:e} m");
    assert!(ds < 0.005, "volume shares differ by up to {ds}");
}

/// Sphere "grains" of the given diameters [um], named g<diameter>.
fn spheres(diameters: &[f64]) -> ClumpLibrary {
    ClumpLibrary {
        clumps: diameters
            .iter()
            .map(|&um| {
                let d = um * 1e-6;
                Clump {
                    spheres: vec![ClumpSphere {
                        offset: [0.0; 3],
                        radius: d / 2.0,
                    }],
                    volume: std::f64::consts::PI / 6.0 * d.powi(3),
                    bounding_radius: d / 2.0,
                    principal_inertia: [1.0; 3],
                    principal_axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                    source: format!("g{um}"),
                }
            })
            .collect(),
        source: "test".into(),
    }
}

fn run_library(
    diameters: &[f64],
    with: serde_json::Value,
) -> (Result<Outputs, StageError>, Vec<String>) {
    let p: <Library as TypedStage>::Params = serde_json::from_value(with).unwrap();
    let mut metas = InputMetas::new();
    // An input whose sizes preflight does not know (an imported library, another grains.*
    // stage): the refusal comes when the clumps are there.
    metas.insert(
        "library".into(),
        ArtifactMeta::of(ArtifactKind::ClumpLibrary),
    );
    let pf = Library.preflight(&p, &metas).unwrap();
    let mut inputs = Inputs::new();
    inputs.insert(
        "library".into(),
        Arc::new(Artifact::ClumpLibrary(spheres(diameters))),
    );
    let rep = grainpipe_core::testing::WarningLog::default();
    let out = Library.run(&p, &pf.plan, &inputs, &RunContext::new(1, &rep));
    (out, rep.warnings())
}

#[test]
fn without_announced_sizes_the_run_refuses_and_drop_oversize_accepts_with_a_warning() {
    // Diameters 100, 120, ..., 280 um; the cap at 250 um drops the two largest, whose share
    // of the volume (d^3) is computed here independently: 39.5 / 88.4 = 44.7 %.
    let d: Vec<f64> = (0..10).map(|k| 100.0 + 20.0 * k as f64).collect();
    let d3: Vec<f64> = d.iter().map(|x| x.powi(3)).collect();
    let share = (d3[8] + d3[9]) / d3.iter().sum::<f64>();
    assert!(share > MAX_DROPPED_SHARE);
    let (out, _) = run_library(
        &d,
        serde_json::json!({"sampling": "all", "max_bounding_diameter": "250 um"}),
    );
    match out {
        Err(StageError::InvalidParam { key, message }) => {
            assert_eq!(key, "max_bounding_diameter");
            assert!(
                message.contains("g260") && message.contains("g280"),
                "{message}"
            );
            assert!(
                message.contains(&format!("{:.1} %", share * 100.0)),
                "{message}"
            );
            assert!(message.contains("drop_oversize: true"), "{message}");
        }
        other => panic!("expected the refusal, got {:?}", other.map(|_| ())),
    }
    let (out, warnings) = run_library(
        &d,
        serde_json::json!({"sampling": "all", "max_bounding_diameter": "250 um", "drop_oversize": true}),
    );
    let lib = out.unwrap()["library"].as_clump_library().unwrap().clone();
    assert_eq!(lib.clumps.len(), 8);
    assert!(lib.clumps.iter().all(|c| 2.0 * c.bounding_radius <= 250e-6));
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(warnings[0].contains("g260") && warnings[0].contains("g280"));
    assert!(warnings[0].contains("drop_oversize: true"));
    // A cap that drops less than 10 %: twelve grains of 200 um and one of 210 um (share
    // 9.261 / 105.261 = 8.8 %) capped at 205 um pass, and the drop is warned about.
    let small: Vec<f64> = [vec![200.0; 12], vec![210.0]].concat();
    let (out, warnings) = run_library(
        &small,
        serde_json::json!({"sampling": "all", "max_bounding_diameter": "205 um"}),
    );
    assert_eq!(
        out.unwrap()["library"]
            .as_clump_library()
            .unwrap()
            .clumps
            .len(),
        12
    );
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(
        warnings[0].contains("1 of 13 grains, 8.8 % of the sand volume: g210"),
        "{warnings:?}"
    );
    // A cap above every grain drops nothing and says nothing.
    let (out, warnings) = run_library(
        &d,
        serde_json::json!({"sampling": "all", "max_bounding_diameter": "300 um"}),
    );
    assert_eq!(
        out.unwrap()["library"]
            .as_clump_library()
            .unwrap()
            .clumps
            .len(),
        10
    );
    assert!(warnings.is_empty(), "{warnings:?}");
}
