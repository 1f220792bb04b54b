//! Overlap removal for clusters of overlapping spheres (Donval et al. 2025, section 2.2):
//! the overlap energy of eqs. (2.4)-(2.6), its gradient with respect to centroids and
//! orientations, FIRE minimisation with rotations through the exponential map (eq. 2.8),
//! Verlet lists built from a periodic cell list over bounding spheres (Remark 3), periodic
//! images in x, y, z (Remark 4), a minimum gap (Remark 5) and the soft layer box (Remark 4).

use grainpipe_core::spatial::CellList;
use grainpipe_core::ParamChoice;
use nalgebra::{UnitQuaternion, Vector3};
use rayon::prelude::*;

type V3 = Vector3<f64>;

/// Which overlap energy is minimised. Both vanish exactly on non-overlapping packings
/// (eq. 2.5), so they have the same solutions; they differ in how easily one is reached.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum EnergyKind {
    /// 1/2 sum over all overlapping sphere pairs of their overlap squared: continuously
    /// differentiable, every touching sphere pair pushes (default).
    AllPairs,
    /// eq. (2.4)-(2.6) as written: only the deepest sphere pair of each clump pair counts;
    /// its gradient jumps whenever another pair becomes the deepest.
    MaxPair,
}

/// How the energy is minimised.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Minimiser {
    /// FIRE (Bitzek et al. 2006), default.
    Fire,
    /// Fixed-step gradient descent, eq. (2.8), with the paper's h_c and h_R.
    GradientDescent,
}

/// Minimisation settings shared by every overlap-removal phase.
#[derive(Clone, Copy, Debug)]
pub struct Relaxation {
    pub energy: EnergyKind,
    pub minimiser: Minimiser,
    /// Gradient-descent step sizes (h_c, h_R) of eq. (2.8); the rotation step is taken in
    /// units of the grain's bounding radius (the paper's grains are of unit size).
    pub step_sizes: [f64; 2],
}

impl Default for Relaxation {
    fn default() -> Self {
        Relaxation {
            energy: EnergyKind::AllPairs,
            minimiser: Minimiser::Fire,
            // Paper, section 2.2: h_c = 0.1, h_R = 0.4.
            step_sizes: [0.1, 0.4],
        }
    }
}

/// A rigid grain shape: spheres (offset in the body frame, radius).
#[derive(Clone, Debug)]
pub struct Shape {
    pub offsets: Vec<V3>,
    pub radii: Vec<f64>,
    /// max |offset| + radius.
    pub bound: f64,
}

impl Shape {
    pub fn new(spheres: impl IntoIterator<Item = ([f64; 3], f64)>) -> Self {
        let (offsets, radii): (Vec<V3>, Vec<f64>) =
            spheres.into_iter().map(|(o, r)| (V3::from(o), r)).unzip();
        let bound = offsets
            .iter()
            .zip(&radii)
            .map(|(o, r)| o.norm() + r)
            .fold(0.0, f64::max);
        Shape {
            offsets,
            radii,
            bound,
        }
    }
}

#[derive(Clone, Debug)]
pub struct Grain {
    pub shape: usize,
    pub pos: V3,
    pub rot: UnitQuaternion<f64>,
    pub frozen: bool,
    /// Soft box on the centroid's z (Remark 4), `None` in mcm.classic.
    pub zbox: Option<(f64, f64)>,
}

/// Sphere index pairs (a of i, b of j) of one body's Verlet list.
type SpherePairs = Vec<(u32, u32)>;

/// One neighbour image: body `j` displaced by `shift` (periodic image, already including the
/// offset between wrapped and unwrapped positions at list-build time).
#[derive(Clone, Copy, Debug)]
struct Nb {
    j: usize,
    shift: V3,
    /// Candidate sphere pairs (a of i, b of j) of this clump pair: `pairs[i][first..last]`.
    first: u32,
    last: u32,
}

pub struct System {
    pub shapes: Vec<Shape>,
    pub grains: Vec<Grain>,
    /// Periodic cell size.
    pub cell: [f64; 3],
    /// Gap added to every sphere pair's contact distance (Remark 5 plus the convergence margin).
    pub gap: f64,
    /// Overlap tolerance: converged when every delta_ij and every box violation is below it.
    pub tol: f64,
    /// Part of `gap` that is convergence margin, not asked-for distance: the reported
    /// energy uses `gap - margin`, the user's minimum gap.
    pub margin: f64,
    pub relaxation: Relaxation,
    nbs: Vec<Vec<Nb>>,
    /// Sphere-level Verlet lists (Remark 3): per body, the sphere pairs within the skin.
    pairs: Vec<SpherePairs>,
    /// Centroids and orientations when the lists were built: a list stays valid while every
    /// grain's displacement from there (|dx| + b |dtheta|, a bound on any of its spheres'
    /// displacement) is below half the skin. Measured from the build state, not summed along
    /// the path: FIRE oscillates near convergence, and a summed path would rebuild the lists
    /// every few iterations for nothing.
    built_at: Vec<(V3, UnitQuaternion<f64>)>,
    /// The lists must be rebuilt before the next evaluation (grains added or moved
    /// collectively by a contraction, a shake or a relocation).
    stale: bool,
    /// First sphere of each grain in the flat array of world offsets.
    first: Vec<usize>,
    skin: f64,
    /// Every grain is a single sphere (set by `rebuild`): no rotations, no clump machinery.
    spheres: bool,
}

/// Grains already placed, in a periodic cell list of their wrapped centroids: what a new
/// grain is checked against when it is placed or relocated.
pub struct Neighbourhood {
    cells: CellList,
    wrapped: Vec<V3>,
    bmax: f64,
}

