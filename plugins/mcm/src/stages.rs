//! The stages `mcm.classic` and `mcm.stacked`.

use crate::engine::{EnergyKind, Grain, Minimiser, Relaxation, Shape, System};
use crate::fabric::{
    anisotropy_z, counts, deviator_norm, fabric, histogram, layer_stats, near_pairs, Cell,
    LayerStats, Layering, Spheres,
};
use crate::pack::{
    contract, mean_sphere_volume, place_all, quat, sphere_volume, sphere_volume_range, uniform, v3,
    FailReason, Mode, Outcome, Pick, RunFailure, RunStats, Schedule, Source,
};
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::spatial::random_quaternion;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, Body, BodyShape, ClumpLibrary, Domain,
    InputMetas, Inputs, Outputs, Packing, PortSpec, Preflight, RunContext, StageError, StageInfo,
    Table, Tensor, TensorConvention, TypedStage,
};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;
use std::time::Instant;

/// `mcm.classic`: Williams and Philipse's MCM for clumps (Schneider et al. 2018).
pub struct Classic;
/// `mcm.stacked`: Donval et al.'s stacked MCM (Algorithm 2).
pub struct Stacked;

/// The contraction settings both stages share (their keys sit beside the stage's own).
#[params]
pub struct ContractionParams {
    /// Sphere radius distribution, used when no `library` is connected.
    #[param(default = SizeDistribution::Fixed { value: Q::new(70e-6) })]
    pub radius: SizeDistribution,
    /// Target solid volume fraction eta (per layer for mcm.stacked).
    // Paper, section 2.2: the sand packings are generated at 50 %.
    #[param(default = 0.5)]
    pub volume_fraction: f64,
    /// Initial schedule: beta is reached in this many equal geometric steps; the rate then
    /// adapts (x1.25 after success, /2 and retry when stuck).
    #[param(default = 30)]
    pub contraction_steps: usize,
    /// Overlap tolerance at the final size, relative to the mean bounding radius; the gap is
    /// padded by it so the final gap is at least min_gap (intermediate sizes stop at 1e-2).
    // A small padding matters: it inflates every grain, and with it the fraction to reach
    // (+1.5 % for spheres at 1e-2; BENCHMARKS.md#mcm, issue 20).
    #[param(default = 1e-3)]
    pub tolerance: f64,
    /// Minimiser iterations allowed per contraction step before it is undone, the rate halved
    /// and the jam shaken loose.
    #[param(default = 3000)]
    pub step_iterations: usize,
    /// Minimiser iteration limit (per layer for mcm.stacked); reaching it fails the stage.
    // Paper, section 3.5: maximal iteration count 30 000.
    #[param(default = 30_000)]
    pub max_iterations: usize,
    /// Overlap energy minimised: all_pairs (default) sums 1/2 delta^2 over every overlapping
    /// sphere pair (smooth); max_pair is eq. (2.4)-(2.6) as written, only the deepest sphere
    /// pair of each grain pair. Both are zero exactly when nothing overlaps.
    #[param(default = Relaxation::default().energy)]
    pub energy: EnergyKind,
    /// fire (default, Bitzek et al. 2006) or the paper's fixed-step gradient descent,
    /// eq. (2.8).
    #[param(default = Relaxation::default().minimiser)]
    pub minimiser: Minimiser,
    /// A layer (the packing, for mcm.classic) that fails within max_iterations is placed
    /// afresh and packed again, up to this many times, each try with its own max_iterations
    /// (paper, section 3.5, counts such tries); the report gives the tries.
    #[param(default = 2)]
    pub restarts: usize,
    /// When a contraction step gets stuck: true (default) re-expands 2 %, shakes the grains
    /// around the worst overlap and relocates that grain before retrying; false only undoes
    /// the step and halves the rate (the plain contraction path).
    #[param(default = true)]
    pub shake: bool,
    /// gradient_descent only: h_c and h_R of eq. (2.8) (paper: 0.1, 0.4); rotation steps in
    /// units of the grain's bounding radius.
    #[param(default = Relaxation::default().step_sizes)]
    pub step_sizes: [f64; 2],
    /// Microstructure statistics (report columns): two grains are in near-contact when their
    /// gap (closest sphere surfaces, periodic images included) is at most min_gap plus this.
    // 1 um: the minimiser leaves pairs it pushed apart within tolerance x mean bounding
    // radius (about 0.1 um for the sand) of min_gap, so a tolerance must exceed that; 1 um is
    // ten times more, 1/8 of the paper's 8 um gap and a quarter of the finest voxel the
    // pipelines use (4 um), so a pair within it is, in any image made of the packing, as
    // close as a pair at the gap (issue 31).
    #[param(default = Q::new(1e-6))]
    pub contact_tolerance: Q<Length>,
    /// Microstructure statistics: grains whose gap is at most this count as bridged (the
    /// report's bridges per grain).
    // 11 um: two surfaces a gap g apart get a level-set binder bridge when g <= 2 a ln 2
    // (LSE_a of two equal distances g/2 is g/2 - a ln 2); binder.levelset at the shipped 2 %
    // binder over grains finds a = 7.7 um on the paper's stacked packing (docs/stages/binder.md),
    // 2 a ln 2 = 10.7 um.
    #[param(default = Q::new(11e-6))]
    pub bridge_distance: Q<Length>,
}

#[params]
pub struct ClassicParams {
    #[param(flatten)]
    pub contraction: ContractionParams,
    /// Minimum distance between two grains (Remark 5).
    #[param(default = Q::new(0.0))]
    pub min_gap: Q<Length>,
    /// Number of grains N (used when `size` is zero).
    #[param(default = 200)]
    pub count: usize,
    /// Final cell size; if non-zero, grains are drawn until eta |Y| is exceeded and rescaled
    /// to hit it (Remark 1), else the cube holding `count` grains at eta.
    #[param(default = [Q::new(0.0); 3])]
    pub size: [Q<Length>; 3],
    /// Linear enlargement of the initial cell (eq. 2.2).
    #[param(default = 2.0)]
    pub beta: f64,
    /// Thermalisation of a stuck contraction step before it is undone: Langevin dynamics on
    /// the overlap energy at the step's size for this many steps (0: off), the temperature
    /// falling to zero, then overlap removal; lets a jammed quench rearrange into a denser,
    /// overlap-free packing (random close packing of spheres needs it). Counted in
    /// max_iterations.
    // 2000 steps at 0.05 reach 0.64 with equal spheres in the fewest iterations among
    // 500-3000 steps and 0.02-0.12 (BENCHMARKS.md, classic MCM towards random close packing).
    #[param(default = 2000)]
    pub anneal_steps: usize,
    /// Starting thermal amplitude of a thermalisation: the square root of the temperature,
    /// i.e. the typical thermal overlap, in mean bounding radii.
    #[param(default = 0.05)]
    pub anneal_amplitude: f64,
    /// Thermalisation cycles per stuck contraction step before it is undone (and shaken).
    #[param(default = 2)]
    pub anneal_cycles: usize,
}

