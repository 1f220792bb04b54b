//! Benchmark of `peridynamics.bond_based` on an n x n grid (default 1024, h = 3 dx, 28
//! neighbours): bond updates per second of the force sweeps and the time to a converged
//! quasi-static state (CG, and ADR for comparison) on a synthetic cemented bidisperse sample.
//!
//! cargo build --release -p grainpipe-peridynamics --example pd_bench
//! target/release/examples/pd_bench [n] [adr_iterations] [out_dir] [multigrid|jacobi|both]

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{Grid, Phase, PhaseImage, RunContext};
use grainpipe_peridynamics::bond_based::{
    resolve_phases, solve_image, BondBasedParams, PreconditionerKind, SolverKind,
};
use grainpipe_peridynamics::lattice::ForceLaw;
use grainpipe_peridynamics::multigrid::{MgOptions, Multigrid};
use grainpipe_peridynamics::setup::{build, Grips, Identity, PhaseSpec, Role, Setup};
use std::io::Write;
use std::time::Instant;

/// Deterministic pseudo-random numbers in [0, 1) (splitmix64).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A cemented bidisperse sample like the paper's (gamma = 5): large disks of radius n/25,
/// small ones of radius n/125, placed by random sequential addition with a 1-voxel gap,
/// matrix in between, voids of radius n/200 sprinkled into the matrix.
fn sample(n: usize) -> PhaseImage {
    let mut labels = vec![3u8; n * n];
    let mut rng = Rng(42);
    let rl = n as f64 / 25.0;
    let rs = rl / 5.0;
    let mut disks: Vec<(f64, f64, f64)> = Vec::new();
    let mut place = |r: f64, tries: usize, disks: &mut Vec<(f64, f64, f64)>| {
        for _ in 0..tries {
            let (x, y) = (rng.next() * n as f64, rng.next() * n as f64);
            if disks
                .iter()
                .all(|&(a, b, q)| (a - x).powi(2) + (b - y).powi(2) > (q + r + 1.0).powi(2))
            {
                disks.push((x, y, r));
            }
        }
    };
    place(rl, 3000, &mut disks);
    place(rs, 60000, &mut disks);
    let large = disks.iter().filter(|d| d.2 == rl).count();
    let mut paint = |cx: f64, cy: f64, r: f64, lab: u8, only: Option<u8>| {
        let (x0, x1) = (
            (cx - r).floor().max(0.0) as usize,
            ((cx + r).ceil() as usize).min(n),
        );
        let (y0, y1) = (
            (cy - r).floor().max(0.0) as usize,
            ((cy + r).ceil() as usize).min(n),
        );
        for y in y0..y1 {
            for x in x0..x1 {
                let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
                if dx * dx + dy * dy <= r * r && only.is_none_or(|o| labels[x + n * y] == o) {
                    labels[x + n * y] = lab;
                }
            }
        }
    };
    for (k, &(x, y, r)) in disks.iter().enumerate() {
        paint(x, y, r, if k < large { 1 } else { 2 }, None);
    }
    let mut rng = Rng(7);
    for _ in 0..n / 4 {
        let (x, y) = (rng.next() * n as f64, rng.next() * n as f64);
        paint(x, y, n as f64 / 200.0, 0, Some(3));
    }
    PhaseImage {
        grid: Grid {
            dims: [n, n, 1],
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
        labels,
        phases: ["pore", "large", "small", "matrix"]
            .iter()
            .enumerate()
            .map(|(i, s)| Phase {
                id: i as u8,
                name: s.to_string(),
            })
            .collect(),
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(1024);
    let adr_its: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(2000);
    let out = args.get(3).cloned();
    if let Some(dir) = &out {
        std::fs::create_dir_all(dir).unwrap_or_else(|e| panic!("cannot create {dir}: {e}"));
    }
    let threads = rayon::current_num_threads();
    println!("grid {n}x{n}, h = 3 dx, {threads} threads");
    let t = Instant::now();
    let img = sample(n);
    let frac: Vec<f64> = (0..4).map(|l| img.fraction(l)).collect();
    println!(
        "sample: void {:.3}, large {:.3}, small {:.3}, matrix {:.3} (built in {:.2} s)",
        frac[0],
        frac[1],
        frac[2],
        frac[3],
        t.elapsed().as_secs_f64()
    );

    // Throughput of the force sweeps on the lattice of the sample.
    let p = BondBasedParams::default();
    let phases = resolve_phases(&p.materials, &img).unwrap();
    let setup = Setup {
        horizon: 3.0,
        interface: PhaseSpec {
            role: Role::Matrix,
            e: 1e9,
            gc: 10.0,
        },
        identity: Identity::Components,
        breaking: false,
        axis: 1,
        grips: Grips::Clamped,
        grip_layers: 1,
        strain: 1e-4,
        fail_on_floating: false,
        stiffness_scale: 1.0,
    };
    let t = Instant::now();
    let b = build(img.grid.dims, &img.labels, &phases, 1e-6, &setup).unwrap();
    println!(
        "lattice set-up {:.2} s: {} nodes, {} bonds (each once), {} floating nodes",
        t.elapsed().as_secs_f64(),
        b.nodes,
        b.bonds.iter().sum::<u64>(),
        b.floating_nodes
    );
    let lat = &b.lattice;
    let mut f = grainpipe_peridynamics::lattice::Vec3::zeros(&lat.layout);
    let neighbours = lat.layout.offsets.len() as f64;
    for (name, law) in [
        ("nonlinear (ADR/explicit)", ForceLaw::Nonlinear),
        ("linear (CG)", ForceLaw::Linear),
    ] {
        lat.forces(&b.u0, law, &mut f, None, true);
        let reps = 20;
        let t = Instant::now();
        for _ in 0..reps {
            lat.forces(&b.u0, law, &mut f, None, true);
        }
        let s = t.elapsed().as_secs_f64();
        // Every grid node visits its 28 stencil offsets (void pairs included: the loop
        // does not branch on them).
        let updates = (n * n) as f64 * neighbours * reps as f64;
        println!(
            "force sweep {name}: {:.1} ms per sweep, {:.3e} bond updates/s ({:.3e} per \
             material bond end)",
            1e3 * s / reps as f64,
            updates / s,
            (2 * b.bonds.iter().sum::<u64>()) as f64 * reps as f64 / s
        );
    }

    // Multigrid set-up and one V-cycle, timed apart from the solve.
    let t = Instant::now();
    let mg = Multigrid::new(lat, MgOptions::default());
    let t_setup = t.elapsed().as_secs_f64();
    let mut z = grainpipe_peridynamics::lattice::Vec3::zeros(&lat.layout);
    lat.forces(&b.u0, ForceLaw::Linear, &mut f, None, true);
    grainpipe_peridynamics::lattice::mask_fixed(lat, &mut f);
    let t = Instant::now();
    let reps = 5;
    for _ in 0..reps {
        mg.apply(lat, &f, &mut z);
    }
    println!(
        "multigrid: {} grids, set-up {:.2} s, {:.1} ms per V-cycle",
        mg.depth(),
        t_setup,
        1e3 * t.elapsed().as_secs_f64() / reps as f64
    );
    drop(mg);
    if std::env::var("PD_MG_SCAN").is_ok() {
        for (fs, cs, oc, cy) in [
            (1, 2, 1.5f32, 1),
            (1, 2, 1.5, 2),
            (1, 2, 1.0, 2),
            (1, 1, 1.5, 2),
        ] {
            let o = MgOptions {
                fine_sweeps: fs,
                coarse_sweeps: cs,
                overcorrection: oc,
                cycle: cy,
            };
            let mut u = b.u0.clone();
            let s = grainpipe_peridynamics::solve::Settings {
                tolerance: 1e-5,
                max_iterations: 2000,
                stagnation_window: 2000,
            };
            let t = Instant::now();
            let r = grainpipe_peridynamics::solve::cg(
                lat,
                &mut u,
                &s,
                grainpipe_peridynamics::solve::Precond::Multigrid(o),
                &mut |_, _| true,
            );
            println!(
                "scan fine {fs} coarse {cs} over {oc} cycle {cy}: {:?} its, {:.2} s",
                r.map(|x| x.iterations),
                t.elapsed().as_secs_f64()
            );
        }
    }

    let rep = SilentReporter;
    let ctx = RunContext::new(1, &rep);
    // CG with each preconditioner (the 4th argument picks one: multigrid | jacobi | both),
    // then ADR (skipped with adr_iterations = 0).
    let which = args.get(4).cloned().unwrap_or_else(|| "both".into());
    let mut runs = Vec::new();
    for (name, pc) in [
        ("multigrid", PreconditionerKind::Multigrid),
        ("jacobi", PreconditionerKind::Jacobi),
    ] {
        if which == "both" || which == name {
            runs.push((SolverKind::Cg, pc, 20000));
        }
    }
    if adr_its > 0 {
        runs.push((SolverKind::Adr, PreconditionerKind::Jacobi, adr_its));
    }
    for (solver, preconditioner, its) in runs {
        let p = BondBasedParams {
            solver,
            preconditioner,
            max_iterations: its,
            stagnation_window: its,
            ..Default::default()
        };
        let t = Instant::now();
        match solve_image(&p, 3.0, &img, &phases, &ctx) {
            Ok(r) => {
                let it = r.stats.iterations;
                println!(
                    "{solver:?} ({preconditioner:?}): converged to {:.2e} in {it} iterations, {:.2} s (stage run: \
                     set-up, solve, stress); E_eff = {:.4e} Pa",
                    r.stats.residual,
                    t.elapsed().as_secs_f64(),
                    r.report.f64_column("effective_modulus").unwrap()[0]
                );
                if let Some(dir) = &out {
                    let path =
                        format!("{dir}/history_{solver:?}_{preconditioner:?}.csv").to_lowercase();
                    let mut w = std::fs::File::create(&path).unwrap();
                    writeln!(w, "iteration,residual").unwrap();
                    let h = &r.stats.history;
                    for (i, r) in h.iteration.iter().zip(&h.residual) {
                        writeln!(w, "{i},{r:.6e}").unwrap();
                    }
                }
            }
            Err(e) => println!(
                "{solver:?}: {e} ({:.2} s, {:.1} ms per iteration)",
                t.elapsed().as_secs_f64(),
                1e3 * t.elapsed().as_secs_f64() / its as f64
            ),
        }
    }
}
