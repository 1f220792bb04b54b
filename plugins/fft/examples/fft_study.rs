//! Accuracy / cost study driver for the benchmarks in plugins/fft/bench (not a test).
//!
//! `cargo run --release -p grainpipe-fft --example fft_study -- <n> <discretization> [cases] [tolerance] [precision]`
//!
//! Solves the simple-cubic spherical pore of porosity 0.2 in a solid (E = 1, nu = 0.3, unit
//! cell) on an n^3 voxel image, the case shared with the muspectre peer (bench/peer.sh), and
//! prints one CSV row per load case to stdout (header with `--header` as the only argument):
//!
//! `n,discretization,precision,tolerance,porosity,case,status,iterations,seconds,c11,c12,c44`
//!
//! `c11`, `c12` are the xx column (sigma_xx, sigma_yy for unit eps_xx), `c44` is sigma_yz for
//! a unit engineering shear gamma_yz (so C44 is the shear modulus). A solver failure (the
//! spectral scheme on pores) is a row with status `failed: <cause>` and empty moduli, so a
//! sweep records it instead of stopping.

mod images;

use grainpipe_core::stage::{Level, Reporter};
use grainpipe_core::RunContext;
use grainpipe_fft::common::{Discretization, Material, Precision};
use grainpipe_fft::elasticity::{solve_all, ElasticityParams, LoadCase};
use grainpipe_fft::kernel::Iso;
use images::sphere_pore;
use indexmap::IndexMap;
use std::time::Instant;

/// Messages of the solver go to stderr so stdout stays a clean CSV.
struct Stderr;
impl Reporter for Stderr {
    fn progress(&self, _: u64, _: u64) {}
    fn message(&self, _: Level, t: &str) {
        eprintln!("  {t}");
    }
    fn cancelled(&self) -> bool {
        false
    }
}

fn parse<T: serde::de::DeserializeOwned>(what: &str, word: &str) -> T {
    serde_json::from_value(serde_json::json!(word))
        .unwrap_or_else(|e| panic!("bad {what} '{word}': {e}"))
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.get(1).map(String::as_str) == Some("--header") {
        println!("n,discretization,precision,tolerance,porosity,case,status,iterations,seconds,c11,c12,c44");
        return;
    }
    let n: usize = a.get(1).map(|s| s.parse().expect("n")).unwrap_or(32);
    let disc_word = a.get(2).cloned().unwrap_or_else(|| "staggered".into());
    let disc: Discretization = parse("discretization", &disc_word);
    let cases: Vec<String> = a
        .get(3)
        .map(|c| c.split(',').map(str::to_string).collect())
        .unwrap_or_else(|| vec!["xx".into(), "yz".into()]);
    let tol: f64 = a
        .get(4)
        .map(|s| s.parse().expect("tolerance"))
        .unwrap_or(1e-5);
    let prec_word = a.get(5).cloned().unwrap_or_else(|| "double".into());
    let prec: Precision = parse("precision", &prec_word);

    let img = sphere_pore(n);
    let porosity = img.fraction(0);
    let mut mats = IndexMap::new();
    mats.insert("solid".to_string(), Material::e_nu(1.0, 0.3));
    let table = grainpipe_fft::common::resolve("materials", &mats, &img, Iso::ZERO, |m| m.iso())
        .expect("materials");
    let rep = Stderr;
    let ctx = RunContext::new(1, &rep);
    // One solve per load case, so each row carries its own time and iteration count (the
    // setup of the operator, a few per cent of a solve, is counted in every case).
    for case in &cases {
        let lc: LoadCase = parse("load case", case);
        let p = ElasticityParams {
            materials: mats.clone(),
            discretization: disc,
            precision: prec,
            load_cases: vec![lc],
            tolerance: tol,
            ..Default::default()
        };
        let t = Instant::now();
        let r = match prec {
            Precision::F64 => solve_all::<f64>(&p, &img, &table, None, &ctx),
            Precision::F32 => solve_all::<f32>(&p, &img, &table, None, &ctx),
        };
        let secs = t.elapsed().as_secs_f64();
        let head = format!("{n},{disc_word},{prec_word},{tol:e},{porosity:.6},{case}");
        match r {
            Ok(r) => {
                let iters = r.history.len().saturating_sub(1);
                let c = r.stiffness;
                let col = lc.column();
                // The column of this load case: c11/c12 for xx, c44 for yz.
                let (c11, c12, c44) = match col {
                    0 => (
                        format!("{:.8e}", c[0][0]),
                        format!("{:.8e}", c[1][0]),
                        String::new(),
                    ),
                    3 => (String::new(), String::new(), format!("{:.8e}", c[3][3])),
                    _ => (String::new(), String::new(), format!("{:.8e}", c[col][col])),
                };
                println!("{head},ok,{iters},{secs:.3},{c11},{c12},{c44}");
            }
            Err(e) => {
                let msg = e.to_string().replace([',', '\n'], ";");
                println!("{head},failed: {msg},,{secs:.3},,,");
            }
        }
    }
}