#[params]
pub struct StackedParams {
    #[param(flatten)]
    pub contraction: ContractionParams,
    /// Minimum distance between two grains (Remark 5).
    // Paper, section 3.5: two layers of (560 um)^2 x 280 um at 50 %, gap 8 um.
    #[param(default = Q::new(8e-6))]
    pub min_gap: Q<Length>,
    /// Number of layers N_layers.
    #[param(default = 2)]
    pub layers: usize,
    /// In-plane size Lx, Ly (periodic).
    #[param(default = [Q::new(560e-6), Q::new(560e-6)])]
    pub layer_size: [Q<Length>; 2],
    /// Layer thickness, fixed (Remark 1).
    #[param(default = Q::new(280e-6))]
    pub layer_thickness: Q<Length>,
    /// Enlargement of each new layer along z only.
    #[param(default = 3.0)]
    pub beta: f64,
    /// true (paper, Remark 4): periodic in z too, the layer being packed also meets the image
    /// of layer 0 above it; false: free surface above each new layer (as when printing),
    /// packing periodic in x, y only (fewer jams, faster; BENCHMARKS.md#mcm).
    #[param(default = true)]
    pub periodic_z: bool,
    /// After the first stuck contraction step of a layer, free the grains of earlier layers
    /// that it touches so they can move with it (true, default: fewer jams); false keeps
    /// earlier layers frozen as in Algorithm 2 (line 2), so a jam is only undone, shaken or
    /// thermalised within the layer (pipelines/sandcore-paper.yaml).
    // Released packings end with fewer near-contacts per grain and were about half as stiff
    // (issue 31); the stage warns whenever it happens.
    #[param(default = true)]
    pub release: bool,
    /// A layer that jammed is placed again with its grains lying flatter on each retry (true,
    /// default: best of 4, then 16 random orientations by extent along z; fewer jams on
    /// elongated grains); false places every try with the paper's uniform orientations.
    // Flatter retries change the orientation fabric and with it the anisotropy (issue 31).
    #[param(default = true)]
    pub flatter_retries: bool,
    /// Tries of each layer with Algorithm 2 as published (earlier layers frozen, no
    /// thermalisation or shaking, uniform orientations) before the fallbacks above are used:
    /// 0 (default) uses them from the first try; n > 0 packs a layer plainly up to n times and
    /// only a layer that jammed on every plain try goes on with `restarts` + 1 tries with the
    /// fallbacks (warned, with the near-contacts it ends with). The paper's protocol, for
    /// grains that pack plainly and spheres that do not (pipelines/sandcore-paper.yaml).
    #[param(default = 0)]
    pub plain_tries: usize,
    /// Thermalisation of a stuck contraction step before it is undone: Langevin dynamics on
    /// the overlap energy at the step's size for this many steps (0: off), the temperature
    /// falling to zero, then overlap removal; lets a jammed quench rearrange into a denser,
    /// overlap-free packing (random close packing of spheres needs it). Counted in
    /// max_iterations.
    // 1000 steps at 0.03 with one cycle: on elongated grains nearly as long as the layer is
    // thick, a quench jams a few per cent above the final size on every try and only a
    // rearrangement gets past it; the shipped sand also needs fewer iterations with it
    // (BENCHMARKS.md, robustness on harder grain families).
    #[param(default = 1000)]
    pub anneal_steps: usize,
    /// Starting thermal amplitude of a thermalisation: the square root of the temperature,
    /// i.e. the typical thermal overlap, in mean bounding radii.
    #[param(default = 0.03)]
    pub anneal_amplitude: f64,
    /// Thermalisation cycles per stuck contraction step before it is undone (and shaken).
    #[param(default = 1)]
    pub anneal_cycles: usize,
}

impl ContractionParams {
    fn relaxation(&self) -> Relaxation {
        Relaxation {
            energy: self.energy,
            minimiser: self.minimiser,
            step_sizes: self.step_sizes,
        }
    }

    /// Checks the shared settings and the stage's `beta` and `min_gap` [m].
    fn check(&self, beta: f64, min_gap: f64) -> Result<(), StageError> {
        let vf = self.volume_fraction;
        if !(vf > 0.0 && vf < 0.74) {
            return Err(StageError::param("volume_fraction", format!("must be in (0, 0.74) (denser than close packing of spheres is impossible), got {vf}")));
        }
        if !(beta.is_finite() && beta > 1.0) {
            return Err(StageError::param(
                "beta",
                format!("enlargement factor must be > 1 (eq. 2.2), got {beta}"),
            ));
        }
        if self.contraction_steps == 0 {
            return Err(StageError::param("contraction_steps", "must be at least 1"));
        }
        if !(min_gap.is_finite() && min_gap >= 0.0) {
            return Err(StageError::param(
                "min_gap",
                format!("must be >= 0, got {min_gap}"),
            ));
        }
        if !(self.tolerance > 0.0 && self.tolerance < 0.1) {
            return Err(StageError::param(
                "tolerance",
                format!("must be in (0, 0.1), got {}", self.tolerance),
            ));
        }
        if self.step_iterations == 0 || self.max_iterations == 0 {
            return Err(StageError::param(
                "max_iterations",
                "iteration limits must be at least 1",
            ));
        }
        let [h_c, h_r] = self.step_sizes;
        if !(h_c > 0.0 && h_c <= 1.0 && h_r > 0.0 && h_r <= 1.0) {
            return Err(StageError::param(
                "step_sizes",
                format!(
                    "h_c and h_R must be in (0, 1] (larger steps overshoot), got [{h_c}, {h_r}]"
                ),
            ));
        }
        self.radius
            .validate()
            .map_err(|(k, m)| StageError::param(&format!("radius.{k}"), m))?;
        let tol = self.contact_tolerance.si();
        if !(tol.is_finite() && tol >= 0.0) {
            return Err(StageError::param(
                "contact_tolerance",
                format!("must be a length >= 0, got {tol} m"),
            ));
        }
        let bridge = self.bridge_distance.si();
        if !(bridge.is_finite() && bridge >= 0.0) {
            return Err(StageError::param(
                "bridge_distance",
                format!("must be a length >= 0, got {bridge} m"),
            ));
        }
        // The neighbour search reaches this far: like min_gap, a bare number is metres.
        if let Some(l) = [tol, bridge].into_iter().find(|&x| x >= 1e-2) {
            return Err(StageError::param(
                if l == tol {
                    "contact_tolerance"
                } else {
                    "bridge_distance"
                },
                format!(
                    "{} is not a gap between grains (a bare number is metres; write e.g. `11 um`)",
                    fmt_len(l)
                ),
            ));
        }
        Ok(())
    }

    /// The contraction schedule from `beta` down to 1.
    fn schedule(
        &self,
        beta: f64,
        anneal: (usize, f64, usize),
        [release, flatter_retries]: [bool; 2],
        plain_tries: usize,
    ) -> Schedule {
        let rate0 = beta.powf(1.0 / self.contraction_steps as f64) - 1.0;
        Schedule {
            rate0,
            rate_min: 1e-5,
            rate_max: rate0.max(0.01) * 2.0,
            step_iterations: self.step_iterations,
            max_iterations: self.max_iterations,
            shake: self.shake,
            loose: crate::pack::LOOSE_TOLERANCE / self.tolerance,
            anneal_steps: anneal.0,
            anneal_amplitude: anneal.1,
            anneal_cycles: anneal.2,
            release,
            flatter_retries,
            plain_tries,
        }
    }
}

/// The thermalisation's amplitude: a fraction of a bounding radius (larger kicks would only
/// re-expand the packing they are meant to rearrange).
fn check_anneal(amp: f64) -> Result<(), StageError> {
    if !(amp.is_finite() && (0.0..=0.5).contains(&amp)) {
        return Err(StageError::param(
            "anneal_amplitude",
            format!("must be in [0, 0.5] mean bounding radii, got {amp}"),
        ));
    }
    Ok(())
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
                let c = l.clumps[i].scaled(*s);
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
    tries: usize,
    stats: RunStats,
    time: f64,
    fraction: f64,
    /// Earlier layers whose grains this layer released (sorted, stacked only).
    released_layers: Vec<usize>,
}

