//! mcm.classic on N spheres towards random close packing (issue 20), for the side-by-side
//! comparison with spheropack in plugins/mcm/bench/peer.sh.
//!
//! cargo run --release -p grainpipe-mcm --example classic_rcp -- PHI [N=1000] [LAW=fixed]
//!     [SEED=1] [OUT.csv]
//!   LAW: `fixed` (equal spheres, radius 1 mm) or `weibull` (scale 1 mm, shape 3.55, the
//!   shape of the sand's Weibull fit in the project's examples). Env MCM_TOL overrides the
//!   stage's `tolerance`, MCM_RESTARTS its `restarts`, MCM_PARAMS (a JSON object) any
//!   other parameter.
//! Prints one line: phi, wall time of the stage [s], iterations, contraction steps, tries;
//! writes the packing as CSV (`x,y,z,r` in metres, first line `# box L`) to OUT.csv when given,
//! for an independent overlap check.

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{BodyShape, InputMetas, Inputs, RunContext, TypedStage};
use grainpipe_mcm::stages::{Classic, ClassicParams};
use serde_json::json;
use std::io::Write;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let phi: f64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(0.64);
    let n: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1000);
    let law = args.get(3).cloned().unwrap_or_else(|| "fixed".into());
    let seed: u64 = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(1);
    let out = args.get(5).cloned();
    let radius = match law.as_str() {
        "fixed" => json!({"kind": "fixed", "value": 1e-3}),
        "weibull" => json!({"kind": "weibull", "scale": 1e-3, "shape": 3.55}),
        other => panic!("unknown law {other}: fixed or weibull"),
    };
    let mut params = json!({"count": n, "volume_fraction": phi, "min_gap": 0.0, "radius": radius});
    if let Ok(t) = std::env::var("MCM_TOL") {
        params["tolerance"] = json!(t.parse::<f64>().expect("MCM_TOL"));
    }
    if let Ok(r) = std::env::var("MCM_RESTARTS") {
        params["restarts"] = json!(r.parse::<usize>().expect("MCM_RESTARTS"));
    }
    // Any other stage parameter as a JSON object, e.g. MCM_PARAMS='{"anneal_steps": 0}'.
    if let Ok(extra) = std::env::var("MCM_PARAMS") {
        let extra: serde_json::Value = serde_json::from_str(&extra).expect("MCM_PARAMS");
        for (k, v) in extra.as_object().expect("MCM_PARAMS: a JSON object") {
            params[k] = v.clone();
        }
    }
    let p: ClassicParams = serde_json::from_value(params).unwrap();
    let t0 = Instant::now();
    let r = Classic.preflight(&p, &InputMetas::new()).and_then(|pf| {
        Classic.run(
            &p,
            &pf.plan,
            &Inputs::new(),
            &RunContext::new(seed, &SilentReporter),
        )
    });
    let dt = t0.elapsed().as_secs_f64();
    let out_artifacts = match r {
        Ok(o) => o,
        Err(e) => {
            println!("mcm.classic phi {phi} n {n} {law} seed {seed}: FAILED after {dt:.2} s: {e}");
            std::process::exit(1);
        }
    };
    let pk = out_artifacts["packing"].as_packing().unwrap();
    let rep = out_artifacts["report"].as_table().unwrap();
    let int = |name: &str| match &rep.column(name).unwrap().data {
        grainpipe_core::ColumnData::I64(v) => v[0],
        _ => panic!("{name}"),
    };
    println!(
        "mcm.classic phi {:.4} n {n} {law} seed {seed}: {dt:.2} s, {} iterations, {} contraction steps, {} tries",
        pk.volume_fraction(),
        int("iterations"),
        int("contraction_steps"),
        int("tries")
    );
    if let Some(path) = out {
        let mut f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
        let l = pk.domain.size();
        writeln!(f, "# box {} {} {}", l[0], l[1], l[2]).unwrap();
        writeln!(f, "x,y,z,r").unwrap();
        for b in &pk.bodies {
            let BodyShape::Sphere { radius } = b.shape else {
                panic!("spheres only")
            };
            let [x, y, z] = b.position;
            writeln!(f, "{x:.17e},{y:.17e},{z:.17e},{radius:.17e}").unwrap();
        }
    }
}
