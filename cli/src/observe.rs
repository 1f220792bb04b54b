//! Terminal feedback while a pipeline runs: progress bars for steps longer than a second,
//! messages, Ctrl-C cancellation, and the end-of-run table of wall time and peak memory.

use grainpipe_core::engine::{Observer, PlannedStep, StepStats};
use grainpipe_core::stage::{Level, Reporter};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
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
}

impl Reporter for StepReporter {
    fn progress(&self, done: u64, total: u64) {
        if self.quiet {
            return;
        }
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
            Level::Warn => self.bar.suspend(|| eprintln!("warning: {text}")),
            Level::Info if !self.quiet => self.bar.suspend(|| eprintln!("  {text}")),
            Level::Info => {}
        }
    }
    fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
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
    pub cached: bool,
}

/// Observer for the terminal.
pub struct TerminalObserver {
    pub quiet: bool,
    pub cancel: Arc<AtomicBool>,
    pub rows: Vec<Row>,
    base: usize,
    written: Vec<std::path::PathBuf>,
}

impl TerminalObserver {
    pub fn new(quiet: bool, cancel: Arc<AtomicBool>) -> Self {
        TerminalObserver {
            quiet,
            cancel,
            rows: Vec::new(),
            base: 0,
            written: Vec::new(),
        }
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
                "{prefix:>16} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_prefix(step.id.clone());
        if !self.quiet {
            eprintln!("running {} ({})", step.id, step.stage.info().id);
        }
        Box::new(StepReporter {
            bar,
            start: Instant::now(),
            quiet: self.quiet,
            cancel: self.cancel.clone(),
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
            cached: stats.from_cache,
        });
    }

    fn exported(&mut self, path: &Path) {
        self.written.push(path.to_path_buf());
        if !self.quiet {
            eprintln!("  wrote {}", path.display());
        }
    }
}
