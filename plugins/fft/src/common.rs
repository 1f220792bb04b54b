//! Parameter types and helpers shared by `elasticity.fft` and `conductivity.fft`.

use grainpipe_core::boundary::{
    axis_list, mirror_image, mirror_subvoxel, Boundary, BoundaryParams, ResolvedBoundary,
};
use grainpipe_core::params::ParamType;
use grainpipe_core::subvoxel::Subvoxel;
use grainpipe_core::units::{Pressure, Q};
use grainpipe_core::{ParamChoice, Phase, PhaseImage, RunContext, StageError};
use indexmap::IndexMap;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::kernel::solver::{Method, SolveError};
use crate::kernel::Scheme;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Discretization {
    /// Staggered grid (Schneider, Ospald & Kabel 2016): stable on porous images, exact on
    /// laminates; the default.
    Staggered,
    /// Trilinear hexahedra with 2x2x2 Gauss points (FANS): stable, a little stiffer.
    Hex8,
    /// Hexahedra with one-point integration (Willot 2015's rotated scheme): hourglass modes.
    Rotated,
    /// Fourier-spectral Moulinec-Suquet discretization: ringing, stalls on pores.
    Spectral,
}

impl Discretization {
    pub fn scheme(self) -> Scheme {
        match self {
            Discretization::Staggered => Scheme::Staggered,
            Discretization::Hex8 => Scheme::Hex8,
            Discretization::Rotated => Scheme::Rotated,
            Discretization::Spectral => Scheme::Spectral,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Solver {
    /// Preconditioned conjugate gradients (Zeman et al. 2010; Brisard & Dormieux 2010).
    Cg,
    /// The basic fixed-point scheme (Moulinec & Suquet 1994), for comparison.
    FixedPoint,
}

impl Solver {
    pub fn method(self) -> Method {
        match self {
            Solver::Cg => Method::Cg,
            Solver::FixedPoint => Method::FixedPoint,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// Double precision fields (64-bit).
    #[serde(rename = "double")]
    F64,
    /// Single precision fields (32-bit; half the memory, reductions stay in double). Below
    /// a residual of about 1e-6 the one CG reports no longer tracks the true one.
    #[serde(rename = "single")]
    F32,
}

/// `{E, nu}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct YoungPoisson {
    #[serde(rename = "E")]
    pub e: Q<Pressure>,
    pub nu: f64,
}

/// `{K, G}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BulkShear {
    #[serde(rename = "K")]
    pub k: Q<Pressure>,
    #[serde(rename = "G")]
    pub g: Q<Pressure>,
}

/// An isotropic material given as `{E, nu}` or `{K, G}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged, try_from = "MaterialKeys")]
pub enum Material {
    YoungPoisson(YoungPoisson),
    BulkShear(BulkShear),
}

/// The keys a material may have, read first so that a wrong combination gets a message
/// naming the keys (an untagged enum only says that no variant matched).
#[derive(Deserialize)]
#[serde(
    deny_unknown_fields,
    expecting = "a map {E: pressure, nu: number} or {K: pressure, G: pressure}"
)]
struct MaterialKeys {
    #[serde(rename = "E")]
    e: Option<Q<Pressure>>,
    nu: Option<f64>,
    #[serde(rename = "K")]
    k: Option<Q<Pressure>>,
    #[serde(rename = "G")]
    g: Option<Q<Pressure>>,
}

impl TryFrom<MaterialKeys> for Material {
    type Error = String;
    fn try_from(m: MaterialKeys) -> Result<Self, String> {
        match m {
            MaterialKeys {
                e: Some(e),
                nu: Some(nu),
                k: None,
                g: None,
            } => Ok(Material::YoungPoisson(YoungPoisson { e, nu })),
            MaterialKeys {
                e: None,
                nu: None,
                k: Some(k),
                g: Some(g),
            } => Ok(Material::BulkShear(BulkShear { k, g })),
            m => {
                let given: Vec<&str> = [
                    ("E", m.e.is_some()),
                    ("nu", m.nu.is_some()),
                    ("K", m.k.is_some()),
                    ("G", m.g.is_some()),
                ]
                .iter()
                .filter(|(_, set)| *set)
                .map(|(key, _)| *key)
                .collect();
                Err(format!(
                    "give either {{E, nu}} or {{K, G}} (e.g. {{E: 66.9 GPa, nu: 0.25}}); got {}",
                    if given.is_empty() {
                        "no keys".to_string()
                    } else {
                        format!("{{{}}}", given.join(", "))
                    }
                ))
            }
        }
    }
}

impl Material {
    pub fn e_nu(e: f64, nu: f64) -> Material {
        Material::YoungPoisson(YoungPoisson { e: Q::new(e), nu })
    }
    /// Lame constants, or a message saying what is wrong.
    pub fn iso(&self) -> Result<crate::kernel::Iso, String> {
        match self {
            Material::YoungPoisson(m) => {
                let e = m.e.si();
                if !(e > 0.0 && e.is_finite()) {
                    return Err(format!("E must be positive, got {e} Pa"));
                }
                plausible_modulus("E", e)?;
                if !(m.nu > -1.0 && m.nu < 0.5) {
                    return Err(format!("nu must lie in (-1, 0.5), got {}", m.nu));
                }
                derived_moduli_plausible(crate::kernel::Iso::from_e_nu(e, m.nu), "E and nu")
            }
            Material::BulkShear(m) => {
                let (k, g) = (m.k.si(), m.g.si());
                if !(k > 0.0 && g > 0.0 && k.is_finite() && g.is_finite()) {
                    return Err(format!("K and G must be positive, got {k} Pa and {g} Pa"));
                }
                plausible_modulus("K", k)?;
                plausible_modulus("G", g)?;
                derived_moduli_plausible(crate::kernel::Iso::from_k_g(k, g), "K and G")
            }
        }
    }
}

pub use grainpipe_core::units::{MAX_MODULUS, MIN_MODULUS};

fn plausible_modulus(key: &str, v: f64) -> Result<(), String> {
    if v > MAX_MODULUS {
        return Err(format!(
            "{key} = {v:.3e} Pa is above {MAX_MODULUS:.0e} Pa (1000x diamond); check the unit \
             (66.9 GPa for quartz)"
        ));
    }
    if v < MIN_MODULUS {
        return Err(format!(
            "{key} = {v:.3e} Pa is below {MIN_MODULUS:.0e} Pa; check the unit (66.9 GPa for \
             quartz; a void is a phase left out of `materials`)"
        ));
    }
    Ok(())
}

/// The moduli the solver uses, derived from the two given: each within the plausible range
/// too. nu = -0.999999 with E = 66.9 GPa gives G = 3.3e16 Pa, nu -> 0.5 an unbounded K; both
/// passed the check on E and returned an indefinite, non-symmetric "stiffness".
fn derived_moduli_plausible(
    iso: crate::kernel::Iso,
    from: &str,
) -> Result<crate::kernel::Iso, String> {
    for (name, v) in [("bulk modulus K", iso.bulk()), ("shear modulus G", iso.mu)] {
        plausible_modulus(name, v).map_err(|m| format!("{m} (derived from {from})"))?;
    }
    Ok(iso)
}

impl ParamType for Material {
    fn type_name() -> String {
        "{E: pressure, nu: number} or {K: pressure, G: pressure}".into()
    }
    fn unit() -> &'static str {
        "Pa"
    }
    fn schema() -> Value {
        let q = <Q<Pressure> as ParamType>::schema();
        json!({"anyOf": [
            {"type": "object", "properties": {"E": q.clone(), "nu": {"type": "number"}},
             "required": ["E", "nu"], "additionalProperties": false},
            {"type": "object", "properties": {"K": q.clone(), "G": q},
             "required": ["K", "G"], "additionalProperties": false},
        ]})
    }
}

