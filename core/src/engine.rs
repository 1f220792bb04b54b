//! The pipeline engine: resolves a [`PipelineDoc`] against a [`Registry`] into a checked
//! [`Plan`] (every stage preflighted before anything runs), then executes only the steps the
//! exports or targets need, with a content-addressed cache.

use crate::cache;
use crate::model::{ArtifactKind, Provenance};
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
    /// Every option the format declares: the export's `with:` value or the default.
    pub options: crate::registry::ExportOptions,
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
    /// Sum of the preflight memory estimates of the steps that will run and of the exports
    /// ([`Exporter::memory_bytes`]) [bytes].
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
///
/// Every phase collects its errors and later phases go on with what is still sound, so the
/// returned error lists every independent fault of the file at once (see
/// [`PipelineError::related`]). A step that failed a phase is skipped by the later ones, and
/// so are the steps that depend on it: their errors would only echo the first.
pub fn plan(
    doc: &PipelineDoc,
    registry: &Registry,
    opts: &PlanOptions,
) -> Result<Plan, PipelineError> {
    if doc.steps.is_empty() {
        return Err(PipelineError::input(
            &doc.file,
            None,
            "the pipeline has no stages",
        ));
    }
    let mut errs = Vec::new();
    check_ids(doc, &mut errs);
    let resolved = resolve_stages(doc, registry, &mut errs);
    let wiring = wire_steps(doc, &resolved.stages, &mut errs);
    let order = topological_order(doc, &wiring.wires, &mut errs);
    let exports = plan_exports(doc, registry, &resolved.stages, &mut errs);
    let referenced = check_reference(doc, &resolved.stages, &mut errs);
    let needed = needed_steps(doc, opts, &exports, &referenced, &wiring.wires, &mut errs);
    let (mut steps, exec_order, mut memory) =
        preflight_steps(doc, &resolved, &wiring, &order, &needed, &mut errs);
    check_export_outputs(doc, &steps, &exports, &mut errs);
    // Each export's write memory (its exporter's preflight) joins its producing step.
    memory = memory.saturating_add(preflight_exports(doc, &mut steps, &exports, &mut errs));
    check_memory(doc, opts, memory, &mut errs);
    PipelineError::collect(errs)?;
    Ok(Plan {
        seed: doc.seed,
        steps,
        order: exec_order,
        exports,
        memory_bytes: memory,
    })
}

/// Step ids are unique and contain no `.` (which separates step and port).
fn check_ids(doc: &PipelineDoc, errs: &mut Vec<PipelineError>) {
    for (i, s) in doc.steps.iter().enumerate() {
        if let Some(prev) = doc.steps[..i].iter().find(|p| p.id == s.id) {
            errs.push(err(
                doc,
                s.id_loc,
                format!(
                    "step id `{}` is used twice (first at line {})",
                    s.id, prev.id_loc.line
                ),
            ));
        }
        if s.id.contains('.') {
            errs.push(err(
                doc,
                s.id_loc,
                format!("step id `{}` must not contain `.`", s.id),
            ));
        }
    }
}

/// Each step's stage and canonical parameters; `None` where they could not be had.
struct Resolved {
    stages: Vec<Option<Arc<dyn Stage>>>,
    origins: Vec<String>,
    params: Vec<Option<serde_json::Value>>,
}

/// Looks up every `use:` and normalizes the parameters of the steps whose stage exists.
fn resolve_stages(
    doc: &PipelineDoc,
    registry: &Registry,
    errs: &mut Vec<PipelineError>,
) -> Resolved {
    let n = doc.steps.len();
    let mut r = Resolved {
        stages: Vec::with_capacity(n),
        origins: Vec::with_capacity(n),
        params: Vec::with_capacity(n),
    };
    for (i, s) in doc.steps.iter().enumerate() {
        let Some(reg) = registry.stage(&s.uses) else {
            errs.push(
                err(doc, s.uses_loc, format!("unknown stage `{}`", s.uses)).with_help(
                    did_you_mean(registry.suggest_stage(&s.uses))
                        .or(Some("`pipe list` shows every stage".into())),
                ),
            );
            r.stages.push(None);
            r.origins.push(String::new());
            r.params.push(None);
            continue;
        };
        let stage = reg.stage.clone();
        let p = stage.normalize_params(&serde_json::Value::Object(s.params.clone()));
        r.params.push(
            p.map_err(|e| errs.extend(stage_errors(doc, i, &*stage, e)))
                .ok(),
        );
        r.origins.push(reg.origin.clone());
        r.stages.push(Some(stage));
    }
    r
}

