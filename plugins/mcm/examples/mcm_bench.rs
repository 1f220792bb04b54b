//! Benchmark of mcm.stacked against the paper's Tables 4-5 (Donval et al. 2025, section 3.5):
//! layers of (L um)^2 x 280 um at 50 % with an 8 um gap, 30 000 iteration limit, several seeds.
//!
//! cargo run --release -p grainpipe-mcm --example mcm_bench -- [seeds, 30] [grains, sand]
//!   grains = sand (the real grains of data/sand-grains as clumps at alpha = MCM_ALPHA,
//!   default 0.99: 186 spheres per clump, the paper's 150-200; bounding diameter capped at
//!   the 280 um layer thickness as in the paper; built by pipelines/clumps.yaml) or spheres
//!   (lognormal, median radius 70 um, D50 = 140 um, radii 40-120 um).
//! Env MCM_CASES="layers:size_um,..." overrides the cases (default: Table 4, then Table 5);
//! MCM_PHI (0.5), MCM_GAP (8e-6 m), MCM_TOL (1e-2), MCM_STEP (3000), MCM_STEPS (30),
//! MCM_BETA (3) override the fraction, gap, tolerance, iterations per contraction step,
//! contraction steps and beta; MCM_PERIODIC_Z=0 gives a free surface above each new layer;
//! MCM_ENERGY (all_pairs | max_pair) and MCM_MINIMISER (fire | gradient_descent) pick the
//! overlap energy and the minimiser; MCM_SHAKE=0 turns jam shaking off; MCM_SEED0 is the
//! first seed.

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{
    Artifact, ArtifactKind, ArtifactMeta, ClumpLibrary, InputMetas, Inputs, RunContext, TypedStage,
};
use grainpipe_mcm::stages::{Stacked, StackedParams};
use serde_json::json;
use std::sync::Arc;
use std::time::Instant;

fn sand_library() -> ClumpLibrary {
    use grainpipe_core::engine::run_quietly;
    use grainpipe_core::pipeline::PipelineDoc;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut doc = PipelineDoc::load(&root.join("pipelines/clumps.yaml")).unwrap();
    doc.exports.clear();
    // The paper's clumps have 150-200 spheres (CT voxel masks at alpha = 0.9); our smooth
    // harmonic grains reach that complexity at alpha = 0.99 (188 spheres on average).
    let alpha = std::env::var("MCM_ALPHA").unwrap_or_else(|_| "0.99".into());
    doc.apply_override(&format!("clumps.alpha={alpha}"))
        .unwrap();
    // Paper, section 3.5: the largest bounding diameter is the layer thickness, 280 um.
    doc.apply_override("library.sampling=all").unwrap();
    doc.apply_override("library.max_bounding_diameter=280 um")
        .unwrap();
    std::env::set_current_dir(&root).unwrap();
    let mut r = grainpipe_core::Registry::new();
    grainpipe_clumps::register(&mut r);
    let res = run_quietly(&doc, &r).unwrap();
    // All clumps up to 280 um (no subsample): mcm.stacked draws by Sobol itself.
    res.outputs["library"]["library"]
        .as_clump_library()
        .unwrap()
        .clone()
}

fn env(key: &str, default: f64) -> f64 {
    std::env::var(key)
        .ok()
        .and_then(|t| t.parse::<f64>().ok())
        .unwrap_or(default)
}

fn env_str(key: &str, default: &str) -> String {
    std::env::var(key).unwrap_or_else(|_| default.into())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(30);
    let grains = args.get(2).cloned().unwrap_or_else(|| "sand".into());
    let lib = (grains == "sand").then(sand_library);
    if let Some(l) = &lib {
        let n: usize = l.clumps.iter().map(|c| c.spheres.len()).sum();
        println!(
            "library: {} clumps, {:.0} spheres per clump on average",
            l.clumps.len(),
            n as f64 / l.clumps.len() as f64
        );
    }
    let cases: Vec<(usize, f64)> = std::env::var("MCM_CASES")
        .unwrap_or_else(|_| "1:560,2:560,3:560,4:560,2:280,2:420,2:840,2:1120".into())
        .split(',')
        .map(|c| {
            let (l, s) = c.split_once(':').unwrap();
            (l.parse().unwrap(), s.parse().unwrap())
        })
        .collect();
    println!("| layers | size (um)^2 | grains | median time (s) | max time (s) | failures / seeds | restarts | median iterations |");
    println!("|---|---|---|---|---|---|---|---|");
    for (layers, size) in cases {
        let mut times = Vec::new();
        let mut iters = Vec::new();
        let mut fails = 0;
        let mut grains_n = 0;
        // Layers placed afresh after a failed try (the paper counts these as failed tries).
        let mut restarts = 0;
        let seed0 = env("MCM_SEED0", 0.0) as u64;
        for seed in seed0..seed0 + seeds {
            let p: StackedParams = serde_json::from_value(json!({
                "layers": layers, "layer_size": [size * 1e-6, size * 1e-6],
                "layer_thickness": 280e-6, "volume_fraction": env("MCM_PHI", 0.5), "min_gap": env("MCM_GAP", 8e-6),
                "radius": {"kind": "lognormal", "median": "70 um", "sigma": 0.2, "min": "40 um", "max": "120 um"},
                "tolerance": env("MCM_TOL", 1e-2),
                "contraction_steps": env("MCM_STEPS", 30.0) as usize,
                "beta": env("MCM_BETA", 3.0),
                "step_iterations": env("MCM_STEP", 3000.0) as usize,
                "periodic_z": env("MCM_PERIODIC_Z", 1.0) != 0.0,
                "energy": env_str("MCM_ENERGY", "all_pairs"),
                "minimiser": env_str("MCM_MINIMISER", "fire"),
                "shake": env("MCM_SHAKE", 1.0) != 0.0,
            }))
            .unwrap();
            let mut inputs = Inputs::new();
            let mut metas = InputMetas::new();
            if let Some(l) = &lib {
                inputs.insert(
                    "library".into(),
                    Arc::new(Artifact::ClumpLibrary(l.clone())),
                );
                metas.insert(
                    "library".into(),
                    ArtifactMeta::of(ArtifactKind::ClumpLibrary),
                );
            }
            let t0 = Instant::now();
            let r = Stacked.preflight(&p, &metas).and_then(|pf| {
                Stacked.run(
                    &p,
                    &pf.plan,
                    &inputs,
                    &RunContext::new(seed, &SilentReporter),
                )
            });
            let dt = t0.elapsed().as_secs_f64();
            match r {
                Ok(out) => {
                    let rep = out["report"].as_table().unwrap();
                    // Sums over the layers of an integer column of the report.
                    let total = |name: &str| match &rep.column(name).unwrap().data {
                        grainpipe_core::ColumnData::I64(v) => v.iter().sum::<i64>(),
                        _ => panic!("report column {name} is not an integer column"),
                    };
                    iters.push(total("iterations") as f64);
                    grains_n = total("grains");
                    restarts += total("tries") - rep.rows() as i64;
                    times.push(dt);
                }
                Err(e) => {
                    fails += 1;
                    times.push(dt);
                    eprintln!("layers {layers}, {size} um, seed {seed}: {e}");
                }
            }
        }
        let med = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            if v.is_empty() {
                f64::NAN
            } else {
                v[v.len() / 2]
            }
        };
        let max = times.iter().cloned().fold(0.0, f64::max);
        println!(
            "| {layers} | {size} | {grains_n} | {:.2} | {:.2} | {fails} / {seeds} | {restarts} | {:.0} |",
            med(&mut times),
            max,
            med(&mut iters)
        );
    }
}
