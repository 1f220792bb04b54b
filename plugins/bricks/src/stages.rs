//! The stages `bricks.method1`, `bricks.method2` and `bricks.curved`.

use crate::assemble::{self, Assembly};
use crate::fill::{FillSettings, FillStats, Filler, Mode};
use crate::sdf::Sdf;
use grainpipe_core::distributions::{
    ks_critical_value, ks_distance, SampleCheck, SizeDistribution,
};
use grainpipe_core::params::ParamType;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, Body, BodyAttribute, ContactGraph, Domain,
    ExcludedSolid, InputMetas, Inputs, Outputs, Packing, PortSpec, Preflight, RunContext,
    StageError, StageInfo, Table, TypedStage, FACE_NAMES,
};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Spheres above which preflight refuses a run (about 4 GB of output at ~400 B per sphere).
const MAX_SPHERES: f64 = 1e7;

/// The parameters every brick stage shares, flattened into each stage's parameters. The
/// defaults below are those of `bricks.method1`; each stage includes the group with its own
/// (`BrickParams::method1_defaults()` and so on), following one of the paper's examples.
#[params]
pub struct BrickParams {
    /// Sphere radius law (Matlab makedist equivalent); default Weibull scale 15.7 um, shape 3.55 (eq. 2.4).
    pub radius: SizeDistribution,
    /// FaceGoal: fraction of each filled face covered by the projections of the spheres on it.
    #[param(default = 0.8, ty = "number in (0, 1]")]
    pub face_goal: f64,
    /// BodyGoal: fraction of the unit-brick (domain) volume filled by spheres.
    #[param(default = 0.55, ty = "number in (0, 1]")]
    pub body_goal: f64,
    /// SphereContactParameter: spheres (and faces) with gaps up to this times the mean radius are in contact.
    #[param(default = 0.2, ty = "number in [0, 1]")]
    pub contact_parameter: f64,
    /// ParentParameter: spheres with gaps up to this times the mean radius are parents of new spheres.
    #[param(default = 0.5, ty = "number in (0, 1]")]
    pub parent_parameter: f64,
    /// BrickSideLengths as multiples of std_length.
    #[param(default = [1.0, 1.0, 1.0])]
    pub brick_sides: [f64; 3],
    /// Reference length in mean radii (paper: 15 or 30 r_mean).
    #[param(default = 15.0)]
    pub std_length: f64,
    /// Fail when a face or the volume saturates below its goal (false: warn and keep the saturated fill).
    #[param(default = true)]
    pub require_goals: bool,
    /// A phase is saturated after this many rejected radius draws in a row.
    #[param(default = 100)]
    pub max_consecutive_rejections: u64,
    /// A phase is saturated once this fraction of its draws (after 100) was rejected; bounds the radius-law distortion (KS <= q/(1-q)). 1 = off.
    #[param(default = 1.0, ty = "number in (0, 1]")]
    pub max_rejected_fraction: f64,
}

impl BrickParams {
    /// Defaults of `bricks.method1`: the paper's Example 1A (the group's own defaults).
    pub fn method1_defaults() -> Self {
        Self::default()
    }

    /// Defaults of `bricks.method2`: the paper's Example 2 goals with the Weibull law of
    /// eq. (2.4), Table 3.
    pub fn method2_defaults() -> Self {
        BrickParams {
            face_goal: 1.0,
            body_goal: 0.9,
            contact_parameter: 0.1,
            std_length: 30.0,
            require_goals: false,
            max_consecutive_rejections: 30,
            max_rejected_fraction: 0.25,
            ..Self::default()
        }
    }

    /// Defaults of `bricks.curved`: the paper's Example 3A.
    pub fn curved_defaults() -> Self {
        BrickParams {
            face_goal: 0.4,
            body_goal: 0.4,
            contact_parameter: 0.1,
            std_length: 30.0,
            ..Self::default()
        }
    }
}

/// Parameters of `bricks.method1`: a box-shaped unit brick, tiled by reflection (defaults:
/// the paper's Example 1A).
#[params]
pub struct Method1Params {
    #[param(flatten, default = BrickParams::method1_defaults())]
    pub common: BrickParams,
    /// BrickNumbers: unit bricks along x, y, z in the total domain.
    #[param(default = [2, 2, 1])]
    pub brick_numbers: [usize; 3],
}