/// The microstructure statistics of a finished packing (issue 31): near pairs within reach
/// of either threshold, per-layer statistics, the whole packing's contact fabric and the
/// per-layer mean <n_z n_z> of the grains' long axes.
struct Micro {
    layers: Vec<LayerStats>,
    fabric: Option<[f64; 9]>,
    orientation_zz: Vec<f64>,
    /// Near-contact threshold min_gap + contact_tolerance [m].
    contact: f64,
    bridge: f64,
    histogram: (Vec<u64>, Vec<u64>),
}

fn microstructure(
    packing: &Packing,
    axes: &[[f64; 3]],
    layers: usize,
    thickness: f64,
    min_gap: f64,
    c: &ContractionParams,
) -> Micro {
    let ws = packing.world_spheres();
    let centres: Vec<[f64; 3]> = ws.iter().map(|w| w.center).collect();
    let radii: Vec<f64> = ws.iter().map(|w| w.radius).collect();
    let body: Vec<u32> = ws.iter().map(|w| w.body as u32).collect();
    let d = &packing.domain;
    let cell = Cell {
        min: d.min,
        len: d.size(),
        periodic: d.periodic,
    };
    let contact = min_gap + c.contact_tolerance.si();
    let bridge = c.bridge_distance.si();
    let pairs = near_pairs(
        Spheres {
            centres: &centres,
            radii: &radii,
            body: &body,
        },
        cell,
        contact.max(bridge),
    );
    let layer: Vec<u32> = packing.bodies.iter().map(|b| b.layer).collect();
    let per_layer = layer_stats(
        &pairs,
        Layering {
            layer: &layer,
            layers,
            z_min: d.min[2],
            thickness,
            periodic_z: d.periodic[2],
        },
        contact,
        bridge,
    );
    let n = packing.bodies.len();
    let orientation_zz = (0..layers)
        .map(|l| {
            let zz: Vec<f64> = (0..axes.len().min(n))
                .filter(|&b| layer[b] as usize == l)
                .map(|b| axes[b][2] * axes[b][2])
                .collect();
            if axes.is_empty() {
                1.0 / 3.0
            } else if zz.is_empty() {
                f64::NAN
            } else {
                zz.iter().sum::<f64>() / zz.len() as f64
            }
        })
        .collect();
    Micro {
        layers: per_layer,
        fabric: fabric(pairs.iter().filter(|p| p.gap <= contact).map(|p| &p.normal)),
        orientation_zz,
        contact,
        bridge,
        histogram: (
            histogram(counts(&pairs, n, contact)),
            histogram(counts(&pairs, n, bridge)),
        ),
    }
}

/// A histogram as text: the counts for 0, 1, 2, ... separated by spaces.
fn histogram_text(h: &[u64]) -> String {
    h.iter()
        .map(|x| x.to_string())
        .collect::<Vec<_>>()
        .join(" ")
}

fn report(rows: &[Row], m: &Micro) -> Table {
    let ints = |f: fn(&Row) -> usize| rows.iter().map(|r| f(r) as i64).collect();
    let per = |f: &dyn Fn(&LayerStats) -> f64| m.layers.iter().map(f).collect::<Vec<f64>>();
    let of = |t: &Option<[f64; 9]>, f: fn(&[f64; 9]) -> f64| t.as_ref().map_or(f64::NAN, f);
    Table::new("mcm")
        .with_i64("layer", "1", (0..rows.len() as i64).collect())
        .with_i64("grains", "1", ints(|r| r.grains))
        .with_i64("tries", "1", ints(|r| r.tries))
        .with_i64("iterations", "1", ints(|r| r.stats.iterations))
        .with_i64("contraction_steps", "1", ints(|r| r.stats.steps))
        .with_i64("backoffs", "1", ints(|r| r.stats.backoffs))
        .with_i64("shakes", "1", ints(|r| r.stats.shakes))
        .with_i64("released", "1", ints(|r| r.stats.released))
        .with_f64("time", "s", rows.iter().map(|r| r.time).collect())
        .with_f64(
            "overlap_energy",
            "m^2",
            rows.iter().map(|r| r.stats.energy).collect(),
        )
        .with_f64(
            "max_violation",
            "m",
            rows.iter().map(|r| r.stats.max_delta).collect(),
        )
        .with_f64("fraction", "1", rows.iter().map(|r| r.fraction).collect())
        .with_f64("near_contacts_per_grain", "1", per(&|l| l.near_per_grain))
        .with_str(
            "near_contact_histogram",
            m.layers
                .iter()
                .map(|l| histogram_text(&l.near_histogram))
                .collect(),
        )
        .with_f64("bridges_per_grain", "1", per(&|l| l.bridges_per_grain))
        .with_str(
            "bridge_histogram",
            m.layers
                .iter()
                .map(|l| histogram_text(&l.bridge_histogram))
                .collect(),
        )
        .with_i64(
            "layer_contacts",
            "1",
            m.layers.iter().map(|l| l.contacts as i64).collect(),
        )
        .with_f64("fabric_xx", "1", per(&|l| of(&l.fabric, |t| t[0])))
        .with_f64("fabric_yy", "1", per(&|l| of(&l.fabric, |t| t[4])))
        .with_f64("fabric_zz", "1", per(&|l| of(&l.fabric, |t| t[8])))
        .with_f64(
            "fabric_anisotropy_z",
            "1",
            per(&|l| of(&l.fabric, anisotropy_z)),
        )
        .with_f64(
            "fabric_deviator",
            "1",
            per(&|l| of(&l.fabric, deviator_norm)),
        )
        .with_i64(
            "interface_contacts",
            "1",
            m.layers
                .iter()
                .map(|l| l.interface_contacts as i64)
                .collect(),
        )
        .with_f64(
            "interface_fabric_zz",
            "1",
            per(&|l| of(&l.interface_fabric, |t| t[8])),
        )
        .with_f64(
            "interface_anisotropy_z",
            "1",
            per(&|l| of(&l.interface_fabric, anisotropy_z)),
        )
        .with_f64("orientation_zz", "1", m.orientation_zz.clone())
}

/// The whole packing's distribution of near-contacts and bridges per grain: one row per
/// count k = 0, 1, ... with the grains having exactly k of each.
fn contacts_table(m: &Micro) -> Table {
    let (near, bridges) = &m.histogram;
    let k = near.len().max(bridges.len()).max(1);
    let col = |h: &[u64]| (0..k).map(|i| *h.get(i).unwrap_or(&0) as i64).collect();
    Table::new("mcm_contacts")
        .with_i64("contacts", "1", (0..k as i64).collect())
        .with_i64("near_contact_grains", "1", col(near))
        .with_i64("bridge_grains", "1", col(bridges))
}

fn fabric_tensor(m: &Micro) -> Tensor {
    Tensor {
        name: "contact_fabric".into(),
        unit: "1".into(),
        shape: vec![3, 3],
        // No near-contact at all: NaN (an empty average), not a made-up isotropic tensor.
        values: m.fabric.map_or(vec![f64::NAN; 9], |t| t.to_vec()),
        convention: TensorConvention::Plain,
    }
}

/// Names the paths beyond Algorithm 2 a layer took (empty: none).
fn fallbacks(r: &Row) -> Vec<String> {
    let mut v = Vec::new();
    if r.tries > 1 {
        v.push(format!(
            "{} restart{} (placed afresh)",
            r.tries - 1,
            if r.tries == 2 { "" } else { "s" }
        ));
    }
    if r.stats.released > 0 {
        v.push(format!(
            "{} grains of earlier layers released",
            r.stats.released
        ));
    }
    let annealed = r
        .stats
        .history
        .iter()
        .filter(|h| matches!(h.outcome, Outcome::Annealed | Outcome::AnnealFailed))
        .count();
    if annealed > 0 {
        v.push(format!(
            "{annealed} thermalisation{} of stuck steps",
            if annealed == 1 { "" } else { "s" }
        ));
    }
    if r.stats.shakes > 0 {
        v.push(format!(
            "{} shake{}",
            r.stats.shakes,
            if r.stats.shakes == 1 { "" } else { "s" }
        ));
    }
    v
}

