//! The pipeline engine: resolves a [`PipelineDoc`] against a [`Registry`] into a checked
//! [`Plan`] (every stage preflighted before anything runs), then executes only the steps the
//! exports or targets need, with a content-addressed cache.

use crate::model::{Artifact, ArtifactMeta, Provenance};
use crate::pipeline::{Loc, PipelineDoc, PipelineError, PortRef};
use crate::registry::{closest, Exporter, Registry};
use crate::stage::{
    InputMetas, Inputs, Outputs, Preflight, Prepared, Reporter, RunContext, Stage, StageError,
};
use indexmap::IndexMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Where a step's input comes from: producer step index and its output port.
#[derive(Clone, Debug)]
pub struct Wire {
    pub producer: usize,
    pub port: String,
}

/// A step resolved against the registry and preflighted.
pub struct PlannedStep {
    /// Index into `doc.steps`.
    pub index: usize,
    pub id: String,
    pub stage: Arc<dyn Stage>,
    /// Canonical parameters (defaults filled in, SI).
    pub params: serde_json::Value,
    pub inputs: IndexMap<String, Wire>,
    pub preflight: Preflight,
    /// What preflight prepared for the run (typed parameters, the stage's plan).
    pub prepared: Prepared,
    /// The step's own seed, derived from (pipeline seed, step id).
    pub seed: u64,
    /// Files and directories the step reads (parameters declared `file`), with the BLAKE3
    /// hash of their content, which is part of the cache key.
    pub input_files: Vec<(String, String)>,
    /// Content hash of (stage id, version, params, seed, input files, input keys).
    pub cache_key: String,
    /// `built-in` or the plugin library the stage came from.
    pub origin: String,
}

/// An export resolved to its producer and writer.
pub struct PlannedExport {
    pub producer: usize,
    pub port: String,
    pub path: PathBuf,
    pub exporter: Arc<dyn Exporter>,
    pub loc: Loc,
}

/// A checked pipeline: steps in execution order (only those needed) and exports.
pub struct Plan {
    pub seed: u64,
    /// Steps by `doc.steps` index; `None` for steps that are not needed.
    pub steps: Vec<Option<PlannedStep>>,
    /// Execution order (indices into `steps`).
    pub order: Vec<usize>,
    pub exports: Vec<PlannedExport>,
    /// Sum of the preflight memory estimates of the steps that will run [bytes].
    pub memory_bytes: u64,
}

/// What to plan for.
#[derive(Clone, Debug, Default)]
pub struct PlanOptions {
    /// Steps to compute even if nothing exports them; when empty and there are exports, only
    /// what the exports need runs; when both are empty, every step runs.
    pub targets: Vec<String>,
    /// Available memory [bytes]; the plan is refused when its estimate exceeds it.
    pub memory_limit: Option<u64>,
}

fn err(doc: &PipelineDoc, loc: Loc, message: impl Into<String>) -> PipelineError {
    PipelineError::input(&doc.file, Some(loc), message)
}

fn did_you_mean(s: Option<String>) -> Option<String> {
    s.map(|s| format!("did you mean `{s}`?"))
}

