//! Issue 17 regressions: no panic from files or cache entries, no silent bad data, no
//! runaway run approved by preflight, exit codes that say whether anything ran. One test
//! (or more) per reproducer of the issue; each failed before its fix.

use grainpipe_core::engine::{
    execute, plan, Observer, PlanOptions, PlannedStep, RunOptions, StepStats,
};
use grainpipe_core::pipeline::{ErrorClass, PipelineDoc, PipelineError};
use grainpipe_core::stage::{Level, Reporter};
use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, Grid, InputMetas, Inputs, Outputs, PhaseImage,
    PortSpec, Preflight, Registry, RunContext, StageError, StageInfo, Table, TypedStage,
};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

fn doc(yaml: &str, dir: &Path) -> PipelineDoc {
    PipelineDoc::parse(&dir.join("h.yaml"), yaml.to_string()).unwrap()
}

fn plan_err(yaml: &str, dir: &Path) -> PipelineError {
    let d = doc(yaml, dir);
    match plan(
        &d,
        &grainpipe_cli::builtin_registry(),
        &PlanOptions::default(),
    ) {
        Ok(_) => panic!("planned although it must be refused:\n{yaml}"),
        Err(e) => e,
    }
}

/// Collects the warnings of a run.
#[derive(Default, Clone)]
struct Warnings(Arc<Mutex<Vec<String>>>);

struct Collect(Arc<Mutex<Vec<String>>>);
impl Reporter for Collect {
    fn progress(&self, _: u64, _: u64) {}
    fn message(&self, level: Level, text: &str) {
        if level == Level::Warn {
            self.0.lock().unwrap().push(text.to_string());
        }
    }
    fn cancelled(&self) -> bool {
        false
    }
}
impl Observer for Warnings {
    fn step_started(&mut self, _: &PlannedStep) -> Box<dyn Reporter> {
        Box::new(Collect(self.0.clone()))
    }
    fn step_finished(&mut self, _: &PlannedStep, _: &StepStats) {}
    fn exported(&mut self, _: &Path) {}
}

fn run_cached(
    d: &PipelineDoc,
    cache: &Path,
) -> (
    Result<grainpipe_core::engine::RunResult, PipelineError>,
    Vec<String>,
) {
    let reg = grainpipe_cli::builtin_registry();
    let p = plan(d, &reg, &PlanOptions::default()).unwrap();
    let mut w = Warnings::default();
    let r = execute(
        d,
        &p,
        &RunOptions {
            cache_dir: Some(cache.to_path_buf()),
        },
        &mut w,
    );
    let warnings = w.0.lock().unwrap().clone();
    (r, warnings)
}

// ------------------------------------------------------------------ panics from files

#[test]
fn raw_dims_whose_product_wraps_are_refused_at_plan_time() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("two.raw"), [1u8, 2]).unwrap();
    // 9223372036854775809 * 2 * 1 wraps to 2 in 64-bit arithmetic: exactly the file size.
    let yaml = format!(
        "name: h\nstages:\n  - id: img\n    use: import.raw\n    with: {{path: {:?}, dims: [9223372036854775809, 2, 1], spacing: 1 um}}\n",
        dir.path().join("two.raw").display().to_string()
    );
    let e = plan_err(&yaml, dir.path());
    assert_eq!(e.exit_code(), 2);
    assert!(e.message.contains("dims"), "{e}");
    assert_eq!(e.loc.map(|l| l.line), Some(5), "{e}");
    // The library reader refuses it too.
    let layout = grainpipe_formats::RawLayout {
        dims: [9223372036854775809, 2, 1],
        dtype: grainpipe_formats::RawDtype::U8,
        endian: grainpipe_formats::Endian::Little,
        header_bytes: 0,
    };
    assert!(layout.expected_size().is_none());
}

