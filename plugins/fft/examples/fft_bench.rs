//! Benchmark / exploration driver (not a test):
//! `cargo run --release -p grainpipe-fft --example fft_bench -- <n> <discretization> <solver> <double|single> <image> [cases] [tolerance]`
//! image: `sand` (seeded random grains ~50 % + binder shell ~2-3 %, rest pore), `sphere`
//! (simple-cubic spherical pore of porosity 0.2 in a solid E = 1, nu = 0.3), `laminate`.
//! Prints iterations, seconds per iteration, the stiffness and the engineering constants.
#![allow(clippy::needless_range_loop)]

mod images;

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{Grid, Phase, PhaseImage, RunContext};
use grainpipe_fft::common::{Discretization, Material, Precision, Solver};
use grainpipe_fft::elasticity::{solve_all, ElasticityParams, LoadCase};
use grainpipe_fft::kernel::Iso;
use images::sphere_pore;
use indexmap::IndexMap;
use std::time::Instant;

fn lcg(s: &mut u64) -> f64 {
    *s = s
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (*s >> 11) as f64 / (1u64 << 53) as f64
}

/// Random overlapping grains (periodic) at ~50 % and a binder shell around them.
pub fn sand(n: usize) -> PhaseImage {
    let mut seed = 12345u64;
    let r = n as f64 / 10.0;
    let mut centres = vec![];
    let vol = (n * n * n) as f64;
    let target = 0.69 * vol; // overlapping spheres: 1 - exp(-phi) = 0.5
    let mut placed = 0.0;
    while placed < target {
        centres.push([lcg(&mut seed), lcg(&mut seed), lcg(&mut seed)].map(|v| v * n as f64));
        placed += 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
    }
    let mut labels = vec![0u8; n * n * n];
    let shell = 1.1 * r;
    for c in &centres {
        let lo = |a: usize| (c[a] - shell).floor() as i64;
        let hi = |a: usize| (c[a] + shell).ceil() as i64;
        for z in lo(2)..=hi(2) {
            for y in lo(1)..=hi(1) {
                for x in lo(0)..=hi(0) {
                    let d2 = [x, y, z]
                        .iter()
                        .zip(c)
                        .map(|(&p, &q)| (p as f64 + 0.5 - q).powi(2))
                        .sum::<f64>();
                    let w = |p: i64| p.rem_euclid(n as i64) as usize;
                    let i = w(x) + n * (w(y) + n * w(z));
                    if d2 < r * r {
                        labels[i] = 1;
                    } else if d2 < shell * shell && labels[i] == 0 {
                        labels[i] = 2;
                    }
                }
            }
        }
    }
    PhaseImage {
        grid: Grid {
            dims: [n; 3],
            spacing: [4e-6; 3],
            origin: [0.0; 3],
            periodic: [true; 3],
        },
        labels,
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 1,
                name: "sand".into(),
            },
            Phase {
                id: 2,
                name: "binder".into(),
            },
        ],
    }
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let n: usize = a.get(1).map(|s| s.parse().unwrap()).unwrap_or(64);
    let word = |i: usize, d: &str| a.get(i).cloned().unwrap_or(d.into());
    let d: Discretization =
        serde_json::from_value(serde_json::json!(word(2, "staggered"))).unwrap();
    let s: Solver = serde_json::from_value(serde_json::json!(word(3, "cg"))).unwrap();
    let pr: Precision = serde_json::from_value(serde_json::json!(word(4, "double"))).unwrap();
    let kind = word(5, "sand");
    let cases: Vec<LoadCase> = match a.get(6) {
        Some(c) => c
            .split(',')
            .map(|w| serde_json::from_value(serde_json::json!(w)).unwrap())
            .collect(),
        None => LoadCase::ALL.to_vec(),
    };
    let tol: f64 = a.get(7).map(|s| s.parse().unwrap()).unwrap_or(1e-5);
    let t = Instant::now();
    let (img, mats) = match kind.as_str() {
        "sphere" => {
            let mut m = IndexMap::new();
            m.insert("solid".to_string(), Material::e_nu(1.0, 0.3));
            (sphere_pore(n), m)
        }
        _ => (sand(n), grainpipe_fft::elasticity::default_materials()),
    };
    eprintln!(
        "image {n}^3 in {:.2} s: fractions pore {:.3} sand {:.3} binder {:.3}",
        t.elapsed().as_secs_f64(),
        img.fraction(0),
        img.fraction(1),
        img.fraction(2)
    );
    let p = ElasticityParams {
        materials: mats,
        discretization: d,
        solver: s,
        precision: pr,
        load_cases: cases,
        tolerance: tol,
        ..Default::default()
    };
    let m = grainpipe_fft::common::resolve("materials", &p.materials, &img, Iso::ZERO, |m| m.iso())
        .unwrap();
    struct Print;
    impl grainpipe_core::stage::Reporter for Print {
        fn progress(&self, _: u64, _: u64) {}
        fn message(&self, _: grainpipe_core::stage::Level, t: &str) {
            eprintln!("  {t}");
        }
        fn cancelled(&self) -> bool {
            false
        }
    }
    let _ = SilentReporter;
    let rep = Print;
    let ctx = RunContext::new(1, &rep);
    let t = Instant::now();
    let r = match pr {
        Precision::F64 => solve_all::<f64>(&p, &img, &m, None, &ctx),
        Precision::F32 => solve_all::<f32>(&p, &img, &m, None, &ctx),
    };
    let secs = t.elapsed().as_secs_f64();
    match r {
        Ok(r) => {
            println!("total {secs:.2} s");
            for row in r.stiffness {
                println!("{}", row.map(|v| format!("{v:12.5e}")).join(" "));
            }
            // All digits, on stderr: bit-for-bit comparisons between builds.
            for row in r.stiffness {
                eprintln!("  {}", row.map(|v| format!("{v:?}")).join(" "));
            }
            let e = grainpipe_fft::kernel::constants::engineering(
                &grainpipe_fft::kernel::constants::symmetrize(&r.stiffness),
            );
            println!(
                "E_x {:.4e} E_y {:.4e} E_z {:.4e} G_yz {:.4e} G_zx {:.4e} G_xy {:.4e}",
                e[0], e[1], e[2], e[3], e[4], e[5]
            );
        }
        Err(e) => println!("error after {secs:.2} s: {e}"),
    }
}
