//! Third-party plugins through the C ABI: a Rust plugin and a C plugin give the same
//! porosity profile as an independent computation; wrong ABI versions, foreign libraries,
//! panics and buffer overruns are refused or contained with clear errors.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// Builds the Rust example plugins once and returns the directory holding them.
fn rust_plugins() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let target = std::env::var_os("CARGO_TARGET_DIR")
            .map(PathBuf::from)
            .unwrap_or_else(|| root().join("target"));
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let status = Command::new(cargo)
            .args([
                "build",
                "-q",
                "-p",
                "grainpipe-plugin-example",
                "-p",
                "grainpipe-plugin-misbehaving",
            ])
            .current_dir(root())
            .status()
            .expect("cargo runs");
        assert!(status.success(), "building the example plugins failed");
        // Keep only the plugins in a directory of their own, as a user would ship them.
        let dir = std::env::temp_dir().join(format!("grainpipe-plugins-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for name in [
            "libgrainpipe_plugin_example.so",
            "libgrainpipe_plugin_misbehaving.so",
        ] {
            std::fs::copy(target.join("debug").join(name), dir.join(name)).unwrap();
        }
        dir
    })
}

/// Compiles a C source into a shared library in `dir`.
fn cc(source: &Path, out: &Path) {
    let status = Command::new(std::env::var("CC").unwrap_or_else(|_| "cc".into()))
        .args(["-shared", "-fPIC", "-O2", "-Wall", "-Werror", "-I"])
        .arg(root().join("plugin-api/include"))
        .arg("-o")
        .arg(out)
        .arg(source)
        .status()
        .expect("a C compiler runs");
    assert!(status.success(), "cc failed for {}", source.display());
}

fn pipe(args: &[&str], dir: &Path) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_pipe"))
        .args(args)
        .current_dir(dir)
        .env_remove("GRAINPIPE_PLUGIN_PATH")
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

const PROFILE_PIPELINE: &str = "name: plugin-profile\nseed: 9\nplugins: [libporosity_c.so]\nstages:
  - id: pack
    use: packing.rsa
    with: { size: [200 um, 200 um, 200 um], volume_fraction: 0.25 }
  - id: vox
    use: voxelize.packing
    in: { packing: pack.packing }
    with: { voxels_per_diameter: 6 }
  - id: rust
    use: example.porosity_profile
    in: { image: vox.image }
    with: { axis: y }
  - id: c
    use: example_c.porosity_profile
    in: { image: vox.image }
    with: { axis: y }
export:
  - { from: vox.image, to: out/image.h5 }
  - { from: rust.profile, to: out/rust.csv }
  - { from: c.profile, to: out/c.csv }
";

#[test]
fn rust_and_c_plugins_match_an_independent_profile() {
    let dir = tempfile::tempdir().unwrap();
    cc(
        &root().join("examples/plugin-c/porosity.c"),
        &dir.path().join("libporosity_c.so"),
    );
    std::fs::write(dir.path().join("p.yaml"), PROFILE_PIPELINE).unwrap();
    let plugins = rust_plugins().to_str().unwrap().to_string();
    let (code, _, err) = pipe(
        &[
            "run",
            "p.yaml",
            "--quiet",
            "--allow-plugins",
            "--plugin-dir",
            &plugins,
        ],
        dir.path(),
    );
    assert_eq!(code, 0, "{err}");
    // Independent reference: the profile recomputed from the exported image.
    let img = grainpipe_formats::read_h5(&dir.path().join("out/image.h5")).unwrap();
    let img = img.as_phase_image().unwrap();
    let [nx, ny, nz] = img.grid.dims;
    let expected: Vec<f64> = (0..ny)
        .map(|y| {
            let pores = (0..nz)
                .flat_map(|z| (0..nx).map(move |x| (x, z)))
                .filter(|&(x, z)| img.labels[img.grid.index(x, y, z)] == 0)
                .count();
            pores as f64 / (nx * nz) as f64
        })
        .collect();
    for name in ["rust.csv", "c.csv"] {
        let t = grainpipe_formats::read_table_csv(&dir.path().join("out").join(name)).unwrap();
        let got = t.f64_column("porosity").unwrap();
        assert_eq!(got.len(), ny);
        for (g, e) in got.iter().zip(&expected) {
            // Both are ratios of the same integer counts: equal up to the CSV's decimal rounding.
            assert!((g - e).abs() < 1e-12, "{name}: {g} vs {e}");
        }
        let pos = t.f64_column("position").unwrap();
        assert!((pos[0] - (img.grid.origin[1] + 0.5 * img.grid.spacing[1])).abs() < 1e-15);
    }
    // A second run takes the plugin stages from the cache like built-in ones.
    let (code, _, err) = pipe(
        &["run", "p.yaml", "--allow-plugins", "--plugin-dir", &plugins],
        dir.path(),
    );
    assert_eq!(code, 0, "{err}");
    for step in [
        "rust (example.porosity_profile)",
        "c (example_c.porosity_profile)",
    ] {
        assert!(
            err.lines().any(|l| l == format!("cached {step}")),
            "{step} not served from the cache:\n{err}"
        );
    }
}

