//! grainpipe-sweep: parameter sweeps, ensembles and resolution studies over a pipeline.
//!
//! - `pipe sweep X.yaml --vary step.key=v1,v2 --realizations R`: the cartesian product of the
//!   varied values times R realizations (seeds in [`spec::realization_seed`]), every run
//!   preflighted before any runs, each run a child process (`pipe sweep run-one DIR ID`, the
//!   same code path as a Slurm array task), resumable, results in `DIR/sweep.csv|h5`,
//!   `DIR/summary.csv` and `DIR/charts/`. See docs/sweeps.md.
//! - `pipe study X.yaml --vary step.key=coarse,...,fine --metric step.port.column`: the
//!   error of each level against the finest and by Richardson extrapolation, against its cost.

pub mod auto;
pub mod charts;
pub mod runner;
pub mod slurm;
pub mod spec;
pub mod study;
pub mod table;

use grainpipe_core::pipeline::PipelineDoc;
use grainpipe_core::Registry;
use runner::LocalOptions;
use spec::{error_text, parse_collect, parse_vary, plan_run, run_doc, Manifest, PluginLoad};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};

/// Where runs execute.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Executor {
    /// Child processes on this machine (`--jobs` at once).
    #[default]
    Local,
    /// A Slurm job array (one task per run), submitted with sbatch.
    Slurm,
}

/// `pipe sweep`.
#[derive(clap::Args, Debug)]
#[command(args_conflicts_with_subcommands = true)]
pub struct SweepArgs {
    #[command(subcommand)]
    pub action: Option<SweepAction>,
    #[command(flatten)]
    pub setup: SetupArgs,
}

/// Defines and starts (or resumes) a sweep.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct SetupArgs {
    /// The pipeline YAML file.
    pub file: Option<PathBuf>,
    /// A varied parameter: `step.key=v1,v2,v3` (values read as YAML, units allowed) or
    /// `step.key=a:b:n` (n evenly spaced values). Repeat for a cartesian product.
    #[arg(long = "vary", value_name = "STEP.KEY=VALUES")]
    pub vary: Vec<String>,
    /// Realizations per parameter point (each with its own seed, the same at every point).
    /// On an existing sweep directory a larger count adds realizations (the runs on record
    /// are kept); a smaller one is refused.
    #[arg(long, default_value_t = 1)]
    pub realizations: usize,
    /// Values to collect into the table: `step.port` (every numeric column of a table, every
    /// value of a tensor) or `step.port.column` (repeatable).
    #[arg(long = "collect", value_name = "STEP.PORT[.COLUMN]")]
    pub collect: Vec<String>,
    /// Fixed override applied to every run: `step.key=value`.
    #[arg(long = "set", value_name = "STEP.KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Base seed of the realizations (default: the pipeline's `seed`).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Sweep directory (default `out/sweep-<pipeline name>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Runs at once (local executor; also the Slurm array's concurrency limit when given).
    #[arg(long)]
    pub jobs: Option<usize>,
    /// Worker threads of each run (default: all cores). Results do not depend on it.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Where runs execute. `slurm` writes a job array whose `--mem` is the largest preflight
    /// memory estimate of the runs x 1.5 + 256 MiB.
    #[arg(long, value_enum, default_value = "local")]
    pub executor: Executor,
    /// Slurm: time limit of each array task.
    #[arg(long, default_value = "01:00:00", value_name = "HH:MM:SS")]
    pub time: String,
    /// Slurm: CPUs of each array task (default: --threads, else 1).
    #[arg(long)]
    pub cpus_per_task: Option<usize>,
    /// Slurm: extra `#SBATCH` option, e.g. `--partition=short` (repeatable).
    #[arg(long = "sbatch-option", value_name = "OPTION")]
    pub sbatch_options: Vec<String>,
    #[command(flatten)]
    pub rve: RveArgs,
    /// Run the failed runs again (they are otherwise kept as results).
    #[arg(long)]
    pub retry_failed: bool,
    /// Step cache shared by the runs (shared upstream steps are computed once).
    #[arg(long, default_value = ".grainpipe-cache")]
    pub cache_dir: PathBuf,
    /// Neither read nor write the step cache.
    #[arg(long)]
    pub no_cache: bool,
    /// Only the final counts.
    #[arg(long, short)]
    pub quiet: bool,
    /// Every run uses the base seed itself instead of a derived realization seed (the levels
    /// of `voxel_size: auto` must see the microstructure of the run they decide for).
    #[arg(skip)]
    pub seed_as_is: bool,
    /// The runs write no exports: only the collected values are wanted.
    #[arg(skip)]
    pub no_exports: bool,
}

