#![allow(dead_code)]
//! Shared helpers: running a stage directly (its preflight announcement checked against what
//! it gives, as the engine does) and an independent brute-force overlap check.

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{
    Artifact, Clump, ClumpLibrary, ClumpSphere, InputMetas, Inputs, Outputs, Packing, RunContext,
    StageError, TypedStage,
};
use std::f64::consts::PI;
use std::sync::Arc;

pub fn run<S: TypedStage>(
    stage: &S,
    params: serde_json::Value,
    lib: Option<&ClumpLibrary>,
    seed: u64,
) -> Result<Outputs, StageError> {
    let p: S::Params = serde_json::from_value(params).expect("params");
    let mut inputs = Inputs::new();
    let mut metas = InputMetas::new();
    if let Some(l) = lib {
        inputs.insert(
            "library".into(),
            Arc::new(Artifact::ClumpLibrary(l.clone())),
        );
        metas.insert(
            "library".into(),
            grainpipe_core::ArtifactMeta::of(grainpipe_core::ArtifactKind::ClumpLibrary),
        );
    }
    let pf = stage.preflight(&p, &metas)?;
    let out = stage.run(
        &p,
        &pf.plan,
        &inputs,
        &RunContext::new(seed, &SilentReporter),
    )?;
    for (port, meta) in &pf.outputs {
        meta.check(&out[port.as_str()])
            .unwrap_or_else(|e| panic!("output `{port}` contradicts its preflight: {e}"));
    }
    Ok(out)
}

pub fn packing(out: &Outputs) -> &Packing {
    out["packing"].as_packing().unwrap()
}

/// Smallest (distance - r_a - r_b) over all sphere pairs of different bodies, over every
/// periodic image within +-2 cells along the domain's periodic axes (brute force, independent
/// of the crate's cell lists).
pub fn min_surface_gap(p: &Packing) -> f64 {
    let ws = p.world_spheres();
    let l = p.domain.size();
    let k = p.domain.periodic.map(|per| if per { 2i32 } else { 0 });
    let mut best = f64::INFINITY;
    for a in 0..ws.len() {
        for b in a + 1..ws.len() {
            if ws[a].body == ws[b].body {
                continue;
            }
            for ix in -k[0]..=k[0] {
                for iy in -k[1]..=k[1] {
                    for iz in -k[2]..=k[2] {
                        let s = [ix as f64 * l[0], iy as f64 * l[1], iz as f64 * l[2]];
                        let d2: f64 = (0..3)
                            .map(|k| (ws[a].center[k] - ws[b].center[k] - s[k]).powi(2))
                            .sum();
                        best = best.min(d2.sqrt() - ws[a].radius - ws[b].radius);
                    }
                }
            }
        }
    }
    best
}

/// As `min_surface_gap` for packings of many-sphere clumps: body pairs whose bounding
/// spheres (computed here from the world spheres) are more than 10 um apart are skipped; images within +-1
/// cell (enough while the cell is at least one bounding diameter wide, which is asserted).
pub fn min_surface_gap_culled(p: &Packing) -> f64 {
    let ws = p.world_spheres();
    let l = p.domain.size();
    let n = p.bodies.len();
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (k, s) in ws.iter().enumerate() {
        members[s.body].push(k);
    }
    let bound: Vec<f64> = (0..n)
        .map(|i| {
            let c = p.bodies[i].position;
            members[i]
                .iter()
                .map(|&k| {
                    let d2: f64 = (0..3).map(|a| (ws[k].center[a] - c[a]).powi(2)).sum();
                    d2.sqrt() + ws[k].radius
                })
                .fold(0.0, f64::max)
        })
        .collect();
    let bmax = bound.iter().cloned().fold(0.0, f64::max);
    assert!(
        l.iter().all(|&x| x >= 2.0 * bmax),
        "cell narrower than a grain"
    );
    let k = p.domain.periodic.map(|per| if per { 1i32 } else { 0 });
    let mut best = f64::INFINITY;
    for i in 0..n {
        for j in i + 1..n {
            for ix in -k[0]..=k[0] {
                for iy in -k[1]..=k[1] {
                    for iz in -k[2]..=k[2] {
                        let s = [ix as f64 * l[0], iy as f64 * l[1], iz as f64 * l[2]];
                        let (ci, cj) = (p.bodies[i].position, p.bodies[j].position);
                        let d2: f64 = (0..3).map(|a| (ci[a] - cj[a] - s[a]).powi(2)).sum();
                        // Pairs farther apart than 10 um cannot break an 8 um gap test.
                        if d2.sqrt() > bound[i] + bound[j] + 1e-5 {
                            continue;
                        }
                        for &a in &members[i] {
                            for &b in &members[j] {
                                let d2: f64 = (0..3)
                                    .map(|x| (ws[a].center[x] - ws[b].center[x] - s[x]).powi(2))
                                    .sum();
                                best = best.min(d2.sqrt() - ws[a].radius - ws[b].radius);
                            }
                        }
                    }
                }
            }
        }
    }
    best
}

/// Three spheres of radius r on the x axis at -r, 0, r: length 4r, width 2r. Union volume
/// = 3 spheres - 2 lenses of two radius-r spheres at distance r (lens = pi (4r+d)(2r-d)^2/12
/// = 5 pi r^3 / 12); the outer spheres only touch.
pub fn rod(r: f64) -> Clump {
    Clump {
        spheres: [-r, 0.0, r]
            .iter()
            .map(|&x| ClumpSphere {
                offset: [x, 0.0, 0.0],
                radius: r,
            })
            .collect(),
        volume: 4.0 * PI * r.powi(3) - 10.0 / 12.0 * PI * r.powi(3),
        bounding_radius: 2.0 * r,
        // Rod along x: smallest moment about x (the ordering is all that matters here).
        principal_inertia: [1.0, 2.0, 2.0],
        principal_axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        source: "test rod".into(),
    }
}

pub fn rods() -> ClumpLibrary {
    ClumpLibrary {
        clumps: [40e-6, 45e-6, 50e-6].iter().map(|&r| rod(r)).collect(),
        source: "test".into(),
    }
}