/// The resolved input wires of every step, and whether all of a step's wiring is sound.
struct Wiring {
    wires: Vec<IndexMap<String, Wire>>,
    sound: Vec<bool>,
}

/// Checks `in:`: ports exist, sources exist, kinds match, required inputs are connected.
/// A step of an unknown stage is not checked (its ports are unknown), nor is an input from
/// one (the unknown stage was reported already).
fn wire_steps(
    doc: &PipelineDoc,
    stages: &[Option<Arc<dyn Stage>>],
    errs: &mut Vec<PipelineError>,
) -> Wiring {
    let n = doc.steps.len();
    let mut out = Wiring {
        wires: vec![IndexMap::new(); n],
        sound: vec![false; n],
    };
    for (i, s) in doc.steps.iter().enumerate() {
        let Some(stage) = &stages[i] else { continue };
        let info = stage.info();
        let before = errs.len();
        let mut silent_gap = false;
        for (port, r) in &s.inputs {
            let Some(spec) = info.inputs.iter().find(|p| p.name == port) else {
                let names: Vec<&str> = info.inputs.iter().map(|p| p.name).collect();
                errs.push(
                    err(
                        doc,
                        r.key_loc,
                        format!("stage `{}` has no input `{port}`", info.id),
                    )
                    .with_help(
                        did_you_mean(closest(port, names.iter().copied()))
                            .or(Some(format!("its inputs are: {}", list_or_none(&names)))),
                    ),
                );
                continue;
            };
            let (producer, out_port) = match resolve_ref(doc, stages, &r.source, r.value_loc) {
                Ok(Some(x)) => x,
                Ok(None) => {
                    silent_gap = true;
                    continue;
                }
                Err(e) => {
                    errs.push(e);
                    continue;
                }
            };
            if producer == i {
                errs.push(err(
                    doc,
                    r.value_loc,
                    format!("step `{}` takes its own output", s.id),
                ));
                continue;
            }
            let out_kind = stages[producer]
                .as_ref()
                .and_then(|st| st.info().outputs.iter().find(|p| p.name == out_port))
                .map(|p| p.kind)
                .expect("resolved port exists");
            if out_kind != spec.kind {
                errs.push(err(
                    doc,
                    r.value_loc,
                    format!(
                        "input `{port}` of `{}` takes a {} but `{}` is a {out_kind}",
                        s.id, spec.kind, r.source
                    ),
                ));
                continue;
            }
            out.wires[i].insert(
                port.clone(),
                Wire {
                    producer,
                    port: out_port,
                },
            );
        }
        for spec in &info.inputs {
            if !spec.optional && !s.inputs.contains_key(spec.name) {
                errs.push(err(
                    doc,
                    s.id_loc,
                    format!(
                        "step `{}` ({}) needs input `{}` ({}): add `in: {{{}: <step>.<port>}}`",
                        s.id, info.id, spec.name, spec.kind, spec.name
                    ),
                ));
            }
        }
        out.sound[i] = errs.len() == before && !silent_gap;
    }
    out
}

