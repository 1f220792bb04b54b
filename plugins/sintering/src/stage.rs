//! The `sintering.laser` stage: drives the heat balance along a laser path and collects
//! bonds, per-particle temperatures, snapshots and the energy history.

use crate::params::{Integrator, LaserParams, PathKind, TopSurface};
use crate::path::LaserPath;
use crate::thermal::{plan_view, Beam, Bed, Material, Multirate, StepStats};
use grainpipe_core::model::{
    Artifact, ArtifactKind, ArtifactMeta, BodyAttribute, BodyShape, ContactGraph, Packing, Series,
    Table,
};
use grainpipe_core::spatial::CellList;
use grainpipe_core::stage::{input, InputMetas, Inputs, Outputs, Preflight, RunContext};
use grainpipe_core::{PortSpec, StageError, StageInfo, TypedStage};
use std::f64::consts::PI;

pub struct LaserSintering;

/// Everything a run produces, for callers that want more than the artifacts.
pub struct RunResult {
    pub bonds: ContactGraph,
    pub packing: Packing,
    pub snapshots: Series,
    pub history: Table,
    pub steps: u64,
    /// Candidate absorbers (particles the beam can reach).
    pub absorbers: Vec<usize>,
}

fn check(cond: bool, key: &str, msg: impl Into<String>) -> Result<(), StageError> {
    if cond {
        Ok(())
    } else {
        Err(StageError::param(key, msg))
    }
}

fn positive(v: f64, key: &str, what: &str) -> Result<(), StageError> {
    check(
        v.is_finite() && v > 0.0,
        key,
        format!("must be a positive {what}, got {v}"),
    )
}

fn non_negative(v: f64, key: &str, what: &str) -> Result<(), StageError> {
    check(
        v.is_finite() && v >= 0.0,
        key,
        format!("must be a non-negative {what}, got {v}"),
    )
}

/// Checks every parameter value (no input needed) and, for `path: csv`, reads and parses the
/// path file: the one file the stage reads, read here once and handed to the run.
pub fn validate(p: &LaserParams) -> Result<Option<LaserPath>, StageError> {
    non_negative(p.power.si(), "power", "power in W")?;
    check(
        (0.0..=1.0).contains(&p.absorptivity),
        "absorptivity",
        format!(
            "must be a fraction in [0, 1], got {} (1 = the paper's literal model)",
            p.absorptivity
        ),
    )?;
    positive(
        p.boiling_temperature.si(),
        "boiling_temperature",
        "absolute temperature",
    )?;
    positive(p.beam_radius.si(), "beam_radius", "length")?;
    positive(p.specific_heat.si(), "specific_heat", "specific heat")?;
    positive(p.density.si(), "density", "density")?;
    non_negative(
        p.convection_conductance.si(),
        "convection_conductance",
        "conductance",
    )?;
    non_negative(
        p.contact_conductance.si(),
        "contact_conductance",
        "conductance",
    )?;
    non_negative(
        p.bonded_conductance.si(),
        "bonded_conductance",
        "conductance",
    )?;
    positive(
        p.ambient_temperature.si(),
        "ambient_temperature",
        "absolute temperature",
    )?;
    if let Some(t) = p.initial_temperature {
        positive(t.si(), "initial_temperature", "absolute temperature")?;
    }
    positive(
        p.sintering_temperature.si(),
        "sintering_temperature",
        "absolute temperature",
    )?;
    positive(p.scan_speed.si(), "scan_speed", "velocity")?;
    non_negative(p.cooldown.si(), "cooldown", "time")?;
    let csv = match p.path {
        PathKind::Raster => {
            positive(p.raster_length.si(), "raster_length", "length")?;
            positive(p.hatch_spacing.si(), "hatch_spacing", "length")?;
            if let Some(c) = p.raster_center {
                check(
                    c.iter().all(|v| v.si().is_finite()),
                    "raster_center",
                    "must be two finite lengths",
                )?;
            }
            None
        }
        PathKind::Csv => {
            positive(p.path_csv_unit.si(), "path_csv_unit", "length")?;
            Some(read_csv_path(p)?)
        }
    };
    positive(p.surface_depth.si(), "surface_depth", "length")?;
    if p.melting {
        check(
            p.melting_temperature.si() > p.ambient_temperature.si(),
            "melting_temperature",
            format!(
                "must exceed ambient_temperature ({} K), got {} K",
                p.ambient_temperature.si(),
                p.melting_temperature.si()
            ),
        )?;
        non_negative(p.latent_heat.si(), "latent_heat", "specific energy")?;
        check(
            p.integrator == Integrator::Explicit,
            "melting",
            "latent heat makes the implicit system nonlinear and is only available with \
             integrator: explicit",
        )?;
    }
    if let Some(dt) = p.dt {
        positive(dt.si(), "dt", "time")?;
    }
    check(
        p.dt_safety > 0.0 && p.dt_safety <= 1.0,
        "dt_safety",
        format!("must be in (0, 1], got {}", p.dt_safety),
    )?;
    check(
        p.cg_tolerance > 0.0 && p.cg_tolerance <= 1e-3,
        "cg_tolerance",
        format!(
            "must be in (0, 1e-3] (1e-12 gives round-off energy balance), got {}",
            p.cg_tolerance
        ),
    )?;
    non_negative(p.snapshot_interval.si(), "snapshot_interval", "time")?;
    non_negative(p.history_interval.si(), "history_interval", "time")?;
    check(p.max_steps >= 1, "max_steps", "must be at least 1")?;
    Ok(csv)
}