/// Finds the map key naming a phase: its name or its label.
fn key_for<'a, V>(map: &'a IndexMap<String, V>, phase: &Phase) -> Option<&'a V> {
    map.get(&phase.name)
        .or_else(|| map.get(&phase.id.to_string()))
}

/// The preflight check of `materials` / `conductivities` keys against the announced phase
/// table (did-you-mean, former default names): one place, shared with peridynamics.
pub use grainpipe_core::phases::check_keys;

/// Keys of a phase-property map that match no phase present in the image (worth a warning:
/// a misspelt phase name would otherwise go unnoticed).
pub fn unused_keys<V>(map: &IndexMap<String, V>, image: &PhaseImage) -> Vec<String> {
    let mut present = [false; 256];
    for &l in &image.labels {
        present[l as usize] = true;
    }
    map.keys()
        .filter(|k| {
            !image
                .phases
                .iter()
                .any(|p| present[p.id as usize] && &p.name == *k)
                && !k
                    .parse::<u8>()
                    .map(|l| present[l as usize])
                    .unwrap_or(false)
        })
        .cloned()
        .collect()
}

/// Resolves the per-label property from a map of phase name or label -> value: label 0
/// left out is a pore (`pore`), any other phase present in the image and left out is an
/// error naming it and the keys given.
pub fn resolve<V: Clone, P>(
    key: &str,
    map: &IndexMap<String, V>,
    image: &PhaseImage,
    pore: P,
    convert: impl Fn(&V) -> Result<P, String>,
) -> Result<Vec<P>, StageError>
where
    P: Clone,
{
    let mut present = [false; 256];
    for &l in &image.labels {
        present[l as usize] = true;
    }
    let mut out = vec![pore.clone(); 256];
    for l in 0..256usize {
        if !present[l] {
            continue;
        }
        let phase = image
            .phases
            .iter()
            .find(|p| p.id as usize == l)
            .cloned()
            .unwrap_or(Phase {
                id: l as u8,
                name: l.to_string(),
            });
        match key_for(map, &phase) {
            Some(v) => {
                out[l] = convert(v).map_err(|m| {
                    StageError::param(key, format!("phase `{}` (label {l}): {m}", phase.name))
                })?
            }
            None if l == 0 => {}
            None => {
                return Err(StageError::param(
                    key,
                    format!(
                        "phase `{}` (label {l}) of the image has no entry; give one under its \
                         name or label (keys given: {:?}); only label 0 defaults to pore",
                        phase.name,
                        map.keys().collect::<Vec<_>>()
                    ),
                ))
            }
        }
    }
    Ok(out)
}

