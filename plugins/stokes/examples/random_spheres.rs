//! Random overlapping spheres (fixed seed) in a periodic cube: iterations and time against
//! resolution, for the solver's benchmark table.
//!
//! cargo run --release -p grainpipe-stokes --example random_spheres -- N [solid_fraction] [radius_fraction] [cases]

use grainpipe_stokes::mac::Dims;
use grainpipe_stokes::multigrid::CycleSettings;
use grainpipe_stokes::solver::{permeability, symmetry_error, SolverSettings};

/// Overlapping spheres of radius r_frac * n at centres from a fixed LCG, added until the
/// solid fraction reaches `solid`; the geometry scales with n so that resolutions compare.
pub fn random_spheres(n: usize, solid: f64, r_frac: f64) -> Vec<bool> {
    let dims = Dims::new([n, n, n]);
    let mut fluid = vec![true; dims.len()];
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let r = r_frac * n as f64;
    let mut solid_count = 0usize;
    while (solid_count as f64) < solid * dims.len() as f64 {
        let c = [next(), next(), next()].map(|v| v * n as f64);
        let lo = |a: usize| (c[a] - r).floor() as i64;
        let hi = |a: usize| (c[a] + r).ceil() as i64;
        for z in lo(2)..=hi(2) {
            for y in lo(1)..=hi(1) {
                for x in lo(0)..=hi(0) {
                    let d = [x, y, z]
                        .iter()
                        .zip(c.iter())
                        .map(|(&p, &q)| (p as f64 + 0.5 - q).powi(2))
                        .sum::<f64>();
                    if d <= r * r {
                        let w = |v: i64| v.rem_euclid(n as i64) as usize;
                        let i = dims.index(w(x), w(y), w(z));
                        if fluid[i] {
                            fluid[i] = false;
                            solid_count += 1;
                        }
                    }
                }
            }
        }
    }
    fluid
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(64);
    let solid: f64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(0.35);
    let rf: f64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(0.0625);
    let cases: usize = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(1);
    let env = |k: &str, d: f64| -> f64 {
        std::env::var(k)
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(d)
    };
    let d = CycleSettings::default();
    let cycle = CycleSettings {
        sweeps: env("STOKES_SWEEPS", d.sweeps as f64) as usize,
        over_correction: env("STOKES_OC", d.over_correction as f64) as f32,
        coarsest_sweeps: env("STOKES_COARSEST", d.coarsest_sweeps as f64) as usize,
    };
    let dims = Dims::new([n, n, n]);
    let fluid = random_spheres(n, solid, rf);
    let s = SolverSettings {
        tolerance: env("STOKES_TOL", 1e-6),
        max_iterations: 5000,
        cycle,
    };
    let axes: Vec<usize> = (0..cases).collect();
    let t = std::time::Instant::now();
    let r = permeability::<(), _>(dims, fluid.to_vec(), &axes, s, &[], |_, _, _| Ok(()))
        .unwrap()
        .unwrap();
    let secs = t.elapsed().as_secs_f64();
    for c in &r.cases {
        println!(
            "n={n} axis={} kappa/h^2={:.6e} iterations={} residual={:.2e} true={:.2e} mass={:.2e}",
            c.axis,
            r.kappa[c.axis][c.axis],
            c.iterations,
            c.residual,
            c.true_residual,
            c.mass_error
        );
    }
    println!(
        "n={n} porosity={:.4} connected={:.4} symmetry_error={:.2e} seconds={secs:.2} cycle={cycle:?}",
        r.porosity,
        r.connected_porosity,
        if cases == 3 { symmetry_error(&r.kappa) } else { f64::NAN }
    );
}
