//! The library behind the `pipe` binary: the registry of built-in stages, the stage
//! listing and descriptions, and the terminal observer. Kept apart from `main.rs` so the
//! workspace tests can drive pipelines exactly as the command does.

pub mod describe;
pub mod observe;

use grainpipe_core::engine::{Plan, PlanOptions};
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
    grainpipe_segment::register(&mut r);
    grainpipe_report::register(&mut r);
    r
}

/// Memory the system can still give, from /proc/meminfo (Linux); `None` elsewhere.
pub fn available_memory() -> Option<u64> {
    grainpipe_core::engine::available_memory()
}

/// How to plan a loaded pipeline: the options `pipe run` / `pipe validate` and the Python
/// package's `run` / `validate` share.
#[derive(Clone, Debug, Default)]
pub struct PlanRequest {
    /// `--set step.key=value` assignments, applied in order.
    pub overrides: Vec<String>,
    /// `--seed`: replaces the pipeline's seed.
    pub seed: Option<u64>,
    /// `--target`: steps to compute with what they need; only their exports are written.
    pub targets: Vec<String>,
    /// Write nothing: the pipeline's exports are dropped, and the targets (every step when
    /// none is named) are computed.
    pub skip_exports: bool,
    /// `--out DIR`: every export moves into DIR.
    pub out_dir: Option<PathBuf>,
}

/// Loads the plugins a pipeline names, applies the request and plans the run (every check,
/// nothing heavy runs). Errors point into the pipeline file (or the `--set` text).
pub fn plan_pipeline(
    mut doc: PipelineDoc,
    registry: &mut Registry,
    loader: &mut PluginLoader,
    req: &PlanRequest,
) -> Result<(PipelineDoc, Plan), PipelineError> {
    loader.load_for(registry, &doc)?;
    for o in &req.overrides {
        doc.apply_override(o)?;
    }
    if let Some(s) = req.seed {
        doc.seed = s;
    }
    let mut targets = req.targets.clone();
    if !targets.is_empty() {
        // As `make TARGET`: the targets and what they need run, and only the exports those
        // steps produce are written (every export used to pull in its whole chain).
        keep_exports_of(&mut doc, &targets);
    }
    if req.skip_exports {
        doc.exports.clear();
        // Without exports nothing would be needed.
        if targets.is_empty() {
            targets = doc.steps.iter().map(|s| s.id.clone()).collect();
        }
    }
    if let Some(dir) = &req.out_dir {
        doc.redirect_exports(dir);
    }
    let opts = PlanOptions {
        targets,
        memory_limit: available_memory(),
    };
    let plan = grainpipe_core::engine::plan(&doc, registry, &opts)?;
    Ok((doc, plan))
}

/// Drops the exports whose step is not a target or upstream of one. Unknown target ids are
/// left for the planner to report (with a suggestion).
fn keep_exports_of(doc: &mut PipelineDoc, targets: &[String]) {
    let mut needed: std::collections::HashSet<&str> = std::collections::HashSet::new();
    let mut todo: Vec<&str> = targets.iter().map(String::as_str).collect();
    while let Some(id) = todo.pop() {
        if !needed.insert(id) {
            continue;
        }
        if let Some((_, step)) = doc.step(id) {
            todo.extend(step.inputs.values().map(|i| i.source.step.as_str()));
        }
    }
    let needed: std::collections::HashSet<String> =
        needed.into_iter().map(str::to_string).collect();
    doc.exports.retain(|e| needed.contains(&e.from.step));
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

/// Writes the manual page of `cmd` (roff) to standard output: clap_mangen's page of `pipe`
/// (synopsis, global options, the list of subcommands) and a section with each subcommand's
/// arguments, so one page documents the whole command.
pub fn print_man(mut cmd: clap::Command) -> std::process::ExitCode {
    use roff::{bold, italic, roman, Roff};
    use std::io::Write;
    cmd.build();
    let mut out = Vec::new();
    let page = clap_mangen::Man::new(cmd.clone()).render(&mut out);
    let mut roff = Roff::default();
    roff.control("SH", ["COMMANDS"]);
    for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set()) {
        roff.control("SS", [format!("pipe {}", sub.get_name()).as_str()]);
        if let Some(about) = sub.get_long_about().or(sub.get_about()) {
            roff.text([roman(about.to_string())]);
        }
        for arg in sub.get_arguments().filter(|a| !a.is_hide_set()) {
            let value = arg
                .get_value_names()
                .map(|v| {
                    v.iter()
                        .map(|n| n.to_string())
                        .collect::<Vec<_>>()
                        .join(" ")
                })
                .unwrap_or_default();
            let mut head = Vec::new();
            match (arg.get_short(), arg.get_long()) {
                (Some(c), Some(l)) => head.push(bold(format!("-{c}, --{l}"))),
                (Some(c), None) => head.push(bold(format!("-{c}"))),
                (None, Some(l)) => head.push(bold(format!("--{l}"))),
                (None, None) => head.push(italic(value.clone())),
            }
            let named = arg.get_long().is_some() || arg.get_short().is_some();
            if named && arg.get_action().takes_values() && !value.is_empty() {
                head.push(roman(" "));
                head.push(italic(value));
            }
            roff.control("TP", []);
            roff.text(head);
            if let Some(help) = arg.get_long_help().or(arg.get_help()) {
                roff.text([roman(help.to_string())]);
            }
        }
    }
    let written = page
        .and_then(|()| roff.to_writer(&mut out))
        .and_then(|()| std::io::stdout().write_all(&out));
    match written {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: cannot write the manual page: {e}");
            std::process::ExitCode::from(1)
        }
    }
}
