//! Wall time of `analysis.phases` on an n^3 three-phase image (balls of label 1 on a
//! periodic lattice, label 2 in a slab, label 0 elsewhere).
//! Run: cargo run --release -p grainpipe-analysis --example phases_timing -- 280

use grainpipe_analysis::phases::analyse;
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{Grid, PhaseImage, RunContext};
use std::time::Instant;

fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(140);
    let mut labels = vec![0u8; n * n * n];
    let cell = 20.0;
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let p = [x, y, z].map(|v| (v as f64 + 0.5) % cell - cell / 2.0);
                let r2 = p.iter().map(|v| v * v).sum::<f64>();
                labels[x + n * (y + n * z)] = if r2 < 8.0 * 8.0 {
                    1
                } else if z % 50 < 3 {
                    2
                } else {
                    0
                };
            }
        }
    }
    let image = PhaseImage {
        grid: Grid {
            dims: [n; 3],
            spacing: [4e-6; 3],
            origin: [0.0; 3],
            periodic: [true; 3],
        },
        labels,
        phases: vec![],
    };
    let t = Instant::now();
    let table = analyse(&image, &[], &RunContext::new(0, &SilentReporter)).unwrap();
    println!(
        "{n}^3 = {} voxels, {} threads: {:.2} s, {} rows",
        n * n * n,
        rayon::current_num_threads(),
        t.elapsed().as_secs_f64(),
        table.rows()
    );
}