fn read_csv_path(p: &LaserParams) -> Result<LaserPath, StageError> {
    if p.path_csv.is_empty() {
        return Err(StageError::param(
            "path_csv",
            "path: csv needs a CSV file with columns x,y[,on]",
        ));
    }
    let text = std::fs::read_to_string(&p.path_csv)
        .map_err(|e| StageError::param("path_csv", format!("cannot read {}: {e}", p.path_csv)))?;
    LaserPath::from_csv(&text, p.path_csv_unit.si(), p.scan_speed.si())
        .map_err(|e| StageError::param("path_csv", format!("{}: {e}", p.path_csv)))
}

/// The raster of `p` centred on `center` (its timing does not depend on the centre).
fn raster(p: &LaserParams, center: [f64; 2]) -> LaserPath {
    LaserPath::raster(
        center,
        p.raster_length.si(),
        p.hatch_spacing.si(),
        p.passes,
        p.alternate,
        p.scan_axis,
        p.scan_speed.si(),
    )
}

/// The laser path for a packing: the CSV path [`validate`] read, or the raster (centred on
/// the domain middle by default).
pub fn build_path(p: &LaserParams, csv: Option<&LaserPath>, packing: &Packing) -> LaserPath {
    match csv {
        Some(path) => path.clone(),
        None => {
            let d = &packing.domain;
            let center = match p.raster_center {
                Some(c) => [c[0].si(), c[1].si()],
                None => [0.5 * (d.min[0] + d.max[0]), 0.5 * (d.min[1] + d.max[1])],
            };
            raster(p, center)
        }
    }
}

/// Candidate absorbers: the top surface by the chosen rule, optionally filtered by shadowing.
pub fn select_absorbers(
    p: &LaserParams,
    pos: &[[f64; 3]],
    radius: &[f64],
    contacts: &ContactGraph,
) -> Result<Vec<usize>, StageError> {
    let n = pos.len();
    let by_depth = || {
        let top = (0..n)
            .map(|i| pos[i][2] + radius[i])
            .fold(f64::NEG_INFINITY, f64::max);
        let depth = p.surface_depth.si();
        (0..n)
            .filter(|&i| pos[i][2] + radius[i] >= top - depth)
            .collect::<Vec<_>>()
    };
    let zmax = &contacts.faces[5];
    let mut ids: Vec<usize> = match p.top_surface {
        TopSurface::Auto if !zmax.is_empty() => zmax.clone(),
        TopSurface::Auto | TopSurface::Depth => by_depth(),
        TopSurface::Face => {
            if zmax.is_empty() {
                return Err(StageError::input(
                    "contacts",
                    "top_surface: face needs the zmax face list, which is empty; use \
                     top_surface: depth",
                ));
            }
            zmax.clone()
        }
        TopSurface::All => (0..n).collect(),
    };
    if let Some(&bad) = ids.iter().find(|&&i| i >= n) {
        return Err(StageError::input(
            "contacts",
            format!("zmax face lists body {bad}, but the packing has {n} bodies"),
        ));
    }
    ids.sort_unstable();
    ids.dedup();
    if p.shadowing {
        // Covered = some higher particle's plan-view disc contains this centre.
        let rmax = radius.iter().cloned().fold(0.0, f64::max);
        let all: Vec<usize> = (0..n).collect();
        let grid = plan_view(&all, pos, (2.0 * rmax).max(1e-12));
        ids.retain(|&i| {
            let mut covered = false;
            grid.visit([pos[i][0], pos[i][1], 0.0], rmax, |j, _| {
                let j = j as usize;
                if j != i && pos[j][2] > pos[i][2] {
                    let d2 = (pos[j][0] - pos[i][0]).powi(2) + (pos[j][1] - pos[i][1]).powi(2);
                    if d2 < radius[j] * radius[j] {
                        covered = true;
                    }
                }
                true
            });
            !covered
        });
    }
    Ok(ids)
}

/// Runs the simulation: checks the parameters (reading a CSV path), then runs.
pub fn simulate(
    p: &LaserParams,
    packing: &Packing,
    contacts: &ContactGraph,
    ctx: &RunContext,
) -> Result<RunResult, StageError> {
    let csv = validate(p)?;
    simulate_checked(p, csv.as_ref(), packing, contacts, ctx)
}

/// Runs the simulation with parameters [`validate`] accepted; `csv` is the path it read.
pub fn simulate_checked(
    p: &LaserParams,
    csv: Option<&LaserPath>,
    packing: &Packing,
    contacts: &ContactGraph,
    ctx: &RunContext,
) -> Result<RunResult, StageError> {
    // Run the time loop on a worker of the current rayon pool: the per-step parallel
    // loops (several per CG iteration) then split locally instead of each waking the pool
    // from outside, which costs more than the work on a busy machine.
    rayon::scope(|_| simulate_in_pool(p, csv, packing, contacts, ctx))
}

