//! `packing.poisson_disk`: two-step fast Poisson disk sampling (FPDS, Bridson 2007) of
//! bidisperse disks or spheres, as in the appendix of Heinze et al. (2020).

use crate::common::{measure, CLASS_ATTR, DISK_ATTR, LARGE, SMALL};
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::spatial::CellList;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    params, ArtifactKind, ArtifactMeta, Body, BodyAttribute, Domain, InputMetas, Inputs, Outputs,
    Packing, PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
};
use rand::{Rng, RngExt};
use rand_distr::{Distribution, StandardNormal};
use std::f64::consts::PI;

/// Largest volume ratio accepted: a packing of touching large disks leaves well above 5 % of
/// the area to the small ones, so theta beyond this cannot be reached by this construction.
pub const THETA_MAX: f64 = 20.0;

#[params]
pub struct PoissonDiskParams {
    /// 2 for disks in a square (a sample of unit thickness), 3 for spheres in a cube.
    #[param(default = 2)]
    pub dimension: u32,
    /// Edge of the square (cube); the box is centred on the origin. The paper's box of area
    /// 900 pi r_L^2 has an edge of 53.17 r_L.
    #[param(default = Q::new(53.17e-3))]
    pub size: Q<Length>,
    /// Mean radius of the large particles, r_L.
    #[param(default = Q::new(1.0e-3))]
    pub large_radius: Q<Length>,
    /// Size ratio gamma = r_L / r_S of the mean radii (eq. 1), at least 1.
    #[param(default = 5.0)]
    pub gamma: f64,
    /// Target volume ratio theta = rho_L / rho_S (eq. 2).
    #[param(default = 1.4)]
    pub theta: f64,
    /// Standard deviation of each radius law relative to its mean (0.25 in the paper).
    #[param(default = 0.25)]
    pub relative_std: f64,
    /// Radii are kept in [r_S - t sigma_S, r_L + t sigma_L], t = this value (1.5 in the paper).
    #[param(default = 1.5)]
    pub truncation: f64,
    /// Surface gap d_min kept between large particles in the first step; absent = calibrated
    /// by bisection until the achieved theta matches the target.
    pub large_gap: Option<Q<Length>>,
    /// Periodic box (in-plane axes in 2-D); otherwise particles stay inside the walls.
    #[param(default = false)]
    pub periodic: bool,
    /// Candidate placements around an active particle before it is retired (Bridson's k).
    #[param(default = 30)]
    pub attempts: u32,
    /// Relative tolerance on theta for the calibration of the gap.
    #[param(default = 0.02)]
    pub theta_tolerance: f64,
    /// Samplings tried while calibrating the gap before the stage fails.
    #[param(default = 40, ty = "integer 1..200")]
    pub max_calibrations: u32,
    /// Work limit: refuse boxes that would hold more particles than this.
    #[param(default = 2_000_000)]
    pub max_particles: u64,
}

/// The parameters in SI, validated.
#[derive(Clone, Debug)]
pub struct Spec {
    pub dim: usize,
    pub size: f64,
    pub periodic: bool,
    pub large: SizeDistribution,
    pub small: SizeDistribution,
    pub r_max: f64,
    pub r_min: f64,
    pub attempts: u32,
    pub max_particles: u64,
}

/// A bidisperse sample: centres, radii and classes.
#[derive(Clone, Debug, Default)]
pub struct Sample {
    pub pos: Vec<[f64; 3]>,
    pub radius: Vec<f64>,
    pub class: Vec<u8>,
}

impl Sample {
    /// (rho_L, rho_S): the large and small volume (area) fractions of the box.
    pub fn fractions(&self, spec: &Spec) -> (f64, f64) {
        let box_measure = spec.size.powi(spec.dim as i32);
        let mut v = [0.0; 2];
        for (r, c) in self.radius.iter().zip(&self.class) {
            v[usize::from(*c == SMALL)] += measure(spec.dim, *r);
        }
        (v[0] / box_measure, v[1] / box_measure)
    }
    /// theta = rho_L / rho_S (eq. 2).
    pub fn theta(&self, spec: &Spec) -> f64 {
        let (l, s) = self.fractions(spec);
        l / s
    }
    /// Ratio of the mean radii of the placed large and small particles (eq. 1).
    pub fn gamma(&self) -> f64 {
        let mut s = [0.0; 2];
        let mut n = [0usize; 2];
        for (r, c) in self.radius.iter().zip(&self.class) {
            let k = usize::from(*c == SMALL);
            s[k] += r;
            n[k] += 1;
        }
        (s[0] / n[0].max(1) as f64) / (s[1] / n[1].max(1) as f64)
    }
}

