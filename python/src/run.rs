//! `run` and `validate`: load a pipeline as `pipe` does (file or text, plugins, `--set`
//! overrides, seed, targets), plan it, and for `run` execute it on a worker thread while the
//! calling thread, detached from the interpreter, relays progress to Python and watches for
//! Ctrl-C.

use crate::{convert, guarded, panic_text, registry, to_py_err};
use grainpipe_cli::{describe, plan_pipeline, PlanRequest, PluginLoader};
use grainpipe_core::engine::{self, Observer, Plan, PlannedStep, RunOptions, RunResult, StepStats};
use grainpipe_core::pipeline::{PipelineDoc, PipelineError as CoreError};
use grainpipe_core::stage::{Level, Reporter};
use grainpipe_core::Registry;
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// What the Python layer passes to `run` and `validate`.
struct Request {
    /// A file path, or the YAML text when `is_text`.
    source: String,
    is_text: bool,
    /// The name errors and provenance use for a pipeline given as text.
    pseudo_path: String,
    overrides: Vec<String>,
    seed: Option<u64>,
    targets: Vec<String>,
    /// Write the pipeline's `export:` entries (as `pipe run`); otherwise drop them.
    exports: bool,
    out_dir: Option<PathBuf>,
    plugin_dirs: Vec<PathBuf>,
    allow_plugins: bool,
}

/// A pipeline error with the source text its location refers to (when we have it).
type Located = Box<(CoreError, Option<String>)>;

/// The document, its source text (for error snippets) and the plan, or the error with the
/// source text it refers to. Planning is `pipe`'s own ([`grainpipe_cli::plan_pipeline`]).
fn load_and_plan(
    req: &Request,
    registry: &mut Registry,
    loader: &mut PluginLoader,
) -> Result<(PipelineDoc, Plan), Located> {
    let (path, text) = if req.is_text {
        (PathBuf::from(&req.pseudo_path), req.source.clone())
    } else {
        let path = PathBuf::from(&req.source);
        // Read here rather than with PipelineDoc::load so a parse error keeps its source.
        let text = std::fs::read_to_string(&path).map_err(|e| {
            Box::new((
                CoreError::input(&path, None, format!("cannot read pipeline: {e}")),
                None,
            ))
        })?;
        (path, text)
    };
    let with_src = |e: CoreError| {
        let src = (e.file == path).then(|| text.clone());
        Box::new((e, src))
    };
    let doc = PipelineDoc::parse(&path, text.clone()).map_err(with_src)?;
    let plan_req = PlanRequest {
        overrides: req.overrides.clone(),
        seed: req.seed,
        targets: req.targets.clone(),
        skip_exports: !req.exports,
        out_dir: req.out_dir.clone(),
    };
    plan_pipeline(doc, registry, loader, &plan_req).map_err(with_src)
}

fn prepare(py: Python<'_>, req: &Request) -> PyResult<(PipelineDoc, Plan, Registry)> {
    let (mut reg, mut loader) = registry(&req.plugin_dirs, req.allow_plugins)?;
    match load_and_plan(req, &mut reg, &mut loader) {
        Ok((doc, plan)) => Ok((doc, plan, reg)),
        Err(located) => {
            let (e, src) = *located;
            Err(to_py_err(py, &e, src.as_deref()))
        }
    }
}

/// What the engine thread tells the calling thread.
enum Event {
    Start {
        step: String,
        stage: String,
        index: usize,
    },
    Progress {
        step: String,
        done: u64,
        total: u64,
    },
    Message {
        step: String,
        warn: bool,
        text: String,
    },
    Finish {
        step: String,
        wall_s: f64,
        from_cache: bool,
    },
    Exported(PathBuf),
}

/// State shared by the engine thread (observer, reporters) and the calling thread.
struct Shared {
    cancel: AtomicBool,
    events: Mutex<Vec<Event>>,
    /// The calling thread, woken when there is something to relay.
    waiter: std::thread::Thread,
}

impl Shared {
    fn push(&self, e: Event) {
        let mut q = self.events.lock().unwrap_or_else(|p| p.into_inner());
        // Stages may report progress millions of times: keep only the latest report of a
        // step so the queue stays short between two relays.
        if let (Event::Progress { step, .. }, Some(Event::Progress { step: last, .. })) =
            (&e, q.last())
        {
            if step == last {
                q.pop();
            }
        }
        q.push(e);
        drop(q);
        self.waiter.unpark();
    }
}