/// Near-contacts per grain of the shipped sand packed without any fallback in the paper's
/// setting (pipelines/mcm.yaml: two (560 um)^2 x 280 um layers at 50 %, 8 um gap, periodic
/// in x, y, z; gap <= 9 um): seeds 1, 2 and 8 of 1-8, the three that took no fallback, give
/// 6.52 and 6.69, 6.60 and 6.56, 6.94 and 6.32 per layer, mean 6.60. The five others
/// released the first layer's grains when packing the second: 2.10-3.81 in both layers.
const TYPICAL_SAND_NEAR_CONTACTS: f64 = 6.6;

/// "No silent outliers" (issue 31): one warning per layer that took a path beyond
/// Algorithm 2, with its near-contacts per grain (and those of the earlier layers whose
/// grains it released and moved) next to the layers of the same run that neither took one
/// nor were moved by one (grain-weighted mean), or, when there is none, next to the value
/// of the shipped sand packed without fallbacks.
fn warn_fallbacks(ctx: &RunContext, what: &str, rows: &[Row], m: &Micro) {
    let paths: Vec<Vec<String>> = rows.iter().map(fallbacks).collect();
    let moved: Vec<bool> = (0..rows.len())
        .map(|l| rows.iter().any(|r| r.released_layers.contains(&l)))
        .collect();
    let clean: Vec<usize> = (0..rows.len())
        .filter(|&l| paths[l].is_empty() && !moved[l])
        .collect();
    let mean_over = |ls: &[usize]| {
        let g: usize = ls.iter().map(|&l| m.layers[l].grains).sum();
        (g > 0).then(|| {
            ls.iter()
                .map(|&l| m.layers[l].near_per_grain * m.layers[l].grains as f64)
                .sum::<f64>()
                / g as f64
        })
    };
    let list = |ls: &[usize]| {
        ls.iter()
            .map(|l| l.to_string())
            .collect::<Vec<_>>()
            .join(", ")
    };
    for (l, p) in paths.iter().enumerate() {
        if p.is_empty() {
            continue;
        }
        let layer = if rows.len() > 1 {
            format!("{what}, layer {l}")
        } else {
            what.to_string()
        };
        let others: Vec<usize> = rows[l]
            .released_layers
            .iter()
            .copied()
            .filter(|&k| k != l)
            .collect();
        let moved_too = match mean_over(&others) {
            Some(x) => format!(
                "; the earlier layer{} whose grains it released and moved ({}) end{} with {x:.2}",
                if others.len() == 1 { "" } else { "s" },
                list(&others),
                if others.len() == 1 { "s" } else { "" },
            ),
            None => String::new(),
        };
        let versus = match mean_over(&clean) {
            Some(x) => format!(
                "against {x:.2} in the layer{} of this run that neither took a fallback nor \
                 had grains moved by one ({})",
                if clean.len() == 1 { "" } else { "s" },
                list(&clean)
            ),
            None => format!(
                "and no layer of this run is free of fallbacks to compare with; the shipped sand \
                 in the paper's setting (pipelines/mcm.yaml) packed without fallbacks has \
                 {TYPICAL_SAND_NEAR_CONTACTS:.1} near-contacts per grain, with them 2.1-3.8 \
                 (docs/stages/mcm.md, microstructure statistics; other grains and fractions differ)"
            ),
        };
        ctx.warn(&format!(
            "{layer} took paths beyond the paper's Algorithm 2 ({}): its grains end with {:.2} \
             near-contacts per grain (gap <= {:.2} um = min_gap + contact_tolerance) and {:.2} \
             within the bridge distance {:.2} um{moved_too}, {versus}. Fewer near-contacts mean \
             a looser contact network (issue 31: such packings were about half as stiff); the \
             report's microstructure columns give the details",
            p.join(", "),
            m.layers[l].near_per_grain,
            m.contact * 1e6,
            m.layers[l].bridges_per_grain,
            m.bridge * 1e6,
        ));
    }
}

/// Convergence history: one row per overlap-removal phase of every layer.
fn history(rows: &[Row]) -> Table {
    let phases: Vec<(usize, &crate::pack::Phase)> = rows
        .iter()
        .enumerate()
        .flat_map(|(l, r)| r.stats.history.iter().map(move |h| (l, h)))
        .collect();
    Table::new("mcm_history")
        .with_i64("layer", "1", phases.iter().map(|p| p.0 as i64).collect())
        .with_f64("scale", "1", phases.iter().map(|p| p.1.scale).collect())
        .with_i64(
            "iterations",
            "1",
            phases.iter().map(|p| p.1.iterations as i64).collect(),
        )
        .with_f64(
            "overlap_energy",
            "m^2",
            phases.iter().map(|p| p.1.energy).collect(),
        )
        .with_f64(
            "max_violation",
            "m",
            phases.iter().map(|p| p.1.max_violation).collect(),
        )
        .with_str(
            "outcome",
            phases
                .iter()
                .map(|p| p.1.outcome.name().to_string())
                .collect(),
        )
}

/// `contract`, and after a failed try (not a cancellation) `replace` followed by another
/// try: first up to `sch.plain_tries` tries with Algorithm 2 as published
/// (`Schedule::plain`), then up to `restarts` + 1 with the schedule's fallbacks; `replace`
/// gets the orientation draws of the new try's placement (see `retry_flat_draws`).
/// Ok = (stats, tries); Err = (tries, the last failure).
#[allow(clippy::too_many_arguments)]
fn contract_with_restarts(
    sys: &mut System,
    mode: &Mode,
    beta: f64,
    sch: &Schedule,
    restarts: usize,
    rng: &mut ChaCha8Rng,
    ctx: &RunContext,
    what: &str,
    mut progress: impl FnMut(f64) -> Result<(), StageError>,
    mut replace: impl FnMut(&mut System, &mut ChaCha8Rng, usize),
) -> Result<(RunStats, usize), (usize, Box<RunFailure>)> {
    let mut tries = 1;
    // mcm.classic's schedule has no plain tries and no flatter retries.
    let plain_tries = sch.plain_tries;
    let total = plain_tries + restarts + 1;
    let plain = sch.plain();
    // Shakes re-expand the cell and a restart begins at beta again, so the contraction's own
    // fraction can fall; reports give the furthest fraction reached so a bar never goes back.
    let mut furthest = 0.0f64;
    let mut monotonic = |f: f64| {
        furthest = furthest.max(f);
        progress(furthest)
    };
    loop {
        let this = if tries <= plain_tries { &plain } else { sch };
        match contract(sys, mode, beta, this, rng, &mut monotonic) {
            Ok(st) => return Ok((st, tries)),
            Err(f) if tries < total && !matches!(f.reason, FailReason::Cancelled(_)) => {
                // Stacked retries with fallbacks lie flatter (`retry_flat_draws`, counted
                // from the first try with fallbacks): the placement and the warning take the
                // draws from here, the orientation statistics of the layer depend on them.
                let next_plain = tries < plain_tries;
                let flat_draws = if sch.flatter_retries && !next_plain {
                    retry_flat_draws(tries + 1 - plain_tries)
                } else {
                    1
                };
                let flatter = if flat_draws > 1 {
                    format!(
                        ", lying flatter (of {flat_draws} random orientations each, the one \
                         with the smallest extent along z)"
                    )
                } else {
                    String::new()
                };
                let fallbacks = if tries == plain_tries {
                    format!(
                        "; all {plain_tries} tries of Algorithm 2 as published jammed, the \
                         next use the fallbacks (release {}, thermalisation {}, shaking {})",
                        if sch.release { "on" } else { "off" },
                        if sch.anneal_steps > 0 { "on" } else { "off" },
                        if sch.shake { "on" } else { "off" },
                    )
                } else {
                    String::new()
                };
                ctx.warn(&format!(
                    "{what}: try {tries} failed ({}){fallbacks}; placing the grains \
                     afresh{flatter} and contracting again from scale {beta} (try {} of {}; \
                     progress resumes once the new try passes the furthest point reached)",
                    f.reason,
                    tries + 1,
                    total
                ));
                tries += 1;
                replace(sys, rng, flat_draws);
            }
            Err(f) => return Err((tries, f)),
        }
    }
}

