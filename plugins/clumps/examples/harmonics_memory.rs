//! Peak memory of `grains.from_harmonics` against its preflight estimate:
//! `cargo run --release -p grainpipe-clumps --example harmonics_memory -- COUNT [rotate]`
//! prints the estimate, the bytes the output holds and the process's peak resident set
//! (VmHWM of /proc/self/status) after one run of the stage on the shipped grains.

use grainpipe_clumps::grains::{FromHarmonics, HarmonicsParams};
use grainpipe_core::stage::{RunContext, SilentReporter};
use grainpipe_core::*;

fn status_kib(key: &str) -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find(|l| l.starts_with(key))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(f64::NAN)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let count: usize = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(4000);
    let rotate = args.get(2).is_some_and(|a| a == "rotate");
    let p = HarmonicsParams {
        count,
        random_rotation: rotate,
        ..HarmonicsParams::default()
    };
    let base = status_kib("VmRSS:") * 1024.0;
    let pf = FromHarmonics.preflight(&p, &InputMetas::new()).unwrap();
    let est = pf.memory_bytes as f64;
    let t = std::time::Instant::now();
    let out = FromHarmonics
        .run(
            &p,
            &pf.plan,
            &Inputs::new(),
            &RunContext::new(1, &SilentReporter),
        )
        .unwrap();
    let secs = t.elapsed().as_secs_f64();
    let Artifact::Collection(c) = &out["grains"] else {
        panic!("no collection")
    };
    let labels: usize = c
        .items
        .iter()
        .map(|(_, a)| a.as_phase_image().map_or(0, |i| i.labels.len()))
        .sum();
    let peak = status_kib("VmHWM:") * 1024.0;
    let gib = |b: f64| b / (1u64 << 30) as f64;
    println!(
        "count {count} rotate {rotate}: estimate {:.3} GiB, labels held {:.3} GiB, peak RSS {:.3} \
         GiB (above start {:.3} GiB), estimate / (peak - start) = {:.2}, {secs:.1} s, {} threads",
        gib(est),
        gib(labels as f64),
        gib(peak),
        gib(peak - base),
        est / (peak - base),
        rayon::current_num_threads()
    );
}
