//! The pipeline engine: cycles, laziness, caching, seeds and overrides, with small test
//! stages whose results are known exactly.

use grainpipe_core::engine::{execute, plan, PlanOptions, RunOptions, SilentObserver};
use grainpipe_core::pipeline::{ErrorClass, PipelineDoc};
use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, InputMetas, Inputs, Outputs, PortSpec, Preflight,
    Registry, RunContext, StageError, StageInfo, Table, TypedStage,
};
use rand::RngExt;
use std::path::Path;

/// Parameters shared by the test stages, to check that a flattened group keeps its keys.
#[params]
struct Noise {
    /// Fail at run time.
    fail: bool,
}

#[params]
struct SourceParams {
    /// Count.
    #[param(default = 4)]
    n: usize,
    #[param(flatten)]
    noise: Noise,
}

/// A stage that includes the same group with other defaults.
#[params]
struct NoisyParams {
    #[param(flatten, default = Noise { fail: true })]
    noise: Noise,
}

/// Gives `n` uniform random numbers from the stage's stream.
struct Source;
impl TypedStage for Source {
    type Params = SourceParams;
    type Plan = ();
    fn info(&self) -> StageInfo {
        StageInfo::new("test.source", "1", "random numbers").outputs(vec![PortSpec::new(
            "table",
            ArtifactKind::Table,
            "numbers",
        )])
    }
    fn preflight(&self, p: &SourceParams, _: &InputMetas) -> Result<Preflight, StageError> {
        if p.n == 0 {
            return Err(StageError::param("n", "must be positive"));
        }
        Ok(
            Preflight::from_info(&self.info(), (p.n * 8) as u64).announce(
                "table",
                ArtifactMeta::of(ArtifactKind::Table).with_count(p.n as u64, Some([p.n as u64; 2])),
            ),
        )
    }
    fn run(
        &self,
        p: &SourceParams,
        _: &(),
        _: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        if p.noise.fail {
            return Err(StageError::failed(
                "diverged after 3 iterations (residual 1e3)",
            ));
        }
        let mut rng = ctx.rng();
        let v: Vec<f64> = (0..p.n).map(|_| rng.random::<f64>()).collect();
        let mut o = Outputs::new();
        o.insert(
            "table".into(),
            Artifact::Table(Table::new("x").with_f64("x", "1", v)),
        );
        Ok(o)
    }
}

/// Includes the `Noise` group with its own default (`fail: true`).
struct Noisy;
impl TypedStage for Noisy {
    type Params = NoisyParams;
    type Plan = ();
    fn info(&self) -> StageInfo {
        StageInfo::new("test.noisy", "1", "fails unless told otherwise")
            .outputs(vec![PortSpec::new("table", ArtifactKind::Table, "nothing")])
    }
    fn preflight(&self, _: &NoisyParams, _: &InputMetas) -> Result<Preflight, StageError> {
        Ok(Preflight::from_info(&self.info(), 0))
    }
    fn run(
        &self,
        p: &NoisyParams,
        _: &(),
        _: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        if p.noise.fail {
            return Err(StageError::failed("noisy by default"));
        }
        let mut o = Outputs::new();
        o.insert("table".into(), Artifact::Table(Table::new("x")));
        Ok(o)
    }
}

#[params]
struct ScaleParams {
    /// Factor.
    #[param(default = 2.0)]
    factor: f64,
    /// Claim one row more than the input has (a stage whose preflight lies).
    lie: bool,
}

