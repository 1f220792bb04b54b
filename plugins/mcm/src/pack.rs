//! The contraction driver shared by `mcm.classic` and `mcm.stacked`: grain sampling
//! (Remarks 1-2), initial placement in the enlarged cell (eq. 2.2), the contraction phases
//! with an adaptive schedule that backs off when the overlap removal gets stuck.

use crate::engine::{Grain, Shape, System};
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::{Clump, ClumpLibrary};
use nalgebra::{UnitQuaternion, Vector3};
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::f64::consts::PI;

/// Where the grains come from.
pub enum Source<'a> {
    Spheres(&'a SizeDistribution),
    Library(&'a ClumpLibrary),
}

/// A sampled grain before placement: library index (None for a sphere), scale, volume.
#[derive(Clone, Copy, Debug)]
pub struct Pick {
    pub index: Option<usize>,
    pub radius: f64,
    pub volume: f64,
}

impl Source<'_> {
    /// k-th draw of a scrambled Sobol sequence (Owen scrambling, Remark 2): for a library the
    /// clumps are sorted by bounding diameter and the point picks a rank; for spheres it is
    /// mapped through the radius quantile function.
    pub fn pick(&self, k: u32, seed: u32, order: &[usize]) -> Pick {
        let u = sobol_burley::sample(k, 0, seed) as f64;
        match self {
            Source::Spheres(d) => {
                let r = d.quantile(u.clamp(1e-12, 1.0 - 1e-12));
                Pick {
                    index: None,
                    radius: r,
                    volume: 4.0 / 3.0 * PI * r.powi(3),
                }
            }
            Source::Library(lib) => {
                let m = order.len();
                let i = order[((u * m as f64) as usize).min(m - 1)];
                Pick {
                    index: Some(i),
                    radius: 0.0,
                    volume: lib.clumps[i].volume,
                }
            }
        }
    }

    /// Library indices sorted by bounding diameter (ties by index).
    pub fn order(&self) -> Vec<usize> {
        match self {
            Source::Spheres(_) => Vec::new(),
            Source::Library(lib) => {
                let mut o: Vec<usize> = (0..lib.clumps.len()).collect();
                o.sort_by(|&a, &b| {
                    lib.clumps[a]
                        .bounding_radius
                        .total_cmp(&lib.clumps[b].bounding_radius)
                        .then(a.cmp(&b))
                });
                o
            }
        }
    }

    /// The shape of a pick scaled linearly by `s`.
    pub fn shape(&self, p: &Pick, s: f64) -> Shape {
        match (self, p.index) {
            (Source::Library(lib), Some(i)) => Shape::new(
                lib.clumps[i]
                    .spheres
                    .iter()
                    .map(|c| (c.offset.map(|x| x * s), c.radius * s)),
            ),
            _ => Shape::new([([0.0; 3], p.radius * s)]),
        }
    }
}

pub fn scale_clump(c: &Clump, s: f64) -> Clump {
    let mut out = c.clone();
    for sp in &mut out.spheres {
        sp.offset = sp.offset.map(|x| x * s);
        sp.radius *= s;
    }
    out.volume *= s.powi(3);
    out.bounding_radius *= s;
    out.principal_inertia = out.principal_inertia.map(|x| x * s.powi(5));
    out
}

