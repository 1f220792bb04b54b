//! The unit-brick filler shared by `bricks.method1`, `bricks.method2` and `bricks.curved`.
//!
//! Paper (sphere filling, sections 2.1, 3, 4): corners get mean-radius spheres, then edges,
//! then faces, then the volume. Every new sphere has a radius drawn from the target law and is
//! placed in contact with "parent" spheres -- two parents on a face, three in the volume --
//! by solving the tangency system of section 2.1 (`|x_n - x_i| = R_i + r`, both roots);
//! a position is rejected when the sphere would overlap another one or leave the domain.
//! Parents are spheres whose gaps are at most `parent_parameter * mean radius`. A radius that
//! fits no parent set is discarded and a new one drawn.
//!
//! Speed comes from three things the Matlab code does not have: a cell list for overlap and
//! parent queries; parent sets ("sites") enumerated once, when their youngest member is placed;
//! and per-site memory of the smallest radius that failed there (a larger sphere at the same
//! pocket fails too, to the approximation that pockets are convex), so a draw skips sites that
//! cannot hold it. A site is retired when the smallest sphere that can touch all its parents
//! is blocked there.
//!
//! Two modes: `Closed` (Method 1 and signed-distance domains): every sphere lies inside the
//! domain and boundary spheres touch the box faces; `Centered` (Method 2): the box is periodic,
//! boundary spheres are centred on the faces, and only the three faces through the origin
//! (and one edge per axis, one corner) are filled -- their copies on the opposite faces are the
//! periodic images, which is what makes translated bricks fit seamlessly.

use crate::sdf::Sdf;
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::spatial::CellList;
use grainpipe_core::{RunContext, StageError};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Method 1 and signed-distance domains: spheres inside, boundary spheres touch faces.
    Closed,
    /// Method 2: periodic brick, boundary spheres centred on the faces.
    Centered,
}

/// Goals and tolerances of one fill.
#[derive(Clone, Debug)]
pub struct FillSettings {
    pub face_goal: f64,
    pub body_goal: f64,
    /// Parents are spheres within `parent_parameter * mean_radius` of each other.
    pub parent_parameter: f64,
    /// Stop a phase after this many rejected draws in a row.
    pub max_consecutive_rejections: u64,
    /// Stop a phase once this fraction of its draws (after 100) was rejected: bounds the
    /// distortion of the radius law, KS <= q / (1 - q).
    pub max_rejected_fraction: f64,
    /// Fail when a goal is missed (otherwise keep the saturated phase and go on).
    pub require_goals: bool,
    /// Faces filled in the face phase (Closed mode), in `FACE_NAMES` order.
    pub faces: [bool; 6],
    /// Stage id, for messages.
    pub stage: &'static str,
}

/// Why a fill stopped without a result.
#[derive(Debug, thiserror::Error)]
pub enum FillError {
    /// A face or the volume saturated below its goal (with `require_goals`).
    #[error(
        "{stage}: {what} after {draws} draws ({rejected} rejected in all): the {region} is \
         saturated, the phase stopped because {stop}; {advice}"
    )]
    Saturated {
        stage: &'static str,
        /// What was reached, e.g. "body fraction reached 0.61 < body_goal 0.95".
        what: String,
        draws: u64,
        rejected: u64,
        /// The condition that stopped the phase, with its numbers and parameter.
        stop: String,
        /// What to change: depends on whether this is an error (`require_goals: true`) or
        /// a warning about a fill that is kept.
        advice: &'static str,
        /// "face" or "volume".
        region: &'static str,
    },
    #[error("cancelled")]
    Cancelled,
}

impl From<FillError> for StageError {
    fn from(e: FillError) -> Self {
        match e {
            FillError::Cancelled => StageError::Cancelled,
            e => StageError::Failed(e.to_string()),
        }
    }
}

/// Consecutive rejections that close an edge (its last gap is too small for most draws).
const EDGE_REJECTIONS: u64 = 10;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Phase {
    Volume,
    /// Face index in `FACE_NAMES` order (Closed) or plane normal axis (Centered).
    Face(usize),
}

