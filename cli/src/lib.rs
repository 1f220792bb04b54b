//! The library behind the `pipe` binary: the registry of built-in stages, the stage
//! listing and descriptions, and the terminal observer. Kept apart from `main.rs` so the
//! workspace tests can drive pipelines exactly as the command does.

pub mod describe;
pub mod observe;

use grainpipe_core::Registry;

/// Every stage and exporter that ships with grainpipe.
pub fn builtin_registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_geometry::register(&mut r);
    r
}

/// Memory the system can still give, from /proc/meminfo (Linux); `None` elsewhere.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}