/// Resolves and preflights a pipeline. No stage runs and nothing large is allocated.
pub fn plan(
    doc: &PipelineDoc,
    registry: &Registry,
    opts: &PlanOptions,
) -> Result<Plan, PipelineError> {
    let n = doc.steps.len();
    if n == 0 {
        return Err(PipelineError::input(
            &doc.file,
            None,
            "the pipeline has no stages",
        ));
    }
    // Unique step ids.
    for (i, s) in doc.steps.iter().enumerate() {
        if let Some(prev) = doc.steps[..i].iter().find(|p| p.id == s.id) {
            return Err(err(
                doc,
                s.id_loc,
                format!(
                    "step id `{}` is used twice (first at line {})",
                    s.id, prev.id_loc.line
                ),
            ));
        }
        if s.id.contains('.') {
            return Err(err(
                doc,
                s.id_loc,
                format!("step id `{}` must not contain `.`", s.id),
            ));
        }
    }
    // Stages and parameters.
    let mut stages: Vec<Arc<dyn Stage>> = Vec::with_capacity(n);
    let mut origins: Vec<String> = Vec::with_capacity(n);
    let mut params: Vec<serde_json::Value> = Vec::with_capacity(n);
    for (i, s) in doc.steps.iter().enumerate() {
        let reg = registry.stage(&s.uses).ok_or_else(|| {
            err(doc, s.uses_loc, format!("unknown stage `{}`", s.uses)).with_help(
                did_you_mean(registry.suggest_stage(&s.uses))
                    .or(Some("`pipe list` shows every stage".into())),
            )
        })?;
        let stage = reg.stage.clone();
        origins.push(reg.origin.clone());
        let p = stage
            .normalize_params(&serde_json::Value::Object(s.params.clone()))
            .map_err(|e| stage_error(doc, i, &*stage, e))?;
        stages.push(stage);
        params.push(p);
    }
    // Wires.
    let mut wires: Vec<IndexMap<String, Wire>> = Vec::with_capacity(n);
    for (i, s) in doc.steps.iter().enumerate() {
        let info = stages[i].info();
        let mut w = IndexMap::new();
        for (port, r) in &s.inputs {
            let spec = info.inputs.iter().find(|p| p.name == port).ok_or_else(|| {
                let names: Vec<&str> = info.inputs.iter().map(|p| p.name).collect();
                err(
                    doc,
                    r.key_loc,
                    format!("stage `{}` has no input `{port}`", info.id),
                )
                .with_help(
                    did_you_mean(closest(port, names.iter().copied()))
                        .or(Some(format!("its inputs are: {}", list_or_none(&names)))),
                )
            })?;
            let (producer, out_port) = resolve_ref(doc, &stages, &r.source, r.value_loc)?;
            if producer == i {
                return Err(err(
                    doc,
                    r.value_loc,
                    format!("step `{}` takes its own output", s.id),
                ));
            }
            let out_kind = stages[producer]
                .info()
                .outputs
                .iter()
                .find(|p| p.name == out_port)
                .map(|p| p.kind)
                .expect("resolved port exists");
            if out_kind != spec.kind {
                return Err(err(
                    doc,
                    r.value_loc,
                    format!(
                        "input `{port}` of `{}` takes a {} but `{}` is a {out_kind}",
                        s.id, spec.kind, r.source
                    ),
                ));
            }
            w.insert(
                port.clone(),
                Wire {
                    producer,
                    port: out_port,
                },
            );
        }
        for spec in &info.inputs {
            if !spec.optional && !w.contains_key(spec.name) {
                return Err(err(
                    doc,
                    s.id_loc,
                    format!(
                        "step `{}` ({}) needs input `{}` ({}): add `in: {{{}: <step>.<port>}}`",
                        s.id, info.id, spec.name, spec.kind, spec.name
                    ),
                ));
            }
        }
        wires.push(w);
    }
    let order = topological_order(doc, &wires)?;
    // Exports.
    let mut exports = Vec::new();
    for e in &doc.exports {
        let (producer, port) = resolve_ref(doc, &stages, &e.from, e.from_loc)?;
        let kind = stages[producer]
            .info()
            .outputs
            .iter()
            .find(|p| p.name == port)
            .expect("port")
            .kind;
        let exporter = registry.exporter_for(e.format.as_deref(), &e.to);
        let accepting: Vec<&str> = registry
            .exporters()
            .iter()
            .filter(|x| x.accepts(kind))
            .map(|x| x.name())
            .collect();
        let exporter = match exporter {
            Some(x) if x.accepts(kind) => x,
            Some(x) => {
                return Err(err(
                    doc,
                    e.format_loc.unwrap_or(e.to_loc),
                    format!("format `{}` cannot hold a {kind} (`{}`)", x.name(), e.from),
                )
                .with_help(Some(format!(
                    "formats for a {kind}: {}",
                    list_or_none(&accepting)
                ))))
            }
            None => {
                let what = e.format.clone().unwrap_or_else(|| {
                    format!(
                        "extension `.{}`",
                        e.to.extension().and_then(|x| x.to_str()).unwrap_or("")
                    )
                });
                return Err(err(
                    doc,
                    e.format_loc.unwrap_or(e.to_loc),
                    format!("no exporter for {what}"),
                )
                .with_help(Some(format!(
                    "formats for a {kind}: {}",
                    list_or_none(&accepting)
                ))));
            }
        };
        check_export_path(&e.to).map_err(|(m, help)| err(doc, e.to_loc, m).with_help(help))?;
        if let Some(prev) = exports
            .iter()
            .find(|p: &&PlannedExport| same_path(&p.path, &e.to))
        {
            return Err(err(
                doc,
                e.to_loc,
                format!(
                    "`{}` is already the target of the export at line {}; the second would \
                     overwrite the first",
                    e.to.display(),
                    prev.loc.line
                ),
            )
            .with_help(Some("give each export its own file name".into())));
        }
        exports.push(PlannedExport {
            producer,
            port,
            path: e.to.clone(),
            exporter,
            loc: e.to_loc,
        });
    }
    // Which steps are needed.
    let mut needed = vec![false; n];
    let mut roots: Vec<usize> = exports.iter().map(|e| e.producer).collect();
    for t in &opts.targets {
        match doc.step(t) {
            Some((i, _)) => roots.push(i),
            None => {
                return Err(PipelineError::input(
                    &doc.file,
                    None,
                    format!("no step `{t}` to target"),
                )
                .with_help(did_you_mean(closest(
                    t,
                    doc.steps.iter().map(|s| s.id.as_str()),
                ))))
            }
        }
    }
    if roots.is_empty() {
        roots = (0..n).collect();
    }
    while let Some(i) = roots.pop() {
        if !needed[i] {
            needed[i] = true;
            roots.extend(wires[i].values().map(|w| w.producer));
        }
    }
    // Preflight in execution order.
    let mut planned: Vec<Option<PlannedStep>> = (0..n).map(|_| None).collect();
    let mut memory = 0u64;
    let mut exec_order = Vec::new();
    for &i in &order {
        if !needed[i] {
            continue;
        }
        let s = &doc.steps[i];
        let mut metas = InputMetas::new();
        for (port, w) in &wires[i] {
            let meta: ArtifactMeta = planned[w.producer]
                .as_ref()
                .and_then(|p| p.preflight.outputs.get(&w.port).cloned())
                .ok_or_else(|| {
                    err(
                        doc,
                        s.inputs[port].value_loc,
                        format!(
                            "step `{}` will not give output `{}` with these parameters",
                            doc.steps[w.producer].id, w.port
                        ),
                    )
                })?;
            metas.insert(port.clone(), meta);
        }
        let (pf, prepared) = stages[i]
            .preflight(&params[i], &metas)
            .map_err(|e| stage_error(doc, i, &*stages[i], e))?;
        memory = memory.saturating_add(pf.memory_bytes);
        let seed = crate::derive_seed(doc.seed, s.id.as_bytes());
        let input_files = hash_input_files(&*stages[i], &params[i]).map_err(|(key, m)| {
            err(
                doc,
                s.param_locs.get(&key).copied().unwrap_or(s.uses_loc),
                m,
            )
        })?;
        let key = cache_key(
            &*stages[i],
            &params[i],
            seed,
            &input_files,
            &wires[i],
            &planned,
        );
        planned[i] = Some(PlannedStep {
            index: i,
            id: s.id.clone(),
            stage: stages[i].clone(),
            params: params[i].clone(),
            inputs: wires[i].clone(),
            preflight: pf,
            prepared,
            seed,
            input_files,
            cache_key: key,
            origin: origins[i].clone(),
        });
        exec_order.push(i);
    }
    for e in &exports {
        let pf = &planned[e.producer]
            .as_ref()
            .expect("export producers are needed")
            .preflight;
        if !pf.outputs.contains_key(&e.port) {
            return Err(err(
                doc,
                e.loc,
                format!(
                    "step `{}` will not give output `{}` with these parameters",
                    doc.steps[e.producer].id, e.port
                ),
            )
            .with_help(Some(format!(
                "it gives: {}",
                pf.outputs
                    .keys()
                    .map(|k| format!("{}.{k}", doc.steps[e.producer].id))
                    .collect::<Vec<_>>()
                    .join(", ")
            ))));
        }
    }
    if let Some(limit) = opts.memory_limit {
        if memory > limit {
            return Err(PipelineError::input(&doc.file, None, format!(
                "the pipeline needs about {} of memory but {} is available",
                human_bytes(memory),
                human_bytes(limit)
            ))
            .with_help(Some("reduce the domain size or resolution (see `pipe validate` for the estimate per stage)".into())));
        }
    }
    Ok(Plan {
        seed: doc.seed,
        steps: planned,
        order: exec_order,
        exports,
        memory_bytes: memory,
    })
}