#[derive(Clone, Debug)]
struct Site {
    p: [[f64; 3]; 3],
    r: [f64; 3],
    /// Smallest radius found blocked here (larger ones are taken as blocked too).
    min_failed: f64,
    /// Largest radius known too small to touch all parents at once.
    too_small: f64,
    /// Smallest radius that touches all parents (0 until computed): the retirement probe.
    probe: f64,
    /// Last sphere that blocked each root: checked first, it usually blocks again.
    blocker: [u32; 2],
    dead: bool,
}

/// Statistics of a finished fill.
#[derive(Clone, Debug, Default)]
pub struct FillStats {
    pub draws: u64,
    pub rejected: u64,
    /// Coverage per face (Closed: `FACE_NAMES` order; Centered: the min face of each axis
    /// repeated on the max face).
    pub face_fraction: [f64; 6],
    pub body_fraction: f64,
    pub goals_reached: bool,
    pub domain_volume: f64,
    /// Faces that had a face phase (all six in Method 2).
    pub filled: [bool; 6],
}

pub struct Filler<'a> {
    pub mode: Mode,
    pub len: [f64; 3],
    pub sdf: &'a Sdf,
    pub pos: Vec<[f64; 3]>,
    pub rad: Vec<f64>,
    /// Closed: bit f = tangent to face f. Centered: bit a = centred on the plane `x_a = 0`.
    pub on_face: Vec<u8>,
    /// Whether the radius came from a draw (corner spheres have the mean radius).
    pub drawn: Vec<bool>,
    /// Cell lists of the spheres up to `split` and of the larger ones (coarser cells), so
    /// a long radius tail does not widen every query.
    grids: [CellList; 2],
    /// Largest radius in each cell list (0 while empty).
    grid_rmax: [f64; 2],
    split: f64,
    dist: &'a SizeDistribution,
    pub rmean: f64,
    r_floor: f64,
    tol: f64,
    parent_gap: f64,
    min_period: f64,
    face_area: [f64; 6],
    face_sum: [f64; 6],
    volume: f64,
    vol_sum: f64,
    rng: ChaCha8Rng,
    pub stats: FillStats,
    set: FillSettings,
    /// Why the last phase stopped short of its goal (for the saturation message).
    last_stop: String,
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn add_scaled(a: [f64; 3], b: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Centres at distances `d` from the three points `p` (trilateration), both roots.
/// This is the tangency system of the paper's section 2.1 with `d_i = R_i + r`.
fn trilaterate(p: &[[f64; 3]; 3], d: [f64; 3]) -> Option<[[f64; 3]; 2]> {
    let e1 = sub(p[1], p[0]);
    let dd = dot(e1, e1).sqrt();
    if dd == 0.0 {
        return None;
    }
    let ex = e1.map(|x| x / dd);
    let w = sub(p[2], p[0]);
    let i = dot(ex, w);
    let t = add_scaled(w, ex, -i);
    let tn = dot(t, t).sqrt();
    if tn < 1e-12 * dd {
        return None; // collinear parents: no unique plane
    }
    let ey = t.map(|x| x / tn);
    let ez = cross(ex, ey);
    let j = dot(ey, w);
    let x = (d[0] * d[0] - d[1] * d[1] + dd * dd) / (2.0 * dd);
    let y = (d[0] * d[0] - d[2] * d[2] + i * i + j * j) / (2.0 * j) - i / j * x;
    let z2 = d[0] * d[0] - x * x - y * y;
    if z2 < 0.0 {
        return None;
    }
    let z = z2.sqrt();
    let base = add_scaled(add_scaled(p[0], ex, x), ey, y);
    Some([add_scaled(base, ez, z), add_scaled(base, ez, -z)])
}

/// Points at distances `d1`, `d2` from the plane points `p1`, `p2` (circle intersection).
fn intersect2(p1: [f64; 2], p2: [f64; 2], d1: f64, d2: f64) -> Option<[[f64; 2]; 2]> {
    let dx = p2[0] - p1[0];
    let dy = p2[1] - p1[1];
    let dd = (dx * dx + dy * dy).sqrt();
    if dd == 0.0 || dd > d1 + d2 || dd < (d1 - d2).abs() {
        return None;
    }
    let a = (d1 * d1 - d2 * d2 + dd * dd) / (2.0 * dd);
    let h = (d1 * d1 - a * a).max(0.0).sqrt();
    let (ux, uy) = (dx / dd, dy / dd);
    let bx = p1[0] + a * ux;
    let by = p1[1] + a * uy;
    Some([[bx - h * uy, by + h * ux], [bx + h * uy, by - h * ux]])
}

fn wrap(x: f64, l: f64) -> f64 {
    let w = x.rem_euclid(l);
    if w >= l {
        0.0
    } else {
        w
    }
}

impl<'a> Filler<'a> {
    pub fn new(
        mode: Mode,
        len: [f64; 3],
        sdf: &'a Sdf,
        dist: &'a SizeDistribution,
        settings: FillSettings,
        rng: ChaCha8Rng,
    ) -> Self {
        let rmean = dist.mean();
        let periodic = [mode == Mode::Centered; 3];
        let grids = [
            CellList::new([0.0; 3], len, periodic, 2.0 * rmean),
            CellList::new([0.0; 3], len, periodic, 8.0 * rmean),
        ];
        let (face_area, volume) = match mode {
            Mode::Closed => {
                let lo = [0.0; 3];
                let mut fa = [0.0; 6];
                for (f, a) in fa.iter_mut().enumerate() {
                    let axis = f / 2;
                    let inward = if f % 2 == 0 {
                        1e-9 * len[axis]
                    } else {
                        len[axis] * (1.0 - 1e-9)
                    };
                    *a = sdf.face_area(lo, len, axis, inward, 400);
                }
                (fa, sdf.volume(lo, len, 160))
            }
            Mode::Centered => {
                let mut fa = [0.0; 6];
                for (f, a) in fa.iter_mut().enumerate() {
                    let axis = f / 2;
                    *a = len[(axis + 1) % 3] * len[(axis + 2) % 3];
                }
                (fa, len[0] * len[1] * len[2])
            }
        };
        Filler {
            mode,
            len,
            sdf,
            pos: Vec::new(),
            rad: Vec::new(),
            on_face: Vec::new(),
            drawn: Vec::new(),
            grids,
            grid_rmax: [0.0; 2],
            split: 2.0 * rmean,
            dist,
            rmean,
            r_floor: dist.quantile(1e-3),
            tol: 1e-9 * rmean,
            parent_gap: settings.parent_parameter * rmean,
            min_period: len.iter().cloned().fold(f64::INFINITY, f64::min),
            face_area,
            face_sum: [0.0; 6],
            volume,
            vol_sum: 0.0,
            rng,
            stats: FillStats {
                domain_volume: volume,
                ..FillStats::default()
            },
            last_stop: String::new(),
            set: settings,
        }
    }

    /// Geometric tolerance: exact tangency is accepted, overlaps beyond it are not.
    pub fn tolerance(&self) -> f64 {
        self.tol
    }

    fn draw(&mut self) -> f64 {
        self.stats.draws += 1;
        self.dist.sample(&mut self.rng)
    }

    fn overlaps(&self, c: [f64; 3], r: f64) -> bool {
        self.blocker(c, r).is_some()
    }

    /// Visits every sphere image that may lie within `reach + its radius` of `c`.
    fn visit_near(
        &self,
        c: [f64; 3],
        reach: f64,
        mut f: impl FnMut(u32, [f64; 3]) -> bool,
    ) -> bool {
        for (g, &rmax) in self.grids.iter().zip(&self.grid_rmax) {
            if rmax > 0.0 && !g.visit(c, reach + rmax, &mut f) {
                return false;
            }
        }
        true
    }

    /// A sphere (any periodic image) overlapping the ball (c, r), if one does.
    fn blocker(&self, c: [f64; 3], r: f64) -> Option<u32> {
        let mut hit = None;
        self.visit_near(c, r + self.tol, |j, s| {
            let q = self.pos[j as usize];
            let d = [c[0] - q[0] - s[0], c[1] - q[1] - s[1], c[2] - q[2] - s[2]];
            let lim = r + self.rad[j as usize] - self.tol;
            if dot(d, d) < lim * lim {
                hit = Some(j);
                false
            } else {
                true
            }
        });
        hit
    }

    /// Whether the ball (c, r) overlaps any image of sphere `j`.
    fn overlaps_one(&self, c: [f64; 3], r: f64, j: u32) -> bool {
        let j = j as usize;
        let q = self.pos[j];
        let lim = r + self.rad[j] - self.tol;
        let mut d2 = 0.0;
        for a in 0..3 {
            let mut d = c[a] - q[a];
            if self.mode == Mode::Centered {
                // Nearest image along each periodic axis.
                d -= (d / self.len[a]).round() * self.len[a];
            }
            d2 += d * d;
        }
        d2 < lim * lim
    }

    fn inside(&self, c: [f64; 3], r: f64) -> bool {
        match self.mode {
            Mode::Closed => self.sdf.contains_ball(c, r, self.tol),
            // Every sphere is repeated with the brick period: it must not touch its own image.
            Mode::Centered => 2.0 * r <= self.min_period - self.tol,
        }
    }

    fn valid(&self, c: [f64; 3], r: f64, phase: Phase) -> bool {
        self.fits_domain(c, r, phase) && !self.overlaps(c, r)
    }

    fn fits_domain(&self, c: [f64; 3], r: f64, phase: Phase) -> bool {
        match (self.mode, phase) {
            (Mode::Centered, Phase::Volume) => {
                // Interior spheres of Method 2 stay inside the brick.
                (0..3).all(|a| c[a] >= r - self.tol && c[a] <= self.len[a] - r + self.tol)
                    && self.inside(c, r)
            }
            _ => self.inside(c, r),
        }
    }

    fn face_bits(&self, c: [f64; 3], r: f64) -> u8 {
        let mut bits = 0u8;
        match self.mode {
            Mode::Closed => {
                let eps = 1e-7 * self.rmean;
                for f in 0..6 {
                    let a = f / 2;
                    let gap = if f % 2 == 0 {
                        c[a] - r
                    } else {
                        self.len[a] - c[a] - r
                    };
                    if gap.abs() <= eps {
                        bits |= 1 << f;
                    }
                }
            }
            Mode::Centered => {
                for (a, x) in c.iter().enumerate() {
                    if *x == 0.0 {
                        bits |= 1 << a;
                    }
                }
            }
        }
        bits
    }

    fn place(&mut self, c: [f64; 3], r: f64, drawn: bool) -> usize {
        let i = self.pos.len();
        let bits = self.face_bits(c, r);
        self.pos.push(c);
        self.rad.push(r);
        self.on_face.push(bits);
        self.drawn.push(drawn);
        let g = usize::from(r > self.split);
        self.grids[g].insert(i as u32, c);
        self.grid_rmax[g] = self.grid_rmax[g].max(r);
        self.vol_sum += 4.0 / 3.0 * PI * r * r * r;
        for f in 0..6 {
            let bit = match self.mode {
                Mode::Closed => f,
                Mode::Centered => f / 2,
            };
            if bits & (1 << bit) != 0 {
                self.face_sum[f] += PI * r * r;
            }
        }
        i
    }

    pub fn face_fraction(&self, f: usize) -> f64 {
        if self.face_area[f] > 0.0 {
            self.face_sum[f] / self.face_area[f]
        } else {
            1.0
        }
    }

    pub fn body_fraction(&self) -> f64 {
        self.vol_sum / self.volume
    }

    /// Neighbours of sphere `s` younger than it (or images of it) within the parent gap,
    /// as (index, image position, radius).
    fn parents_of(&self, s: usize) -> Vec<(usize, [f64; 3], f64)> {
        let c = self.pos[s];
        let r = self.rad[s];
        let mut out = Vec::new();
        self.visit_near(c, r + self.parent_gap, |j, sh| {
            let j = j as usize;
            if j > s || (j == s && sh == [0.0; 3]) {
                return true;
            }
            let q = [
                self.pos[j][0] + sh[0],
                self.pos[j][1] + sh[1],
                self.pos[j][2] + sh[2],
            ];
            let d = sub(c, q);
            let gap = dot(d, d).sqrt() - r - self.rad[j];
            if gap <= self.parent_gap {
                out.push((j, q, self.rad[j]));
            }
            true
        });
        out
    }

    fn on_phase_face(&self, j: usize, q: [f64; 3], phase: Phase) -> bool {
        match (self.mode, phase) {
            (_, Phase::Volume) => true,
            (Mode::Closed, Phase::Face(f)) => self.on_face[j] & (1 << f) != 0,
            // Images shifted along the normal are off the plane.
            (Mode::Centered, Phase::Face(a)) => self.on_face[j] & (1 << a) != 0 && q[a] == 0.0,
        }
    }

    fn add_sites(&self, s: usize, phase: Phase, sites: &mut Vec<Site>) {
        let c = self.pos[s];
        if !self.on_phase_face(s, c, phase) {
            return;
        }
        let nb: Vec<_> = self
            .parents_of(s)
            .into_iter()
            .filter(|(j, q, _)| self.on_phase_face(*j, *q, phase))
            .collect();
        match phase {
            Phase::Face(_) => {
                for &(_, q, rq) in &nb {
                    sites.push(Site {
                        p: [c, q, [0.0; 3]],
                        r: [self.rad[s], rq, 0.0],
                        min_failed: f64::INFINITY,
                        too_small: 0.0,
                        probe: 0.0,
                        blocker: [u32::MAX; 2],
                        dead: false,
                    });
                }
            }
            Phase::Volume => {
                for a in 0..nb.len() {
                    for b in a + 1..nb.len() {
                        let d = sub(nb[a].1, nb[b].1);
                        let gap = dot(d, d).sqrt() - nb[a].2 - nb[b].2;
                        if gap <= self.parent_gap {
                            sites.push(Site {
                                p: [c, nb[a].1, nb[b].1],
                                r: [self.rad[s], nb[a].2, nb[b].2],
                                min_failed: f64::INFINITY,
                                too_small: 0.0,
                                probe: 0.0,
                                blocker: [u32::MAX; 2],
                                dead: false,
                            });
                        }
                    }
                }
            }
        }
    }

    /// Candidate centres for a sphere of radius `r` touching the site's parents.
    fn candidates(&self, site: &Site, r: f64, phase: Phase) -> [Option<[f64; 3]>; 2] {
        match phase {
            Phase::Volume => {
                let d = [site.r[0] + r, site.r[1] + r, site.r[2] + r];
                match trilaterate(&site.p, d) {
                    Some([a, b]) => [Some(a), Some(b)],
                    None => [None, None],
                }
            }
            Phase::Face(f) => {
                let (axis, side) = match self.mode {
                    Mode::Closed => (f / 2, f % 2),
                    Mode::Centered => (f, 0),
                };
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                let (d1, d2) = match self.mode {
                    // Both spheres touch the plane: in-plane distance^2 = (r + r_i)^2 - (r - r_i)^2.
                    Mode::Closed => (2.0 * (r * site.r[0]).sqrt(), 2.0 * (r * site.r[1]).sqrt()),
                    // Both centred on the plane: great circles touch.
                    Mode::Centered => (r + site.r[0], r + site.r[1]),
                };
                let p1 = [site.p[0][u], site.p[0][v]];
                let p2 = [site.p[1][u], site.p[1][v]];
                let Some(sol) = intersect2(p1, p2, d1, d2) else {
                    return [None, None];
                };
                sol.map(|s| {
                    let mut c = [0.0; 3];
                    match self.mode {
                        Mode::Closed => {
                            c[axis] = if side == 0 { r } else { self.len[axis] - r };
                            c[u] = s[0];
                            c[v] = s[1];
                        }
                        Mode::Centered => {
                            c[axis] = 0.0;
                            c[u] = wrap(s[0], self.len[u]);
                            c[v] = wrap(s[1], self.len[v]);
                        }
                    }
                    Some(c)
                })
            }
        }
    }

    fn try_site(&self, site: &Site, r: f64, phase: Phase) -> Option<[f64; 3]> {
        self.candidates(site, r, phase)
            .into_iter()
            .flatten()
            .find(|&c| self.valid(c, r, phase))
    }

    fn progress(&self, ctx: &RunContext) -> Result<(), FillError> {
        let done = (self.body_fraction() * 1000.0) as u64;
        ctx.progress(done, (self.set.body_goal * 1000.0) as u64)
            .map_err(|_| FillError::Cancelled)
    }

    /// Runs one site-based phase until `goal` holds, the sites are exhausted, or
    /// `max_consecutive_rejections` draws in a row fit nowhere. Returns whether the goal holds.
    fn run_phase(
        &mut self,
        phase: Phase,
        goal: impl Fn(&Self) -> bool,
        ctx: &RunContext,
    ) -> Result<(bool, u64), FillError> {
        let mut sites = Vec::new();
        for s in 0..self.pos.len() {
            self.add_sites(s, phase, &mut sites);
        }
        let mut consecutive = 0u64;
        let (draws0, rejected0) = (self.stats.draws, self.stats.rejected);
        let mut dead = 0usize;
        let mut tick = 0u32;
        loop {
            let (d, q) = (self.stats.draws - draws0, self.stats.rejected - rejected0);
            let too_many = d >= 100 && q as f64 > self.set.max_rejected_fraction * d as f64;
            if goal(self)
                || consecutive >= self.set.max_consecutive_rejections
                || too_many
                || dead == sites.len()
            {
                // Name the condition that actually stopped the phase.
                self.last_stop = if too_many {
                    format!(
                        "{q} of its {d} draws were rejected, above max_rejected_fraction = {}",
                        self.set.max_rejected_fraction
                    )
                } else if consecutive >= self.set.max_consecutive_rejections {
                    format!(
                        "{consecutive} draws in a row were rejected \
                         (max_consecutive_rejections = {})",
                        self.set.max_consecutive_rejections
                    )
                } else {
                    "no site is left where a sphere could touch its parents".to_string()
                };
                return Ok((goal(self), consecutive));
            }
            if dead * 2 > sites.len() && sites.len() > 1024 {
                sites.retain(|s| !s.dead);
                dead = 0;
            }
            tick += 1;
            if tick % 256 == 0 {
                self.progress(ctx)?;
            }
            let r = self.draw();
            let mut placed = None;
            for site in sites.iter_mut() {
                if site.dead || site.min_failed <= r || site.too_small >= r {
                    continue;
                }
                let cands = self.candidates(site, r, phase);
                if cands.iter().all(|c| c.is_none()) {
                    // The parents are too far apart for this radius: remember it.
                    site.too_small = r;
                    continue;
                }
                let mut found = None;
                for (k, c) in cands.into_iter().enumerate() {
                    let Some(c) = c else { continue };
                    let b = site.blocker[k];
                    if b != u32::MAX && self.overlaps_one(c, r, b) {
                        continue;
                    }
                    if !self.fits_domain(c, r, phase) {
                        continue;
                    }
                    match self.blocker(c, r) {
                        Some(j) => site.blocker[k] = j,
                        None => {
                            found = Some(c);
                            break;
                        }
                    }
                }
                if found.is_some() {
                    placed = found;
                    break;
                }
                site.min_failed = r;
                // Retire the site when even the smallest sphere that touches all its parents
                // (found once by bisection on solvability, which grows with r) is blocked.
                if site.probe == 0.0 {
                    let mut lo = site.too_small.max(self.r_floor);
                    if self.candidates(site, lo, phase).iter().all(|c| c.is_none()) {
                        let mut hi = r;
                        for _ in 0..24 {
                            let mid = 0.5 * (lo + hi);
                            if self
                                .candidates(site, mid, phase)
                                .iter()
                                .all(|c| c.is_none())
                            {
                                lo = mid;
                            } else {
                                hi = mid;
                            }
                        }
                        site.too_small = lo;
                        lo = hi;
                    }
                    site.probe = lo;
                }
                let lo = site.probe;
                if self.try_site(site, lo, phase).is_none() {
                    site.dead = true;
                    dead += 1;
                }
            }
            match placed {
                Some(c) => {
                    let s = self.place(c, r, true);
                    self.add_sites(s, phase, &mut sites);
                    consecutive = 0;
                }
                None => {
                    self.stats.rejected += 1;
                    consecutive += 1;
                }
            }
        }
    }

    fn corners(&mut self) {
        let r = self.rmean;
        match self.mode {
            Mode::Closed => {
                for k in 0..8 {
                    let c = [0, 1, 2].map(|a| if k >> a & 1 == 0 { r } else { self.len[a] - r });
                    if self.inside(c, r) && !self.overlaps(c, r) {
                        self.place(c, r, false);
                    }
                }
            }
            Mode::Centered => {
                self.place([0.0; 3], r, false);
            }
        }
    }

    /// Closed mode: the 12 edges, each a chain of touching spheres that touch both faces of
    /// the edge. Where the domain cuts the edge (curved domains) the chain resumes at the next
    /// admissible position, found by marching along the edge.
    fn edges_closed(&mut self) {
        let step = 0.05 * self.rmean;
        for a in 0..3 {
            let (b, c) = ((a + 1) % 3, (a + 2) % 3);
            for k in 0..4 {
                let (sb, sc) = (k & 1, k >> 1);
                let off = |len: f64, side: usize, r: f64| if side == 0 { r } else { len - r };
                let at = |t: f64, r: f64, len: &[f64; 3]| {
                    let mut p = [0.0; 3];
                    p[a] = t;
                    p[b] = off(len[b], sb, r);
                    p[c] = off(len[c], sc, r);
                    p
                };
                // The chain starts at the corner sphere, if the corner is in the domain.
                let start = at(self.rmean, self.rmean, &self.len);
                let mut prev = self
                    .pos
                    .iter()
                    .position(|p| sub(*p, start).iter().all(|x| x.abs() < self.tol))
                    .map(|i| (self.pos[i][a], self.rad[i]));
                let mut consecutive = 0;
                while consecutive < EDGE_REJECTIONS {
                    let r = self.draw();
                    let t0 = match prev {
                        Some((tp, rp)) => {
                            // Touching the previous sphere: offsets differ by (r - rp) in two axes.
                            let d2 = (r + rp) * (r + rp) - 2.0 * (r - rp) * (r - rp);
                            if d2 <= 0.0 {
                                self.stats.rejected += 1;
                                consecutive += 1;
                                continue;
                            }
                            tp + d2.sqrt()
                        }
                        None => r,
                    };
                    let mut t = t0;
                    let mut found = false;
                    while t <= self.len[a] - r + self.tol {
                        let p = at(t, r, &self.len);
                        if self.valid(p, r, Phase::Volume) {
                            found = true;
                            break;
                        }
                        if prev.is_some() && self.sdf.contains_ball(p, r, self.tol) {
                            // Blocked by a sphere (the far corner), not by the domain: done.
                            break;
                        }
                        t += step;
                    }
                    if found {
                        self.place(at(t, r, &self.len), r, true);
                        prev = Some((t, r));
                        consecutive = 0;
                    } else {
                        self.stats.rejected += 1;
                        consecutive += 1;
                    }
                }
            }
        }
    }

    /// Centered mode: one edge per axis through the origin, a chain of touching spheres
    /// centred on the edge line from the corner sphere to its periodic image.
    fn edges_centered(&mut self) {
        for a in 0..3 {
            let mut t = 0.0;
            let mut rp = self.rmean;
            let mut consecutive = 0;
            while consecutive < EDGE_REJECTIONS {
                let r = self.draw();
                let tn = t + rp + r;
                let mut p = [0.0; 3];
                p[a] = tn;
                if tn < self.len[a] && self.valid(p, r, Phase::Face((a + 1) % 3)) {
                    self.place(p, r, true);
                    t = tn;
                    rp = r;
                    consecutive = 0;
                } else {
                    self.stats.rejected += 1;
                    consecutive += 1;
                }
            }
        }
    }

    fn fail_or_warn(&self, what: String, ctx: &RunContext) -> Result<(), FillError> {
        let e = FillError::Saturated {
            stage: self.set.stage,
            region: if what.starts_with("body") {
                "volume"
            } else {
                "face"
            },
            what,
            draws: self.stats.draws,
            rejected: self.stats.rejected,
            stop: self.last_stop.clone(),
            advice: if self.set.require_goals {
                "lower the goal, enlarge the brick, or set require_goals: false to keep the \
                 saturated fill"
            } else {
                "the saturated fill is kept (require_goals: false); raise \
                 max_consecutive_rejections or max_rejected_fraction to fill further"
            },
        };
        if self.set.require_goals {
            Err(e)
        } else {
            ctx.warn(&e.to_string());
            Ok(())
        }
    }

    /// Fills the unit brick: corners, edges, faces, volume.
    pub fn fill(&mut self, ctx: &RunContext) -> Result<(), FillError> {
        self.corners();
        let mut reached = true;
        match self.mode {
            Mode::Closed => {
                self.edges_closed();
                for f in 0..6 {
                    if !self.set.faces[f] || self.face_area[f] <= 0.0 {
                        continue;
                    }
                    let goal = self.set.face_goal;
                    let (ok, _) = self.run_phase(
                        Phase::Face(f),
                        move |s: &Self| s.face_fraction(f) >= goal,
                        ctx,
                    )?;
                    if !ok {
                        reached = false;
                        self.fail_or_warn(
                            format!(
                                "face {} coverage reached {:.4} < face_goal {}",
                                grainpipe_core::FACE_NAMES[f],
                                self.face_fraction(f),
                                goal
                            ),
                            ctx,
                        )?;
                    }
                }
            }
            Mode::Centered => {
                self.edges_centered();
                for a in 0..3 {
                    let goal = self.set.face_goal;
                    let (ok, _) = self.run_phase(
                        Phase::Face(a),
                        move |s: &Self| s.face_fraction(2 * a) >= goal,
                        ctx,
                    )?;
                    if !ok {
                        reached = false;
                        self.fail_or_warn(
                            format!(
                                "face {}/{} coverage reached {:.4} < face_goal {}",
                                grainpipe_core::FACE_NAMES[2 * a],
                                grainpipe_core::FACE_NAMES[2 * a + 1],
                                self.face_fraction(2 * a),
                                goal
                            ),
                            ctx,
                        )?;
                    }
                }
            }
        }
        let goal = self.set.body_goal;
        let (ok, _) = self.run_phase(
            Phase::Volume,
            move |s: &Self| s.body_fraction() >= goal,
            ctx,
        )?;
        if !ok {
            reached = false;
            self.fail_or_warn(
                format!(
                    "body fraction reached {:.4} < body_goal {goal}",
                    self.body_fraction()
                ),
                ctx,
            )?;
        }
        self.progress(ctx)?;
        self.stats.goals_reached = reached;
        self.stats.body_fraction = self.body_fraction();
        for f in 0..6 {
            self.stats.face_fraction[f] = self.face_fraction(f);
            self.stats.filled[f] = match self.mode {
                Mode::Closed => self.set.faces[f] && self.face_area[f] > 0.0,
                Mode::Centered => true,
            };
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trilateration_roots_touch_all_parents() {
        let p = [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 1.7, 0.0]];
        let r = [1.0, 0.9, 0.8];
        let rn = 0.6;
        let roots = trilaterate(&p, r.map(|x| x + rn)).unwrap();
        for c in roots {
            for i in 0..3 {
                let d = sub(c, p[i]);
                // Closed-form solution: distances exact to round-off.
                assert!((dot(d, d).sqrt() - (r[i] + rn)).abs() < 1e-12);
            }
        }
        // The two roots are mirror images through the parents' plane z = 0.
        assert!((roots[0][2] + roots[1][2]).abs() < 1e-12);
    }

    #[test]
    fn circle_intersection_is_exact() {
        let s = intersect2([0.0, 0.0], [3.0, 0.0], 2.0, 2.0).unwrap();
        // Symmetric: x = 1.5, y = +-sqrt(4 - 2.25).
        for q in s {
            assert!((q[0] - 1.5).abs() < 1e-15);
            assert!((q[1].abs() - 1.75f64.sqrt()).abs() < 1e-15);
        }
        assert!(intersect2([0.0, 0.0], [5.0, 0.0], 2.0, 2.0).is_none());
    }
}