impl PoissonDiskParams {
    /// Validates and converts to SI; errors name the key.
    pub fn spec(&self) -> Result<Spec, StageError> {
        let dim = match self.dimension {
            2 => 2,
            3 => 3,
            d => {
                return Err(StageError::param(
                    "dimension",
                    format!("{d}: must be 2 or 3"),
                ))
            }
        };
        let r_l = self.large_radius.si();
        if !(r_l.is_finite() && r_l > 0.0) {
            return Err(StageError::param(
                "large_radius",
                "must be a positive length",
            ));
        }
        if !(self.gamma.is_finite() && self.gamma >= 1.0 && self.gamma <= 50.0) {
            return Err(StageError::param("gamma", "must be in [1, 50]"));
        }
        if !(self.theta.is_finite() && self.theta > 0.0) {
            return Err(StageError::param("theta", "must be positive"));
        }
        if self.theta > THETA_MAX {
            return Err(StageError::param(
                "theta",
                format!(
                    "{} is unreachable: touching large particles leave too much room for small \
                     ones to get theta above {THETA_MAX}",
                    self.theta
                ),
            ));
        }
        if !(self.relative_std >= 0.0 && self.relative_std <= 0.5) {
            return Err(StageError::param("relative_std", "must be in [0, 0.5]"));
        }
        if !(self.truncation >= 0.0 && self.truncation <= 3.0) {
            return Err(StageError::param("truncation", "must be in [0, 3]"));
        }
        let r_s = r_l / self.gamma;
        let (s_l, s_s) = (self.relative_std * r_l, self.relative_std * r_s);
        let lo = r_s - self.truncation * s_s;
        let hi = r_l + self.truncation * s_l;
        if lo <= 0.0 {
            return Err(StageError::param(
                "truncation",
                "the smallest radius r_S - t sigma_S is not positive",
            ));
        }
        // Both laws are cut to the paper's common range [r_S - t s_S, r_L + t s_L] (sec. II.A).
        let law = |mean: f64, sd: f64| {
            if sd == 0.0 {
                SizeDistribution::Fixed {
                    value: Q::new(mean),
                }
            } else {
                SizeDistribution::Normal {
                    mean: Q::new(mean),
                    std_dev: Q::new(sd),
                    min: Some(Q::new(lo)),
                    max: Some(Q::new(hi)),
                }
            }
        };
        let size = self.size.si();
        if !(size.is_finite() && size > 0.0) {
            return Err(StageError::param("size", "must be a positive length"));
        }
        if size < 4.0 * 2.0 * hi {
            return Err(StageError::param(
                "size",
                format!(
                    "{size:.3e} m holds fewer than four of the largest particles (diameter \
                     {:.3e} m)",
                    2.0 * hi
                ),
            ));
        }
        if let Some(g) = self.large_gap {
            let g = g.si();
            if !(g.is_finite() && g >= 0.0) {
                return Err(StageError::param("large_gap", "must be a length >= 0"));
            }
            if g > 0.25 * size {
                return Err(StageError::param(
                    "large_gap",
                    format!("{g:.3e} m is larger than a quarter of the box edge {size:.3e} m"),
                ));
            }
        }
        if self.attempts == 0 || self.attempts > 10_000 {
            return Err(StageError::param("attempts", "must be in [1, 10000]"));
        }
        if !(self.theta_tolerance > 0.0 && self.theta_tolerance <= 0.05) {
            return Err(StageError::param(
                "theta_tolerance",
                "must be in (0, 0.05] (the test criterion is 5 %)",
            ));
        }
        // Each calibration is a whole sampling, and a bisection has halved its bracket to
        // f64 round-off within about 60: 10^9 calibrations only repeat the last sampling.
        if self.max_calibrations == 0 || self.max_calibrations > MAX_CALIBRATIONS {
            return Err(StageError::param(
                "max_calibrations",
                format!("must be in 1..{MAX_CALIBRATIONS} (the gap bisection reaches f64 round-off within about 60)"),
            ));
        }
        let spec = Spec {
            dim,
            size,
            periodic: self.periodic,
            large: law(r_l, s_l),
            small: law(r_s, s_s),
            r_max: hi,
            r_min: lo,
            attempts: self.attempts,
            max_particles: self.max_particles,
        };
        let n = spec.count_estimate(self.theta);
        if n > self.max_particles as f64 {
            return Err(StageError::param(
                "size",
                format!(
                    "about {n:.0} particles, more than max_particles = {}; shrink the box or \
                     raise the limit",
                    self.max_particles
                ),
            ));
        }
        Ok(spec)
    }
}

