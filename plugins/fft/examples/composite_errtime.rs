//! Error against CPU time of composite voxels and labels (issue 32), hex8, on two cells with
//! exact answers: the Hashin coated sphere (bulk modulus K*, nominal geometry) and Rayleigh's
//! simple-cubic array of conducting spheres (k = 10 in 1, f = 0.2, McKenzie et al. 1978).
//! Prints CSV to stdout: case, interfaces, n, error, cpu_s (this process's user + system
//! time of the solve, from /proc/self/stat), wall_s.
//!
//!   cargo run --release -p grainpipe-fft --example composite_errtime > plugins/fft/bench/composite_errtime.csv

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::subvoxel::{self, InterfaceParams, Interfaces, PoreVoxels};
use grainpipe_core::units::Q;
use grainpipe_core::{Grid, Phase, PhaseImage, RunContext};
use grainpipe_fft::common::{Discretization, Material, Solver};
use grainpipe_fft::conductivity::ConductivityParams;
use grainpipe_fft::elasticity::{solve_image, ElasticityParams, LoadCase};
use grainpipe_fft::kernel::Iso;
use std::time::Instant;

/// User + system CPU seconds of this process (Linux /proc/self/stat fields 14 and 15).
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // fields after the command: state is index 0, utime is field 14 overall -> index 11
    (ticks(11) + ticks(12)) / 100.0
}

fn image(n: usize, phase_at: &impl Fn([f64; 3]) -> usize, phases: usize) -> PhaseImage {
    let mut labels = Vec::with_capacity(n * n * n);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let p = [x, y, z].map(|v| (v as f64 + 0.5) / n as f64);
                labels.push(phase_at(p) as u8 + 1);
            }
        }
    }
    PhaseImage {
        grid: Grid {
            dims: [n; 3],
            spacing: [1.0 / n as f64; 3],
            origin: [0.0; 3],
            periodic: [true; 3],
        },
        labels,
        phases: (1..=phases as u8)
            .map(|id| Phase {
                id,
                name: format!("m{id}"),
            })
            .collect(),
    }
}

fn interface(composite: bool) -> InterfaceParams {
    InterfaceParams {
        interfaces: if composite {
            Interfaces::Composite
        } else {
            Interfaces::Labels
        },
        coarsen: 1,
        pore_voxels: PoreVoxels::Majority,
    }
}

fn main() {
    let rep = SilentReporter;
    let ctx = RunContext::new(1, &rep);
    println!("case,interfaces,n,error,cpu_s,wall_s");
    // Coated sphere.
    let (core, shell) = (Iso::from_e_nu(20.0, 0.2), Iso::from_e_nu(1.5, 0.3));
    let (ra, rb): (f64, f64) = (0.26, 0.38);
    let c = (ra / rb).powi(3);
    let (k1, k2, g2) = (core.bulk(), shell.bulk(), shell.mu);
    let k_star = k2 + c * (k1 - k2) / (1.0 + (1.0 - c) * (k1 - k2) / (k2 + 4.0 * g2 / 3.0));
    let e_m = 3.0 * k_star * (1.0 - 2.0 * 0.3);
    let coated = |p: [f64; 3]| {
        let r2: f64 = p.iter().map(|&v| (v - 0.5) * (v - 0.5)).sum();
        if r2 < ra * ra {
            0
        } else if r2 < rb * rb {
            1
        } else {
            2
        }
    };
    for n in [12usize, 16, 24, 32, 48, 64] {
        let img = image(n, &coated, 3);
        for composite in [false, true] {
            let (t0, c0) = (Instant::now(), cpu_seconds());
            let field = composite.then(|| {
                subvoxel::sample(&img, 6, coated)
                    .expect("phases")
                    .to_field(&img.grid)
            });
            let p = ElasticityParams {
                materials: [
                    ("m1", Material::e_nu(20.0, 0.2)),
                    ("m2", Material::e_nu(1.5, 0.3)),
                    ("m3", Material::e_nu(e_m, 0.3)),
                ]
                .into_iter()
                .map(|(k, v)| (k.to_string(), v))
                .collect(),
                discretization: Discretization::Hex8,
                solver: Solver::Cg,
                tolerance: 1e-6,
                load_cases: vec![LoadCase::Xx, LoadCase::Yy, LoadCase::Zz],
                interface: interface(composite),
                ..Default::default()
            };
            let cst = solve_image(&p, &img, field.as_ref(), &ctx)
                .expect("solve")
                .1
                .stiffness;
            let k: f64 = (0..3)
                .flat_map(|i| (0..3).map(move |j| (i, j)))
                .map(|(i, j)| cst[i][j])
                .sum::<f64>()
                / 9.0;
            println!(
                "coated_sphere_bulk,{},{n},{:.6e},{:.3},{:.3}",
                if composite { "composite" } else { "labels" },
                (k / k_star - 1.0).abs(),
                cpu_seconds() - c0,
                t0.elapsed().as_secs_f64()
            );
        }
    }
    // Rayleigh array.
    let f = 0.2;
    let r = (f * 3.0 / (4.0 * std::f64::consts::PI)).cbrt();
    let sphere = |p: [f64; 3]| {
        let r2: f64 = p.iter().map(|&v| (v - 0.5) * (v - 0.5)).sum();
        usize::from(r2 >= r * r)
    };
    let (ks, km) = (10.0, 1.0);
    let t = (ks + 2.0 * km) / (ks - km);
    let cc = (ks - km) / (ks + 4.0 / 3.0 * km);
    let want = km * (1.0 + 3.0 * f / (t - f - 1.305 * cc * f.powf(10.0 / 3.0)));
    for n in [12usize, 16, 24, 32, 48, 64, 96] {
        let img = image(n, &sphere, 2);
        for composite in [false, true] {
            let (t0, c0) = (Instant::now(), cpu_seconds());
            let field = composite.then(|| {
                subvoxel::sample(&img, 6, sphere)
                    .expect("phases")
                    .to_field(&img.grid)
            });
            let p = ConductivityParams {
                conductivities: [
                    ("m1".to_string(), Q::new(ks)),
                    ("m2".to_string(), Q::new(km)),
                ]
                .into_iter()
                .collect(),
                discretization: Discretization::Hex8,
                solver: Solver::Cg,
                tolerance: 1e-8,
                interface: interface(composite),
                ..Default::default()
            };
            let k = grainpipe_fft::conductivity::solve_image(&p, &img, field.as_ref(), &ctx)
                .expect("solve")
                .0;
            println!(
                "rayleigh_conductivity,{},{n},{:.6e},{:.3},{:.3}",
                if composite { "composite" } else { "labels" },
                (k[0][0] / want - 1.0).abs(),
                cpu_seconds() - c0,
                t0.elapsed().as_secs_f64()
            );
        }
    }
}
