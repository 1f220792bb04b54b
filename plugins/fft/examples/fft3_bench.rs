//! Times the 3-D real FFT: `cargo run --release -p grainpipe-fft --example fft3_bench -- 140`
#![allow(clippy::needless_range_loop)]
use grainpipe_fft::fft3::Fft3;
use num_complex::Complex;
use std::time::Instant;
fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .map(|s| s.parse().unwrap())
        .unwrap_or(140);
    let f = Fft3::<f64>::new([n; 3]);
    let input: Vec<f64> = (0..n * n * n).map(|i| (i as f64 * 0.37).sin()).collect();
    let mut spec = vec![Complex::new(0.0, 0.0); f.spectrum_len()];
    let mut out = vec![0.0; n * n * n];
    for _ in 0..2 {
        let t = Instant::now();
        f.forward(&input, &mut spec);
        let a = t.elapsed().as_secs_f64();
        let t = Instant::now();
        f.inverse(&mut spec, &mut out);
        println!(
            "forward {a:.4} s inverse {:.4} s",
            t.elapsed().as_secs_f64()
        );
    }
    let f = Fft3::<f32>::new([n; 3]);
    let input: Vec<f32> = (0..n * n * n).map(|i| (i as f32 * 0.37).sin()).collect();
    let mut spec = vec![Complex::new(0.0f32, 0.0); f.spectrum_len()];
    let mut out = vec![0.0f32; n * n * n];
    for _ in 0..2 {
        let t = Instant::now();
        f.forward(&input, &mut spec);
        let a = t.elapsed().as_secs_f64();
        let t = Instant::now();
        f.inverse(&mut spec, &mut out);
        println!(
            "f32 forward {a:.4} s inverse {:.4} s",
            t.elapsed().as_secs_f64()
        );
    }
}
