//! `pipe`: run, validate, list and describe grainpipe pipelines.
//!
//! Exit codes: 0 success, 1 a stage failed or an output could not be written, 2 the input
//! (YAML, parameters, references, files) is wrong; nothing heavy has run in that case.

use clap::{Parser, Subcommand};
use grainpipe_cli::observe::{CountingAllocator, TerminalObserver};
use grainpipe_cli::{available_memory, builtin_registry, describe, PluginLoader};
use grainpipe_core::engine::{self, PlanOptions, RunOptions};
use grainpipe_core::pipeline::{PipelineDoc, PipelineError};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[global_allocator]
static ALLOC: CountingAllocator = CountingAllocator;

#[derive(Parser)]
#[command(
    name = "pipe",
    version,
    about = "grainpipe: YAML scene -> validated digital twin of a granular material"
)]
struct Cli {
    /// Load third-party stages from the shared libraries in DIR (repeatable; also
    /// GRAINPIPE_PLUGIN_PATH and `plugins:` in the pipeline).
    #[arg(long = "plugin-dir", value_name = "DIR", global = true)]
    plugin_dirs: Vec<PathBuf>,
    /// Trust the plugin libraries a pipeline file names in `plugins:` (loading a library
    /// runs its code; without this flag only --plugin-dir / GRAINPIPE_PLUGIN_PATH load).
    #[arg(long = "allow-plugins", global = true)]
    allow_plugins: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Args)]
struct PipelineArgs {
    /// The pipeline YAML file.
    file: PathBuf,
    /// Override a parameter: `--set step.key=value` (value read as YAML, units allowed).
    #[arg(long = "set", value_name = "STEP.KEY=VALUE")]
    overrides: Vec<String>,
    /// Override the pipeline's seed.
    #[arg(long)]
    seed: Option<u64>,
    /// Run this step and the steps it needs, and nothing else (repeatable), as `make TARGET`:
    /// only the exports of those steps are written. Without --target every export is.
    #[arg(long = "target", value_name = "STEP")]
    targets: Vec<String>,
}

#[derive(Subcommand)]
enum Command {
    /// Check, then run a pipeline (only the steps its exports or targets need).
    Run {
        #[command(flatten)]
        pipeline: PipelineArgs,
        /// Recompute everything; neither read nor write the cache.
        #[arg(long)]
        no_cache: bool,
        /// Cache directory.
        #[arg(long, default_value = ".grainpipe-cache")]
        cache_dir: PathBuf,
        /// No progress bars or step messages (warnings and errors still print).
        #[arg(long, short)]
        quiet: bool,
        /// Worker threads (default: all cores). Results do not depend on it.
        #[arg(long)]
        threads: Option<usize>,
        /// Run directory: every export moves into DIR (a path under `out/` keeps the part
        /// after `out/`) and the run record (run.json, report-data/) is written there.
        /// Default: the exports' own paths, the record in their common parent directory.
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
        /// Also write the run's HTML report (DIR/report.html, as `pipe report DIR` does).
        #[arg(long)]
        report: bool,
    },
    /// Check a pipeline (YAML, stages, parameters, wiring, memory) without running it.
    Validate {
        #[command(flatten)]
        pipeline: PipelineArgs,
    },
    /// List every stage and export format.
    List {
        /// Markdown table (used for the README).
        #[arg(long)]
        markdown: bool,
    },
    /// Describe a stage (parameters, defaults, units, ports) or an export format.
    Describe {
        /// Stage id or export format (all of them with --json when omitted).
        id: Option<String>,
        /// Machine-readable JSON (parameters with types, units, defaults and JSON Schema).
        #[arg(long)]
        json: bool,
    },
    /// Print the JSON Schema of pipeline files (for editors and validators).
    Schema,
    /// Run a pipeline over a grid of parameter values and realizations (locally or on Slurm).
    Sweep(Box<grainpipe_sweep::SweepArgs>),
    /// Resolution (speed against accuracy) study of one pipeline parameter.
    Study(Box<grainpipe_sweep::StudyArgs>),
    /// Write a self-contained HTML report of a run or a sweep directory.
    Report(grainpipe_report::ReportArgs),
    /// Show the step cache (size, largest and least recently used entries) or prune it.
    Cache {
        #[command(subcommand)]
        action: Option<CacheAction>,
        /// Cache directory.
        #[arg(long, default_value = ".grainpipe-cache", global = true)]
        cache_dir: PathBuf,
    },
    /// Print a shell completion script: `pipe completions bash > /etc/bash_completion.d/pipe`.
    Completions {
        /// The shell to complete for.
        shell: clap_complete::Shell,
    },
    /// Print the manual page (roff) to standard output: `pipe man | man -l -`.
    Man,
}