/// An export target must name a file: not empty, not a directory (`.`, `out/`, an existing
/// directory), and not an existing non-regular file (a device node, FIFO or socket: an
/// export replaces its target by rename, which would replace the node itself). Checked at
/// plan time so a bad path fails before any stage runs. Returns (message, help).
fn check_export_path(path: &Path) -> Result<(), (String, Option<String>)> {
    let text = path.as_os_str().to_string_lossy();
    let suggestion = Some("write a file path such as `out/result.vti`".to_string());
    if text.trim().is_empty() {
        return Err(("export `to:` is empty".into(), suggestion));
    }
    if text.ends_with('/')
        || text.ends_with(std::path::MAIN_SEPARATOR)
        || path.file_name().is_none()
        || matches!(
            path.components().next_back(),
            Some(std::path::Component::CurDir | std::path::Component::ParentDir)
        )
    {
        return Err((
            format!("export target `{text}` names a directory, not a file"),
            suggestion,
        ));
    }
    if let Ok(meta) = std::fs::metadata(path) {
        if meta.is_dir() {
            return Err((
                format!("export target `{text}` is an existing directory"),
                suggestion,
            ));
        }
        if !meta.is_file() {
            return Err((
                format!(
                    "export target `{text}` exists and is not a regular file (a device, FIFO \
                     or socket); grainpipe only replaces regular files"
                ),
                suggestion,
            ));
        }
    }
    Ok(())
}