/// Parameters of `bricks.method2`: a box-shaped unit brick, tiled by translation (defaults:
/// the paper's Example 2 goals with the Weibull law of eq. (2.4), Table 3).
#[params]
pub struct Method2Params {
    #[param(flatten, default = BrickParams::method2_defaults())]
    pub common: BrickParams,
    /// BrickNumbers: unit bricks along x, y, z in the total domain.
    #[param(default = [2, 2, 1])]
    pub brick_numbers: [usize; 3],
}

/// A sphere cut out of the `bricks.curved` domain, in absolute coordinates (brick corner at 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExcludedSphere {
    pub center: [Q<Length>; 3],
    pub radius: Q<Length>,
}

impl ParamType for ExcludedSphere {
    fn type_name() -> String {
        "{center: [x, y, z], radius}".to_string()
    }
    fn unit() -> &'static str {
        "m"
    }
    fn schema() -> serde_json::Value {
        serde_json::json!({
            "type": "object",
            "required": ["center", "radius"],
            "additionalProperties": false,
            "properties": {
                "center": <[Q<Length>; 3]>::schema(),
                "radius": Q::<Length>::schema(),
            }
        })
    }
}

/// Parameters of `bricks.curved` (defaults: the paper's Example 3A).
#[params]
pub struct CurvedParams {
    #[param(flatten, default = BrickParams::curved_defaults())]
    pub common: BrickParams,
    /// HemisphereRadii as multiples of std_length: balls centred on the x faces, cut from the brick (0 = none; at most half the smallest side).
    #[param(default = [0.5, 0.5])]
    pub hemisphere_radii: [f64; 2],
    /// Further balls cut from the domain (brick corner at the origin).
    pub excluded_spheres: Vec<ExcludedSphere>,
    /// Planar faces covered before the volume (paper Example 3: the y and z faces).
    #[param(
        default = ["ymin", "ymax", "zmin", "zmax"].map(String::from).to_vec(),
        ty = "list of: xmin, xmax, ymin, ymax, zmin, zmax"
    )]
    pub filled_faces: Vec<String>,
}

/// What preflight works out and run fills: the unit brick and its domain.
#[derive(Clone, Debug)]
pub struct UnitBrick {
    /// Side lengths [m].
    pub sides: [f64; 3],
    /// The domain as a signed distance (a box, or a box minus balls).
    pub sdf: Sdf,
    /// Planar faces filled before the volume, in `FACE_NAMES` order.
    pub faces: [bool; 6],
    /// Solids cut out of the domain, recorded in the packing.
    pub excluded: Vec<ExcludedSolid>,
}

impl UnitBrick {
    /// A plain box of the given sides, every face filled.
    fn plain(sides: [f64; 3]) -> Self {
        UnitBrick {
            sides,
            sdf: Sdf::Box {
                min: [0.0; 3],
                max: sides,
            },
            faces: [true; 6],
            excluded: Vec::new(),
        }
    }
}

fn unit_interval(key: &str, v: f64, open_zero: bool) -> Result<(), StageError> {
    let ok = v.is_finite() && v <= 1.0 && if open_zero { v > 0.0 } else { v >= 0.0 };
    if ok {
        Ok(())
    } else {
        Err(StageError::param(
            key,
            format!(
                "must lie in {}0, 1], got {v}",
                if open_zero { "(" } else { "[" }
            ),
        ))
    }
}

