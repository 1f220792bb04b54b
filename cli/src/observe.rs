//! Terminal feedback while a pipeline runs: progress bars for steps longer than a second,
//! messages, Ctrl-C cancellation, and the end-of-run table of wall time and peak memory.

use grainpipe_core::engine::{Observer, PlannedStep, StepStats};
use grainpipe_core::stage::{Level, Reporter};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The system allocator, counting live and peak bytes so each step's peak memory can be
/// reported. Install with `#[global_allocator]` in the binary.
pub struct CountingAllocator;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size > layout.size() {
                let now = LIVE.fetch_add(new_size - layout.size(), Ordering::Relaxed) + new_size
                    - layout.size();
                PEAK.fetch_max(now, Ordering::Relaxed);
            } else {
                LIVE.fetch_sub(layout.size() - new_size, Ordering::Relaxed);
            }
        }
        p
    }
}

/// Starts a new peak-memory window at the current live size.
fn reset_peak() -> usize {
    let live = LIVE.load(Ordering::Relaxed);
    PEAK.store(live, Ordering::Relaxed);
    live
}

/// Progress for one step: the bar appears only once the step has run for a second.
struct StepReporter {
    bar: ProgressBar,
    start: Instant,
    quiet: bool,
    cancel: Arc<AtomicBool>,
    /// The "running STEP (stage)" line, when it is held back until the step shows it is
    /// computing (see [`TerminalObserver::step_started`]).
    announce: Arc<Mutex<Option<String>>>,
    /// The furthest fraction shown so far, as (done, total).
    shown: Mutex<(u64, u64)>,
    /// The step's id and the run's warnings (step, text), for the run record.
    step: String,
    warnings: Arc<Mutex<Vec<(String, String)>>>,
}

impl StepReporter {
    fn announce(&self) {
        let line = self
            .announce
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take();
        if let Some(line) = line {
            self.bar.suspend(|| eprintln!("{line}"));
        }
    }
}

/// The position to show for a report of `done` of `total` after having shown `shown`: the
/// report itself unless it is behind what was shown; a bar never moves back, even when a
/// stage re-reports with another total.
fn forward(shown: (u64, u64), done: u64, total: u64) -> (u64, u64) {
    let (sd, st) = shown;
    if total == 0 || st == 0 {
        return if total == st {
            (done.max(sd), total)
        } else {
            (done, total)
        };
    }
    // Compare done/total with sd/st without rounding: done * st against sd * total.
    if (done as u128) * (st as u128) >= (sd as u128) * (total as u128) {
        (done, total)
    } else {
        let at_least = ((sd as u128) * (total as u128)).div_ceil(st as u128);
        (at_least.min(total as u128) as u64, total)
    }
}

impl Reporter for StepReporter {
    fn progress(&self, done: u64, total: u64) {
        if self.quiet {
            return;
        }
        self.announce();
        let (done, total) = {
            let mut shown = self.shown.lock().unwrap_or_else(|p| p.into_inner());
            *shown = forward(*shown, done, total);
            *shown
        };
        if self.bar.is_hidden() && self.start.elapsed() > Duration::from_secs(1) {
            self.bar.set_draw_target(ProgressDrawTarget::stderr());
        }
        if total > 0 && self.bar.length() != Some(total) {
            self.bar.set_length(total);
        }
        self.bar.set_position(done);
    }
    fn message(&self, level: Level, text: &str) {
        match level {
            Level::Warn => {
                self.announce();
                self.warnings
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .push((self.step.clone(), text.to_string()));
                self.bar.suspend(|| eprintln!("warning: {text}"))
            }
            Level::Info if !self.quiet => {
                self.announce();
                self.bar.suspend(|| eprintln!("  {text}"))
            }
            Level::Info => {}
        }
    }
    fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
    }
    fn detail(&self, text: &str) {
        if !self.quiet {
            self.bar.set_message(text.to_string());
        }
    }
}

impl Drop for StepReporter {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}

/// One row of the end-of-run table.
pub struct Row {
    pub step: String,
    pub stage: String,
    pub wall: Duration,
    pub peak_bytes: usize,
    /// Peak live heap of the whole process during the step (baseline included).
    pub peak_heap_bytes: usize,
    /// The step's preflight memory estimate (exports of its outputs included) [bytes].
    pub estimate_bytes: u64,
    pub cached: bool,
}

/// Observer for the terminal.
pub struct TerminalObserver {
    pub quiet: bool,
    pub cancel: Arc<AtomicBool>,
    pub rows: Vec<Row>,
    base: usize,
    written: Vec<std::path::PathBuf>,
    /// The run's cache directory, to tell a step that will be served from the cache.
    cache_dir: Option<std::path::PathBuf>,
    /// The held-back "running" line of the current step, shared with its reporter.
    announce: Arc<Mutex<Option<String>>>,
    /// Every warning of the run, as (step, text), shared with the reporters.
    warnings: Arc<Mutex<Vec<(String, String)>>>,
}

impl TerminalObserver {
    pub fn new(quiet: bool, cancel: Arc<AtomicBool>) -> Self {
        TerminalObserver {
            quiet,
            cancel,
            rows: Vec::new(),
            base: 0,
            written: Vec::new(),
            cache_dir: None,
            announce: Arc::new(Mutex::new(None)),
            warnings: Arc::new(Mutex::new(Vec::new())),
        }
    }