/// Multiplies a table's first column.
struct Scale;
impl TypedStage for Scale {
    type Params = ScaleParams;
    type Plan = ();
    fn info(&self) -> StageInfo {
        StageInfo::new("test.scale", "1", "scales")
            .inputs(vec![PortSpec::new("table", ArtifactKind::Table, "in")])
            .outputs(vec![PortSpec::new("table", ArtifactKind::Table, "out")])
    }
    fn preflight(&self, p: &ScaleParams, i: &InputMetas) -> Result<Preflight, StageError> {
        let mut meta = i["table"].clone();
        if let (true, Some([lo, hi])) = (p.lie, meta.count_bounds) {
            meta.count_bounds = Some([lo + 1, hi + 1]);
        }
        Ok(Preflight::from_info(&self.info(), 0).announce("table", meta))
    }
    fn run(
        &self,
        p: &ScaleParams,
        _: &(),
        i: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        let t = grainpipe_core::input(i, "table", Artifact::as_table)?;
        let v: Vec<f64> = t
            .f64_column("x")
            .unwrap()
            .iter()
            .map(|x| x * p.factor)
            .collect();
        let mut o = Outputs::new();
        o.insert(
            "table".into(),
            Artifact::Table(Table::new("x").with_f64("x", "1", v)),
        );
        Ok(o)
    }
}

#[params]
struct ReadParams {
    /// A text file of numbers, one per line.
    #[param(file)]
    path: String,
}

/// Reads numbers from a file; parses it once, in preflight, and hands the values to `run`.
struct ReadNumbers;
impl TypedStage for ReadNumbers {
    type Params = ReadParams;
    type Plan = Vec<f64>;
    fn info(&self) -> StageInfo {
        StageInfo::new("test.read", "1", "reads numbers from a file").outputs(vec![PortSpec::new(
            "table",
            ArtifactKind::Table,
            "numbers",
        )])
    }
    fn preflight(&self, p: &ReadParams, _: &InputMetas) -> Result<Preflight<Vec<f64>>, StageError> {
        let text = std::fs::read_to_string(&p.path)
            .map_err(|e| StageError::param("path", format!("cannot read `{}`: {e}", p.path)))?;
        let values = text
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| l.trim().parse::<f64>())
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| StageError::param("path", e.to_string()))?;
        let n = values.len() as u64;
        Ok(Preflight::from_info(&self.info(), 0)
            .announce(
                "table",
                ArtifactMeta::of(ArtifactKind::Table).with_count(n, Some([n, n])),
            )
            .with_plan(values))
    }
    fn run(
        &self,
        _: &ReadParams,
        values: &Vec<f64>,
        _: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        let mut o = Outputs::new();
        o.insert(
            "table".into(),
            Artifact::Table(Table::new("x").with_f64("x", "1", values.clone())),
        );
        Ok(o)
    }
}

fn registry() -> Registry {
    let mut r = Registry::new();
    r.add_stage(Source);
    r.add_stage(Scale);
    r.add_stage(ReadNumbers);
    r.add_stage(Noisy);
    r.check_consistency().unwrap();
    r
}

fn doc(yaml: &str) -> PipelineDoc {
    PipelineDoc::parse(Path::new("p.yaml"), yaml.to_string()).unwrap()
}

/// Plans `d` for the given target steps.
fn plan_targets(d: &PipelineDoc, reg: &Registry, targets: &[&str]) -> grainpipe_core::engine::Plan {
    let opts = PlanOptions {
        targets: targets.iter().map(|t| t.to_string()).collect(),
        ..Default::default()
    };
    plan(d, reg, &opts).unwrap()
}

fn column(r: &grainpipe_core::engine::RunResult, step: &str) -> Vec<f64> {
    r.outputs[step]["table"]
        .as_table()
        .unwrap()
        .f64_column("x")
        .unwrap()
        .to_vec()
}

const CHAIN: &str = "name: t\nseed: 5\nstages:\n  - id: src\n    use: test.source\n  - id: twice\n    use: test.scale\n    in: {table: src}\n  - id: unused\n    use: test.scale\n    in: {table: src.table}\n    with: {factor: 3}\n";