struct PyReporter {
    shared: Arc<Shared>,
    step: String,
}

impl Reporter for PyReporter {
    fn progress(&self, done: u64, total: u64) {
        self.shared.push(Event::Progress {
            step: self.step.clone(),
            done,
            total,
        });
    }
    fn message(&self, level: Level, text: &str) {
        self.shared.push(Event::Message {
            step: self.step.clone(),
            warn: level == Level::Warn,
            text: text.to_string(),
        });
    }
    fn cancelled(&self) -> bool {
        self.shared.cancel.load(Ordering::SeqCst)
    }
}

struct PyObserver {
    shared: Arc<Shared>,
    index: usize,
    written: Vec<PathBuf>,
}

impl Observer for PyObserver {
    fn step_started(&mut self, step: &PlannedStep) -> Box<dyn Reporter> {
        self.shared.push(Event::Start {
            step: step.id.clone(),
            stage: step.stage.info().id.to_string(),
            index: self.index,
        });
        self.index += 1;
        Box::new(PyReporter {
            shared: self.shared.clone(),
            step: step.id.clone(),
        })
    }
    fn step_finished(&mut self, step: &PlannedStep, stats: &StepStats) {
        self.shared.push(Event::Finish {
            step: step.id.clone(),
            wall_s: stats.wall.as_secs_f64(),
            from_cache: stats.from_cache,
        });
    }
    fn exported(&mut self, path: &Path) {
        self.written.push(path.to_path_buf());
        self.shared.push(Event::Exported(path.to_path_buf()));
    }
}

fn event_dict<'py>(py: Python<'py>, e: Event, count: usize) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    match e {
        Event::Start { step, stage, index } => {
            d.set_item("event", "start")?;
            d.set_item("step", step)?;
            d.set_item("stage", stage)?;
            d.set_item("index", index)?;
            d.set_item("count", count)?;
        }
        Event::Progress { step, done, total } => {
            d.set_item("event", "progress")?;
            d.set_item("step", step)?;
            d.set_item("done", done)?;
            d.set_item("total", total)?;
        }
        Event::Message { step, warn, text } => {
            d.set_item("event", "message")?;
            d.set_item("step", step)?;
            d.set_item("level", if warn { "warn" } else { "info" })?;
            d.set_item("text", text)?;
        }
        Event::Finish {
            step,
            wall_s,
            from_cache,
        } => {
            d.set_item("event", "finish")?;
            d.set_item("step", step)?;
            d.set_item("wall_s", wall_s)?;
            d.set_item("from_cache", from_cache)?;
        }
        Event::Exported(p) => {
            d.set_item("event", "exported")?;
            d.set_item("path", p.display().to_string())?;
        }
    }
    Ok(d)
}

/// Provenance of a step's outputs: the entries the exporters write into files, except the
/// timings, which are not a property of the result. tests/python compares them with an
/// exported file's.
fn provenance<'py>(
    py: Python<'py>,
    doc: &PipelineDoc,
    plan: &Plan,
    step: &PlannedStep,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    for (key, value) in engine::result_provenance(doc, plan, step).entries {
        d.set_item(key, value)?;
    }
    Ok(d)
}

