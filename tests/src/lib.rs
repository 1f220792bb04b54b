//! Helpers for the workspace-level tests in `tests/tests/`: run a shipped pipeline with its
//! outputs redirected to a temporary directory.

use grainpipe_core::engine::{run_quietly, RunResult};
use grainpipe_core::pipeline::{PipelineDoc, PipelineError};
use std::path::{Path, PathBuf};

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("workspace root")
        .to_path_buf()
}

/// Loads `pipelines/<name>`, applies `overrides`, rewrites export paths `out/...` into
/// `out_dir`, and runs it without cache through the built-in registry.
pub fn run_pipeline(
    name: &str,
    overrides: &[&str],
    out_dir: &Path,
) -> Result<RunResult, PipelineError> {
    let path = repo_root().join("pipelines").join(name);
    let mut doc = PipelineDoc::load(&path)?;
    for o in overrides {
        doc.apply_override(o)?;
    }
    doc.redirect_exports(out_dir);
    run_quietly(&doc, &grainpipe_cli::builtin_registry())
}