impl Neighbourhood {
    /// An empty neighbourhood in the system's current cell.
    pub fn new(sys: &System) -> Self {
        let bmax = sys.shapes.iter().map(|s| s.bound).fold(0.0, f64::max);
        Neighbourhood {
            cells: CellList::new([0.0; 3], sys.cell, [true; 3], 2.0 * bmax + sys.gap),
            wrapped: vec![V3::zeros(); sys.grains.len()],
            bmax,
        }
    }

    /// Adds grain `j` at its current position.
    pub fn add(&mut self, sys: &System, j: usize) {
        let dims = self.cells.dims();
        let w = V3::from([0, 1, 2].map(|a| {
            let l = sys.cell[a];
            let w = sys.grains[j].pos[a].rem_euclid(l);
            // As in `System::rebuild`: a position within rounding of the period is stored in
            // cell 0, so its images are reported from w - l.
            if (w / (l / dims[a] as f64)).floor() as usize >= dims[a] {
                w - l
            } else {
                w
            }
        }));
        if self.wrapped.len() <= j {
            self.wrapped.resize(j + 1, V3::zeros());
        }
        self.wrapped[j] = w;
        self.cells.insert(j as u32, w.into());
    }
}

/// Outcome of one minimisation.
#[derive(Clone, Copy, Debug)]
pub struct Minimised {
    /// Every violation within the tolerance. A minimisation also stops unconverged when it
    /// stalls: the largest violation did not fall by a tenth over `STALL_WINDOW` iterations
    /// (a jammed configuration; more iterations would not help).
    pub converged: bool,
    pub iterations: usize,
    /// eq. (2.6) at the user's minimum gap, plus the soft-box penalty [m^2].
    pub energy: f64,
    pub max_delta: f64,
    pub worst: Worst,
}

/// Where the largest violation sits.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Worst {
    #[default]
    None,
    /// Overlap (with the padded gap) between grains i and j.
    Pair(usize, usize),
    /// Centroid of grain i outside its layer's soft box.
    Box(usize),
}

impl std::fmt::Display for Worst {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Worst::None => write!(f, "none"),
            Worst::Pair(i, j) => write!(f, "between grains {i} and {j}"),
            Worst::Box(i) => write!(f, "centroid of grain {i} outside its layer (soft box)"),
        }
    }
}

/// One body's share of an evaluation: its own force and torque, the reactions on the
/// higher-index mobile grains it is paired with, its part of the energy and violations.
#[derive(Default)]
struct BodyEval {
    force: V3,
    torque: V3,
    reactions: Vec<(usize, V3, V3)>,
    minimised: f64,
    reported: f64,
    max_violation: f64,
    worst: Worst,
}

struct Eval {
    worst: Worst,
    /// The energy whose gradient `force`/`torque` are (with the padded gap).
    minimised: f64,
    force: Vec<V3>,
    torque: Vec<V3>,
    /// eq. (2.6) with the user's gap plus the box penalty, for reports.
    reported: f64,
    max_violation: f64,
}

/// Verlet skin in mean bounding radii: lists hold every sphere pair within this distance of
/// touching and are rebuilt after half of it of motion.
const SKIN: f64 = 0.1;
/// Verlet skin for packings of single spheres, in radii.
const SKIN_SPHERES: f64 = 0.3;
/// Largest packing of single spheres evaluated serially by `evaluate_spheres`; above it the
/// generic parallel path (the same numbers) spreads the work over the threads.
const SPHERES_SERIAL_MAX: usize = 20_000;
/// Bodies per rayon task: below this, scheduling costs more than the contacts of a body.
const PAR_MIN: usize = 32;

/// Iterations over which the largest violation must fall by a tenth, else the minimisation
/// is stalled (jammed) and stops early.
const STALL_WINDOW: usize = 300;

/// Unit vector pushing sphere a of i away from sphere b of j (d = p_a - p_b); falls back to
/// the centroid separation, then to x, when the centres coincide.
fn contact_normal(d: V3, dist: f64, sep: V3) -> V3 {
    if dist > 1e-300 {
        d / dist
    } else if sep.norm() > 1e-300 {
        sep / sep.norm()
    } else {
        V3::x()
    }
}

/// Remark 4's soft box: the signed distance that brings a centroid at height `z` back into
/// `[lo, hi]` (0 inside); it is both the penalty force along z and the excursion.
fn box_push(z: f64, lo: f64, hi: f64) -> f64 {
    if z < lo {
        lo - z
    } else if z > hi {
        hi - z
    } else {
        0.0
    }
}

impl System {
    pub fn new(shapes: Vec<Shape>, grains: Vec<Grain>, cell: [f64; 3], gap: f64, tol: f64) -> Self {
        let n = grains.len();
        System {
            shapes,
            grains,
            cell,
            gap,
            tol,
            margin: 0.0,
            relaxation: Relaxation::default(),
            nbs: vec![Vec::new(); n],
            pairs: vec![Vec::new(); n],
            built_at: Vec::new(),
            stale: true,
            first: Vec::new(),
            skin: 0.0,
            spheres: false,
        }
    }

    fn bound(&self, i: usize) -> f64 {
        self.shapes[self.grains[i].shape].bound
    }

    /// Rebuilds the Verlet lists (Remark 3): a cell list over bounding spheres with every
    /// periodic image inside the cut-off (so cells thinner than a grain are handled), then,
    /// per clump pair whose bounding spheres come within the skin, the sphere pairs that do.
    /// Frozen grains get no lists: their pairs are evaluated from the mobile side; a pair of
    /// mobile grains is listed once, on the lower index.
    pub fn rebuild(&mut self) {
        let spheres = self.shapes.iter().all(|s| s.radii.len() == 1);
        self.rebuild_lists(spheres);
    }