/// Resolves every export to its producer, format and options. An export of a step whose
/// stage is unknown is skipped (reported already).
fn plan_exports(
    doc: &PipelineDoc,
    registry: &Registry,
    stages: &[Option<Arc<dyn Stage>>],
    errs: &mut Vec<PipelineError>,
) -> Vec<PlannedExport> {
    let mut exports: Vec<PlannedExport> = Vec::new();
    for e in &doc.exports {
        let (producer, port) = match resolve_ref(doc, stages, &e.from, e.from_loc) {
            Ok(Some(x)) => x,
            Ok(None) => continue,
            Err(x) => {
                errs.push(x);
                continue;
            }
        };
        let kind = stages[producer]
            .as_ref()
            .and_then(|st| st.info().outputs.iter().find(|p| p.name == port))
            .expect("resolved port exists")
            .kind;
        let Some(exporter) = export_format(doc, registry, e, kind, errs) else {
            continue;
        };
        let before = errs.len();
        let path_ok = match check_export_path(&e.to) {
            Err((m, help)) => {
                errs.push(err(doc, e.to_loc, m).with_help(help));
                false
            }
            Ok(()) => true,
        };
        let options = export_options(doc, e, exporter.as_ref(), errs);
        let Some(options) = options.filter(|_| path_ok) else {
            continue;
        };
        let mine = written_paths(exporter.as_ref(), &e.to, &options);
        for prev in &exports {
            let theirs = written_paths(prev.exporter.as_ref(), &prev.path, &prev.options);
            if let Some(m) = collision(&e.to, &mine, &prev.path, &theirs, prev.loc.line) {
                errs.push(
                    err(doc, e.to_loc, m).with_help(Some(
                        "give each export its own file name (a `.mhd` also writes the `.raw` \
                         beside it, a `.csv` its `.csv.json`, a TIFF `stack: directory` the \
                         directory named like the file)"
                            .into(),
                    )),
                );
                break;
            }
        }
        if errs.len() == before {
            exports.push(PlannedExport {
                producer,
                port,
                path: e.to.clone(),
                exporter,
                options,
                loc: e.to_loc,
            });
        }
    }
    exports
}

/// What an export writes, each path made absolute and normalised ([`normalised_path`]).
fn written_paths(
    exporter: &dyn Exporter,
    path: &Path,
    options: &crate::registry::ExportOptions,
) -> Vec<crate::registry::WrittenPath> {
    exporter
        .written_paths(path, options)
        .into_iter()
        .map(|w| crate::registry::WrittenPath {
            path: normalised_path(&w.path),
            directory: w.directory,
        })
        .collect()
}

/// Why two exports (`to`, writing `mine`; `prev_to` at line `line`, writing `theirs`) would
/// overwrite each other, or `None`: one file written by both, or a file inside a directory
/// the other replaces as a whole.
fn collision(
    to: &Path,
    mine: &[crate::registry::WrittenPath],
    prev_to: &Path,
    theirs: &[crate::registry::WrittenPath],
    line: u64,
) -> Option<String> {
    let target = |p: &Path, t: &Path| normalised_path(t) == p;
    for a in mine {
        for b in theirs {
            let inside_b = b.directory && a.path != b.path && a.path.starts_with(&b.path);
            let inside_a = a.directory && a.path != b.path && b.path.starts_with(&a.path);
            if a.path != b.path && !inside_a && !inside_b {
                continue;
            }
            if a.path == b.path && target(&a.path, to) && target(&b.path, prev_to) {
                return Some(format!(
                    "`{}` is already the target of the export at line {line} (`{}`); the \
                     second would overwrite the first",
                    to.display(),
                    prev_to.display()
                ));
            }
            let what = |p: &Path, t: &Path| {
                if target(p, t) {
                    format!("`{}`", t.display())
                } else {
                    format!("`{}` (written with `{}`)", p.display(), t.display())
                }
            };
            let (mine_shown, theirs_shown) = (what(&a.path, to), what(&b.path, prev_to));
            let relation = if a.path == b.path {
                "is also written by"
            } else if inside_b {
                "lies in a directory replaced as a whole by"
            } else {
                "is a directory, replaced as a whole, that holds a file of"
            };
            return Some(format!(
                "the export to `{}` writes {mine_shown}, which {relation} the export at line \
                 {line} ({theirs_shown}); one would overwrite the other",
                to.display()
            ));
        }
    }
    None
}

/// The absolute, normalised form of an export path, so that `out/x.vti`,
/// `./out/../out/x.vti` and `/abs/out/x.vti` compare equal: the longest existing ancestor is
/// resolved by the file system (symbolic links, `..` across them), the rest lexically (`.`
/// dropped, `..` removes the previous component).
pub fn normalised_path(p: &Path) -> PathBuf {
    use std::path::Component;
    let absolute = if p.is_absolute() {
        p.to_path_buf()
    } else {
        std::env::current_dir()
            .map(|d| d.join(p))
            .unwrap_or_else(|_| p.to_path_buf())
    };
    // Longest existing prefix, resolved by the file system.
    let comps: Vec<Component> = absolute.components().collect();
    let mut base = PathBuf::new();
    let mut rest = comps.len();
    for k in (1..=comps.len()).rev() {
        let prefix: PathBuf = comps[..k].iter().collect();
        if let Ok(c) = std::fs::canonicalize(&prefix) {
            base = c;
            rest = k;
            break;
        }
    }
    if base.as_os_str().is_empty() {
        rest = 0;
    }
    for c in &comps[rest..] {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                base.pop();
            }
            other => base.push(other.as_os_str()),
        }
    }
    base
}

