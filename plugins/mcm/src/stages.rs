//! The stages `mcm.classic` and `mcm.stacked`.

use crate::engine::{Grain, Shape, System};
use crate::pack::{
    contract, place, random_rotation, scale_clump, uniform, v3, Mode, Pick, Schedule, Source,
};
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    input, Artifact, ArtifactKind, Body, BodyShape, ClumpLibrary, Domain, InputMetas, Inputs,
    Outputs, Packing, ParamSpec, PortSpec, Preflight, RunContext, StageError, StageInfo, Table,
    Tensor, TensorConvention, TypedStage,
};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Random initial positions tried per grain before the least overlapping one is kept.
const PLACE_ATTEMPTS: usize = 200;

/// `mcm.classic`: Williams and Philipse's MCM for clumps (Schneider et al. 2018).
pub struct Classic;
/// `mcm.stacked`: Donval et al.'s stacked MCM (Algorithm 2).
pub struct Stacked;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ClassicParams {
    pub radius: SizeDistribution,
    pub count: usize,
    pub size: [Q<Length>; 3],
    pub volume_fraction: f64,
    pub beta: f64,
    pub contraction_steps: usize,
    pub min_gap: Q<Length>,
    pub tolerance: f64,
    pub step_iterations: usize,
    pub max_iterations: usize,
}