/// The Kanit et al. RVE analysis of a sweep over cell sizes (eqs. 3.14-3.16).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct RveArgs {
    /// Column of the sweep table holding each run's cell volume (a varied parameter or a
    /// collected value): fits Var = D^2 (A_3/vol)^alpha over the points, writes rve.csv,
    /// rve_tradeoff.csv and charts/rve_*.
    #[arg(long, value_name = "COLUMN")]
    pub rve_volume: Option<String>,
    /// Point variance D_Z^2 of eq. (3.16), for the integral range A_3.
    #[arg(long, value_name = "D2")]
    pub point_variance: Option<f64>,
}

impl RveArgs {
    fn spec(&self) -> Option<spec::RveSpec> {
        self.rve_volume.as_ref().map(|v| spec::RveSpec {
            volume_column: v.clone(),
            point_variance: self.point_variance,
        })
    }
}

#[derive(clap::Subcommand, Debug)]
pub enum SweepAction {
    /// Merge the results of a sweep directory into its tables and charts (after Slurm jobs).
    Collect {
        /// The sweep directory.
        dir: PathBuf,
        #[command(flatten)]
        rve: RveArgs,
    },
    /// Run one run of a sweep (what every child process and Slurm task does).
    #[command(hide = true)]
    RunOne {
        dir: PathBuf,
        id: String,
        #[arg(long)]
        threads: Option<usize>,
    },
    /// Run the run numbered SLURM_ARRAY_TASK_ID of a sweep (the job array's command).
    #[command(hide = true)]
    SlurmTask {
        dir: PathBuf,
        #[arg(long)]
        threads: Option<usize>,
    },
}

/// `pipe study`.
#[derive(clap::Args, Debug)]
pub struct StudyArgs {
    /// The pipeline YAML file.
    pub file: PathBuf,
    /// The resolution parameter and its levels, coarse to fine: `step.key=8um,4um,2um`.
    #[arg(long = "vary", value_name = "STEP.KEY=LEVELS")]
    pub vary: String,
    /// The quantity whose convergence is studied: `step.port.column` (a one-row column).
    #[arg(long, value_name = "STEP.PORT.COLUMN")]
    pub metric: String,
    /// Pick the coarsest level whose estimated relative error is below this target (recorded
    /// in study.json).
    #[arg(long)]
    pub target_error: Option<f64>,
    /// Fixed override: `step.key=value` (repeatable).
    #[arg(long = "set", value_name = "STEP.KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Study directory (default `out/study-<pipeline name>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Worker threads of each run. (Levels run one at a time without the step cache, so
    /// their wall times and memories compare.)
    #[arg(long)]
    pub threads: Option<usize>,
    /// Only the final table.
    #[arg(long, short)]
    pub quiet: bool,
}

fn fail(code: u8, msg: impl std::fmt::Display) -> ExitCode {
    eprintln!("error: {msg}");
    ExitCode::from(code)
}

fn set_threads(threads: Option<usize>) -> Result<(), String> {
    if let Some(t) = threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build_global()
            .map_err(|e| format!("cannot set {t} threads: {e}"))?;
    }
    Ok(())
}

/// The command that runs one run in a child process of this binary.
pub fn self_launcher(
    exe: PathBuf,
    plugin_dirs: Vec<PathBuf>,
    threads: Option<usize>,
) -> impl Fn(&Path, &str) -> Command + Sync {
    move |dir: &Path, id: &str| {
        let mut c = Command::new(&exe);
        for p in &plugin_dirs {
            c.arg("--plugin-dir").arg(p);
        }
        c.arg("sweep").arg("run-one").arg(dir).arg(id);
        if let Some(t) = threads {
            c.arg("--threads").arg(t.to_string());
        }
        c
    }
}

