//! `voxel_size: auto` (issue 32, item 4) end to end: the choice of `pipe run` against a
//! brute-force scan of the same pipeline at many resolutions, and the refusals.
//!
//! The pipeline: one sphere (conductivity 100) in a periodic 40 um cube of matrix
//! (conductivity 1), i.e. a simple cubic array at 26.8 % (Rayleigh's problem), imaged by
//! voxelize.packing with sub-voxel fractions and solved by conductivity.fft with composite
//! voxels on hex8, which converges monotonically at first order in the voxel size (measured:
//! k_xx = 2.38, 2.23, 2.16, 2.13, 2.12 at 8, 16, 32, 48, 64 voxels per diameter), so the
//! Richardson estimate has something to find.

use grainpipe_cli::{builtin_registry, plan_pipeline, PlanRequest, PluginLoader};
use grainpipe_core::engine::{execute, RunOptions, SilentObserver};
use grainpipe_core::pipeline::PipelineDoc;
use grainpipe_core::Artifact;
use std::path::Path;
use std::process::Command;

fn pipe(args: &[&str], dir: &Path) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_pipe"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("pipe runs");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// The test pipeline with `extra` lines added to the voxelize step's `with:`.
fn yaml(target: &str, extra: &str) -> String {
    format!(
        r#"name: auto-sphere
seed: 7
stages:
  - id: pack
    use: packing.rsa
    with:
      size: [40 um, 40 um, 40 um]
      radius: {{ kind: fixed, value: 16 um }}
      volume_fraction: 0.268
  - id: voxels
    use: voxelize.packing
    in: {{ packing: pack.packing }}
    with:
      voxel_size: auto
      target_error: {target}
      auto_quantities: [cond.conductivity.0]
      auto_levels: [8, 16, 32]
      subvoxel: true
{extra}  - id: cond
    use: conductivity.fft
    in: {{ image: voxels.image, subvoxel: voxels.subvoxel }}
    with:
      conductivities: {{ grain: 100 W/(m K), pore: 1 W/(m K) }}
      load_cases: [x]
      interfaces: composite
      discretization: hex8
export:
  - {{ from: cond.conductivity, to: out/auto/conductivity.csv }}
"#
    )
}

/// k_xx of the pipeline in this process at `n` voxels per diameter (same seed, so the same
/// sphere as the levels and the run).
fn k_xx(file: &Path, n: f64) -> f64 {
    let mut reg = builtin_registry();
    let mut loader = PluginLoader::default();
    let req = PlanRequest {
        overrides: vec![
            "voxels.voxel_size=0".into(),
            format!("voxels.voxels_per_diameter={n}"),
        ],
        targets: vec!["cond".into()],
        skip_exports: true,
        ..Default::default()
    };
    let (doc, plan) = plan_pipeline(
        PipelineDoc::load(file).unwrap(),
        &mut reg,
        &mut loader,
        &req,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let res = execute(
        &doc,
        &plan,
        &RunOptions { cache_dir: None },
        &mut SilentObserver,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    match &res.outputs["cond"]["conductivity"] {
        Artifact::Tensor(t) => t.values[0],
        other => panic!("not a tensor: {}", other.kind()),
    }
}

fn auto_record(dir: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(dir.join("out/auto/run.json")).unwrap();
    let run: serde_json::Value = serde_json::from_str(&text).unwrap();
    run["auto_voxel"].clone()
}

/// The choice against a brute-force scan: the reference is the Richardson limit of three
/// finer runs (32, 48, 64 voxels per diameter; order observed there); the run at the chosen
/// resolution is within the target of it, and the scan's candidates coarser than the choice
/// are not (the choice is the coarsest that works, to the scan's spacing).
#[test]
fn the_auto_choice_meets_the_target_against_a_brute_force_scan() {
    let tmp = tempfile::tempdir().unwrap();
    let target = 0.05;
    std::fs::write(tmp.path().join("p.yaml"), yaml(&target.to_string(), "")).unwrap();
    let (code, out, err) = pipe(&["run", "p.yaml", "--no-cache"], tmp.path());
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(
        err.contains("voxels.voxel_size: auto -> "),
        "the choice is printed:\n{err}"
    );
    let rec = auto_record(tmp.path());
    let chosen = rec["voxels_per_diameter"].as_f64().unwrap();
    let q = &rec["quantities"][0];
    assert!(q["order_basis"].as_str().unwrap().starts_with("observed"));
    let predicted = q["predicted_error"].as_f64().unwrap();
    assert!(predicted <= target + 1e-12, "{rec}");
    // The run ran at the choice and says so in its overrides (reproducible with --set).
    let run: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("out/auto/run.json")).unwrap(),
    )
    .unwrap();
    assert!(run["overrides"]
        .as_array()
        .unwrap()
        .iter()
        .any(|o| o == format!("voxels.voxels_per_diameter={chosen}").as_str()));

    let file = tmp.path().join("p.yaml");
    let fine: Vec<f64> = [32.0, 48.0, 64.0].iter().map(|&n| k_xx(&file, n)).collect();
    let (order, reference) =
        grainpipe_sweep::study::richardson(&[1.0 / 32.0, 1.0 / 48.0, 1.0 / 64.0], &fine)
            .expect("the fine runs converge monotonically");
    let error = |n: f64| (k_xx(&file, n) - reference).abs() / reference;
    let at_choice = error(chosen);
    let estimate_vs_true = (predicted - at_choice).abs();
    eprintln!(
        "chosen {chosen} voxels/diameter: predicted error {predicted:.4}, true {at_choice:.4} \
         (reference {reference:.5}, order {order:.2}); level estimates {}",
        q["errors"]
    );
    assert!(
        at_choice <= target,
        "the run at {chosen} has error {at_choice} > target {target}"
    );
    // Measured: predicted 5.00 %, true 4.77 % at 26.6 voxels per diameter. The levels 8,
    // 16, 32 observe order 1.25 where the fine runs show 0.87: without the cap at the
    // formal order 1 and the safety factor 1.25 the choice was 17.8 with a true error of
    // 6.7 %. Agreement asserted to half a percentage point.
    assert!(estimate_vs_true < 0.005, "{predicted} vs {at_choice}");
    // Coarser candidates of a scan 1.25x apart miss the target.
    for n in [chosen / 1.25, chosen / 1.25 / 1.25] {
        if n >= 8.0 {
            let e = error(n);
            eprintln!("  scan {n:.2}: true error {e:.4}");
            assert!(e > target, "{n} voxels/diameter also meets {target}: {e}");
        }
    }
}