    /// `rebuild`, through the single-sphere shortcuts when `spheres` (the same lists).
    fn rebuild_lists(&mut self, spheres: bool) {
        let n = self.grains.len();
        self.skin = self.skin_width();
        self.spheres = spheres;
        self.index_spheres();
        let bmax = (0..n).map(|i| self.bound(i)).fold(0.0, f64::max);
        let cut = 2.0 * bmax + self.gap + self.skin;
        let l = self.cell;
        let mut cells = CellList::new([0.0; 3], l, [true; 3], cut);
        // Cell edges as the cell list computes them: a wrapped position within rounding of
        // the period lands in cell 0, where its images are reported from `w - l`.
        let dims = cells.dims();
        let edge: [f64; 3] = [0, 1, 2].map(|a| l[a] / dims[a] as f64);
        let mut wrapped = Vec::with_capacity(n);
        for (i, g) in self.grains.iter().enumerate() {
            let w: [f64; 3] = [0, 1, 2].map(|a| g.pos[a].rem_euclid(l[a]));
            cells.insert(i as u32, w);
            wrapped.push(V3::from([0, 1, 2].map(|a| {
                if (w[a] / edge[a]).floor() as usize >= dims[a] {
                    w[a] - l[a]
                } else {
                    w[a]
                }
            })));
        }
        let world = self.world();
        let first = &self.first;
        let grains = &self.grains;
        let shapes = &self.shapes;
        let reach_gap = self.gap + self.skin;
        let lists: Vec<(Vec<Nb>, SpherePairs)> = (0..n)
            .into_par_iter()
            .with_min_len(PAR_MIN)
            .map(|i| {
                let mut nbs = Vec::new();
                let mut pairs = Vec::new();
                if grains[i].frozen {
                    return (nbs, pairs);
                }
                let wi = wrapped[i];
                let si = &shapes[grains[i].shape];
                // Every periodic image within the cut-off, also when the cell is thinner
                // than a grain.
                cells.visit(wi.into(), cut, |j, img| {
                    let (j, img) = (j as usize, V3::from(img));
                    if j == i && img == V3::zeros() {
                        return true;
                    }
                    // Two mobile grains: listed once, on the lower index.
                    if j < i && !grains[j].frozen {
                        return true;
                    }
                    let wj = wrapped[j];
                    let sj = &shapes[grains[j].shape];
                    let sep = wi - (wj + img);
                    if sep.norm() >= si.bound + sj.bound + reach_gap {
                        return true;
                    }
                    // shift such that pos_i - (pos_j + shift) = sep
                    let shift = img + (wj - grains[j].pos) - (wi - grains[i].pos);
                    let pi = grains[i].pos;
                    let cj = grains[j].pos + shift;
                    if spheres {
                        // The tests below for one sphere each (offsets are zero, bounds are
                        // radii), without the candidate vector.
                        if (pi - cj).norm() < si.bound + sj.bound + reach_gap {
                            let first = pairs.len() as u32;
                            pairs.push((0, 0));
                            nbs.push(Nb {
                                j,
                                shift,
                                first,
                                last: first + 1,
                            });
                        }
                        return true;
                    }
                    // Remark 3: only spheres inside the other's bounding sphere.
                    let wj = &world[first[j]..first[j] + sj.radii.len()];
                    let wi = &world[first[i]..first[i] + si.radii.len()];
                    let near_j: Vec<u32> = (0..sj.radii.len())
                        .filter(|&b| (cj + wj[b] - pi).norm() < sj.radii[b] + si.bound + reach_gap)
                        .map(|b| b as u32)
                        .collect();
                    let first = pairs.len() as u32;
                    for (a, oa) in wi.iter().enumerate() {
                        let pa = pi + oa;
                        if (pa - cj).norm() >= si.radii[a] + sj.bound + reach_gap {
                            continue;
                        }
                        for &b in &near_j {
                            let pb = cj + wj[b as usize];
                            if (pa - pb).norm() < si.radii[a] + sj.radii[b as usize] + reach_gap {
                                pairs.push((a as u32, b));
                            }
                        }
                    }
                    let last = pairs.len() as u32;
                    if last > first {
                        nbs.push(Nb {
                            j,
                            shift,
                            first,
                            last,
                        });
                    }
                    true
                });
                (nbs, pairs)
            })
            .collect();
        (self.nbs, self.pairs) = lists.into_iter().unzip();
        self.built_at = self.grains.iter().map(|g| (g.pos, g.rot)).collect();
        self.stale = false;
    }

    /// Verlet skin: `SKIN` mean bounding radii for clumps; `SKIN_SPHERES` when every grain
    /// is a single sphere (a sphere pair costs no more than a grain pair there, so a wider
    /// skin trades a few more listed pairs for far fewer rebuilds).
    fn skin_width(&self) -> f64 {
        let n = self.grains.len();
        let bmean = (0..n).map(|i| self.bound(i)).sum::<f64>() / n.max(1) as f64;
        let spheres_only = self.shapes.iter().all(|s| s.radii.len() == 1);
        bmean * if spheres_only { SKIN_SPHERES } else { SKIN }
    }

    /// The flat sphere numbering: grain i owns world offsets `first[i]..first[i + 1]`.
    fn index_spheres(&mut self) {
        self.first.clear();
        let mut k = 0;
        for g in &self.grains {
            self.first.push(k);
            k += self.shapes[g.shape].radii.len();
        }
        self.first.push(k);
    }

