//! The stages `bricks.method1`, `bricks.method2` and `bricks.curved`.

use crate::assemble::{self, Assembly};
use crate::fill::{FillSettings, FillStats, Filler, Mode};
use crate::sdf::Sdf;
use grainpipe_core::distributions::{ks_critical_value, ks_distance, SizeDistribution};
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    Artifact, ArtifactKind, Body, BodyAttribute, ContactGraph, Domain, ExcludedSolid, InputMetas,
    Inputs, Outputs, Packing, ParamSpec, PortSpec, Preflight, RunContext, StageError, StageInfo,
    Table, TypedStage, FACE_NAMES,
};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Spheres above which preflight refuses a run (about 4 GB of output at ~400 B per sphere).
const MAX_SPHERES: f64 = 1e7;

macro_rules! brick_params {
    ($name:ident, $doc:literal, face $fg:expr, body $bg:expr, contact $cp:expr, std $sl:expr,
     require $rq:expr, rejections $mr:expr, fraction $mf:expr) => {
        #[doc = $doc]
        #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
        #[serde(deny_unknown_fields, default)]
        pub struct $name {
            pub radius: SizeDistribution,
            pub face_goal: f64,
            pub body_goal: f64,
            pub contact_parameter: f64,
            pub parent_parameter: f64,
            pub brick_sides: [f64; 3],
            pub std_length: f64,
            pub brick_numbers: [usize; 3],
            pub require_goals: bool,
            pub max_consecutive_rejections: u64,
            pub max_rejected_fraction: f64,
        }

        impl Default for $name {
            fn default() -> Self {
                $name {
                    radius: SizeDistribution::default(),
                    face_goal: $fg,
                    body_goal: $bg,
                    contact_parameter: $cp,
                    parent_parameter: 0.5,
                    brick_sides: [1.0, 1.0, 1.0],
                    std_length: $sl,
                    brick_numbers: [2, 2, 1],
                    require_goals: $rq,
                    max_consecutive_rejections: $mr,
                    max_rejected_fraction: $mf,
                }
            }
        }

        impl $name {
            fn common(&self) -> Common<'_> {
                Common {
                    radius: &self.radius,
                    face_goal: self.face_goal,
                    body_goal: self.body_goal,
                    contact_parameter: self.contact_parameter,
                    parent_parameter: self.parent_parameter,
                    brick_sides: self.brick_sides,
                    std_length: self.std_length,
                    brick_numbers: self.brick_numbers,
                    require_goals: self.require_goals,
                    max_consecutive_rejections: self.max_consecutive_rejections,
                    max_rejected_fraction: self.max_rejected_fraction,
                }
            }
        }
    };
}

brick_params!(Method1Params, "Parameters of `bricks.method1` (defaults: the paper's Example 1A).",
    face 0.8, body 0.55, contact 0.2, std 15.0, require true, rejections 100, fraction 1.0);
brick_params!(Method2Params, "Parameters of `bricks.method2` (defaults: the paper's Example 2 \
    goals with the Weibull law of eq. (2.4), Table 3).",
    face 1.0, body 0.9, contact 0.1, std 30.0, require false, rejections 30, fraction 0.25);

/// A sphere cut out of the `bricks.curved` domain, in absolute coordinates (brick corner at 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExcludedSphere {
    pub center: [Q<Length>; 3],
    pub radius: Q<Length>,
}

/// Parameters of `bricks.curved` (defaults: the paper's Example 3A).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CurvedParams {
    pub radius: SizeDistribution,
    pub face_goal: f64,
    pub body_goal: f64,
    pub contact_parameter: f64,
    pub parent_parameter: f64,
    pub brick_sides: [f64; 3],
    pub std_length: f64,
    pub hemisphere_radii: [f64; 2],
    pub excluded_spheres: Vec<ExcludedSphere>,
    pub filled_faces: Vec<String>,
    pub require_goals: bool,
    pub max_consecutive_rejections: u64,
    pub max_rejected_fraction: f64,
}

impl Default for CurvedParams {
    fn default() -> Self {
        CurvedParams {
            radius: SizeDistribution::default(),
            face_goal: 0.4,
            body_goal: 0.4,
            contact_parameter: 0.1,
            parent_parameter: 0.5,
            brick_sides: [1.0, 1.0, 1.0],
            std_length: 30.0,
            hemisphere_radii: [0.5, 0.5],
            excluded_spheres: Vec::new(),
            filled_faces: ["ymin", "ymax", "zmin", "zmax"].map(String::from).to_vec(),
            require_goals: true,
            max_consecutive_rejections: 100,
            max_rejected_fraction: 1.0,
        }
    }
}