fn simulate_in_pool(
    p: &LaserParams,
    csv: Option<&LaserPath>,
    packing: &Packing,
    contacts: &ContactGraph,
    ctx: &RunContext,
) -> Result<RunResult, StageError> {
    let n = packing.bodies.len();
    if n == 0 {
        return Err(StageError::input("packing", "has no bodies"));
    }
    let (pos, radius, volume) = particles(packing)?;
    let (pairs, bonded0) = conduction_pairs(contacts, n)?;
    let beam = Beam {
        // Only the absorbed part of the beam heats the bed.
        power: p.absorptivity * p.power.si(),
        radius: p.beam_radius.si(),
        profile: p.beam_profile,
    };
    let t0 = initial_temperatures(p, packing)?;
    let absorbers = select_absorbers(p, &pos, &radius, contacts)?;
    let path = build_path(p, csv, packing);
    let grid = plan_view(&absorbers, &pos, beam.reach());
    let bed = Bed::new(pos, radius, &volume, pairs, bonded0, material(p), t0);

    let t_end = path.duration() + p.cooldown.si();
    let beam_dt = beam.radius / (5.0 * p.scan_speed.si());
    let user_dt = p.dt.map(|d| d.si());
    let explicit = p.integrator == Integrator::Explicit;
    let mut integrator: Box<dyn Integrate> = if explicit {
        Box::new(Explicit {
            p,
            user_dt,
            beam_dt,
            multirate: p.multirate && p.substep,
            plan: None,
        })
    } else {
        Box::new(Implicit {
            dt: user_dt.unwrap_or(beam_dt),
            tolerance: p.cg_tolerance,
        })
    };
    let mut s = Stepper {
        limit: bed.stability_limit(),
        qlas: vec![0.0; n],
        bed,
        path: &path,
        grid: &grid,
        beam: &beam,
        explicit,
        t_end,
        // Relative time tolerance for "reached" tests against accumulated float time.
        eps: 1e-12 * t_end.max(1e-300),
        max_steps: p.max_steps,
        t: 0.0,
        steps: 0,
        laser_in: 0.0,
        convected: 0.0,
        last: Last::default(),
        touched: Vec::new(),
        samples: Vec::new(),
        changed: Vec::new(),
    };
    let mut rec = Recorder::new(p, packing, &s);
    let mut reported = 0u64;
    while s.t < t_end - s.eps {
        let h = rec.shorten(&s, integrator.dt(&s).min(t_end - s.t));
        s.last.substeps = 0;
        s.last.stiff = 0;
        integrator.step(&mut s, h)?;
        rec.record(&s, packing);
        let permille = (s.t / t_end * 1000.0) as u64;
        if permille > reported {
            reported = permille;
            ctx.progress(permille.min(1000), 1000)?;
        }
    }
    results(p, packing, contacts, s, rec, absorbers, ctx)
}

/// Positions, volume-equivalent radii and volumes of the bodies.
#[allow(clippy::type_complexity)]
fn particles(packing: &Packing) -> Result<(Vec<[f64; 3]>, Vec<f64>, Vec<f64>), StageError> {
    let n = packing.bodies.len();
    let mut pos = Vec::with_capacity(n);
    let mut radius = Vec::with_capacity(n);
    let mut volume = Vec::with_capacity(n);
    for (i, b) in packing.bodies.iter().enumerate() {
        let v = packing.body_volume(b);
        if !(v.is_finite() && v > 0.0) {
            return Err(StageError::input(
                "packing",
                format!("body {i} has volume {v}; a particle needs a positive volume"),
            ));
        }
        pos.push(b.position);
        volume.push(v);
        radius.push(match b.shape {
            BodyShape::Sphere { radius } => radius,
            // Volume-equivalent sphere for clumps.
            BodyShape::Clump { .. } => (3.0 * v / (4.0 * PI)).cbrt(),
        });
    }
    Ok((pos, radius, volume))
}

/// Conduction pairs: every contact and every pre-existing bond, each once and sorted, with
/// whether it starts bonded.
fn conduction_pairs(
    contacts: &ContactGraph,
    n: usize,
) -> Result<(Vec<[usize; 2]>, Vec<bool>), StageError> {
    let mut keyed: Vec<([usize; 2], bool)> = Vec::new();
    for c in &contacts.contacts {
        keyed.push(([c.i.min(c.j), c.i.max(c.j)], false));
    }
    for b in &contacts.bonds {
        keyed.push(([b[0].min(b[1]), b[0].max(b[1])], true));
    }
    for (pr, _) in &keyed {
        if pr[1] >= n || pr[0] == pr[1] {
            return Err(StageError::input(
                "contacts",
                format!(
                    "pair ({}, {}) is invalid for a packing of {n} bodies",
                    pr[0], pr[1]
                ),
            ));
        }
    }
    // Sort by pair, bonded last so the bonded flag wins when deduplicating.
    keyed.sort_unstable();
    let mut pairs: Vec<[usize; 2]> = Vec::with_capacity(keyed.len());
    let mut bonded0: Vec<bool> = Vec::with_capacity(keyed.len());
    for (pr, b) in keyed {
        if pairs.last() == Some(&pr) {
            *bonded0.last_mut().expect("same length") |= b;
        } else {
            pairs.push(pr);
            bonded0.push(b);
        }
    }
    Ok((pairs, bonded0))
}

fn material(p: &LaserParams) -> Material {
    Material {
        specific_heat: p.specific_heat.si(),
        density: p.density.si(),
        convection: p.convection_conductance.si(),
        contact: p.contact_conductance.si(),
        bonded: p.bonded_conductance.si(),
        ambient: p.ambient_temperature.si(),
        sintering: p.sintering_temperature.si(),
        melting: p
            .melting
            .then(|| (p.melting_temperature.si(), p.latent_heat.si())),
    }
}

/// The starting temperatures: `initial_temperature`, else the packing's `temperature`
/// attribute (a previous run), else ambient.
fn initial_temperatures(p: &LaserParams, packing: &Packing) -> Result<Vec<f64>, StageError> {
    let n = packing.bodies.len();
    match (p.initial_temperature, packing.attributes.get("temperature")) {
        (Some(t), _) => Ok(vec![t.si(); n]),
        (None, Some(a)) => {
            if a.values.len() != n || a.values.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(StageError::input(
                    "packing",
                    format!(
                        "attribute `temperature` must hold {n} positive temperatures in K to \
                         start from; set initial_temperature to ignore it"
                    ),
                ));
            }
            Ok(a.values.clone())
        }
        (None, None) => Ok(vec![p.ambient_temperature.si(); n]),
    }
}