    /// Body-frame offsets rotated to the world frame, one flat array for every sphere (no
    /// allocation per grain: with single-sphere grains the per-grain vectors cost more than
    /// the contacts).
    fn world(&self) -> Vec<V3> {
        let mut w = Vec::with_capacity(self.first.last().copied().unwrap_or(0));
        for g in &self.grains {
            w.extend(self.shapes[g.shape].offsets.iter().map(|o| g.rot * o));
        }
        w
    }

    /// Largest displacement bound (|dx| + b |dtheta|) of any mobile grain since the lists were
    /// built.
    fn max_displacement(&self) -> f64 {
        if self.spheres {
            // A sphere's orientation never changes (its torque is zero): no angle to add.
            return self
                .grains
                .iter()
                .zip(&self.built_at)
                .filter(|(g, _)| !g.frozen)
                .map(|(g, (p0, _))| (g.pos - p0).norm())
                .fold(0.0, f64::max);
        }
        self.grains
            .iter()
            .zip(&self.built_at)
            .enumerate()
            .filter(|(_, (g, _))| !g.frozen)
            .map(|(i, (g, (p0, r0)))| {
                (g.pos - p0).norm() + self.bound(i) * (g.rot * r0.inverse()).angle()
            })
            .fold(0.0, f64::max)
    }

    /// Forces = -grad_c E and torques = -grad_R E (as axial vectors) of the chosen overlap
    /// energy plus the soft-box penalty, and eq. (2.6) at the user's gap for reports. Each body's force is summed over its own neighbour list in list
    /// order, so the result does not depend on the number of threads.
    fn evaluate(&self) -> Eval {
        if self.spheres && self.grains.len() <= SPHERES_SERIAL_MAX {
            return self.evaluate_spheres();
        }
        let world = self.world();
        let first = &self.first;
        let gap = self.gap;
        let margin = self.margin;
        let kind = self.relaxation.energy;
        let per: Vec<BodyEval> = (0..self.grains.len())
            .into_par_iter()
            .with_min_len(PAR_MIN)
            .map(|i| {
                let gi = &self.grains[i];
                let si = &self.shapes[gi.shape];
                let mut out = BodyEval::default();
                if gi.frozen {
                    // Frozen grains do not move: their pairs with mobile grains are counted
                    // from the mobile side, frozen-frozen overlaps and frozen soft boxes are
                    // constants of the layer being packed (at most the previous layer's tol).
                    return out;
                }
                for nb in &self.nbs[i] {
                    let gj = &self.grains[nb.j];
                    let sj = &self.shapes[gj.shape];
                    let cj = gj.pos + nb.shift;
                    // A pair of two mobile grains is listed once (on the lower index) and
                    // pushes both; a self-image pair is met from both images, each half.
                    let mutual = !gj.frozen && nb.j != i;
                    let w = if nb.j == i { 0.25 } else { 0.5 };
                    let (mut fj, mut tj) = (V3::zeros(), V3::zeros());
                    let wi = &world[first[i]..first[i + 1]];
                    let wj = &world[first[nb.j]..first[nb.j + 1]];
                    let mut push = |a: usize, b: usize, fa: V3| {
                        out.minimised += w * fa.norm_squared();
                        out.force += fa;
                        out.torque += wi[a].cross(&fa);
                        if mutual {
                            fj -= fa;
                            tj -= wj[b].cross(&fa);
                        }
                    };
                    // eq. (2.4): delta_ij is the largest sphere-pair overlap.
                    let mut best = 0.0;
                    let mut arg: Option<(usize, usize, V3)> = None;
                    for &(a, b) in &self.pairs[i][nb.first as usize..nb.last as usize] {
                        let (a, b) = (a as usize, b as usize);
                        let d = gi.pos + wi[a] - (cj + wj[b]);
                        let dist = d.norm();
                        let delta = si.radii[a] + sj.radii[b] + gap - dist;
                        if delta <= 0.0 {
                            continue;
                        }
                        if kind == EnergyKind::AllPairs {
                            push(a, b, contact_normal(d, dist, gi.pos - cj) * delta);
                        }
                        if delta > best {
                            best = delta;
                            arg = Some((a, b, d));
                        }
                    }
                    if let Some((a, b, d)) = arg {
                        if kind == EnergyKind::MaxPair {
                            // -dE/dc_i of 1/2 delta_ij^2: only the deepest pair pushes.
                            push(a, b, contact_normal(d, d.norm(), gi.pos - cj) * best);
                        }
                        let true_delta = (best - margin).max(0.0);
                        out.reported += w * true_delta * true_delta;
                        if best > out.max_violation {
                            out.max_violation = best;
                            out.worst = Worst::Pair(i, nb.j);
                        }
                    }
                    if mutual && (fj != V3::zeros() || tj != V3::zeros()) {
                        out.reactions.push((nb.j, fj, tj));
                    }
                }
                if let Some((lo, hi)) = gi.zbox {
                    // Remark 4: soft box on the centroid, quadratic penalty.
                    let v = box_push(gi.pos.z, lo, hi);
                    out.force.z += v;
                    out.minimised += 0.5 * v * v;
                    // The box is padded by `margin` like the gap: report the true excursion.
                    let outside = (v.abs() - margin).max(0.0);
                    out.reported += 0.5 * outside * outside;
                    if v.abs() > out.max_violation {
                        out.max_violation = v.abs();
                        out.worst = Worst::Box(i);
                    }
                }
                out
            })
            .collect();
        // Sequential reduction in body order: the same sums for any number of threads.
        let mut ev = Eval {
            worst: Worst::None,
            force: per.iter().map(|p| p.force).collect(),
            torque: per.iter().map(|p| p.torque).collect(),
            minimised: 0.0,
            reported: 0.0,
            max_violation: 0.0,
        };
        for p in &per {
            ev.minimised += p.minimised;
            for &(j, f, t) in &p.reactions {
                ev.force[j] += f;
                ev.torque[j] += t;
            }
            ev.reported += p.reported;
            if p.max_violation > ev.max_violation {
                ev.max_violation = p.max_violation;
                ev.worst = p.worst;
            }
        }
        ev
    }