/// The writer of an export: by `format:` or by extension, and it must accept the kind (among
/// exporters sharing an extension, the one that accepts it).
fn export_format(
    doc: &PipelineDoc,
    registry: &Registry,
    e: &crate::pipeline::Export,
    kind: crate::model::ArtifactKind,
    errs: &mut Vec<PipelineError>,
) -> Option<Arc<dyn Exporter>> {
    let accepting: Vec<&str> = registry
        .exporters()
        .iter()
        .filter(|x| x.accepts(kind))
        .map(|x| x.name())
        .collect();
    let help = Some(format!(
        "formats for a {kind}: {}",
        list_or_none(&accepting)
    ));
    let loc = e.format_loc.unwrap_or(e.to_loc);
    match registry.exporter_for(e.format.as_deref(), &e.to, kind) {
        Some(x) if x.accepts(kind) => Some(x),
        Some(x) => {
            errs.push(
                err(
                    doc,
                    loc,
                    format!("format `{}` cannot hold a {kind} (`{}`)", x.name(), e.from),
                )
                .with_help(help),
            );
            None
        }
        None => {
            let what = e.format.clone().unwrap_or_else(|| {
                format!(
                    "extension `.{}`",
                    e.to.extension().and_then(|x| x.to_str()).unwrap_or("")
                )
            });
            errs.push(err(doc, loc, format!("no exporter for {what}")).with_help(help));
            None
        }
    }
}

/// Steps upstream of the exports and `--target`s; every step when there are neither.
fn needed_steps(
    doc: &PipelineDoc,
    opts: &PlanOptions,
    exports: &[PlannedExport],
    referenced: &[usize],
    wires: &[IndexMap<String, Wire>],
    errs: &mut Vec<PipelineError>,
) -> Vec<bool> {
    let n = doc.steps.len();
    let mut needed = vec![false; n];
    let mut roots: Vec<usize> = exports.iter().map(|e| e.producer).collect();
    for t in &opts.targets {
        match doc.step(t) {
            Some((i, _)) => roots.push(i),
            None => errs.push(
                PipelineError::input(&doc.file, None, format!("no step `{t}` to target"))
                    .with_help(did_you_mean(closest(
                        t,
                        doc.steps.iter().map(|s| s.id.as_str()),
                    ))),
            ),
        }
    }
    if roots.is_empty() {
        roots = (0..n).collect();
    } else if opts.targets.is_empty() {
        // The values `reference:` compares are computed even when nothing exports them (a
        // `--target` run computes what its targets need and compares what it has).
        roots.extend_from_slice(referenced);
    }
    while let Some(i) = roots.pop() {
        if !needed[i] {
            needed[i] = true;
            roots.extend(wires[i].values().map(|w| w.producer));
        }
    }
    needed
}

/// Each `reference:` quantity names a step of the pipeline and an output of its stage that
/// holds values (a table or a tensor). Returns the steps they name.
fn check_reference(
    doc: &PipelineDoc,
    stages: &[Option<Arc<dyn Stage>>],
    errs: &mut Vec<PipelineError>,
) -> Vec<usize> {
    let Some(r) = &doc.reference else {
        return Vec::new();
    };
    let mut steps = Vec::new();
    for (v, &loc) in r.values.iter().zip(&doc.reference_locs) {
        let Some((step, port, _)) = crate::values::split_quantity(&v.quantity) else {
            continue;
        };
        let Some((i, _)) = doc.step(step) else {
            errs.push(
                err(
                    doc,
                    loc,
                    format!("reference quantity `{}`: no step `{step}`", v.quantity),
                )
                .with_help(did_you_mean(closest(
                    step,
                    doc.steps.iter().map(|s| s.id.as_str()),
                ))),
            );
            continue;
        };
        let Some(stage) = &stages[i] else {
            continue;
        };
        let info = stage.info();
        match info.outputs.iter().find(|o| o.name == port) {
            None => errs.push(
                err(
                    doc,
                    loc,
                    format!(
                        "reference quantity `{}`: step `{step}` ({}) has no output `{port}`",
                        v.quantity, info.id
                    ),
                )
                .with_help(did_you_mean(closest(
                    port,
                    info.outputs.iter().map(|o| o.name),
                ))),
            ),
            Some(o) if !matches!(o.kind, ArtifactKind::Table | ArtifactKind::Tensor) => {
                errs.push(err(
                    doc,
                    loc,
                    format!(
                        "reference quantity `{}`: `{step}.{port}` is a {}, which holds no single \
                         values (name a table column or a tensor component)",
                        v.quantity, o.kind
                    ),
                ))
            }
            Some(_) => steps.push(i),
        }
    }
    steps
}