/// Runs the plan on a worker thread. The calling thread stays detached from the interpreter
/// except to relay events to `progress` and to check for signals (Python runs signal
/// handlers only on the main thread, with the interpreter attached): a KeyboardInterrupt, or
/// any exception raised by `progress`, sets the engine's cancel flag, the running stage stops
/// at its next checkpoint, and the exception is raised once the engine has returned. Exports
/// are written atomically by the engine, so a cancelled run leaves no partial file.
fn execute_relaying(
    py: Python<'_>,
    doc: &PipelineDoc,
    plan: &Plan,
    opts: &RunOptions,
    progress: Option<&Bound<'_, PyAny>>,
) -> PyResult<(Result<RunResult, CoreError>, Vec<PathBuf>)> {
    let shared = Arc::new(Shared {
        cancel: AtomicBool::new(false),
        events: Mutex::new(Vec::new()),
        waiter: std::thread::current(),
    });
    let count = plan.order.len();
    let mut pending: Option<PyErr> = None;
    let outcome = std::thread::scope(|s| {
        let sh = shared.clone();
        let worker = s.spawn(move || {
            let mut observer = PyObserver {
                shared: sh.clone(),
                index: 0,
                written: Vec::new(),
            };
            // Unpark the caller also on a panic, so it notices the finished thread at once.
            struct Wake(Arc<Shared>);
            impl Drop for Wake {
                fn drop(&mut self) {
                    self.0.waiter.unpark();
                }
            }
            let _wake = Wake(sh);
            let r = engine::execute(doc, plan, opts, &mut observer);
            (r, observer.written)
        });
        loop {
            let finished = worker.is_finished();
            let events =
                std::mem::take(&mut *shared.events.lock().unwrap_or_else(|p| p.into_inner()));
            for e in events {
                if pending.is_some() {
                    break;
                }
                if let Some(cb) = progress {
                    if let Err(err) = event_dict(py, e, count).and_then(|d| cb.call1((d,))) {
                        pending = Some(err);
                        shared.cancel.store(true, Ordering::SeqCst);
                    }
                }
            }
            if pending.is_none() {
                if let Err(err) = py.check_signals() {
                    pending = Some(err);
                    shared.cancel.store(true, Ordering::SeqCst);
                }
            }
            if finished {
                break worker.join();
            }
            // Woken by the next event; the timeout bounds how late a Ctrl-C is noticed.
            py.detach(|| std::thread::park_timeout(Duration::from_millis(50)));
        }
    });
    match outcome {
        Ok(r) => match pending {
            Some(err) => Err(err),
            None => Ok(r),
        },
        Err(payload) => Err(PyRuntimeError::new_err(format!(
            "internal error in grainpipe (please report this): {}",
            panic_text(&*payload)
        ))),
    }
}

#[allow(clippy::too_many_arguments)]
fn request(
    source: String,
    is_text: bool,
    pseudo_path: String,
    overrides: Vec<String>,
    seed: Option<u64>,
    targets: Vec<String>,
    exports: bool,
    out_dir: Option<PathBuf>,
    plugin_dirs: Vec<PathBuf>,
    allow_plugins: bool,
) -> Request {
    Request {
        source,
        is_text,
        pseudo_path,
        overrides,
        seed,
        targets,
        exports,
        out_dir,
        plugin_dirs,
        allow_plugins,
    }
}

/// Runs a pipeline. Returns `{"outputs": {step: {port: artifact}}, "provenance": {step:
/// {...}}, "stats": {step: {"wall_s", "from_cache"}}, "written": [paths], "seed": int}`.
#[pyfunction]
#[pyo3(signature = (source, is_text, pseudo_path, overrides, seed, targets, exports, out_dir,
                    plugin_dirs, allow_plugins, cache_dir, progress))]
#[allow(clippy::too_many_arguments)]
pub fn run<'py>(
    py: Python<'py>,
    source: String,
    is_text: bool,
    pseudo_path: String,
    overrides: Vec<String>,
    seed: Option<u64>,
    targets: Vec<String>,
    exports: bool,
    out_dir: Option<PathBuf>,
    plugin_dirs: Vec<PathBuf>,
    allow_plugins: bool,
    cache_dir: Option<PathBuf>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let req = request(
        source,
        is_text,
        pseudo_path,
        overrides,
        seed,
        targets,
        exports,
        out_dir,
        plugin_dirs,
        allow_plugins,
    );
    guarded(|| {
        let (doc, plan, _registry) = prepare(py, &req)?;
        let opts = RunOptions { cache_dir };
        let (result, written) = execute_relaying(py, &doc, &plan, &opts, progress.as_ref())?;
        let result = result.map_err(|e| to_py_err(py, &e, Some(&doc.source)))?;
        let out = PyDict::new(py);
        let outputs = PyDict::new(py);
        let provs = PyDict::new(py);
        let stats = PyDict::new(py);
        for (id, o) in result.outputs {
            // The engine keeps no other reference: take the artifacts without a copy.
            let o = Arc::try_unwrap(o).unwrap_or_else(|a| (*a).clone());
            let ports = PyDict::new(py);
            for (port, a) in o {
                ports.set_item(port, convert::artifact(py, a)?)?;
            }
            outputs.set_item(&id, ports)?;
            if let Some(step) = plan.steps.iter().flatten().find(|s| s.id == id) {
                provs.set_item(&id, provenance(py, &doc, &plan, step)?)?;
            }
        }
        for (id, st) in result.stats {
            let d = PyDict::new(py);
            d.set_item("wall_s", st.wall.as_secs_f64())?;
            d.set_item("from_cache", st.from_cache)?;
            stats.set_item(id, d)?;
        }
        out.set_item("outputs", outputs)?;
        out.set_item("provenance", provs)?;
        out.set_item("stats", stats)?;
        let written: Vec<String> = written.iter().map(|p| p.display().to_string()).collect();
        out.set_item("written", written)?;
        out.set_item("seed", plan.seed)?;
        out.set_item("file", doc.file.display().to_string())?;
        Ok(out)
    })
}