impl BrickParams {
    /// Validates; returns (mean radius, unit brick side lengths). `numbers` are the unit
    /// bricks per axis, for the size limit reported on `count_key`.
    fn check(
        &self,
        min_sides_in_radii: f64,
        numbers: [usize; 3],
        count_key: &str,
    ) -> Result<(f64, [f64; 3]), StageError> {
        self.radius
            .validate()
            .map_err(|(k, m)| StageError::param(&format!("radius.{k}"), m))?;
        unit_interval("face_goal", self.face_goal, true)?;
        unit_interval("body_goal", self.body_goal, true)?;
        unit_interval("contact_parameter", self.contact_parameter, false)?;
        unit_interval("parent_parameter", self.parent_parameter, true)?;
        if !(self.std_length.is_finite() && self.std_length > 0.0) {
            return Err(StageError::param(
                "std_length",
                format!(
                    "must be a positive number of mean radii, got {}",
                    self.std_length
                ),
            ));
        }
        for (a, s) in self.brick_sides.iter().enumerate() {
            if !(s.is_finite() && *s > 0.0) {
                return Err(StageError::param(
                    "brick_sides",
                    format!("side {a} must be positive, got {s}"),
                ));
            }
            if s * self.std_length < min_sides_in_radii {
                return Err(StageError::param(
                    "brick_sides",
                    format!(
                        "side {a} is {} mean radii; at least {min_sides_in_radii} are needed \
                         for the corner spheres",
                        s * self.std_length
                    ),
                ));
            }
        }
        unit_interval("max_rejected_fraction", self.max_rejected_fraction, true)?;
        if self.max_consecutive_rejections == 0 {
            return Err(StageError::param(
                "max_consecutive_rejections",
                "must be >= 1 (30 to 100 are good values)",
            ));
        }
        let rmean = self.radius.mean();
        let sides = self.brick_sides.map(|s| s * self.std_length * rmean);
        let est = self.estimate_spheres(rmean, sides, numbers);
        if est > MAX_SPHERES {
            return Err(StageError::param(
                count_key,
                format!(
                    "about {est:.3e} spheres would be made (limit {MAX_SPHERES:e}); use fewer \
                     or smaller bricks"
                ),
            ));
        }
        let r_tail = self.tail_radius();
        let upper = self.estimate_spheres(r_tail, sides, numbers);
        if upper.is_nan() || upper > MAX_SPHERES {
            return Err(StageError::param(
                "radius",
                format!(
                    "the law's small radii would fill the brick: a saturated fill keeps placing \
                     spheres as long as about 1 draw in {} fits, i.e. down to r = {r_tail:.3e} m \
                     (its {:.1} % quantile), which in bricks of {:.3e} x {:.3e} x {:.3e} m \
                     (std_length x the mean radius {rmean:.3e} m) could make up to {upper:.3e} \
                     spheres (limit {MAX_SPHERES:e}); narrow the law or truncate it with \
                     `min:` (a minimum radius), or lower std_length or brick_numbers",
                    self.max_consecutive_rejections,
                    100.0 * self.tail_fraction(),
                    sides[0],
                    sides[1],
                    sides[2]
                ),
            ));
        }
        Ok((rmean, sides))
    }

    /// The fraction of the radius law below which draws stop mattering: a phase ends after
    /// `max_consecutive_rejections` rejections in a row, so it keeps going while about one
    /// draw in that many fits, and the gaps are filled down to this quantile of the law.
    fn tail_fraction(&self) -> f64 {
        (1.0 / self.max_consecutive_rejections as f64).clamp(1e-3, 0.5)
    }

    /// The radius at [`Self::tail_fraction`]: the smallest spheres a saturated fill makes in
    /// bulk. Work and memory are estimated from it, not from the mean radius: with a broad
    /// law (a lognormal of sigma 2.5) the mean is far above the radii that do the filling.
    fn tail_radius(&self) -> f64 {
        self.radius.quantile(self.tail_fraction())
    }

    fn estimate_spheres(&self, rmean: f64, sides: [f64; 3], numbers: [usize; 3]) -> f64 {
        let v: f64 = sides.iter().product();
        // Packing fractions above ~0.7 are not reached; the face copies add at most ~30 %.
        let per_brick = 1.3 * v * self.body_goal.min(0.7) / (4.0 / 3.0 * PI * rmean.powi(3));
        per_brick * numbers.iter().product::<usize>() as f64
    }

    fn settings(&self, stage: &'static str, faces: [bool; 6]) -> FillSettings {
        FillSettings {
            face_goal: self.face_goal,
            body_goal: self.body_goal,
            parent_parameter: self.parent_parameter,
            max_consecutive_rejections: self.max_consecutive_rejections,
            max_rejected_fraction: self.max_rejected_fraction,
            require_goals: self.require_goals,
            faces,
            stage,
        }
    }