/// Preflights the needed steps in execution order, passing each one's announced outputs
/// downstream. Returns the planned steps, the execution order and the summed memory.
fn preflight_steps(
    doc: &PipelineDoc,
    r: &Resolved,
    wiring: &Wiring,
    order: &[usize],
    needed: &[bool],
    errs: &mut Vec<PipelineError>,
) -> (Vec<Option<PlannedStep>>, Vec<usize>, u64) {
    let mut planned: Vec<Option<PlannedStep>> = (0..doc.steps.len()).map(|_| None).collect();
    let mut memory = 0u64;
    let mut exec_order = Vec::new();
    for &i in order {
        let (Some(stage), Some(params), true, true) =
            (&r.stages[i], &r.params[i], needed[i], wiring.sound[i])
        else {
            continue;
        };
        let s = &doc.steps[i];
        let wires = &wiring.wires[i];
        let mut metas = InputMetas::new();
        let mut upstream_failed = false;
        for (port, w) in wires {
            let Some(producer) = planned[w.producer].as_ref() else {
                upstream_failed = true;
                continue;
            };
            match producer.preflight.outputs.get(&w.port) {
                Some(meta) => {
                    metas.insert(port.clone(), meta.clone());
                }
                None => {
                    upstream_failed = true;
                    errs.push(err(
                        doc,
                        s.inputs[port].value_loc,
                        format!(
                            "step `{}` will not give output `{}` with these parameters",
                            doc.steps[w.producer].id, w.port
                        ),
                    ));
                }
            }
        }
        if upstream_failed {
            continue;
        }
        let (pf, prepared) = match stage.preflight(params, &metas) {
            Ok(x) => x,
            Err(e) => {
                errs.extend(stage_errors(doc, i, &**stage, e));
                continue;
            }
        };
        let input_files = match hash_input_files(&**stage, params) {
            Ok(x) => x,
            Err((key, m)) => {
                errs.push(param_error(doc, i, &key, true, m));
                continue;
            }
        };
        memory = memory.saturating_add(pf.memory_bytes);
        let seed = crate::derive_seed(doc.seed, s.id.as_bytes());
        let info = stage.info();
        let cache_key = crate::cache::key(
            info.id,
            info.version,
            params,
            seed,
            &input_files,
            wires.iter().map(|(port, w)| {
                let producer = planned[w.producer].as_ref().expect("producer planned");
                (port.as_str(), producer.cache_key.as_str(), w.port.as_str())
            }),
        );
        planned[i] = Some(PlannedStep {
            index: i,
            id: s.id.clone(),
            stage: stage.clone(),
            params: params.clone(),
            inputs: wires.clone(),
            preflight: pf,
            prepared,
            seed,
            input_files,
            cache_key,
            origin: r.origins[i].clone(),
        });
        exec_order.push(i);
    }
    (planned, exec_order, memory)
}

/// What the exports need while they write, from what their producers announced: part of
/// the plan's memory estimate (an exporter that builds its file in memory needs about the
/// file's size; streaming ones little).
fn export_memory(planned: &[Option<PlannedStep>], exports: &[PlannedExport]) -> u64 {
    exports
        .iter()
        .filter_map(|e| {
            let meta = planned[e.producer]
                .as_ref()?
                .preflight
                .outputs
                .get(&e.port)?;
            e.exporter.preflight(meta, &e.options).ok()
        })
        .fold(0u64, u64::saturating_add)
}

/// Peak memory of one planned export [bytes] (`pipe validate` shows it).
pub fn export_memory_bytes(plan: &Plan, e: &PlannedExport) -> u64 {
    export_memory(&plan.steps, std::slice::from_ref(e))
}

