//! Executing runs: [`run_one`] is what one child process (or one Slurm array task) does;
//! [`run_local`] starts child processes, at most `jobs` at once and no more than the free
//! memory allows by the preflight estimates, and records a result for every run, including
//! runs whose process crashed.

use crate::spec::{error_text, parse_collect, plan_run, run_doc, Manifest, PluginLoad, RunSpec};
use grainpipe_core::engine::{self, RunOptions, SilentObserver};
pub use grainpipe_core::values::{component_name, values_of, Value};
use grainpipe_core::Registry;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Condvar, Mutex};
use std::time::Instant;

/// What a finished run left: `DIR/runs/<id>/result.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunResult {
    pub id: String,
    /// `ok` or `failed`.
    pub status: String,
    pub error: String,
    pub seed: u64,
    /// Wall time of the run [s].
    pub wall_time: f64,
    /// Peak resident memory of the run's process [bytes] (0 when unknown).
    pub peak_memory: u64,
    pub values: Vec<Value>,
}

pub fn run_dir(dir: &Path, id: &str) -> PathBuf {
    dir.join("runs").join(id)
}

pub fn result_path(dir: &Path, id: &str) -> PathBuf {
    run_dir(dir, id).join("result.json")
}

pub fn load_result(dir: &Path, id: &str) -> Option<RunResult> {
    let text = std::fs::read_to_string(result_path(dir, id)).ok()?;
    serde_json::from_str(&text).ok()
}

pub fn save_result(dir: &Path, r: &RunResult) -> Result<(), String> {
    let text = serde_json::to_string_pretty(r).map_err(|e| e.to_string())?;
    grainpipe_core::fsutil::atomic_write_bytes(&result_path(dir, &r.id), text.as_bytes())
}

/// The lock a run holds while it computes: `DIR/runs/<id>/.running`, an advisory lock
/// (flock) held by the process that runs it. The kernel releases it when that process ends,
/// however it ends, so a held lock means a live run.
pub fn running_lock_path(dir: &Path, id: &str) -> PathBuf {
    run_dir(dir, id).join(".running")
}

/// Takes the run's lock: `Ok(None)` when another live process holds it (the run is being
/// computed elsewhere, e.g. by a runner that was killed but whose child still finishes, or
/// a second `pipe sweep` resuming the same directory).
pub fn lock_run(dir: &Path, id: &str) -> Result<Option<std::fs::File>, String> {
    let path = running_lock_path(dir, id);
    std::fs::create_dir_all(run_dir(dir, id))
        .map_err(|e| format!("{}: {e}", run_dir(dir, id).display()))?;
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    if try_lock_exclusive(&file).map_err(|e| format!("{}: {e}", path.display()))? {
        Ok(Some(file))
    } else {
        Ok(None)
    }
}

/// flock(LOCK_EX | LOCK_NB): `Ok(false)` when another open file description holds the lock.
/// (`File::try_lock` does the same from Rust 1.89, above this workspace's minimum version.)
#[cfg(target_os = "linux")]
fn try_lock_exclusive(file: &std::fs::File) -> std::io::Result<bool> {
    use std::os::fd::AsRawFd;
    // SAFETY: flock on a descriptor this function borrows for the duration of the call.
    if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0 {
        return Ok(true);
    }
    let e = std::io::Error::last_os_error();
    if e.kind() == std::io::ErrorKind::WouldBlock {
        Ok(false)
    } else {
        Err(e)
    }
}

/// Elsewhere runs are not locked (the local executor and Slurm tasks target Linux).
#[cfg(not(target_os = "linux"))]
fn try_lock_exclusive(_: &std::fs::File) -> std::io::Result<bool> {
    Ok(true)
}

/// The exit code of a `run-one` child that found its run already running elsewhere
/// (EX_TEMPFAIL): it leaves no result, and the runner records none.
pub const EXIT_RUN_BUSY: u8 = 75;

/// Makes a child process die with the runner (Linux: PR_SET_PDEATHSIG), so that killing a
/// sweep (SIGTERM, SIGKILL, or SIGINT sent to the runner alone) does not leave its runs
/// computing unseen. The signal fires when the spawning thread ends: the runner's worker
/// thread waits for its child, so that is when the runner dies.
fn die_with_parent(command: &mut Command) {
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::process::CommandExt;
        let parent = std::process::id() as libc::pid_t;
        // SAFETY: the closure runs between fork and exec and calls only async-signal-safe
        // functions (prctl, getppid, _exit); it allocates nothing.
        unsafe {
            command.pre_exec(move || {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                // The runner may have died between fork and prctl: then nobody waits for us.
                if libc::getppid() != parent {
                    libc::_exit(1);
                }
                Ok(())
            });
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = command;
}

/// Peak resident set size of this process (VmHWM of /proc/self/status) [bytes]; 0 elsewhere.
pub fn peak_rss() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            let l = s.lines().find(|l| l.starts_with("VmHWM:"))?;
            l.split_whitespace().nth(1)?.parse::<u64>().ok()
        })
        .map_or(0, |kib| kib * 1024)
}