/// A `.vti` of one u8 cell whose zlib header claims `claimed` uncompressed bytes.
fn crafted_vti(dir: &Path, claimed: u64, nblocks: u64) -> PathBuf {
    use base64::Engine;
    use std::io::Write;
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
    z.write_all(&[1u8]).unwrap();
    let body = z.finish().unwrap();
    let mut header = vec![nblocks, claimed, 0];
    header.extend(std::iter::repeat_n(
        body.len() as u64,
        nblocks.min(4) as usize,
    ));
    let hb: Vec<u8> = header.iter().flat_map(|v| v.to_le_bytes()).collect();
    let b64 = base64::engine::general_purpose::STANDARD;
    let text = format!(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\" compressor=\"vtkZLibDataCompressor\">\n<ImageData WholeExtent=\"0 1 0 1 0 1\" Origin=\"0 0 0\" Spacing=\"1 1 1\">\n<Piece Extent=\"0 1 0 1 0 1\">\n<CellData Scalars=\"phase\">\n<DataArray type=\"UInt8\" Name=\"phase\" format=\"binary\">{}{}</DataArray>\n</CellData>\n</Piece>\n</ImageData>\n</VTKFile>\n",
        b64.encode(&hb),
        b64.encode(&body)
    );
    let p = dir.join(format!("crafted_{claimed}_{nblocks}.vti"));
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn crafted_vti_zlib_headers_are_errors_not_aborts() {
    let dir = tempfile::tempdir().unwrap();
    // The honest file reads.
    let ok = crafted_vti(dir.path(), 1, 1);
    assert!(grainpipe_formats::read_vti(&ok, None).is_ok());
    for (claimed, nblocks) in [
        (1u64 << 63, 1u64), // capacity overflow
        (1u64 << 40, 1),    // a 1 TiB allocation
        (1, 1u64 << 61),    // a header longer than the file
        (u64::MAX, 3),      // (n - 1) * block size overflows
    ] {
        let p = crafted_vti(dir.path(), claimed, nblocks);
        let e = grainpipe_formats::read_vti(&p, None).unwrap_err();
        assert!(!e.is_empty(), "{claimed} x {nblocks}");
    }
}

#[test]
fn phase_image_metadata_whose_dims_wrap_is_invalid() {
    // [2^32, 2^32, 1] wraps to 0 voxels: it matched an empty label array.
    let img = PhaseImage {
        grid: Grid {
            dims: [1 << 32, 1 << 32, 1],
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
        labels: vec![],
        phases: vec![],
    };
    assert_eq!(img.grid.checked_voxel_count(), None);
    assert_eq!(img.grid.voxel_count(), usize::MAX);
    assert!(Artifact::PhaseImage(img).validate().is_err());
}

// ------------------------------------------------------------------------ the cache

const SPHERES: &str = "name: h\nseed: 3\nstages:\n  - id: pack\n    use: packing.rsa\n    with: { size: [200 um, 200 um, 200 um], radius: { kind: fixed, value: 25 um }, volume_fraction: 0.2 }\n  - id: other\n    use: packing.rsa\n    with: { size: [200 um, 200 um, 200 um], radius: { kind: fixed, value: 20 um }, volume_fraction: 0.1 }\n  - id: img\n    use: import.raw\n    with: { path: PATH, dims: [4, 4, 4], spacing: 1 um }\n";

fn entries(cache: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(cache)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "bin"))
        .collect();
    v.sort();
    v
}

#[test]
fn a_flipped_bit_in_a_cache_entry_is_detected_and_recomputed() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("l.raw");
    std::fs::write(&raw, [0u8; 64]).unwrap();
    let d = doc(
        &SPHERES.replace("PATH", &format!("{:?}", raw.display().to_string())),
        dir.path(),
    );
    let cache = dir.path().join("cache");
    let (first, w) = run_cached(&d, &cache);
    let first = first.unwrap();
    assert!(w.is_empty(), "{w:?}");
    let reg = grainpipe_cli::builtin_registry();
    let key = plan(&d, &reg, &PlanOptions::default()).unwrap().steps[0]
        .as_ref()
        .unwrap()
        .cache_key
        .clone();
    let entry = cache.join(format!("{key}.bin"));
    let mut bytes = std::fs::read(&entry).unwrap();
    let last = bytes.len() - 20;
    bytes[last] ^= 0x10; // one bit of the payload (a radius or a position)
    std::fs::write(&entry, &bytes).unwrap();
    let (again, w) = run_cached(&d, &cache);
    let again = again.unwrap();
    assert!(
        !again.stats["pack"].from_cache,
        "a corrupt entry was served"
    );
    assert!(w.iter().any(|m| m.contains("corrupt")), "{w:?}");
    assert_eq!(
        again.outputs["pack"]["packing"],
        first.outputs["pack"]["packing"]
    );
    // The recomputed entry is good again.
    let (third, w) = run_cached(&d, &cache);
    assert!(third.unwrap().stats["pack"].from_cache && w.is_empty());
}

