//! Times the 3-D real FFT and the parts of one CG iteration of the staggered elastic problem:
//! `cargo run --release -p grainpipe-fft --example fft3_bench -- 140 [repeats]`
//! Each figure is the fastest of `repeats` runs (default 5): on a shared machine the minimum
//! is the figure least disturbed by other processes.
#![allow(clippy::needless_range_loop)]
use grainpipe_fft::fft3::Fft3;
use grainpipe_fft::kernel::elastic::Elastic;
use grainpipe_fft::kernel::solver::{dot, CellProblem};
use grainpipe_fft::kernel::{Iso, Scheme};
use grainpipe_fft::real::Real;
use num_complex::Complex;
use std::time::Instant;

/// CPU time (user + system, all threads) of this process [s], from /proc/self/stat (clock
/// ticks of 10 ms).
fn cpu_seconds() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = s.rsplit(')').next().unwrap_or("");
    let f: Vec<f64> = after
        .split_whitespace()
        .map(|w| w.parse().unwrap_or(0.0))
        .collect();
    // Fields 14 and 15 of stat(5); `after` starts at field 3.
    (f.get(11).unwrap_or(&0.0) + f.get(12).unwrap_or(&0.0)) / 100.0
}

/// Fastest wall time of `repeats` runs, and the mean CPU time per run (with
/// RAYON_NUM_THREADS=1 the CPU time is the work itself, less disturbed by other processes
/// than the wall time; with more threads it includes rayon's spinning).
fn best(repeats: usize, mut f: impl FnMut()) -> (f64, f64) {
    let c = cpu_seconds();
    let wall = (0..repeats)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min);
    (wall, (cpu_seconds() - c) / repeats as f64)
}

fn ffts<T: Real>(n: usize, repeats: usize, name: &str) {
    let f = Fft3::<T>::new([n; 3]);
    let len = n * n * n;
    let input: Vec<T> = (0..len).map(|i| T::of((i as f64 * 0.37).sin())).collect();
    let zero = Complex::new(T::zero(), T::zero());
    let mut spec = vec![zero; 3 * f.spectrum_len()];
    let mut out = vec![T::zero(); len];
    let fw = best(repeats, || f.forward(&input, &mut spec[..f.spectrum_len()]));
    let inv = best(repeats, || {
        f.inverse(&mut spec[..f.spectrum_len()], &mut out);
    });
    let mut o3 = vec![T::zero(); 3 * len];
    let filt = best(repeats, || {
        let (a, rest) = o3.split_at_mut(len);
        let (b, c) = rest.split_at_mut(len);
        f.filter([&input, &input, &input], [a, b, c], &mut spec, |_, _, _| {});
    });
    println!(
        "{name} (wall min / cpu mean): forward {:.4} / {:.4} s, inverse {:.4} / {:.4} s; \
         filter of 3 fields (3 forward + 3 inverse) {:.4} / {:.4} s",
        fw.0, fw.1, inv.0, inv.1, filt.0, filt.1
    );
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let n: usize = a.get(1).map(|s| s.parse().unwrap()).unwrap_or(140);
    let repeats: usize = a.get(2).map(|s| s.parse().unwrap()).unwrap_or(5);
    ffts::<f64>(n, repeats, "f64");
    ffts::<f32>(n, repeats, "f32");
    parts::<f64>(n, repeats, "f64");
    parts::<f32>(n, repeats, "f32");
}

/// Times the parts of one staggered CG iteration in precision `T`.
fn parts<T: Real>(n: usize, repeats: usize, name: &str) {
    // A three-phase image of pseudo-random labels; the cost of one CG iteration does not
    // depend on the microstructure.
    let len = n * n * n;
    let labels: Vec<u8> = (0..len)
        .map(|i| ((i as u64).wrapping_mul(2654435761) >> 7) as u8 % 3)
        .collect();
    let mut mats = [Iso::ZERO; 256];
    mats[1] = Iso::from_e_nu(66.9e9, 0.25);
    mats[2] = Iso::from_e_nu(43e9, 0.17);
    let mut p = Elastic::<T>::new(
        [n; 3],
        [4e-6; 3],
        labels,
        mats,
        Scheme::Staggered,
        Iso::from_e_nu(55e9, 0.2),
    );
    let u: Vec<T> = (0..3 * len)
        .map(|i| T::of((i as f64 * 0.11).sin()))
        .collect();
    let mut q = vec![T::zero(); 3 * len];
    let mut z = vec![T::zero(); 3 * len];
    let apply = best(repeats, || p.apply(&u, None, &mut q));
    let pre = best(repeats, || p.precondition(&u, &mut z));
    let mut r = u.clone();
    let fused = best(repeats, || {
        p.precondition_dot(Some((0.0, &q)), &mut r, &mut z);
    });
    let mut s = 0.0;
    let d = best(repeats, || s += dot(&u, &q));
    println!(
        "staggered {name}, parts of one CG iteration (wall min / cpu mean): apply {:.4} / {:.4} \
         s, precondition {:.4} / {:.4} s, precondition with r -= a q and r . z {:.4} / {:.4} s, \
         one dot product {:.4} / {:.4} s ({s:.1e})",
        apply.0, apply.1, pre.0, pre.1, fused.0, fused.1, d.0, d.1
    );
}
