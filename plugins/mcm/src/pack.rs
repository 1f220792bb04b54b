//! The contraction driver shared by `mcm.classic` and `mcm.stacked`: grain sampling
//! (Remarks 1-2), initial placement in the enlarged cell (eq. 2.2), the contraction phases
//! with an adaptive schedule that backs off when the overlap removal gets stuck.

use crate::engine::{Grain, Minimised, Neighbourhood, Shape, System, Worst};
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::spatial::{min_image, random_quaternion};
use grainpipe_core::ClumpLibrary;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

/// Sobol points are kept this far inside (0, 1) before the radius quantile is taken.
const U_EDGE: f64 = 1e-12;

/// Volume of a sphere of radius `r`.
pub fn sphere_volume(r: f64) -> f64 {
    4.0 / 3.0 * PI * r.powi(3)
}

/// The smallest and the largest volume of a sphere drawn from `d` by [`Source::pick`].
pub fn sphere_volume_range(d: &SizeDistribution) -> (f64, f64) {
    (
        sphere_volume(d.quantile(U_EDGE)),
        sphere_volume(d.quantile(1.0 - U_EDGE)),
    )
}

/// Mean volume of a sphere drawn from `d`, from 1024 quantiles (an estimate for preflight).
pub fn mean_sphere_volume(d: &SizeDistribution) -> f64 {
    let n = 1024;
    (0..n)
        .map(|i| sphere_volume(d.quantile((i as f64 + 0.5) / n as f64)))
        .sum::<f64>()
        / n as f64
}

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
                let r = d.quantile(u.clamp(U_EDGE, 1.0 - U_EDGE));
                Pick {
                    index: None,
                    radius: r,
                    volume: sphere_volume(r),
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

/// Random initial positions tried per grain before the least overlapping one is kept.
pub const PLACE_ATTEMPTS: usize = 200;

/// How a placement draws a grain's orientation: `flat_draws` uniform random rotations, of
/// which the one with the smallest extent along z is kept. 1 is the uniform (isotropic)
/// draw of the paper; more draws bias the grains towards lying flat, as a recoater leaves
/// them. A layer contracted along z jams on grains that stand upright (an elongated grain
/// nearly as long as the layer is thick leaves no room above or below it), so the
/// retries of a stacked layer and the relocation of a wedged grain draw flatter
/// orientations (see `contract` and `mcm.stacked`).
pub fn draw_orientation(
    shape: &Shape,
    rng: &mut ChaCha8Rng,
    flat_draws: usize,
) -> UnitQuaternion<f64> {
    let mut best = quat(random_quaternion(rng));
    if flat_draws <= 1 {
        return best;
    }
    let mut lowest = z_extent(shape, &best);
    for _ in 1..flat_draws {
        let q = quat(random_quaternion(rng));
        let h = z_extent(shape, &q);
        if h < lowest {
            (best, lowest) = (q, h);
        }
    }
    best
}

/// Extent along z of a shape turned by `rot`: its width along `R^T e_z` in the body frame.
pub fn z_extent(shape: &Shape, rot: &UnitQuaternion<f64>) -> f64 {
    width_along(shape, rot.inverse_transform_vector(&Vector3::z()))
}

/// The width of a shape along unit direction `n` (body frame): the extent of its spheres'
/// projections.
pub fn width_along(s: &Shape, n: Vector3<f64>) -> f64 {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (o, r) in s.offsets.iter().zip(&s.radii) {
        let x = o.dot(&n);
        lo = lo.min(x - r);
        hi = hi.max(x + r);
    }
    hi - lo
}

/// Paper, section 2.2: "in the initial configuration, the grains should not overlap". Draws
/// up to `attempts` positions (from `draw`) and orientations (see [`draw_orientation`]) for
/// grain `i` and keeps the first without overlap against the grains in `near`, else the
/// least overlapping one (the minimiser then removes the rest).
pub fn place(
    sys: &mut System,
    i: usize,
    near: &Neighbourhood,
    rng: &mut ChaCha8Rng,
    attempts: usize,
    flat_draws: usize,
    mut draw: impl FnMut(&mut ChaCha8Rng) -> Vector3<f64>,
) {
    let mut best = (f64::INFINITY, sys.grains[i].pos, sys.grains[i].rot);
    for _ in 0..attempts {
        sys.grains[i].pos = draw(rng);
        sys.grains[i].rot = draw_orientation(&sys.shapes[sys.grains[i].shape], rng, flat_draws);
        let o = sys.max_overlap(i, near);
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

/// Places grains `range` one after the other (each against the grains `0..range.start`
/// and those placed before it), drawing positions from `draw` and orientations with
/// `flat_draws` (see [`draw_orientation`]).
pub fn place_all(
    sys: &mut System,
    range: std::ops::Range<usize>,
    rng: &mut ChaCha8Rng,
    flat_draws: usize,
    mut draw: impl FnMut(&mut ChaCha8Rng) -> Vector3<f64>,
) {
    let mut near = Neighbourhood::new(sys);
    for j in 0..range.start {
        near.add(sys, j);
    }
    for i in range {
        place(sys, i, &near, rng, PLACE_ATTEMPTS, flat_draws, &mut draw);
        near.add(sys, i);
    }
    sys.invalidate();
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
    /// Shake jams loose after a stuck step (else only undo and halve).
    pub shake: bool,
    /// Convergence threshold of the phases before the final size, as a multiple (>= 1) of
    /// the final tolerance `System::tol`.
    pub loose: f64,
    /// Thermalisation of a stuck contraction step (`System::anneal`): Langevin steps per
    /// cycle (0: off), starting thermal amplitude sqrt(T) in mean bounding radii of the
    /// mobile grains, cycles per stuck step.
    pub anneal_steps: usize,
    pub anneal_amplitude: f64,
    pub anneal_cycles: usize,
    /// Stacked only: free the earlier layers' grains that a stuck layer touches
    /// (`release_contacts`); false keeps them frozen (Algorithm 2).
    pub release: bool,
    /// Stacked only: retries of a jammed layer draw flatter orientations
    /// (`retry_flat_draws`); false: the uniform draw on every try.
    pub flatter_retries: bool,
    /// Stacked only: tries with Algorithm 2 as published (`Schedule::plain`) before the
    /// fallbacks configured here are used.
    pub plain_tries: usize,
}

impl Schedule {
    /// Algorithm 2 as published: no release, thermalisation, shaking or flatter retries.
    pub fn plain(&self) -> Schedule {
        Schedule {
            shake: false,
            anneal_steps: 0,
            release: false,
            flatter_retries: false,
            ..*self
        }
    }
}

/// Convergence threshold of intermediate phases, in mean bounding radii. An intermediate
/// configuration only has to be free enough of overlaps for the next contraction step
/// (whose own overlaps are larger); only the final size needs the tight tolerance that
/// pads the gap. Relaxing intermediate phases to the tight tolerance costs iterations,
/// while padding the gap by a loose tolerance inflates every grain by it, and with it the
/// fraction that has to be reached: at 1e-2 radii that is +1.5 % for spheres, enough to
/// push 0.64 past the jamming density of a contraction (issue 20).
pub const LOOSE_TOLERANCE: f64 = 1e-2;

/// One overlap-removal phase of the convergence history.
#[derive(Clone, Copy, Debug)]
pub struct Phase {
    /// Contraction scale the phase relaxed at (1 = final size).
    pub scale: f64,
    pub iterations: usize,
    /// eq. (2.6) at the user's gap plus the soft-box penalty [m^2].
    pub energy: f64,
    /// Largest violation with the padded gap [m].
    pub max_violation: f64,
    pub outcome: Outcome,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// Converged: the contraction is kept.
    Converged,
    /// Not converged within `step_iterations` or stalled: undone.
    Stuck,
    /// Re-expanded, shaken and the worst grain relocated, then relaxed.
    Shaken,
    /// A shake whose relaxation did not converge: undone.
    ShakeFailed,
    /// A stuck step thermalised at its size, then relaxed to convergence: kept.
    Annealed,
    /// A thermalisation cycle whose relaxation did not converge.
    AnnealFailed,
}

impl Outcome {
    pub fn name(self) -> &'static str {
        match self {
            Outcome::Converged => "converged",
            Outcome::Stuck => "stuck",
            Outcome::Shaken => "shaken",
            Outcome::ShakeFailed => "shake_failed",
            Outcome::Annealed => "annealed",
            Outcome::AnnealFailed => "anneal_failed",
        }
    }
}

/// What one contraction run reached.
#[derive(Clone, Debug, Default)]
pub struct RunStats {
    pub iterations: usize,
    pub steps: usize,
    pub backoffs: usize,
    /// Back-offs that re-expanded and shook the layer (see `contract`).
    pub shakes: usize,
    /// Grains of earlier (frozen) layers released to move with the layer being packed after
    /// it got stuck (see `release_contacts`).
    pub released: usize,
    /// Which grains those are (indices into the system's grains).
    pub released_grains: Vec<usize>,
    pub energy: f64,
    pub max_delta: f64,
    pub worst: Worst,
    pub history: Vec<Phase>,
}

impl RunStats {
    fn record(&mut self, scale: f64, m: &Minimised, outcome: Outcome) {
        self.iterations += m.iterations;
        self.energy = m.energy;
        self.max_delta = m.max_delta;
        self.worst = m.worst;
        self.history.push(Phase {
            scale,
            iterations: m.iterations,
            energy: m.energy,
            max_violation: m.max_delta,
            outcome,
        });
    }
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

/// A converged step that used more than 1/HARD_STEP of `step_iterations` halves the rate.
const HARD_STEP: usize = 10;

/// Relative re-expansion of the cell before a shake: room for the shaken grains, undone by
/// the next contraction steps.
const SHAKE_EXPANSION: f64 = 0.02;
/// Random displacement (in bounding radii) and rotation (rad) of a shake.
const SHAKE_AMPLITUDE: f64 = 0.05;
/// Reach of a shake around the stuck grain, in largest bounding radii.
const SHAKE_REACH: f64 = 4.0;

/// Moves every mobile grain within `SHAKE_REACH` largest bounding radii of grain `around`
/// (every mobile grain if `None`) by a random vector in the ball of radius `amp` bounding
/// radii and turns it by a random angle of at most `amp` rad, in body order
/// (deterministic). A jam is local: shaking only its surroundings keeps the rest relaxed.
fn shake(sys: &mut System, rng: &mut ChaCha8Rng, amp: f64, around: Option<usize>) {
    let cell = sys.cell;
    let bmax = sys.shapes.iter().map(|s| s.bound).fold(0.0, f64::max);
    let centre = around.map(|i| sys.grains[i].pos);
    for i in 0..sys.grains.len() {
        if sys.grains[i].frozen {
            continue;
        }
        if let Some(c) = centre {
            let d = Vector3::from(
                [0, 1, 2].map(|a| min_image(sys.grains[i].pos[a] - c[a], cell[a], true)),
            );
            if d.norm() > SHAKE_REACH * bmax {
                continue;
            }
        }
        let b = sys.shapes[sys.grains[i].shape].bound;
        let dx = random_in_ball(rng) * (amp * b);
        let dth = random_in_ball(rng) * amp;
        let g = &mut sys.grains[i];
        g.pos += dx;
        g.rot = UnitQuaternion::from_scaled_axis(dth) * g.rot;
    }
    sys.invalidate();
}

/// Orientation draws (see [`draw_orientation`]) of a grain relocated out of a jam in a
/// stacked layer.
pub const RELOCATE_FLAT_DRAWS: usize = 4;

/// Moves grain `i` to the least overlapping of `PLACE_ATTEMPTS` random spots (and
/// orientations) in its layer (stacked) or the cell (classic) at scale `s`.
fn relocate(sys: &mut System, mode: &Mode, s: f64, i: usize, rng: &mut ChaCha8Rng) {
    let cell = sys.cell;
    let n = sys.grains.len();
    let (zlo, zhi) = match mode {
        Mode::Isotropic { .. } => (0.0, cell[2]),
        Mode::Stacked { z0, thickness, .. } => (*z0, z0 + s * thickness),
    };
    let mut near = Neighbourhood::new(sys);
    for j in (0..n).filter(|&j| j != i) {
        near.add(sys, j);
    }
    // A wedged grain in a layer contracted along z usually stands upright: it is put back
    // lying flatter (see `draw_orientation`).
    let flat_draws = match mode {
        Mode::Isotropic { .. } => 1,
        Mode::Stacked { .. } => RELOCATE_FLAT_DRAWS,
    };
    place(sys, i, &near, rng, PLACE_ATTEMPTS, flat_draws, |r| {
        Vector3::new(
            uniform(r, 0.0, cell[0]),
            uniform(r, 0.0, cell[1]),
            uniform(r, zlo, zhi),
        )
    });
    sys.invalidate();
}

/// Stacked layers only: releases the frozen grains of earlier layers that the layer being
/// packed (bodies `first..`) can reach before its final size, i.e. whose bounding spheres come
/// within `b_i + b_j + gap` plus the contraction still to come (`(s - 1) thickness`) of a mobile
/// grain's, counting periodic images. They keep their own layer's soft box (centroids stay in
/// their layer), so the stack stays layered. Returns the released grains.
///
/// Why: a layer is contracted onto the rough, rigid surface of the layer below and, with
/// `periodic_z`, under the equally rigid bottom of layer 0's image above. Both were shaped
/// against other neighbours, and a new layer jams in their pockets long before its own
/// jamming density (issue 20: a second layer of elongated grains stuck at 7 % above its final
/// size on every try). Letting the grains in contact adjust (a recoater does disturb the
/// surface it spreads on) removes that mould; grains out of reach stay frozen.
fn release_contacts(sys: &mut System, mode: &Mode, s: f64) -> Vec<usize> {
    let Mode::Stacked {
        first, thickness, ..
    } = mode
    else {
        return Vec::new();
    };
    let cell = sys.cell;
    let reach = sys.gap + (s - 1.0).max(0.0) * thickness;
    let bound = |sys: &System, i: usize| sys.shapes[sys.grains[i].shape].bound;
    let released: Vec<usize> = (0..*first)
        .filter(|&j| sys.grains[j].frozen)
        .filter(|&j| {
            (*first..sys.grains.len()).any(|i| {
                let d = Vector3::from([0, 1, 2].map(|a| {
                    min_image(sys.grains[i].pos[a] - sys.grains[j].pos[a], cell[a], true)
                }));
                d.norm() < bound(sys, i) + bound(sys, j) + reach
            })
        })
        .collect();
    for &j in &released {
        sys.grains[j].frozen = false;
    }
    sys.invalidate();
    released
}

fn random_in_ball(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::from([0; 3].map(|_| uniform(rng, -1.0, 1.0)));
        if v.norm_squared() <= 1.0 {
            return v;
        }
    }
}

/// Why a contraction run ended without reaching scale 1.
#[derive(Debug)]
pub enum FailReason {
    /// The overlaps of the initial placement could not be removed.
    InitialOverlap,
    /// `max_iterations` reached at contraction scale `scale`.
    IterationLimit { limit: usize, scale: f64 },
    /// The rate was halved below `rate_min` at contraction scale `scale`.
    Jammed { rate_min: f64, scale: f64 },
    /// The user interrupted the run (the error to pass on as is).
    Cancelled(grainpipe_core::StageError),
}

impl std::fmt::Display for FailReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FailReason::InitialOverlap => write!(f, "initial overlap removal did not converge"),
            FailReason::IterationLimit { limit, scale } => write!(
                f,
                "iteration limit {limit} reached at contraction scale {scale:.5} (target 1)"
            ),
            FailReason::Jammed { rate_min, scale } => write!(
                f,
                "contraction rate fell below {rate_min:e} at scale {scale:.5}: the packing is jammed"
            ),
            FailReason::Cancelled(_) => write!(f, "cancelled"),
        }
    }
}

