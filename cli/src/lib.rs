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
    r
}

/// Memory the system can still give, from /proc/meminfo (Linux); `None` elsewhere.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Loads plugin libraries into a registry, each library once.
#[derive(Default)]
pub struct PluginLoader {
    loaded: HashSet<PathBuf>,
}

impl PluginLoader {
    /// Loads every library found at `locations` (files, or directories of libraries).
    pub fn load(&mut self, registry: &mut Registry, locations: &[PathBuf]) -> Result<(), String> {
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

    /// Loads the `plugins:` of a pipeline; errors point at the YAML entry.
    pub fn load_for(
        &mut self,
        registry: &mut Registry,
        doc: &PipelineDoc,
    ) -> Result<(), PipelineError> {
        for (path, loc) in &doc.plugins {
            self.load(registry, std::slice::from_ref(path))
                .map_err(|e| PipelineError::input(Path::new(&doc.file), Some(*loc), e))?;
        }
        Ok(())
    }
}