    /// `evaluate` for packings of single spheres, serial and without the clump machinery
    /// (body-frame offsets, torques, per-body allocations): the same operations in the same
    /// order, so the same numbers bit for bit, several times cheaper per iteration (a body's
    /// own force first, in list order; then the reactions on the higher-index bodies in body
    /// order, as the generic path's reduction adds them).
    fn evaluate_spheres(&self) -> Eval {
        let n = self.grains.len();
        let (gap, margin) = (self.gap, self.margin);
        let mut ev = Eval {
            worst: Worst::None,
            force: vec![V3::zeros(); n],
            torque: vec![V3::zeros(); n],
            minimised: 0.0,
            reported: 0.0,
            max_violation: 0.0,
        };
        let mut reactions: Vec<(u32, V3)> = Vec::with_capacity(4 * n);
        // Flat copies: the grain and shape structs are large and the radius sits behind two
        // indirections; the pair loop reads these for every neighbour.
        let pos: Vec<V3> = self.grains.iter().map(|g| g.pos).collect();
        let rad: Vec<f64> = self
            .grains
            .iter()
            .map(|g| self.shapes[g.shape].radii[0])
            .collect();
        let frozen: Vec<bool> = self.grains.iter().map(|g| g.frozen).collect();
        for i in 0..n {
            let gi = &self.grains[i];
            if gi.frozen {
                continue;
            }
            let (pi, ri) = (pos[i], rad[i]);
            let (mut force, mut minimised, mut reported) = (V3::zeros(), 0.0, 0.0);
            let (mut max_violation, mut worst) = (0.0, Worst::None);
            for nb in &self.nbs[i] {
                let rj = rad[nb.j];
                let cj = pos[nb.j] + nb.shift;
                let mutual = !frozen[nb.j] && nb.j != i;
                let w = if nb.j == i { 0.25 } else { 0.5 };
                // One sphere pair per neighbour; its overlap is also delta_ij (eq. 2.4), so
                // both energies push with it.
                let d = pi - cj;
                let dist = d.norm();
                let delta = ri + rj + gap - dist;
                if delta <= 0.0 {
                    continue;
                }
                let fa = contact_normal(d, dist, d) * delta;
                minimised += w * fa.norm_squared();
                force += fa;
                if mutual {
                    reactions.push((nb.j as u32, V3::zeros() - fa));
                }
                let true_delta = (delta - margin).max(0.0);
                reported += w * true_delta * true_delta;
                if delta > max_violation {
                    max_violation = delta;
                    worst = Worst::Pair(i, nb.j);
                }
            }
            if let Some((lo, hi)) = gi.zbox {
                let v = box_push(gi.pos.z, lo, hi);
                force.z += v;
                minimised += 0.5 * v * v;
                let outside = (v.abs() - margin).max(0.0);
                reported += 0.5 * outside * outside;
                if v.abs() > max_violation {
                    max_violation = v.abs();
                    worst = Worst::Box(i);
                }
            }
            ev.force[i] = force;
            ev.minimised += minimised;
            ev.reported += reported;
            if max_violation > ev.max_violation {
                ev.max_violation = max_violation;
                ev.worst = worst;
            }
        }
        // The generic path starts every body's force from its own sum and adds the reactions
        // afterwards, in body order then list order: deferred to here, they keep that order.
        for (j, f) in reactions {
            ev.force[j as usize] += f;
        }
        ev
    }

    /// Current overlap energy (eq. 2.6 at the user's gap, plus box penalty) and largest
    /// violation (with the padded gap).
    pub fn energy(&mut self) -> (f64, f64) {
        self.rebuild();
        let e = self.evaluate();
        (e.reported, e.max_violation)
    }