#[test]
fn list_and_describe_show_where_plugin_stages_come_from() {
    let dir = tempfile::tempdir().unwrap();
    let plugins = rust_plugins().to_str().unwrap().to_string();
    let (code, out, err) = pipe(&["list", "--plugin-dir", &plugins], dir.path());
    assert_eq!(code, 0, "{err}");
    let line = out
        .lines()
        .find(|l| l.contains("example.porosity_profile"))
        .expect("listed");
    assert!(line.contains("libgrainpipe_plugin_example.so"), "{line}");
    let (code, out, _) = pipe(
        &[
            "describe",
            "example.porosity_profile",
            "--plugin-dir",
            &plugins,
        ],
        dir.path(),
    );
    assert_eq!(code, 0);
    assert!(
        out.contains("axis") && out.contains("pore_label") && out.contains("image: PhaseImage"),
        "{out}"
    );
}

#[test]
fn plugin_parameters_are_checked_with_locations() {
    let dir = tempfile::tempdir().unwrap();
    let plugins = rust_plugins().to_str().unwrap().to_string();
    let yaml = PROFILE_PIPELINE
        .replace("plugins: [libporosity_c.so]\n", "")
        .replace("with: { axis: y }", "with: { axes: y }");
    let yaml = &yaml[..yaml.find("  - id: c").unwrap()];
    std::fs::write(dir.path().join("p.yaml"), yaml).unwrap();
    let (code, _, err) = pipe(
        &["validate", "p.yaml", "--plugin-dir", &plugins],
        dir.path(),
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("p.yaml:14:13") && err.contains("did you mean `axis`"),
        "{err}"
    );
    std::fs::write(
        dir.path().join("p.yaml"),
        yaml.replace("axes: y", "axis: w"),
    )
    .unwrap();
    let (code, _, err) = pipe(
        &["validate", "p.yaml", "--plugin-dir", &plugins],
        dir.path(),
    );
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("is not one of x, y, z"), "{err}");
    // Two mistakes in one step: both reported in one run, each at its own key.
    std::fs::write(
        dir.path().join("p.yaml"),
        yaml.replace("axes: y", "axes: y, pore_label: none"),
    )
    .unwrap();
    let (code, _, err) = pipe(
        &["validate", "p.yaml", "--plugin-dir", &plugins],
        dir.path(),
    );
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("p.yaml:14:13")
            && err.contains("did you mean `axis`")
            && err.contains("parameter `pore_label`: expected a number, got a string"),
        "{err}"
    );
}

#[test]
fn wrong_abi_version_and_foreign_libraries_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("future.c");
    std::fs::write(
        &src,
        "#include <stdint.h>\nuint32_t grainpipe_abi_version(void) { return (2u << 16) | 3u; }\n",
    )
    .unwrap();
    cc(&src, &dir.path().join("libfuture.so"));
    let (code, _, err) = pipe(
        &["list", "--plugin-dir", dir.path().to_str().unwrap()],
        dir.path(),
    );
    assert_eq!(code, 2);
    assert!(err.contains("ABI 2.3") && err.contains("ABI 1.0"), "{err}");

    let other = tempfile::tempdir().unwrap();
    let src = other.path().join("foreign.c");
    std::fs::write(&src, "int not_a_plugin(void) { return 1; }\n").unwrap();
    cc(&src, &other.path().join("libforeign.so"));
    let (code, _, err) = pipe(
        &["list", "--plugin-dir", other.path().to_str().unwrap()],
        other.path(),
    );
    assert_eq!(code, 2);
    assert!(
        err.contains("is not a grainpipe plugin") && err.contains("grainpipe_abi_version"),
        "{err}"
    );

    let (code, _, err) = pipe(
        &["list", "--plugin-dir", "/nonexistent/plugins"],
        other.path(),
    );
    assert_eq!(code, 2);
    assert!(err.contains("does not exist"), "{err}");
}

#[test]
fn panics_and_buffer_overruns_become_stage_errors() {
    let dir = tempfile::tempdir().unwrap();
    let plugins = rust_plugins().to_str().unwrap().to_string();
    for (stage, needle) in [
        ("misbehave.panic", "deliberate panic"),
        ("misbehave.overflow", "index out of bounds"),
    ] {
        let yaml = format!("name: t\nstages:\n  - id: s\n    use: {stage}\n");
        std::fs::write(dir.path().join("p.yaml"), yaml).unwrap();
        let (code, _, err) = pipe(
            &[
                "run",
                "p.yaml",
                "--quiet",
                "--no-cache",
                "--plugin-dir",
                &plugins,
            ],
            dir.path(),
        );
        assert_eq!(code, 1, "{stage}: {err}");
        assert!(
            err.contains("plugin panicked") && err.contains(needle),
            "{stage}: {err}"
        );
    }
}

#[test]
fn plugins_from_the_environment_path() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_pipe"))
        .args(["describe", "example.porosity_profile"])
        .current_dir(dir.path())
        .env("GRAINPIPE_PLUGIN_PATH", rust_plugins())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
