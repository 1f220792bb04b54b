//! Helpers for the tests of every crate: run a shipped pipeline through a registry with its
//! exports redirected, and read results by `step.port` and column, with messages that say
//! what is missing instead of a bare `unwrap` panic.

use crate::engine::{run_quietly, RunResult};
use crate::model::{Artifact, ColumnData, Table};
use crate::pipeline::{PipelineDoc, PipelineError};
use crate::registry::Registry;
use crate::stage::{Level, Reporter};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// A reporter that keeps the warnings of a stage run (tests assert on what they say).
#[derive(Default)]
pub struct WarningLog(Mutex<Vec<String>>);

impl WarningLog {
    /// The warnings so far, in the order given.
    pub fn warnings(&self) -> Vec<String> {
        self.0.lock().unwrap().clone()
    }
}

impl Reporter for WarningLog {
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

/// The workspace root, found from a crate's manifest directory (the nearest ancestor that
/// holds `pipelines/`).
pub fn workspace_root(manifest_dir: &str) -> PathBuf {
    Path::new(manifest_dir)
        .ancestors()
        .find(|p| p.join("pipelines").is_dir() && p.join("Cargo.toml").is_file())
        .unwrap_or_else(|| panic!("no workspace root above {manifest_dir}"))
        .to_path_buf()
}

/// Loads `pipelines/<name>` under `root`, applies `--set`-style overrides, redirects the
/// exports into `out_dir` and runs it without cache or progress output.
pub fn run_pipeline(
    registry: &Registry,
    root: &Path,
    name: &str,
    overrides: &[&str],
    out_dir: &Path,
) -> Result<RunResult, PipelineError> {
    let mut doc = PipelineDoc::load(&root.join("pipelines").join(name))?;
    for o in overrides {
        doc.apply_override(o)?;
    }
    doc.redirect_exports(out_dir);
    run_quietly(&doc, registry)
}

/// Runs pipeline text (for tests that build a small pipeline inline).
pub fn run_yaml(registry: &Registry, yaml: &str) -> Result<RunResult, PipelineError> {
    let doc = PipelineDoc::parse(Path::new("test.yaml"), yaml.to_string())?;
    run_quietly(&doc, registry)
}

impl RunResult {
    /// The artifact at `step.port`; panics with the available names when absent.
    pub fn artifact(&self, step_port: &str) -> &Artifact {
        let (step, port) = step_port
            .split_once('.')
            .unwrap_or_else(|| panic!("`{step_port}` is not of the form step.port"));
        let outs = self.outputs.get(step).unwrap_or_else(|| {
            panic!(
                "no step `{step}` ran; ran: {:?}",
                self.outputs.keys().collect::<Vec<_>>()
            )
        });
        outs.get(port).unwrap_or_else(|| {
            panic!(
                "step `{step}` gave no `{port}`; gave: {:?}",
                outs.keys().collect::<Vec<_>>()
            )
        })
    }

    /// The table at `step.port`.
    pub fn table(&self, step_port: &str) -> &Table {
        self.artifact(step_port)
            .as_table()
            .unwrap_or_else(|| panic!("`{step_port}` is not a table"))
    }

    /// A numeric column (f64 or integer) of the table at `step.port`, as f64.
    pub fn column(&self, step_port: &str, column: &str) -> Vec<f64> {
        let t = self.table(step_port);
        let c = t.column(column).unwrap_or_else(|| {
            panic!(
                "table `{step_port}` has no column `{column}`; it has: {:?}",
                t.columns.iter().map(|c| &c.name).collect::<Vec<_>>()
            )
        });
        match &c.data {
            ColumnData::F64(v) => v.clone(),
            ColumnData::I64(v) => v.iter().map(|&x| x as f64).collect(),
            ColumnData::Str(_) => panic!("column `{column}` of `{step_port}` holds text"),
        }
    }

    /// The single value of a one-row numeric column.
    pub fn value(&self, step_port: &str, column: &str) -> f64 {
        let v = self.column(step_port, column);
        assert_eq!(v.len(), 1, "`{step_port}.{column}` has {} rows", v.len());
        v[0]
    }
}