impl Spec {
    /// Particle count for a total fraction of 0.85 split by theta (the paper's rho_p range).
    pub fn count_estimate(&self, theta: f64) -> f64 {
        let box_measure = self.size.powi(self.dim as i32);
        let rho_s = 0.85 / (1.0 + theta);
        let rho_l = 0.85 - rho_s;
        let m = |d: &SizeDistribution| measure(self.dim, d.mean());
        rho_l * box_measure / m(&self.large) + rho_s * box_measure / m(&self.small)
    }

    fn half(&self) -> f64 {
        0.5 * self.size
    }

    /// The axes the sample extends along.
    fn axes(&self) -> usize {
        self.dim
    }
}

/// A uniformly random unit vector in the plane (2-D) or in space (3-D).
fn random_direction<R: Rng + ?Sized>(rng: &mut R, dim: usize) -> [f64; 3] {
    if dim == 2 {
        let a = 2.0 * PI * rng.random::<f64>();
        [a.cos(), a.sin(), 0.0]
    } else {
        loop {
            let v: [f64; 3] = [0; 3].map(|_| StandardNormal.sample(rng));
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if n > 1e-12 {
                return v.map(|x| x / n);
            }
        }
    }
}

/// The growing sample with its background grid.
struct Sampler<'a> {
    spec: &'a Spec,
    cells: CellList,
    sample: Sample,
}

impl<'a> Sampler<'a> {
    fn new(spec: &'a Spec) -> Self {
        let h = spec.half();
        let per = spec.periodic;
        let (min, len, periodic) = if spec.dim == 2 {
            (
                [-h, -h, -spec.r_max],
                [spec.size, spec.size, 2.0 * spec.r_max],
                [per, per, false],
            )
        } else {
            ([-h; 3], [spec.size; 3], [per; 3])
        };
        // Background grid (appendix): cells of about the smallest diameter, so a cell holds
        // O(1) centres; queries walk every cell within the interaction reach.
        let cells = CellList::new(min, len, periodic, 2.0 * spec.r_min);
        Sampler {
            spec,
            cells,
            sample: Sample::default(),
        }
    }

    /// Wraps a position into the box on periodic axes; `None` when a wall is crossed.
    fn admissible(&self, c: [f64; 3], r: f64) -> Option<[f64; 3]> {
        let h = self.spec.half();
        let mut c = c;
        for a in 0..self.spec.axes() {
            if self.spec.periodic {
                c[a] = (c[a] + h).rem_euclid(self.spec.size) - h;
            } else if c[a] - r < -h || c[a] + r > h {
                return None;
            }
        }
        Some(c)
    }

    /// Whether a particle (c, r) keeps a surface gap of at least `gap` to every other one
    /// (periodic images included). The tolerance absorbs the round-off of placing a
    /// particle exactly in contact.
    fn fits(&self, c: [f64; 3], r: f64, gap: f64) -> bool {
        let reach = r + self.spec.r_max + gap;
        let s = &self.sample;
        let tol = 1e-12 * self.spec.r_max;
        self.cells.visit(c, reach, |j, shift| {
            let j = j as usize;
            let d = [0, 1, 2].map(|a| s.pos[j][a] + shift[a] - c[a]);
            let lim = r + s.radius[j] + gap - tol;
            d[0] * d[0] + d[1] * d[1] + d[2] * d[2] >= lim * lim
        })
    }

    fn add(&mut self, c: [f64; 3], r: f64, class: u8) -> Result<usize, PdsError> {
        let k = self.sample.pos.len();
        if k as u64 >= self.spec.max_particles {
            return Err(PdsError::TooMany(self.spec.max_particles));
        }
        self.cells.insert(k as u32, c);
        self.sample.pos.push(c);
        self.sample.radius.push(r);
        self.sample.class.push(class);
        Ok(k)
    }