/// Same YAML and seed: the same choice, from levels run afresh in another directory.
#[test]
fn the_choice_is_reproducible_and_two_levels_state_their_assumed_order() {
    let tmp = tempfile::tempdir().unwrap();
    let two = yaml("0.05", "").replace("auto_levels: [8, 16, 32]", "auto_levels: [8, 16]");
    std::fs::write(tmp.path().join("p.yaml"), &two).unwrap();
    let mut choices = Vec::new();
    for out in ["out/a", "out/b"] {
        let (code, _, err) = pipe(
            &["run", "p.yaml", "--no-cache", "--quiet", "--out", out],
            tmp.path(),
        );
        assert_eq!(code, 0, "{err}");
        let run: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(tmp.path().join(out).join("run.json")).unwrap(),
        )
        .unwrap();
        let rec = run["auto_voxel"].clone();
        assert_eq!(rec["quantities"][0]["order_basis"], "assumed");
        assert_eq!(rec["quantities"][0]["order"], 1.0);
        assert!(rec["levels_dir"]
            .as_str()
            .unwrap()
            .contains(&out.replace("out/", "")));
        choices.push((
            rec["voxels_per_diameter"].clone(),
            rec["quantities"][0]["values"].clone(),
        ));
    }
    assert_eq!(choices[0], choices[1]);
}

/// Bad settings are refused before anything runs, at their key, with exit code 2.
#[test]
fn bad_settings_are_refused_at_their_key() {
    let cases: [(&str, &str, &str); 4] = [
        ("0", "", "target_error"),
        ("1.5", "", "target_error"),
        (".nan", "", "target_error"),
        ("0.03", "", "no step `nope`"),
    ];
    for (target, extra, needle) in cases {
        let tmp = tempfile::tempdir().unwrap();
        let mut y = yaml(target, extra);
        if needle.contains("nope") {
            y = y.replace("[cond.conductivity.0]", "[nope.conductivity.0]");
        }
        std::fs::write(tmp.path().join("p.yaml"), y).unwrap();
        for cmd in ["validate", "run"] {
            let (code, _, err) = pipe(&[cmd, "p.yaml"], tmp.path());
            assert_eq!(code, 2, "{cmd} {target}: {err}");
            assert!(err.contains(needle), "{cmd}: no `{needle}` in\n{err}");
            // The line of the key: target_error on 15, auto_quantities on 16.
            let line = if needle == "target_error" { 15 } else { 16 };
            assert!(err.contains(&format!("p.yaml:{line}:")), "{cmd}: {err}");
            assert!(!tmp.path().join("out").exists(), "nothing ran");
        }
    }
}

/// `pipe validate` says what will run and plans the finest level.
#[test]
fn validate_explains_the_levels() {
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("p.yaml"), yaml("0.03", "")).unwrap();
    let (code, out, err) = pipe(&["validate", "p.yaml"], tmp.path());
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains(
            "voxels.voxel_size: auto: first runs the levels 8, 16, 32 voxels per diameter"
        ) && out.contains("below 3 %")
            && out.contains("the order observed"),
        "{out}"
    );
    // The finest level's grid: 40 um / (32 um / 32) = 40 voxels.
    assert!(out.contains("grid 40x40x40"), "{out}");
    assert!(!tmp.path().join("out").exists(), "validate runs nothing");
}

/// A target beyond the memory: the levels run, then a loud refusal naming the resolution
/// and the memory it would take (never a silent fallback to a coarser voxel).
#[test]
fn an_unreachable_target_names_the_memory() {
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("p.yaml"), yaml("0.0001", "")).unwrap();
    let (code, _, err) = pipe(&["run", "p.yaml", "--no-cache", "--quiet"], tmp.path());
    assert_eq!(code, 2, "{err}");
    for needle in [
        "target_error 0.0001",
        "voxels per diameter",
        "of memory",
        "is available",
    ] {
        assert!(err.contains(needle), "no `{needle}` in\n{err}");
    }
    assert!(
        !tmp.path().join("out/auto/conductivity.csv").exists(),
        "the run did not run"
    );
}
