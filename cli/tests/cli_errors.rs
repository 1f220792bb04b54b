//! The `pipe` command on bad input: each mistake gives a one-screen error naming
//! file:line:col, and exit code 2, before anything runs.

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

/// Writes `yaml`, validates it and checks exit code 2, the location and the message.
fn expect_error(yaml: &str, location: &str, needles: &[&str]) {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("p.yaml"), yaml).unwrap();
    for cmd in ["validate", "run"] {
        let (code, _, err) = pipe(
            &[cmd, "p.yaml", "--quiet"][..if cmd == "run" { 3 } else { 2 }],
            dir.path(),
        );
        assert_eq!(code, 2, "{cmd}: exit code for\n{yaml}\n{err}");
        assert!(
            err.contains(&format!("p.yaml:{location}")),
            "{cmd}: no `p.yaml:{location}` in\n{err}"
        );
        for n in needles {
            assert!(err.contains(n), "{cmd}: no `{n}` in\n{err}");
        }
        assert!(err.lines().count() <= 24, "more than one screen:\n{err}");
        // Nothing ran, so nothing was written.
        assert!(!dir.path().join("out").exists());
    }
}

#[test]
fn malformed_yaml() {
    expect_error(
        "name: t\nstages:\n  - id: a\n    use: [packing.rsa\n",
        "4:",
        &["expected"],
    );
}

#[test]
fn unknown_stage_with_suggestion() {
    expect_error(
        "name: t\nstages:\n  - id: a\n    use: packing.rsb\n",
        "4:10",
        &["unknown stage `packing.rsb`", "did you mean `packing.rsa`"],
    );
}

#[test]
fn unknown_key_in_params_with_suggestion() {
    expect_error(
        "name: t\nstages:\n  - id: a\n    use: packing.rsa\n    with:\n      volume_fracton: 0.3\n",
        "6:7",
        &["volume_fracton", "did you mean `volume_fraction`"],
    );
}

#[test]
fn unknown_key_in_step_with_suggestion() {
    expect_error(
        "name: t\nstages:\n  - id: a\n    use: packing.rsa\n    wiht: {}\n",
        "5:5",
        &["unknown field `wiht`", "did you mean `with`"],
    );
}

#[test]
fn wrong_type_and_wrong_unit() {
    expect_error(
        "name: t\nstages:\n  - id: a\n    use: packing.rsa\n    with:\n      volume_fraction: lots\n",
        "6:7",
        &["volume_fraction"],
    );
    expect_error(
        "name: t\nstages:\n  - id: a\n    use: packing.rsa\n    with:\n      size: [1 mm, 1 mm, 3 W]\n",
        "6:7",
        &["size", "takes m"],
    );
}

#[test]
fn missing_input() {
    expect_error(
        "name: t\nstages:\n  - id: vox\n    use: voxelize.packing\n",
        "3:9",
        &["needs input `packing`"],
    );
}

#[test]
fn reference_to_unknown_step_and_port() {
    expect_error(
        "name: t\nstages:\n  - id: pack\n    use: packing.rsa\n  - id: vox\n    use: voxelize.packing\n    in: {packing: pak.packing}\n",
        "7:19",
        &["no step `pak`", "did you mean `pack`"],
    );
    expect_error(
        "name: t\nstages:\n  - id: pack\n    use: packing.rsa\n  - id: vox\n    use: voxelize.packing\n    in: {packing: pack.packin}\n",
        "7:19",
        &["no output `packin`", "pack.packing"],
    );
}

#[test]
fn kind_mismatch() {
    expect_error(
        "name: t\nstages:\n  - id: pack\n    use: packing.rsa\n  - id: vox\n    use: voxelize.packing\n    in: {packing: pack.report}\n",
        "7:19",
        &["takes a Packing but `pack.report` is a Table"],
    );
}

#[test]
fn self_reference() {
    // The shortest cycle; cycles through several steps are tested in core/tests/engine.rs
    // with stages that map a kind to itself.
    expect_error(
        "name: t\nstages:\n  - id: a\n    use: voxelize.packing\n    in: {packing: a.image}\n",
        "5:19",
        &["own output"],
    );
}

#[test]
fn impossible_parameter_is_refused_before_running() {
    expect_error(
        "name: t\nstages:\n  - id: a\n    use: packing.rsa\n    with:\n      volume_fraction: 0.5\nexport:\n  - {from: a.packing, to: out/p.vtp}\n",
        "6:7",
        &["jamming limit"],
    );
}