/// Whether two export targets are the same file: compared after lexical normalisation
/// (`a/./b` = `a/b`) and, when the parent directory exists, after resolving it (so
/// `out/x.vti` and `./out/../out/x.vti` or a symlinked directory collide too).
fn same_path(a: &Path, b: &Path) -> bool {
    fn norm(p: &Path) -> PathBuf {
        let lexical: PathBuf = p
            .components()
            .filter(|c| !matches!(c, std::path::Component::CurDir))
            .collect();
        let parent = lexical.parent().filter(|d| !d.as_os_str().is_empty());
        let dir = parent
            .map(Path::to_path_buf)
            .unwrap_or_else(|| PathBuf::from("."));
        match (std::fs::canonicalize(&dir), lexical.file_name()) {
            (Ok(d), Some(name)) => d.join(name),
            _ => lexical,
        }
    }
    norm(a) == norm(b)
}

fn list_or_none(names: &[&str]) -> String {
    if names.is_empty() {
        "none".into()
    } else {
        names.join(", ")
    }
}

/// Maps a stage's preflight error to the YAML place it concerns.
fn stage_error(doc: &PipelineDoc, i: usize, stage: &dyn Stage, e: StageError) -> PipelineError {
    let s = &doc.steps[i];
    let info = stage.info();
    match e {
        StageError::UnknownParam { key, suggestion } => {
            let loc = s.param_locs.get(&key).copied().unwrap_or(s.uses_loc);
            err(
                doc,
                loc,
                format!("step `{}` ({}): unknown parameter `{key}`", s.id, info.id),
            )
            .with_help(did_you_mean(suggestion).or(Some(format!(
                "`pipe describe {}` lists its parameters",
                info.id
            ))))
        }
        StageError::InvalidParam { key, message } => {
            let top = key.split(['.', '[']).next().unwrap_or(&key).to_string();
            let loc = s.param_locs.get(&top).copied().unwrap_or(s.uses_loc);
            let help = if message.starts_with("unknown field") {
                did_you_mean(closest(&top, info.params.iter().map(|p| p.name))).or(Some(format!(
                    "`pipe describe {}` lists its parameters",
                    info.id
                )))
            } else {
                info.params
                    .iter()
                    .find(|p| p.name == top)
                    .map(|p| format!("`{}`: {}{}", p.name, p.doc, unit_hint(&p.unit)))
            };
            err(
                doc,
                loc,
                format!(
                    "step `{}` ({}): parameter `{key}`: {message}",
                    s.id, info.id
                ),
            )
            .with_help(help)
        }
        StageError::InvalidInput { port, message } => {
            let loc = s.inputs.get(&port).map(|r| r.value_loc).unwrap_or(s.id_loc);
            err(
                doc,
                loc,
                format!("step `{}` ({}): input `{port}`: {message}", s.id, info.id),
            )
        }
        other => err(
            doc,
            s.uses_loc,
            format!("step `{}` ({}): {other}", s.id, info.id),
        ),
    }
}

fn unit_hint(unit: &str) -> String {
    if unit.is_empty() || unit == "1" {
        String::new()
    } else {
        format!(" [{unit}; a number in SI or a string such as \"140 um\"]")
    }
}