/// Orientation draws (see [`crate::pack::draw_orientation`]) of the placement of a stacked
/// layer's try `try_no` (1-based): the first try is the paper's isotropic draw; a layer that
/// jammed is placed again with grains lying flatter on each retry (best of 4, then 16 draws
/// by extent along z), since grains standing upright are what a contraction along z cannot
/// resolve (BENCHMARKS.md, robustness on harder grain families).
pub fn retry_flat_draws(try_no: usize) -> usize {
    1 << (2 * try_no.saturating_sub(1)).min(4)
}

/// The stage error for a contraction run that did not reach the final size.
fn run_failed(stage: &str, layer: usize, layers: usize, tries: usize, f: RunFailure) -> StageError {
    let RunFailure { stats: st, reason } = f;
    if let FailReason::Cancelled(e) = reason {
        return e;
    }
    StageError::failed(format!(
        "{stage}, layer {layer} of {layers}, try {tries} of {tries}: {}; overlap energy reached {:.3e} m^2, largest violation {:.3e} m ({}), after {} iterations, {} contraction steps, {} back-offs, {} shakes. Lower volume_fraction or min_gap, or raise max_iterations",
        reason, st.energy, st.max_delta, st.worst, st.iterations, st.steps, st.backoffs, st.shakes
    ))
}

fn outputs_of(rows: &[Row], packing: Packing, axes: &[[f64; 3]], m: &Micro) -> Outputs {
    let mut out = Outputs::new();
    out.insert("packing".into(), Artifact::Packing(packing));
    out.insert("report".into(), Artifact::Table(report(rows, m)));
    out.insert("history".into(), Artifact::Table(history(rows)));
    out.insert(
        "orientation".into(),
        Artifact::Tensor(orientation_tensor(axes)),
    );
    out.insert("contact_fabric".into(), Artifact::Tensor(fabric_tensor(m)));
    out.insert("contacts".into(), Artifact::Table(contacts_table(m)));
    out
}

/// The connected clump library, else spheres from `radius`.
fn grain_source<'a>(
    inputs: &'a Inputs,
    radius: &'a SizeDistribution,
) -> Result<Source<'a>, StageError> {
    if !inputs.contains_key("library") {
        return Ok(Source::Spheres(radius));
    }
    let lib = input(inputs, "library", Artifact::as_clump_library)?;
    if lib.clumps.is_empty() {
        return Err(StageError::input("library", "the clump library is empty"));
    }
    Ok(Source::Library(lib))
}

/// A grain whose bounding diameter plus the gap exceeds the periodic cell could touch its
/// own image (Remark 4 with Remark 5); refused before anything is placed.
fn check_fits(key: &str, width: f64, gap: f64, shapes: &[Shape]) -> Result<(), StageError> {
    let widest = 2.0 * shapes.iter().map(|s| s.bound).fold(0.0, f64::max);
    if width < widest + gap {
        return Err(StageError::param(
            key,
            format!(
                "a drawn grain's bounding diameter ({:.1} um) plus min_gap ({:.1} um) exceeds the cell width ({:.1} um): it would come closer than min_gap to its own periodic image; enlarge the cell, lower min_gap or cap the library (clumps.library max_bounding_diameter)",
                widest * 1e6,
                gap * 1e6,
                width * 1e6
            ),
        ));
    }
    Ok(())
}

/// Directions over a hemisphere (Fibonacci lattice) for the thinnest width of a grain.
const WIDTH_DIRECTIONS: usize = 400;

/// The thinnest width of a shape over `WIDTH_DIRECTIONS` directions, less a bound on the
/// error of the sampling (the width is within bound * spacing^2 of its minimum near it), so
/// it never exceeds the true thinnest width by more than rounding.
fn thinnest_width(s: &Shape) -> f64 {
    let m = WIDTH_DIRECTIONS;
    let golden = PI * (3.0 - 5f64.sqrt());
    let w = (0..m)
        .map(|k| {
            let z = 1.0 - (k as f64 + 0.5) / m as f64; // upper hemisphere suffices: w(n) = w(-n)
            let rho = (1.0 - z * z).sqrt();
            let phi = golden * k as f64;
            crate::pack::width_along(
                s,
                nalgebra::Vector3::new(rho * phi.cos(), rho * phi.sin(), z),
            )
        })
        .fold(f64::INFINITY, f64::min);
    // Mean spacing of m points on a hemisphere (area 2 pi): sqrt(2 pi / m).
    let spacing = (2.0 * PI / m as f64).sqrt();
    (w - s.bound * spacing * spacing).max(0.0)
}

/// With `periodic_z`, a grain in the first layer meets its own image one layer thickness
/// above: it fits only if it can lie with its thinnest width plus min_gap within the layer.
fn check_thickness(t: f64, gap: f64, shapes: &[Shape]) -> Result<(), StageError> {
    let (k, w) = shapes
        .iter()
        .map(thinnest_width)
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap_or((0, 0.0));
    if w + gap > t {
        return Err(StageError::param(
            "layer_thickness",
            format!(
                "grain {k} of the layer is {:.1} um thick at its thinnest (bounding diameter {:.1} um); with min_gap {:.1} um it cannot fit a {:.1} um layer that is periodic in z (it would touch its own image one layer above). Raise layer_thickness to at least {:.1} um, cap the grains (clumps.library max_bounding_diameter), or use periodic_z: false",
                w * 1e6,
                2e6 * shapes[k].bound,
                gap * 1e6,
                t * 1e6,
                (w + gap) * 1e6 * 1.05
            ),
        ));
    }
    Ok(())
}

/// Kepler's bound: no packing of equal or unequal spheres is denser than pi / sqrt(18).
const KEPLER: f64 = 0.7405;