impl Default for ClassicParams {
    fn default() -> Self {
        ClassicParams {
            radius: SizeDistribution::Fixed {
                value: Q::new(70e-6),
            },
            count: 200,
            size: [Q::new(0.0); 3],
            // Paper, section 2.2: the sand packings are generated at 50 %.
            volume_fraction: 0.5,
            beta: 2.0,
            contraction_steps: 30,
            min_gap: Q::new(0.0),
            tolerance: 1e-4,
            step_iterations: 3000,
            // Paper, section 3.5: maximal iteration count 30 000.
            max_iterations: 30_000,
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StackedParams {
    pub radius: SizeDistribution,
    pub layers: usize,
    pub layer_size: [Q<Length>; 2],
    pub layer_thickness: Q<Length>,
    pub volume_fraction: f64,
    pub beta: f64,
    pub contraction_steps: usize,
    pub min_gap: Q<Length>,
    pub tolerance: f64,
    pub step_iterations: usize,
    pub max_iterations: usize,
    pub periodic_z: bool,
}

impl Default for StackedParams {
    fn default() -> Self {
        StackedParams {
            radius: SizeDistribution::Fixed {
                value: Q::new(70e-6),
            },
            // Paper, section 3.5: two layers of (560 um)^2 x 280 um at 50 %, gap 8 um.
            layers: 2,
            layer_size: [Q::new(560e-6), Q::new(560e-6)],
            layer_thickness: Q::new(280e-6),
            volume_fraction: 0.5,
            beta: 3.0,
            contraction_steps: 30,
            min_gap: Q::new(8e-6),
            tolerance: 1e-4,
            step_iterations: 3000,
            max_iterations: 30_000,
            periodic_z: true,
        }
    }
}

fn common_params() -> Vec<ParamSpec> {
    vec![
        ParamSpec { name: "radius", ty: "SizeDistribution", unit: "m", doc: "sphere radius distribution, used when no `library` is connected" },
        ParamSpec { name: "volume_fraction", ty: "f64", unit: "1", doc: "target solid volume fraction eta (per layer for mcm.stacked)" },
        ParamSpec { name: "contraction_steps", ty: "usize", unit: "1", doc: "initial schedule: beta is reached in this many equal geometric steps; the rate then adapts (x1.25 after success, /2 and retry when stuck)" },
        ParamSpec { name: "min_gap", ty: "Q<Length>", unit: "m", doc: "minimum distance between two grains (Remark 5)" },
        ParamSpec { name: "tolerance", ty: "f64", unit: "1", doc: "overlap tolerance relative to the mean bounding radius; the gap is padded by it so the final gap is at least min_gap" },
        ParamSpec { name: "step_iterations", ty: "usize", unit: "1", doc: "FIRE iterations allowed per contraction step before the step is undone and halved" },
        ParamSpec { name: "max_iterations", ty: "usize", unit: "1", doc: "FIRE iteration limit (per layer for mcm.stacked); reaching it fails the stage" },
    ]
}

fn outputs() -> Vec<PortSpec> {
    vec![
        PortSpec::new("packing", ArtifactKind::Packing, "periodic packing with layer ids (library embedded for clumps)"),
        PortSpec::new("report", ArtifactKind::Table, "per layer: grains, iterations, contraction steps, back-offs, time, final overlap energy, achieved fraction"),
        PortSpec::new("orientation", ArtifactKind::Tensor, "3x3 orientation tensor <n n> of the grains' long axes (smallest principal moment of inertia); 1/3 I for spheres"),
    ]
}

#[allow(clippy::too_many_arguments)]
fn check_common(
    vf: f64,
    beta: f64,
    steps: usize,
    gap: f64,
    tol: f64,
    step_it: usize,
    max_it: usize,
    radius: &SizeDistribution,
) -> Result<(), StageError> {
    if !(vf > 0.0 && vf < 0.74) {
        return Err(StageError::param("volume_fraction", format!("must be in (0, 0.74) (denser than close packing of spheres is impossible), got {vf}")));
    }
    if !(beta.is_finite() && beta > 1.0) {
        return Err(StageError::param(
            "beta",
            format!("enlargement factor must be > 1 (eq. 2.2), got {beta}"),
        ));
    }
    if steps == 0 {
        return Err(StageError::param("contraction_steps", "must be at least 1"));
    }
    if !(gap.is_finite() && gap >= 0.0) {
        return Err(StageError::param(
            "min_gap",
            format!("must be >= 0, got {gap}"),
        ));
    }
    if !(tol > 0.0 && tol < 0.1) {
        return Err(StageError::param(
            "tolerance",
            format!("must be in (0, 0.1), got {tol}"),
        ));
    }
    if step_it == 0 || max_it == 0 {
        return Err(StageError::param(
            "max_iterations",
            "iteration limits must be at least 1",
        ));
    }
    radius
        .validate()
        .map_err(|(k, m)| StageError::param(&format!("radius.{k}"), m))?;
    Ok(())
}

fn schedule(beta: f64, steps: usize, step_it: usize, max_it: usize) -> Schedule {
    let rate0 = beta.powf(1.0 / steps as f64) - 1.0;
    Schedule {
        rate0,
        rate_min: 1e-5,
        rate_max: rate0.max(0.01) * 2.0,
        step_iterations: step_it,
        max_iterations: max_it,
    }
}

/// Remark 1: draw grains (Remark 2) until their volume exceeds `target`, then the linear
/// factor that makes the total exactly `target`.
fn sample_volume(src: &Source, target: f64, seed: u32, order: &[usize]) -> (Vec<Pick>, f64) {
    let mut picks = Vec::new();
    let mut v = 0.0;
    while v < target {
        let p = src.pick(picks.len() as u32, seed, order);
        v += p.volume;
        picks.push(p);
    }
    (picks, (target / v).cbrt())
}

struct Built {
    bodies: Vec<Body>,
    library: Option<ClumpLibrary>,
    axes: Vec<[f64; 3]>,
}

/// Turns the system back into bodies; each (pick, scale) of a library clump becomes one
/// clump of the embedded library.
fn build(sys: &System, src: &Source, picks: &[(Pick, f64, u32)], cell: [f64; 3]) -> Built {
    let mut lib = ClumpLibrary {
        clumps: Vec::new(),
        source: String::new(),
    };
    let mut bodies = Vec::new();
    let mut axes = Vec::new();
    for (g, (p, s, layer)) in sys.grains.iter().zip(picks) {
        let pos: [f64; 3] = [0, 1, 2].map(|a| g.pos[a].rem_euclid(cell[a]));
        let q = g.rot.quaternion();
        let orientation = [q.w, q.i, q.j, q.k];
        let shape = match (src, p.index) {
            (Source::Library(l), Some(i)) => {
                let c = scale_clump(&l.clumps[i], *s);
                let k = c
                    .principal_inertia
                    .iter()
                    .enumerate()
                    .min_by(|a, b| a.1.total_cmp(b.1))
                    .map(|x| x.0)
                    .unwrap_or(0);
                let ax = g.rot * v3(c.principal_axes[k]);
                let n = ax.norm().max(1e-300);
                axes.push([ax.x / n, ax.y / n, ax.z / n]);
                lib.source = l.source.clone();
                lib.clumps.push(c);
                BodyShape::Clump {
                    index: lib.clumps.len() - 1,
                }
            }
            _ => BodyShape::Sphere {
                radius: p.radius * s,
            },
        };
        bodies.push(Body {
            shape,
            position: pos,
            orientation,
            layer: *layer,
            frozen: false,
        });
    }
    Built {
        bodies,
        library: (!lib.clumps.is_empty()).then_some(lib),
        axes,
    }
}

fn orientation_tensor(axes: &[[f64; 3]]) -> Tensor {
    let mut t = vec![0.0; 9];
    if axes.is_empty() {
        // Spheres have no long axis: the isotropic tensor by convention.
        for a in 0..3 {
            t[4 * a] = 1.0 / 3.0;
        }
    } else {
        for n in axes {
            for a in 0..3 {
                for b in 0..3 {
                    t[3 * a + b] += n[a] * n[b] / axes.len() as f64;
                }
            }
        }
    }
    Tensor {
        name: "orientation".into(),
        unit: "1".into(),
        shape: vec![3, 3],
        values: t,
        convention: TensorConvention::Plain,
    }
}

struct Row {
    grains: usize,
    iterations: usize,
    steps: usize,
    backoffs: usize,
    time: f64,
    energy: f64,
    fraction: f64,
}

fn report(rows: &[Row]) -> Table {
    Table::new("mcm")
        .with_i64("layer", "1", (0..rows.len() as i64).collect())
        .with_i64(
            "grains",
            "1",
            rows.iter().map(|r| r.grains as i64).collect(),
        )
        .with_i64(
            "iterations",
            "1",
            rows.iter().map(|r| r.iterations as i64).collect(),
        )
        .with_i64(
            "contraction_steps",
            "1",
            rows.iter().map(|r| r.steps as i64).collect(),
        )
        .with_i64(
            "backoffs",
            "1",
            rows.iter().map(|r| r.backoffs as i64).collect(),
        )
        .with_f64("time", "s", rows.iter().map(|r| r.time).collect())
        .with_f64(
            "overlap_energy",
            "m^2",
            rows.iter().map(|r| r.energy).collect(),
        )
        .with_f64("fraction", "1", rows.iter().map(|r| r.fraction).collect())
}

fn library_input(inputs: &Inputs) -> Result<Option<&ClumpLibrary>, StageError> {
    if !inputs.contains_key("library") {
        return Ok(None);
    }
    let lib = input(inputs, "library", Artifact::as_clump_library)?;
    if lib.clumps.is_empty() {
        return Err(StageError::input("library", "the clump library is empty"));
    }
    Ok(Some(lib))
}

fn mean_bound(shapes: &[Shape]) -> f64 {
    shapes.iter().map(|s| s.bound).sum::<f64>() / shapes.len().max(1) as f64
}

impl TypedStage for Classic {
    type Params = ClassicParams;
    fn info(&self) -> StageInfo {
        let mut params = common_params();
        params.extend([
            ParamSpec { name: "count", ty: "usize", unit: "1", doc: "number of grains N (used when `size` is zero)" },
            ParamSpec { name: "size", ty: "[Q<Length>; 3]", unit: "m", doc: "final cell size; if non-zero, grains are drawn until eta |Y| is exceeded and rescaled to hit it (Remark 1), else the cube holding `count` grains at eta" },
            ParamSpec { name: "beta", ty: "f64", unit: "1", doc: "linear enlargement of the initial cell (eq. 2.2)" },
        ]);
        StageInfo {
            id: "mcm.classic",
            version: "1",
            doc: "Mechanical contraction method: grains placed in a cell enlarged by beta, isotropic contraction steps each followed by overlap removal (FIRE on eq. 2.6 over centroids and orientations), periodic in x, y, z",
            params,
            inputs: vec![PortSpec::optional("library", ArtifactKind::ClumpLibrary, "clumps to pack (drawn by scrambled Sobol sampling on bounding diameter); spheres from `radius` if absent")],
            outputs: outputs(),
        }
    }
    fn preflight(&self, p: &Self::Params, _: &InputMetas) -> Result<Preflight, StageError> {
        check_common(
            p.volume_fraction,
            p.beta,
            p.contraction_steps,
            p.min_gap.si(),
            p.tolerance,
            p.step_iterations,
            p.max_iterations,
            &p.radius,
        )?;
        let sized = p.size.iter().all(|l| l.si() > 0.0);
        if !sized && p.size.iter().any(|l| l.si() != 0.0) {
            return Err(StageError::param(
                "size",
                "give all three lengths > 0, or leave all zero to use `count`",
            ));
        }
        if !sized && !(1..=200_000).contains(&p.count) {
            return Err(StageError::param(
                "count",
                format!("must be in 1..=200000, got {}", p.count),
            ));
        }
        Ok(Preflight::from_info(
            &self.info(),
            (p.count as u64 + 1) * 4096,
        ))
    }
    fn run(
        &self,
        p: &Self::Params,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let t0 = Instant::now();
        let lib = library_input(inputs)?;
        let src = match lib {
            Some(l) => Source::Library(l),
            None => Source::Spheres(&p.radius),
        };
        let order = src.order();
        let seed = grainpipe_core::derive_seed(ctx.seed, b"mcm.sobol") as u32;
        let sized = p.size.iter().all(|l| l.si() > 0.0);
        let (picks, scale, cell) = if sized {
            let cell = p.size.map(|l| l.si());
            let (pk, s) = sample_volume(
                &src,
                p.volume_fraction * cell.iter().product::<f64>(),
                seed,
                &order,
            );
            (pk, s, cell)
        } else {
            let pk: Vec<Pick> = (0..p.count as u32)
                .map(|k| src.pick(k, seed, &order))
                .collect();
            let v: f64 = pk.iter().map(|x| x.volume).sum();
            let l = (v / p.volume_fraction).cbrt();
            (pk, 1.0, [l; 3])
        };
        let mut rng = ctx.rng();
        let shapes: Vec<Shape> = picks.iter().map(|x| src.shape(x, scale)).collect();
        let bmean = mean_bound(&shapes);
        if cell
            .iter()
            .any(|&l| l < 2.0 * shapes.iter().map(|s| s.bound).fold(0.0, f64::max))
        {
            return Err(StageError::param(
                "size",
                "the cell must be at least two largest grain diameters wide",
            ));
        }
        let tol = p.tolerance * bmean;
        let grains: Vec<Grain> = (0..picks.len())
            .map(|i| Grain {
                shape: i,
                pos: v3([0.0; 3]),
                rot: random_rotation(&mut rng),
                frozen: false,
                zbox: None,
            })
            .collect();
        // eq. (2.2): the grains are placed in the cell enlarged by beta.
        let big = cell.map(|l| l * p.beta);
        let mut sys = System::new(shapes, grains, big, p.min_gap.si() + tol, tol);
        for i in 0..sys.grains.len() {
            place(&mut sys, i, &mut rng, PLACE_ATTEMPTS, |r| {
                v3([0, 1, 2].map(|a| uniform(r, 0.0, big[a])))
            });
        }
        let mode = Mode::Isotropic { final_cell: cell };
        let sch = schedule(
            p.beta,
            p.contraction_steps,
            p.step_iterations,
            p.max_iterations,
        );
        let st = contract(&mut sys, &mode, p.beta, &sch, |f| ctx.progress((f * 1000.0) as u64, 1000))
            .map_err(|(st, why, e)| {
                e.unwrap_or_else(|| StageError::failed(format!(
                    "mcm.classic, layer 0: {why}; overlap energy reached {:.3e} m^2 (largest overlap {:.3e} m) after {} iterations, {} contraction steps, {} back-offs",
                    st.energy, st.max_delta, st.iterations, st.steps, st.backoffs
                )))
            })?;
        let tagged: Vec<(Pick, f64, u32)> = picks.iter().map(|x| (*x, scale, 0)).collect();
        let built = build(&sys, &src, &tagged, cell);
        let mut packing = Packing::new(Domain::boxed([0.0; 3], cell, [true; 3]));
        packing.bodies = built.bodies;
        packing.library = built.library;
        let fraction = packing.volume_fraction();
        let rows = [Row {
            grains: picks.len(),
            iterations: st.iterations,
            steps: st.steps,
            backoffs: st.backoffs,
            time: t0.elapsed().as_secs_f64(),
            energy: st.energy,
            fraction,
        }];
        let mut out = Outputs::new();
        out.insert("packing".into(), Artifact::Packing(packing));
        out.insert("report".into(), Artifact::Table(report(&rows)));
        out.insert(
            "orientation".into(),
            Artifact::Tensor(orientation_tensor(&built.axes)),
        );
        Ok(out)
    }
}

impl TypedStage for Stacked {
    type Params = StackedParams;
    fn info(&self) -> StageInfo {
        let mut params = common_params();
        params.extend([
            ParamSpec {
                name: "layers",
                ty: "usize",
                unit: "1",
                doc: "number of layers N_layers",
            },
            ParamSpec {
                name: "layer_size",
                ty: "[Q<Length>; 2]",
                unit: "m",
                doc: "in-plane size Lx, Ly (periodic)",
            },
            ParamSpec {
                name: "layer_thickness",
                ty: "Q<Length>",
                unit: "m",
                doc: "layer thickness, fixed (Remark 1)",
            },
            ParamSpec {
                name: "beta",
                ty: "f64",
                unit: "1",
                doc: "enlargement of each new layer along z only",
            },
            ParamSpec {
                name: "periodic_z",
                ty: "bool",
                unit: "",
                doc: "true (paper, Remark 4): periodic in z too, the layer being packed also meets the image of layer 0 above it; false: free surface above each new layer (as when printing), packing periodic in x, y only, far fewer jams (docs/bench/mcm.md)",
            },
        ]);
        StageInfo {
            id: "mcm.stacked",
            version: "1",
            doc: "Stacked mechanical contraction method (Algorithm 2): layer by layer, x-y periodic, contraction along z only, earlier layers frozen, soft box on the centroids, each layer filled to eta exactly",
            params,
            inputs: vec![PortSpec::optional("library", ArtifactKind::ClumpLibrary, "clumps to pack (scrambled Sobol sampling on bounding diameter, Remark 2); spheres from `radius` if absent")],
            outputs: outputs(),
        }
    }
    fn preflight(&self, p: &Self::Params, _: &InputMetas) -> Result<Preflight, StageError> {
        check_common(
            p.volume_fraction,
            p.beta,
            p.contraction_steps,
            p.min_gap.si(),
            p.tolerance,
            p.step_iterations,
            p.max_iterations,
            &p.radius,
        )?;
        if !(1..=1000).contains(&p.layers) {
            return Err(StageError::param(
                "layers",
                format!("must be in 1..=1000, got {}", p.layers),
            ));
        }
        if p.layer_size
            .iter()
            .any(|l| l.si().is_nan() || l.si() <= 0.0)
        {
            return Err(StageError::param("layer_size", "both lengths must be > 0"));
        }
        if p.layer_thickness.si().is_nan() || p.layer_thickness.si() <= 0.0 {
            return Err(StageError::param("layer_thickness", "must be > 0"));
        }
        Ok(Preflight::from_info(&self.info(), 64 << 20))
    }
    fn run(
        &self,
        p: &Self::Params,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let lib = library_input(inputs)?;
        let src = match lib {
            Some(l) => Source::Library(l),
            None => Source::Spheres(&p.radius),
        };
        let order = src.order();
        let (lx, ly, t) = (
            p.layer_size[0].si(),
            p.layer_size[1].si(),
            p.layer_thickness.si(),
        );
        let mut rng = ctx.rng();
        let mut sys = System::new(Vec::new(), Vec::new(), [lx, ly, t], 0.0, 0.0);
        let mut tagged: Vec<(Pick, f64, u32)> = Vec::new();
        let mut rows = Vec::new();
        let sch = schedule(
            p.beta,
            p.contraction_steps,
            p.step_iterations,
            p.max_iterations,
        );
        for layer in 0..p.layers {
            let t0 = Instant::now();
            let seed =
                grainpipe_core::derive_seed(ctx.seed, format!("mcm.sobol.{layer}").as_bytes())
                    as u32;
            // Remark 1: sample until eta V_layer is exceeded, rescale to hit it.
            let target = p.volume_fraction * lx * ly * t;
            let (picks, s) = sample_volume(&src, target, seed, &order);
            let z0 = layer as f64 * t;
            let first = sys.grains.len();
            // Line 2: freeze the earlier layers.
            for g in &mut sys.grains {
                g.frozen = true;
            }
            let bmean = {
                let b: f64 = picks.iter().map(|pk| src.shape(pk, s).bound).sum();
                (b + sys.shapes.iter().map(|x| x.bound).sum::<f64>())
                    / (picks.len() + sys.shapes.len()) as f64
            };
            let tol = p.tolerance * bmean;
            sys.tol = tol;
            sys.gap = p.min_gap.si() + tol;
            sys.cell[2] = crate::pack::stacked_cell_z(z0 + p.beta * t, t, p.periodic_z);
            for pk in &picks {
                sys.shapes.push(src.shape(pk, s));
                sys.grains.push(Grain {
                    shape: sys.shapes.len() - 1,
                    pos: v3([0.0; 3]),
                    rot: random_rotation(&mut rng),
                    frozen: false,
                    zbox: None,
                });
                let i = sys.grains.len() - 1;
                place(&mut sys, i, &mut rng, PLACE_ATTEMPTS, |r| {
                    v3([
                        uniform(r, 0.0, lx),
                        uniform(r, 0.0, ly),
                        uniform(r, z0, z0 + p.beta * t),
                    ])
                });
                tagged.push((*pk, s, layer as u32));
            }
            if lx.min(ly) < 2.0 * sys.shapes.iter().map(|x| x.bound).fold(0.0, f64::max) {
                return Err(StageError::param(
                    "layer_size",
                    "the layer must be at least two largest grain diameters wide",
                ));
            }
            let mode = Mode::Stacked {
                first,
                z0,
                thickness: t,
                margin: tol,
                periodic_z: p.periodic_z,
            };
            let nl = p.layers as f64;
            let st = contract(&mut sys, &mode, p.beta, &sch, |f| {
                ctx.progress(((layer as f64 + f) / nl * 1000.0) as u64, 1000)
            })
            .map_err(|(st, why, e)| {
                e.unwrap_or_else(|| StageError::failed(format!(
                    "mcm.stacked, layer {layer} of {}: {why}; overlap energy reached {:.3e} m^2 (largest violation {:.3e} m) after {} iterations, {} contraction steps, {} back-offs",
                    p.layers, st.energy, st.max_delta, st.iterations, st.steps, st.backoffs
                )))
            })?;
            let vol: f64 = picks.iter().map(|x| x.volume * s.powi(3)).sum();
            rows.push(Row {
                grains: picks.len(),
                iterations: st.iterations,
                steps: st.steps,
                backoffs: st.backoffs,
                time: t0.elapsed().as_secs_f64(),
                energy: st.energy,
                fraction: vol / (lx * ly * t),
            });
        }
        let cell = [lx, ly, t * p.layers as f64];
        let built = build(&sys, &src, &tagged, cell);
        let mut packing = Packing::new(Domain::boxed([0.0; 3], cell, [true, true, p.periodic_z]));
        packing.bodies = built.bodies;
        packing.library = built.library;
        let mut out = Outputs::new();
        out.insert("packing".into(), Artifact::Packing(packing));
        out.insert("report".into(), Artifact::Table(report(&rows)));
        out.insert(
            "orientation".into(),
            Artifact::Tensor(orientation_tensor(&built.axes)),
        );
        Ok(out)
    }
}
