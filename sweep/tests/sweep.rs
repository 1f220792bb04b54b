//! End-to-end sweeps and studies over small real pipelines. The runs are child processes as
//! with `pipe`: this test binary re-runs itself with `child_entry` (an ignored test that acts
//! as `pipe sweep run-one DIR ID` when GP_SWEEP_DIR/GP_SWEEP_ID are set).

use grainpipe_core::engine::run_quietly;
use grainpipe_core::pipeline::PipelineDoc;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, ColumnData, InputMetas, Inputs, Outputs,
    PortSpec, Preflight, Registry, RunContext, StageError, StageInfo, Table, TypedStage,
};
use grainpipe_sweep::runner::{self, LocalOptions};
use grainpipe_sweep::spec::{self, Manifest};
use grainpipe_sweep::{prepare, SetupArgs, StudyArgs};
use std::path::Path;
use std::process::Command;

/// The volume of a sphere of radius `radius` voxelised in slices of thickness `voxel_size`
/// (a stack of cylinders through the slice centres): the midpoint rule on pi (R^2 - z^2),
/// whose error is exactly pi R h^2 / 6, a problem of known order 2.
#[params]
struct SlicedParams {
    /// slice thickness
    #[param(default = Q::new(1e-5))]
    voxel_size: Q<Length>,
    /// sphere radius
    #[param(default = Q::new(1e-4))]
    radius: Q<Length>,
}

struct SlicedSphere;

impl TypedStage for SlicedSphere {
    type Params = SlicedParams;
    type Plan = ();
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "test.sliced_sphere",
            "1.0.0",
            "Test stage: a sliced sphere's volume.",
        )
        .outputs(vec![
            PortSpec::new("report", ArtifactKind::Table, "volume"),
            PortSpec::new("volume", ArtifactKind::Tensor, "the volume as a 1-tensor"),
        ])
    }
    fn preflight(&self, p: &SlicedParams, _: &InputMetas) -> Result<Preflight, StageError> {
        if p.voxel_size.si().is_nan() || p.voxel_size.si() <= 0.0 {
            return Err(StageError::param("voxel_size", "must be positive"));
        }
        Ok(Preflight::from_info(&self.info(), 1024)
            .announce("report", ArtifactMeta::of(ArtifactKind::Table))
            .announce("volume", ArtifactMeta::of(ArtifactKind::Tensor)))
    }
    fn run(
        &self,
        p: &SlicedParams,
        _: &(),
        _: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        let (h, r) = (p.voxel_size.si(), p.radius.si());
        let n = (2.0 * r / h).round() as usize;
        let h = 2.0 * r / n as f64;
        let v: f64 = (0..n)
            .map(|k| {
                let z = -r + (k as f64 + 0.5) * h;
                std::f64::consts::PI * (r * r - z * z) * h
            })
            .sum();
        let mut o = Outputs::new();
        o.insert(
            "report".into(),
            Artifact::Table(Table::new("v").with_f64("volume", "m^3", vec![v])),
        );
        o.insert(
            "volume".into(),
            Artifact::Tensor(grainpipe_core::Tensor {
                name: "volume".into(),
                unit: "m^3".into(),
                shape: vec![1],
                values: vec![v],
                convention: grainpipe_core::TensorConvention::Plain,
            }),
        );
        Ok(o)
    }
}

/// A run that takes `seconds` of wall time (and checks for interruption while it waits): the
/// live child that the process tests kill.
#[params]
struct WaitParams {
    /// how long to wait [s]
    #[param(default = 1.0)]
    seconds: f64,
}

struct Wait;

