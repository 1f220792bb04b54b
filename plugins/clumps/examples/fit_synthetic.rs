//! Fits the default `grains.synthetic` roughness spectrum to the real grains of
//! data/sand-grains and prints the shape statistics of both sets.
//!
//! `cargo run --release -p grainpipe-clumps --example fit_synthetic`
//!
//! Fit: for each real grain, the relative angular power spectrum of its radius function,
//! `C_n = (|a_n0|^2 + 2 sum_{m>0} |a_nm|^2) / (2n+1) / r0^2` with `r0 = a_00 / sqrt(4 pi)`
//! (the spectrum of ln r to first order), averaged over grains; then a least-squares line
//! `ln C_n = ln K - beta ln n` over n = 3..30, and the roughness
//! `sigma^2 = sum_n (2n+1) K n^-beta / (4 pi)`.

use grainpipe_clumps::grains::{grain_from_shape, GrainMask};
use grainpipe_clumps::grains::{stats_tables, synthetic_grains, SyntheticParams};
use grainpipe_clumps::shape::{Harmonics, StarShape};
use std::f64::consts::PI;

fn main() {
    let dir = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../data/sand-grains/MA107-6-fine"
    );
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    let nmin = 3;
    let nmax = 30;
    let mut mean = vec![0.0; nmax + 1];
    let mut real: Vec<GrainMask> = Vec::new();
    for f in &files {
        let h = Harmonics::read(f).unwrap();
        let r0 = h.coef[0].0 / (4.0 * PI).sqrt();
        for (n, m_n) in mean.iter_mut().enumerate().take(nmax + 1).skip(1) {
            let mut s = 0.0;
            for m in 0..=n {
                let (re, im) = h.coef[n * (n + 1) / 2 + m];
                s += if m == 0 { 1.0 } else { 2.0 } * (re * re + im * im);
            }
            *m_n += s / (2 * n + 1) as f64 / (r0 * r0) / files.len() as f64;
        }
        let t = h.tabulate(120, 240);
        let shape = StarShape {
            table: t,
            transform: nalgebra::Matrix3::identity() * 1e-3 * 0.140 / 1.54,
        };
        real.push(
            grain_from_shape(&shape, 4e-6, &f.file_name().unwrap().to_string_lossy()).unwrap(),
        );
    }
    let (mut sx, mut sy, mut sxx, mut sxy, mut k) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (n, c) in mean.iter().enumerate().take(nmax + 1).skip(nmin) {
        let (x, y) = ((n as f64).ln(), c.ln());
        sx += x;
        sy += y;
        sxx += x * x;
        sxy += x * y;
        k += 1.0;
    }
    let slope = (k * sxy - sx * sy) / (k * sxx - sx * sx);
    let icpt = (sy - slope * sx) / k;
    let beta = -slope;
    let sigma2: f64 = (nmin..=nmax)
        .map(|n| (2 * n + 1) as f64 * icpt.exp() * (n as f64).powf(-beta) / (4.0 * PI))
        .sum();
    println!("mean relative spectrum C_n (n = 1..8): {:?}", &mean[1..9]);
    println!(
        "fit n = {nmin}..{nmax}: beta = {beta:.3}, roughness sigma = {:.4}",
        sigma2.sqrt()
    );
    let describe = |name: &str, g: &[GrainMask]| {
        let (t, _) = stats_tables(g);
        for c in ["elongation", "flatness", "sphericity"] {
            let v = t.f64_column(c).unwrap();
            let m = v.iter().sum::<f64>() / v.len() as f64;
            let sd = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt();
            println!("{name}: {c} = {m:.3} +- {sd:.3}");
        }
        let l = t.f64_column("length").unwrap();
        let th = t.f64_column("thickness").unwrap();
        let w = t.f64_column("width").unwrap();
        let lt: f64 = l.iter().zip(th).map(|(a, b)| a / b).sum::<f64>() / l.len() as f64;
        let wt: f64 = w.iter().zip(th).map(|(a, b)| a / b).sum::<f64>() / l.len() as f64;
        println!("{name}: mean L/T = {lt:.3}, W/T = {wt:.3}");
    };
    describe("real (30 grains, d_eq ~ 140 um, 4 um voxels)", &real);
    // Optional overrides: `-- <roughness> <spectral_exponent>` to explore other settings.
    let args: Vec<f64> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let mut p = SyntheticParams {
        count: 200,
        ..SyntheticParams::default()
    };
    if args.len() == 2 {
        p.roughness = args[0];
        p.spectral_exponent = args[1];
    }
    let syn = synthetic_grains(&p, 1);
    let name = format!(
        "synthetic roughness {} beta {} (200 grains)",
        p.roughness, p.spectral_exponent
    );
    describe(&name, &syn);
}