    /// The announcement of every brick stage: the box `[0, sides x numbers]` (not periodic,
    /// also for Method 2, whose tiled bed closes its own faces), the estimated sphere count and
    /// mean diameter, and a one-row report. The unit brick goes to `run` as the plan.
    fn preflight(
        &self,
        info: &StageInfo,
        rmean: f64,
        numbers: [usize; 3],
        brick: UnitBrick,
    ) -> Preflight<UnitBrick> {
        let n = self.estimate_spheres(rmean, brick.sides, numbers);
        // Memory per sphere (~400 B): the filler's position, radius and flags and its cell
        // list entry (~40 B), the assembled copy with its brick index (40 B), ~3.5 contacts
        // of the contact search and of the output graph (2 x ~3.5 x 24 B), and the output
        // body (~90 B). The count is the announced one, or the one of the law's median radius
        // where that is larger (a broad law whose mean sits far above the radii that fill).
        // Not the lower tail: a saturated fill is made by the bulk of the law, and the tail
        // count overstated the memory 30 to 70 times.
        let typical = self
            .estimate_spheres(self.radius.quantile(0.5), brick.sides, numbers)
            .max(n);
        // The same product as `assemble`, so the announced box is the produced one exactly.
        let size = [0, 1, 2].map(|a| brick.sides[a] * numbers[a] as f64);
        Preflight::from_info(info, (typical * 400.0) as u64 + (64 << 10))
            .announce(
                "packing",
                ArtifactMeta::packing([0.0; 3], size, [false; 3])
                    .with_count(n as u64, None)
                    .with_length_scale(2.0 * rmean),
            )
            .announce(
                "contacts",
                ArtifactMeta::of(ArtifactKind::ContactGraph).with_count(n as u64, None),
            )
            .announce(
                "report",
                ArtifactMeta::of(ArtifactKind::Table).with_count(1, Some([1, 1])),
            )
            .with_plan(brick)
    }

    /// The preflight of the box stages (`bricks.method1`, `bricks.method2`): validates the
    /// brick `numbers`; plans the plain unit brick with the announcement.
    fn preflight_box(
        &self,
        info: &StageInfo,
        min_sides_in_radii: f64,
        numbers: [usize; 3],
    ) -> Result<Preflight<UnitBrick>, StageError> {
        if numbers.contains(&0) {
            return Err(StageError::param(
                "brick_numbers",
                "every count must be >= 1",
            ));
        }
        let (rmean, sides) = self.check(min_sides_in_radii, numbers, "brick_numbers")?;
        Ok(self.preflight(info, rmean, numbers, UnitBrick::plain(sides)))
    }

    /// The run of every brick stage: fill the unit brick, tile it, find contacts and faces.
    fn run(
        &self,
        stage: &'static str,
        brick: &UnitBrick,
        mode: Mode,
        numbers: [usize; 3],
        tile: fn(&Filler, [usize; 3]) -> Assembly,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let mut f = Filler::new(
            mode,
            brick.sides,
            &brick.sdf,
            &self.radius,
            self.settings(stage, brick.faces),
            ctx.rng(),
        );
        f.fill(ctx)?;
        // Rejected draws bias the radii (the 1A brick rejects large spheres that do not fit):
        // say so when the sample fails its own KS test, with how far the mean moved.
        let check = SampleCheck::new(
            &drawn_radii(&f),
            &self.radius,
            f.stats.rejected,
            f.stats.draws,
        );
        if let Some(w) = check.warning("the radii of the unit brick") {
            ctx.warn(&w);
        }
        let asm = tile(&f, numbers);
        Ok(finish(&f, asm, mode, self, brick.excluded.clone()))
    }
}

fn outputs() -> Vec<PortSpec> {
    vec![
        PortSpec::new("packing", ArtifactKind::Packing, "Spheres of the total domain (attribute `brick`: unit-brick copy index)."),
        PortSpec::new("contacts", ArtifactKind::ContactGraph, "Touching pairs (gap <= contact_parameter * mean radius), spheres per face (ListXmin..ListZmax), positions."),
        PortSpec::new("report", ArtifactKind::Table, "Achieved face and body fractions, sphere counts, draws, rejected draws, KS distance."),
    ]
}

/// The radii drawn from the size law (not those placed by other rules).
fn drawn_radii(f: &Filler) -> Vec<f64> {
    f.rad
        .iter()
        .zip(&f.drawn)
        .filter(|(_, d)| **d)
        .map(|(r, _)| *r)
        .collect()
}