/// The values a `--collect` names in a run's outputs (see [`values_of`]).
pub fn collect_values(
    res: &engine::RunResult,
    spec: &crate::spec::CollectSpec,
) -> Result<Vec<Value>, String> {
    values_of(
        &res.outputs,
        &spec.step,
        &spec.port,
        spec.column.as_deref(),
        "--collect",
    )
}

/// Runs one run of a sweep in this process and writes its `result.json` (also when it fails).
/// Returns the result, or `None` (writing nothing) when the run is already being computed
/// by another live process.
pub fn run_one(
    dir: &Path,
    id: &str,
    registry: &mut Registry,
    load_plugins: &mut PluginLoad,
) -> Result<Option<RunResult>, String> {
    let start = Instant::now();
    let m = Manifest::load(dir)?;
    let run = m
        .run(id)
        .ok_or_else(|| format!("{}: no run `{id}`", Manifest::path(dir).display()))?
        .clone();
    // Held until this function returns (and released by the kernel if the process dies).
    let Some(_running) = lock_run(dir, id)? else {
        return Ok(None);
    };
    let outcome = execute_run(&m, &run, dir, registry, load_plugins);
    let (status, error, values) = match outcome {
        Ok(v) => ("ok", String::new(), v),
        Err(e) => ("failed", e, Vec::new()),
    };
    let r = RunResult {
        id: id.to_string(),
        status: status.into(),
        error,
        seed: run.seed,
        wall_time: start.elapsed().as_secs_f64(),
        peak_memory: peak_rss(),
        values,
    };
    save_result(dir, &r)?;
    Ok(Some(r))
}

fn execute_run(
    m: &Manifest,
    run: &RunSpec,
    dir: &Path,
    registry: &mut Registry,
    load_plugins: &mut PluginLoad,
) -> Result<Vec<Value>, String> {
    let now = grainpipe_core::fsutil::content_hash(&m.pipeline)
        .map_err(|e| format!("{}: {e}", m.pipeline.display()))?;
    if now != m.pipeline_blake3 {
        return Err(format!(
            "{} changed since the sweep was set up; its runs would mix two pipelines \
             (start a new sweep with another --out)",
            m.pipeline.display()
        ));
    }
    let doc = run_doc(m, run, dir).map_err(|e| error_text(&e))?;
    load_plugins(registry, &doc).map_err(|e| error_text(&e))?;
    let collect = m
        .collect
        .iter()
        .map(|c| parse_collect(c))
        .collect::<Result<Vec<_>, _>>()?;
    let plan = plan_run(&doc, registry, &collect, None).map_err(|e| error_text(&e))?;
    let res = engine::execute(
        &doc,
        &plan,
        &RunOptions {
            cache_dir: m.cache_dir.clone(),
        },
        &mut SilentObserver,
    )
    .map_err(|e| error_text(&e))?;
    let mut values = Vec::new();
    for c in &collect {
        values.extend(collect_values(&res, c)?);
    }
    Ok(values)
}

/// Builds the command that runs one run of the sweep in `dir` in a child process.
pub type Launcher<'a> = dyn Fn(&Path, &str) -> Command + Sync + 'a;

/// How the local executor runs.
pub struct LocalOptions {
    /// Runs at once at most.
    pub jobs: usize,
    /// Memory the runs may use together [bytes]; a run starts only when its preflight
    /// estimate fits beside the running ones (one run always may start).
    pub memory_budget: Option<u64>,
    /// Stop starting runs after this many have started (tests simulate an interrupted sweep).
    pub stop_after: Option<usize>,
    pub quiet: bool,
}

struct Shared {
    next: usize,
    started: usize,
    running_memory: u64,
    running: usize,
    done: usize,
    failed: usize,
    /// Runs found computing in another live process (not run here, no result written).
    busy: usize,
}