fn main() -> ExitCode {
    // A closed stdout (`pipe schema | head`) ends the process quietly, as for any Unix filter,
    // instead of a panic in print! (exit 101): Rust ignores SIGPIPE by default.
    #[cfg(unix)]
    // SAFETY: restoring the default disposition of one signal before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    let mut registry = builtin_registry();
    let mut loader = PluginLoader::default();
    loader.allow_pipeline_plugins = cli.allow_plugins;
    let mut locations = cli.plugin_dirs.clone();
    locations.extend(grainpipe_core::plugin_host::env_locations());
    if let Err(e) = loader.load(&mut registry, &locations) {
        eprintln!("error: {e}");
        return ExitCode::from(2);
    }
    match cli.command {
        Command::List { markdown } => {
            if markdown {
                print!("{}", describe::list_markdown(&registry));
            } else {
                print!("{}", describe::list_text(&registry));
            }
            ExitCode::SUCCESS
        }
        Command::Describe { id, json } => {
            let out = match (id, json) {
                (None, true) => Ok(json_text(&describe::registry_json(&registry))),
                (None, false) => Err("name a stage or format, or use --json for all".to_string()),
                (Some(id), true) => match registry.stage(&id) {
                    Some(x) => Ok(json_text(&describe::stage_json(x))),
                    None => describe::describe(&registry, &id).and_then(|_| {
                        Err(format!(
                            "`{id}` is an export format; --json describes stages"
                        ))
                    }),
                },
                (Some(id), false) => describe::describe(&registry, &id),
            };
            match out {
                Ok(text) => {
                    print!("{text}");
                    ExitCode::SUCCESS
                }
                Err(e) => {
                    eprintln!("error: {e}");
                    ExitCode::from(2)
                }
            }
        }
        Command::Sweep(args) => grainpipe_sweep::sweep_command(
            *args,
            &mut registry,
            &mut |r, d| loader.load_for(r, d),
            &cli.plugin_dirs,
        ),
        Command::Study(args) => grainpipe_sweep::study_command(
            *args,
            &mut registry,
            &mut |r, d| loader.load_for(r, d),
            &cli.plugin_dirs,
        ),
        Command::Report(args) => grainpipe_report::report_command(args, &registry),
        Command::Cache { action, cache_dir } => cache_command(action, &cache_dir),
        Command::Schema => {
            print!("{}", json_text(&describe::pipeline_schema(&registry)));
            ExitCode::SUCCESS
        }
        Command::Completions { shell } => {
            let mut cmd = <Cli as clap::CommandFactory>::command();
            clap_complete::generate(shell, &mut cmd, "pipe", &mut std::io::stdout());
            ExitCode::SUCCESS
        }
        Command::Man => grainpipe_cli::print_man(<Cli as clap::CommandFactory>::command()),
        Command::Validate { mut pipeline } => {
            // voxel_size: auto: every level is planned and the plan shown is the finest
            // level's; nothing runs.
            let auto_text = match auto_step(&pipeline, &mut registry, &mut loader) {
                Ok(Some((doc, a))) => {
                    let finest = *a.settings.auto_levels.last().expect("checked levels");
                    match grainpipe_sweep::auto::explain(&doc, &a, &registry) {
                        Ok(text) => {
                            pipeline.overrides.extend(a.overrides(finest));
                            Some(text)
                        }
                        Err(e) => return report(&e),
                    }
                }
                Ok(None) => None,
                Err(e) => return report(&e),
            };
            let (doc, plan) = match load_and_plan(&pipeline, &mut registry, &mut loader) {
                Ok(x) => x,
                Err(e) => return report(&e),
            };
            if let Some(text) = &auto_text {
                println!("{text}; the plan below is at the finest level");
            }
            println!(
                "{}: ok ({} of {} steps needed)",
                doc.file.display(),
                plan.order.len(),
                doc.steps.len()
            );
            for &i in &plan.order {
                let s = plan.steps[i].as_ref().expect("planned");
                println!(
                    "  {:16} {:22} ~{}",
                    s.id,
                    s.stage.info().id,
                    engine::human_bytes(s.preflight.memory_bytes)
                );
                for (port, meta) in &s.preflight.outputs {
                    if let Some(what) = describe::announced(meta) {
                        println!("      {port}: {what}");
                    }
                }
            }
            for e in &plan.exports {
                println!(
                    "  -> {} ({}) ~{}",
                    e.path.display(),
                    e.exporter.name(),
                    engine::human_bytes(engine::export_memory_bytes(&plan, e))
                );
            }
            if let Some(r) = &doc.reference {
                println!(
                    "  reference: {} value(s) compared after the run ({})",
                    r.values.len(),
                    r.source
                );
            }
            println!(
                "estimated memory: {}",
                engine::human_bytes(plan.memory_bytes)
            );
            ExitCode::SUCCESS
        }
        Command::Run {
            pipeline,
            no_cache,
            cache_dir,
            quiet,
            threads,
            out,
            report: html_report,
        } => {
            if let Some(t) = threads {
                if let Err(e) = rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build_global()
                {
                    eprintln!("error: cannot set {t} threads: {e}");
                    return ExitCode::from(2);
                }
            }
            // voxel_size: auto: the levels run first (child processes), then this run at the
            // chosen resolution, whose overrides join the run's (run.json reproduces it).
            let mut pipeline = pipeline;
            let auto_choice = match auto_step(&pipeline, &mut registry, &mut loader) {
                Ok(Some((doc, a))) => {
                    let parent = out
                        .clone()
                        .or_else(|| grainpipe_report::default_run_dir(&doc))
                        .unwrap_or_else(|| PathBuf::from("out"));
                    let req = grainpipe_sweep::auto::Request {
                        file: &pipeline.file,
                        overrides: &pipeline.overrides,
                        seed: doc.seed,
                        levels_dir: grainpipe_sweep::auto::levels_dir(
                            &parent,
                            &doc,
                            &pipeline.overrides,
                            &a.step,
                        ),
                        cache_dir: (!no_cache).then(|| cache_dir.clone()),
                        threads,
                        quiet,
                        memory_limit: available_memory(),
                    };
                    let exe = match std::env::current_exe() {
                        Ok(e) => e,
                        Err(e) => {
                            eprintln!("error: cannot locate the pipe binary: {e}");
                            return ExitCode::from(2);
                        }
                    };
                    let launch =
                        grainpipe_sweep::self_launcher(exe, cli.plugin_dirs.clone(), threads);
                    let resolved = grainpipe_sweep::auto::resolve(
                        &doc,
                        &a,
                        &req,
                        &mut registry,
                        &mut |r, d| loader.load_for(r, d),
                        &launch,
                    );
                    match resolved {
                        Ok(c) => {
                            pipeline.overrides.extend(c.overrides.iter().cloned());
                            Some(c)
                        }
                        Err(grainpipe_sweep::auto::Failure::Pipeline(e)) => return report(&e),
                        Err(grainpipe_sweep::auto::Failure::Printed(code)) => return code,
                    }
                }
                Ok(None) => None,
                Err(e) => return report(&e),
            };
            let (doc, plan) = match load_and_plan(&pipeline, &mut registry, &mut loader) {
                Ok(x) => x,
                Err(e) => return report(&e),
            };
            // --out: move the exports into the run directory and plan again (planning is
            // cheap: preflights allocate nothing large).
            let (doc, plan) = match &out {
                Some(dir) => {
                    let mut doc = doc;
                    doc.redirect_exports(dir);
                    let opts = PlanOptions {
                        targets: pipeline.targets.clone(),
                        memory_limit: available_memory(),
                    };
                    match engine::plan(&doc, &registry, &opts) {
                        Ok(p) => (doc, p),
                        Err(e) => return report(&e),
                    }
                }
                None => (doc, plan),
            };
            let run_dir = out
                .clone()
                .or_else(|| grainpipe_report::default_run_dir(&doc));
            let started = std::time::SystemTime::now();
            let clock = std::time::Instant::now();
            let cancel = Arc::new(AtomicBool::new(false));
            let flag = cancel.clone();
            // First Ctrl-C asks stages to stop at their next progress report; a second one exits.
            let _ = ctrlc::set_handler(move || {
                // Writers (exports) poll the core's flag; stages poll `cancel`.
                grainpipe_core::fsutil::request_interrupt();
                if flag.swap(true, Ordering::SeqCst) {
                    // No half-written `.grainpipe-tmp` file is left behind.
                    grainpipe_core::fsutil::remove_live_temps();
                    std::process::exit(130);
                }
                eprintln!("\ninterrupted: stopping at the next checkpoint (Ctrl-C again to abort)");
            });
            let opts = RunOptions {
                cache_dir: (!no_cache).then_some(cache_dir),
            };
            let mut observer =
                TerminalObserver::new(quiet, cancel).with_cache_dir(opts.cache_dir.clone());
            let result = engine::execute(&doc, &plan, &opts, &mut observer);
            if let Some(dir) = &opts.cache_dir {
                cap_cache(dir, &plan, quiet);
            }
            if !quiet || result.is_err() {
                eprint!("\n{}", observer.table());
            }
            let reference =
                grainpipe_report::record::ReferenceRecord::of(&doc, result.as_ref().ok());
            if let (Some(r), true) = (&reference, result.is_ok()) {
                print_reference(r);
            }
            // The run record, also of a failed run; a record that cannot be written does not
            // fail a run whose exports were written.
            if let Some(dir) = &run_dir {
                let end = grainpipe_report::RunEnd {
                    doc: &doc,
                    plan: &plan,
                    overrides: &pipeline.overrides,
                    steps: observer.step_records(),
                    started,
                    wall_s: clock.elapsed().as_secs_f64(),
                    result: result.as_ref().map_err(|e| e.to_string()),
                    written: observer.written().to_vec(),
                    warnings: observer.warnings(),
                    auto_voxel: auto_choice
                        .as_ref()
                        .and_then(|c| serde_json::to_value(c).ok()),
                    reference,
                };
                match grainpipe_report::write_run_dir(dir, &end) {
                    Ok(()) if !quiet => {
                        eprintln!("run record: {}", dir.join("run.json").display())
                    }
                    Ok(()) => {}
                    Err(e) => eprintln!("warning: run record not written: {e}"),
                }
                if html_report {
                    match grainpipe_report::render_dir(dir, None) {
                        Ok(p) if !quiet => eprintln!("report: {}", p.display()),
                        Ok(_) => {}
                        Err(e) => eprintln!("warning: report not written: {e}"),
                    }
                }
            } else if html_report {
                eprintln!(
                    "warning: no report: the exports share no directory; give one with --out DIR"
                );
            }
            match result {
                Ok(_) => ExitCode::SUCCESS,
                Err(e) => report(&e),
            }
        }
    }
}