/// A time integrator of the bed: the step it takes next and the step itself (laser
/// deposition and bookkeeping go through [`Stepper::advance`], bonding through
/// [`Stepper::bond`]).
trait Integrate {
    /// The next step length, before the end time and the snapshot schedule shorten it.
    fn dt(&mut self, s: &Stepper) -> f64;
    /// Advances `s` by `h`.
    fn step(&mut self, s: &mut Stepper, h: f64) -> Result<(), StageError>;
}

/// Backward Euler, solved by conjugate gradients.
struct Implicit {
    dt: f64,
    tolerance: f64,
}

impl Integrate for Implicit {
    fn dt(&mut self, _: &Stepper) -> f64 {
        self.dt
    }

    fn step(&mut self, s: &mut Stepper, h: f64) -> Result<(), StageError> {
        let (t, tol) = (s.t, self.tolerance);
        let st = s.advance(h, |bed, q| {
            bed.implicit_step(h, q, tol)
                .map_err(|e| StageError::failed(format!("at t = {t:.6e} s: {e}")))
        })?;
        s.last.substeps = 1;
        s.bond(&mut None);
        s.check(&st, Scheme::Implicit)
    }
}

/// Forward Euler (the paper's scheme): either one global step in which the particles of a
/// multirate plan are sub-cycled at their own stable step, or stable sub-steps of the whole
/// bed.
struct Explicit<'p> {
    p: &'p LaserParams,
    user_dt: Option<f64>,
    beam_dt: f64,
    /// Whether to plan multirate sub-cycling (`multirate` and `substep`).
    multirate: bool,
    /// The current plan; dropped when bonding makes too many particles stiff.
    plan: Option<Multirate>,
}

impl Integrate for Explicit<'_> {
    fn dt(&mut self, s: &Stepper) -> f64 {
        if self.multirate && self.plan.is_none() {
            self.plan = Some(s.bed.plan(self.beam_dt, self.p.dt_safety, self.user_dt));
        }
        match (&self.plan, self.user_dt) {
            (Some(pl), _) => pl.dt,
            (None, Some(d)) => d,
            (None, None) => (self.p.dt_safety * s.limit).min(self.beam_dt),
        }
    }

    fn step(&mut self, s: &mut Stepper, h: f64) -> Result<(), StageError> {
        let n = s.bed.n;
        let sub_cycles = self
            .plan
            .as_ref()
            .is_some_and(|pl| !pl.stiff.is_empty() && 2 * pl.stiff.len() <= n);
        if sub_cycles {
            self.multirate_step(s, h)
        } else {
            self.sub_steps(s, h)
        }
    }
}

impl Explicit<'_> {
    fn multirate_step(&mut self, s: &mut Stepper, h: f64) -> Result<(), StageError> {
        let (n, safety) = (s.bed.n, self.p.dt_safety);
        let pl = self.plan.as_ref().expect("called with a plan");
        let stiff = pl.stiff.len();
        // max_steps bounds the real work, counted in whole-bed steps: a sub-cycle of the
        // `stiff` particles costs 2 stiff / n of one (sequential, as the plan counts it), and
        // a global step whose sub-cycles would pass the limit is not started.
        let planned = (h / (safety * pl.stiff_limit)).ceil().max(1.0);
        let work = |cycles: f64| ((cycles - 1.0).max(0.0) * 2.0 * stiff as f64 / n as f64).ceil();
        if s.steps as f64 + 1.0 + work(planned) > s.max_steps as f64 {
            return Err(StageError::failed(format!(
                "reached max_steps = {} at t = {:.6e} s of {:.6e} s: the next step of {h:.3e} \
                 s would sub-cycle {stiff} stiff particles {planned} times (their stability \
                 limit is {:.3e} s); raise max_steps, lower bonded_conductance or \
                 contact_conductance, or use integrator: implicit",
                s.max_steps, s.t, s.t_end, pl.stiff_limit
            )));
        }
        let mut cycles = 0;
        let st = s.advance(h, |bed, q| {
            let (st, k) = bed.explicit_step_multirate(h, q, pl, safety);
            cycles = k;
            Ok(st)
        })?;
        s.last.substeps = cycles;
        s.last.stiff = stiff;
        // `advance` counted the global step; the further sub-cycles are work too.
        s.steps = s.steps.saturating_add(work(cycles as f64) as u64);
        s.bond(&mut self.plan);
        s.check(&st, Scheme::Multirate)
    }

    /// A step up to the stability limit is taken as given (automatic steps are dt_safety x
    /// limit). Above it: refuse a user dt, or split into equal stable sub-steps, re-planned
    /// when bonding changes the limit.
    fn sub_steps(&mut self, s: &mut Stepper, h: f64) -> Result<(), StageError> {
        let p = self.p;
        let single = h <= s.limit * (1.0 + 1e-12);
        if !single && !p.substep && self.user_dt.is_some() {
            return Err(StageError::param(
                "dt",
                format!(
                    "dt = {:.6e} s exceeds the explicit stability limit {:.6e} s (min over \
                     particles of m_i C_p / (sum_j k_ij + k_b)) at t = {:.6e} s; use dt <= \
                     {:.6e} s, substep: true or integrator: implicit",
                    self.user_dt.unwrap_or(h),
                    s.limit,
                    s.t,
                    s.limit
                ),
            ));
        }
        let mut remaining = h;
        let mut sub_len = 0.0;
        while remaining > s.eps {
            let sub = if single {
                remaining
            } else {
                if sub_len == 0.0 {
                    sub_len = remaining / (remaining / (p.dt_safety * s.limit)).ceil();
                }
                if remaining < 1.5 * sub_len {
                    remaining
                } else {
                    sub_len
                }
            };
            let st = s.advance(sub, |bed, q| Ok(bed.explicit_step(sub, q)))?;
            remaining -= sub;
            s.last.substeps += 1;
            if s.bond(&mut self.plan) {
                sub_len = 0.0;
            }
            s.check(&st, Scheme::Explicit)?;
        }
        Ok(())
    }
}