/// Every export's port must be among what its producer's preflight announced.
fn check_export_outputs(
    doc: &PipelineDoc,
    planned: &[Option<PlannedStep>],
    exports: &[PlannedExport],
    errs: &mut Vec<PipelineError>,
) {
    for e in exports {
        let Some(p) = planned[e.producer].as_ref() else {
            continue;
        };
        let pf = &p.preflight;
        if !pf.outputs.contains_key(&e.port) {
            errs.push(
                err(
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
                ))),
            );
        }
    }
}

/// Each export checked against its producer's announced output ([`Exporter::preflight`]);
/// the memory a write needs is added to the producing step's estimate (exports are written
/// while the step's outputs are held). Returns the memory added.
fn preflight_exports(
    doc: &PipelineDoc,
    planned: &mut [Option<PlannedStep>],
    exports: &[PlannedExport],
    errs: &mut Vec<PipelineError>,
) -> u64 {
    let mut added = 0u64;
    for e in exports {
        let Some(p) = planned[e.producer].as_mut() else {
            continue;
        };
        let Some(meta) = p.preflight.outputs.get(&e.port) else {
            continue;
        };
        match e.exporter.preflight(meta, &e.options) {
            Ok(bytes) => {
                p.preflight.memory_bytes = p.preflight.memory_bytes.saturating_add(bytes);
                added = added.saturating_add(bytes);
            }
            Err((key, message)) => {
                let loc = doc
                    .exports
                    .iter()
                    .find(|x| x.to_loc == e.loc)
                    .and_then(|x| x.option_locs.get(&key).copied())
                    .unwrap_or(e.loc);
                let what = if key == "to" {
                    format!("format `{}`: {message}", e.exporter.name())
                } else {
                    format!("format `{}`, option `{key}`: {message}", e.exporter.name())
                };
                errs.push(err(doc, loc, what));
            }
        }
    }
    added
}

/// The summed preflight estimate against the memory available. With other errors the sum
/// misses the failed steps, so it can only be too low: a refusal still holds.
fn check_memory(doc: &PipelineDoc, opts: &PlanOptions, memory: u64, errs: &mut Vec<PipelineError>) {
    if let Some(limit) = opts.memory_limit {
        if memory > limit {
            errs.push(
                PipelineError::input(
                    &doc.file,
                    None,
                    format!(
                        "the pipeline needs about {} of memory but {} is available",
                        human_bytes(memory),
                        human_bytes(limit)
                    ),
                )
                .with_help(Some(
                    "reduce the domain size or resolution (see `pipe validate` for the \
                     estimate per stage)"
                        .into(),
                )),
            );
        }
    }
}

