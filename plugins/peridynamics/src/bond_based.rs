//! `peridynamics.bond_based`: bond-based peridynamics of a phase image under uniaxial
//! tension (Heinze et al. 2020, sections II.C-II.D).

use crate::lattice::{ForceLaw, Vec3};
use crate::multigrid::MgOptions;
use crate::setup::{build, Grips, Identity, PhaseSpec, Role, Setup};
use crate::solve::{cg, relax, Dynamics, Precond, Settings, SolveError, Stats};
use grainpipe_core::params::ParamType;
use grainpipe_core::phases;
use grainpipe_core::units::{Density, Dim, Dimension, Length, Pressure, Time, MAX_MODULUS, Q};
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, ComponentConvention, Field, FieldData,
    Grid, InputMetas, Inputs, Outputs, ParamChoice, Phase, PhaseImage, PortSpec, Preflight,
    RunContext, StageError, StageInfo, Table, TypedStage,
};
use indexmap::IndexMap;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::f64::consts::PI;

/// Critical energy release rate (J/m^2 = N/m).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Toughness;
impl Dim for Toughness {
    const DIM: Dimension = Dimension([0, 1, -2, 0, 0, 0, 0]);
    const SI_UNIT: &'static str = "J/m^2";
    const NAME: &'static str = "energy release rate";
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum PhaseRole {
    /// Particles: bonds inside one particle take the phase's E.
    Particle,
    /// Cementing matrix: matrix-matrix bonds take the phase's E.
    Matrix,
    /// No material (voids, pores): no nodes, no bonds.
    Void,
}

/// One phase: `{role, E, toughness}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhaseMaterial {
    pub role: PhaseRole,
    #[serde(rename = "E", default)]
    pub e: Q<Pressure>,
    #[serde(default)]
    pub toughness: Q<Toughness>,
}

impl ParamType for PhaseMaterial {
    fn type_name() -> String {
        "{role: particle|matrix|void, E: pressure, toughness: energy release rate}".into()
    }
    fn unit() -> &'static str {
        "Pa"
    }
    fn schema() -> Value {
        let q = <Q<Pressure> as ParamType>::schema();
        let t = <Q<Toughness> as ParamType>::schema();
        json!({"type": "object",
               "properties": {"role": {"enum": ["particle", "matrix", "void"]}, "E": q,
                              "toughness": t},
               "required": ["role"], "additionalProperties": false})
    }
}

/// The interface bond class: `{E, toughness}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InterfaceMaterial {
    #[serde(rename = "E")]
    pub e: Q<Pressure>,
    pub toughness: Q<Toughness>,
}

impl ParamType for InterfaceMaterial {
    fn type_name() -> String {
        "{E: pressure, toughness: energy release rate}".into()
    }
    fn unit() -> &'static str {
        "Pa"
    }
    fn schema() -> Value {
        let q = <Q<Pressure> as ParamType>::schema();
        let t = <Q<Toughness> as ParamType>::schema();
        json!({"type": "object", "properties": {"E": q, "toughness": t},
               "required": ["E", "toughness"], "additionalProperties": false})
    }
}

/// Matrix modulus of the defaults. Table I gives ratios only; PDFs of sigma / mean do not
/// depend on the scale (linear elasticity).
pub const E_MATRIX: f64 = 1e9;
/// Matrix toughness of the defaults (energy release rate; only used with breaking).
pub const GC_MATRIX: f64 = 10.0;
/// Table I: K_p = 3.5 K_m and E_p = 4 E_m; with G = K^2 / E, G_p = 3.5^2 / 4 G_m.
pub const GC_PARTICLE_RATIO: f64 = 3.5 * 3.5 / 4.0;

fn particle(e: f64, gc: f64) -> PhaseMaterial {
    PhaseMaterial {
        role: PhaseRole::Particle,
        e: Q::new(e),
        toughness: Q::new(gc),
    }
}

/// Table I: E_p = 4 E_m, E_i = E_m; the phase names of the cemented sample chain.
pub fn default_materials() -> IndexMap<String, PhaseMaterial> {
    let mut m = IndexMap::new();
    m.insert(
        phases::PORE.into(),
        PhaseMaterial {
            role: PhaseRole::Void,
            e: Q::new(0.0),
            toughness: Q::new(0.0),
        },
    );
    m.insert(
        phases::LARGE.into(),
        particle(4.0 * E_MATRIX, GC_PARTICLE_RATIO * GC_MATRIX),
    );
    m.insert(
        phases::SMALL.into(),
        particle(4.0 * E_MATRIX, GC_PARTICLE_RATIO * GC_MATRIX),
    );
    m.insert(
        phases::MATRIX.into(),
        PhaseMaterial {
            role: PhaseRole::Matrix,
            e: Q::new(E_MATRIX),
            toughness: Q::new(GC_MATRIX),
        },
    );
    m
}