#[test]
fn export_format_that_cannot_hold_the_artifact() {
    expect_error(
        "name: t\nstages:\n  - id: a\n    use: packing.rsa\nexport:\n  - {from: a.packing, to: out/p.nc}\n",
        "6:",
        &["cannot hold a Packing", "formats for a Packing"],
    );
}

#[test]
fn describe_and_list_show_every_parameter_with_units() {
    let dir = tempfile::tempdir().unwrap();
    let (code, out, _) = pipe(&["describe", "packing.rsa"], dir.path());
    assert_eq!(code, 0);
    for k in [
        "size",
        "radius",
        "volume_fraction",
        "periodic",
        "max_attempts_per_sphere",
        "[m]",
        "default",
    ] {
        assert!(out.contains(k), "describe lacks `{k}`:\n{out}");
    }
    let (code, out, _) = pipe(&["list"], dir.path());
    assert_eq!(code, 0);
    assert!(out.contains("packing.rsa") && out.contains("voxelize.packing") && out.contains("vti"));
    let (code, _, err) = pipe(&["describe", "packing.rsb"], dir.path());
    assert_eq!(code, 2);
    assert!(err.contains("did you mean `packing.rsa`"));
}

#[test]
fn readme_stage_table_is_generated_from_the_registry() {
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../README.md")).unwrap();
    let begin = readme
        .find("<!-- stages:begin -->\n")
        .expect("begin marker")
        + "<!-- stages:begin -->\n".len();
    let end = readme.find("<!-- stages:end -->").expect("end marker");
    let expected = grainpipe_cli::describe::list_markdown(&grainpipe_cli::builtin_registry());
    assert!(
        readme[begin..end] == expected,
        "README.md's stage table is out of date: run `make readme-stages`"
    );
}

#[test]
fn output_not_selected_by_parameters_is_refused_before_running() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("v.raw"), vec![0u8; 8]).unwrap();
    let yaml = "name: t\nstages:\n  - id: img\n    use: import.raw\n    with: {path: v.raw, dims: [2, 2, 2], spacing: 1 um, as: phase_image}\nexport:\n  - {from: img.field, to: out/f.vti}\n";
    std::fs::write(dir.path().join("p.yaml"), yaml).unwrap();
    let (code, _, err) = pipe(&["run", "p.yaml"], dir.path());
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("p.yaml:7:")
            && err.contains("will not give output `field`")
            && err.contains("img.image"),
        "{err}"
    );
    // The selected output runs and exports.
    std::fs::write(
        dir.path().join("p.yaml"),
        yaml.replace("img.field", "img.image"),
    )
    .unwrap();
    let (code, _, err) = pipe(&["run", "p.yaml", "--quiet"], dir.path());
    assert_eq!(code, 0, "{err}");
    assert!(dir.path().join("out/f.vti").exists());
}

#[test]
fn validate_prints_each_steps_grid_box_and_memory() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let (code, out, err) = pipe(&["validate", "pipelines/spheres.yaml"], &root);
    assert_eq!(code, 0, "{err}");
    // 400 um box, 25 um spheres at 20 voxels per diameter: 160^3 voxels of 2.5 um, periodic.
    assert!(
        out.contains(
            "image: PhaseImage (grid 160x160x160 of 2.5000 x 2.5000 x 2.5000 um, periodic in xyz)"
        ),
        "{out}"
    );
    assert!(
        out.contains("packing: Packing (box 400.0 x 400.0 x 400.0 um"),
        "{out}"
    );
    assert!(out.contains("estimated memory:"), "{out}");
}

#[test]
fn describe_json_and_schema_are_machine_readable() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let (code, out, err) = pipe(&["describe", "packing.rsa", "--json"], &root);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let size = v["params"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "size")
        .unwrap();
    assert_eq!(size["type"], "[length, length, length]");
    assert_eq!(size["unit"], "m");
    assert_eq!(size["default"], serde_json::json!([5e-4, 5e-4, 5e-4]));
    assert_eq!(v["with_schema"]["additionalProperties"], false);
    let (code, out, _) = pipe(&["schema"], &root);
    assert_eq!(code, 0);
    let s: serde_json::Value = serde_json::from_str(&out).unwrap();
    let ids = s["properties"]["stages"]["items"]["properties"]["use"]["enum"]
        .as_array()
        .unwrap();
    assert!(ids.iter().any(|i| i == "mcm.stacked"));
}
