//! Benchmark of grainpipe-clumps (BENCHMARKS.md#grains-and-clumps).
//!
//! `cargo run --release -p grainpipe-clumps --example clumps_bench [-- quick]`
//!
//! 1. Seconds per real CT grain (data/sand-grains rescaled to D50 = 140 um, 4 um voxels as
//!    in the paper, and 2 um) at alpha = 0.9, one thread; spheres per grain.
//! 2. Lazy-heap gain on a 100-voxel cube at alpha = 0.9 (paper: x67.5), and the gain of the
//!    medial-surface restriction (paper: about x3).
//! 3. A library of 2,000 synthetic grains through the stages (grains.synthetic ->
//!    clumps.garcia -> clumps.library) on all cores.

use grainpipe_clumps::clumps::{clump_grain, Garcia, Library, LibraryParams};
use grainpipe_clumps::garcia::{garcia, GarciaOptions};
use grainpipe_clumps::grains::{
    collection_to_grains, FromHarmonics, HarmonicsParams, Synthetic, SyntheticParams,
};
use grainpipe_core::stage::{RunContext, SilentReporter};
use grainpipe_core::units::Q;
use grainpipe_core::{Inputs, TypedStage};
use std::sync::Arc;
use std::time::Instant;

/// CPU seconds (user + system) used by this process so far, from /proc/self/stat.
fn cpu_seconds() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let f: Vec<&str> = s
        .rsplit(')')
        .next()
        .unwrap_or("")
        .split_whitespace()
        .collect();
    let tick = 100.0; // USER_HZ on Linux
    let get = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // Fields 14 and 15 (utime, stime) are at 11 and 12 after the `)`.
    (get(11) + get(12)) / tick
}

fn main() {
    let quick = std::env::args().any(|a| a == "quick");
    println!("threads: {}", rayon::current_num_threads());
    let ctx = RunContext::new(42, &SilentReporter);

    // 1. Real grains.
    for voxel in [4e-6, 2e-6] {
        let p = HarmonicsParams {
            voxel_size: Q::new(voxel),
            ..HarmonicsParams::default()
        };
        let files = FromHarmonics
            .preflight(&p, &Default::default())
            .unwrap()
            .plan;
        let out = FromHarmonics.run(&p, &files, &Inputs::new(), &ctx).unwrap();
        let grains = collection_to_grains(out["grains"].as_collection().unwrap()).unwrap();
        let mut times = Vec::new();
        let mut spheres = Vec::new();
        let mut voxels = Vec::new();
        let mut cov = Vec::new();
        let mut inertia = Vec::new();
        for g in &grains {
            let t = Instant::now();
            let c = clump_grain(g, &GarciaOptions::default(), 2).unwrap();
            times.push(t.elapsed().as_secs_f64());
            spheres.push(c.clump.spheres.len() as f64);
            voxels.push(g.voxels() as f64);
            cov.push(c.result.coverage());
            inertia.push(c.metrics.inertia_error());
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let max = |v: &[f64]| v.iter().copied().fold(f64::MIN, f64::max);
        let min = |v: &[f64]| v.iter().copied().fold(f64::MAX, f64::min);
        println!(
            "real grains, voxel {:.0} um: {} grains, voxels/grain mean {:.0} (max {:.0}); \
             seconds/grain mean {:.4} max {:.4} (Algorithm 1 + volume/inertia, 1 thread); \
             spheres/grain mean {:.1} min {} max {}; coverage min {:.4}; inertia error mean {:.3}",
            voxel * 1e6,
            grains.len(),
            mean(&voxels),
            max(&voxels),
            mean(&times),
            max(&times),
            mean(&spheres),
            min(&spheres),
            max(&spheres),
            min(&cov),
            mean(&inertia)
        );
    }

    // 2. Lazy-heap gain on a cube of side 100 voxels.
    let side = if quick { 40 } else { 100 };
    let n = side + 2;
    let dims = [n, n, n];
    let mut mask = vec![false; n * n * n];
    for z in 1..=side {
        for y in 1..=side {
            for x in 1..=side {
                mask[x + n * (y + n * z)] = true;
            }
        }
    }
    let run = |medial: bool, lazy: bool| {
        let o = GarciaOptions {
            alpha: 0.9,
            medial,
            lazy,
            max_spheres: 100_000,
            strict: false,
        };
        let t = Instant::now();
        let r = garcia(&mask, dims, &o).unwrap();
        (t.elapsed().as_secs_f64(), r)
    };
    let (t_lazy, r_lazy) = run(true, true);
    let (t_naive, r_naive) = run(true, false);
    assert_eq!(r_lazy.spheres, r_naive.spheres);
    let (t_all, r_all) = run(false, true);
    println!(
        "cube {side}^3, alpha 0.9: {} spheres, coverage {:.4}; medial candidates {} of {} voxels; \
         lazy {:.3} s ({} evaluations), naive {:.3} s ({} evaluations): lazy-heap gain x{:.1} \
         (time), x{:.1} (evaluations); all-voxel candidates (lazy) {:.3} s ({} spheres): \
         medial-surface gain x{:.2}",
        r_lazy.spheres.len(),
        r_lazy.coverage(),
        r_lazy.candidates,
        side * side * side,
        t_lazy,
        r_lazy.evaluations,
        t_naive,
        r_naive.evaluations,
        t_naive / t_lazy,
        r_naive.evaluations as f64 / r_lazy.evaluations as f64,
        t_all,
        r_all.spheres.len(),
        t_all / t_lazy
    );

    // 3. A library of 2,000 grains through the stages.
    let count = if quick { 200 } else { 2000 };
    let c0 = cpu_seconds();
    let t0 = Instant::now();
    let sp = SyntheticParams {
        count,
        ..SyntheticParams::default()
    };
    let law = grainpipe_clumps::grains::sampled_law(&sp).unwrap().0;
    let g = Synthetic.run(&sp, &law, &Inputs::new(), &ctx).unwrap();
    let t1 = Instant::now();
    let mut inp = Inputs::new();
    inp.insert("grains".into(), Arc::new(g["grains"].clone()));
    let c = Garcia.run(&Default::default(), &(), &inp, &ctx).unwrap();
    let t2 = Instant::now();
    let mut inp2 = Inputs::new();
    inp2.insert("library".into(), Arc::new(c["library"].clone()));
    let l = Library
        .run(&LibraryParams::default(), &(), &inp2, &ctx)
        .unwrap();
    let t3 = Instant::now();
    let cpu = cpu_seconds() - c0;
    let lib = c["library"].as_clump_library().unwrap();
    let spheres: usize = lib.clumps.iter().map(|c| c.spheres.len()).sum();
    println!(
        "library of {count} synthetic grains (D50 140 um, 4 um voxels): grains.synthetic {:.2} s, \
         clumps.garcia {:.2} s ({:.1} spheres/grain), clumps.library {:.3} s ({} clumps); total {:.2} s wall, {:.1} CPU s \
         (= {:.1} s on 2 idle cores)",
        (t1 - t0).as_secs_f64(),
        (t2 - t1).as_secs_f64(),
        spheres as f64 / count as f64,
        (t3 - t2).as_secs_f64(),
        l["library"].as_clump_library().unwrap().clumps.len(),
        (t3 - t0).as_secs_f64(),
        cpu,
        cpu / 2.0
    );
}