/// Refuses at preflight a `min_gap` that cannot fit:
/// - against the cell (and the layer): every grain keeps min_gap from its own periodic
///   images, so min_gap must be below half the cell width (a bare number is metres: `8` is
///   8 m, which also makes the neighbour search walk (2 cut / cell + 1)^3 periodic images);
/// - against the grains: each grain keeps min_gap / 2 of clearance all round, so its padded
///   volume is at least that of its volume-equivalent sphere grown by min_gap / 2 (the sphere
///   has the least surface for its volume). If the padded grains would fill more than
///   Kepler's 0.7405 (spheres) or the whole cell (clumps), no packing exists;
/// - with `periodic_z`, against the layer thickness: a grain of the mean diameter plus the
///   gap must fit the thickness (exactly per grain, with its thinnest width, at run time).
fn check_gap(
    gap: f64,
    grains: &GrainSizes,
    c: &ContractionParams,
    cell_min: Option<f64>,
    layer: Option<(f64, bool)>,
) -> Result<(), StageError> {
    let key = "min_gap";
    if let Some(l) = cell_min {
        if gap >= 0.5 * l {
            return Err(StageError::param(
                key,
                format!(
                    "{} is at least half the cell width ({}): each grain would have to keep it from its own periodic images. A gap is a small clearance (Remark 5: typically the voxel size, e.g. `8 um`; a bare number is metres)",
                    fmt_len(gap),
                    fmt_len(l)
                ),
            ));
        }
    }
    if let Some((t, _)) = layer {
        if gap >= 0.5 * t {
            return Err(StageError::param(
                key,
                format!(
                    "{} is at least half the layer thickness ({}): a gap is a small clearance (Remark 5: typically the voxel size, e.g. `8 um`; a bare number is metres)",
                    fmt_len(gap),
                    fmt_len(t)
                ),
            ));
        }
    }
    let vf = c.volume_fraction;
    // Padded fraction from the volume-equivalent diameters (spheres: the law itself).
    let (padded, d, limit, what) = match (&grains.diameter, grains.volume_range) {
        (Some(_), Some(_)) => {
            let n = 1024;
            let (mut v, mut vp) = (0.0, 0.0);
            for i in 0..n {
                let r = c.radius.quantile((i as f64 + 0.5) / n as f64);
                v += r.powi(3);
                vp += (r + 0.5 * gap).powi(3);
            }
            (
                vf * vp / v,
                2.0 * c.radius.mean(),
                KEPLER,
                "Kepler's bound 0.7405 for spheres",
            )
        }
        (Some(d), None) => (vf * (1.0 + gap / d).powi(3), *d, 1.0, "the whole cell"),
        _ => (vf, 0.0, f64::INFINITY, ""),
    };
    if padded > limit {
        let fits = d * ((limit / vf).cbrt() - 1.0);
        return Err(StageError::param(
            key,
            format!(
                "{} cannot fit grains of mean diameter {} at volume_fraction {vf}: grains kept min_gap apart fill at least {padded:.3} of the volume, more than {what}. Use min_gap below {} or lower volume_fraction",
                fmt_len(gap),
                fmt_len(d),
                fmt_len(fits)
            ),
        ));
    }
    if let (Some((t, true)), Some(d)) = (layer, grains.diameter) {
        if d + gap > t {
            return Err(StageError::param(
                "layer_thickness",
                format!(
                    "grains of mean diameter {} plus min_gap {} exceed the layer thickness {}: with periodic_z a grain would touch its own image one layer above. Raise layer_thickness above {}, lower min_gap, or use periodic_z: false",
                    fmt_len(d),
                    fmt_len(gap),
                    fmt_len(t),
                    fmt_len(d + gap)
                ),
            ));
        }
    }
    Ok(())
}

/// A length for messages, in um below 1 cm, else in m.
fn fmt_len(x: f64) -> String {
    if x.abs() < 1e-2 {
        format!("{:.2} um", x * 1e6)
    } else {
        format!("{x} m")
    }
}

/// Peak memory of a run with `bodies` grains: per grain its state, neighbour list and the
/// sphere-pair Verlet list (Remark 3; about 30 listed sphere pairs per sphere of a 150-200
/// sphere clump, one pair per neighbour for spheres), plus the shared structures. The
/// neighbour search visits at most 5^3 cells per grain: the gap checks above bound the
/// cut-off by the cell.
fn memory_estimate(bodies: u64, clumps: bool) -> u64 {
    let spheres_per_grain: u64 = if clumps { 256 } else { 1 };
    let per_grain = 1024 + spheres_per_grain * (64 + 30 * 8);
    (1 << 20) + bodies.saturating_mul(per_grain)
}

fn mean_bound(shapes: &[Shape]) -> f64 {
    shapes.iter().map(|s| s.bound).sum::<f64>() / shapes.len().max(1) as f64
}

/// Side of the cube holding grains of these volumes at volume fraction `vf`.
fn cube_side(volumes: impl Iterator<Item = f64>, vf: f64) -> f64 {
    (volumes.sum::<f64>() / vf).cbrt()
}

fn library_port(doc: &'static str) -> PortSpec {
    PortSpec::optional("library", ArtifactKind::ClumpLibrary, doc)
}

fn outputs() -> Vec<PortSpec> {
    vec![
        PortSpec::new("packing", ArtifactKind::Packing, "periodic packing with layer ids (library embedded for clumps)"),
        PortSpec::new("report", ArtifactKind::Table, "per layer: grains, tries, iterations, contraction steps, back-offs, shakes, grains of earlier layers released after a stuck step, time, final overlap energy (eq. 2.6 at min_gap) and largest violation, achieved fraction; microstructure: near-contacts per grain (gap <= min_gap + contact_tolerance) and bridges per grain (gap <= bridge_distance) with their histograms, the contact-normal fabric of the layer's own contacts (xx, yy, zz, 3 N_zz - 1, deviator norm) and of the contacts across the interface at its bottom, the grains' long-axis <n_z n_z>"),
        PortSpec::new("history", ArtifactKind::Table, "convergence history: per layer and overlap-removal phase, the contraction scale, iterations, overlap energy, largest violation and outcome (converged, stuck, shaken, shake_failed)"),
        PortSpec::new("orientation", ArtifactKind::Tensor, "3x3 orientation tensor <n n> of the grains' long axes (smallest principal moment of inertia); 1/3 I for spheres"),
        PortSpec::new("contact_fabric", ArtifactKind::Tensor, "3x3 contact-normal fabric tensor <n n> over the near-contacts of the whole packing (gap <= min_gap + contact_tolerance; n: unit vector between the closest sphere pair of the two grains); NaN without any near-contact"),
        PortSpec::new("contacts", ArtifactKind::Table, "distribution of near-contacts and bridges per grain over the whole packing: per count k = 0, 1, ... the grains with exactly k near-contacts and with exactly k grains within bridge_distance"),
    ]
}

/// What preflight knows of the grains before any is drawn: their mean diameter and volume
/// (estimates) and, for spheres from `radius`, the range of one grain's volume.
struct GrainSizes {
    diameter: Option<f64>,
    volume: Option<f64>,
    volume_range: Option<(f64, f64)>,
}

impl GrainSizes {
    fn of(c: &ContractionParams, inputs: &InputMetas) -> Self {
        match inputs.get("library") {
            Some(lib) => GrainSizes {
                diameter: lib.length_scale,
                volume: lib.length_scale.map(|d| PI / 6.0 * d.powi(3)),
                volume_range: None,
            },
            None => GrainSizes {
                diameter: Some(2.0 * c.radius.mean()),
                volume: Some(mean_sphere_volume(&c.radius)),
                volume_range: Some(sphere_volume_range(&c.radius)),
            },
        }
    }

    /// Estimated number of grains drawn to fill `target` [m^3] (0 when unknown).
    fn estimate(&self, target: f64) -> u64 {
        self.volume
            .filter(|v| *v > 0.0)
            .map(|v| (target / v).ceil() as u64)
            .unwrap_or(0)
    }

    /// Bounds on the number of grains `sample_volume` draws to exceed `target` [m^3]: at
    /// least target / vmax, fewer than target / vmin + 1 (with a margin for rounding). Only
    /// for spheres from `radius`, and only when the range is of a sensible size.
    fn bounds(&self, target: f64) -> Option<[u64; 2]> {
        let (vmin, vmax) = self.volume_range?;
        if !(vmin > 0.0 && vmax.is_finite()) {
            return None;
        }
        let lo = (target / vmax * (1.0 - 1e-6)).floor().max(1.0);
        let hi = (target / vmin * (1.0 + 1e-6)).ceil() + 1.0;
        (hi <= 1e9).then_some([lo as u64, hi as u64])
    }