/// `pipe sweep ...`. `load_plugins` loads a pipeline's `plugins:` into the registry;
/// `plugin_dirs` are the `--plugin-dir`s given to `pipe` (passed on to the child processes).
pub fn sweep_command(
    args: SweepArgs,
    registry: &mut Registry,
    load_plugins: &mut PluginLoad,
    plugin_dirs: &[PathBuf],
) -> ExitCode {
    match args.action {
        Some(SweepAction::RunOne { dir, id, threads }) => {
            if let Err(e) = set_threads(threads) {
                return fail(2, e);
            }
            match runner::run_one(&dir, &id, registry, load_plugins) {
                Ok(Some(r)) if r.status == "ok" => ExitCode::SUCCESS,
                Ok(Some(r)) => fail(1, format!("run {id}: {}", r.error)),
                Ok(None) => fail(
                    runner::EXIT_RUN_BUSY,
                    format!("run {id} is being computed by another process; not run twice"),
                ),
                Err(e) => fail(2, e),
            }
        }
        Some(SweepAction::SlurmTask { dir, threads }) => {
            if let Err(e) = set_threads(threads) {
                return fail(2, e);
            }
            let id = match slurm::task_run_id(&dir) {
                Ok(id) => id,
                Err(e) => return fail(2, e),
            };
            eprintln!("slurm task: run {id}");
            match runner::run_one(&dir, &id, registry, load_plugins) {
                Ok(Some(r)) if r.status == "ok" => ExitCode::SUCCESS,
                Ok(Some(r)) => fail(1, format!("run {id}: {}", r.error)),
                Ok(None) => fail(
                    runner::EXIT_RUN_BUSY,
                    format!("run {id} is being computed by another process; not run twice"),
                ),
                Err(e) => fail(2, e),
            }
        }
        Some(SweepAction::Collect { dir, rve }) => collect_command(&dir, &rve),
        None => {
            let exe = match std::env::current_exe() {
                Ok(e) => e,
                Err(e) => return fail(2, format!("cannot locate the pipe binary: {e}")),
            };
            let launch = self_launcher(exe.clone(), plugin_dirs.to_vec(), args.setup.threads);
            let setup = args.setup;
            let prepared = match prepare(&setup, registry, load_plugins) {
                Ok(p) => p,
                Err(code) => return code,
            };
            match setup.executor {
                Executor::Local => {
                    let opts = LocalOptions {
                        jobs: setup.jobs.unwrap_or(1),
                        memory_budget: spec::available_memory(),
                        stop_after: None,
                        quiet: setup.quiet,
                    };
                    execute_local(&prepared, &opts, &launch)
                }
                Executor::Slurm => match slurm::submit(&prepared, &setup, &exe, plugin_dirs) {
                    Ok(()) => ExitCode::SUCCESS,
                    Err(e) => fail(2, e),
                },
            }
        }
    }
}

/// A sweep set up on disk: its directory, manifest and the runs still to do.
pub struct Prepared {
    pub dir: PathBuf,
    pub manifest: Manifest,
    /// Indices into `manifest.runs`.
    pub todo: Vec<usize>,
}