/// A contraction run that ended without reaching scale 1, with what it reached.
pub struct RunFailure {
    pub stats: RunStats,
    pub reason: FailReason,
}

/// Alternates contraction and overlap removal from scale `beta` down to 1 (Algorithm 2,
/// lines 10-17). A contraction whose overlap removal does not converge within
/// `step_iterations` (or stalls earlier, see `System::minimise`) is undone, and the rate is
/// halved. A stuck contraction means a jammed arrangement, usually one grain wedged between
/// its neighbours (or against its layer's soft box) that smaller steps alone cannot free:
/// the cell is re-expanded by `SHAKE_EXPANSION`, the mobile grains around the one with the
/// largest violation are shaken (random displacement and rotation of `SHAKE_AMPLITUDE`), it is
/// moved to the least overlapping of `PLACE_ATTEMPTS` random spots, and the overlaps are
/// removed before contraction resumes. Reaching `max_iterations` or a rate below `rate_min`
/// fails.
pub fn contract(
    sys: &mut System,
    mode: &Mode,
    beta: f64,
    sch: &Schedule,
    rng: &mut ChaCha8Rng,
    progress: impl FnMut(f64) -> Result<(), grainpipe_core::StageError>,
) -> Result<RunStats, Box<RunFailure>> {
    // The phases change the convergence threshold; the final tolerance is restored on every
    // way out, so a restart starts from it again.
    let tight = sys.tol;
    let r = contract_phases(sys, mode, beta, sch, rng, progress);
    sys.tol = tight;
    r
}