/// The stage error for a solver failure of one load case.
pub fn solve_failure(case: &str, scheme: &str, e: &SolveError) -> StageError {
    match e {
        SolveError::Cancelled => StageError::Cancelled,
        e => StageError::failed(format!("load case {case} ({scheme}): {e}")),
    }
}

pub fn validate_solver(
    tolerance: f64,
    max_iterations: usize,
    stagnation_window: usize,
) -> Result<(), StageError> {
    if !(tolerance > 0.0 && tolerance < 1.0) {
        return Err(StageError::param("tolerance", "must lie in (0, 1)"));
    }
    if max_iterations == 0 {
        return Err(StageError::param("max_iterations", "must be at least 1"));
    }
    if stagnation_window < 10 {
        return Err(StageError::param(
            "stagnation_window",
            "must be at least 10",
        ));
    }
    Ok(())
}

/// What building the composite voxels found, for the stage's log.
pub struct CompositeSummary {
    /// Voxels holding more than one phase.
    pub mixed: usize,
    /// Mixed voxels without an interface normal (they keep their label's material).
    pub without_normal: usize,
}

impl CompositeSummary {
    /// One line for the log, and a warning when mixed voxels had no normal.
    pub fn report(&self, ctx: &grainpipe_core::RunContext, voxels: usize) {
        ctx.info(&format!(
            "composite voxels: {} of {voxels} voxels ({:.1} %) are mixed",
            self.mixed,
            100.0 * self.mixed as f64 / voxels.max(1) as f64
        ));
        if self.without_normal > 0 {
            ctx.warn(&format!(
                "{} mixed voxels have no interface normal (a lamina thinner than the \
                 sampling, or a symmetric arrangement) and keep the material of their label",
                self.without_normal
            ));
        }
    }
}