    /// One FPDS step (appendix): while particles are active, pick one at random and try
    /// `attempts` candidates at a surface gap in [gap, 2 gap] from it (touching it when
    /// gap = 0), each with a fresh radius; a candidate that keeps the gap to every particle
    /// is added and becomes active; an active particle whose attempts all fail is retired.
    fn fill<R: Rng + ?Sized>(
        &mut self,
        rng: &mut R,
        law: &SizeDistribution,
        gap: f64,
        class: u8,
        mut active: Vec<usize>,
    ) -> Result<(), PdsError> {
        while !active.is_empty() {
            let slot = rng.random_range(0..active.len());
            let j = active[slot];
            let mut placed = false;
            for _ in 0..self.spec.attempts {
                let r = law.sample(rng);
                let s = gap * (1.0 + rng.random::<f64>());
                let dir = random_direction(rng, self.spec.dim);
                let dist = self.sample.radius[j] + r + s;
                let c = [0, 1, 2].map(|a| self.sample.pos[j][a] + dist * dir[a]);
                let Some(c) = self.admissible(c, r) else {
                    continue;
                };
                if self.fits(c, r, gap) {
                    let k = self.add(c, r, class)?;
                    active.push(k);
                    placed = true;
                    break;
                }
            }
            if !placed {
                active.swap_remove(slot);
            }
        }
        Ok(())
    }
}

#[derive(Debug)]
pub enum PdsError {
    TooMany(u64),
}

impl std::fmt::Display for PdsError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PdsError::TooMany(n) => write!(
                f,
                "the sample grew past max_particles = {n}; shrink the box or raise the limit"
            ),
        }
    }
}

/// The two-step FPDS (appendix): large particles with the surface gap `gap` (d_min), then
/// small ones with none, seeded from a random large particle. Deterministic in `seed`.
pub fn two_step_sample(spec: &Spec, gap: f64, seed: u64) -> Result<Sample, PdsError> {
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut s = Sampler::new(spec);
    let h = spec.half();
    // Seed particle, uniformly inside the walls.
    let r0 = spec.large.sample(&mut rng);
    let c0 = [0, 1, 2].map(|a| {
        if a < spec.dim {
            let free = if spec.periodic { h } else { h - r0 };
            -free + 2.0 * free * rng.random::<f64>()
        } else {
            0.0
        }
    });
    let first = s.add(c0, r0, LARGE)?;
    s.fill(&mut rng, &spec.large, gap, LARGE, vec![first])?;
    // Step 2: every large particle starts active; small ones fill the gaps touching others.
    let active: Vec<usize> = (0..s.sample.pos.len()).collect();
    s.fill(&mut rng, &spec.small, 0.0, SMALL, active)?;
    Ok(s.sample)
}

/// The result of the stage's kernel: the sample, the gap used, the samplings run.
pub struct Calibrated {
    pub sample: Sample,
    pub gap: f64,
    pub samplings: u32,
}

/// Most samplings the gap calibration may run (`max_calibrations`).
pub const MAX_CALIBRATIONS: u32 = 200;