fn json_text(v: &serde_json::Value) -> String {
    format!(
        "{}\n",
        serde_json::to_string_pretty(v).expect("JSON values serialize")
    )
}

/// The `pipe run`/`pipe validate` arguments as a [`grainpipe_cli::PlanRequest`]: the same
/// loading, overrides, targets and planning as the Python package.
fn load_and_plan(
    args: &PipelineArgs,
    registry: &mut grainpipe_core::Registry,
    loader: &mut PluginLoader,
) -> Result<(PipelineDoc, engine::Plan), PipelineError> {
    let request = grainpipe_cli::PlanRequest {
        overrides: args.overrides.clone(),
        seed: args.seed,
        targets: args.targets.clone(),
        skip_exports: false,
        out_dir: None,
    };
    grainpipe_cli::plan_pipeline(PipelineDoc::load(&args.file)?, registry, loader, &request)
}

/// The pipeline (plugins loaded, `--set` and `--seed` applied) and its `voxel_size: auto`
/// step, when it has one (settings checked, errors at their key).
fn auto_step(
    args: &PipelineArgs,
    registry: &mut grainpipe_core::Registry,
    loader: &mut PluginLoader,
) -> Result<Option<(PipelineDoc, grainpipe_sweep::auto::AutoStep)>, PipelineError> {
    let mut doc = PipelineDoc::load(&args.file)?;
    loader.load_for(registry, &doc)?;
    for o in &args.overrides {
        doc.apply_override(o)?;
    }
    if let Some(s) = args.seed {
        doc.seed = s;
    }
    Ok(grainpipe_sweep::auto::find(&doc, registry)?.map(|a| (doc, a)))
}

