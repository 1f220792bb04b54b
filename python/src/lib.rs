//! The `grainpipe` Python extension module (PyO3): the same registry, engine and cache as
//! `pipe`.
//!
//! This is `grainpipe._native`; the public API (`grainpipe.run`, result classes, the
//! optional xarray / pandas / pyvista helpers) is the pure-Python package around it in
//! `python/python/grainpipe/`. Every entry point here is wrapped in `catch_unwind` so a Rust
//! panic surfaces as a `RuntimeError`, never as an abort or a `PanicException` (which
//! `except Exception` would not catch).

mod convert;
mod run;

use grainpipe_cli::{builtin_registry, describe, PluginLoader};
use grainpipe_core::pipeline::{ErrorClass, PipelineError as CoreError};
use grainpipe_core::Registry;
use pyo3::exceptions::{PyException, PyKeyboardInterrupt, PyRuntimeError};
use pyo3::prelude::*;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;

pyo3::create_exception!(
    grainpipe,
    GrainpipeError,
    PyException,
    "Base class of grainpipe's errors."
);
pyo3::create_exception!(
    grainpipe,
    PipelineError,
    GrainpipeError,
    "The pipeline is wrong (YAML, keys, types, references, parameters, files): nothing ran. \
     Attributes: message, file, line, column, key, suggestion."
);
pyo3::create_exception!(
    grainpipe,
    StageError,
    GrainpipeError,
    "A stage failed while running, or an output could not be written. Attributes as \
     PipelineError; the message carries the numbers the stage reached."
);

/// The text a location points at (the key or value of the YAML), when the error is about
/// the document whose source we have.
fn snippet(source: Option<&str>, e: &CoreError) -> Option<String> {
    let loc = e.loc?;
    let src = source?;
    src.get(loc.offset..loc.offset + loc.len)
        .map(|s| s.trim().to_string())
}

/// A core pipeline error as the Python exception of its class: input errors as
/// `PipelineError`, run failures as `StageError`, an interrupted run as `KeyboardInterrupt`.
pub(crate) fn to_py_err(py: Python<'_>, e: &CoreError, source: Option<&str>) -> PyErr {
    let text = e.to_string();
    let err = match e.class {
        ErrorClass::Input => PipelineError::new_err(text),
        ErrorClass::Run => StageError::new_err(text),
        ErrorClass::Interrupted => return PyKeyboardInterrupt::new_err(text),
    };
    let v = err.value(py);
    let set = || -> PyResult<()> {
        v.setattr("message", &e.message)?;
        v.setattr("file", e.file.display().to_string())?;
        v.setattr("line", e.loc.map(|l| l.line))?;
        v.setattr("column", e.loc.map(|l| l.col))?;
        v.setattr("key", snippet(source, e))?;
        v.setattr("suggestion", e.help.clone())?;
        Ok(())
    };
    match set() {
        Ok(()) => err,
        Err(x) => x,
    }
}

/// Runs `f`, turning a Rust panic into a `RuntimeError` with the panic's message.
pub(crate) fn guarded<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => Err(PyRuntimeError::new_err(format!(
            "internal error in grainpipe (please report this): {}",
            panic_text(&*payload)
        ))),
    }
}

pub(crate) fn panic_text(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "panic".to_string())
}

/// The built-in registry plus plugin libraries from `plugin_dirs` and GRAINPIPE_PLUGIN_PATH,
/// loaded as `pipe --plugin-dir` does.
pub(crate) fn registry(
    plugin_dirs: &[PathBuf],
    allow_plugins: bool,
) -> PyResult<(Registry, PluginLoader)> {
    let mut registry = builtin_registry();
    let mut loader = PluginLoader::default();
    loader.allow_pipeline_plugins = allow_plugins;
    let mut locations = plugin_dirs.to_vec();
    locations.extend(grainpipe_core::plugin_host::env_locations());
    loader
        .load(&mut registry, &locations)
        .map_err(|e| PipelineError::new_err(format!("plugins: {e}")))?;
    Ok((registry, loader))
}

pub(crate) fn json_to_py<'py>(
    py: Python<'py>,
    v: &serde_json::Value,
) -> PyResult<Bound<'py, PyAny>> {
    // `json.loads` keeps the key order and maps numbers exactly as Python users expect.
    let text = serde_json::to_string(v).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// Every stage's description (`pipe describe --json`): a dict with `stages` and
/// `export_formats`.
#[pyfunction]
#[pyo3(signature = (plugin_dirs = Vec::new()))]
fn registry_description(py: Python<'_>, plugin_dirs: Vec<PathBuf>) -> PyResult<Bound<'_, PyAny>> {
    guarded(|| {
        let (r, _) = registry(&plugin_dirs, false)?;
        json_to_py(py, &describe::registry_json(&r))
    })
}

/// One stage's description (`pipe describe --json ID`).
#[pyfunction]
#[pyo3(signature = (id, plugin_dirs = Vec::new()))]
fn describe_stage<'py>(
    py: Python<'py>,
    id: &str,
    plugin_dirs: Vec<PathBuf>,
) -> PyResult<Bound<'py, PyAny>> {
    guarded(|| {
        let (r, _) = registry(&plugin_dirs, false)?;
        match r.stage(id) {
            Some(x) => json_to_py(py, &describe::stage_json(x)),
            None => {
                let err = PipelineError::new_err(format!("no stage `{id}`"));
                let v = err.value(py);
                v.setattr("message", format!("no stage `{id}`"))?;
                v.setattr("key", id)?;
                v.setattr("suggestion", r.suggest_stage(id))?;
                for a in ["file", "line", "column"] {
                    v.setattr(a, py.None())?;
                }
                Err(err)
            }
        }
    })
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("GrainpipeError", py.get_type::<GrainpipeError>())?;
    m.add("PipelineError", py.get_type::<PipelineError>())?;
    m.add("StageError", py.get_type::<StageError>())?;
    m.add("VERSION", grainpipe_core::VERSION)?;
    m.add_function(wrap_pyfunction!(registry_description, m)?)?;
    m.add_function(wrap_pyfunction!(describe_stage, m)?)?;
    m.add_function(wrap_pyfunction!(run::run, m)?)?;
    m.add_function(wrap_pyfunction!(run::validate, m)?)?;
    Ok(())
}