/// Everything computed after the unit brick is filled.
fn finish(
    f: &Filler,
    asm: Assembly,
    mode: Mode,
    c: &BrickParams,
    excluded: Vec<ExcludedSolid>,
) -> Outputs {
    let max_gap = c.contact_parameter * f.rmean;
    let contacts = assemble::contacts(&asm.pos, &asm.rad, asm.size, max_gap);
    let faces = assemble::face_lists(&asm, mode, max_gap);
    let drawn = drawn_radii(f);
    let ks = ks_distance(&drawn, &c.radius);
    let mean_drawn = drawn.iter().sum::<f64>() / drawn.len().max(1) as f64;
    let st: &FillStats = &f.stats;

    let mut domain = Domain::boxed([0.0; 3], asm.size, [false; 3]);
    domain.excluded = excluded;
    let mut packing = Packing::new(domain);
    packing.bodies = asm
        .pos
        .iter()
        .zip(&asm.rad)
        .map(|(p, r)| Body::sphere(*p, *r))
        .collect();
    packing.attributes.insert(
        "brick".into(),
        BodyAttribute {
            unit: String::new(),
            values: asm.brick.iter().map(|&b| b as f64).collect(),
        },
    );
    let graph = ContactGraph {
        contacts,
        faces,
        bonds: Vec::new(),
        bond_attributes: Default::default(),
        positions: asm.pos.clone(),
        radii: asm.rad.clone(),
    };
    let face_min = (0..6)
        .filter(|&k| st.filled[k])
        .map(|k| st.face_fraction[k])
        .fold(f64::INFINITY, f64::min);
    let mut t = Table::new("bricks report")
        .with_i64("spheres_unit_brick", "", vec![asm.unit_count as i64])
        .with_i64("spheres_total", "", vec![asm.pos.len() as i64])
        .with_i64("contacts", "", vec![graph.contacts.len() as i64])
        .with_i64("draws", "", vec![st.draws as i64])
        .with_i64("rejected_draws", "", vec![st.rejected as i64])
        .with_f64("body_fraction", "", vec![st.body_fraction])
        .with_f64("body_goal", "", vec![c.body_goal])
        .with_f64("face_fraction_min", "", vec![face_min])
        .with_f64("face_goal", "", vec![c.face_goal]);
    for (k, name) in FACE_NAMES.iter().enumerate() {
        t = t.with_f64(
            &format!("face_fraction_{name}"),
            "",
            vec![st.face_fraction[k]],
        );
    }
    t = t
        .with_i64("goals_reached", "", vec![i64::from(st.goals_reached)])
        .with_i64("ks_samples", "", vec![drawn.len() as i64])
        .with_f64("ks_distance", "", vec![ks])
        .with_f64(
            "ks_critical_0_05",
            "",
            vec![ks_critical_value(drawn.len(), 0.05)],
        )
        .with_f64("mean_radius_target", "m", vec![f.rmean])
        .with_f64("mean_radius_drawn", "m", vec![mean_drawn])
        .with_f64("domain_volume_unit", "m^3", vec![st.domain_volume])
        .with_f64("size_x", "m", vec![asm.size[0]])
        .with_f64("size_y", "m", vec![asm.size[1]])
        .with_f64("size_z", "m", vec![asm.size[2]]);
    let mut out = Outputs::new();
    out.insert("packing".into(), Artifact::Packing(packing));
    out.insert("contacts".into(), Artifact::ContactGraph(graph));
    out.insert("report".into(), Artifact::Table(t));
    out
}

/// `bricks.method1`: the paper's Method 1.
pub struct Method1;

impl TypedStage for Method1 {
    type Params = Method1Params;
    type Plan = UnitBrick;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "bricks.method1",
            "1.0.0",
            "Sphere filling Method 1 (sphere-filling paper, section 2): mean-radius spheres in the \
             8 corners of a unit brick, random-radius chains along the 12 edges, then the 6 \
             faces and the volume, every sphere touching 2 (face) or 3 (volume) parents and \
             lying inside the brick; faces and volume stop at FaceGoal / BodyGoal. The total \
             domain is built by reflecting the unit brick about its faces.",
        )
        .outputs(outputs())
    }
    fn preflight(
        &self,
        p: &Method1Params,
        _: &InputMetas,
    ) -> Result<Preflight<UnitBrick>, StageError> {
        p.common.preflight_box(&self.info(), 4.0, p.brick_numbers)
    }
    fn run(
        &self,
        p: &Method1Params,
        brick: &UnitBrick,
        _: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        p.common.run(
            "bricks.method1",
            brick,
            Mode::Closed,
            p.brick_numbers,
            assemble::reflect,
            ctx,
        )
    }
}

/// `bricks.method2`: the paper's Method 2.
pub struct Method2;