fn grid_dict<'py>(
    py: Python<'py>,
    g: &grainpipe_core::model::Grid,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("dims", g.dims.to_vec())?;
    d.set_item("spacing", g.spacing.to_vec())?;
    d.set_item("origin", g.origin.to_vec())?;
    d.set_item("periodic", g.periodic.to_vec())?;
    Ok(d)
}

/// Checks and plans a pipeline without running it (`pipe validate`): the steps that would
/// run with what their preflight announced (grids, boxes, counts), the exports, and the
/// memory estimate.
#[pyfunction]
#[pyo3(signature = (source, is_text, pseudo_path, overrides, seed, targets, exports, out_dir,
                    plugin_dirs, allow_plugins))]
#[allow(clippy::too_many_arguments)]
pub fn validate<'py>(
    py: Python<'py>,
    source: String,
    is_text: bool,
    pseudo_path: String,
    overrides: Vec<String>,
    seed: Option<u64>,
    targets: Vec<String>,
    exports: bool,
    out_dir: Option<PathBuf>,
    plugin_dirs: Vec<PathBuf>,
    allow_plugins: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let req = request(
        source,
        is_text,
        pseudo_path,
        overrides,
        seed,
        targets,
        exports,
        out_dir,
        plugin_dirs,
        allow_plugins,
    );
    guarded(|| {
        let (doc, plan, _registry) = prepare(py, &req)?;
        let steps = PyList::empty(py);
        for &i in &plan.order {
            let s = plan.steps[i]
                .as_ref()
                .ok_or_else(|| PyRuntimeError::new_err("planned step missing"))?;
            let d = PyDict::new(py);
            d.set_item("id", &s.id)?;
            d.set_item("stage", s.stage.info().id)?;
            d.set_item("origin", &s.origin)?;
            d.set_item("memory_bytes", s.preflight.memory_bytes)?;
            d.set_item("params", crate::json_to_py(py, &s.params)?)?;
            let outs = PyDict::new(py);
            for (port, meta) in &s.preflight.outputs {
                let m = PyDict::new(py);
                m.set_item("kind", meta.kind.to_string())?;
                match &meta.grid {
                    Some(g) => m.set_item("grid", grid_dict(py, g)?)?,
                    None => m.set_item("grid", py.None())?,
                }
                m.set_item("count_estimate", meta.count_estimate)?;
                m.set_item("count_bounds", meta.count_bounds.map(|b| b.to_vec()))?;
                m.set_item(
                    "domain_box",
                    meta.domain_box.map(|(lo, hi)| (lo.to_vec(), hi.to_vec())),
                )?;
                m.set_item("summary", describe::announced(meta))?;
                outs.set_item(port, m)?;
            }
            d.set_item("outputs", outs)?;
            steps.append(d)?;
        }
        let exports = PyList::empty(py);
        for e in &plan.exports {
            let d = PyDict::new(py);
            d.set_item("step", &doc.steps[e.producer].id)?;
            d.set_item("port", &e.port)?;
            d.set_item("path", e.path.display().to_string())?;
            d.set_item("format", e.exporter.name())?;
            exports.append(d)?;
        }
        let out = PyDict::new(py);
        out.set_item("file", doc.file.display().to_string())?;
        out.set_item("name", &doc.name)?;
        out.set_item("seed", plan.seed)?;
        out.set_item("steps", steps)?;
        out.set_item("step_count", doc.steps.len())?;
        out.set_item("exports", exports)?;
        out.set_item("memory_bytes", plan.memory_bytes)?;
        Ok(out)
    })
}