#[test]
fn cycle_through_several_steps_is_named_with_its_location() {
    let d = doc("name: t\nstages:\n  - id: a\n    use: test.scale\n    in: {table: c.table}\n  - id: b\n    use: test.scale\n    in: {table: a.table}\n  - id: c\n    use: test.scale\n    in: {table: b.table}\n");
    let e = plan(&d, &registry(), &PlanOptions::default())
        .err()
        .unwrap();
    assert_eq!(e.class, ErrorClass::Input);
    assert_eq!(e.loc.unwrap().line, 3);
    assert!(
        e.message.contains("`a`, `b`, `c`") && e.message.contains("cycle"),
        "{e}"
    );
}

#[test]
fn only_steps_needed_by_targets_run() {
    let d = doc(CHAIN);
    let p = plan_targets(&d, &registry(), &["twice"]);
    let ids: Vec<&str> = p.order.iter().map(|&i| d.steps[i].id.as_str()).collect();
    assert_eq!(ids, ["src", "twice"]);
    let r = execute(&d, &p, &RunOptions { cache_dir: None }, &mut SilentObserver).unwrap();
    assert!(!r.outputs.contains_key("unused"));
    // The scaled column is exactly twice the source (a multiplication by 2 is exact in binary).
    let src = column(&r, "src");
    assert_eq!(
        column(&r, "twice"),
        src.iter().map(|x| 2.0 * x).collect::<Vec<_>>()
    );
}

#[test]
fn same_seed_same_numbers_other_seed_other_numbers_and_streams_per_step() {
    let reg = registry();
    let run = |yaml: &str| {
        let d = doc(yaml);
        let p = plan(&d, &reg, &PlanOptions::default()).unwrap();
        execute(&d, &p, &RunOptions { cache_dir: None }, &mut SilentObserver).unwrap()
    };
    let a = run(CHAIN);
    let b = run(CHAIN);
    assert_eq!(column(&a, "src"), column(&b, "src"));
    let c = run(&CHAIN.replace("seed: 5", "seed: 6"));
    assert_ne!(column(&a, "src"), column(&c, "src"));
    // Two sources in one pipeline draw from different streams.
    let two = run("name: t\nseed: 5\nstages:\n  - id: s1\n    use: test.source\n  - id: s2\n    use: test.source\n");
    assert_ne!(column(&two, "s1"), column(&two, "s2"));
    // A step's numbers depend on its own id and the seed only, not on what else is in the file.
    assert_eq!(
        column(&two, "s1"),
        column(
            &run("name: t\nseed: 5\nstages:\n  - id: s1\n    use: test.source\n"),
            "s1"
        )
    );
}

#[test]
fn cache_reuses_upstream_results_and_tracks_parameter_changes() {
    let dir = tempfile::tempdir().unwrap();
    let reg = registry();
    let opts = RunOptions {
        cache_dir: Some(dir.path().to_path_buf()),
    };
    let yaml = CHAIN.replace("seed: 5", "seed: 77");
    let run = |yaml: &str| {
        let d = doc(yaml);
        let p = plan_targets(&d, &reg, &["twice"]);
        execute(&d, &p, &opts, &mut SilentObserver).unwrap()
    };
    let cold = run(&yaml);
    assert!(cold.stats.values().all(|s| !s.from_cache));
    let warm = run(&yaml);
    assert!(warm.stats.values().all(|s| s.from_cache));
    assert_eq!(column(&cold, "twice"), column(&warm, "twice"));
    // Changing a downstream parameter re-runs only downstream.
    let changed = yaml.replace(
        "    in: {table: src}\n",
        "    in: {table: src}\n    with: {factor: 4}\n",
    );
    let r = run(&changed);
    assert!(r.stats["src"].from_cache && !r.stats["twice"].from_cache);
    assert_eq!(
        column(&r, "twice"),
        column(&cold, "src")
            .iter()
            .map(|x| 4.0 * x)
            .collect::<Vec<_>>()
    );
    // A corrupt cache file is ignored and recomputed, not trusted.
    for f in std::fs::read_dir(dir.path()).unwrap() {
        std::fs::write(f.unwrap().path(), b"garbage").unwrap();
    }
    let r = run(&yaml);
    assert!(r.stats.values().all(|s| !s.from_cache));
    assert_eq!(column(&r, "twice"), column(&cold, "twice"));
}