/// `step` or `step.port` to (producer index, port name).
fn resolve_ref(
    doc: &PipelineDoc,
    stages: &[Arc<dyn Stage>],
    r: &PortRef,
    loc: Loc,
) -> Result<(usize, String), PipelineError> {
    let (i, _) = doc.step(&r.step).ok_or_else(|| {
        err(doc, loc, format!("no step `{}` in this pipeline", r.step)).with_help(did_you_mean(
            closest(&r.step, doc.steps.iter().map(|s| s.id.as_str())),
        ))
    })?;
    let outputs: Vec<&str> = stages[i].info().outputs.iter().map(|p| p.name).collect();
    match &r.port {
        Some(p) if outputs.contains(&p.as_str()) => Ok((i, p.clone())),
        Some(p) => Err(err(
            doc,
            loc,
            format!(
                "step `{}` ({}) has no output `{p}`",
                r.step,
                stages[i].info().id
            ),
        )
        .with_help(
            did_you_mean(closest(p, outputs.iter().copied()).map(|o| format!("{}.{o}", r.step)))
                .or(Some(format!("its outputs are: {}", list_or_none(&outputs)))),
        )),
        None if outputs.len() == 1 => Ok((i, outputs[0].to_string())),
        None => Err(err(
            doc,
            loc,
            format!("step `{}` has several outputs; name one", r.step),
        )
        .with_help(Some(format!(
            "write one of: {}",
            outputs
                .iter()
                .map(|o| format!("{}.{o}", r.step))
                .collect::<Vec<_>>()
                .join(", ")
        )))),
    }
}