    /// Overlap removal: FIRE or gradient descent (eq. 2.8) on centroids and rotation vectors
    /// scaled by the bounding radius (so both are lengths with unit mass). Orientation
    /// updates are R <- exp([omega]x) R (eq. 2.8). Stops when every violation is below `tol`.
    pub fn minimise(&mut self, max_iter: usize) -> Minimised {
        const N_MIN: usize = 5;
        const F_INC: f64 = 1.1;
        const F_DEC: f64 = 0.5;
        const ALPHA0: f64 = 0.1;
        const F_ALPHA: f64 = 0.99;
        let n = self.grains.len();
        let b: Vec<f64> = (0..n).map(|i| self.bound(i)).collect();
        let bmin = b.iter().cloned().fold(f64::INFINITY, f64::min);
        // Forces are overlaps (lengths) with unit stiffness: dt ~ 0.1-0.5 is stable for a
        // dozen contacts per grain.
        let dt_max = 0.5;
        let mut dt = 0.1;
        let mut alpha = ALPHA0;
        let mut npos = 0usize;
        // No grain moves more than a tenth of the smallest grain per iteration, whatever
        // the forces: keeps the Verlet lists valid and the iteration stable.
        let max_step = 0.1 * bmin;
        let mut v = vec![V3::zeros(); n];
        let mut w = vec![V3::zeros(); n];
        if self.stale || self.built_at.len() != n {
            self.rebuild();
        }
        let [h_c, h_r] = self.relaxation.step_sizes;
        let mut ev = self.evaluate();
        let (mut window_best, mut previous_best) = (f64::INFINITY, f64::INFINITY);
        for it in 0..max_iter {
            if ev.max_violation <= self.tol {
                return Minimised {
                    converged: true,
                    iterations: it,
                    energy: ev.reported,
                    max_delta: ev.max_violation,
                    worst: ev.worst,
                };
            }
            window_best = window_best.min(ev.max_violation);
            if it > 0 && it % STALL_WINDOW == 0 {
                if window_best > 0.9 * previous_best {
                    return Minimised {
                        converged: false,
                        iterations: it,
                        energy: ev.reported,
                        max_delta: ev.max_violation,
                        worst: ev.worst,
                    };
                }
                previous_best = previous_best.min(window_best);
                window_best = f64::INFINITY;
            }
            // Generalised force on (b theta): torque / b.
            let gf: Vec<V3> = (0..n).map(|i| ev.torque[i] / b[i]).collect();
            if self.relaxation.minimiser == Minimiser::Fire {
                let mut p = 0.0;
                let mut vn = 0.0;
                let mut fnorm = 0.0;
                for i in 0..n {
                    p += ev.force[i].dot(&v[i]) + gf[i].dot(&w[i]);
                    vn += v[i].norm_squared() + w[i].norm_squared();
                    fnorm += ev.force[i].norm_squared() + gf[i].norm_squared();
                }
                let (vn, fnorm) = (vn.sqrt(), fnorm.sqrt());
                if p > 0.0 {
                    if fnorm > 0.0 {
                        let c = alpha * vn / fnorm;
                        for i in 0..n {
                            v[i] = v[i] * (1.0 - alpha) + ev.force[i] * c;
                            w[i] = w[i] * (1.0 - alpha) + gf[i] * c;
                        }
                    }
                    npos += 1;
                    if npos > N_MIN {
                        dt = (dt * F_INC).min(dt_max);
                        alpha *= F_ALPHA;
                    }
                } else {
                    npos = 0;
                    dt *= F_DEC;
                    alpha = ALPHA0;
                    v.iter_mut().for_each(|x| *x = V3::zeros());
                    w.iter_mut().for_each(|x| *x = V3::zeros());
                }
            }
            for i in 0..n {
                if self.grains[i].frozen {
                    continue;
                }
                let (mut dx, mut dth) = match self.relaxation.minimiser {
                    Minimiser::Fire => {
                        v[i] += ev.force[i] * dt;
                        w[i] += gf[i] * dt;
                        (v[i] * dt, w[i] * dt)
                    }
                    // eq. (2.8): c <- c - h_c grad_c E, (b theta) <- (b theta) - h_R grad.
                    Minimiser::GradientDescent => (ev.force[i] * h_c, gf[i] * h_r),
                };
                let s = (dx.norm() + dth.norm()) / max_step;
                if s > 1.0 {
                    dx /= s;
                    dth /= s;
                }
                self.grains[i].pos += dx;
                // eq. (2.8): rotation through the exponential map of the axial vector.
                let ang = dth / b[i];
                self.grains[i].rot = UnitQuaternion::from_scaled_axis(ang) * self.grains[i].rot;
            }
            if 2.0 * self.max_displacement() > self.skin {
                self.rebuild();
            }
            ev = self.evaluate();
        }
        Minimised {
            converged: ev.max_violation <= self.tol,
            iterations: max_iter,
            energy: ev.reported,
            max_delta: ev.max_violation,
            worst: ev.worst,
        }
    }

