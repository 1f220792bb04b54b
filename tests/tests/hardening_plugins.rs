//! Issue 17 regressions for plugins and untrusted pipeline files: a panic in a plugin's
//! metadata call, truncated and empty libraries, libraries named by a pipeline file (trust
//! model), and a plugin asking for more memory than there is.

use grainpipe_core::engine::{execute, plan, PlanOptions, RunOptions, SilentObserver};
use grainpipe_core::pipeline::PipelineDoc;
use grainpipe_core::plugin_host::{check_library_file, load_plugin};
use grainpipe_core::Registry;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// The misbehaving fixture plugin, built once.
fn fixture() -> &'static PathBuf {
    static LIB: OnceLock<PathBuf> = OnceLock::new();
    LIB.get_or_init(|| {
        let target = std::env::var_os("CARGO_TARGET_DIR")
            .map(PathBuf::from)
            .unwrap_or_else(|| root().join("target"));
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let ok = Command::new(cargo)
            .args(["build", "-q", "-p", "grainpipe-plugin-misbehaving"])
            .current_dir(root())
            .status()
            .expect("cargo runs")
            .success();
        assert!(ok, "building the fixture plugin failed");
        target.join("debug/libgrainpipe_plugin_misbehaving.so")
    })
}

/// Serialises the tests of this file: one of them sets an environment variable that the
/// fixture reads while loading.
fn serial() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// A private copy of the fixture (dlopen keys libraries by file: a copy loads afresh).
fn copy_of_fixture(dir: &Path, name: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::copy(fixture(), &p).unwrap();
    p
}

#[test]
fn a_panic_in_the_metadata_call_is_an_error_not_an_abort() {
    let dir = tempfile::tempdir().unwrap();
    let lib = copy_of_fixture(dir.path(), "libmeta_panic.so");
    let _serial = serial();
    std::env::set_var("GRAINPIPE_MISBEHAVE_PANIC_IN_METADATA", "1");
    let r = load_plugin(&lib, &mut Registry::new());
    std::env::remove_var("GRAINPIPE_MISBEHAVE_PANIC_IN_METADATA");
    let e = r.expect_err("refused");
    assert!(
        e.contains("panicked") && e.contains("deliberate panic in metadata"),
        "{e}"
    );
}

#[test]
fn truncated_and_empty_libraries_are_refused_before_dlopen() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let good = copy_of_fixture(dir.path(), "libgood.so");
    check_library_file(&good).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    // Cut inside the loadable segments (the code starts in the first pages): dlopen would
    // map past the end of the file and fault (SIGBUS). Debug sections at the end of the file
    // are not mapped, so cutting those alone is harmless and not refused.
    for keep in [16 * 1024, 4096, 1000, 64] {
        let cut = dir.path().join(format!("libcut{keep}.so"));
        std::fs::write(&cut, &bytes[..keep]).unwrap();
        let e = load_plugin(&cut, &mut Registry::new()).expect_err("refused");
        assert!(
            e.contains("truncated") && e.contains("libcut"),
            "{keep}: {e}"
        );
    }
    let empty = dir.path().join("libempty.so");
    std::fs::write(&empty, b"").unwrap();
    let e = load_plugin(&empty, &mut Registry::new()).expect_err("refused");
    assert!(e.contains("empty (0 bytes)"), "{e}");
    let text = dir.path().join("libtext.so");
    std::fs::write(&text, b"#!/bin/sh\necho not a library\n").unwrap();
    let e = load_plugin(&text, &mut Registry::new()).expect_err("refused");
    assert!(e.contains("not an ELF"), "{e}");
}

#[test]
fn libraries_named_by_a_pipeline_load_only_with_consent() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let lib = copy_of_fixture(dir.path(), "libevil.so");
    let yaml = format!(
        "name: t\nplugins: [{:?}]\nstages:\n  - id: s\n    use: misbehave.panic\n",
        lib.display().to_string()
    );
    let doc = PipelineDoc::parse(&dir.path().join("p.yaml"), yaml).unwrap();
    // Someone else's file: refused at its `plugins:` entry, nothing loaded.
    let mut reg = Registry::new();
    let mut loader = grainpipe_cli::PluginLoader::default();
    let e = loader.load_for(&mut reg, &doc).expect_err("refused");
    assert_eq!(e.exit_code(), 2);
    assert_eq!(e.loc.map(|l| l.line), Some(2), "{e}");
    assert!(
        e.help.as_deref().unwrap_or("").contains("--allow-plugins"),
        "{e:?}"
    );
    assert!(
        reg.stage("misbehave.panic").is_none(),
        "the library was loaded"
    );
    // --allow-plugins: loads.
    let mut loader = grainpipe_cli::PluginLoader::default();
    loader.allow_pipeline_plugins = true;
    loader.load_for(&mut reg, &doc).unwrap();
    assert!(reg.stage("misbehave.panic").is_some());
    // A configured directory holding it: loads without the flag.
    let other = tempfile::tempdir().unwrap();
    let lib2 = copy_of_fixture(other.path(), "libconfigured.so");
    let yaml = format!(
        "name: t\nplugins: [{:?}]\nstages:\n  - id: s\n    use: misbehave.panic\n",
        lib2.display().to_string()
    );
    let doc = PipelineDoc::parse(&other.path().join("p.yaml"), yaml).unwrap();
    let mut reg = Registry::new();
    let mut loader = grainpipe_cli::PluginLoader::default();
    loader
        .load(&mut reg, &[other.path().to_path_buf()])
        .unwrap();
    loader.load_for(&mut reg, &doc).unwrap();
}

#[test]
fn a_plugin_asking_for_a_terabyte_gets_an_error_not_an_abort() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let lib = copy_of_fixture(dir.path(), "libhuge.so");
    let mut reg = Registry::new();
    load_plugin(&lib, &mut reg).unwrap();
    let doc = PipelineDoc::parse(
        &dir.path().join("p.yaml"),
        "name: t\nstages:\n  - id: s\n    use: misbehave.huge\n".into(),
    )
    .unwrap();
    let p = plan(&doc, &reg, &PlanOptions::default()).unwrap();
    let e = match execute(
        &doc,
        &p,
        &RunOptions { cache_dir: None },
        &mut SilentObserver,
    ) {
        Ok(_) => panic!("must fail"),
        Err(e) => e,
    };
    assert_eq!(e.exit_code(), 1);
    assert!(e.message.contains("could not allocate"), "{e}");
}