/// Runs the two-step sampling with the given gap, or calibrates the gap by bisection on the
/// achieved theta (which falls as the gap grows: more room is left to small particles).
pub fn calibrated_sample(
    spec: &Spec,
    theta: f64,
    gap: Option<f64>,
    tolerance: f64,
    max_runs: u32,
    seed: u64,
    mut progress: impl FnMut(u32) -> Result<(), StageError>,
) -> Result<Calibrated, StageError> {
    let fail = |e: PdsError| StageError::failed(e.to_string());
    if let Some(g) = gap {
        let sample = two_step_sample(spec, g, seed).map_err(fail)?;
        return Ok(Calibrated {
            sample,
            gap: g,
            samplings: 1,
        });
    }
    let err = |s: &Sample| (s.theta(spec) - theta) / theta;
    let mut runs = 0u32;
    let mut run = |g: f64, runs: &mut u32| -> Result<Sample, StageError> {
        *runs += 1;
        progress(*runs)?;
        two_step_sample(spec, g, seed).map_err(fail)
    };
    let s0 = run(0.0, &mut runs)?;
    let e0 = err(&s0);
    let mut best = (e0.abs(), 0.0, s0);
    if e0 < -tolerance {
        return Err(StageError::failed(format!(
            "theta = {theta} is unreachable: with touching large particles (gap 0) the small \
             ones already take rho_S = {:.4}, theta = {:.4}; lower theta or gamma",
            best.2.fractions(spec).1,
            best.2.theta(spec)
        )));
    }
    if best.0 <= tolerance {
        return Ok(Calibrated {
            sample: best.2,
            gap: 0.0,
            samplings: 1,
        });
    }
    // Bracket: grow the gap from the mean small diameter until theta drops below the target.
    let mut lo = 0.0;
    let mut hi = 2.0 * spec.small.mean();
    loop {
        if runs >= max_runs {
            break;
        }
        let s = run(hi, &mut runs)?;
        let e = err(&s);
        if e.abs() < best.0 {
            best = (e.abs(), hi, s);
        }
        if e <= 0.0 || hi > 0.25 * spec.size {
            break;
        }
        lo = hi;
        hi *= 2.0;
    }
    while best.0 > tolerance && runs < max_runs {
        // A collapsed bracket samples the same gap again and again.
        if hi - lo <= 1e-12 * hi {
            return Err(StageError::failed(format!(
                "the gap calibration cannot reach theta = {theta} within {:.1} %: theta jumps \
                 across it at a gap of {:.6e} m (best theta = {:.4} after {runs} samplings); \
                 loosen theta_tolerance, change the seed, or give large_gap",
                100.0 * tolerance,
                best.1,
                best.2.theta(spec)
            )));
        }
        let mid = 0.5 * (lo + hi);
        let s = run(mid, &mut runs)?;
        let e = err(&s);
        if e.abs() < best.0 {
            best = (e.abs(), mid, s);
        }
        if e > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    if best.0 > tolerance {
        return Err(StageError::failed(format!(
            "the gap calibration did not reach theta = {theta} within {:.1} % after {runs} \
             samplings: best theta = {:.4} at gap {:.4e} m; raise max_calibrations or \
             theta_tolerance, or give large_gap",
            100.0 * tolerance,
            best.2.theta(spec),
            best.1
        )));
    }
    Ok(Calibrated {
        sample: best.2,
        gap: best.1,
        samplings: runs,
    })
}

/// Builds the packing artifact: disks are bodies at z = 0 in a slab of the largest diameter.
pub fn to_packing(spec: &Spec, s: &Sample) -> Packing {
    let periodic = if spec.dim == 2 {
        [spec.periodic, spec.periodic, false]
    } else {
        [spec.periodic; 3]
    };
    let (min, max) = box_of(spec);
    let mut p = Packing::new(Domain::boxed(min, max, periodic));
    p.bodies = s
        .pos
        .iter()
        .zip(&s.radius)
        .map(|(c, r)| Body::sphere(*c, *r))
        .collect();
    p.attributes.insert(
        CLASS_ATTR.into(),
        BodyAttribute {
            unit: String::new(),
            values: s.class.iter().map(|&c| c as f64).collect(),
        },
    );
    p.attributes.insert(
        DISK_ATTR.into(),
        BodyAttribute {
            unit: String::new(),
            values: vec![if spec.dim == 2 { 1.0 } else { 0.0 }; s.pos.len()],
        },
    );
    p
}

fn box_of(spec: &Spec) -> ([f64; 3], [f64; 3]) {
    let h = spec.half();
    if spec.dim == 2 {
        ([-h, -h, -spec.r_max], [h, h, spec.r_max])
    } else {
        ([-h; 3], [h; 3])
    }
}

/// Peak memory of a sampling announced at `n` particles [bytes]. The count estimate takes
/// mean radii and a 0.85 fill; achieved samples land within ~20 % of it either way (theta
/// within its tolerance, more large ones by the gap), so the arrays are sized for 1.25 n.
/// Per particle: the sample (centre, radius, class: 33 B) and the calibration's kept copy
/// (33 B), the active list (8 B), the output body and its `class` and `disk` attributes
/// (`Body` + 16 B). The background grid is the sampler's cell list: cells of the smallest
/// diameter over the whole box, in 2-D also across the 2 r_max slab in z.
fn memory(spec: &Spec, n: u64) -> u64 {
    let (min, max) = box_of(spec);
    let len = [0, 1, 2].map(|a| max[a] - min[a]);
    let n = n + n / 4;
    let per = 33 + 33 + 8 + std::mem::size_of::<grainpipe_core::Body>() as u64 + 16;
    per * n + CellList::memory_bytes(len, 2.0 * spec.r_min, n) + (64 << 10)
}

pub struct PoissonDisk;

impl TypedStage for PoissonDisk {
    type Params = PoissonDiskParams;
    type Plan = Spec;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "packing.poisson_disk",
            "1.0.0",
            "Two-step fast Poisson disk sampling (Bridson 2007) of bidisperse disks (2-D) or \
             spheres (3-D), as in the appendix of Heinze et al., Phys. Rev. E 101, 052901 \
             (2020). Radii of large and small particles follow normal laws (sigma = 0.25 of \
             the mean) cut to [r_S - 1.5 sigma_S, r_L + 1.5 sigma_L] (sec. II.A). Step 1 grows \
             large particles from a random seed, each new one at a surface gap in [d, 2d] of \
             an active one and at least d from all others; step 2 fills the rest with small \
             particles touching an active one (d = 0). A background grid answers the \
             neighbour queries. Without large_gap, d = d_min(gamma, theta) is found by \
             bisection so the achieved theta = rho_L/rho_S matches the target (the paper \
             states d_min exists but not its formula). The box is centred on the origin; \
             bodies carry the attributes `class` (1 large, 2 small) and `disk` (1 in 2-D).",
        )
        .outputs(vec![
            PortSpec::new("packing", ArtifactKind::Packing, "the disks or spheres"),
            PortSpec::new(
                "report",
                ArtifactKind::Table,
                "counts, target and achieved theta and gamma, fractions, the gap d_min",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &PoissonDiskParams,
        _inputs: &InputMetas,
    ) -> Result<Preflight<Spec>, StageError> {
        let spec = p.spec()?;
        let n = spec.count_estimate(p.theta) as u64;
        let (min, max) = box_of(&spec);
        let periodic = if spec.dim == 2 {
            [p.periodic, p.periodic, false]
        } else {
            [p.periodic; 3]
        };
        let packing = ArtifactMeta::packing(min, max, periodic)
            .with_count(n, Some([1, p.max_particles]))
            .with_length_scale(2.0 * spec.large.mean());
        Ok(Preflight::from_info(&self.info(), memory(&spec, n))
            .announce("packing", packing)
            .announce(
                "report",
                ArtifactMeta::of(ArtifactKind::Table).with_count(1, Some([1, 1])),
            )
            .with_plan(spec))
    }

    fn run(
        &self,
        p: &PoissonDiskParams,
        spec: &Spec,
        _inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let total = p.max_calibrations as u64;
        let c = calibrated_sample(
            spec,
            p.theta,
            p.large_gap.map(|g| g.si()),
            p.theta_tolerance,
            p.max_calibrations,
            ctx.seed,
            |k| ctx.progress(k as u64, total),
        )?;
        let s = &c.sample;
        let (rho_l, rho_s) = s.fractions(spec);
        let theta = s.theta(spec);
        if p.large_gap.is_some() && ((theta - p.theta) / p.theta).abs() > 0.05 {
            ctx.warn(&format!(
                "with the given large_gap the achieved theta is {theta:.4}, target {}",
                p.theta
            ));
        }
        let n_l = s.class.iter().filter(|&&c| c == LARGE).count();
        let report = Table::new("poisson_disk")
            .with_i64("n_large", "", vec![n_l as i64])
            .with_i64("n_small", "", vec![(s.class.len() - n_l) as i64])
            .with_f64("theta_target", "", vec![p.theta])
            .with_f64("theta", "", vec![theta])
            .with_f64("gamma_target", "", vec![p.gamma])
            .with_f64("gamma", "", vec![s.gamma()])
            .with_f64("rho_large", "", vec![rho_l])
            .with_f64("rho_small", "", vec![rho_s])
            .with_f64("rho_particles", "", vec![rho_l + rho_s])
            .with_f64("large_gap", "m", vec![c.gap])
            .with_i64("samplings", "", vec![c.samplings as i64]);
        let mut out = Outputs::new();
        out.insert(
            "packing".into(),
            grainpipe_core::Artifact::Packing(to_packing(spec, s)),
        );
        out.insert("report".into(), grainpipe_core::Artifact::Table(report));
        Ok(out)
    }
}