#[test]
fn a_cache_entry_copied_onto_another_step_s_key_is_recomputed_not_trusted() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("l.raw");
    std::fs::write(&raw, [0u8; 64]).unwrap();
    let d = doc(
        &SPHERES.replace("PATH", &format!("{:?}", raw.display().to_string())),
        dir.path(),
    );
    let cache = dir.path().join("cache");
    run_cached(&d, &cache).0.unwrap();
    let reg = grainpipe_cli::builtin_registry();
    let p = plan(&d, &reg, &PlanOptions::default()).unwrap();
    let key = |i: usize| p.steps[i].as_ref().unwrap().cache_key.clone();
    // The image entry (a PhaseImage) onto the packing step, the other packing onto it too.
    for from in [2usize, 1] {
        std::fs::copy(
            cache.join(format!("{}.bin", key(from))),
            cache.join(format!("{}.bin", key(0))),
        )
        .unwrap();
        let (r, w) = run_cached(&d, &cache);
        let r = r.expect("no panic, no error: the step is recomputed");
        assert!(!r.stats["pack"].from_cache);
        assert!(!w.is_empty(), "the refusal is said");
        assert_eq!(
            r.outputs["pack"]["packing"]
                .as_packing()
                .unwrap()
                .bodies
                .len(),
            r.outputs["pack"]["packing"]
                .as_packing()
                .unwrap()
                .bodies
                .len()
        );
        assert!(r.outputs["pack"]["packing"].as_packing().is_some());
    }
    assert_eq!(entries(&cache).len(), 3);
}

// ---------------------------------------------------------------------------- exports

#[test]
fn export_targets_that_collide_or_name_directories_are_refused_at_plan_time() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("existing")).unwrap();
    let base = "name: h\nstages:\n  - id: pack\n    use: packing.rsa\n    with: { size: [200 um, 200 um, 200 um], volume_fraction: 0.1 }\nexport:\n";
    let existing = dir.path().join("existing").display().to_string();
    for (exports, needle) in [
        (
            "  - { from: pack.packing, to: out/a.vtp }\n  - { from: pack.packing, to: out/./a.vtp }\n".to_string(),
            "already the target",
        ),
        ("  - { from: pack.packing, to: '', format: vtp }\n".to_string(), "empty"),
        ("  - { from: pack.packing, to: ., format: vtp }\n".to_string(), "directory"),
        ("  - { from: pack.packing, to: out/, format: vtp }\n".to_string(), "directory"),
        (
            format!("  - {{ from: pack.packing, to: {existing:?}, format: vtp }}\n"),
            "directory",
        ),
        (
            "  - { from: pack.packing, to: /dev/null, format: vtp }\n".to_string(),
            "not a regular file",
        ),
    ] {
        let e = plan_err(&format!("{base}{exports}"), dir.path());
        assert_eq!(e.exit_code(), 2, "{e}");
        assert!(e.message.contains(needle), "{exports}: {e}");
        assert!(e.loc.is_some_and(|l| l.line >= 7), "{e}");
    }
}

// ------------------------------------------------------------------ preflight bounds

#[test]
fn sparse_rsa_box_gets_a_cell_list_sized_by_its_spheres() {
    let dir = tempfile::tempdir().unwrap();
    let yaml = "name: h\nstages:\n  - id: pack\n    use: packing.rsa\n    with: { size: [0.25, 0.25, 0.25], radius: { kind: fixed, value: 25 um }, volume_fraction: 1e-9 }\n";
    let d = doc(yaml, dir.path());
    let reg = grainpipe_cli::builtin_registry();
    let p = plan(&d, &reg, &PlanOptions::default()).unwrap();
    assert!(p.memory_bytes < 1 << 20, "estimate {}", p.memory_bytes);
    let t = std::time::Instant::now();
    let r = grainpipe_core::engine::run_quietly(&d, &reg).unwrap();
    assert!(!r.outputs["pack"]["packing"]
        .as_packing()
        .unwrap()
        .bodies
        .is_empty());
    // A 1024^3 (or 2^24) cell list takes seconds to allocate and fill with empty cells.
    assert!(t.elapsed().as_secs_f64() < 1.0, "{:?}", t.elapsed());
}

#[test]
fn method2_with_a_broad_law_is_refused_from_its_tail() {
    let dir = tempfile::tempdir().unwrap();
    let yaml = "name: h\nstages:\n  - id: bed\n    use: bricks.method2\n    with:\n      radius: { kind: lognormal, median: 10 um, sigma: 2.5 }\n      std_length: 30\n";
    let e = plan_err(yaml, dir.path());
    assert_eq!(e.exit_code(), 2);
    assert!(
        e.message.contains("radius") && e.message.contains("quantile"),
        "{e}"
    );
    assert_eq!(e.loc.map(|l| l.line), Some(6), "{e}");
}