/// Kahn's algorithm over the input wires; a cycle is reported with its members.
fn topological_order(
    doc: &PipelineDoc,
    wires: &[IndexMap<String, Wire>],
) -> Result<Vec<usize>, PipelineError> {
    let n = wires.len();
    let mut indegree: Vec<usize> = wires.iter().map(|w| w.len()).collect();
    let mut consumers: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (i, w) in wires.iter().enumerate() {
        for wire in w.values() {
            consumers[wire.producer].push(i);
        }
    }
    // Keep file order among independent steps so runs read top to bottom.
    let mut ready: std::collections::BTreeSet<usize> =
        (0..n).filter(|&i| indegree[i] == 0).collect();
    let mut order = Vec::with_capacity(n);
    while let Some(i) = ready.pop_first() {
        order.push(i);
        for &c in &consumers[i] {
            indegree[c] -= 1;
            if indegree[c] == 0 {
                ready.insert(c);
            }
        }
    }
    if order.len() < n {
        let in_cycle: Vec<&str> = (0..n)
            .filter(|&i| indegree[i] > 0)
            .map(|i| doc.steps[i].id.as_str())
            .collect();
        let first = (0..n).find(|&i| indegree[i] > 0).expect("cycle member");
        return Err(err(
            doc,
            doc.steps[first].id_loc,
            format!(
                "the steps {} depend on each other in a cycle",
                in_cycle
                    .iter()
                    .map(|s| format!("`{s}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        )
        .with_help(Some(
            "a step's inputs must come from steps that do not need its outputs".into(),
        )));
    }
    Ok(order)
}

/// The content hash of every file or directory named by a parameter declared `file`
/// (`reads_file`), so editing an input invalidates the cache. Errors name the parameter.
fn hash_input_files(
    stage: &dyn Stage,
    params: &serde_json::Value,
) -> Result<Vec<(String, String)>, (String, String)> {
    let mut out = Vec::new();
    for spec in stage.info().params.iter().filter(|p| p.reads_file) {
        let mut paths = Vec::new();
        collect_paths(
            params.get(spec.name).unwrap_or(&serde_json::Value::Null),
            &mut paths,
        );
        for path in paths {
            let hash = crate::fsutil::content_hash(Path::new(&path)).map_err(|e| {
                (
                    spec.name.to_string(),
                    format!("parameter `{}`: cannot read `{path}`: {e}", spec.name),
                )
            })?;
            out.push((path, hash));
        }
    }
    Ok(out)
}

/// Strings in a parameter value (a path, or a list or map of paths); empty strings are unset.
fn collect_paths(v: &serde_json::Value, out: &mut Vec<String>) {
    match v {
        serde_json::Value::String(s) if !s.is_empty() => out.push(s.clone()),
        serde_json::Value::Array(a) => a.iter().for_each(|x| collect_paths(x, out)),
        serde_json::Value::Object(m) => m.values().for_each(|x| collect_paths(x, out)),
        _ => {}
    }
}

fn cache_key(
    stage: &dyn Stage,
    params: &serde_json::Value,
    seed: u64,
    input_files: &[(String, String)],
    wires: &IndexMap<String, Wire>,
    planned: &[Option<PlannedStep>],
) -> String {
    let mut h = blake3::Hasher::new();
    let info = stage.info();
    h.update(info.id.as_bytes());
    h.update(b"\0");
    h.update(info.version.as_bytes());
    h.update(b"\0");
    h.update(params.to_string().as_bytes());
    h.update(&seed.to_le_bytes());
    for (path, hash) in input_files {
        h.update(path.as_bytes());
        h.update(b"#");
        h.update(hash.as_bytes());
        h.update(b";");
    }
    let mut inputs: Vec<_> = wires.iter().collect();
    inputs.sort_by(|a, b| a.0.cmp(b.0));
    for (port, w) in inputs {
        h.update(port.as_bytes());
        h.update(b"=");
        h.update(
            planned[w.producer]
                .as_ref()
                .expect("producer planned")
                .cache_key
                .as_bytes(),
        );
        h.update(b".");
        h.update(w.port.as_bytes());
        h.update(b";");
    }
    h.finalize().to_hex()[..32].to_string()
}

/// Memory the system can still give [bytes], from /proc/meminfo (Linux); `None` elsewhere.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// Human-readable byte count.
pub fn human_bytes(b: u64) -> String {
    const U: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = b as f64;
    let mut u = 0;
    while v >= 1024.0 && u < U.len() - 1 {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{b} B")
    } else {
        format!("{v:.1} {}", U[u])
    }
}

/// Receives what happens during execution (the CLI draws progress and the summary table).
pub trait Observer {
    /// A step starts; the returned reporter receives its progress and messages.
    fn step_started(&mut self, step: &PlannedStep) -> Box<dyn Reporter>;
    fn step_finished(&mut self, step: &PlannedStep, stats: &StepStats);
    fn exported(&mut self, path: &Path);
}

/// An observer that shows nothing (tests, benchmarks, embedding).
pub struct SilentObserver;

impl Observer for SilentObserver {
    fn step_started(&mut self, _: &PlannedStep) -> Box<dyn Reporter> {
        Box::new(crate::stage::SilentReporter)
    }
    fn step_finished(&mut self, _: &PlannedStep, _: &StepStats) {}
    fn exported(&mut self, _: &Path) {}
}

/// How one step went.
#[derive(Clone, Debug)]
pub struct StepStats {
    pub wall: Duration,
    pub from_cache: bool,
}

/// Execution settings.
#[derive(Clone, Debug)]
pub struct RunOptions {
    pub cache_dir: Option<PathBuf>,
}

/// Results of a run.
pub struct RunResult {
    /// Outputs of every executed step, by step id.
    pub outputs: IndexMap<String, Arc<Outputs>>,
    pub stats: IndexMap<String, StepStats>,
}

/// Identifies the layout of cached artifacts: bump it whenever the serialized data model
/// or the entry layout changes, so entries written by an older grainpipe are recomputed
/// instead of misread. 2: field component conventions, bond attributes, collections.
/// 3: a BLAKE3 checksum of (key, payload) after the magic.
const CACHE_MAGIC: &[u8; 8] = b"GRPCACH3";

fn cache_path(dir: &Path, key: &str) -> PathBuf {
    dir.join(format!("{key}.bin"))
}

/// What reading a cache entry gave.
enum CacheRead {
    /// No entry (the normal miss), or one written by another grainpipe layout.
    Miss,
    Hit(Outputs),
    /// An entry that exists but cannot be trusted; the reason is shown as a warning.
    Corrupt(String),
}

/// The checksum covers the key too, so an entry copied onto another step's key is refused
/// like a flipped bit, before its payload is even decoded.
fn cache_checksum(key: &str, body: &[u8]) -> blake3::Hash {
    let mut h = blake3::Hasher::new();
    h.update(key.as_bytes());
    h.update(b"\0");
    h.update(body);
    h.finalize()
}

fn cache_load(dir: &Path, key: &str) -> CacheRead {
    let Ok(bytes) = std::fs::read(cache_path(dir, key)) else {
        return CacheRead::Miss;
    };
    let Some(rest) = bytes.strip_prefix(CACHE_MAGIC.as_slice()) else {
        return CacheRead::Miss;
    };
    if rest.len() < 32 {
        return CacheRead::Corrupt("truncated entry".into());
    }
    let (sum, body) = rest.split_at(32);
    if cache_checksum(key, body).as_bytes() != sum {
        return CacheRead::Corrupt(
            "checksum mismatch (damaged file, or another step's entry)".into(),
        );
    }
    match postcard::from_bytes::<Vec<(String, Artifact)>>(body) {
        Ok(v) => CacheRead::Hit(v.into_iter().collect()),
        Err(e) => CacheRead::Corrupt(format!("undecodable payload: {e}")),
    }
}

fn cache_store(dir: &Path, key: &str, outputs: &Outputs) -> Result<(), String> {
    let v: Vec<(&String, &Artifact)> = outputs.iter().collect();
    let body = postcard::to_stdvec(&v).map_err(|e| e.to_string())?;
    let mut bytes = CACHE_MAGIC.to_vec();
    bytes.extend_from_slice(cache_checksum(key, &body).as_bytes());
    bytes.extend(body);
    crate::fsutil::atomic_write_bytes(&cache_path(dir, key), &bytes)
}

/// A cache entry is used only if it holds exactly what the step's preflight announced
/// (kinds, grids, boxes, counts) and every artifact is internally consistent; otherwise the
/// step is recomputed. The message says why an entry was refused.
fn check_cached(step: &PlannedStep, o: &Outputs) -> Result<(), String> {
    let info = step.stage.info();
    for (name, a) in o.iter() {
        let Some(spec) = info.outputs.iter().find(|p| p.name == name.as_str()) else {
            return Err(format!("holds an output `{name}` the stage does not have"));
        };
        if a.kind() != spec.kind {
            return Err(format!(
                "output `{name}` is a {}, not a {}",
                a.kind(),
                spec.kind
            ));
        }
        a.validate().map_err(|e| format!("output `{name}`: {e}"))?;
    }
    for (name, announced) in &step.preflight.outputs {
        let a = o
            .get(name)
            .ok_or_else(|| format!("lacks the announced output `{name}`"))?;
        announced
            .check(a)
            .map_err(|m| format!("output `{name}` {m}"))?;
    }
    Ok(())
}

/// Runs a checked plan: steps in order, cached results reused, exports written as soon as
/// their producer has finished.
/// Plans and runs `doc` without cache or progress output: the whole pipeline in one call,
/// for tests, benchmarks and embedding.
pub fn run_quietly(doc: &PipelineDoc, registry: &Registry) -> Result<RunResult, PipelineError> {
    let p = plan(doc, registry, &PlanOptions::default())?;
    execute(
        doc,
        &p,
        &RunOptions { cache_dir: None },
        &mut SilentObserver,
    )
}

pub fn execute(
    doc: &PipelineDoc,
    plan: &Plan,
    opts: &RunOptions,
    observer: &mut dyn Observer,
) -> Result<RunResult, PipelineError> {
    let mut results: Vec<Option<Arc<Outputs>>> = (0..plan.steps.len()).map(|_| None).collect();
    let mut stats = IndexMap::new();
    let mut timings: Vec<(String, f64)> = Vec::new();
    for &i in &plan.order {
        let step = plan.steps[i].as_ref().expect("planned");
        let mut inputs = Inputs::new();
        for (port, w) in &step.inputs {
            let out = results[w.producer]
                .as_ref()
                .expect("producer ran before consumer");
            let a = out.get(&w.port).ok_or_else(|| {
                PipelineError::run(
                    &doc.file,
                    Some(doc.steps[w.producer].id_loc),
                    format!(
                        "step `{}` did not produce its declared output `{}`",
                        doc.steps[w.producer].id, w.port
                    ),
                )
            })?;
            inputs.insert(port.clone(), Arc::new(a.clone()));
        }
        let start = Instant::now();
        let reporter = observer.step_started(step);
        let cached = match opts
            .cache_dir
            .as_ref()
            .map(|d| cache_load(d, &step.cache_key))
        {
            Some(CacheRead::Hit(o)) => match check_cached(step, &o) {
                Ok(()) => Some(o),
                Err(m) => {
                    reporter.message(
                        crate::stage::Level::Warn,
                        &format!("cache entry {} refused ({m}); recomputing", step.cache_key),
                    );
                    None
                }
            },
            Some(CacheRead::Corrupt(m)) => {
                reporter.message(
                    crate::stage::Level::Warn,
                    &format!(
                        "cache entry {} is corrupt ({m}); recomputing",
                        step.cache_key
                    ),
                );
                None
            }
            Some(CacheRead::Miss) | None => None,
        };
        let from_cache = cached.is_some();
        let outputs = match cached {
            Some(o) => o,
            None => {
                let ctx = RunContext::new(step.seed, &*reporter);
                let o = step
                    .stage
                    .run(&step.params, &step.prepared, &inputs, &ctx)
                    .map_err(|e| {
                        // Exit code 2 promises that nothing ran: an input error found at run
                        // time after other steps ran (or were served) is a run failure.
                        let class_input = matches!(
                            e,
                            StageError::InvalidParam { .. } | StageError::InvalidInput { .. }
                        ) && stats.is_empty();
                        let cancelled = matches!(e, StageError::Cancelled);
                        let mut pe = stage_error(doc, i, &*step.stage, e);
                        if cancelled {
                            pe.class = crate::pipeline::ErrorClass::Interrupted;
                        } else if !class_input {
                            pe.class = crate::pipeline::ErrorClass::Run;
                        }
                        pe
                    })?;
                check_outputs(doc, i, step, &o)?;
                if let Some(d) = &opts.cache_dir {
                    if let Err(e) = cache_store(d, &step.cache_key, &o) {
                        reporter.message(
                            crate::stage::Level::Warn,
                            &format!("cache not written: {e}"),
                        );
                    }
                }
                o
            }
        };
        drop(reporter);
        let st = StepStats {
            wall: start.elapsed(),
            from_cache,
        };
        observer.step_finished(step, &st);
        timings.push((step.id.clone(), st.wall.as_secs_f64()));
        stats.insert(step.id.clone(), st);
        let outputs = Arc::new(outputs);
        results[i] = Some(outputs.clone());
        for e in plan.exports.iter().filter(|e| e.producer == i) {
            let artifact = outputs.get(&e.port).ok_or_else(|| {
                PipelineError::run(
                    &doc.file,
                    Some(e.loc),
                    format!("step `{}` gave no output `{}` to export", step.id, e.port),
                )
            })?;
            let prov = provenance(doc, plan, step, &e.port, &timings);
            e.exporter.write(artifact, &e.path, &prov).map_err(|m| {
                PipelineError::run(&doc.file, Some(e.loc), format!("export failed: {m}"))
            })?;
            observer.exported(&e.path);
        }
    }
    let outputs = plan
        .order
        .iter()
        .map(|&i| (doc.steps[i].id.clone(), results[i].clone().expect("ran")))
        .collect();
    Ok(RunResult { outputs, stats })
}

/// A stage must give every output its preflight announced, with the declared kind.
fn check_outputs(
    doc: &PipelineDoc,
    i: usize,
    step: &PlannedStep,
    o: &Outputs,
) -> Result<(), PipelineError> {
    for spec in &step.stage.info().outputs {
        let Some(announced) = step.preflight.outputs.get(spec.name) else {
            continue;
        };
        match o.get(spec.name) {
            Some(a) if a.kind() == spec.kind => {
                if let Err(m) = announced.check(a) {
                    return Err(PipelineError::run(
                        &doc.file,
                        Some(doc.steps[i].uses_loc),
                        format!(
                            "internal error in stage `{}`: output `{}` {m} (its preflight \
                             announced one thing and its run produced another; please report \
                             this)",
                            step.stage.info().id,
                            spec.name
                        ),
                    ));
                }
            }
            Some(a) => {
                return Err(PipelineError::run(
                    &doc.file,
                    Some(doc.steps[i].uses_loc),
                    format!(
                        "stage `{}` gave a {} for output `{}`, declared {}",
                        step.stage.info().id,
                        a.kind(),
                        spec.name,
                        spec.kind
                    ),
                ))
            }
            None => {
                return Err(PipelineError::run(
                    &doc.file,
                    Some(doc.steps[i].uses_loc),
                    format!(
                        "stage `{}` did not give its output `{}`",
                        step.stage.info().id,
                        spec.name
                    ),
                ))
            }
        }
    }
    Ok(())
}

/// Provenance written into every exported file.
fn provenance(
    doc: &PipelineDoc,
    plan: &Plan,
    step: &PlannedStep,
    port: &str,
    timings: &[(String, f64)],
) -> Provenance {
    let info = step.stage.info();
    let mut p = Provenance::default();
    let e = &mut p.entries;
    e.insert("grainpipe_version".into(), crate::VERSION.into());
    e.insert("pipeline_file".into(), doc.file.display().to_string());
    e.insert("pipeline_name".into(), doc.name.clone());
    e.insert("seed".into(), plan.seed.to_string());
    e.insert("step".into(), format!("{}.{port}", step.id));
    e.insert("stage".into(), format!("{} {}", info.id, info.version));
    e.insert("stage_origin".into(), step.origin.clone());
    e.insert("stage_seed".into(), step.seed.to_string());
    e.insert("params".into(), step.params.to_string());
    e.insert("cache_key".into(), step.cache_key.clone());
    if !step.input_files.is_empty() {
        e.insert(
            "input_files_blake3".into(),
            step.input_files
                .iter()
                .map(|(p, h)| format!("{p}={h}"))
                .collect::<Vec<_>>()
                .join(", "),
        );
    }
    e.insert(
        "stage_timings_s".into(),
        timings
            .iter()
            .map(|(s, t)| format!("{s}={t:.3}"))
            .collect::<Vec<_>>()
            .join(", "),
    );
    e.insert("pipeline_yaml".into(), doc.source.clone());
    p
}