impl TypedStage for Wait {
    type Params = WaitParams;
    type Plan = ();
    fn info(&self) -> StageInfo {
        StageInfo::new("test.wait", "1.0.0", "Test stage: waits.").outputs(vec![PortSpec::new(
            "report",
            ArtifactKind::Table,
            "waited",
        )])
    }
    fn preflight(&self, _: &WaitParams, _: &InputMetas) -> Result<Preflight, StageError> {
        Ok(Preflight::from_info(&self.info(), 1024)
            .announce("report", ArtifactMeta::of(ArtifactKind::Table)))
    }
    fn run(
        &self,
        p: &WaitParams,
        _: &(),
        _: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        let t = std::time::Instant::now();
        while t.elapsed().as_secs_f64() < p.seconds {
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let mut o = Outputs::new();
        o.insert(
            "report".into(),
            Artifact::Table(Table::new("w").with_f64("seconds", "s", vec![p.seconds])),
        );
        Ok(o)
    }
}

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_geometry::register(&mut r);
    grainpipe_analysis::register(&mut r);
    r.add_stage(SlicedSphere);
    r.add_stage(Wait);
    r
}

#[test]
#[ignore = "the child process of the other tests"]
fn child_entry() {
    let (Ok(dir), Ok(id)) = (std::env::var("GP_SWEEP_DIR"), std::env::var("GP_SWEEP_ID")) else {
        return;
    };
    let mut reg = registry();
    match runner::run_one(Path::new(&dir), &id, &mut reg, &mut |_, _| Ok(())).unwrap() {
        Some(r) => std::process::exit(if r.status == "ok" { 0 } else { 1 }),
        None => std::process::exit(i32::from(runner::EXIT_RUN_BUSY)),
    }
}

#[test]
#[ignore = "the runner process of `a_killed_runner_takes_its_runs_with_it`"]
fn runner_entry() {
    let Ok(dir) = std::env::var("GP_RUNNER_DIR") else {
        return;
    };
    let dir = Path::new(&dir);
    let m = Manifest::load(dir).unwrap();
    let todo: Vec<usize> = (0..m.runs.len()).collect();
    runner::run_local(dir, &m, &todo, &opts(1, None), &launcher());
}