/// The parameters every brick stage shares, borrowed.
struct Common<'a> {
    radius: &'a SizeDistribution,
    face_goal: f64,
    body_goal: f64,
    contact_parameter: f64,
    parent_parameter: f64,
    brick_sides: [f64; 3],
    std_length: f64,
    brick_numbers: [usize; 3],
    require_goals: bool,
    max_consecutive_rejections: u64,
    max_rejected_fraction: f64,
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

impl Common<'_> {
    /// Validates and returns (mean radius, unit brick side lengths).
    fn check(&self, min_sides_in_radii: f64) -> Result<(f64, [f64; 3]), StageError> {
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
        if self.brick_numbers.contains(&0) {
            return Err(StageError::param(
                "brick_numbers",
                "every count must be >= 1",
            ));
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
        let est = self.estimate_spheres(rmean, sides);
        if est > MAX_SPHERES {
            return Err(StageError::param(
                "brick_numbers",
                format!(
                    "about {est:.3e} spheres would be made (limit {MAX_SPHERES:e}); use fewer \
                     or smaller bricks"
                ),
            ));
        }
        Ok((rmean, sides))
    }

    fn estimate_spheres(&self, rmean: f64, sides: [f64; 3]) -> f64 {
        let v: f64 = sides.iter().product();
        // Packing fractions above ~0.7 are not reached; the face copies add at most ~30 %.
        let per_brick = 1.3 * v * self.body_goal.min(0.7) / (4.0 / 3.0 * PI * rmean.powi(3));
        per_brick * self.brick_numbers.iter().product::<usize>() as f64
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
}

fn common_params(curved: bool) -> Vec<ParamSpec> {
    let mut v = vec![
        ParamSpec {
            name: "radius",
            ty: "size distribution {kind: weibull|gamma|normal|lognormal|exponential|uniform|beta|triangular|tabulated|fixed, ...}",
            unit: "m",
            doc: "Sphere radius law (Matlab makedist equivalent); default Weibull scale 15.7 um, shape 3.55 (eq. 2.4).",
        },
        ParamSpec {
            name: "face_goal",
            ty: "number in (0, 1]",
            unit: "",
            doc: "FaceGoal: fraction of each filled face covered by the projections of the spheres on it.",
        },
        ParamSpec {
            name: "body_goal",
            ty: "number in (0, 1]",
            unit: "",
            doc: "BodyGoal: fraction of the unit-brick (domain) volume filled by spheres.",
        },
        ParamSpec {
            name: "contact_parameter",
            ty: "number in [0, 1]",
            unit: "",
            doc: "SphereContactParameter: spheres (and faces) with gaps up to this times the mean radius are in contact.",
        },
        ParamSpec {
            name: "parent_parameter",
            ty: "number in (0, 1]",
            unit: "",
            doc: "ParentParameter: spheres with gaps up to this times the mean radius are parents of new spheres.",
        },
        ParamSpec {
            name: "brick_sides",
            ty: "[x, y, z]",
            unit: "std_length",
            doc: "BrickSideLengths as multiples of std_length.",
        },
        ParamSpec {
            name: "std_length",
            ty: "number",
            unit: "mean radii",
            doc: "Reference length in mean radii (paper: 15 or 30 r_mean).",
        },
    ];
    if curved {
        v.push(ParamSpec {
            name: "hemisphere_radii",
            ty: "[r_xmin, r_xmax]",
            unit: "std_length",
            doc: "HemisphereRadii: balls centred on the x faces, cut from the brick (0 = none; at most half the smallest side).",
        });
        v.push(ParamSpec {
            name: "excluded_spheres",
            ty: "list of {center: [x, y, z], radius}",
            unit: "m",
            doc: "Further balls cut from the domain (brick corner at the origin).",
        });
        v.push(ParamSpec {
            name: "filled_faces",
            ty: "list of xmin|xmax|ymin|ymax|zmin|zmax",
            unit: "",
            doc: "Planar faces covered before the volume (paper Example 3: the y and z faces).",
        });
    } else {
        v.push(ParamSpec {
            name: "brick_numbers",
            ty: "[m, n, p]",
            unit: "",
            doc: "BrickNumbers: unit bricks along x, y, z in the total domain.",
        });
    }
    v.push(ParamSpec {
        name: "require_goals",
        ty: "bool",
        unit: "",
        doc: "Fail when a face or the volume saturates below its goal (false: warn and keep the saturated fill).",
    });
    v.push(ParamSpec {
        name: "max_consecutive_rejections",
        ty: "integer",
        unit: "",
        doc: "A phase is saturated after this many rejected radius draws in a row.",
    });
    v.push(ParamSpec {
        name: "max_rejected_fraction",
        ty: "number in (0, 1]",
        unit: "",
        doc: "A phase is saturated once this fraction of its draws (after 100) was rejected; bounds the radius-law distortion (KS <= q/(1-q)). 1 = off.",
    });
    v
}

fn outputs() -> Vec<PortSpec> {
    vec![
        PortSpec::new("packing", ArtifactKind::Packing, "Spheres of the total domain (attribute `brick`: unit-brick copy index)."),
        PortSpec::new("contacts", ArtifactKind::ContactGraph, "Touching pairs (gap <= contact_parameter * mean radius), spheres per face (ListXmin..ListZmax), positions."),
        PortSpec::new("report", ArtifactKind::Table, "Achieved face and body fractions, sphere counts, draws, rejected draws, KS distance."),
    ]
}

fn preflight_for(info: &StageInfo, c: &Common, min_side: f64) -> Result<Preflight, StageError> {
    let (rmean, sides) = c.check(min_side)?;
    let n = c.estimate_spheres(rmean, sides);
    let mut pf = Preflight::from_info(info, (n * 400.0) as u64);
    for m in pf.outputs.values_mut() {
        if m.kind != ArtifactKind::Table {
            m.count_estimate = n as u64;
        }
    }
    Ok(pf)
}

/// The domain `bricks.curved` fills: sides, filled faces, signed distance, cut-outs.
type CurvedDomain = ([f64; 3], [bool; 6], Sdf, Vec<ExcludedSolid>);

/// The run of Method 1 and Method 2: fill one box-shaped unit brick, then tile it.
fn run_box(
    id: &'static str,
    c: &Common,
    mode: Mode,
    factor: f64,
    tile: fn(&Filler, [usize; 3]) -> Assembly,
    ctx: &RunContext,
) -> Result<Outputs, StageError> {
    let (_, sides) = c.check(factor)?;
    let sdf = Sdf::Box {
        min: [0.0; 3],
        max: sides,
    };
    let mut f = Filler::new(
        mode,
        sides,
        sdf,
        c.radius,
        c.settings(id, [true; 6]),
        ctx.rng(),
    );
    f.fill(ctx)?;
    let asm = tile(&f, c.brick_numbers);
    Ok(finish(
        &f,
        asm,
        mode,
        c.contact_parameter,
        c.body_goal,
        c.face_goal,
        c.radius,
        Vec::new(),
    ))
}

/// Everything computed after the unit brick is filled.
#[allow(clippy::too_many_arguments)]
fn finish(
    f: &Filler,
    asm: Assembly,
    mode: Mode,
    contact_parameter: f64,
    body_goal: f64,
    face_goal: f64,
    dist: &SizeDistribution,
    excluded: Vec<ExcludedSolid>,
) -> Outputs {
    let max_gap = contact_parameter * f.rmean;
    let contacts = assemble::contacts(&asm.pos, &asm.rad, asm.size, max_gap);
    let faces = assemble::face_lists(&asm, mode, max_gap);
    let drawn: Vec<f64> = f
        .rad
        .iter()
        .zip(&f.drawn)
        .filter(|(_, d)| **d)
        .map(|(r, _)| *r)
        .collect();
    let ks = ks_distance(&drawn, dist);
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
        positions: asm.pos.clone(),
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
        .with_f64("body_goal", "", vec![body_goal])
        .with_f64("face_fraction_min", "", vec![face_min])
        .with_f64("face_goal", "", vec![face_goal]);
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
    fn info(&self) -> StageInfo {
        StageInfo {
            id: "bricks.method1",
            version: "1.0.0",
            doc: "Sphere filling Method 1 (sphere-filling paper, section 2): mean-radius spheres in the \
                  8 corners of a unit brick, random-radius chains along the 12 edges, then the 6 \
                  faces and the volume, every sphere touching 2 (face) or 3 (volume) parents and \
                  lying inside the brick; faces and volume stop at FaceGoal / BodyGoal. The total \
                  domain is built by reflecting the unit brick about its faces.",
            params: common_params(false),
            inputs: vec![],
            outputs: outputs(),
        }
    }
    fn preflight(&self, p: &Method1Params, _: &InputMetas) -> Result<Preflight, StageError> {
        preflight_for(&self.info(), &p.common(), 4.0)
    }
    fn run(&self, p: &Method1Params, _: &Inputs, ctx: &RunContext) -> Result<Outputs, StageError> {
        run_box(
            "bricks.method1",
            &p.common(),
            Mode::Closed,
            4.0,
            assemble::reflect,
            ctx,
        )
    }
}

/// `bricks.method2`: the paper's Method 2.
pub struct Method2;

impl TypedStage for Method2 {
    type Params = Method2Params;
    fn info(&self) -> StageInfo {
        StageInfo {
            id: "bricks.method2",
            version: "1.0.0",
            doc: "Sphere filling Method 2 (sphere-filling paper, section 3): boundary spheres are \
                  centred on the brick faces; one corner, one edge per axis and three faces are \
                  filled and repeated on their opposites (the brick is periodic), then the volume. \
                  Bricks are tiled by translation with a seamless fit. Fractions are those of the \
                  tiled bed (each sphere counted once per period); the paper's goals 1.0 / 0.9 \
                  exceed what non-overlapping spheres reach, so by default the fill stops when \
                  saturated (require_goals: false).",
            params: common_params(false),
            inputs: vec![],
            outputs: outputs(),
        }
    }
    fn preflight(&self, p: &Method2Params, _: &InputMetas) -> Result<Preflight, StageError> {
        preflight_for(&self.info(), &p.common(), 2.0)
    }
    fn run(&self, p: &Method2Params, _: &Inputs, ctx: &RunContext) -> Result<Outputs, StageError> {
        run_box(
            "bricks.method2",
            &p.common(),
            Mode::Centered,
            2.0,
            assemble::translate,
            ctx,
        )
    }
}

/// `bricks.curved`: a brick minus balls (the paper's Example 3), filled through its signed
/// distance function.
pub struct Curved;

impl CurvedParams {
    fn common(&self) -> Common<'_> {
        Common {
            radius: &self.radius,
            face_goal: self.face_goal,
            body_goal: self.body_goal,
            contact_parameter: self.contact_parameter,
            parent_parameter: self.parent_parameter,
            brick_sides: self.brick_sides,
            std_length: self.std_length,
            brick_numbers: [1, 1, 1],
            require_goals: self.require_goals,
            max_consecutive_rejections: self.max_consecutive_rejections,
            max_rejected_fraction: self.max_rejected_fraction,
        }
    }

    /// Validates; returns (sides, faces, domain sdf, excluded solids).
    fn build(&self) -> Result<CurvedDomain, StageError> {
        let (_, sides) = self.common().check(4.0)?;
        let std = sides[0] / self.brick_sides[0];
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
        Ok((sides, faces, sdf, excluded))
    }
}