fn default_interface() -> InterfaceMaterial {
    InterfaceMaterial {
        e: Q::new(E_MATRIX),
        toughness: Q::new(GC_MATRIX),
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum ParticleIdentity {
    /// `packing` when the `particles` input is connected, `components` otherwise.
    Auto,
    /// From the `particles` input (binder.bridges gives it, from the packing the image was
    /// made of): touching particles of one phase stay apart, and the bonds between them
    /// follow the interface rule of Table I.
    Packing,
    /// Face-connected regions of one particle phase are particles (two touching particles of
    /// the same phase merge into one: bonds between them are particle bonds).
    Components,
    /// No identity: every bond between two nodes of one particle phase is a particle bond.
    Phase,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Axis {
    /// Tension along x.
    X,
    /// Tension along y (the paper).
    Y,
    /// Tension along z (3-D images).
    Z,
}

impl Axis {
    pub fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum GripMode {
    /// All displacement components prescribed on the grip layers (the paper: lower boundary
    /// fixed, top line displaced).
    Clamped,
    /// Only the load component prescribed (free lateral contraction at the grips); one node
    /// per cluster pinned transversally.
    Sliding,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum SolverKind {
    /// Preconditioned conjugate gradients on the linearised bonds (the linear regime; far
    /// fewer iterations); see `preconditioner`.
    Cg,
    /// Adaptive dynamic relaxation (Kilic & Madenci 2010) with the nonlinear bond law.
    Adr,
    /// Damped explicit dynamics (section II.C) with the real density, run to rest.
    Explicit,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum PreconditionerKind {
    /// Aggregation multigrid W-cycle (2x2 blocks, Galerkin coarse operators, block-Jacobi
    /// smoothing, dense Cholesky on the coarsest grid): iterations bounded under refinement.
    Multigrid,
    /// Inverse diagonal: iterations grow about linearly with the grid edge.
    Jacobi,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Micromodulus {
    /// The continuum micromodulus of eq. (5), as the paper: on the voxel lattice a bulk
    /// region is stiffer than E (at h = 3: +6.4 % in 2-D, K +12 % in 3-D; the stencil sum
    /// exceeds the horizon integral).
    Continuum,
    /// Eq. (5) scaled so that the lattice's uniaxial modulus along an axis equals E (a
    /// calibrated micromodulus): every bond constant times E / E_lattice, the critical
    /// stretches divided by its square root so that G_c is kept.
    Calibrated,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum FloatingMode {
    /// Drop clusters with no bond path to a grip (zero displacement and stress), with a note.
    Exclude,
    /// Fail naming the clusters.
    Fail,
}

#[params]
pub struct BondBasedParams {
    /// Phase name or label -> {role: particle|matrix|void, E, toughness}. Label 0 (`pore`)
    /// left out has the void role; any other phase of the image left out is an error.
    /// Defaults, keyed by the cemented images' phases (`pore`, `large`, `small`, `matrix`):
    /// Table I with
    /// E_m = 1 GPa (the paper gives ratios: E_p = 4 E_m; toughness K_p = 3.5 K_m, i.e.
    /// G_p = 3.5^2/4 G_m with G = K^2/E; G_m = 10 J/m^2 is an assumed scale).
    #[param(default = default_materials())]
    pub materials: IndexMap<String, PhaseMaterial>,
    /// Interface bonds (particle-matrix and particle-particle of different particles):
    /// E_i = E_m, K_i = K_m (Table I).
    #[param(default = default_interface())]
    pub interface: InterfaceMaterial,
    /// How "the same particle" is decided: from the image maker's particle ids (`packing`,
    /// the default when the `particles` input is connected) or from the labels.
    #[param(default = ParticleIdentity::Auto)]
    pub particle_identity: ParticleIdentity,
    /// Horizon h in voxel edges (the paper: 3, 28 neighbours in 2-D, 122 in 3-D).
    #[param(default = 3.0)]
    pub horizon: f64,
    /// Horizon as a length; overrides `horizon` when given (rounded to the lattice).
    #[param(default = None)]
    pub horizon_length: Option<Q<Length>>,
    /// Tension axis; the grips are the first and last `grip_layers` node layers along it.
    #[param(default = Axis::Y)]
    pub axis: Axis,
    /// Nominal tensile strain between the inner grip layers (small: the paper stays linear).
    #[param(default = 1e-4)]
    pub strain: f64,
    /// How the grips hold the sample.
    #[param(default = GripMode::Clamped)]
    pub grips: GripMode,
    /// Node layers held by each grip.
    #[param(default = 1)]
    pub grip_layers: usize,
    /// Equilibrium solver.
    #[param(default = SolverKind::Cg)]
    pub solver: SolverKind,
    /// Preconditioner of solver: cg. multigrid: aggregation W-cycle, about 10 iterations at
    /// 256^2 to 1024^2 (set-up about 4 force sweeps, about 150 B more per node in 2-D);
    /// jacobi: no set-up, iterations grow linearly with the grid edge (600 at 256^2).
    #[param(default = PreconditionerKind::Multigrid)]
    pub preconditioner: PreconditionerKind,
    /// Convergence: |F| over the free DOFs relative to |F| of the initial affine state over
    /// all DOFs (grip reactions included). f32 vectors floor it near 1e-6 (2e-6 measured for
    /// ADR at strain 1e-4).
    #[param(default = 1e-5)]
    pub tolerance: f64,
    /// Iteration limit; reaching it fails the stage naming the residual.
    #[param(default = 20000)]
    pub max_iterations: usize,
    /// Fail as stagnated when the best residual has not dropped by 10 % over this many
    /// iterations.
    #[param(default = 2000)]
    pub stagnation_window: usize,
    /// Break bonds beyond the critical stretch (adr or explicit only).
    #[param(default = false)]
    pub breaking: bool,
    /// Mass density (explicit dynamics only; ADR uses fictitious densities).
    #[param(default = Q::new(1400.0))]
    pub density: Q<Density>,
    /// Explicit time step; default 0.8 x the critical step (Silling & Askari 2005). A step
    /// above the critical one is refused.
    #[param(default = None)]
    pub time_step: Option<Q<Time>>,
    /// Explicit dynamics viscosity as a fraction of the critical sqrt(2 m k) (section II.C).
    #[param(default = 0.5)]
    pub damping: f64,
    /// What to do with clusters that no bond path connects to a grip.
    #[param(default = FloatingMode::Exclude)]
    pub floating: FloatingMode,
    /// Micromodulus rule: `continuum` (eq. (5), the paper) or `calibrated` (the lattice's
    /// uniaxial bulk modulus equals E; see `lattice_modulus_ratio`).
    #[param(default = Micromodulus::Continuum)]
    pub micromodulus: Micromodulus,
    /// Memory the stage may use, in GiB; 0 = the available memory of this machine.
    #[param(default = 0.0)]
    pub memory_limit_gib: f64,
}

/// What preflight worked out.
#[derive(Clone, Debug)]
pub struct Plan {
    pub grid: Grid,
    /// Horizon in voxel edges.
    pub horizon: f64,
}

pub struct BondBased;

/// Bytes per padded node at the peak of a run (f32 vectors).
pub fn bytes_per_node(dim3: bool, neighbours: usize, breaking: bool) -> f64 {
    let nc = if dim3 { 3.0 } else { 2.0 };
    let nstress = if dim3 { 6.0 } else { 3.0 };
    // region + bond constant + flags + critical stretch, components (u32),
    // u + 7 solver vectors (CG: r z p q diag + 2 transient; ADR: v f f_prev mass diag gersh),
    // outputs (displacement, stress), broken-bond flags.
    let lattice = 4.0 + 4.0 + 1.0 + if breaking { 4.0 } else { 0.0 };
    // (u itself is f64: 4 more bytes per component)
    let vectors = 8.0 * 4.0 * nc + 4.0 * nc;
    let outputs = 4.0 * (nc + nstress);
    let flags = if breaking {
        8.0 * neighbours.div_ceil(64) as f64
    } else {
        0.0
    };
    // Multigrid (the default CG preconditioner; counted always, an upper bound for jacobi
    // and ADR): fine diagonal blocks, two work vectors, and the first coarse grid's block
    // stencil (5 x 5 blocks of 2 x 2 per 4 nodes in 2-D, 5^3 blocks of 3 x 3 per 8 in 3-D)
    // plus about a third of that for the coarser grids.
    let first_coarse = if dim3 {
        125.0 * 9.0 * 4.0 / 8.0
    } else {
        25.0 * 4.0 * 4.0 / 4.0
    };
    let multigrid = 4.0 * nc * nc + 8.0 * nc + first_coarse * 4.0 / 3.0;
    lattice + 4.0 + vectors + outputs + flags + 1.0 + multigrid
}

fn available_memory() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = s.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

fn check_material(key: &str, name: &str, m: &PhaseMaterial) -> Result<(), StageError> {
    if m.role == PhaseRole::Void {
        return Ok(());
    }
    let e = m.e.si();
    if !(e > 0.0 && e.is_finite()) {
        return Err(StageError::param(
            key,
            format!(
                "`{name}`: E must be positive for a {:?} phase, got {e} Pa",
                m.role
            ),
        ));
    }
    check_modulus_range(key, name, e)?;
    let g = m.toughness.si();
    if !(g >= 0.0 && g.is_finite()) {
        return Err(StageError::param(
            key,
            format!("`{name}`: toughness must be >= 0, got {g} J/m^2"),
        ));
    }
    Ok(())
}

/// A modulus above [`MAX_MODULUS`] is a unit slip, and stresses of order E overflow f32.
fn check_modulus_range(key: &str, name: &str, e: f64) -> Result<(), StageError> {
    if e > MAX_MODULUS {
        return Err(StageError::param(
            key,
            format!(
                "`{name}`: E = {e:.3e} Pa is above {MAX_MODULUS:.0e} Pa (1000 times diamond's); \
                 check the unit (e.g. `43 GPa`)"
            ),
        ));
    }
    Ok(())
}

/// Zener ratio 2 C_1212 / (C_1111 - C_1122) of the bond lattice of horizon `h` voxel edges
/// (the stencil sums of the bond law, Cauchy's C_1212 = C_1122): 1 for an isotropic lattice,
/// 0 where no bond is diagonal (no shear stiffness).
pub fn lattice_zener_ratio(h: f64, dim3: bool) -> f64 {
    let (c11, c12) = stencil_sums(h, dim3);
    2.0 * c12 / (c11 - c12)
}

/// The stencil sums S11 = sum x^4 / |m|^3 and S12 = sum x^2 y^2 / |m|^3 over the integer
/// offsets m within a horizon of `h` voxel edges (the lattice's C11, C12 up to the factor
/// c dx^d / 2 of the bond law).
fn stencil_sums(h: f64, dim3: bool) -> (f64, f64) {
    let r = h.floor() as i64;
    let (mut s11, mut s12) = (0.0, 0.0);
    let zs = if dim3 { -r..=r } else { 0..=0 };
    for z in zs {
        for y in -r..=r {
            for x in -r..=r {
                let l2 = (x * x + y * y + z * z) as f64;
                if l2 == 0.0 || l2 > h * h * (1.0 + 1e-9) {
                    continue;
                }
                let l3 = l2 * l2.sqrt();
                let (x2, y2) = ((x * x) as f64, (y * y) as f64);
                s11 += x2 * x2 / l3;
                s12 += x2 * y2 / l3;
            }
        }
    }
    (s11, s12)
}

/// The lattice's uniaxial modulus along an axis over the continuum E of eq. (5) (plane
/// stress, nu = 1/3 in 2-D; nu = 1/4 in 3-D), from the stencil sums
/// S11 = sum x^4 / |m|^3, S12 = sum x^2 y^2 / |m|^3 over the integer offsets m within the
/// horizon: C11, C12 = (c dx^d / 2) S11, S12; E_axis = C11 - C12^2 / C11 in 2-D and
/// (C11 - C12)(C11 + 2 C12) / (C11 + C12) in 3-D (cubic symmetry). The horizon integrals
/// give exactly E; at h = 3 the sums give 1.0644 (2-D) and 0.9974 (3-D, where K is 1.121
/// and nu 0.25 -> 0.28 instead: the calibration matches E only).
pub fn lattice_modulus_ratio(h: f64, dim3: bool) -> f64 {
    let (s11, s12) = stencil_sums(h, dim3);
    // c dx^d / 2 per unit E: 2-D c dx^4 = 9 E dx / (pi H^3); 3-D c dx^4 = 12 E / (pi H^4)
    // (eq. (5) with K = 2E/3), per unit thickness resp. volume.
    let k = if dim3 {
        6.0 / (PI * h.powi(4))
    } else {
        4.5 / (PI * h.powi(3))
    };
    let (c11, c12) = (k * s11, k * s12);
    if dim3 {
        (c11 - c12) * (c11 + 2.0 * c12) / (c11 + c12)
    } else {
        c11 - c12 * c12 / c11
    }
}

/// Horizon in voxel edges.
fn horizon_voxels(p: &BondBasedParams, dx: f64) -> Result<f64, StageError> {
    let (h, key) = match p.horizon_length {
        Some(l) => (l.si() / dx, "horizon_length"),
        None => (p.horizon, "horizon"),
    };
    if !(h.is_finite() && (1.0..=8.0).contains(&h)) {
        return Err(StageError::param(
            key,
            format!("the horizon must be 1 to 8 voxel edges (the paper uses 3), got {h:.3} voxels"),
        ));
    }
    // Below sqrt(2) edges every bond lies along an axis: the lattice has no shear stiffness,
    // the stiffness matrix is singular and a solve "converges" to a mechanism.
    if h < std::f64::consts::SQRT_2 {
        return Err(StageError::param(
            key,
            format!(
                "a horizon of {h:.3} voxel edges bonds only along the axes: no shear stiffness \
                 (the lattice's Zener ratio is 0), so the problem is singular; use at least \
                 1.5 (2.5 to 3 for a nearly isotropic lattice; the paper uses 3)"
            ),
        ));
    }
    Ok(h)
}

fn check_params(p: &BondBasedParams) -> Result<(), StageError> {
    for (k, m) in &p.materials {
        if k.trim().is_empty() {
            return Err(StageError::param("materials", "empty phase name"));
        }
        check_material("materials", k, m)?;
    }
    let i = &p.interface;
    if !(i.e.si() > 0.0 && i.e.si().is_finite()) {
        return Err(StageError::param("interface", "E must be positive"));
    }
    check_modulus_range("interface", "interface", i.e.si())?;
    if !(i.toughness.si() >= 0.0 && i.toughness.si().is_finite()) {
        return Err(StageError::param("interface", "toughness must be >= 0"));
    }
    if !(p.strain.is_finite() && p.strain != 0.0 && p.strain.abs() <= 0.05) {
        return Err(StageError::param(
            "strain",
            "must be non-zero and at most 0.05 in magnitude (bond-based PD without contact \
             is meant for small strains)",
        ));
    }
    if p.grip_layers == 0 {
        return Err(StageError::param("grip_layers", "must be at least 1"));
    }
    if !(p.tolerance > 0.0 && p.tolerance < 1.0) {
        return Err(StageError::param("tolerance", "must lie in (0, 1)"));
    }
    if p.max_iterations == 0 {
        return Err(StageError::param("max_iterations", "must be at least 1"));
    }
    if p.stagnation_window < 10 {
        return Err(StageError::param(
            "stagnation_window",
            "must be at least 10",
        ));
    }
    if p.breaking && p.solver == SolverKind::Cg {
        return Err(StageError::param(
            "breaking",
            "bond breaking needs solver: adr or explicit (CG solves the linear regime)",
        ));
    }
    if p.breaking {
        for (k, m) in &p.materials {
            if m.role != PhaseRole::Void && m.toughness.si() <= 0.0 {
                return Err(StageError::param(
                    "materials",
                    format!("`{k}`: breaking needs a positive toughness"),
                ));
            }
        }
        if p.interface.toughness.si() <= 0.0 {
            return Err(StageError::param(
                "interface",
                "breaking needs a positive toughness",
            ));
        }
    }
    if !(p.density.si() > 0.0 && p.density.si().is_finite()) {
        return Err(StageError::param("density", "must be positive"));
    }
    if !(0.0..1.0).contains(&p.damping) {
        return Err(StageError::param(
            "damping",
            "must lie in [0, 1) (a fraction of the critical viscosity)",
        ));
    }
    if let Some(t) = p.time_step {
        if !(t.si() > 0.0 && t.si().is_finite()) {
            return Err(StageError::param("time_step", "must be positive"));
        }
        if p.solver != SolverKind::Explicit {
            return Err(StageError::param(
                "time_step",
                "only explicit dynamics takes a time step (ADR uses dt = 1 with fictitious \
                 densities; CG has none)",
            ));
        }
    }
    if !(p.memory_limit_gib >= 0.0 && p.memory_limit_gib.is_finite()) {
        return Err(StageError::param("memory_limit_gib", "must be >= 0"));
    }
    Ok(())
}

/// Largest modulus among the material phases and the interface [Pa].
fn e_max(p: &BondBasedParams) -> f64 {
    p.materials
        .values()
        .filter(|m| m.role != PhaseRole::Void)
        .map(|m| m.e.si())
        .chain(std::iter::once(p.interface.e.si()))
        .fold(0.0, f64::max)
}

/// Smallest explicit step accepted, as a fraction of the critical one.
pub const MIN_STEP_FRACTION: f64 = 1e-3;

/// A step far below the critical one does not fail, it never arrives: the damped dynamics
/// needs about 1/dt steps to reach equilibrium, so max_iterations runs out (1e-300 s was
/// answered with "diverging ... reduce time_step").
fn too_small_step(t: f64, critical: f64) -> Result<(), StageError> {
    if t < MIN_STEP_FRACTION * critical {
        return Err(StageError::param(
            "time_step",
            format!(
                "{t:.4e} s is below {MIN_STEP_FRACTION} x the critical explicit step \
                 ({critical:.4e} s): equilibrium would take about {:.0e} times the iterations of \
                 the default step (0.8 x critical); leave time_step out, or use the adr solver",
                0.8 * critical / t
            ),
        ));
    }
    Ok(())
}

/// The smallest critical time step any image can have: a node with the full stencil of the
/// stiffest bond class (Silling & Askari 2005, eq. (20)): dt = sqrt(2 rho / sum_j c V_j /
/// |xi_j|) [s].
pub fn bulk_critical_step(p: &BondBasedParams, dx: f64, h: f64, dim3: bool) -> f64 {
    let e = e_max(p);
    let c = crate::setup::micromodulus(e, h * dx, dim3);
    let v = if dim3 { dx.powi(3) } else { dx * dx };
    let layout = crate::lattice::Layout::new(if dim3 { [8, 8, 8] } else { [8, 8, 1] }, h);
    let sum: f64 = layout
        .offsets
        .iter()
        .map(|o| c * v / (o.len as f64 * dx))
        .sum();
    (2.0 * p.density.si() / sum).sqrt()
}

fn check_grid(grid: &Grid, axis: usize) -> Result<(), StageError> {
    let dim3 = grid.dims[2] > 1;
    let n = if dim3 { 3 } else { 2 };
    let dx = grid.spacing[0];
    if (0..n).any(|a| (grid.spacing[a] / dx - 1.0).abs() > 1e-6) {
        return Err(StageError::input(
            "image",
            format!(
                "the PD lattice needs square (cubic) voxels, got spacing {:?} m",
                grid.spacing
            ),
        ));
    }
    if axis >= n {
        return Err(StageError::param(
            "axis",
            "a 2-D image (nz = 1) is loaded along x or y",
        ));
    }
    if grid.voxel_count() == 0 || grid.voxel_count() >= (u32::MAX / 2) as usize {
        return Err(StageError::input(
            "image",
            "the image must have between 1 and 2^31 voxels",
        ));
    }
    Ok(())
}

/// Resolves the material of every label present in the image.
pub fn resolve_phases(
    materials: &IndexMap<String, PhaseMaterial>,
    image: &PhaseImage,
) -> Result<[PhaseSpec; 256], StageError> {
    let mut present = [false; 256];
    for &l in &image.labels {
        present[l as usize] = true;
    }
    let mut out = [PhaseSpec::VOID; 256];
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
        let m = materials
            .get(&phase.name)
            .or_else(|| materials.get(&l.to_string()));
        match m {
            Some(m) => {
                out[l] = PhaseSpec {
                    role: match m.role {
                        PhaseRole::Particle => Role::Particle,
                        PhaseRole::Matrix => Role::Matrix,
                        PhaseRole::Void => Role::Void,
                    },
                    e: m.e.si(),
                    gc: m.toughness.si(),
                }
            }
            None if l == 0 => {}
            None => {
                return Err(StageError::param(
                    "materials",
                    format!(
                        "phase `{}` (label {l}) of the image has no entry; give one under its \
                         name or label (keys given: {:?}); only label 0 defaults to the void role",
                        phase.name,
                        materials.keys().collect::<Vec<_>>()
                    ),
                ))
            }
        }
    }
    Ok(out)
}

impl TypedStage for BondBased {
    type Params = BondBasedParams;
    type Plan = Plan;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "peridynamics.bond_based",
            "1.2.0",
            "Bond-based peridynamics of a phase image under uniaxial tension (Heinze et al. \
             2020, sections II.C-D). Each non-void voxel is a node; it bonds to every node \
             within the horizon h (default 3 voxel edges: 28 neighbours in 2-D, 122 in 3-D) \
             through fixed grid offsets, so no bond list is stored (about 70-100 bytes per \
             node, f32). Bond classes (II.D): both nodes in the same particle -> that phase's \
             E; both matrix -> matrix E; otherwise (different particles, particle-matrix) -> \
             interface E; bonds to void do not exist. Particle identity comes from the \
             image maker's particle ids (`particles` input, e.g. binder.bridges: touching \
             particles stay apart), else from face-connected regions of a particle label \
             (touching particles of one label merge) or from the label alone. Micromodulus eq. (5): 2-D plane stress \
             c = 6E/(pi h^3 (1 - nu)), nu = 1/3, per unit thickness; 3-D c = 18K/(pi h^4), \
             nu = 1/4; bond force f = c s n V_i V_j (eq. (6)-(7)). The first and last \
             `grip_layers` node layers along `axis` are held (clamped or sliding); the \
             top grip moves by strain x gauge length, the sides are free. Equilibrium by \
             CG on the linearised bonds (multigrid or Jacobi preconditioner), adaptive \
             dynamic relaxation (Kilic & Madenci 2010) or damped explicit dynamics with the \
             nonlinear bond law; \
             optional critical-stretch breaking (s_c = sqrt(4 pi G_c/(9 E h)) in 2-D, Ha & \
             Bobaru 2010; sqrt(5 G_c/(9 K h)) in 3-D). Clusters with no bond path to a grip \
             are excluded (or refused). The explicit step is checked against the critical \
             step (Silling & Askari 2005); energy growth stops the run. Nodal stress \
             sigma_i = 1/(2 V_i) sum_j f_ij (x) xi_ij. Deterministic for any thread count.",
        )
        .inputs(vec![
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "phase image with square (2-D, nz = 1) or cubic voxels; phases named or \
                 labelled in `materials`",
            ),
            PortSpec::optional(
                "particles",
                ArtifactKind::Field,
                "particle identity per voxel on the image grid (1 + particle index on particle \
                 voxels, 0 elsewhere; binder.bridges `particles`): used by \
                 particle_identity: packing (the default when connected)",
            ),
        ])
        .outputs(vec![
            PortSpec::new(
                "displacement",
                ArtifactKind::Field,
                "nodal displacement (m), vector (x, y) in 2-D, (x, y, z) in 3-D; zero on void \
                 and excluded nodes",
            ),
            PortSpec::new(
                "stress",
                ArtifactKind::Field,
                "nodal stress (Pa), Voigt order (xx, yy, xy) in 2-D (plane stress), \
                 (xx, yy, zz, yz, xz, xy) in 3-D; zero on void and excluded nodes",
            ),
            PortSpec::new(
                "report",
                ArtifactKind::Table,
                "one row: solver, iterations, residual, strain energy, broken bonds, \
                 effective moduli (mean stress / strain and grip reaction / strain), nodes, \
                 floating nodes, bonds per class, critical time step, notes",
            ),
            PortSpec::new(
                "history",
                ArtifactKind::Table,
                "convergence history: iteration, relative residual, energy (J per metre of \
                 thickness in 2-D, J in 3-D)",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &BondBasedParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<Plan>, StageError> {
        check_params(p)?;
        // Phase names the image will not have (a typo, a former default such as `void`) are
        // refused before the upstream steps run.
        grainpipe_core::phases::check_keys(
            "materials",
            &p.materials,
            inputs.get("image").and_then(|m| m.phases.as_deref()),
        )?;
        let grid = grainpipe_core::announced_grid(inputs, "image")?;
        check_grid(&grid, p.axis.index())?;
        match (p.particle_identity, inputs.get("particles")) {
            (ParticleIdentity::Packing, None) => {
                return Err(StageError::param(
                    "particle_identity",
                    "`packing` needs the `particles` input (in: { particles: \
                     bridges.particles }); without it use `components`",
                ))
            }
            (_, Some(m)) => {
                if let Some(g) = &m.grid {
                    if g.dims != grid.dims {
                        return Err(StageError::input(
                            "particles",
                            format!(
                                "the particle ids are on a {:?} grid, the image on {:?}",
                                g.dims, grid.dims
                            ),
                        ));
                    }
                }
            }
            _ => {}
        }
        let dx = grid.spacing[0];
        let h = horizon_voxels(p, dx)?;
        let dim3 = grid.dims[2] > 1;
        if grid.dims[p.axis.index()] < 2 * p.grip_layers + 1 {
            return Err(StageError::param(
                "grip_layers",
                format!(
                    "{} grip layers at each end leave no free layer of the {} along the axis",
                    p.grip_layers,
                    grid.dims[p.axis.index()]
                ),
            ));
        }
        if p.solver == SolverKind::Explicit {
            let crit = bulk_critical_step(p, dx, h, dim3);
            if let Some(t) = p.time_step {
                too_small_step(t.si(), crit)?;
                if t.si() > crit {
                    return Err(StageError::param(
                        "time_step",
                        format!(
                            "{:.4e} s exceeds the critical explicit step {crit:.4e} s of a bulk \
                             node of the stiffest bond class (Silling & Askari 2005: \
                             sqrt(2 rho / sum_j c V_j / |xi|)); use at most {crit:.4e} s",
                            t.si()
                        ),
                    ));
                }
            }
        }
        let layout = crate::lattice::Layout::new(grid.dims, h);
        let bpn = bytes_per_node(dim3, layout.offsets.len(), p.breaking);
        // Per node (above), plus the dense factor of the multigrid's coarsest level (counted
        // always, as the multigrid itself) and the tables.
        let bytes = bpn * layout.len() as f64
            + crate::multigrid::dense_bytes(grid.dims, if dim3 { 3 } else { 2 }) as f64
            + (64 << 10) as f64;
        let limit = if p.memory_limit_gib > 0.0 {
            Some(p.memory_limit_gib * (1u64 << 30) as f64)
        } else {
            available_memory().map(|b| b as f64)
        };
        if let Some(limit) = limit {
            if bytes > limit {
                return Err(StageError::input(
                    "image",
                    format!(
                        "{}x{}x{} nodes need {:.2} GiB ({bpn:.0} bytes per node) but {:.2} GiB \
                         are available; coarsen the image to at most {:.0} nodes",
                        grid.dims[0],
                        grid.dims[1],
                        grid.dims[2],
                        bytes / (1u64 << 30) as f64,
                        limit / (1u64 << 30) as f64,
                        limit / bpn
                    ),
                ));
            }
        }
        Ok(Preflight::from_info(&self.info(), bytes as u64)
            .announce(
                "displacement",
                ArtifactMeta::on_grid(ArtifactKind::Field, grid.clone()),
            )
            .announce(
                "stress",
                ArtifactMeta::on_grid(ArtifactKind::Field, grid.clone()),
            )
            .with_plan(Plan { grid, horizon: h }))
    }

    fn run(
        &self,
        p: &BondBasedParams,
        plan: &Plan,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let image = input(inputs, "image", Artifact::as_phase_image)?;
        let grid = &image.grid;
        check_grid(grid, p.axis.index())?;
        let unused: Vec<&String> = p
            .materials
            .keys()
            .filter(|k| {
                !image.phases.iter().any(|ph| &&ph.name == k)
                    && k.parse::<u8>()
                        .map(|l| image.fraction(l) == 0.0)
                        .unwrap_or(true)
            })
            .collect();
        if !unused.is_empty() {
            ctx.info(&format!(
                "materials {unused:?} name no phase of the image (phases: {:?})",
                image.phases.iter().map(|p| &p.name).collect::<Vec<_>>()
            ));
        }
        let phases = resolve_phases(&p.materials, image)?;
        let particles = match inputs.get("particles") {
            Some(a) => Some(particle_ids(
                a.as_field().ok_or_else(|| {
                    StageError::input("particles", "expects a Field of particle ids")
                })?,
                &image.grid,
            )?),
            None => None,
        };
        let out = run_model(p, plan.horizon, image, particles, &phases, ctx)?;
        Ok(out)
    }
}

/// Everything a run produces, before it becomes artifacts (tests use it directly).
pub struct RunResult {
    pub displacement: Vec<f32>,
    pub stress: Vec<f32>,
    pub report: Table,
    pub history: Table,
    pub stats: Stats,
}

/// The particle ids of a `particles` field: non-negative integers on the image's grid.
fn particle_ids(field: &Field, grid: &Grid) -> Result<std::sync::Arc<[u32]>, StageError> {
    if field.grid.dims != grid.dims || field.components != 1 {
        return Err(StageError::input(
            "particles",
            format!(
                "a scalar field on the image grid {:?} is needed, got {} component(s) on {:?}",
                grid.dims, field.components, field.grid.dims
            ),
        ));
    }
    let n = field.data.len();
    (0..n)
        .map(|v| {
            let x = match &field.data {
                FieldData::F32(d) => d[v] as f64,
                FieldData::F64(d) => d[v],
            };
            if x >= 0.0 && x.fract() == 0.0 && x < u32::MAX as f64 {
                Ok(x as u32)
            } else {
                Err(StageError::input(
                    "particles",
                    format!("value {x} at voxel {v} is not a particle id (0, 1, 2, ...)"),
                ))
            }
        })
        .collect()
}

/// Runs the model on an image with resolved phases (and, for `particle_identity: packing`
/// or `auto`, the particle ids of its voxels).
pub fn run_model(
    p: &BondBasedParams,
    horizon: f64,
    image: &PhaseImage,
    particles: Option<std::sync::Arc<[u32]>>,
    phases: &[PhaseSpec; 256],
    ctx: &RunContext,
) -> Result<Outputs, StageError> {
    let r = solve_image_with(p, horizon, image, particles, phases, ctx)?;
    let grid = &image.grid;
    let mut out = Outputs::new();
    let field = |name: &str, unit: &str, conv, data| {
        Field::new(grid.clone(), name, unit, conv, FieldData::F32(data)).map_err(StageError::failed)
    };
    out.insert(
        "displacement".into(),
        Artifact::Field(field(
            "displacement",
            "m",
            ComponentConvention::Vector,
            r.displacement,
        )?),
    );
    out.insert(
        "stress".into(),
        Artifact::Field(field("stress", "Pa", ComponentConvention::Voigt, r.stress)?),
    );
    out.insert("report".into(), Artifact::Table(r.report));
    out.insert("history".into(), Artifact::Table(r.history));
    Ok(out)
}

/// The solve behind the stage, with particle identity from the labels (`packing` is refused).
pub fn solve_image(
    p: &BondBasedParams,
    horizon: f64,
    image: &PhaseImage,
    phases: &[PhaseSpec; 256],
    ctx: &RunContext,
) -> Result<RunResult, StageError> {
    solve_image_with(p, horizon, image, None, phases, ctx)
}

/// The solve behind the stage; `particles` are the voxels' particle ids, if known.
pub fn solve_image_with(
    p: &BondBasedParams,
    horizon: f64,
    image: &PhaseImage,
    particles: Option<std::sync::Arc<[u32]>>,
    phases: &[PhaseSpec; 256],
    ctx: &RunContext,
) -> Result<RunResult, StageError> {
    let grid = &image.grid;
    let dx = grid.spacing[0];
    let dims = grid.dims;
    let dim3 = dims[2] > 1;
    // The lattice's own anisotropy (its stencil sums): at h = 3 the Zener ratio is 0.93 in
    // 2-D and 1.25 in 3-D; far from 1 the moduli depend on the loading direction.
    let zener = lattice_zener_ratio(horizon, dim3);
    if (zener - 1.0).abs() > 0.3 {
        ctx.warn(&format!(
            "a horizon of {horizon:.3} voxel edges gives a strongly anisotropic lattice (Zener \
             ratio {zener:.2}, 1 = isotropic): the moduli depend on the loading direction; \
             2.5 to 3 edges are nearly isotropic"
        ));
    }
    let setup = Setup {
        horizon,
        interface: PhaseSpec {
            role: Role::Matrix,
            e: p.interface.e.si(),
            gc: p.interface.toughness.si(),
        },
        identity: match (p.particle_identity, particles) {
            (ParticleIdentity::Auto | ParticleIdentity::Packing, Some(ids)) => Identity::Given(ids),
            (ParticleIdentity::Packing, None) => {
                return Err(StageError::param(
                    "particle_identity",
                    "`packing` needs the `particles` input (binder.bridges `particles`)",
                ))
            }
            (ParticleIdentity::Auto | ParticleIdentity::Components, _) => Identity::Components,
            (ParticleIdentity::Phase, _) => Identity::Phase,
        },
        breaking: p.breaking,
        axis: p.axis.index(),
        grips: match p.grips {
            GripMode::Clamped => Grips::Clamped,
            GripMode::Sliding => Grips::Sliding,
        },
        grip_layers: p.grip_layers,
        strain: p.strain,
        fail_on_floating: p.floating == FloatingMode::Fail,
        stiffness_scale: match p.micromodulus {
            Micromodulus::Continuum => 1.0,
            Micromodulus::Calibrated => 1.0 / lattice_modulus_ratio(horizon, dim3),
        },
    };
    let built = build(dims, &image.labels, phases, dx, &setup).map_err(|e| match e {
        crate::setup::SetupError::Unloaded => StageError::input("image", e.to_string()),
        crate::setup::SetupError::Identity(_) => StageError::input("particles", e.to_string()),
        _ => StageError::failed(e.to_string()),
    })?;
    let mut notes = Vec::new();
    if built.floating_nodes > 0 {
        let n = format!(
            "{} floating cluster(s) with {} nodes have no bond path to a grip and were \
             excluded (zero displacement and stress)",
            built.floating_clusters, built.floating_nodes
        );
        ctx.warn(&n);
        notes.push(n);
    }
    if built.mechanism_dofs > 0 {
        let n = format!(
            "{} displacement components had no bond along them (one-voxel lines) and were \
             pinned",
            built.mechanism_dofs
        );
        ctx.warn(&n);
        notes.push(n);
    }
    let lat = &built.lattice;
    let e_ref = built.e_ref;
    // Scaled time unit dx sqrt(rho / E_ref) (see lattice.rs).
    let tau = dx * (p.density.si() / e_ref).sqrt();
    let sums = lat.spring_sums();
    let smax = sums.iter().cloned().fold(0f32, f32::max) as f64;
    // Silling & Askari 2005 eq. (20) per node with the scaled mass 1; the smallest.
    let dt_crit = if smax > 0.0 {
        (2.0 / smax).sqrt() * tau
    } else {
        f64::INFINITY
    };
    let settings = Settings {
        tolerance: p.tolerance,
        max_iterations: p.max_iterations,
        stagnation_window: p.stagnation_window,
    };
    let mut u = built.u0.clone();
    let mut prog = |it: usize, max: usize| ctx.progress(it as u64, max as u64).is_ok();
    let mut broken: Option<Vec<u64>> = if p.breaking {
        Some(vec![
            0u64;
            lat.layout.len()
                * crate::lattice::broken_words(&lat.layout)
        ])
    } else {
        None
    };
    let (law, result) = match p.solver {
        SolverKind::Cg => {
            let pc = match p.preconditioner {
                PreconditionerKind::Multigrid => Precond::Multigrid(MgOptions::default()),
                PreconditionerKind::Jacobi => Precond::Jacobi,
            };
            (ForceLaw::Linear, cg(lat, &mut u, &settings, pc, &mut prog))
        }
        SolverKind::Adr => (
            ForceLaw::Nonlinear,
            relax(lat, &mut u, &settings, None, broken.as_mut(), &mut prog),
        ),
        SolverKind::Explicit => {
            let dt = match p.time_step {
                Some(t) => {
                    too_small_step(t.si(), dt_crit)?;
                    if t.si() > dt_crit {
                        return Err(StageError::param(
                            "time_step",
                            format!(
                                "{:.4e} s exceeds the critical explicit step {dt_crit:.4e} s of \
                                 this image (Silling & Askari 2005); use at most that",
                                t.si()
                            ),
                        ));
                    }
                    t.si()
                }
                None => 0.8 * dt_crit,
            };
            let kmax = (lat.kself.iter().cloned().fold(lat.kint, f32::max)) as f64;
            let d = Dynamics {
                dt: dt / tau,
                damping: p.damping,
                kmax,
            };
            (
                ForceLaw::Nonlinear,
                relax(lat, &mut u, &settings, Some(d), broken.as_mut(), &mut prog),
            )
        }
    };
    let solver_name = match p.solver {
        SolverKind::Cg => "cg",
        SolverKind::Adr => "adr",
        SolverKind::Explicit => "explicit",
    };
    let stats = result.map_err(|e| match e {
        SolveError::Cancelled => StageError::Cancelled,
        // The dynamic solvers march to rest; in the linear regime CG needs far fewer steps.
        e @ SolveError::NotConverged { .. } if p.solver != SolverKind::Cg => StageError::failed(
            format!("{solver_name} solver: {e}; or use solver: cg for the linear regime"),
        ),
        e => StageError::failed(format!("{solver_name} solver: {e}")),
    })?;

    // Stress (eq. in II.C) in E_ref, then Pa.
    let sigma = lat.stress(&u, law, broken.as_deref());
    let nstress = if dim3 { 6 } else { 3 };
    let stress: Vec<f32> = sigma.iter().map(|&s| (s as f64 * e_ref) as f32).collect();
    let nc = lat.layout.ncomp();
    let [nx, ny, nz] = dims;
    let mut displacement = vec![0f32; nx * ny * nz * nc];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let i = lat.layout.pidx(x, y, z);
                let v = x + nx * (y + ny * z);
                if lat.region[i] == 0 {
                    continue;
                }
                // Add back the affine background (see Lattice::bg).
                let c = [x, y, z];
                for b in 0..nc {
                    let affine = lat.bg[b] as f64 * (c[b] as f64 - (p.grip_layers as f64 - 1.0));
                    displacement[v * nc + b] = ((u.c[b][i] + affine) * dx) as f32;
                }
            }
        }
    }
    // Effective moduli: mean stress over the whole image (voids count zero) / strain, and
    // grip reaction / cross-section / strain.
    let a = p.axis.index();
    // Voigt: the normal component of axis a is component a in 2-D and 3-D.
    let comp = a;
    let mean: f64 = stress
        .iter()
        .skip(comp)
        .step_by(nstress)
        .map(|&s| s as f64)
        .sum::<f64>()
        / (nx * ny * nz) as f64;
    let mut f = Vec3::zeros(&lat.layout);
    lat.forces(&u, law, &mut f, broken.clone().as_deref_mut(), true);
    let na = dims[a];
    let mut reaction = 0.0;
    for i in 0..lat.layout.len() {
        if lat.region[i] == 0 {
            continue;
        }
        if let Some(c) = lat.layout.coords(i) {
            if c[a] + p.grip_layers >= na {
                // The grip must pull with -F_int.
                reaction -= f.c[a][i] as f64;
            }
        }
    }
    // Forces are in E_ref dx^(d-1); the cross-section is the product of the other extents.
    let section: f64 = (0..if dim3 { 3 } else { 2 })
        .filter(|&b| b != a)
        .map(|b| dims[b] as f64)
        .product::<f64>();
    let reaction_stress = reaction * e_ref / section;
    let energy_scale = e_ref * dx.powi(if dim3 { 3 } else { 2 });
    let note = notes.join("; ");
    ctx.info(&format!(
        "{:?}: {} iterations, residual {:.2e}, E_eff = {:.4e} Pa (mean stress), {:.4e} Pa \
         (grip reaction), {} broken bonds",
        p.solver,
        stats.iterations,
        stats.residual,
        mean / p.strain,
        reaction_stress / p.strain,
        stats.broken_bonds
    ));
    let energy_unit = if dim3 { "J" } else { "J/m" };
    let report = Table::new("peridynamics")
        .with_str("solver", vec![solver_name.into()])
        .with_i64("iterations", "1", vec![stats.iterations as i64])
        .with_f64("residual", "1", vec![stats.residual])
        .with_f64(
            "strain_energy",
            energy_unit,
            vec![stats.energy * energy_scale],
        )
        .with_i64("broken_bonds", "1", vec![stats.broken_bonds as i64])
        .with_f64("strain", "1", vec![p.strain])
        .with_f64("mean_stress", "Pa", vec![mean])
        .with_f64("effective_modulus", "Pa", vec![mean / p.strain])
        .with_f64("reaction_modulus", "Pa", vec![reaction_stress / p.strain])
        .with_i64("nodes", "1", vec![built.nodes as i64])
        .with_i64("floating_nodes", "1", vec![built.floating_nodes as i64])
        .with_i64(
            "floating_clusters",
            "1",
            vec![built.floating_clusters as i64],
        )
        .with_i64("particles", "1", vec![built.particles as i64])
        .with_i64("particle_bonds", "1", vec![built.bonds[0] as i64])
        .with_i64("matrix_bonds", "1", vec![built.bonds[1] as i64])
        .with_i64("interface_bonds", "1", vec![built.bonds[2] as i64])
        .with_f64("horizon", "m", vec![horizon * dx])
        .with_f64("critical_time_step", "s", vec![dt_crit])
        .with_str("note", vec![note]);
    let h = &stats.history;
    let history = Table::new("history")
        .with_str("solver", vec![solver_name.to_string(); h.iteration.len()])
        .with_i64(
            "iteration",
            "1",
            h.iteration.iter().map(|&i| i as i64).collect(),
        )
        .with_f64("residual", "1", h.residual.clone())
        .with_f64(
            "energy",
            energy_unit,
            h.energy.iter().map(|e| e * energy_scale).collect(),
        );
    Ok(RunResult {
        displacement,
        stress,
        report,
        history,
        stats,
    })
}