fn launcher() -> impl Fn(&Path, &str) -> Command + Sync {
    let exe = std::env::current_exe().unwrap();
    move |dir: &Path, id: &str| {
        let mut c = Command::new(&exe);
        c.args([
            "child_entry",
            "--exact",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .env("GP_SWEEP_DIR", dir)
        .env("GP_SWEEP_ID", id)
        .env("RAYON_NUM_THREADS", "1");
        c
    }
}

const PIPELINE: &str = "name: tiny
seed: 7
stages:
  - id: pack
    use: packing.rsa
    with:
      size: [200 um, 200 um, 200 um]
      radius: { kind: fixed, value: 25 um }
      volume_fraction: 0.2
  - id: voxels
    use: voxelize.packing
    in: { packing: pack.packing }
    with: { voxels_per_diameter: 6 }
  - id: phases
    use: analysis.phases
    in: { image: voxels.image }
export:
  - { from: phases.phases, to: out/tiny/phases.csv }
";

fn setup(dir: &Path, vary: &[&str], realizations: usize, collect: &[&str]) -> SetupArgs {
    let file = dir.join("tiny.yaml");
    if !file.exists() {
        std::fs::write(&file, PIPELINE).unwrap();
    }
    SetupArgs {
        file: Some(file),
        vary: vary.iter().map(|s| s.to_string()).collect(),
        realizations,
        collect: collect.iter().map(|s| s.to_string()).collect(),
        out: Some(dir.join("sweep")),
        cache_dir: dir.join("cache"),
        quiet: true,
        ..Default::default()
    }
}

fn opts(jobs: usize, stop_after: Option<usize>) -> LocalOptions {
    LocalOptions {
        jobs,
        memory_budget: spec::available_memory(),
        stop_after,
        quiet: true,
    }
}

fn mtime(p: &Path) -> std::time::SystemTime {
    std::fs::metadata(p).unwrap().modified().unwrap()
}

/// Every combination runs once; an interrupted sweep resumes without redoing finished runs; a
/// re-run does nothing; an impossible point fails at run time and is counted and recorded; the
/// collected values equal an in-process run of the same pipeline with the run's overrides and
/// seed; realization k has the same seed at every point.
#[test]
fn sweep_runs_once_resumes_and_records_failures() {
    let tmp = tempfile::tempdir().unwrap();
    let a = setup(
        tmp.path(),
        &[
            "pack.volume_fraction=0.15,0.25",
            "pack.max_attempts_per_sphere=200000,1",
        ],
        2,
        &[
            "phases.phases.volume_fraction",
            "voxels.report.image_fraction",
        ],
    );
    let mut reg = registry();
    let launch = launcher();
    let p = prepare(&a, &mut reg, &mut |_, _| Ok(())).unwrap();
    assert_eq!(p.manifest.runs.len(), 8);
    assert_eq!(p.todo.len(), 8);
    // Interrupted after 3 runs.
    let (done, _) = runner::run_local(&p.dir, &p.manifest, &p.todo, &opts(1, Some(3)), &launch);
    assert_eq!(done, 3);
    let first: Vec<_> = p.manifest.runs[..3]
        .iter()
        .map(|r| mtime(&runner::result_path(&p.dir, &r.id)))
        .collect();
    assert!(runner::load_result(&p.dir, &p.manifest.runs[3].id).is_none());
    // Resume: only the 5 others run.
    let p = prepare(&a, &mut reg, &mut |_, _| Ok(())).unwrap();
    assert_eq!(p.todo, (3..8).collect::<Vec<_>>());
    let (done, failed) = runner::run_local(&p.dir, &p.manifest, &p.todo, &opts(2, None), &launch);
    assert_eq!(
        (done, failed),
        (5, 3),
        "points with one attempt per sphere jam"
    );
    for (r, t) in p.manifest.runs[..3].iter().zip(&first) {
        assert_eq!(
            mtime(&runner::result_path(&p.dir, &r.id)),
            *t,
            "{} was redone",
            r.id
        );
    }
    // Nothing left to do.
    let p = prepare(&a, &mut reg, &mut |_, _| Ok(())).unwrap();
    assert!(p.todo.is_empty());
    let (t, counts) = grainpipe_sweep::table::write_tables(&p.dir, &p.manifest).unwrap();
    assert_eq!((counts.ok, counts.failed, counts.missing), (4, 4, 0));
    // The table: one row per run, failures with their error and NaN values.
    assert_eq!(t.rows(), 8);
    let status = match &t.column("status").unwrap().data {
        ColumnData::Str(s) => s.clone(),
        _ => panic!("status is text"),
    };
    let errors = match &t.column("error").unwrap().data {
        ColumnData::Str(s) => s.clone(),
        _ => panic!("error is text"),
    };
    let attempts = t.f64_column("pack.max_attempts_per_sphere").unwrap();
    let solid = t.f64_column("phases.phases.volume_fraction[1]").unwrap();
    for k in 0..8 {
        assert_eq!(
            status[k] == "ok",
            attempts[k] > 1.0,
            "row {k}: {}",
            errors[k]
        );
        if status[k] != "ok" {
            assert!(errors[k].contains("jammed"), "{}", errors[k]);
            assert!(solid[k].is_nan());
        }
    }
    assert_eq!(
        t.column("phases.phases.volume_fraction[1]").unwrap().unit,
        "1"
    );
    // Common random numbers.
    let seeds = match &t.column("seed").unwrap().data {
        ColumnData::I64(s) => s.clone(),
        _ => panic!(),
    };
    assert_eq!(seeds[0], seeds[2]);
    assert_ne!(seeds[0], seeds[1]);
    // Independent reference: the same pipeline run in-process with the run's overrides and
    // seed (no cache, no child process) gives the same numbers.
    let run = &p.manifest.runs[5]; // p002-r01: volume_fraction 0.25, 200000 attempts
    assert_eq!(
        run.overrides,
        [
            "pack.volume_fraction=0.25",
            "pack.max_attempts_per_sphere=200000"
        ]
    );
    let mut doc = PipelineDoc::load(&tmp.path().join("tiny.yaml")).unwrap();
    for o in &run.overrides {
        doc.apply_override(o).unwrap();
    }
    doc.seed = run.seed;
    doc.redirect_exports(&tmp.path().join("reference"));
    let reference = run_quietly(&doc, &registry()).unwrap();
    assert_eq!(
        reference.column("phases.phases", "volume_fraction")[1],
        solid[5]
    );
    // Exports of each run went to its own folder.
    assert!(p.dir.join("runs/p002-r01/tiny/phases.csv").is_file());
    // The HDF5 table holds the same and the summary has one row per point and quantity.
    let h5 = grainpipe_formats::read_h5_table(&p.dir.join("sweep.h5")).unwrap();
    assert_eq!(
        h5.f64_column("phases.phases.volume_fraction[1]")
            .unwrap()
            .len(),
        8
    );
    let csv = grainpipe_formats::read_table_csv(&p.dir.join("sweep.csv")).unwrap();
    assert_eq!(csv.rows(), 8);
    let summary = grainpipe_formats::read_table_csv(&p.dir.join("summary.csv")).unwrap();
    let n_failed = match &summary.column("n_failed").unwrap().data {
        ColumnData::I64(v) => v.clone(),
        _ => panic!(),
    };
    assert_eq!(
        n_failed.iter().sum::<i64>(),
        4 * 3,
        "4 failed runs x 3 collected quantities"
    );
    // A different sweep in the same directory is refused.
    let other = setup(tmp.path(), &["pack.volume_fraction=0.15"], 2, &[]);
    assert!(prepare(&other, &mut reg, &mut |_, _| Ok(())).is_err());
}

/// Issue 36: `--realizations N` on an existing sweep directory adds realizations: only the
/// new runs are to do, the runs on record are not recomputed, the table holds all of them,
/// and asking for fewer than the directory holds is refused.
#[test]
fn more_realizations_extend_a_sweep() {
    let tmp = tempfile::tempdir().unwrap();
    let vary = ["pack.volume_fraction=0.15,0.25"];
    let collect = ["phases.phases.volume_fraction"];
    let mut reg = registry();
    let launch = launcher();
    let p = prepare(
        &setup(tmp.path(), &vary, 2, &collect),
        &mut reg,
        &mut |_, _| Ok(()),
    )
    .unwrap();
    let (done, failed) = runner::run_local(&p.dir, &p.manifest, &p.todo, &opts(2, None), &launch);
    assert_eq!((done, failed), (4, 0));
    let before: Vec<_> = p
        .manifest
        .runs
        .iter()
        .map(|r| (r.id.clone(), mtime(&runner::result_path(&p.dir, &r.id))))
        .collect();
    let p = prepare(
        &setup(tmp.path(), &vary, 3, &collect),
        &mut reg,
        &mut |_, _| Ok(()),
    )
    .unwrap();
    assert_eq!(p.manifest.realizations, 3);
    assert_eq!(p.manifest.runs.len(), 6);
    let todo: Vec<_> = p
        .todo
        .iter()
        .map(|&i| p.manifest.runs[i].id.as_str())
        .collect();
    assert_eq!(todo, ["p000-r02", "p001-r02"]);
    let (done, failed) = runner::run_local(&p.dir, &p.manifest, &p.todo, &opts(2, None), &launch);
    assert_eq!((done, failed), (2, 0));
    for (id, t) in &before {
        assert_eq!(
            mtime(&runner::result_path(&p.dir, id)),
            *t,
            "{id} was not rerun"
        );
    }
    let (table, _) = grainpipe_sweep::table::write_tables(&p.dir, &p.manifest).unwrap();
    assert_eq!(table.rows(), 6);
    // Issue 36: the charts name a table row's value by its column and row
    // (`volume_fraction (grain)`), as the report does, not by its CSV index (`[1]`).
    grainpipe_sweep::charts::sweep_charts(&p.dir, &table, &p.manifest).unwrap();
    let svg = std::fs::read_to_string(p.dir.join("charts").join(format!(
        "violin_{}.svg",
        grainpipe_sweep::charts::sanitize("phases.phases.volume_fraction[1]")
    )))
    .unwrap();
    assert!(
        svg.contains("phases.phases volume_fraction (grain): distribution per point"),
        "title"
    );
    // The new realization is the one a 3-realization sweep planned from the start runs.
    let fresh = tempfile::tempdir().unwrap();
    let q = prepare(
        &setup(fresh.path(), &vary, 3, &collect),
        &mut reg,
        &mut |_, _| Ok(()),
    )
    .unwrap();
    assert_eq!(q.manifest.runs[2].seed, p.manifest.runs[2].seed);
    // A directory only grows.
    assert!(prepare(
        &setup(tmp.path(), &vary, 1, &collect),
        &mut reg,
        &mut |_, _| Ok(())
    )
    .is_err());
}

/// Every parameter point is preflighted before anything runs and every invalid point is
/// reported, with the did-you-mean help of `--set`.
const WAIT_PIPELINE: &str = "name: wait
seed: 3
stages:
  - id: wait
    use: test.wait
    with: { seconds: 120 }
";

fn wait_sweep(dir: &Path, realizations: usize) -> grainpipe_sweep::Prepared {
    let file = dir.join("wait.yaml");
    std::fs::write(&file, WAIT_PIPELINE).unwrap();
    let a = SetupArgs {
        file: Some(file),
        realizations,
        collect: vec!["wait.report.seconds".into()],
        out: Some(dir.join("sweep")),
        no_cache: true,
        quiet: true,
        ..Default::default()
    };
    prepare(&a, &mut registry(), &mut |_, _| Ok(())).unwrap()
}

fn wait_until(what: &str, limit_s: f64, mut done: impl FnMut() -> bool) {
    let t = std::time::Instant::now();
    while !done() {
        assert!(
            t.elapsed().as_secs_f64() < limit_s,
            "{what}: not within {limit_s} s"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

/// Issue 35: a sweep killed with SIGKILL used to leave its `run-one` child computing, and a
/// resume then ran the same id twice at once. The child now dies with its runner (parent-death
/// signal), which the run's lock shows: held while the child lives, free once it is gone.
#[cfg(target_os = "linux")]
#[test]
fn a_killed_runner_takes_its_runs_with_it() {
    let tmp = tempfile::tempdir().unwrap();
    let p = wait_sweep(tmp.path(), 1);
    let id = p.manifest.runs[0].id.clone();
    let mut runner = Command::new(std::env::current_exe().unwrap())
        .args(["runner_entry", "--exact", "--ignored", "--test-threads=1"])
        .env("GP_RUNNER_DIR", &p.dir)
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // The child holds the run's lock while it computes (a 120 s wait).
    wait_until("the child takes the run's lock", 60.0, || {
        runner::lock_run(&p.dir, &id).unwrap().is_none()
    });
    runner.kill().unwrap(); // SIGKILL: no handler in the runner can help
    runner.wait().unwrap();
    wait_until("the child dies with its runner", 10.0, || {
        runner::lock_run(&p.dir, &id).unwrap().is_some()
    });
    assert!(
        runner::load_result(&p.dir, &id).is_none(),
        "a killed run leaves no result, so a resume runs it again"
    );
}

/// A resume never starts a run that a live process is computing: it is skipped, and neither its
/// result nor its files are touched.
#[test]
fn a_resume_skips_a_run_that_is_still_computing() {
    let tmp = tempfile::tempdir().unwrap();
    let p = wait_sweep(tmp.path(), 2);
    // Realization 0 is "computing" in another process (this test holds its lock); realization
    // 1 is quick.
    let quick = std::fs::read_to_string(&p.manifest.pipeline)
        .unwrap()
        .replace("seconds: 120", "seconds: 0.01");
    std::fs::write(&p.manifest.pipeline, quick).unwrap();
    let mut m = p.manifest.clone();
    m.pipeline_blake3 = grainpipe_core::fsutil::content_hash(&m.pipeline).unwrap();
    m.save(&p.dir).unwrap();
    let busy = &m.runs[0].id;
    let lock = runner::lock_run(&p.dir, busy)
        .unwrap()
        .expect("free at first");
    std::fs::write(
        runner::run_dir(&p.dir, busy).join("log.txt"),
        "the other process's log",
    )
    .unwrap();
    let (done, failed) = runner::run_local(&p.dir, &m, &[0, 1], &opts(2, None), &launcher());
    assert_eq!((done, failed), (2, 0));
    assert!(
        runner::load_result(&p.dir, busy).is_none(),
        "not run, no result"
    );
    assert_eq!(
        std::fs::read_to_string(runner::run_dir(&p.dir, busy).join("log.txt")).unwrap(),
        "the other process's log",
        "the live run's files are left alone"
    );
    assert_eq!(
        runner::load_result(&p.dir, &m.runs[1].id).unwrap().status,
        "ok"
    );
    // The child itself refuses too (a race between two runners): exit 75, no result.
    let status = launcher()(&p.dir, busy).status().unwrap();
    assert_eq!(status.code(), Some(i32::from(runner::EXIT_RUN_BUSY)));
    assert!(runner::load_result(&p.dir, busy).is_none());
    drop(lock);
    let (done, failed) = runner::run_local(&p.dir, &m, &[0], &opts(1, None), &launcher());
    assert_eq!((done, failed), (1, 0));
    assert_eq!(runner::load_result(&p.dir, busy).unwrap().status, "ok");
}

#[test]
fn invalid_points_are_all_reported_before_running() {
    let tmp = tempfile::tempdir().unwrap();
    let reg = registry();
    let a = setup(
        tmp.path(),
        &["pack.volume_fraction=0.1,1.5,0.2,2.0"],
        3,
        &[],
    );
    let doc = PipelineDoc::load(a.file.as_ref().unwrap()).unwrap();
    let vary = vec![spec::parse_vary(&a.vary[0]).unwrap()];
    let m = Manifest {
        format: spec::MANIFEST_FORMAT,
        pipeline: a.file.clone().unwrap(),
        pipeline_blake3: String::new(),
        pipeline_name: doc.name.clone(),
        base_seed: 7,
        fixed: vec![],
        vary: vary.clone(),
        realizations: 3,
        collect: vec![],
        cache_dir: None,
        threads: None,
        rve: None,
        no_exports: false,
        runs: spec::runs(&vary, 3, 7),
    };
    let (mem, errors) = grainpipe_sweep::preflight_points(&m, tmp.path(), &reg, &[], false);
    assert_eq!(mem.len(), 4);
    assert_eq!(errors.len(), 2, "{errors:?}");
    assert!(errors[0].0.contains("1.5") && errors[1].0.contains("2.0"));
    assert!(errors[0].1.contains("volume_fraction"));
    // A misspelt key: every point is refused, with a suggestion.
    let vary = vec![spec::parse_vary("pack.volume_fractio=0.1,0.2").unwrap()];
    let m = Manifest {
        runs: spec::runs(&vary, 1, 7),
        vary,
        ..m
    };
    let (_, errors) = grainpipe_sweep::preflight_points(&m, tmp.path(), &reg, &[], false);
    assert_eq!(errors.len(), 2);
    assert!(
        errors[0].1.contains("did you mean `volume_fraction`"),
        "{}",
        errors[0].1
    );
    // A bad --collect port, with a suggestion.
    let c = spec::parse_collect("voxels.reprt.image_fraction").unwrap();
    let (_, errors) = grainpipe_sweep::preflight_points(&m, tmp.path(), &reg, &[c], false);
    assert!(
        errors[0].1.contains("did you mean `voxels.report`"),
        "{}",
        errors[0].1
    );
    // An image cannot be collected: refused at preflight (it used to fail after every run).
    let c = spec::parse_collect("voxels.image").unwrap();
    let (_, errors) = grainpipe_sweep::preflight_points(&m, tmp.path(), &reg, &[c], false);
    assert!(
        errors[0].1.contains("no values to collect") && errors[0].1.contains("voxels.report"),
        "{}",
        errors[0].1
    );
    // prepare() refuses before running anything.
    let mut reg = registry();
    assert!(prepare(&a, &mut reg, &mut |_, _| Ok(())).is_err());
    assert!(!tmp.path().join("sweep/runs").exists());
}

/// A study of a problem of known order: the sliced sphere converges as h^2 to 4/3 pi R^3;
/// the study recovers the order and the limit, and the target error picks the expected level.
#[test]
fn study_recovers_order_and_extrapolated_volume() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("sphere.yaml");
    std::fs::write(
        &file,
        "name: sphere\nstages:\n  - id: s\n    use: test.sliced_sphere\n    with: { radius: 100 um }\n",
    )
    .unwrap();
    let args = StudyArgs {
        file,
        vary: "s.voxel_size=40um,20um,10um,5um".into(),
        metric: "s.report.volume".into(),
        target_error: Some(0.01),
        overrides: vec![],
        out: Some(tmp.path().join("study")),
        threads: None,
        quiet: true,
    };
    let mut reg = registry();
    let (dir, a) =
        grainpipe_sweep::study::run_study(&args, &mut reg, &mut |_, _| Ok(()), &launcher())
            .unwrap_or_else(|_| panic!("study failed"));
    let (p, v) = a.richardson.expect("monotone convergence");
    let exact = 4.0 / 3.0 * std::f64::consts::PI * 1e-12;
    assert!((p - 2.0).abs() < 1e-6, "order {p}");
    assert!((v / exact - 1.0).abs() < 1e-9, "extrapolated {v}");
    // Relative errors pi R h^2 / 6 / V = h^2 / (8 R^2): 2 %, 0.5 %, 0.125 %, 0.03 %.
    assert!((a.levels[0].error - 0.02).abs() < 1e-9);
    assert_eq!(a.chosen, Some(1), "20 um is the coarsest level under 1 %");
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("study.json")).unwrap()).unwrap();
    assert_eq!(s["chosen_level"], "20um");
    for f in ["study.csv", "study.png", "study.svg", "study_memory.png"] {
        assert!(dir.join(f).is_file(), "{f}");
    }
    // A tensor component as the metric (`step.port.k`, collected as `step.port[k]`): the
    // same volumes, the same order.
    let args = StudyArgs {
        metric: "s.volume.0".into(),
        out: Some(tmp.path().join("study-tensor")),
        ..args
    };
    let (_, a) =
        grainpipe_sweep::study::run_study(&args, &mut reg, &mut |_, _| Ok(()), &launcher())
            .unwrap_or_else(|_| panic!("study of a tensor component failed"));
    let (p, _) = a.richardson.expect("monotone convergence");
    assert!((p - 2.0).abs() < 1e-6, "order {p}");
    // ... and by its name (`volume_0`).
    let args = StudyArgs {
        metric: "s.volume.volume_0".into(),
        out: Some(tmp.path().join("study-named")),
        ..args
    };
    let (_, a) =
        grainpipe_sweep::study::run_study(&args, &mut reg, &mut |_, _| Ok(()), &launcher())
            .unwrap_or_else(|_| panic!("study of a named tensor component failed"));
    let (p, _) = a.richardson.expect("monotone convergence");
    assert!((p - 2.0).abs() < 1e-6, "order {p}");
}