impl TypedStage for Curved {
    type Params = CurvedParams;
    fn info(&self) -> StageInfo {
        StageInfo {
            id: "bricks.curved",
            version: "1.0.0",
            doc: "Sphere filling of a domain given by a signed distance function (sphere-filling \
                  paper, section 4, Example 3): a brick minus two balls centred on the x faces \
                  (hemispherical cavities) and any further balls. Corner spheres and edge chains \
                  where the domain allows, then the chosen planar faces, then the volume, with the \
                  Method 1 rules (spheres inside, parents touched).",
            params: common_params(true),
            inputs: vec![],
            outputs: outputs(),
        }
    }
    fn preflight(&self, p: &CurvedParams, _: &InputMetas) -> Result<Preflight, StageError> {
        p.build()?;
        preflight_for(&self.info(), &p.common(), 4.0)
    }
    fn run(&self, p: &CurvedParams, _: &Inputs, ctx: &RunContext) -> Result<Outputs, StageError> {
        let (sides, faces, sdf, excluded) = p.build()?;
        let c = p.common();
        let mut f = Filler::new(
            Mode::Closed,
            sides,
            sdf,
            &p.radius,
            c.settings("bricks.curved", faces),
            ctx.rng(),
        );
        f.fill(ctx)?;
        let asm = assemble::reflect(&f, [1, 1, 1]);
        Ok(finish(
            &f,
            asm,
            Mode::Closed,
            p.contact_parameter,
            p.body_goal,
            p.face_goal,
            &p.radius,
            excluded,
        ))
    }
}