/// The history rows and temperature snapshots of a run, on their schedules.
struct Recorder {
    hist: History,
    snapshots: Series,
    snap_every: f64,
    hist_every: f64,
    next_snap: f64,
    next_hist: f64,
}

impl Recorder {
    /// Starts with the initial state.
    fn new(p: &LaserParams, packing: &Packing, s: &Stepper) -> Self {
        let snap_every = p.snapshot_interval.si();
        let hist_every = p.history_interval.si();
        let mut r = Recorder {
            hist: History::default(),
            snapshots: Series { frames: Vec::new() },
            snap_every,
            hist_every,
            next_snap: if snap_every > 0.0 {
                snap_every
            } else {
                f64::INFINITY
            },
            next_hist: hist_every,
        };
        r.snapshots.frames.push((0.0, frame(packing, &s.bed.t)));
        r.hist.push(s);
        r
    }

    /// `h` shortened to end on the next snapshot time.
    fn shorten(&self, s: &Stepper, h: f64) -> f64 {
        if self.next_snap - s.t > s.eps {
            h.min(self.next_snap - s.t)
        } else {
            h
        }
    }

    /// Records the state after a step: a history row when one is due or the run ends, a
    /// snapshot when one is due, and the final state.
    fn record(&mut self, s: &Stepper, packing: &Packing) {
        let (t, eps) = (s.t, s.eps);
        let done = t >= s.t_end - eps;
        if done || t >= self.next_hist - eps || self.hist_every == 0.0 {
            self.hist.push(s);
            while self.next_hist <= t + eps {
                self.next_hist += self.hist_every.max(f64::MIN_POSITIVE);
                if self.hist_every == 0.0 {
                    break;
                }
            }
        }
        if t >= self.next_snap - eps {
            self.snapshots.frames.push((t, frame(packing, &s.bed.t)));
            while self.next_snap <= t + eps {
                self.next_snap += self.snap_every;
            }
        } else if done && self.snapshots.frames.last().map(|f| f.0) != Some(t) {
            self.snapshots.frames.push((t, frame(packing, &s.bed.t)));
        }
    }
}

/// The run's artifacts: per-particle attributes, the bond graph, the message and the
/// validity check.
fn results(
    p: &LaserParams,
    packing: &Packing,
    contacts: &ContactGraph,
    s: Stepper,
    rec: Recorder,
    absorbers: Vec<usize>,
    ctx: &RunContext,
) -> Result<RunResult, StageError> {
    let Stepper {
        bed,
        t,
        steps,
        laser_in,
        convected,
        ..
    } = s;
    let n = bed.n;
    let mut out = packing.clone();
    let attr = |unit: &str, values: Vec<f64>| BodyAttribute {
        unit: unit.into(),
        values,
    };
    let mut bond_count = vec![0.0; n];
    let mut bonds = Vec::new();
    let mut bond_time = Vec::new();
    for ((pr, &b), &t) in bed.pairs.iter().zip(&bed.bonded).zip(&bed.bond_time) {
        if b {
            bonds.push(*pr);
            bond_time.push(t);
            bond_count[pr[0]] += 1.0;
            bond_count[pr[1]] += 1.0;
        }
    }
    out.attributes
        .insert("temperature".into(), attr("K", bed.t.clone()));
    out.attributes
        .insert("peak_temperature".into(), attr("K", bed.peak.clone()));
    out.attributes.insert(
        "time_above_sintering".into(),
        attr("s", bed.time_above.clone()),
    );
    out.attributes
        .insert("bond_count".into(), attr("", bond_count));
    let graph = ContactGraph {
        contacts: contacts.contacts.clone(),
        faces: contacts.faces.clone(),
        bonds,
        // When each bond formed (0 for bonds given by the input graph).
        bond_attributes: [("bond_time".to_string(), attr("s", bond_time))]
            .into_iter()
            .collect(),
        positions: bed.pos.clone(),
        radii: bed.radius.clone(),
    };
    let peak = bed.peak.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    ctx.info(&format!(
        "sintering.laser: {n} particles, {} absorbers, {steps} steps to t = {t:.4e} s, {} of \
         {} contacts bonded, peak {peak:.4e} K, energy residual {:.2e} J of {:.3e} J laser input",
        absorbers.len(),
        graph.bonds.len(),
        bed.pairs.len(),
        laser_in - bed.stored() - convected,
        laser_in
    ));
    if let Some(m) = validity_warning(p, peak, &bed.peak) {
        if p.refuse_invalid {
            return Err(StageError::failed(m));
        }
        ctx.warn(&m);
    }
    Ok(RunResult {
        bonds: graph,
        packing: out,
        snapshots: rec.snapshots,
        history: rec.hist.table(),
        steps,
        absorbers,
    })
}

/// The warning for a result outside the model's range of validity: a peak temperature above
/// `boiling_temperature`, where the real powder evaporates and the model (conduction between
/// rigid spheres, convection, optional latent heat of melting) no longer describes it.
pub fn validity_warning(p: &LaserParams, peak: f64, peaks: &[f64]) -> Option<String> {
    let boil = p.boiling_temperature.si();
    if peak.is_finite() && peak <= boil {
        return None;
    }
    let above = peaks.iter().filter(|&&t| t.is_nan() || t > boil).count();
    Some(format!(
        "RESULT OUTSIDE THE MODEL'S RANGE OF VALIDITY: peak temperature {peak:.4e} K exceeds \
         boiling_temperature = {boil} K in {above} of {} particles (the model has no \
         evaporation or melt flow, so these temperatures are not physical). Lower power \
         ({} W) or absorptivity ({}), or raise scan_speed ({} m/s) or beam_radius; \
         refuse_invalid: true makes this an error",
        peaks.len(),
        p.power.si(),
        p.absorptivity,
        p.scan_speed.si()
    ))
}