/// The composite-voxel table of a solve: every mixed voxel of `sv` gets
/// `law(phases, normal)` with `phases` its `(fraction, property)` pairs, `props[label]`
/// the property of each phase.
pub fn composite_table<P: Copy + Sync, M: Send>(
    image: &PhaseImage,
    sv: &grainpipe_core::subvoxel::Subvoxel,
    props: &[P],
    law: impl Fn(&[(f64, P)], [f64; 3]) -> M + Sync,
) -> (crate::kernel::composite::Composite<M>, CompositeSummary) {
    use rayon::prelude::*;
    let n = image.labels.len();
    let ids: Vec<usize> = image.phases.iter().map(|p| p.id as usize).collect();
    let mixed: Vec<(usize, Option<M>)> = (0..n)
        .into_par_iter()
        .filter(|&v| sv.is_mixed(v))
        .map(|v| {
            let nrm = sv.normals[v].map(f64::from);
            if nrm == [0.0; 3] {
                return (v, None);
            }
            let phases: Vec<(f64, P)> = sv
                .of(v)
                .iter()
                .zip(&ids)
                .filter(|(f, _)| **f > 0.0)
                .map(|(&f, &id)| (f as f64, props[id]))
                .collect();
            (v, Some(law(&phases, nrm)))
        })
        .collect();
    let mut table = crate::kernel::composite::Composite::new(n);
    let mut summary = CompositeSummary {
        mixed: mixed.len(),
        without_normal: 0,
    };
    for (v, m) in mixed {
        match m {
            Some(m) => table.push(v, m),
            None => summary.without_normal += 1,
        }
    }
    (table, summary)
}

/// An image with one voxel of every phase that holds volume somewhere (by label or by
/// sub-voxel fraction), so that [`resolve`] asks for a property of each.
pub fn phases_present(
    image: &PhaseImage,
    sv: Option<&grainpipe_core::subvoxel::Subvoxel>,
) -> PhaseImage {
    let mut present = [false; 256];
    for &l in &image.labels {
        present[l as usize] = true;
    }
    if let Some(sv) = sv {
        for (k, ph) in image.phases.iter().enumerate() {
            if (0..image.labels.len()).any(|v| sv.of(v)[k] > 0.0) {
                present[ph.id as usize] = true;
            }
        }
    }
    PhaseImage {
        grid: image.grid.clone(),
        labels: (0..=255u8).filter(|&l| present[l as usize]).collect(),
        phases: image.phases.clone(),
    }
}

/// Preflight of the interface settings of a solver (see
/// [`grainpipe_core::subvoxel::InterfaceParams::check`]): the grid that is solved on.
pub fn check_interfaces(
    p: &grainpipe_core::subvoxel::InterfaceParams,
    scheme: Scheme,
    inputs: &grainpipe_core::InputMetas,
    grid: &grainpipe_core::Grid,
) -> Result<grainpipe_core::Grid, StageError> {
    use grainpipe_core::subvoxel::Interfaces;
    let solved = p.check(inputs.get("subvoxel"), grid)?;
    if p.interfaces == Interfaces::Composite && !matches!(scheme, Scheme::Hex8 | Scheme::Rotated) {
        return Err(StageError::param(
            "interfaces",
            "composite voxels need discretization: hex8 (or rotated): the laminate stiffness \
             of a voxel is applied at its element's Gauss points; the staggered grid keeps \
             normal and shear strains at different places (measured without the couplings: \
             no gain over labels on curved interfaces) and the spectral scheme has no element",
        ));
    }
    Ok(solved)
}

/// The boundaries the FFT solvers offer (walls are a flow boundary).
pub const FFT_BOUNDARIES: [Boundary; 2] = [Boundary::Periodic, Boundary::Mirror];

/// The cell the FFT solvers solve: the boundary resolved on `image` (its warning given) and,
/// with `boundary: mirror`, the image (and its sub-voxel geometry) reflected across its
/// non-periodic axes. The cell is `None` when nothing is mirrored.
pub fn mirrored_cell(
    boundary: &BoundaryParams,
    image: &PhaseImage,
    subvoxel: Option<Subvoxel>,
    ctx: &RunContext,
) -> Result<(ResolvedBoundary, Option<PhaseImage>, Option<Subvoxel>), StageError> {
    let bc = boundary.resolve(image.grid.periodic, &FFT_BOUNDARIES)?;
    if let Some(w) = bc.warning() {
        ctx.warn(&w);
    }
    if bc.voxel_factor() == 1 {
        return Ok((bc, None, subvoxel));
    }
    let cell = mirror_image(image, bc.mirror);
    let [x, y, z] = cell.grid.dims;
    ctx.info(&format!(
        "boundary: mirror: the image reflected across {} ({x}x{y}x{z} voxels)",
        axis_list(bc.mirror)
    ));
    let sv = subvoxel.map(|sv| mirror_subvoxel(&sv, image.grid.dims, bc.mirror));
    Ok((bc, Some(cell), sv))
}