    fn with_scale(&self, meta: ArtifactMeta) -> ArtifactMeta {
        match self.diameter {
            Some(d) => meta.with_length_scale(d),
            None => meta,
        }
    }
}

/// The announcement shared by both stages: the packing as given, `layers` report rows, a
/// history of at least one phase per layer, the 3x3 orientation tensor.
fn announce<P>(
    info: &StageInfo,
    memory: u64,
    packing: ArtifactMeta,
    layers: u64,
    c: &ContractionParams,
    plan: P,
) -> Preflight<P> {
    let table = ArtifactMeta::of(ArtifactKind::Table);
    Preflight::from_info(info, memory)
        .announce("packing", packing)
        .announce(
            "report",
            table.clone().with_count(layers, Some([layers, layers])),
        )
        .announce(
            "history",
            table.with_count(layers * (c.contraction_steps as u64 + 1), None),
        )
        .announce(
            "orientation",
            ArtifactMeta::of(ArtifactKind::Tensor).with_count(9, Some([9, 9])),
        )
        .announce(
            "contact_fabric",
            ArtifactMeta::of(ArtifactKind::Tensor).with_count(9, Some([9, 9])),
        )
        .announce(
            "contacts",
            ArtifactMeta::of(ArtifactKind::Table).with_count(16, None),
        )
        .with_plan(plan)
}

/// What `mcm.classic`'s preflight settles for its run.
pub struct ClassicPlan {
    schedule: Schedule,
    /// The final cell when `size` gives it; `None`: the cube holding `count` grains at eta.
    size: Option<[f64; 3]>,
}

impl TypedStage for Classic {
    type Params = ClassicParams;
    type Plan = ClassicPlan;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "mcm.classic",
            "2.2.0",
            "Mechanical contraction method: grains placed in a cell enlarged by beta, isotropic contraction steps each followed by overlap removal (FIRE or the paper's gradient descent over centroids and orientations), jams shaken loose, periodic in x, y, z",
        )
        .inputs(vec![library_port("clumps to pack (drawn by scrambled Sobol sampling on bounding diameter); spheres from `radius` if absent")])
        .outputs(outputs())
    }
    fn preflight(
        &self,
        p: &ClassicParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<ClassicPlan>, StageError> {
        let c = &p.contraction;
        c.check(p.beta, p.min_gap.si())?;
        check_anneal(p.anneal_amplitude)?;
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
        let grains = GrainSizes::of(c, inputs);
        let size = sized.then(|| p.size.map(|l| l.si()));
        // The cell, or its estimate from `count` grains of the mean volume at eta.
        let cell_min = match size {
            Some(cell) => Some(cell.iter().cloned().fold(f64::INFINITY, f64::min)),
            None => grains
                .volume
                .map(|v| (p.count as f64 * v / c.volume_fraction).cbrt()),
        };
        check_gap(p.min_gap.si(), &grains, c, cell_min, None)?;
        let mut packing = ArtifactMeta::of(ArtifactKind::Packing);
        packing.periodic = Some([true; 3]);
        if let Some(cell) = size {
            let target = c.volume_fraction * cell.iter().product::<f64>();
            packing = ArtifactMeta::packing([0.0; 3], cell, [true; 3])
                .with_count(grains.estimate(target), grains.bounds(target));
        } else {
            let n = p.count as u64;
            packing = packing.with_count(n, Some([n, n]));
            // Equal spheres: the cube is known before drawing (the run sums the same volumes).
            if let (SizeDistribution::Fixed { value }, false) =
                (&c.radius, inputs.contains_key("library"))
            {
                let v = sphere_volume(value.si());
                let side = cube_side((0..p.count).map(|_| v), c.volume_fraction);
                packing = ArtifactMeta::packing([0.0; 3], [side; 3], [true; 3])
                    .with_count(n, Some([n, n]));
            }
        }
        let plan = ClassicPlan {
            // mcm.classic has no earlier layers to release and retries with uniform draws.
            schedule: c.schedule(
                p.beta,
                (p.anneal_steps, p.anneal_amplitude, p.anneal_cycles),
                [false, false],
                0,
            ),
            size,
        };
        Ok(announce(
            &self.info(),
            memory_estimate(p.count as u64, inputs.contains_key("library")),
            grains.with_scale(packing),
            1,
            c,
            plan,
        ))
    }
    fn run(
        &self,
        p: &ClassicParams,
        plan: &ClassicPlan,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let t0 = Instant::now();
        let c = &p.contraction;
        let src = grain_source(inputs, &c.radius)?;
        let order = src.order();
        let seed = grainpipe_core::derive_seed(ctx.seed, b"mcm.sobol") as u32;
        let (picks, scale, cell) = match plan.size {
            Some(cell) => {
                let (pk, s) = sample_volume(
                    &src,
                    c.volume_fraction * cell.iter().product::<f64>(),
                    seed,
                    &order,
                );
                (pk, s, cell)
            }
            None => {
                let pk: Vec<Pick> = (0..p.count as u32)
                    .map(|k| src.pick(k, seed, &order))
                    .collect();
                let l = cube_side(pk.iter().map(|x| x.volume), c.volume_fraction);
                (pk, 1.0, [l; 3])
            }
        };
        let mut rng = ctx.rng();
        let shapes: Vec<Shape> = picks.iter().map(|x| src.shape(x, scale)).collect();
        let bmean = mean_bound(&shapes);
        check_fits(
            if plan.size.is_some() { "size" } else { "count" },
            cell.iter().cloned().fold(f64::INFINITY, f64::min),
            p.min_gap.si(),
            &shapes,
        )?;
        let tol = c.tolerance * bmean;
        let grains: Vec<Grain> = (0..picks.len())
            .map(|i| Grain {
                shape: i,
                pos: v3([0.0; 3]),
                rot: quat(random_quaternion(&mut rng)),
                frozen: false,
                zbox: None,
            })
            .collect();
        // eq. (2.2): the grains are placed in the cell enlarged by beta.
        let big = cell.map(|l| l * p.beta);
        let mut sys = System::new(shapes, grains, big, p.min_gap.si() + tol, tol);
        sys.margin = tol;
        sys.relaxation = c.relaxation();
        let mode = Mode::Isotropic { final_cell: cell };
        let place_afresh = |sys: &mut System, rng: &mut ChaCha8Rng, flat_draws: usize| {
            sys.cell = big;
            let n = sys.grains.len();
            place_all(sys, 0..n, rng, flat_draws, |r| {
                v3([0, 1, 2].map(|a| uniform(r, 0.0, big[a])))
            });
        };
        place_afresh(&mut sys, &mut rng, 1);
        let (st, tries) = contract_with_restarts(
            &mut sys,
            &mode,
            p.beta,
            &plan.schedule,
            c.restarts,
            &mut rng,
            ctx,
            "mcm.classic",
            |f| ctx.progress((f * 1000.0) as u64, 1000),
            place_afresh,
        )
        .map_err(|(tries, f)| run_failed("mcm.classic", 0, 1, tries, *f))?;
        let tagged: Vec<(Pick, f64, u32)> = picks.iter().map(|x| (*x, scale, 0)).collect();
        let built = build(&sys, &src, &tagged, cell);
        let mut packing = Packing::new(Domain::boxed([0.0; 3], cell, [true; 3]));
        packing.bodies = built.bodies;
        packing.library = built.library;
        let fraction = packing.volume_fraction();
        let rows = [Row {
            grains: picks.len(),
            tries,
            stats: st,
            time: t0.elapsed().as_secs_f64(),
            fraction,
            released_layers: Vec::new(),
        }];
        let m = microstructure(&packing, &built.axes, 1, cell[2], p.min_gap.si(), c);
        warn_fallbacks(ctx, "mcm.classic", &rows, &m);
        Ok(outputs_of(&rows, packing, &built.axes, &m))
    }
}