/// Everything before the first run: parse the arguments, preflight every parameter point
/// (all errors reported at once), write or check the manifest, list the runs to do.
/// Errors are printed; the exit code is returned.
pub fn prepare(
    a: &SetupArgs,
    registry: &mut Registry,
    load_plugins: &mut PluginLoad,
) -> Result<Prepared, ExitCode> {
    let Some(file) = &a.file else {
        return Err(fail(
            2,
            "name a pipeline file: pipe sweep X.yaml --vary step.key=v1,v2 (or `pipe sweep collect DIR`)",
        ));
    };
    let doc = PipelineDoc::load(file).map_err(|e| fail(2, error_text(&e)))?;
    load_plugins(registry, &doc).map_err(|e| fail(2, error_text(&e)))?;
    if a.realizations == 0 {
        return Err(fail(2, "--realizations must be at least 1"));
    }
    let vary = a
        .vary
        .iter()
        .map(|v| parse_vary(v))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| fail(2, e))?;
    for (k, v) in vary.iter().enumerate() {
        if vary[..k].iter().any(|w| w.key == v.key) {
            return Err(fail(2, format!("--vary `{}` is given twice", v.key)));
        }
    }
    spec::run_count(&vary, a.realizations).map_err(|e| fail(2, e))?;
    let collect = a
        .collect
        .iter()
        .map(|c| parse_collect(c))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| fail(2, e))?;
    let dir = a
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("out").join(format!("sweep-{}", doc.name)));
    std::fs::create_dir_all(&dir)
        .map_err(|e| fail(2, format!("cannot create {}: {e}", dir.display())))?;
    let dir =
        std::fs::canonicalize(&dir).map_err(|e| fail(2, format!("{}: {e}", dir.display())))?;
    let pipeline =
        std::fs::canonicalize(file).map_err(|e| fail(2, format!("{}: {e}", file.display())))?;
    let hash = grainpipe_core::fsutil::content_hash(&pipeline)
        .map_err(|e| fail(2, format!("{}: {e}", pipeline.display())))?;
    let base_seed = a.seed.unwrap_or(doc.seed);
    let cache_dir = if a.no_cache {
        None
    } else {
        std::fs::create_dir_all(&a.cache_dir)
            .and_then(|_| std::fs::canonicalize(&a.cache_dir))
            .map(Some)
            .map_err(|e| fail(2, format!("cache {}: {e}", a.cache_dir.display())))?
    };
    let mut m = Manifest {
        format: spec::MANIFEST_FORMAT,
        pipeline,
        pipeline_blake3: hash,
        pipeline_name: doc.name.clone(),
        base_seed,
        fixed: a.overrides.clone(),
        vary: vary.clone(),
        realizations: a.realizations,
        collect: a.collect.clone(),
        cache_dir,
        threads: a.threads,
        rve: a.rve.spec(),
        no_exports: a.no_exports,
        runs: spec::runs(&vary, a.realizations, base_seed),
    };
    if a.seed_as_is {
        for r in &mut m.runs {
            r.seed = base_seed;
        }
    }
    let (point_memory, errors) = preflight_points(&m, &dir, registry, &collect, !a.quiet);
    if !errors.is_empty() {
        let points = point_memory.len();
        eprintln!(
            "error: {} of {points} parameter point{} cannot run (nothing ran):",
            errors.len(),
            if points == 1 { "" } else { "s" }
        );
        // Points that fail the same way are listed under one message.
        let mut seen: Vec<(&str, Vec<&str>)> = Vec::new();
        for (what, e) in &errors {
            match seen.iter_mut().find(|(m, _)| *m == e.as_str()) {
                Some((_, w)) => w.push(what),
                None => seen.push((e, vec![what])),
            }
        }
        for (e, whats) in seen {
            let mut at = whats.iter().take(3).copied().collect::<Vec<_>>().join("; ");
            if whats.len() > 3 {
                at += &format!("; and {} more", whats.len() - 3);
            }
            eprintln!("  {e}\n    at {at}");
        }
        return Err(ExitCode::from(2));
    }
    for r in &mut m.runs {
        r.memory_bytes = point_memory[r.point];
    }
    if Manifest::path(&dir).exists() {
        let old = Manifest::load(&dir).map_err(|e| fail(2, e))?;
        if !old.same_points(&m) {
            return Err(fail(
                2,
                format!(
                    "{} holds a different sweep (pipeline content, seed, --set, --vary or \
                     --collect differ); choose another --out or delete it",
                    dir.display()
                ),
            ));
        }
        if m.realizations < old.realizations {
            return Err(fail(
                2,
                format!(
                    "{} holds this sweep with {} realizations; a sweep directory only grows: \
                     ask for --realizations {} (or more, to add realizations)",
                    dir.display(),
                    old.realizations,
                    old.realizations
                ),
            ));
        }
        if m.realizations > old.realizations {
            // Issue 36: `--realizations N` on an existing sweep adds realizations; the runs
            // already done keep their ids and results.
            if !a.quiet {
                eprintln!(
                    "sweep {}: extending from {} to {} realizations (the {} runs on record are kept)",
                    m.pipeline_name,
                    old.realizations,
                    m.realizations,
                    old.runs.len()
                );
            }
        }
        // The runs on record keep their ids (a sweep extended earlier has ids of two widths).
        m = old.extended_to(&m);
    }
    m.save(&dir).map_err(|e| fail(1, e))?;
    let todo: Vec<usize> = (0..m.runs.len())
        .filter(|&i| match runner::load_result(&dir, &m.runs[i].id) {
            Some(r) => a.retry_failed && r.status != "ok",
            None => true,
        })
        .collect();
    if !a.quiet {
        let points = point_memory.len();
        eprintln!(
            "sweep {}: {} runs ({points} point{} x {} realization{}), {} to do, ~{} per run -> {}",
            m.pipeline_name,
            m.runs.len(),
            if points == 1 { "" } else { "s" },
            m.realizations,
            if m.realizations == 1 { "" } else { "s" },
            todo.len(),
            grainpipe_core::engine::human_bytes(point_memory.iter().copied().max().unwrap_or(0)),
            dir.display()
        );
    }
    Ok(Prepared {
        dir,
        manifest: m,
        todo,
    })
}

