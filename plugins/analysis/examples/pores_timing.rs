//! Wall time of the pore-space kernels on an n^3 periodic Boolean model (overlapping balls
//! of radius `r` voxels at pore fraction about 0.5).
//! Run: cargo run --release -p grainpipe-analysis --example pores_timing -- 200 8

use grainpipe_analysis::chords::chord_counts;
use grainpipe_analysis::thickness::local_thickness;
use grainpipe_analysis::tortuosity::tortuosity;
use grainpipe_analysis::two_point::pair_counts;
use std::time::Instant;

/// Small deterministic generator (64-bit LCG, top 53 bits).
fn lcg(s: &mut u64) -> f64 {
    *s = s
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (*s >> 11) as f64 / (1u64 << 53) as f64
}

fn main() {
    let mut args = std::env::args().skip(1);
    let n: usize = args.next().and_then(|a| a.parse().ok()).unwrap_or(128);
    let r: f64 = args.next().and_then(|a| a.parse().ok()).unwrap_or(6.0);
    let count = (std::f64::consts::LN_2 * (n as f64).powi(3)
        / (4.0 / 3.0 * std::f64::consts::PI * r.powi(3))) as usize;
    let mut pore = vec![true; n * n * n];
    let mut seed = 1u64;
    let k = r.ceil() as i64 + 1;
    for _ in 0..count {
        let c = [lcg(&mut seed), lcg(&mut seed), lcg(&mut seed)].map(|v| v * n as f64);
        let b = c.map(|v| v.floor() as i64);
        for dz in -k..=k {
            for dy in -k..=k {
                for dx in -k..=k {
                    let v = [b[0] + dx, b[1] + dy, b[2] + dz];
                    let s: f64 = (0..3).map(|a| (v[a] as f64 + 0.5 - c[a]).powi(2)).sum();
                    if s <= r * r {
                        let w = v.map(|t| t.rem_euclid(n as i64) as usize);
                        pore[w[0] + n * (w[1] + n * w[2])] = false;
                    }
                }
            }
        }
    }
    let phi = pore.iter().filter(|&&p| p).count() as f64 / pore.len() as f64;
    println!(
        "{n}^3 voxels, {count} balls of {r} voxels, pore fraction {phi:.3}, {} threads",
        rayon::current_num_threads()
    );
    let d = [n; 3];
    let t0 = Instant::now();
    let t = local_thickness(&pore, d, [1.0; 3], [true; 3]);
    let mean = t.iter().filter(|v| **v > 0.0).sum::<f64>() / (phi * pore.len() as f64);
    println!(
        "local_thickness: {:.2} s (mean pore thickness {mean:.2} voxels)",
        t0.elapsed().as_secs_f64()
    );
    let t0 = Instant::now();
    for a in 0..3 {
        pair_counts(&pore, d, a, true, n / 2);
    }
    println!("two_point x, y, z: {:.2} s", t0.elapsed().as_secs_f64());
    let t0 = Instant::now();
    for a in 0..3 {
        chord_counts(&pore, d, a, true);
    }
    println!("chords x, y, z: {:.2} s", t0.elapsed().as_secs_f64());
    let t0 = Instant::now();
    let g = tortuosity(&pore, d, [1.0; 3], [true; 3], 2);
    println!(
        "tortuosity z: {:.2} s (tau {:.4})",
        t0.elapsed().as_secs_f64(),
        g.mean
    );
}