impl TypedStage for Stacked {
    type Params = StackedParams;
    type Plan = Schedule;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "mcm.stacked",
            "2.4.0",
            "Stacked mechanical contraction method (Algorithm 2): layer by layer, periodic in x, y (and z), contraction along z only, earlier layers frozen (those a jammed layer touches released, unless `release: false`), soft box on the centroids, each layer filled to eta exactly, jams thermalised and shaken loose (after `plain_tries` tries of Algorithm 2 as published)",
        )
        .inputs(vec![library_port("clumps to pack (scrambled Sobol sampling on bounding diameter, Remark 2); spheres from `radius` if absent")])
        .outputs(outputs())
    }
    fn preflight(
        &self,
        p: &StackedParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<Schedule>, StageError> {
        let c = &p.contraction;
        c.check(p.beta, p.min_gap.si())?;
        check_anneal(p.anneal_amplitude)?;
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
        let t = p.layer_thickness.si();
        if t.is_nan() || t <= 0.0 {
            return Err(StageError::param("layer_thickness", "must be > 0"));
        }
        let (lx, ly) = (p.layer_size[0].si(), p.layer_size[1].si());
        let grains = GrainSizes::of(c, inputs);
        check_gap(
            p.min_gap.si(),
            &grains,
            c,
            Some(lx.min(ly)),
            Some((t, p.periodic_z)),
        )?;
        let layers = p.layers as u64;
        // Remark 1: each layer is filled to eta Lx Ly T.
        let target = c.volume_fraction * lx * ly * t;
        let packing = ArtifactMeta::packing(
            [0.0; 3],
            [lx, ly, t * p.layers as f64],
            [true, true, p.periodic_z],
        )
        .with_count(
            layers * grains.estimate(target),
            grains
                .bounds(target)
                .map(|[lo, hi]| [layers * lo, layers * hi]),
        );
        Ok(announce(
            &self.info(),
            memory_estimate(
                layers * grains.estimate(target).max(1),
                inputs.contains_key("library"),
            ),
            grains.with_scale(packing),
            layers,
            c,
            c.schedule(
                p.beta,
                (p.anneal_steps, p.anneal_amplitude, p.anneal_cycles),
                [p.release, p.flatter_retries],
                p.plain_tries,
            ),
        ))
    }
    fn run(
        &self,
        p: &StackedParams,
        sch: &Schedule,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let c = &p.contraction;
        let src = grain_source(inputs, &c.radius)?;
        let order = src.order();
        let (lx, ly, t) = (
            p.layer_size[0].si(),
            p.layer_size[1].si(),
            p.layer_thickness.si(),
        );
        let mut rng = ctx.rng();
        let mut sys = System::new(Vec::new(), Vec::new(), [lx, ly, t], 0.0, 0.0);
        sys.relaxation = c.relaxation();
        let mut tagged: Vec<(Pick, f64, u32)> = Vec::new();
        let mut rows = Vec::new();
        for layer in 0..p.layers {
            let t0 = Instant::now();
            let seed =
                grainpipe_core::derive_seed(ctx.seed, format!("mcm.sobol.{layer}").as_bytes())
                    as u32;
            // Remark 1: sample until eta V_layer is exceeded, rescale to hit it.
            let target = c.volume_fraction * lx * ly * t;
            let (picks, s) = sample_volume(&src, target, seed, &order);
            let z0 = layer as f64 * t;
            let first = sys.grains.len();
            // Line 2: freeze the earlier layers.
            for g in &mut sys.grains {
                g.frozen = true;
            }
            // A try that got stuck may have moved grains of the earlier layers it released
            // (`contract`); a new try starts from them as they were.
            let earlier: Vec<Grain> = sys.grains.clone();
            let bmean = {
                let b: f64 = picks.iter().map(|pk| src.shape(pk, s).bound).sum();
                (b + sys.shapes.iter().map(|x| x.bound).sum::<f64>())
                    / (picks.len() + sys.shapes.len()) as f64
            };
            let tol = c.tolerance * bmean;
            sys.tol = tol;
            sys.margin = tol;
            sys.gap = p.min_gap.si() + tol;
            sys.cell[2] = crate::pack::stacked_cell_z(z0 + p.beta * t, t, p.periodic_z);
            // Centroids uniform in the layer enlarged by beta along z.
            let in_layer = |r: &mut ChaCha8Rng| {
                v3([
                    uniform(r, 0.0, lx),
                    uniform(r, 0.0, ly),
                    uniform(r, z0, z0 + p.beta * t),
                ])
            };
            let layer_shapes: Vec<Shape> = picks.iter().map(|pk| src.shape(pk, s)).collect();
            check_fits("layer_size", lx.min(ly), p.min_gap.si(), &layer_shapes)?;
            if p.periodic_z {
                check_thickness(t, p.min_gap.si(), &layer_shapes)?;
            }
            for pk in &picks {
                sys.shapes.push(src.shape(pk, s));
                sys.grains.push(Grain {
                    shape: sys.shapes.len() - 1,
                    pos: v3([0.0; 3]),
                    rot: quat(random_quaternion(&mut rng)),
                    frozen: false,
                    zbox: None,
                });
                tagged.push((*pk, s, layer as u32));
            }
            let n = sys.grains.len();
            place_all(&mut sys, first..n, &mut rng, 1, in_layer);
            let mode = Mode::Stacked {
                first,
                z0,
                thickness: t,
                margin: tol,
                periodic_z: p.periodic_z,
            };
            let nl = p.layers as f64;
            let (st, tries) = contract_with_restarts(
                &mut sys,
                &mode,
                p.beta,
                sch,
                c.restarts,
                &mut rng,
                ctx,
                &format!("mcm.stacked, layer {layer}"),
                |f| ctx.progress(((layer as f64 + f) / nl * 1000.0) as u64, 1000),
                |sys, rng, flat_draws| {
                    sys.grains[..first].clone_from_slice(&earlier);
                    sys.cell[2] = crate::pack::stacked_cell_z(z0 + p.beta * t, t, p.periodic_z);
                    let n = sys.grains.len();
                    place_all(sys, first..n, rng, flat_draws, in_layer);
                },
            )
            .map_err(|(tries, f)| run_failed("mcm.stacked", layer, p.layers, tries, *f))?;
            let vol: f64 = picks.iter().map(|x| x.volume * s.powi(3)).sum();
            let mut released_layers: Vec<usize> = st
                .released_grains
                .iter()
                .map(|&g| tagged[g].2 as usize)
                .collect();
            released_layers.sort_unstable();
            released_layers.dedup();
            rows.push(Row {
                grains: picks.len(),
                tries,
                stats: st,
                time: t0.elapsed().as_secs_f64(),
                fraction: vol / (lx * ly * t),
                released_layers,
            });
        }
        let cell = [lx, ly, t * p.layers as f64];
        let built = build(&sys, &src, &tagged, cell);
        let mut packing = Packing::new(Domain::boxed([0.0; 3], cell, [true, true, p.periodic_z]));
        packing.bodies = built.bodies;
        packing.library = built.library;
        let m = microstructure(&packing, &built.axes, p.layers, t, p.min_gap.si(), c);
        warn_fallbacks(ctx, "mcm.stacked", &rows, &m);
        Ok(outputs_of(&rows, packing, &built.axes, &m))
    }
}