/// Preflights every parameter point of a sweep (realizations differ only by seed, which no
/// preflight reads) against the available memory. Returns the memory estimate of each point
/// and every error as (the point's overrides, message), so all are reported at once.
pub fn preflight_points(
    m: &Manifest,
    dir: &Path,
    registry: &Registry,
    collect: &[spec::CollectSpec],
    show_progress: bool,
) -> (Vec<u64>, Vec<(String, String)>) {
    let limit = spec::available_memory();
    let mut errors: Vec<(String, String)> = Vec::new();
    let mut point_memory: Vec<u64> = Vec::new();
    let points = m.runs.iter().filter(|r| r.realization == 0).count();
    // Thousands of points take seconds to minutes to preflight: say so instead of going silent.
    let bar = if show_progress && points >= 1000 {
        indicatif::ProgressBar::new(points as u64).with_style(
            indicatif::ProgressStyle::with_template(
                "preflight of the parameter points {pos}/{len} [{bar:30}] eta {eta}",
            )
            .expect("a valid template"),
        )
    } else {
        indicatif::ProgressBar::hidden()
    };
    for r in m.runs.iter().filter(|r| r.realization == 0) {
        bar.inc(1);
        let planned = run_doc(m, r, dir).and_then(|d| plan_run(&d, registry, collect, limit));
        match planned {
            Ok(p) => point_memory.push(p.memory_bytes),
            Err(e) => {
                point_memory.push(0);
                let what = if r.overrides.is_empty() {
                    "the pipeline".to_string()
                } else {
                    r.overrides.join(" ")
                };
                errors.push((what, error_text(&e)));
            }
        }
    }
    bar.finish_and_clear();
    (point_memory, errors)
}

/// Runs the pending runs locally, then writes the tables and charts.
pub fn execute_local(p: &Prepared, opts: &LocalOptions, launch: &runner::Launcher) -> ExitCode {
    if !p.todo.is_empty() {
        // Ctrl-C reaches the children too (same process group): interrupted runs leave no
        // result and are run again by the next `pipe sweep` with the same arguments.
        runner::run_local(&p.dir, &p.manifest, &p.todo, opts, launch);
    }
    finish(&p.dir, &p.manifest, opts.quiet)
}

/// Writes tables and charts and prints the counts.
pub fn finish(dir: &Path, m: &Manifest, quiet: bool) -> ExitCode {
    match table::write_tables(dir, m) {
        Ok((t, c)) => {
            if let Err(e) = charts::sweep_charts(dir, &t, m) {
                eprintln!("warning: charts not drawn: {e}");
            }
            if let Some(r) = &m.rve {
                match table::rve_outputs(dir, &t, m, r) {
                    Ok(text) => eprint!("{text}"),
                    Err(e) => eprintln!("warning: no RVE analysis: {e}"),
                }
            }
            eprintln!(
                "sweep {}: {} ok, {} failed, {} missing -> {}",
                m.pipeline_name,
                c.ok,
                c.failed,
                c.missing,
                dir.join("sweep.csv").display()
            );
            if c.failed > 0 && !quiet {
                eprintln!(
                    "  failed runs are kept in the table (status, error); --retry-failed runs them again"
                );
            }
            if c.missing > 0 {
                ExitCode::from(1)
            } else {
                ExitCode::SUCCESS
            }
        }
        Err(e) => fail(1, e),
    }
}

fn collect_command(dir: &Path, rve: &RveArgs) -> ExitCode {
    let mut m = match Manifest::load(dir) {
        Ok(m) => m,
        Err(e) => return fail(2, e),
    };
    if let Some(r) = rve.spec() {
        m.rve = Some(r);
        if let Err(e) = m.save(dir) {
            return fail(1, e);
        }
    }
    finish(dir, &m, false)
}

/// `pipe study ...`.
pub fn study_command(
    args: StudyArgs,
    registry: &mut Registry,
    load_plugins: &mut PluginLoad,
    plugin_dirs: &[PathBuf],
) -> ExitCode {
    study::study_command(args, registry, load_plugins, plugin_dirs)
}