    /// Thermalisation at fixed size (not in the paper): Langevin dynamics on the same overlap
    /// energy (eq. 2.6 with all pairs, or eq. 2.4-2.6) and the same generalised coordinates as
    /// `minimise` (centroid, b theta; unit mass, unit stiffness), with friction `gamma` and a
    /// temperature falling linearly from `temperature` [m^2, i.e. a mean kinetic energy per
    /// degree of freedom of temperature / 2] to zero over `steps` steps. A minimisation from
    /// a jammed configuration stops in the nearest minimum of the energy landscape (a quench,
    /// jamming near 0.63-0.64 for equal spheres); thermal motion lets the grains cross the
    /// low barriers between minima towards denser, unjammed arrangements, as the
    /// Lubachevsky-Stillinger dynamics do. The noise comes from `rng`, drawn in body order,
    /// and the forces are reduced in body order: the trajectory does not depend on the
    /// number of threads. Returns the steps taken (each costs one energy evaluation).
    pub fn anneal(
        &mut self,
        steps: usize,
        temperature: f64,
        rng: &mut rand_chacha::ChaCha8Rng,
    ) -> usize {
        use rand::RngExt;
        // Unit stiffness and about a dozen contacts: dt = 0.1 resolves the contact period
        // (2 pi / sqrt(12) ~ 1.8) with ~20 steps; gamma = 0.2 damps a contact in a few periods.
        const DT: f64 = 0.1;
        const GAMMA: f64 = 0.2;
        let n = self.grains.len();
        if steps == 0 || n == 0 || temperature <= 0.0 {
            return 0;
        }
        let b: Vec<f64> = (0..n).map(|i| self.bound(i)).collect();
        let bmin = b.iter().cloned().fold(f64::INFINITY, f64::min);
        let max_step = 0.1 * bmin;
        let rotates: Vec<bool> = (0..n)
            .map(|i| self.shapes[self.grains[i].shape].radii.len() > 1)
            .collect();
        let mut v = vec![V3::zeros(); n];
        let mut w = vec![V3::zeros(); n];
        if self.stale || self.built_at.len() != n {
            self.rebuild();
        }
        let gauss = |rng: &mut rand_chacha::ChaCha8Rng| -> V3 {
            // Box-Muller, three normal deviates (the fourth is dropped: simpler, still exact).
            let mut g = [0.0; 4];
            for k in 0..2 {
                let u1: f64 = 1.0 - rng.random::<f64>();
                let u2: f64 = rng.random::<f64>();
                let r = (-2.0 * u1.ln()).sqrt();
                g[2 * k] = r * (2.0 * std::f64::consts::PI * u2).cos();
                g[2 * k + 1] = r * (2.0 * std::f64::consts::PI * u2).sin();
            }
            V3::new(g[0], g[1], g[2])
        };
        let mut ev = self.evaluate();
        for step in 0..steps {
            let t = temperature * (1.0 - step as f64 / steps as f64);
            // Euler-Maruyama of dv = (F - gamma v) dt + sqrt(2 gamma T) dW.
            let kick = (2.0 * GAMMA * t * DT).sqrt();
            for i in 0..n {
                if self.grains[i].frozen {
                    continue;
                }
                v[i] = v[i] * (1.0 - GAMMA * DT) + ev.force[i] * DT + gauss(rng) * kick;
                if rotates[i] {
                    w[i] = w[i] * (1.0 - GAMMA * DT) + ev.torque[i] / b[i] * DT + gauss(rng) * kick;
                }
                let (mut dx, mut dth) = (v[i] * DT, w[i] * DT);
                let s = (dx.norm() + dth.norm()) / max_step;
                if s > 1.0 {
                    dx /= s;
                    dth /= s;
                }
                self.grains[i].pos += dx;
                if rotates[i] {
                    self.grains[i].rot =
                        UnitQuaternion::from_scaled_axis(dth / b[i]) * self.grains[i].rot;
                }
            }
            if 2.0 * self.max_displacement() > self.skin {
                self.rebuild();
            }
            ev = self.evaluate();
        }
        steps
    }

    /// Largest overlap delta_ij (eq. 2.4, with the gap) of grain `i` against the grains in
    /// `near`, over every periodic image within reach (used for the initial placement and
    /// relocations: a cell list, so placing N grains costs O(N), not O(N^2)).
    pub fn max_overlap(&self, i: usize, near: &Neighbourhood) -> f64 {
        let gi = &self.grains[i];
        let si = &self.shapes[gi.shape];
        let pi = V3::from([0, 1, 2].map(|a| gi.pos[a].rem_euclid(self.cell[a])));
        let wi: Vec<V3> = si.offsets.iter().map(|o| pi + gi.rot * o).collect();
        let mut worst: f64 = 0.0;
        near.cells
            .visit(pi.into(), si.bound + near.bmax + self.gap, |j, img| {
                let j = j as usize;
                if j == i {
                    return true;
                }
                let gj = &self.grains[j];
                let sj = &self.shapes[gj.shape];
                let cj = near.wrapped[j] + V3::from(img);
                if (pi - cj).norm() >= si.bound + sj.bound + self.gap {
                    return true;
                }
                for (b, o) in sj.offsets.iter().enumerate() {
                    let pb = cj + gj.rot * o;
                    for (a, pa) in wi.iter().enumerate() {
                        let delta = si.radii[a] + sj.radii[b] + self.gap - (pa - pb).norm();
                        worst = worst.max(delta);
                    }
                }
                true
            });
        worst
    }