fn contract_phases(
    sys: &mut System,
    mode: &Mode,
    beta: f64,
    sch: &Schedule,
    rng: &mut ChaCha8Rng,
    mut progress: impl FnMut(f64) -> Result<(), grainpipe_core::StageError>,
) -> Result<RunStats, Box<RunFailure>> {
    let mut st = RunStats::default();
    let fail = |stats: RunStats, reason: FailReason| Box::new(RunFailure { stats, reason });
    let limit = |scale: f64| FailReason::IterationLimit {
        limit: sch.max_iterations,
        scale,
    };
    let mut s = beta;
    apply(sys, mode, s, s);
    let tight = sys.tol;
    let loose = tight * sch.loose.max(1.0);
    // Intermediate phases stop at the loose threshold, the final size at the tight one.
    let threshold = |scale: f64| if scale > 1.0 { loose } else { tight };
    // Initial overlap removal at the dilute fraction.
    sys.tol = threshold(s);
    let m = sys.minimise(sch.max_iterations);
    st.record(
        s,
        &m,
        if m.converged {
            Outcome::Converged
        } else {
            Outcome::Stuck
        },
    );
    if !m.converged {
        return Err(fail(st, FailReason::InitialOverlap));
    }
    let mut rate = sch.rate0;
    let mut released: Vec<usize> = Vec::new();
    let restore = |sys: &mut System, snapshot: &[Grain], cell: [f64; 3], released: &[usize]| {
        sys.grains = snapshot.to_vec();
        for &j in released {
            sys.grains[j].frozen = false;
        }
        sys.cell = cell;
        sys.invalidate();
    };
    // Starting temperature of a thermalisation: thermal overlaps sqrt(T) of
    // `anneal_amplitude` mean bounding radii of the mobile grains.
    let temperature = {
        let mobile: Vec<f64> = sys
            .grains
            .iter()
            .filter(|g| !g.frozen)
            .map(|g| sys.shapes[g.shape].bound)
            .collect();
        let bmean = mobile.iter().sum::<f64>() / mobile.len().max(1) as f64;
        (sch.anneal_amplitude * bmean).powi(2)
    };
    while s > 1.0 {
        if let Err(e) = progress((beta - s) / (beta - 1.0).max(1e-12)) {
            return Err(fail(st, FailReason::Cancelled(e)));
        }
        let budget = |st: &RunStats| {
            sch.step_iterations
                .min(sch.max_iterations.saturating_sub(st.iterations))
        };
        let snapshot: Vec<Grain> = sys.grains.clone();
        let cell = sys.cell;
        let s_new = (s / (1.0 + rate)).max(1.0);
        apply(sys, mode, s, s_new);
        sys.tol = threshold(s_new);
        let m = sys.minimise(budget(&st));
        if m.converged {
            st.record(s_new, &m, Outcome::Converged);
            s = s_new;
            st.steps += 1;
            // Step-size control on the work the step took: a step that needed more than
            // `HARD_STEP` of its budget was close to a jam, so the next one is smaller (near
            // the jamming density every contraction costs more, and a step that gets stuck
            // wastes its whole budget and is undone); an easy step lets the rate grow.
            if m.iterations * HARD_STEP > sch.step_iterations {
                rate = (rate * 0.5).max(sch.rate_min);
            } else {
                rate = (rate * 1.25).min(sch.rate_max);
            }
            continue;
        }
        st.record(s_new, &m, Outcome::Stuck);
        if st.iterations >= sch.max_iterations {
            return Err(fail(st, limit(s_new)));
        }
        // The first stuck step of a layer on earlier ones releases the grains it touches
        // (`release_contacts`); they stay released for the rest of this run, also across the
        // undos below (the snapshots were taken while they were frozen).
        if sch.release && released.is_empty() {
            released = release_contacts(sys, mode, s_new);
            st.released = released.len();
            st.released_grains = released.clone();
        }
        // A stuck step is a quench that jammed: thermalise it at its size and relax again
        // (System::anneal) before giving the step up; each cycle counts its Langevin steps
        // and its relaxation against the run's iteration limit.
        let mut m = m;
        for _ in 0..sch.anneal_cycles {
            if sch.anneal_steps == 0 || st.iterations >= sch.max_iterations {
                break;
            }
            let steps = sch
                .anneal_steps
                .min(sch.max_iterations.saturating_sub(st.iterations));
            let took = sys.anneal(steps, temperature, rng);
            // The relaxation after a thermalisation gets a step's whole budget (the stall
            // test still ends it early if it jams): it starts from a hot, overlapping state,
            // and cut to what the Langevin steps left of one step (1000 of 3000) it often
            // stopped just above the tolerance and the cycle was wasted.
            let mut a = sys.minimise(
                sch.step_iterations
                    .min(sch.max_iterations.saturating_sub(st.iterations + took)),
            );
            a.iterations += took;
            if a.converged {
                st.record(s_new, &a, Outcome::Annealed);
                break;
            }
            st.record(s_new, &a, Outcome::AnnealFailed);
            m = a;
        }
        if st.history.last().map(|h| h.outcome) == Some(Outcome::Annealed) {
            s = s_new;
            st.steps += 1;
            rate = (rate * 0.5).max(sch.rate_min);
            continue;
        }
        if st.iterations >= sch.max_iterations {
            return Err(fail(st, limit(s_new)));
        }
        // Only a grain of the layer being packed may be relocated within it.
        let own = |i: usize| match mode {
            Mode::Stacked { first, .. } => i >= *first,
            Mode::Isotropic { .. } => true,
        };
        let stuck_grain = match m.worst {
            Worst::Pair(i, j) => [i, j].into_iter().find(|&k| own(k)),
            Worst::Box(i) => Some(i).filter(|&k| own(k)),
            Worst::None => None,
        };
        // Undo the contraction, halve the rate, shake the jammed arrangement loose.
        restore(sys, &snapshot, cell, &released);
        st.backoffs += 1;
        rate *= 0.5;
        if rate < sch.rate_min {
            return Err(fail(
                st,
                FailReason::Jammed {
                    rate_min: sch.rate_min,
                    scale: s,
                },
            ));
        }
        if !sch.shake {
            continue;
        }
        let s_up = (s * (1.0 + SHAKE_EXPANSION)).min(beta);
        apply(sys, mode, s, s_up);
        shake(sys, rng, SHAKE_AMPLITUDE, stuck_grain);
        if let Some(i) = stuck_grain {
            relocate(sys, mode, s_up, i, rng);
        }
        sys.tol = threshold(s_up);
        let m = sys.minimise(budget(&st));
        st.shakes += 1;
        if m.converged {
            st.record(s_up, &m, Outcome::Shaken);
            s = s_up;
            // Resume at the halved rate: jumping back to the rate that jammed (or to the
            // expansion) only jams again at the same scale.
            rate = rate.min(0.5 * SHAKE_EXPANSION);
        } else {
            st.record(s_up, &m, Outcome::ShakeFailed);
            restore(sys, &snapshot, cell, &released);
            if st.iterations >= sch.max_iterations {
                return Err(fail(st, limit(s)));
            }
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

/// The rotation of a unit quaternion (w, x, y, z), e.g. from
/// [`grainpipe_core::spatial::random_quaternion`] (already normalised).
pub fn quat([w, x, y, z]: [f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::new_unchecked(Quaternion::new(w, x, y, z))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// A dumbbell: two spheres of radius r at +-a along the body x axis.
    fn dumbbell(a: f64, r: f64) -> Shape {
        Shape::new([([a, 0.0, 0.0], r), ([-a, 0.0, 0.0], r)])
    }

    #[test]
    fn flat_draws_follow_the_order_statistics_of_the_tilt() {
        // For isotropic directions |n_z| is uniform on [0, 1], so the smallest of k draws has
        // mean 1 / (k + 1); the dumbbell's extent along z is 2 a |n_z| + 2 r.
        let (a, r) = (1.0, 0.1);
        let shape = dumbbell(a, r);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let samples = 20_000;
        for k in [1usize, 4, 16] {
            let mean = (0..samples)
                .map(|_| z_extent(&shape, &draw_orientation(&shape, &mut rng, k)))
                .sum::<f64>()
                / samples as f64;
            let exact = 2.0 * a / (k as f64 + 1.0) + 2.0 * r;
            // Standard error of the mean of 2 a |n_z|_min: below 2 a / sqrt(12 samples).
            let tol = 4.0 * 2.0 * a / (12.0 * samples as f64).sqrt();
            assert!(
                (mean - exact).abs() < tol,
                "k = {k}: mean extent {mean}, exact {exact} +- {tol}"
            );
        }
    }

    #[test]
    fn one_flat_draw_is_the_isotropic_draw() {
        // The first try of a layer must stay the paper's uniform draw, bit for bit.
        let shape = dumbbell(1.0, 0.1);
        let mut a = ChaCha8Rng::seed_from_u64(5);
        let mut b = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..100 {
            let q = draw_orientation(&shape, &mut a, 1);
            assert_eq!(q, quat(random_quaternion(&mut b)));
        }
    }

    #[test]
    fn release_frees_only_the_earlier_grains_within_reach() {
        // Unit spheres (bound 1), gap 0.1, layer thickness 10 at scale 1.2 (cell height
        // 10 + 12): reach 0.1 + 0.2 * 10 = 2.1, so an earlier grain is released when its
        // centre is within 1 + 1 + 2.1 = 4.1 of a mobile one's, across periodic images too.
        let shapes = vec![Shape::new([([0.0; 3], 1.0)])];
        let grain = |x: f64, z: f64, frozen: bool| Grain {
            shape: 0,
            pos: v3([x, 5.0, z]),
            rot: UnitQuaternion::identity(),
            frozen,
            zbox: None,
        };
        let grains = vec![
            grain(5.0, 8.0, true),  // 4.0 below mobile grain 4: released
            grain(5.0, 7.8, true),  // 4.2 below it: stays frozen
            grain(18.0, 1.0, true), // 2.0 above mobile grain 5 through the z period: released
            grain(1.5, 1.0, true),  // (3.5, 2.0) from grain 5 through both periods: released
            grain(5.0, 12.0, false),
            grain(18.0, 21.0, false),
        ];
        let mut sys = System::new(shapes, grains, [20.0, 20.0, 22.0], 0.1, 1e-3);
        let mode = Mode::Stacked {
            first: 4,
            z0: 10.0,
            thickness: 10.0,
            margin: 0.0,
            periodic_z: true,
        };
        let released = release_contacts(&mut sys, &mode, 1.2);
        assert_eq!(released, vec![0, 2, 3]);
        let frozen: Vec<bool> = sys.grains.iter().map(|g| g.frozen).collect();
        assert_eq!(frozen, vec![false, true, false, false, false, false]);
        // Classic packings have no earlier layers.
        let iso = Mode::Isotropic {
            final_cell: [20.0; 3],
        };
        assert!(release_contacts(&mut sys, &iso, 1.2).is_empty());
    }
}