/// How a step was integrated, for the messages of [`Stepper::check`].
#[derive(Clone, Copy, PartialEq)]
enum Scheme {
    /// Explicit, stiff particles sub-cycled inside the global step.
    Multirate,
    /// Explicit (sub-)step of the whole bed.
    Explicit,
    /// Backward Euler.
    Implicit,
}

/// The time loop's state that every integrator advances the same way: the bed, the clock,
/// the energy bookkeeping, the laser deposition and bonding.
struct Stepper<'a> {
    bed: Bed,
    path: &'a LaserPath,
    grid: &'a CellList,
    beam: &'a Beam,
    /// Whether the integrator is explicit (the stability limit then follows bonding).
    explicit: bool,
    t_end: f64,
    /// Tolerance of "reached" tests against the accumulated time [s].
    eps: f64,
    max_steps: u64,
    t: f64,
    steps: u64,
    /// Laser energy put in and energy convected out so far [J].
    laser_in: f64,
    convected: f64,
    /// Explicit stability limit of the current conductances [s].
    limit: f64,
    last: Last,
    // Scratch: laser power per particle over a step, particles it touched, spot samples,
    // particles whose conductance changed.
    qlas: Vec<f64>,
    touched: Vec<usize>,
    samples: Vec<([f64; 2], f64)>,
    changed: Vec<usize>,
}

impl Stepper<'_> {
    /// Advances by `dt` with `step` (an integrator step given the mean laser power per
    /// particle over it): deposits the laser power, books the energy and counts the step.
    fn advance(
        &mut self,
        dt: f64,
        step: impl FnOnce(&mut Bed, &[f64]) -> Result<StepStats, StageError>,
    ) -> Result<StepStats, StageError> {
        let q_sum = deposit(
            self.path,
            self.grid,
            self.beam,
            &self.bed.pos,
            &self.bed.radius,
            self.t,
            self.t + dt,
            &mut self.qlas,
            &mut self.touched,
            &mut self.samples,
        );
        let st = step(&mut self.bed, &self.qlas)?;
        clear(&mut self.qlas, &mut self.touched);
        self.laser_in += dt * q_sum;
        self.convected += st.convected;
        self.t += dt;
        self.steps += 1;
        self.last.dt = dt;
        self.last.stats = st;
        Ok(st)
    }

    /// Bonds the hot contacts. When conductances changed under an explicit integrator, the
    /// stability limit is recomputed and the multirate plan kept valid (dropped when too many
    /// particles would be sub-cycled sequentially, so a new global step is chosen). Returns
    /// whether conductances changed.
    fn bond(&mut self, plan: &mut Option<Multirate>) -> bool {
        self.changed.clear();
        let (_, changed) = self.bed.form_bonds(self.t, &mut self.changed);
        if changed && self.explicit {
            self.limit = self.bed.stability_limit();
            if let Some(pl) = plan.as_mut() {
                self.bed.update_plan(pl, &self.changed);
                if 2 * pl.stiff.len() > self.bed.n {
                    *plan = None;
                }
            }
        }
        changed
    }

    /// Fails when the temperature became non-finite (explicit) or the step limit is reached.
    fn check(&self, st: &StepStats, scheme: Scheme) -> Result<(), StageError> {
        let (t, dt, steps) = (self.t, self.last.dt, self.steps);
        if scheme != Scheme::Implicit && !st.max_t.is_finite() {
            let detail = match scheme {
                Scheme::Multirate => format!("{} sub-cycled particles", self.last.stiff),
                _ => format!("stability limit {:.3e} s", self.limit),
            };
            return Err(StageError::failed(format!(
                "temperature became non-finite at t = {t:.6e} s after {steps} steps (dt \
                 {dt:.3e} s, {detail})"
            )));
        }
        if steps >= self.max_steps {
            let detail = match scheme {
                Scheme::Explicit => format!(
                    ", stability limit {:.3e} s); raise max_steps or use integrator: implicit",
                    self.limit
                ),
                _ => ")".to_string(),
            };
            return Err(StageError::failed(format!(
                "reached max_steps = {} at t = {t:.6e} s of {:.6e} s (dt {dt:.3e} s{detail}",
                self.max_steps, self.t_end
            )));
        }
        Ok(())
    }
}

/// Accumulates the mean laser power per particle over [a, b] into `qlas` (indices listed
/// in `touched`) and returns its sum [W]. The spot is sampled at most r_L/8 apart along the
/// lit path (see [`LaserPath::samples`]), so a long implicit step deposits the whole swept
/// track and the laser switches off exactly at the end of a scan line.
#[allow(clippy::too_many_arguments)]
fn deposit(
    path: &LaserPath,
    grid: &CellList,
    beam: &Beam,
    pos: &[[f64; 3]],
    radius: &[f64],
    a: f64,
    b: f64,
    qlas: &mut [f64],
    touched: &mut Vec<usize>,
    samples: &mut Vec<([f64; 2], f64)>,
) -> f64 {
    path.samples(a, b, beam.radius / 8.0, samples);
    let reach = beam.reach();
    for &(spot, w) in samples.iter() {
        grid.visit([spot[0], spot[1], 0.0], reach, |i, _| {
            let i = i as usize;
            let d2 = (pos[i][0] - spot[0]).powi(2) + (pos[i][1] - spot[1]).powi(2);
            let q = beam.flux(radius[i], d2);
            if q > 0.0 {
                if qlas[i] == 0.0 {
                    touched.push(i);
                }
                qlas[i] += w * q;
            }
            true
        });
    }
    // Sum in index order so the total does not depend on the visiting order.
    touched.sort_unstable();
    touched.iter().map(|&i| qlas[i]).sum()
}

