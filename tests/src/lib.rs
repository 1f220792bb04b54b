//! Helpers for the workspace-level tests in `tests/tests/`: run a shipped pipeline with its
//! outputs redirected to a temporary directory, through the built-in registry.

use grainpipe_core::engine::RunResult;
use grainpipe_core::pipeline::PipelineError;
use std::path::{Path, PathBuf};

/// The repository root.
pub fn repo_root() -> PathBuf {
    grainpipe_core::testing::workspace_root(env!("CARGO_MANIFEST_DIR"))
}

/// Loads `pipelines/<name>`, applies `overrides`, rewrites export paths `out/...` into
/// `out_dir`, and runs it without cache through the built-in registry.
pub fn run_pipeline(
    name: &str,
    overrides: &[&str],
    out_dir: &Path,
) -> Result<RunResult, PipelineError> {
    grainpipe_core::testing::run_pipeline(
        &grainpipe_cli::builtin_registry(),
        &repo_root(),
        name,
        overrides,
        out_dir,
    )
}