#[derive(Debug, thiserror::Error, miette::Diagnostic)]
#[error("{message}")]
struct YamlDiagnostic {
    message: String,
    #[source_code]
    src: miette::NamedSource<String>,
    #[label("here")]
    span: miette::SourceSpan,
    #[help]
    help: Option<String>,
}

/// Prints every diagnostic of a pipeline error with its file:line:col and snippet (the
/// `--set` text for an override), and gives the exit code. An interrupted run is one line.
fn report(e: &PipelineError) -> ExitCode {
    if e.class == grainpipe_core::pipeline::ErrorClass::Interrupted {
        eprintln!("{}", e.message);
        return ExitCode::from(e.exit_code() as u8);
    }
    let handler =
        miette::GraphicalReportHandler::new_themed(miette::GraphicalTheme::unicode_nocolor())
            .with_context_lines(1);
    let mut files: std::collections::HashMap<PathBuf, Option<String>> = Default::default();
    let count = e.all().count();
    for one in e.all() {
        let source = match &one.source_text {
            Some(t) => Some(t.clone()),
            None => files
                .entry(one.file.clone())
                .or_insert_with(|| std::fs::read_to_string(&one.file).ok())
                .clone(),
        };
        let mut out = String::new();
        let rendered = match (one.loc, source) {
            (Some(loc), Some(src)) if loc.offset <= src.len() => {
                let len = loc.len.min(src.len() - loc.offset);
                let d = YamlDiagnostic {
                    message: one.message.clone(),
                    src: miette::NamedSource::new(one.file.display().to_string(), src),
                    span: (loc.offset, len).into(),
                    help: one.help.clone(),
                };
                handler.render_report(&mut out, &d).is_ok()
            }
            _ => false,
        };
        if rendered {
            eprint!("{out}");
        } else {
            let mut plain = one.clone();
            plain.related.clear();
            eprintln!("error: {plain}");
        }
    }
    if count > 1 {
        eprintln!("{count} errors in {}", e.file.display());
    }
    ExitCode::from(e.exit_code() as u8)
}