impl TypedStage for Method2 {
    type Params = Method2Params;
    type Plan = UnitBrick;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "bricks.method2",
            "1.0.0",
            "Sphere filling Method 2 (sphere-filling paper, section 3): boundary spheres are \
             centred on the brick faces; one corner, one edge per axis and three faces are \
             filled and repeated on their opposites (the brick is periodic), then the volume. \
             Bricks are tiled by translation with a seamless fit. Fractions are those of the \
             tiled bed (each sphere counted once per period); the paper's goals 1.0 / 0.9 \
             exceed what non-overlapping spheres reach, so by default the fill stops when \
             saturated (require_goals: false).",
        )
        .outputs(outputs())
    }
    fn preflight(
        &self,
        p: &Method2Params,
        _: &InputMetas,
    ) -> Result<Preflight<UnitBrick>, StageError> {
        p.common.preflight_box(&self.info(), 2.0, p.brick_numbers)
    }
    fn run(
        &self,
        p: &Method2Params,
        brick: &UnitBrick,
        _: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        p.common.run(
            "bricks.method2",
            brick,
            Mode::Centered,
            p.brick_numbers,
            assemble::translate,
            ctx,
        )
    }
}

/// `bricks.curved`: a brick minus balls (the paper's Example 3), filled through its signed
/// distance function.
pub struct Curved;

impl CurvedParams {
    /// Validates the cut-outs and faces of the brick of `sides` [m]; builds its domain.
    fn build(&self, sides: [f64; 3]) -> Result<UnitBrick, StageError> {
        let std = sides[0] / self.common.brick_sides[0];
        let smallest = sides.iter().cloned().fold(f64::INFINITY, f64::min);
        let mut balls = Vec::new();
        for (k, h) in self.hemisphere_radii.iter().enumerate() {
            let r = h * std;
            if !(r.is_finite() && r >= 0.0 && r <= 0.5 * smallest * (1.0 + 1e-12)) {
                return Err(StageError::param(
                    "hemisphere_radii",
                    format!(
                        "radius {k} is {h} std_length; it must lie in [0, {}] (half the smallest \
                         brick side, as in the paper)",
                        0.5 * smallest / std
                    ),
                ));
            }
            if r > 0.0 {
                let x = if k == 0 { 0.0 } else { sides[0] };
                balls.push(([x, 0.5 * sides[1], 0.5 * sides[2]], r));
            }
        }
        for e in &self.excluded_spheres {
            let r = e.radius.si();
            let c = e.center.map(|q| q.si());
            if !(r.is_finite() && r > 0.0 && c.iter().all(|x| x.is_finite())) {
                return Err(StageError::param(
                    "excluded_spheres",
                    "every sphere needs a finite center and a positive radius",
                ));
            }
            balls.push((c, r));
        }
        let mut faces = [false; 6];
        for name in &self.filled_faces {
            let k = FACE_NAMES.iter().position(|n| n == name).ok_or_else(|| {
                StageError::param(
                    "filled_faces",
                    format!("unknown face `{name}`; use {}", FACE_NAMES.join(", ")),
                )
            })?;
            faces[k] = true;
        }
        let sdf = Sdf::Subtract {
            base: Box::new(Sdf::Box {
                min: [0.0; 3],
                max: sides,
            }),
            cut: balls
                .iter()
                .map(|&(center, radius)| Sdf::Ball { center, radius })
                .collect(),
        };
        // The domain must keep some volume.
        let v = sdf.volume([0.0; 3], sides, 40);
        if v <= 0.0 {
            return Err(StageError::param(
                "excluded_spheres",
                "the cut-outs remove the whole brick",
            ));
        }
        let excluded = balls
            .into_iter()
            .map(|(center, radius)| ExcludedSolid::Sphere { center, radius })
            .collect();
        Ok(UnitBrick {
            sides,
            sdf,
            faces,
            excluded,
        })
    }
}

impl TypedStage for Curved {
    type Params = CurvedParams;
    type Plan = UnitBrick;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "bricks.curved",
            "1.0.0",
            "Sphere filling of a domain given by a signed distance function (sphere-filling \
             paper, section 4, Example 3): a brick minus two balls centred on the x faces \
             (hemispherical cavities) and any further balls. Corner spheres and edge chains \
             where the domain allows, then the chosen planar faces, then the volume, with the \
             Method 1 rules (spheres inside, parents touched).",
        )
        .outputs(outputs())
    }
    fn preflight(
        &self,
        p: &CurvedParams,
        _: &InputMetas,
    ) -> Result<Preflight<UnitBrick>, StageError> {
        let (rmean, sides) = p.common.check(4.0, [1; 3], "brick_sides")?;
        let brick = p.build(sides)?;
        Ok(p.common.preflight(&self.info(), rmean, [1; 3], brick))
    }
    fn run(
        &self,
        p: &CurvedParams,
        brick: &UnitBrick,
        _: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        p.common.run(
            "bricks.curved",
            brick,
            Mode::Closed,
            [1; 3],
            assemble::reflect,
            ctx,
        )
    }
}
