//! The library behind the `pipe` binary: the registry of built-in stages, the stage
//! listing and descriptions, and the terminal observer. Kept apart from `main.rs` so the
//! workspace tests can drive pipelines exactly as the command does.

pub mod describe;
pub mod observe;

use grainpipe_core::pipeline::{PipelineDoc, PipelineError};
use grainpipe_core::plugin_host::{expand_locations, load_plugin};
use grainpipe_core::Registry;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// Every stage and exporter that ships with grainpipe.
pub fn builtin_registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_geometry::register(&mut r);
    grainpipe_bricks::register(&mut r);
    grainpipe_sintering::register(&mut r);
    grainpipe_clumps::register(&mut r);
    grainpipe_mcm::register(&mut r);
    grainpipe_binder::register(&mut r);
    grainpipe_analysis::register(&mut r);
    grainpipe_fft::register(&mut r);
    grainpipe_stokes::register(&mut r);
    grainpipe_cemented::register(&mut r);
    grainpipe_peridynamics::register(&mut r);
    grainpipe_report::register(&mut r);
    r
}

/// Memory the system can still give, from /proc/meminfo (Linux); `None` elsewhere.
pub fn available_memory() -> Option<u64> {
    grainpipe_core::engine::available_memory()
}

/// Loads plugin libraries into a registry, each library once.
///
/// Trust model: loading a library runs its code. Libraries the user configured
/// (`--plugin-dir`, `GRAINPIPE_PLUGIN_PATH`) are trusted. A library named by a pipeline
/// file's `plugins:` is someone else's choice: it loads only when it lies in a configured
/// location, or when the user passed `--allow-plugins`; otherwise the pipeline is refused
/// before anything is loaded, so `pipe validate` of a downloaded file runs no foreign code.
#[derive(Default)]
pub struct PluginLoader {
    loaded: HashSet<PathBuf>,
    /// Configured locations (canonical): directories and files given on the command line or
    /// in the environment.
    trusted: Vec<PathBuf>,
    /// `--allow-plugins`: trust the libraries a pipeline file names.
    pub allow_pipeline_plugins: bool,
}

impl PluginLoader {
    /// Loads every library found at `locations` (files, or directories of libraries); these
    /// are the user's own configuration and become trusted locations.
    pub fn load(&mut self, registry: &mut Registry, locations: &[PathBuf]) -> Result<(), String> {
        for loc in locations {
            if let Ok(c) = std::fs::canonicalize(loc) {
                if !self.trusted.contains(&c) {
                    self.trusted.push(c);
                }
            }
        }
        self.load_libraries(registry, locations)
    }

    fn load_libraries(
        &mut self,
        registry: &mut Registry,
        locations: &[PathBuf],
    ) -> Result<(), String> {
        for lib in expand_locations(locations)? {
            // An absolute path: dlopen would search the system library path for a bare name.
            let key = std::fs::canonicalize(&lib)
                .map_err(|e| format!("plugin {}: {e}", lib.display()))?;
            if self.loaded.insert(key.clone()) {
                load_plugin(&key, registry)?;
            }
        }
        Ok(())
    }

    /// Whether a canonical library path lies in (or is) a configured location.
    fn is_trusted(&self, lib: &Path) -> bool {
        self.trusted
            .iter()
            .any(|t| lib == t.as_path() || lib.parent() == Some(t.as_path()))
    }

    /// Loads the `plugins:` of a pipeline; errors point at the YAML entry. Libraries outside
    /// the configured locations need `--allow-plugins` (see [`PluginLoader`]).
    pub fn load_for(
        &mut self,
        registry: &mut Registry,
        doc: &PipelineDoc,
    ) -> Result<(), PipelineError> {
        let at = |loc, e| PipelineError::input(Path::new(&doc.file), Some(loc), e);
        for (path, loc) in &doc.plugins {
            if !self.allow_pipeline_plugins {
                let libs = expand_locations(std::slice::from_ref(path)).map_err(|e| at(*loc, e))?;
                for lib in libs {
                    let key = std::fs::canonicalize(&lib)
                        .map_err(|e| at(*loc, format!("plugin {}: {e}", lib.display())))?;
                    if !self.is_trusted(&key) {
                        return Err(at(
                            *loc,
                            format!(
                                "the pipeline asks to load the plugin library {}, which would \
                                 run its code; not loaded",
                                key.display()
                            ),
                        )
                        .with_help(Some(
                            "if you trust this pipeline file, pass --allow-plugins, or put the \
                             library in a directory given by --plugin-dir or \
                             GRAINPIPE_PLUGIN_PATH"
                                .into(),
                        )));
                    }
                }
            }
            self.load_libraries(registry, std::slice::from_ref(path))
                .map_err(|e| at(*loc, e))?;
        }
        Ok(())
    }
}