fn clear(qlas: &mut [f64], touched: &mut Vec<usize>) {
    for &i in touched.iter() {
        qlas[i] = 0.0;
    }
    touched.clear();
}

/// A snapshot frame: the packing with its temperature attribute.
fn frame(packing: &Packing, t: &[f64]) -> Artifact {
    let mut f = packing.clone();
    f.attributes.insert(
        "temperature".into(),
        BodyAttribute {
            unit: "K".into(),
            values: t.to_vec(),
        },
    );
    Artifact::Packing(f)
}

#[derive(Default)]
struct Last {
    dt: f64,
    substeps: u64,
    stiff: usize,
    stats: StepStats,
}

#[derive(Default)]
struct History {
    time: Vec<f64>,
    steps: Vec<i64>,
    dt: Vec<f64>,
    substeps: Vec<i64>,
    stiff: Vec<i64>,
    limit: Vec<f64>,
    bonds: Vec<i64>,
    bonded_fraction: Vec<f64>,
    bonded_particle_fraction: Vec<f64>,
    max_t: Vec<f64>,
    mean_t: Vec<f64>,
    laser: Vec<f64>,
    stored: Vec<f64>,
    convected: Vec<f64>,
    residual: Vec<f64>,
    cg: Vec<i64>,
}

impl History {
    fn push(&mut self, s: &Stepper) {
        let (bed, t, steps, last) = (&s.bed, s.t, s.steps, &s.last);
        let (laser, convected, limit) = (s.laser_in, s.convected, s.limit);
        let nb = bed.bond_count();
        let stored = bed.stored();
        let n = bed.n as f64;
        self.time.push(t);
        self.steps.push(steps as i64);
        self.dt.push(last.dt);
        self.substeps.push(last.substeps as i64);
        self.stiff.push(last.stiff as i64);
        self.limit.push(limit);
        self.bonds.push(nb as i64);
        self.bonded_fraction
            .push(nb as f64 / (bed.pairs.len().max(1)) as f64);
        self.bonded_particle_fraction
            .push(bed.bonded_particles() as f64 / n);
        let (mx, mean) = if steps == 0 {
            (
                bed.t.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
                bed.t.iter().sum::<f64>() / n,
            )
        } else {
            (last.stats.max_t, last.stats.sum_t / n)
        };
        self.max_t.push(mx);
        self.mean_t.push(mean);
        self.laser.push(laser);
        self.stored.push(stored);
        self.convected.push(convected);
        // Conduction only moves energy between particles: laser in = stored + convected.
        self.residual.push(laser - stored - convected);
        self.cg.push(last.stats.iterations as i64);
    }

    fn table(self) -> Table {
        Table::new("sintering_history")
            .with_f64("time", "s", self.time)
            .with_i64("steps", "", self.steps)
            .with_f64("dt", "s", self.dt)
            .with_i64("substeps", "", self.substeps)
            .with_i64("subcycled_particles", "", self.stiff)
            .with_f64("stability_limit", "s", self.limit)
            .with_i64("bonds", "", self.bonds)
            .with_f64("bonded_fraction", "", self.bonded_fraction)
            .with_f64(
                "bonded_particle_fraction",
                "",
                self.bonded_particle_fraction,
            )
            .with_f64("max_temperature", "K", self.max_t)
            .with_f64("mean_temperature", "K", self.mean_t)
            .with_f64("laser_energy", "J", self.laser)
            .with_f64("stored_energy", "J", self.stored)
            .with_f64("convected_energy", "J", self.convected)
            .with_f64("energy_residual", "J", self.residual)
            .with_i64("cg_iterations", "", self.cg)
    }
}

/// Frames of the snapshot series over `t_end` with snapshots every `every` (0 = none): the
/// initial state, one frame per snapshot time reached and the final state unless it falls on
/// one. Bounds: the count is exact up to whether the last snapshot time and the end coincide
/// in the accumulated time.
fn frame_bounds(t_end: f64, every: f64) -> [u64; 2] {
    let end = u64::from(t_end > 0.0);
    if every > 0.0 {
        let k = t_end / every;
        [
            1 + (k * (1.0 - 1e-9)).floor() as u64,
            1 + end + (k * (1.0 + 1e-9)).floor() as u64,
        ]
    } else {
        [1 + end; 2]
    }
}