#[test]
fn overrides_change_parameters_and_unknown_params_are_located() {
    let mut d = doc(CHAIN);
    d.apply_override("twice.factor=0.5").unwrap();
    let p = plan_targets(&d, &registry(), &["twice"]);
    let r = execute(&d, &p, &RunOptions { cache_dir: None }, &mut SilentObserver).unwrap();
    assert_eq!(
        column(&r, "twice"),
        column(&r, "src")
            .iter()
            .map(|x| 0.5 * x)
            .collect::<Vec<_>>()
    );
    let d = doc(&CHAIN.replace("with: {factor: 3}", "with: {factr: 3}"));
    let e = plan(&d, &registry(), &PlanOptions::default())
        .err()
        .unwrap();
    assert_eq!(e.loc.unwrap().line, 12);
    assert_eq!(e.help.as_deref(), Some("did you mean `factor`?"));
}

#[test]
fn every_bad_parameter_of_a_step_is_reported_at_once() {
    // An unknown key, a wrong type and a wrong type inside a flattened group, on lines 5-7.
    let d = doc("name: t\nstages:\n  - id: s\n    use: test.source\n    with:\n      nn: 3\n      n: lots\n      fail: maybe\n");
    let e = plan(&d, &registry(), &PlanOptions::default())
        .err()
        .unwrap();
    let all: Vec<_> = e.all().collect();
    assert_eq!(all.len(), 3, "{e}");
    assert!(all[0].message.contains("unknown parameter `nn`"), "{e}");
    assert_eq!(all[0].help.as_deref(), Some("did you mean `n`?"));
    assert!(all[1].message.contains("parameter `n`"), "{e}");
    assert!(all[2].message.contains("parameter `fail`"), "{e}");
    let lines: Vec<u64> = all.iter().map(|x| x.loc.unwrap().line).collect();
    assert_eq!(lines, [6, 7, 8]);
}

#[test]
fn preflight_errors_and_memory_limit_stop_before_running() {
    let d = doc("name: t\nstages:\n  - id: s\n    use: test.source\n    with: {n: 0}\n");
    let e = plan(&d, &registry(), &PlanOptions::default())
        .err()
        .unwrap();
    assert!(
        e.message.contains("must be positive") && e.loc.unwrap().line == 5,
        "{e}"
    );
    let d = doc("name: t\nstages:\n  - id: s\n    use: test.source\n    with: {n: 1000}\n");
    let e = plan(
        &d,
        &registry(),
        &PlanOptions {
            memory_limit: Some(1000),
            ..Default::default()
        },
    )
    .err()
    .unwrap();
    assert!(
        e.message.contains("7.8 KiB") && e.message.contains("1000 B"),
        "{e}"
    );
}

#[test]
fn a_failing_stage_is_a_run_error_with_its_message() {
    let d = doc("name: t\nstages:\n  - id: s\n    use: test.source\n    with: {fail: true}\n");
    let p = plan(&d, &registry(), &PlanOptions::default()).unwrap();
    let e = execute(&d, &p, &RunOptions { cache_dir: None }, &mut SilentObserver)
        .err()
        .unwrap();
    assert_eq!(e.class, ErrorClass::Run);
    assert_eq!(e.exit_code(), 1);
    assert!(e.message.contains("diverged after 3 iterations"), "{e}");
}

#[test]
fn duplicate_step_ids_are_refused() {
    let d =
        doc("name: t\nstages:\n  - id: s\n    use: test.source\n  - id: s\n    use: test.source\n");
    let e = plan(&d, &registry(), &PlanOptions::default())
        .err()
        .unwrap();
    assert_eq!(e.loc.unwrap().line, 5);
    assert!(e.message.contains("used twice"));
}