/// Uniformly distributed random rotation (normalised 4-D Gaussian).
pub fn random_rotation(rng: &mut ChaCha8Rng) -> UnitQuaternion<f64> {
    let q: [f64; 4] = [0; 4].map(|_| StandardNormal.sample(rng));
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// Paper, section 2.2: "in the initial configuration, the grains should not overlap". Draws
/// up to `attempts` positions (from `draw`) and orientations for grain `i` and keeps the first
/// without overlap against grains `0..i`, else the least overlapping one (the minimiser then
/// removes the rest).
pub fn place(
    sys: &mut System,
    i: usize,
    rng: &mut ChaCha8Rng,
    attempts: usize,
    mut draw: impl FnMut(&mut ChaCha8Rng) -> Vector3<f64>,
) {
    let mut best = (f64::INFINITY, sys.grains[i].pos, sys.grains[i].rot);
    for _ in 0..attempts {
        sys.grains[i].pos = draw(rng);
        sys.grains[i].rot = random_rotation(rng);
        let o = sys.max_overlap(i, 0..i);
        if o < best.0 {
            best = (o, sys.grains[i].pos, sys.grains[i].rot);
        }
        if o <= 0.0 {
            break;
        }
    }
    sys.grains[i].pos = best.1;
    sys.grains[i].rot = best.2;
}

pub fn uniform(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.random::<f64>()
}

/// Schedule and limits of one contraction run.
#[derive(Clone, Copy, Debug)]
pub struct Schedule {
    /// First relative contraction per step (eq. 2.2 beta reached in `steps` steps).
    pub rate0: f64,
    pub rate_min: f64,
    pub rate_max: f64,
    pub step_iterations: usize,
    pub max_iterations: usize,
}

/// What one contraction run reached.
#[derive(Clone, Copy, Debug, Default)]
pub struct RunStats {
    pub iterations: usize,
    pub steps: usize,
    pub backoffs: usize,
    pub energy: f64,
    pub max_delta: f64,
}

/// Contraction geometry: isotropic about the origin (classic) or along z about `z0` for the
/// bodies `first..` (stacked).
pub enum Mode {
    Isotropic {
        final_cell: [f64; 3],
    },
    Stacked {
        first: usize,
        z0: f64,
        thickness: f64,
        margin: f64,
        periodic_z: bool,
    },
}

fn apply(sys: &mut System, mode: &Mode, s_old: f64, s_new: f64) {
    match mode {
        Mode::Isotropic { final_cell } => {
            let f = s_new / s_old;
            for g in &mut sys.grains {
                g.pos *= f;
            }
            sys.cell = final_cell.map(|l| l * s_new);
        }
        Mode::Stacked {
            first,
            z0,
            thickness,
            margin,
            periodic_z,
        } => {
            let f = s_new / s_old;
            let top = z0 + s_new * thickness;
            for g in &mut sys.grains[*first..] {
                g.pos.z = z0 + (g.pos.z - z0) * f;
                g.zbox = Some((z0 + margin, top - margin));
            }
            sys.cell[2] = stacked_cell_z(top, *thickness, *periodic_z);
        }
    }
    sys.invalidate();
}

/// Alternates contraction and overlap removal from scale `beta` down to 1 (Algorithm 2,
/// lines 10-17). A contraction whose overlap removal does not converge within
/// `step_iterations` is undone and retried with half the rate. Err = (stats, reason).
pub fn contract(
    sys: &mut System,
    mode: &Mode,
    beta: f64,
    sch: &Schedule,
    mut progress: impl FnMut(f64) -> Result<(), grainpipe_core::StageError>,
) -> Result<RunStats, (RunStats, String, Option<grainpipe_core::StageError>)> {
    let mut st = RunStats::default();
    let mut s = beta;
    apply(sys, mode, s, s);
    // Initial overlap removal at the dilute fraction.
    let m = sys.minimise(sch.max_iterations);
    st.iterations += m.iterations;
    st.energy = m.energy;
    st.max_delta = m.max_delta;
    if !m.converged {
        return Err((st, "initial overlap removal did not converge".into(), None));
    }
    let mut rate = sch.rate0;
    while s > 1.0 {
        if let Err(e) = progress((beta - s) / (beta - 1.0).max(1e-12)) {
            return Err((st, "cancelled".into(), Some(e)));
        }
        let snapshot: Vec<Grain> = sys.grains.clone();
        let cell = sys.cell;
        let s_new = (s / (1.0 + rate)).max(1.0);
        apply(sys, mode, s, s_new);
        let budget = sch
            .step_iterations
            .min(sch.max_iterations.saturating_sub(st.iterations));
        let m = sys.minimise(budget);
        st.iterations += m.iterations;
        st.energy = m.energy;
        st.max_delta = m.max_delta;
        if m.converged {
            s = s_new;
            st.steps += 1;
            rate = (rate * 1.25).min(sch.rate_max);
            continue;
        }
        if st.iterations >= sch.max_iterations {
            return Err((
                st,
                format!(
                    "iteration limit {} reached at contraction scale {:.5} (target 1)",
                    sch.max_iterations, s_new
                ),
                None,
            ));
        }
        // Stuck: undo the contraction and try a smaller one.
        sys.grains = snapshot;
        sys.cell = cell;
        sys.invalidate();
        st.backoffs += 1;
        rate *= 0.5;
        if rate < sch.rate_min {
            return Err((
                st,
                format!(
                    "contraction rate fell below {:e} at scale {:.5}: the packing is jammed",
                    sch.rate_min, s
                ),
                None,
            ));
        }
    }
    Ok(st)
}

/// z period while a layer is packed: the current height (periodic in z, Remark 4), or, for a
/// free surface above the layer, a period so long that no image is ever within reach.
pub fn stacked_cell_z(top: f64, thickness: f64, periodic_z: bool) -> f64 {
    if periodic_z {
        top
    } else {
        2.0 * top + 10.0 * thickness
    }
}

pub fn v3(a: [f64; 3]) -> Vector3<f64> {
    Vector3::from(a)
}