#[derive(Subcommand)]
enum CacheAction {
    /// Delete entries: the least recently used beyond --max-size, those unused for longer
    /// than --older-than, or --all. Entries go one by one, each with a single unlink.
    Prune {
        /// Keep at most this much (e.g. `2GB`, `500MiB`).
        #[arg(long, value_name = "SIZE")]
        max_size: Option<String>,
        /// Delete entries not used for this long (e.g. `7d`, `12h`).
        #[arg(long, value_name = "AGE")]
        older_than: Option<String>,
        /// Delete every entry.
        #[arg(long)]
        all: bool,
    },
}

fn cache_command(action: Option<CacheAction>, dir: &std::path::Path) -> ExitCode {
    use grainpipe_core::cache;
    let result = match action {
        None => cache::describe(dir, 5).map_err(|e| e.to_string()),
        Some(CacheAction::Prune {
            max_size,
            older_than,
            all,
        }) => (|| {
            let rule = cache::PruneRule {
                max_size: max_size.as_deref().map(cache::parse_size).transpose()?,
                older_than: older_than.as_deref().map(cache::parse_age).transpose()?,
                all,
            };
            if rule.max_size.is_none() && rule.older_than.is_none() && !rule.all {
                return Err("say what to prune: --max-size SIZE, --older-than AGE or --all".into());
            }
            let r = cache::prune(dir, &rule, &[]).map_err(|e| format!("{}: {e}", dir.display()))?;
            Ok(format!(
                "removed {} entries ({}); {} left ({})\n",
                r.removed,
                engine::human_bytes(r.freed),
                r.kept,
                engine::human_bytes(r.kept_size)
            ))
        })(),
    };
    match result {
        Ok(text) => {
            print!("{text}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}

/// Applies the cache size cap after a run, sparing this run's entries.
fn cap_cache(dir: &std::path::Path, plan: &engine::Plan, quiet: bool) {
    use grainpipe_core::cache;
    let cap = match cache::default_max_size() {
        Ok(Some(cap)) => cap,
        Ok(None) => return,
        Err(e) => {
            eprintln!("warning: cache not capped: {e}");
            return;
        }
    };
    let keep: Vec<String> = plan
        .order
        .iter()
        .filter_map(|&i| plan.steps[i].as_ref().map(|s| s.cache_key.clone()))
        .collect();
    let rule = cache::PruneRule {
        max_size: Some(cap),
        ..Default::default()
    };
    match cache::prune(dir, &rule, &keep) {
        Ok(r) if r.removed > 0 && !quiet => eprintln!(
            "cache: removed {} least recently used entries ({}) to stay under {}",
            r.removed,
            engine::human_bytes(r.freed),
            engine::human_bytes(cap)
        ),
        Ok(_) => {}
        Err(e) => eprintln!("warning: cache not capped: {e}"),
    }
}

/// The `reference:` comparison of a finished run, one line per value (printed also with
/// --quiet: it is a result, not progress).
fn print_reference(r: &grainpipe_report::record::ReferenceRecord) {
    use grainpipe_core::values::Verdict;
    eprintln!("reference ({}):", r.source);
    for c in &r.rows {
        let what = c
            .component
            .as_deref()
            .map(|k| format!(" ({k})"))
            .unwrap_or_default();
        let (factor, unit) = c.written_unit();
        let unit = if unit.is_empty() {
            String::new()
        } else {
            format!(" {unit}")
        };
        let line = match (c.result, c.difference(), c.relative_difference) {
            (Some(x), Some(d), Some(r)) => format!(
                "{:.4}{unit} against {}: {:+.4}{unit} ({:+.1} %){}",
                x / factor,
                c.reference_written,
                d / factor,
                100.0 * r,
                match c.verdict {
                    Verdict::Within => format!(", within {}", c.tolerance),
                    Verdict::Outside => format!(", OUTSIDE {}", c.tolerance),
                    _ => String::new(),
                }
            ),
            _ => format!("not computed: {}", c.why),
        };
        eprintln!("  {}{what}: {line}", c.quantity);
    }
}