/// Runs `todo` (indices into the manifest's runs) as child processes; every run ends with a
/// `result.json` (the child's, or one written here when the child died without one).
/// Returns (finished, failed).
pub fn run_local(
    dir: &Path,
    m: &Manifest,
    todo: &[usize],
    opts: &LocalOptions,
    launch: &Launcher,
) -> (usize, usize) {
    let shared = Mutex::new(Shared {
        next: 0,
        started: 0,
        running_memory: 0,
        running: 0,
        done: 0,
        failed: 0,
        busy: 0,
    });
    let freed = Condvar::new();
    let t0 = Instant::now();
    let total = todo.len();
    std::thread::scope(|scope| {
        for _ in 0..opts.jobs.max(1).min(total.max(1)) {
            scope.spawn(|| loop {
                let run = {
                    let mut s = shared.lock().expect("lock");
                    if s.next >= total || opts.stop_after.is_some_and(|k| s.started >= k) {
                        return;
                    }
                    let run = &m.runs[todo[s.next]];
                    // Memory-aware: wait while this run's estimate does not fit beside the
                    // running ones.
                    while let Some(budget) = opts.memory_budget {
                        if s.running == 0 || s.running_memory + run.memory_bytes <= budget {
                            break;
                        }
                        s = freed.wait(s).expect("lock");
                    }
                    if s.next >= total || opts.stop_after.is_some_and(|k| s.started >= k) {
                        return;
                    }
                    let run = &m.runs[todo[s.next]];
                    s.next += 1;
                    s.started += 1;
                    s.running += 1;
                    s.running_memory += run.memory_bytes;
                    run
                };
                let outcome = run_child(dir, run, launch);
                let mut s = shared.lock().expect("lock");
                s.running -= 1;
                s.running_memory -= run.memory_bytes;
                s.done += 1;
                let Some(r) = outcome else {
                    s.busy += 1;
                    if !opts.quiet {
                        eprintln!(
                            "[{}/{total}] {} is running in another process: skipped (its result \
                             appears when that process ends)",
                            s.done, run.id
                        );
                    }
                    drop(s);
                    freed.notify_all();
                    continue;
                };
                if r.status != "ok" {
                    s.failed += 1;
                }
                if !opts.quiet {
                    let elapsed = t0.elapsed().as_secs_f64();
                    let left = total - s.done;
                    // Runs finish at the observed rate (which includes the parallelism).
                    let eta = elapsed / s.done as f64 * left as f64;
                    eprintln!(
                        "[{}/{total}] {} {} {:.1} s {} ({} failed) ETA {}",
                        s.done,
                        r.id,
                        if r.status == "ok" { "ok" } else { "FAILED" },
                        r.wall_time,
                        engine::human_bytes(r.peak_memory),
                        s.failed,
                        human_duration(eta),
                    );
                    if r.status != "ok" {
                        eprintln!("      {}", r.error.lines().next().unwrap_or(""));
                    }
                }
                drop(s);
                freed.notify_all();
            });
        }
    });
    let s = shared.into_inner().expect("lock");
    (s.done, s.failed)
}

/// Runs one child and returns its result; a child that died without writing one gets a failed
/// result naming its exit status and the end of its log. `None` when the run is computing in
/// another live process (its lock is held): nothing is started, its files are left alone.
fn run_child(dir: &Path, run: &RunSpec, launch: &Launcher) -> Option<RunResult> {
    // Checked before touching the run's files; the child takes the lock itself (and exits
    // with EXIT_RUN_BUSY if another process won it in between).
    match lock_run(dir, &run.id) {
        Ok(Some(lock)) => drop(lock),
        Ok(None) => return None,
        Err(_) => {} // the child reports the same error in its result
    }
    let rdir = run_dir(dir, &run.id);
    let _ = std::fs::remove_file(result_path(dir, &run.id));
    let t = Instant::now();
    let log = rdir.join("log.txt");
    let spawned = std::fs::create_dir_all(&rdir)
        .and_then(|_| std::fs::File::create(&log))
        .and_then(|f| {
            let f2 = f.try_clone()?;
            let mut command = launch(dir, &run.id);
            die_with_parent(&mut command);
            command.stdout(f).stderr(f2).status()
        });
    if let Some(r) = load_result(dir, &run.id) {
        return Some(r);
    }
    if matches!(&spawned, Ok(st) if st.code() == Some(i32::from(EXIT_RUN_BUSY))) {
        return None;
    }
    let why = match spawned {
        Ok(st) => format!("the run's process ended with {st} without a result"),
        Err(e) => format!("cannot start the run's process: {e}"),
    };
    let tail: String = std::fs::read_to_string(&log)
        .map(|s| {
            let lines: Vec<&str> = s.lines().collect();
            lines[lines.len().saturating_sub(5)..].join("\n")
        })
        .unwrap_or_default();
    let r = RunResult {
        id: run.id.clone(),
        status: "failed".into(),
        error: if tail.is_empty() {
            why
        } else {
            format!("{why}; log: {tail}")
        },
        seed: run.seed,
        wall_time: t.elapsed().as_secs_f64(),
        peak_memory: 0,
        values: Vec::new(),
    };
    let _ = save_result(dir, &r);
    Some(r)
}

pub fn human_duration(s: f64) -> String {
    if !s.is_finite() {
        return "?".into();
    }
    let s = s.round() as u64;
    match s {
        0..60 => format!("{s}s"),
        60..3600 => format!("{}m{:02}s", s / 60, s % 60),
        _ => format!("{}h{:02}m", s / 3600, (s % 3600) / 60),
    }
}