/// An export's `with:` checked against its format's declared options, defaults filled in;
/// `None` (with the errors pushed) when an option is unknown or refused.
fn export_options(
    doc: &PipelineDoc,
    e: &crate::pipeline::Export,
    exporter: &dyn Exporter,
    errs: &mut Vec<PipelineError>,
) -> Option<crate::registry::ExportOptions> {
    let declared = exporter.options();
    let names: Vec<&str> = declared.iter().map(|o| o.name).collect();
    let mut unknown = false;
    for key in e.options.keys() {
        if !names.contains(&key.as_str()) {
            let help = match crate::suggest::closest(key, names.iter().copied()) {
                Some(s) => format!("did you mean `{s}`?"),
                None => format!("options of `{}`: {}", exporter.name(), list_or_none(&names)),
            };
            errs.push(
                err(
                    doc,
                    e.option_locs[key],
                    format!("format `{}` has no option `{key}`", exporter.name()),
                )
                .with_help(Some(help)),
            );
            unknown = true;
        }
    }
    if unknown {
        return None;
    }
    let mut options = exporter.default_options();
    for (key, value) in &e.options {
        options.insert(key.clone(), value.clone());
    }
    match exporter.check_options(&options) {
        Ok(()) => Some(options),
        Err((key, message)) => {
            let loc = e.option_locs.get(&key).copied().unwrap_or(e.to_loc);
            errs.push(err(
                doc,
                loc,
                format!("format `{}`, option `{key}`: {message}", exporter.name()),
            ));
            None
        }
    }
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

fn list_or_none(names: &[&str]) -> String {
    if names.is_empty() {
        "none".into()
    } else {
        names.join(", ")
    }
}

/// Maps a stage's preflight error to the YAML places it concerns, one per parameter when it
/// reports several.
fn stage_errors(
    doc: &PipelineDoc,
    i: usize,
    stage: &dyn Stage,
    e: StageError,
) -> Vec<PipelineError> {
    match e {
        StageError::Several(all) => all
            .into_iter()
            .flat_map(|e| stage_errors(doc, i, stage, e))
            .collect(),
        e => vec![stage_error(doc, i, stage, e)],
    }
}

/// Maps one stage error to the YAML place it concerns.
fn stage_error(doc: &PipelineDoc, i: usize, stage: &dyn Stage, e: StageError) -> PipelineError {
    let s = &doc.steps[i];
    let info = stage.info();
    match e {
        StageError::UnknownParam { key, suggestion } => param_error(
            doc,
            i,
            &key,
            false,
            format!("step `{}` ({}): unknown parameter `{key}`", s.id, info.id),
        )
        .with_help(did_you_mean(suggestion).or(Some(format!(
            "`pipe describe {}` lists its parameters",
            info.id
        )))),
        StageError::InvalidParam { key, message } => {
            let top = key.split(['.', '[']).next().unwrap_or(&key).to_string();
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
            param_error(
                doc,
                i,
                &top,
                true,
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

/// An error about parameter `key` of step `i`, located where its value comes from: the last
/// `--set` that changed it (its value, or its key when `at_value` is false), else the key in
/// the file, else the step's `use:`.
fn param_error(
    doc: &PipelineDoc,
    i: usize,
    key: &str,
    at_value: bool,
    message: String,
) -> PipelineError {
    let s = &doc.steps[i];
    match doc.override_of(&s.id, key) {
        Some(o) => o.error(at_value, message),
        None => err(
            doc,
            s.param_locs.get(key).copied().unwrap_or(s.uses_loc),
            message,
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

/// `step` or `step.port` to (producer index, port name); `Ok(None)` when the step exists but
/// its stage is unknown (already reported, so its ports cannot be checked).
fn resolve_ref(
    doc: &PipelineDoc,
    stages: &[Option<Arc<dyn Stage>>],
    r: &PortRef,
    loc: Loc,
) -> Result<Option<(usize, String)>, PipelineError> {
    let (i, _) = doc.step(&r.step).ok_or_else(|| {
        err(doc, loc, format!("no step `{}` in this pipeline", r.step)).with_help(did_you_mean(
            closest(&r.step, doc.steps.iter().map(|s| s.id.as_str())),
        ))
    })?;
    let Some(stage) = &stages[i] else {
        return Ok(None);
    };
    let outputs: Vec<&str> = stage.info().outputs.iter().map(|p| p.name).collect();
    match &r.port {
        Some(p) if outputs.contains(&p.as_str()) => Ok(Some((i, p.clone()))),
        Some(p) => Err(err(
            doc,
            loc,
            format!(
                "step `{}` ({}) has no output `{p}`",
                r.step,
                stage.info().id
            ),
        )
        .with_help(
            did_you_mean(closest(p, outputs.iter().copied()).map(|o| format!("{}.{o}", r.step)))
                .or(Some(format!("its outputs are: {}", list_or_none(&outputs)))),
        )),
        None if outputs.len() == 1 => Ok(Some((i, outputs[0].to_string()))),
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

/// Kahn's algorithm over the input wires; a cycle is reported with its members, and the
/// order returned then holds only the steps outside it (and not downstream of it).
fn topological_order(
    doc: &PipelineDoc,
    wires: &[IndexMap<String, Wire>],
    errs: &mut Vec<PipelineError>,
) -> Vec<usize> {
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
        errs.push(
            err(
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
            )),
        );
    }
    order
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
            .map(|d| cache::load(d, &step.cache_key))
        {
            Some(cache::CacheRead::Hit(o)) => match check_cached(step, &o) {
                Ok(()) => Some(o),
                Err(m) => {
                    reporter.message(
                        crate::stage::Level::Warn,
                        &format!("cache entry {} refused ({m}); recomputing", step.cache_key),
                    );
                    None
                }
            },
            Some(cache::CacheRead::Corrupt(m)) => {
                reporter.message(
                    crate::stage::Level::Warn,
                    &format!(
                        "cache entry {} is corrupt ({m}); recomputing",
                        step.cache_key
                    ),
                );
                None
            }
            Some(cache::CacheRead::Miss) | None => None,
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
                        if matches!(e, StageError::Cancelled) {
                            // Not a fault of the file: no location, one line naming the step
                            // (the steps before it are in the cache and `stats`).
                            let mut pe = PipelineError::run(
                                &doc.file,
                                None,
                                format!(
                                    "interrupted during step `{}` after {:.1} s",
                                    step.id,
                                    start.elapsed().as_secs_f64()
                                ),
                            );
                            pe.class = crate::pipeline::ErrorClass::Interrupted;
                            return pe;
                        }
                        let mut pe = stage_error(doc, i, &*step.stage, e);
                        if !class_input {
                            pe.class = crate::pipeline::ErrorClass::Run;
                        }
                        pe
                    })?;
                check_outputs(doc, i, step, &o)?;
                if let Some(d) = &opts.cache_dir {
                    let header = cache::EntryHeader {
                        step: step.id.clone(),
                        stage: format!("{} {}", step.stage.info().id, step.stage.info().version),
                        pipeline: doc.name.clone(),
                        created: std::time::SystemTime::now()
                            .duration_since(std::time::UNIX_EPOCH)
                            .map(|d| d.as_secs())
                            .unwrap_or(0),
                    };
                    if let Err(e) = cache::store(d, &step.cache_key, &header, &o) {
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
            e.exporter
                .write(artifact, &e.path, &prov, &e.options)
                .map_err(|m| {
                    if crate::fsutil::interrupted() {
                        // A writer stopped by Ctrl-C (its temporary file removed): one line,
                        // like an interrupted step.
                        let mut pe = PipelineError::run(
                            &doc.file,
                            None,
                            format!(
                                "interrupted while writing {} (nothing written there)",
                                e.path.display()
                            ),
                        );
                        pe.class = crate::pipeline::ErrorClass::Interrupted;
                        return pe;
                    }
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

/// Provenance written into every exported file: the step's result provenance, the output
/// port and the run's stage timings.
fn provenance(
    doc: &PipelineDoc,
    plan: &Plan,
    step: &PlannedStep,
    port: &str,
    timings: &[(String, f64)],
) -> Provenance {
    let mut p = result_provenance(doc, plan, step);
    p.entries
        .insert("step".into(), format!("{}.{port}", step.id));
    p.entries.insert(
        "stage_timings_s".into(),
        timings
            .iter()
            .map(|(s, t)| format!("{s}={t:.3}"))
            .collect::<Vec<_>>()
            .join(", "),
    );
    p
}

/// Provenance of a step's results: what the exported files of `step` carry, except the
/// output port (`step` is the step id here) and the run's timings, which are not a property
/// of the result. Python's `Results.provenance` shows it.
pub fn result_provenance(doc: &PipelineDoc, plan: &Plan, step: &PlannedStep) -> Provenance {
    let info = step.stage.info();
    let mut p = Provenance::default();
    let e = &mut p.entries;
    e.insert("grainpipe_version".into(), crate::VERSION.into());
    e.insert("pipeline_file".into(), doc.file.display().to_string());
    e.insert("pipeline_name".into(), doc.name.clone());
    e.insert("seed".into(), plan.seed.to_string());
    e.insert("step".into(), step.id.clone());
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
    // The file as written when nothing was overridden (it keeps its comments); otherwise
    // what actually ran, with the overrides listed next to it.
    if doc.overrides.is_empty() && doc.seed == doc.file_seed {
        e.insert("pipeline_yaml".into(), doc.source.clone());
    } else {
        e.insert("pipeline_yaml".into(), doc.effective_yaml());
        if !doc.overrides.is_empty() {
            e.insert(
                "overrides".into(),
                doc.overrides
                    .iter()
                    .map(|o| format!("--set {}", o.text))
                    .collect::<Vec<_>>()
                    .join("\n"),
            );
        }
        if doc.seed != doc.file_seed {
            e.insert(
                "seed_override".into(),
                format!("--seed {} (the file says {})", doc.seed, doc.file_seed),
            );
        }
    }
    p
}