/// A reporter that says "cancelled" once `after` has passed.
struct CancelAfter(std::time::Instant, std::time::Duration);
impl Reporter for CancelAfter {
    fn progress(&self, _: u64, _: u64) {}
    fn message(&self, _: Level, _: &str) {}
    fn cancelled(&self) -> bool {
        self.0.elapsed() > self.1
    }
}

#[test]
fn ctrl_c_stops_rsa_near_jamming() {
    // Monodisperse spheres at 0.375 in a small walled box jam: the last spheres spend their
    // (here huge) attempt budgets; before, the cancel flag was read only between spheres.
    let reg = grainpipe_cli::builtin_registry();
    let stage = reg.stage("packing.rsa").unwrap().stage.clone();
    let params = stage
        .normalize_params(&serde_json::json!({
            "size": ["100 um", "100 um", "100 um"],
            "radius": {"kind": "fixed", "value": "10 um"},
            "volume_fraction": 0.375,
            "max_attempts_per_sphere": 2_000_000_000u64
        }))
        .unwrap();
    let (_, prepared) = stage.preflight(&params, &InputMetas::new()).unwrap();
    let reporter = CancelAfter(
        std::time::Instant::now(),
        std::time::Duration::from_millis(200),
    );
    let ctx = RunContext::new(1, &reporter);
    let t = std::time::Instant::now();
    let r = stage.run(&params, &prepared, &Inputs::new(), &ctx);
    assert!(
        matches!(r, Err(StageError::Cancelled)),
        "{:?}",
        r.map(|_| ())
    );
    assert!(t.elapsed().as_secs_f64() < 5.0, "{:?}", t.elapsed());
}

// ------------------------------------------------------------------------ exit codes

#[params]
struct FailParams {
    /// How to fail at run time: "input", "cancel" or "" (succeed).
    mode: String,
}

/// Gives a one-row table, or fails at run time the way `mode` says.
struct Fails;
impl TypedStage for Fails {
    type Params = FailParams;
    type Plan = ();
    fn info(&self) -> StageInfo {
        StageInfo::new("test.fails", "1", "fails on request").outputs(vec![PortSpec::new(
            "table",
            ArtifactKind::Table,
            "a row",
        )])
    }
    fn preflight(&self, _: &FailParams, _: &InputMetas) -> Result<Preflight, StageError> {
        Ok(Preflight::from_info(&self.info(), 8)
            .announce("table", ArtifactMeta::of(ArtifactKind::Table)))
    }
    fn run(
        &self,
        p: &FailParams,
        _: &(),
        _: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        match p.mode.as_str() {
            "input" => Err(StageError::input("x", "the file changed since planning")),
            "cancel" => Err(StageError::Cancelled),
            _ => {
                let mut o = Outputs::new();
                o.insert(
                    "table".into(),
                    Artifact::Table(Table::new("t").with_f64("x", "1", vec![1.0])),
                );
                Ok(o)
            }
        }
    }
}

fn run_fails(steps: &[&str]) -> PipelineError {
    let mut yaml = String::from("name: h\nstages:\n");
    for (k, mode) in steps.iter().enumerate() {
        yaml.push_str(&format!(
            "  - id: s{k}\n    use: test.fails\n    with: {{ mode: {mode:?} }}\n"
        ));
    }
    let d = PipelineDoc::parse(Path::new("h.yaml"), yaml).unwrap();
    let mut reg = Registry::new();
    reg.add_stage(Fails);
    let p = plan(&d, &reg, &PlanOptions::default()).unwrap();
    match execute(
        &d,
        &p,
        &RunOptions { cache_dir: None },
        &mut grainpipe_core::engine::SilentObserver,
    ) {
        Ok(_) => panic!("must fail"),
        Err(e) => e,
    }
}

#[test]
fn exit_code_2_only_when_nothing_ran_and_130_when_interrupted() {
    let first = run_fails(&["input"]);
    assert_eq!((first.class, first.exit_code()), (ErrorClass::Input, 2));
    let after = run_fails(&["", "input"]);
    assert_eq!(after.exit_code(), 1, "a step already ran: {after}");
    assert_eq!(run_fails(&["", "cancel"]).exit_code(), 130);
    assert_eq!(run_fails(&["cancel"]).exit_code(), 130);
}