impl TypedStage for LaserSintering {
    type Params = LaserParams;
    /// The path file of `path: csv`, parsed once, in preflight.
    type Plan = Option<LaserPath>;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "sintering.laser",
            "0.2.0",
            "Laser heating of a particle bed with bond formation (Method 2 paper, \
             section 5): per-particle heat balance m_i C_p dT_i/dt = Q r_i^2/r_L^2 (top-\
             surface particles within r_L of the spot) + k_b (T_R - T_i) + sum_j k_ij \
             (T_j - T_i) over the contact graph, integrated explicitly (paper) with \
             automatic stable sub-steps or implicitly (backward Euler, CG); a contact \
             bonds when both particles exceed T_S. Laser path: raster of a rectangle \
             (default: the section 5.2 five-pass square in the middle) or a CSV polyline.",
        )
        .inputs(vec![
            PortSpec::new("packing", ArtifactKind::Packing, "particle bed (spheres or clumps)"),
            PortSpec::new(
                "contacts",
                ArtifactKind::ContactGraph,
                "conduction pairs (contacts, existing bonds) and face lists (zmax = top surface)",
            ),
        ])
        .outputs(vec![
            PortSpec::new("bonds", ArtifactKind::ContactGraph, "input contacts and faces with the bonds formed, and body positions"),
            PortSpec::new("packing", ArtifactKind::Packing, "input packing with attributes temperature (final) [K], peak_temperature [K], time_above_sintering [s], bond_count"),
            PortSpec::new("snapshots", ArtifactKind::Series, "packing frames with a temperature attribute every snapshot_interval, plus the initial and final state"),
            PortSpec::new("history", ArtifactKind::Table, "time, bonds, bonded fractions, max/mean temperature, laser/stored/convected energy, energy residual, dt, sub-steps, stability limit"),
        ])
    }

    /// Announces the outputs: the packing is the input packing (same bodies, box and
    /// periodicity, so its metadata carries over), the bond graph keeps the input contacts
    /// (their count carries over), the snapshot count follows from the path duration.
    fn preflight(
        &self,
        p: &LaserParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<Option<LaserPath>>, StageError> {
        let csv = validate(p)?;
        for (port, kind) in [
            ("packing", ArtifactKind::Packing),
            ("contacts", ArtifactKind::ContactGraph),
        ] {
            match inputs.get(port) {
                None => return Err(StageError::input(port, "not connected")),
                Some(m) if m.kind != kind => {
                    return Err(StageError::input(
                        port,
                        format!("expects a {kind}, got a {}", m.kind),
                    ))
                }
                _ => {}
            }
        }
        let n = inputs["packing"].count_estimate.max(1);
        // The run's end time, without building a raster (a billion passes must be refused
        // here, not allocated): each line takes raster_length / scan_speed.
        let (duration, path_segments) = match &csv {
            Some(path) => (path.duration(), path.segments.len() as u64),
            None => (
                f64::from(p.passes) * p.raster_length.si() / p.scan_speed.si(),
                u64::from(p.passes),
            ),
        };
        let t_end = duration + p.cooldown.si();
        // A lower bound on the steps: no step is longer than the user's dt, or than the time
        // the beam takes to move a fifth of its radius (explicit and implicit alike).
        let dt_cap =
            p.dt.map(|d| d.si())
                .unwrap_or(p.beam_radius.si() / (5.0 * p.scan_speed.si()));
        let min_steps = (t_end / dt_cap).ceil();
        if min_steps > p.max_steps as f64 {
            return Err(StageError::param(
                if p.dt.is_some() { "dt" } else { "passes" },
                format!(
                    "the run needs at least {min_steps:.3e} time steps ({t_end:.3e} s of path \
                     and cooldown at steps of at most {dt_cap:.3e} s), above max_steps = {}; \
                     shorten the path (passes, raster_length) or the cooldown, or raise max_steps",
                    p.max_steps
                ),
            ));
        }
        let frames = frame_bounds(t_end, p.snapshot_interval.si());
        // One history row per interval, or per global step when the interval is 0; never
        // more than one per step, and the steps are bounded by max_steps.
        let step_bound = p.max_steps.saturating_add(2);
        let rows = if p.history_interval.si() > 0.0 {
            ((t_end / p.history_interval.si()).ceil() as u64)
                .saturating_add(2)
                .min(step_bound)
        } else {
            match p.dt {
                Some(_) => (min_steps as u64).saturating_add(2).min(step_bound),
                None => step_bound,
            }
        };
        // Per particle: ~16 f64 of state and scratch, ~8 contacts x 24 bytes, and one
        // packing clone (~100 bytes per body) per snapshot frame; per history row 16 columns
        // of 8 bytes; per path segment its 48 bytes.
        let memory = n
            .saturating_mul(16 * 8 + 8 * 24)
            .saturating_add(frames[1].saturating_mul(n).saturating_mul(112))
            .saturating_add(rows.saturating_mul(16 * 8))
            .saturating_add(path_segments.saturating_mul(48));
        if let Some(avail) = grainpipe_core::engine::available_memory() {
            if memory > avail {
                let (key, what) = if rows.saturating_mul(128) > avail / 2 {
                    (
                        "history_interval",
                        format!(
                            "{rows} history rows; a history_interval of at least {:.3e} s fits",
                            t_end * 256.0 / avail as f64
                        ),
                    )
                } else if path_segments.saturating_mul(48) > avail / 2 {
                    (
                        "passes",
                        format!("{path_segments} path segments; at most {} fit", avail / 96),
                    )
                } else {
                    (
                        "snapshot_interval",
                        format!(
                            "{} snapshot frames of {n} particles; a snapshot_interval of at \
                             least {:.3e} s fits",
                            frames[1],
                            t_end * (n as f64 * 224.0) / avail as f64
                        ),
                    )
                };
                return Err(StageError::param(
                    key,
                    format!(
                        "the run would need about {} MiB but {} MiB are available: {what}",
                        memory >> 20,
                        avail >> 20
                    ),
                ));
            }
        }
        Ok(Preflight::from_info(&self.info(), memory)
            .announce("bonds", inputs["contacts"].clone())
            .announce("packing", inputs["packing"].clone())
            .announce(
                "snapshots",
                ArtifactMeta::of(ArtifactKind::Series).with_count(frames[1], Some(frames)),
            )
            .announce(
                "history",
                ArtifactMeta::of(ArtifactKind::Table).with_count(rows, None),
            )
            .with_plan(csv))
    }

    fn run(
        &self,
        p: &LaserParams,
        csv: &Option<LaserPath>,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let packing = input(inputs, "packing", Artifact::as_packing)?;
        let contacts = input(inputs, "contacts", Artifact::as_contact_graph)?;
        let r = simulate_checked(p, csv.as_ref(), packing, contacts, ctx)?;
        let mut out = Outputs::new();
        out.insert("bonds".into(), Artifact::ContactGraph(r.bonds));
        out.insert("packing".into(), Artifact::Packing(r.packing));
        out.insert("snapshots".into(), Artifact::Series(r.snapshots));
        out.insert("history".into(), Artifact::Table(r.history));
        Ok(out)
    }
}