    /// The warnings the steps gave so far, as (step, text), in order.
    pub fn warnings(&self) -> Vec<(String, String)> {
        self.warnings
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// The cache directory the run uses (`RunOptions::cache_dir`): a step with an entry
    /// there prints "cached STEP" instead of "running STEP".
    pub fn with_cache_dir(mut self, dir: Option<std::path::PathBuf>) -> Self {
        self.cache_dir = dir;
        self
    }

    /// The end-of-run table.
    pub fn table(&self) -> String {
        let mut s = format!(
            "{:16} {:22} {:>10} {:>12}  {}\n",
            "step", "stage", "wall [s]", "peak mem", ""
        );
        for r in &self.rows {
            s.push_str(&format!(
                "{:16} {:22} {:>10.3} {:>12}  {}\n",
                r.step,
                r.stage,
                r.wall.as_secs_f64(),
                grainpipe_core::engine::human_bytes(r.peak_bytes as u64),
                if r.cached { "cached" } else { "" }
            ));
        }
        s
    }
}

impl TerminalObserver {
    /// The steps run so far, for the run record (`run.json`). Memory is only known when the
    /// binary installed [`CountingAllocator`]; otherwise the counters stay at zero and the
    /// record says "not measured".
    pub fn step_records(&self) -> Vec<grainpipe_report::StepRecord> {
        let measured = LIVE.load(Ordering::Relaxed) > 0;
        self.rows
            .iter()
            .map(|r| grainpipe_report::StepRecord {
                step: r.step.clone(),
                stage: r.stage.clone(),
                wall_s: r.wall.as_secs_f64(),
                from_cache: r.cached,
                peak_bytes: measured.then_some(r.peak_bytes as u64),
                peak_heap_bytes: measured.then_some(r.peak_heap_bytes as u64),
                estimate_bytes: Some(r.estimate_bytes),
            })
            .collect()
    }

    /// Paths written so far.
    pub fn written(&self) -> &[std::path::PathBuf] {
        &self.written
    }
}

impl Observer for TerminalObserver {
    fn step_started(&mut self, step: &PlannedStep) -> Box<dyn Reporter> {
        self.base = reset_peak();
        let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::hidden());
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:>16} [{bar:30}] {percent:>3}% {elapsed_precise} eta {eta} {msg}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_prefix(step.id.clone());
        let line = format!("running {} ({})", step.id, step.stage.info().id);
        // The engine tells whether a step came from the cache only once it has finished.
        // A step with a cache entry holds its "running" line back: it prints "cached" when
        // served, or "running" as soon as it shows it computes (a progress report, or the
        // warning that the entry was refused).
        let held = if self.quiet {
            None
        } else if self
            .cache_dir
            .as_deref()
            .is_some_and(|d| has_cache_entry(d, &step.cache_key))
        {
            Some(line)
        } else {
            eprintln!("{line}");
            None
        };
        *self.announce.lock().unwrap_or_else(|p| p.into_inner()) = held;
        Box::new(StepReporter {
            bar,
            start: Instant::now(),
            quiet: self.quiet,
            cancel: self.cancel.clone(),
            announce: self.announce.clone(),
            shown: Mutex::new((0, 0)),
            step: step.id.clone(),
            warnings: self.warnings.clone(),
        })
    }

    fn step_finished(&mut self, step: &PlannedStep, stats: &StepStats) {
        let heap = PEAK.load(Ordering::Relaxed);
        self.rows.push(Row {
            step: step.id.clone(),
            stage: step.stage.info().id.to_string(),
            wall: stats.wall,
            peak_bytes: heap.saturating_sub(self.base),
            peak_heap_bytes: heap,
            estimate_bytes: step.preflight.memory_bytes,
            cached: stats.from_cache,
        });
        let held = self
            .announce
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take();
        if let Some(line) = held {
            if stats.from_cache {
                eprintln!("cached {} ({})", step.id, step.stage.info().id);
            } else {
                eprintln!("{line}");
            }
        }
    }

    fn exported(&mut self, path: &Path) {
        self.written.push(path.to_path_buf());
        if !self.quiet {
            eprintln!("  wrote {}", path.display());
        }
    }
}

/// Whether the cache holds an entry for `key` (a stale or damaged entry is refused by the
/// engine, which then warns: the held-back line prints with the warning).
fn has_cache_entry(dir: &Path, key: &str) -> bool {
    grainpipe_core::cache::path(dir, key).is_file()
}

#[cfg(test)]
mod tests {
    use super::forward;

    #[test]
    fn bar_never_moves_back() {
        // A plain advance is shown as reported.
        assert_eq!(forward((0, 0), 3, 10), (3, 10));
        assert_eq!(forward((3, 10), 7, 10), (7, 10));
        // A report behind the shown one keeps the shown position.
        assert_eq!(forward((7, 10), 2, 10), (7, 10));
        // A new total keeps the shown fraction: 700/1000 shown, 1/4 reported -> 3 of 4
        // (the smallest position not below 70 %).
        assert_eq!(forward((700, 1000), 1, 4), (3, 4));
        // Ahead with a new total: shown as reported.
        assert_eq!(forward((1, 4), 900, 1000), (900, 1000));
        // Unknown totals: counts only go up.
        assert_eq!(forward((5, 0), 2, 0), (5, 0));
    }
}