#[test]
fn cache_key_follows_the_content_of_input_files_not_their_path() {
    let cache = tempfile::tempdir().unwrap();
    let data = tempfile::tempdir().unwrap();
    let file = data.path().join("numbers.txt");
    std::fs::write(&file, "1\n2\n").unwrap();
    let reg = registry();
    let opts = RunOptions {
        cache_dir: Some(cache.path().to_path_buf()),
    };
    let yaml = format!(
        "name: t\nstages:\n  - id: read\n    use: test.read\n    with: {{path: {:?}}}\n",
        file.display().to_string()
    );
    let run = || {
        let d = doc(&yaml);
        let p = plan(&d, &reg, &PlanOptions::default()).unwrap();
        execute(&d, &p, &opts, &mut SilentObserver).unwrap()
    };
    let first = run();
    assert_eq!(column(&first, "read"), vec![1.0, 2.0]);
    assert!(run().stats["read"].from_cache);
    // Same path, same size, new content: the stale result must not be reused.
    std::fs::write(&file, "3\n4\n").unwrap();
    let edited = run();
    assert!(!edited.stats["read"].from_cache);
    assert_eq!(column(&edited, "read"), vec![3.0, 4.0]);
    // Back to the first content: the first entry is valid again.
    std::fs::write(&file, "1\n2\n").unwrap();
    let back = run();
    assert!(back.stats["read"].from_cache);
    assert_eq!(column(&back, "read"), vec![1.0, 2.0]);
}

#[test]
fn a_stage_whose_run_contradicts_its_preflight_fails_with_an_internal_error() {
    let d = doc(&CHAIN.replace("with: {factor: 3}", "with: {factor: 3, lie: true}"));
    let p = plan(&d, &registry(), &PlanOptions::default()).unwrap();
    let e = execute(&d, &p, &RunOptions { cache_dir: None }, &mut SilentObserver)
        .err()
        .unwrap();
    assert!(
        e.message.contains("internal error in stage `test.scale`")
            && e.message
                .contains("announced between 5 and 5 items but gave 4"),
        "{e}"
    );
}

#[test]
fn keys_of_a_flattened_group_are_accepted_and_typos_still_refused() {
    let reg = registry();
    let info = reg.stage("test.source").unwrap().stage.info().clone();
    let names: Vec<&str> = info.params.iter().map(|p| p.name).collect();
    assert_eq!(names, ["n", "fail"]);
    assert_eq!(info.params[0].default, serde_json::json!(4));
    assert_eq!(info.params[0].ty, "integer");
    assert_eq!(info.params[1].ty, "true or false");
    assert_eq!(info.params[1].default, serde_json::json!(false));
    // The group's defaults can differ per stage, and the declaration shows this stage's.
    use grainpipe_core::Params;
    let noisy = NoisyParams::specs();
    assert_eq!(noisy[0].name, "fail");
    assert_eq!(noisy[0].default, serde_json::json!(true));
    assert!(NoisyParams::default().noise.fail);
    // ... and a run without `with:` uses them (serde alone would take the group's own
    // default, `fail: false`, for a key missing inside a flattened field).
    let d = doc("name: t\nstages:\n  - id: n\n    use: test.noisy\n");
    let p = plan(&d, &reg, &PlanOptions::default()).unwrap();
    let e = execute(&d, &p, &RunOptions { cache_dir: None }, &mut SilentObserver)
        .err()
        .unwrap();
    assert!(e.message.contains("noisy by default"), "{e}");
    let d = doc("name: t\nstages:\n  - id: n\n    use: test.noisy\n    with: {fail: false}\n");
    let p = plan(&d, &reg, &PlanOptions::default()).unwrap();
    execute(&d, &p, &RunOptions { cache_dir: None }, &mut SilentObserver).unwrap();
    let d =
        doc("name: t\nstages:\n  - id: s\n    use: test.source\n    with: {n: 2, fial: true}\n");
    let e = plan(&d, &reg, &PlanOptions::default()).err().unwrap();
    assert!(e.message.contains("unknown parameter `fial`"), "{e}");
    assert_eq!(e.help.as_deref(), Some("did you mean `fail`?"));
    assert_eq!(e.loc.unwrap().line, 5);
    // A wrong type inside the group is located at its key, though serde reports it without
    // a path (flattened fields are deserialized from a buffer).
    let d = doc(
        "name: t\nstages:\n  - id: s\n    use: test.source\n    with:\n      n: 2\n      fail: 3\n",
    );
    let e = plan(&d, &reg, &PlanOptions::default()).err().unwrap();
    assert!(e.message.contains("parameter `fail`: invalid type"), "{e}");
    assert_eq!(e.loc.unwrap().line, 7);
}