    /// Marks the lists stale (after a contraction moved every centroid).
    pub fn invalidate(&mut self) {
        self.stale = true;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two overlapping three-sphere clumps in a large cell.
    fn two_clumps(kind: EnergyKind) -> System {
        let shape = Shape::new([
            ([-1.0, 0.0, 0.0], 1.0),
            ([0.0, 0.3, 0.0], 1.2),
            ([1.1, 0.0, 0.2], 0.9),
        ]);
        let grains = vec![
            Grain {
                shape: 0,
                pos: V3::new(10.0, 10.0, 10.0),
                rot: UnitQuaternion::from_scaled_axis(V3::new(0.1, 0.2, 0.3)),
                frozen: false,
                zbox: None,
            },
            Grain {
                shape: 1,
                pos: V3::new(11.7, 11.1, 10.4),
                rot: UnitQuaternion::from_scaled_axis(V3::new(-0.4, 0.1, 0.7)),
                frozen: false,
                zbox: None,
            },
        ];
        let mut sys = System::new(vec![shape.clone(), shape], grains, [40.0; 3], 0.05, 1e-3);
        sys.relaxation.energy = kind;
        sys.rebuild();
        sys
    }

    #[test]
    fn forces_and_torques_are_minus_the_energy_gradient() {
        // Central finite differences of the minimised energy (an independent reference for
        // the hand-derived gradient), for translations and rotations of each grain.
        for kind in [EnergyKind::AllPairs, EnergyKind::MaxPair] {
            let mut sys = two_clumps(kind);
            let ev = sys.evaluate();
            assert!(ev.minimised > 0.01, "the clumps must overlap");
            let h = 1e-6;
            for i in 0..2 {
                for a in 0..3 {
                    let e = V3::ith(a, h);
                    let g0 = sys.grains[i].clone();
                    sys.grains[i].pos = g0.pos + e;
                    let up = sys.evaluate().minimised;
                    sys.grains[i].pos = g0.pos - e;
                    let down = sys.evaluate().minimised;
                    sys.grains[i].rot = UnitQuaternion::from_scaled_axis(e) * g0.rot;
                    sys.grains[i].pos = g0.pos;
                    let rot_up = sys.evaluate().minimised;
                    sys.grains[i].rot = UnitQuaternion::from_scaled_axis(-e) * g0.rot;
                    let rot_down = sys.evaluate().minimised;
                    sys.grains[i] = g0;
                    let fd_force = -(up - down) / (2.0 * h);
                    let fd_torque = -(rot_up - rot_down) / (2.0 * h);
                    assert!(
                        (ev.force[i][a] - fd_force).abs() < 1e-6,
                        "{kind:?} force {i}.{a}: {} vs {fd_force}",
                        ev.force[i][a]
                    );
                    assert!(
                        (ev.torque[i][a] - fd_torque).abs() < 1e-6,
                        "{kind:?} torque {i}.{a}: {} vs {fd_torque}",
                        ev.torque[i][a]
                    );
                }
            }
            // Newton's third law: the pair's forces cancel.
            assert!((ev.force[0] + ev.force[1]).norm() < 1e-12);
        }
    }

    /// Overlapping spheres of radii 0.6-1.0 in a periodic cell, some frozen, some in a soft
    /// box (so every branch of the evaluation is taken).
    fn spheres(frozen_and_boxed: bool) -> System {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let cell = [6.0, 5.0, 7.0];
        let n = 40;
        let shapes: Vec<Shape> = (0..n)
            .map(|_| Shape::new([([0.0; 3], 0.6 + 0.4 * rng.random::<f64>())]))
            .collect();
        let grains = (0..n)
            .map(|i| Grain {
                shape: i,
                pos: V3::from(cell.map(|l| l * rng.random::<f64>())),
                rot: UnitQuaternion::identity(),
                frozen: frozen_and_boxed && i % 7 == 3,
                zbox: (frozen_and_boxed && i % 5 == 1).then_some((2.0, 5.0)),
            })
            .collect();
        let mut sys = System::new(shapes, grains, cell, 0.05, 1e-3);
        sys.margin = 0.01;
        sys
    }

    #[test]
    fn sphere_shortcuts_give_the_clump_path_numbers_bit_for_bit() {
        // The serial single-sphere evaluation and list building promise the generic path's
        // numbers exactly (so trajectories and iteration counts do not change with them).
        type Lists = Vec<Vec<(usize, [f64; 3], u32, u32)>>;
        let lists = |sys: &System| -> Lists {
            sys.nbs
                .iter()
                .map(|l| {
                    l.iter()
                        .map(|b| (b.j, b.shift.into(), b.first, b.last))
                        .collect()
                })
                .collect()
        };
        let mut sys = spheres(true);
        sys.rebuild_lists(false);
        let slow_lists = lists(&sys);
        let (slow_pairs, slow) = (sys.pairs.clone(), sys.evaluate());
        sys.rebuild_lists(true);
        assert_eq!(slow_lists, lists(&sys));
        assert_eq!(slow_pairs, sys.pairs);
        let fast = sys.evaluate();
        assert!(slow.max_violation > 0.1, "the spheres must overlap");
        assert_eq!(slow.force, fast.force);
        assert_eq!(slow.torque, fast.torque);
        assert_eq!(slow.minimised.to_bits(), fast.minimised.to_bits());
        assert_eq!(slow.reported.to_bits(), fast.reported.to_bits());
        assert_eq!(slow.max_violation.to_bits(), fast.max_violation.to_bits());
        assert_eq!(slow.worst, fast.worst);
    }

    #[test]
    fn sphere_energy_and_forces_match_a_brute_force_sum() {
        // Independent reference: every pair once under the minimum image (the cell is wider
        // than two contact distances), 1/2 delta^2 with the padded gap, force delta n.
        let mut sys = spheres(false);
        sys.rebuild();
        let ev = sys.evaluate();
        let n = sys.grains.len();
        let (mut e, mut f) = (0.0, vec![V3::zeros(); n]);
        for i in 0..n {
            for j in i + 1..n {
                let d = V3::from([0, 1, 2].map(|a| {
                    let l = sys.cell[a];
                    let x = sys.grains[i].pos[a] - sys.grains[j].pos[a];
                    x - l * (x / l).round()
                }));
                let delta = sys.shapes[i].radii[0] + sys.shapes[j].radii[0] + sys.gap - d.norm();
                if delta > 0.0 {
                    e += 0.5 * delta * delta;
                    f[i] += d / d.norm() * delta;
                    f[j] -= d / d.norm() * delta;
                }
            }
        }
        assert!(e > 0.01, "the spheres must overlap");
        assert!(
            (ev.minimised - e).abs() < 1e-12 * e,
            "{} vs {e}",
            ev.minimised
        );
        for (i, (got, want)) in ev.force.iter().zip(&f).enumerate() {
            assert!((got - want).norm() < 1e-12, "{i}: {got} vs {want}");
        }
    }

    #[test]
    fn both_energies_are_zero_exactly_when_nothing_overlaps() {
        for kind in [EnergyKind::AllPairs, EnergyKind::MaxPair] {
            let mut sys = two_clumps(kind);
            sys.grains[1].pos.x += 10.0;
            sys.rebuild();
            let ev = sys.evaluate();
            assert_eq!(ev.minimised, 0.0);
            assert_eq!(ev.max_violation, 0.0);
            assert!(ev.force.iter().all(|f| *f == V3::zeros()));
        }
    }
}
