//! Periodic arrays against their references: simple-cubic spheres (Zick & Homsy 1982,
//! Table 2) and square arrays of cylinders (Sangani & Acrivos 1982, Table 1).
//!
//! cargo run --release -p grainpipe-stokes --example arrays -- spheres 40 [fractions...]
//! cargo run --release -p grainpipe-stokes --example arrays -- cylinders 40 [fractions...]

use grainpipe_stokes::mac::Dims;
use grainpipe_stokes::multigrid::CycleSettings;
use grainpipe_stokes::solver::{permeability, SolverSettings};
use std::f64::consts::PI;

/// Zick & Homsy (1982), Table 2, simple cubic: (solid fraction, K = F / (6 pi mu a U)).
const ZICK_HOMSY: [(f64, f64); 7] = [
    (0.027, 2.008),
    (0.064, 2.810),
    (0.125, 4.292),
    (0.216, 7.442),
    (0.343, 15.4),
    (0.45, 28.1),
    (std::f64::consts::FRAC_PI_6, 42.1), // touching spheres, 0.5236
];
/// Sangani & Acrivos (1982), Table 1, square arrays: (solid fraction, F / (mu U)).
const SANGANI_ACRIVOS: [(f64, f64); 6] = [
    (0.05, 15.56),
    (0.1, 24.83),
    (0.2, 51.53),
    (0.3, 102.90),
    (0.4, 217.89),
    (0.5, 532.55),
];

/// Volume-matched centred body (see tests/common).
fn body(dims: Dims, fraction: f64, dim3: bool) -> Vec<bool> {
    let n = dims.len();
    let c = dims.n.map(|v| v as f64 / 2.0);
    let d2: Vec<f64> = (0..n)
        .map(|i| {
            let p = dims.coords(i);
            (0..if dim3 { 3 } else { 2 })
                .map(|a| (p[a] as f64 + 0.5 - c[a]).powi(2))
                .sum()
        })
        .collect();
    let mut s = d2.clone();
    s.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let target = fraction * n as f64;
    let (mut best, mut cut, mut k) = (f64::INFINITY, 0.0, 0);
    while k < n {
        let mut e = k;
        while e < n && s[e] == s[k] {
            e += 1;
        }
        if (e as f64 - target).abs() < best {
            best = (e as f64 - target).abs();
            cut = s[k];
        }
        k = e;
    }
    d2.iter().map(|&v| v > cut).collect()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let kind = args.get(1).map(String::as_str).unwrap_or("spheres");
    let vpd: f64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(20.0);
    let wanted: Vec<f64> = args[3.min(args.len())..]
        .iter()
        .filter_map(|s| s.parse().ok())
        .collect();
    let spheres = kind == "spheres";
    let table: &[(f64, f64)] = if spheres {
        &ZICK_HOMSY
    } else {
        &SANGANI_ACRIVOS
    };
    println!(
        "kind,fraction,voxels_per_diameter,n,reference,computed,error_percent,iterations,seconds"
    );
    for &(c, reference) in table {
        if !wanted.is_empty() && !wanted.iter().any(|w| (w - c).abs() < 1e-4) {
            continue;
        }
        // Diameter per cell edge.
        let d_over_l = if spheres {
            2.0 * (3.0 * c / (4.0 * PI)).cbrt()
        } else {
            2.0 * (c / PI).sqrt()
        };
        let n = (vpd / d_over_l).round() as usize;
        let dims = if spheres {
            Dims::new([n, n, n])
        } else {
            Dims::new([n, n, 1])
        };
        let fluid = body(dims, c, spheres);
        let s = SolverSettings {
            tolerance: 1e-6,
            max_iterations: 2000,
            cycle: CycleSettings::default(),
        };
        let t = std::time::Instant::now();
        let r = permeability::<(), _>(dims, fluid.to_vec(), &[0], s, &[], |_, _, _| Ok(()))
            .unwrap()
            .unwrap();
        let secs = t.elapsed().as_secs_f64();
        let k = r.kappa[0][0];
        let nf = n as f64;
        let computed = if spheres {
            let a = d_over_l / 2.0 * nf;
            nf.powi(3) / (6.0 * PI * a * k)
        } else {
            nf * nf / k
        };
        println!(
            "{kind},{c},{:.1},{n},{reference},{computed:.4},{:.2},{},{secs:.2}",
            d_over_l * nf,
            100.0 * (computed / reference - 1.0),
            r.cases[0].iterations
        );
    }
}