/// Issue 36: a `reference:` block is checked when planning (unknown steps and ports named at
/// their line, with a suggestion) and compared with the results after the run: the relative
/// difference is (result - reference) / |reference| of the value the run computed, a value in
/// another dimension or one the step does not give is reported missing, not compared.
#[test]
fn reference_values_are_checked_before_and_compared_after_the_run() {
    let with_ref = |values: &str| {
        format!(
            "{}reference:\n  source: a test\n  values:\n{values}",
            CHAIN.replace("use: test.source\n", "use: test.source\n    with: {n: 1}\n")
        )
    };
    let bad = doc(&with_ref(
        "    - {quantity: twise.table.x, value: 1}\n    - {quantity: src.tabel.x, value: 1}\n",
    ));
    let e = plan(&bad, &registry(), &PlanOptions::default())
        .err()
        .unwrap();
    let all: Vec<String> = std::iter::once(&e)
        .chain(e.related.iter())
        .map(|x| {
            format!(
                "{} @{} {:?}",
                x.message,
                x.loc.map_or(0, |l| l.line),
                x.help
            )
        })
        .collect();
    let all = all.join("\n");
    assert!(
        all.contains("no step `twise`") && all.contains("`twice`"),
        "{all}"
    );
    assert!(
        all.contains("has no output `tabel`") && all.contains("`table`"),
        "{all}"
    );
    assert!(all.contains("@17") && all.contains("@18"), "{all}");

    let d = doc(&with_ref(
        "    - {quantity: twice.table.x, value: 1, tolerance: 100 %}\n    - {quantity: src.table.x, value: 5 m}\n    - {quantity: twice.table.y, value: 1}\n",
    ));
    let p = plan(&d, &registry(), &PlanOptions::default()).unwrap();
    let r = execute(&d, &p, &RunOptions { cache_dir: None }, &mut SilentObserver).unwrap();
    let rows = grainpipe_core::values::compare(d.reference.as_ref().unwrap(), &r.outputs);
    let x = 2.0 * column(&r, "src")[0];
    use grainpipe_core::values::Verdict;
    assert_eq!(rows[0].result, Some(x));
    assert!((rows[0].relative_difference.unwrap() - (x - 1.0)).abs() < 1e-15);
    // x = 2 u with u uniform on [0, 1): always within 100 % of 1.
    assert_eq!(rows[0].verdict, Verdict::Within);
    assert_eq!(rows[1].verdict, Verdict::Missing);
    assert!(
        rows[1].why.contains("the result is in 1"),
        "{}",
        rows[1].why
    );
    assert_eq!(rows[2].verdict, Verdict::Missing);
    assert!(
        rows[2].why.contains("it has: twice.table.x"),
        "{}",
        rows[2].why
    );
    // The effective YAML keeps the block (sweeps and the run record re-read it).
    let again = doc(&d.effective_yaml());
    assert_eq!(again.reference, d.reference);
}
