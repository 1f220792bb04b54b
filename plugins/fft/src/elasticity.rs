//! `elasticity.fft`: apparent stiffness of a periodic multi-phase voxel image (paper,
//! section 3.2, eq. 3.2-3.5).

use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, Collection, ComponentConvention, Field,
    FieldData, Grid, InputMetas, Inputs, Outputs, ParamChoice, PhaseImage, PortSpec, Preflight,
    ResidualProgress, RunContext, StageError, StageInfo, Table, Tensor, TensorConvention,
    TypedStage,
};
use indexmap::IndexMap;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use crate::common::{
    check_interfaces, check_keys, composite_table, mirrored_cell, phases_present, resolve,
    solve_failure, unused_keys, validate_solver, Discretization, Material, Precision, Solver,
    FFT_BOUNDARIES,
};
use crate::kernel::composite::{laminate_stiffness, majority_pore_stiffness, Composite, M6};
use crate::kernel::constants::{self, Class, ENGINEERING_NAMES};
use crate::kernel::elastic::{bytes_per_voxel, Elastic};
use crate::kernel::solver::{solve, SolveError, SolveOptions};
use crate::kernel::{Iso, Scheme};
use crate::real::Real;
use grainpipe_core::boundary::{crop_lower, BoundaryParams};
use grainpipe_core::subvoxel::{InterfaceParams, Interfaces, PoreVoxels};
use std::sync::Arc;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum LoadCase {
    /// Uniaxial strain E_xx = 1.
    Xx,
    /// Uniaxial strain E_yy = 1.
    Yy,
    /// Uniaxial strain E_zz = 1.
    Zz,
    /// Shear, engineering strain 2 E_yz = 1.
    Yz,
    /// Shear, engineering strain 2 E_xz = 1.
    Xz,
    /// Shear, engineering strain 2 E_xy = 1.
    Xy,
}

impl LoadCase {
    pub const ALL: [LoadCase; 6] = [
        LoadCase::Xx,
        LoadCase::Yy,
        LoadCase::Zz,
        LoadCase::Yz,
        LoadCase::Xz,
        LoadCase::Xy,
    ];
    /// Voigt column (order 11, 22, 33, 23, 13, 12).
    pub fn column(self) -> usize {
        self as usize
    }
    pub fn name(self) -> &'static str {
        ["xx", "yy", "zz", "yz", "xz", "xy"][self as usize]
    }
}

/// Table 1 of the paper: sand grains (`grain`) E = 66.9 GPa, nu = 0.25; binder E = 43 GPa, nu = 0.17.
pub fn default_materials() -> IndexMap<String, Material> {
    let mut m = IndexMap::new();
    m.insert(
        grainpipe_core::phases::GRAIN.to_string(),
        Material::e_nu(66.9e9, 0.25),
    );
    m.insert(
        grainpipe_core::phases::BINDER.to_string(),
        Material::e_nu(43e9, 0.17),
    );
    m
}

#[params]
pub struct ElasticityParams {
    /// Phase name or label -> {E, nu} or {K, G} (isotropic). A phase left out that is label 0
    /// is a pore (zero stiffness); any other phase of the image left out is an error. The
    /// default is Table 1 of the paper (grain, i.e. sand, 66.9 GPa / 0.25; binder 43 GPa /
    /// 0.17).
    #[param(default = default_materials())]
    pub materials: IndexMap<String, Material>,
    /// Macroscopic unit strains to apply (engineering shear); the stiffness column of a
    /// load case left out is zero. The constants need all six, except the orthotropic row's
    /// E_x, E_y, E_z and Poisson ratios (xx, yy, zz suffice: half the time for the
    /// anisotropy of a sand core) and each of its shear moduli (its own case).
    #[param(default = LoadCase::ALL.to_vec())]
    pub load_cases: Vec<LoadCase>,
    /// Discretization of eq. (3.3).
    #[param(default = Discretization::Staggered)]
    pub discretization: Discretization,
    /// Linear solver.
    #[param(default = Solver::Cg)]
    pub solver: Solver,
    /// Convergence: the reference-energy norm of the preconditioned residual relative to
    /// that of the macroscopic strain (Schneider 2021).
    #[param(default = 1e-5)]
    pub tolerance: f64,
    /// Iteration limit per load case; reaching it fails the stage with the residual.
    #[param(default = 1000)]
    pub max_iterations: usize,
    /// The stage fails as stagnated when the best residual has not dropped by 1 % over this
    /// many iterations.
    #[param(default = 200)]
    pub stagnation_window: usize,
    /// Floating-point precision of the fields. `single` takes ~2/3 of the time and halves
    /// the memory of each load case; at tolerances down to 1e-5 it needs the same iterations
    /// and gives the moduli to 5-6 digits. Where f32 round-off stalls the residual above the
    /// tolerance, the stage warns and solves again in double precision, one load case at a
    /// time (the memory estimate counts that state).
    #[param(default = Precision::F64)]
    pub precision: Precision,
    /// Also output the strain and stress fields (voxel centred, one per load case).
    #[param(default = false)]
    pub fields: bool,
    #[param(flatten)]
    pub interface: InterfaceParams,
    #[param(flatten)]
    pub boundary: BoundaryParams,
}

pub struct ElasticityFft;

/// What preflight worked out: the grid and the memory per voxel.
#[derive(Clone, Debug)]
pub struct ElasticityPlan {
    pub grid: Grid,
}

fn check_params(p: &ElasticityParams) -> Result<(), StageError> {
    validate_solver(p.tolerance, p.max_iterations, p.stagnation_window)?;
    if p.load_cases.is_empty() {
        return Err(StageError::param(
            "load_cases",
            "give at least one load case",
        ));
    }
    for (i, a) in p.load_cases.iter().enumerate() {
        if p.load_cases[..i].contains(a) {
            return Err(StageError::param(
                "load_cases",
                format!("`{}` is listed twice", a.name()),
            ));
        }
    }
    for (k, m) in &p.materials {
        m.iso()
            .map_err(|e| StageError::param("materials", format!("`{k}`: {e}")))?;
    }
    Ok(())
}

/// Bytes per voxel of the composite-voxel table, shared by the load cases: a 4-byte slot
/// per voxel and a 6x6 stiffness (288 bytes) per mixed voxel, counted for a mixed share of
/// one half (a sand core at 8 um has about a third), plus the decoded sub-voxel geometry
/// (4 (P + 3) bytes, counted for up to five phases).
pub const COMPOSITE_BYTES_PER_VOXEL: f64 = 4.0 + 0.5 * 288.0 + 32.0;

/// Memory of a run [bytes].
pub fn memory(p: &ElasticityParams, voxels: u64) -> u64 {
    let real = match p.precision {
        Precision::F64 => 8,
        Precision::F32 => 4,
    };
    let lane_of = |real| bytes_per_voxel(p.discretization.scheme(), p.solver == Solver::Cg, real);
    let lane = lane_of(real);
    let lanes = concurrent_cases(p.load_cases.len(), (lane * voxels as f64) as u64) as f64;
    let mut b = lanes * lane;
    if p.precision == Precision::F32 {
        // A stagnated single-precision solve is repeated in double, one load case at a time
        // (`solve_image`).
        b = b.max(lane_of(8));
    }
    if p.fields {
        // 12 f64 per voxel and load case, plus the voxel values gathered per plane.
        b += 96.0 * p.load_cases.len() as f64 + 96.0;
    }
    if p.interface.interfaces == Interfaces::Composite {
        b += COMPOSITE_BYTES_PER_VOXEL;
    }
    (b * voxels as f64) as u64
}

impl TypedStage for ElasticityFft {
    type Params = ElasticityParams;
    type Plan = ElasticityPlan;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "elasticity.fft",
            "1.4.0",
            "Apparent stiffness of a periodic voxel image (Donval et al. 2025, section 3.2, \
             eq. 3.2-3.5): for each macroscopic unit strain E the periodic displacement \
             fluctuation u solving div C(x):(E + grad^s u) = 0 is computed by FFT-preconditioned \
             conjugate gradients (or the basic fixed-point scheme) on a staggered grid \
             (default), trilinear hexahedra, the rotated scheme or the spectral \
             discretization; the columns of the apparent stiffness are the average stresses. \
             Pores (label 0 without a material) have zero stiffness. The stiffness is in \
             Voigt order 11, 22, 33, 23, 13, 12 with engineering shear strains (C44 is a \
             shear modulus), in Pa. The solver fails, naming the residual reached, on \
             stagnation, divergence, loss of positive definiteness or the iteration limit. \
             An image that is not periodic (a scan) needs boundary: mirror (the image reflected across its non-periodic axes, the fields given on its grid) or periodic (its faces glued, warned). Memory: about 177 bytes per voxel per load case solved at a time (two at a time with two or more threads while one state is at most 1 GiB, about 170^3) for staggered CG in double precision, half in single.",
        )
        .inputs(vec![
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "phase image, periodic or with `boundary:` (label 0 = pore unless given a material)",
            ),
            PortSpec::optional(
                "subvoxel",
                ArtifactKind::Field,
                "with interfaces: composite, the image maker's sub-voxel geometry (phase \
                 fractions and interface normals, the `subvoxel` output of binder.levelset or \
                 voxelize.packing run with subvoxel: true)",
            ),
        ])
        .outputs(vec![
            PortSpec::new(
                "stiffness",
                ArtifactKind::Tensor,
                "6x6 apparent stiffness, Voigt order 11, 22, 33, 23, 13, 12, engineering shear, Pa",
            ),
            PortSpec::new(
                "constants",
                ArtifactKind::Table,
                "engineering constants of the apparent stiffness and of its closest orthotropic, \
                 transversely isotropic (z) and isotropic approximations, with relative errors \
                 and the anisotropy E_z / mean(E_x, E_y) - 1",
            ),
            PortSpec::new(
                "phase_stress",
                ArtifactKind::Table,
                "average stress per phase and load case",
            ),
            PortSpec::new(
                "history",
                ArtifactKind::Table,
                "residual per iteration and load case",
            ),
            PortSpec::optional(
                "strain",
                ArtifactKind::Collection,
                "with fields: true, the strain field (Voigt, engineering shear) per load case",
            ),
            PortSpec::optional(
                "stress",
                ArtifactKind::Collection,
                "with fields: true, the stress field (Voigt, Pa) per load case",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &ElasticityParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<ElasticityPlan>, StageError> {
        check_params(p)?;
        check_keys(
            "materials",
            &p.materials,
            inputs.get("image").and_then(|m| m.phases.as_deref()),
        )?;
        let grid = grainpipe_core::announced_grid(inputs, "image")?;
        let bc = p.boundary.resolve(grid.periodic, &FFT_BOUNDARIES)?;
        let grid = check_interfaces(&p.interface, p.discretization.scheme(), inputs, &grid)?;
        // The mirrored cell is what the solver holds, with its labels.
        let n = bc.solved_grid(&grid).voxel_count() as u64;
        let mirrored_labels = if bc.voxel_factor() > 1 { n } else { 0 };
        let cases = p.load_cases.len() as u64;
        let solved = bc.solved_grid(&grid);
        let plane = (solved.dims[0] * solved.dims[1]) as u64;
        let real = if p.precision == Precision::F64 { 8 } else { 4 };
        let threads = rayon::current_num_threads() as u64;
        // Per rayon task, the transform of one plane of the three components (complex, in and
        // out: 12 reals per plane voxel); `map_init` makes one per task and a thread can hold
        // a stolen task's beside its own, so twice the threads are counted; with the staggered scheme, per solve the rings
        // of 18 planes per slab (two slabs per thread, at least 8 planes deep) beyond the one
        // scalar per voxel `memory` counts for them (small images have fewer planes).
        let mut extra = 2 * threads * plane * 12 * real;
        if p.discretization.scheme() == Scheme::Staggered {
            let nz = solved.dims[2] as u64;
            let slabs = (2 * threads).min(nz / 8).max(1);
            let lanes = concurrent_cases(p.load_cases.len(), memory(p, n)) as u64;
            extra += lanes * (slabs * 18).saturating_sub(nz) * plane * real;
        }
        let mut pf = Preflight::from_info(
            &self.info(),
            memory(p, n) + mirrored_labels + extra + (64 << 10),
        )
        .announce(
            "stiffness",
            ArtifactMeta::of(ArtifactKind::Tensor).with_count(36, Some([36, 36])),
        )
        .announce(
            "constants",
            ArtifactMeta::of(ArtifactKind::Table).with_count(4, Some([4, 4])),
        )
        .announce(
            "history",
            ArtifactMeta::of(ArtifactKind::Table).with_count(
                cases * 50,
                Some([cases, cases * (p.max_iterations as u64 + 1)]),
            ),
        );
        if p.fields {
            for port in ["strain", "stress"] {
                pf = pf.announce(
                    port,
                    ArtifactMeta::of(ArtifactKind::Collection)
                        .with_count(cases, Some([cases, cases])),
                );
            }
        } else {
            pf.outputs.retain(|k, _| k != "strain" && k != "stress");
        }
        Ok(pf.with_plan(ElasticityPlan { grid }))
    }

    fn run(
        &self,
        p: &ElasticityParams,
        _plan: &ElasticityPlan,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let input_image = input(inputs, "image", Artifact::as_phase_image)?;
        let field = InterfaceParams::subvoxel_input(inputs)?;
        let (image, result) = solve_image(p, input_image, field, ctx)?;
        check_stiffness(&result.stiffness, &p.load_cases)?;
        outputs(p, &image, result)
    }
}

/// Largest relative asymmetry `|C - C^T| / |C|` of an apparent stiffness that is reported. A
/// converged solve is symmetric to about its tolerance (1e-5 by default); 5 % means the
/// solve did not reach the problem's solution (round-off at a contrast the precision cannot
/// carry: 1e17 gave 1.3).
pub const MAX_STIFFNESS_ASYMMETRY: f64 = 0.05;

/// A stiffness that is not one fails loudly instead of being reported: every computed
/// diagonal entry positive and finite; with all six load cases, symmetric to
/// [`MAX_STIFFNESS_ASYMMETRY`] and positive definite.
pub fn check_stiffness(c: &[[f64; 6]; 6], cases: &[LoadCase]) -> Result<(), StageError> {
    for case in cases {
        let k = case.column();
        if !(c[k][k] > 0.0 && c.iter().all(|row| row[k].is_finite())) {
            return Err(StageError::failed(format!(
                "load case {} gave C{}{} = {:.3e} Pa: not a stiffness (the solve lost its accuracy; \
                 check the material contrast, or use precision: double)",
                case.name(),
                k + 1,
                k + 1,
                c[k][k]
            )));
        }
    }
    if cases.len() == 6 {
        let asym = constants::asymmetry(c);
        if asym > MAX_STIFFNESS_ASYMMETRY {
            return Err(StageError::failed(format!(
                "the apparent stiffness is not symmetric (|C - C^T| / |C| = {asym:.2e}, above \
                 {MAX_STIFFNESS_ASYMMETRY}): the solve did not converge to the solution; check the \
                 material contrast and the residual history, or use precision: double"
            )));
        }
        if !constants::positive_definite(c) {
            return Err(StageError::failed(
                "the apparent stiffness is not positive definite (some strain would release \
                 energy): the solve did not converge to the solution; check the material \
                 contrast and the residual history, or use precision: double",
            ));
        }
    }
    Ok(())
}

/// The image that is solved (the input, or its coarsening) and the solve: the interface
/// settings applied (composite voxels from `field` or from coarsening), the materials
/// resolved for every phase that holds volume, all load cases solved.
pub fn solve_image<'a>(
    p: &ElasticityParams,
    input_image: &'a PhaseImage,
    field: Option<&Field>,
    ctx: &RunContext,
) -> Result<(std::borrow::Cow<'a, PhaseImage>, ElasticResult), StageError> {
    let (image, subvoxel) = p
        .interface
        .prepare(input_image, field)
        .map_err(|m| StageError::input("subvoxel", m))?;
    let (bc, mirrored, subvoxel) = mirrored_cell(&p.boundary, image.as_ref(), subvoxel, ctx)?;
    let solved = mirrored.as_ref().unwrap_or(image.as_ref());
    let mats = resolve(
        "materials",
        &p.materials,
        &phases_present(solved, subvoxel.as_ref()),
        Iso::ZERO,
        |m| m.iso(),
    )?;
    let law = match p.interface.pore_voxels {
        PoreVoxels::Majority => majority_pore_stiffness,
        PoreVoxels::Laminate => laminate_stiffness,
    };
    let composite = subvoxel.map(|sv| {
        let (table, summary) = composite_table(solved, &sv, &mats, law);
        summary.report(ctx, solved.labels.len());
        Arc::new(table)
    });
    let unused = unused_keys(&p.materials, solved);
    if !unused.is_empty() {
        ctx.warn(&format!(
            "materials {unused:?} match no phase of the image (phases: {:?})",
            solved.phases.iter().map(|p| &p.name).collect::<Vec<_>>()
        ));
    }
    let result = match p.precision {
        Precision::F64 => solve_all::<f64>(p, solved, &mats, composite, ctx)?,
        Precision::F32 => match solve_lanes::<f32>(p, solved, &mats, composite.clone(), ctx, 2) {
            Ok(r) => r,
            // f32 round-off holds the residual above a tolerance below what f32 resolves;
            // the double-precision solve is the answer there, so give it instead of failing,
            // and say so. A residual that stagnates in double too (3 of 90 sand cores of the
            // validation ensembles, at 1.0e-5 to 4.2e-5) still fails. One load case at a
            // time: the peak is one double-precision state, which `memory` counts.
            Err(CaseFailure {
                error,
                stagnated: true,
            }) => {
                ctx.warn(&format!(
                    "precision single: {error}; every load case is solved again in double \
                     precision, one at a time (the results are the double-precision ones)"
                ));
                solve_lanes::<f64>(p, solved, &mats, composite, ctx, 1).map_err(|f| f.error)?
            }
            Err(f) => return Err(f.error),
        },
    };
    let result = match mirrored {
        Some(cell) => on_input_grid(result, &cell.grid, &image.grid, bc.voxel_factor()),
        None => result,
    };
    Ok((image, result))
}

/// The mirrored cell's result on the input's grid: the fields cropped to the input's voxels
/// (the cell's first octant is the input), the phase voxel counts divided by the number of
/// copies (each phase appears `copies` times), the stiffness and histories unchanged.
fn on_input_grid(mut r: ElasticResult, cell: &Grid, input: &Grid, copies: u64) -> ElasticResult {
    for x in r.phase_stress.iter_mut() {
        x.2 /= copies;
    }
    for (_, e, s) in r.fields.iter_mut() {
        *e = crop_lower(e, 6, cell.dims, input.dims);
        *s = crop_lower(s, 6, cell.dims, input.dims);
    }
    r
}

/// Everything the load cases give.
pub struct ElasticResult {
    pub stiffness: [[f64; 6]; 6],
    /// (load case, iteration, residual)
    pub history: Vec<(String, usize, f64)>,
    /// (load case, label, count, mean stress)
    pub phase_stress: Vec<(String, u8, u64, [f64; 6])>,
    pub fields: Vec<(String, Vec<f64>, Vec<f64>)>,
}

/// The reference medium. CG: the mean of the extreme solid Lame constants (the CG iterates
/// do not depend on its scale). Fixed point: `alpha0 Id` with `alpha0` the mean of the
/// largest and smallest stiffness eigenvalues over all phases (Moulinec & Suquet 1998), so
/// the basic scheme is a contraction whenever the smallest is positive.
pub fn reference(mats: &[Iso], present: &[bool], solver: Solver) -> Result<Iso, StageError> {
    let used: Vec<Iso> = (0..256).filter(|&l| present[l]).map(|l| mats[l]).collect();
    let solid: Vec<Iso> = used.iter().copied().filter(|m| !m.is_zero()).collect();
    if solid.is_empty() {
        return Err(StageError::failed(
            "the image has no solid voxel: the apparent stiffness is zero",
        ));
    }
    Ok(match solver {
        Solver::Cg => {
            let ext = |f: fn(&Iso) -> f64| {
                let v: Vec<f64> = solid.iter().map(f).collect();
                let max = v.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                let min = v.iter().cloned().fold(f64::INFINITY, f64::min);
                0.5 * (max + min)
            };
            Iso {
                lambda: ext(|m| m.lambda).max(0.0),
                mu: ext(|m| m.mu),
            }
        }
        Solver::FixedPoint => {
            let hi = used.iter().map(|m| m.eig_range().0).fold(0.0, f64::max);
            let lo = used
                .iter()
                .map(|m| m.eig_range().1)
                .fold(f64::INFINITY, f64::min);
            Iso {
                lambda: 0.0,
                mu: 0.25 * (hi + lo),
            }
        }
    })
}

/// Load cases solved at the same time (each with its own solver state): one per rayon thread,
/// at most two. Why: an iteration is ~20 short parallel sweeps, each ending in a join, and
/// on a shared 2-core machine every join waits for the thread the OS descheduled; with one
/// load case per thread the threads rarely wait on each other (rayon still steals inner
/// work when one runs out). At most two because each one costs the whole solver state
/// (`memory`), and only while one state (`lane_bytes`) is at most [`SECOND_LANE_MAX_BYTES`]:
/// the gain is ~10 % of wall time, not worth doubling the memory of an image that is large
/// next to the machine (a 400^3 image would need 27 GB instead of 14 GB). The results do not
/// depend on this: every load case runs the same arithmetic.
pub fn concurrent_cases(cases: usize, lane_bytes: u64) -> usize {
    if lane_bytes > SECOND_LANE_MAX_BYTES {
        return 1;
    }
    cases.min(rayon::current_num_threads()).clamp(1, 2)
}

/// Largest solver state that is run twice at once (see [`concurrent_cases`]): 1 GiB, a
/// 170^3 image in double precision with the staggered scheme.
pub const SECOND_LANE_MAX_BYTES: u64 = 1 << 30;

/// What one load case gives.
struct CaseResult {
    history: Vec<f64>,
    stats: Vec<([f64; 6], u64)>,
    fields: Option<(Vec<f64>, Vec<f64>)>,
    secs: f64,
}

/// Solves every load case of `p` on `image` in precision `T` (two at a time where the
/// memory and the threads allow).
pub fn solve_all<T: Real>(
    p: &ElasticityParams,
    image: &PhaseImage,
    mats: &[Iso],
    composite: Option<Arc<Composite<M6>>>,
    ctx: &RunContext,
) -> Result<ElasticResult, StageError> {
    solve_lanes::<T>(p, image, mats, composite, ctx, 2).map_err(|f| f.error)
}

/// Why `solve_lanes` failed: the stage error, and whether a load case stagnated (above the
/// tolerance, the residual no longer falling: in single precision, f32 round-off).
pub struct CaseFailure {
    pub error: StageError,
    pub stagnated: bool,
}

impl From<StageError> for CaseFailure {
    fn from(error: StageError) -> Self {
        CaseFailure {
            error,
            stagnated: false,
        }
    }
}

/// [`solve_all`] with at most `max_lanes` load cases at a time.
fn solve_lanes<T: Real>(
    p: &ElasticityParams,
    image: &PhaseImage,
    mats: &[Iso],
    composite: Option<Arc<Composite<M6>>>,
    ctx: &RunContext,
    max_lanes: usize,
) -> Result<ElasticResult, CaseFailure> {
    let g = &image.grid;
    let mut present = [false; 256];
    for &l in &image.labels {
        present[l as usize] = true;
    }
    let reference = reference(mats, &present, p.solver)?;
    let scheme = p.discretization.scheme();
    let mut table = [Iso::ZERO; 256];
    table.copy_from_slice(&mats[..256]);
    let opt = SolveOptions {
        method: p.solver.method(),
        tolerance: p.tolerance,
        max_iterations: p.max_iterations,
        stagnation_window: p.stagnation_window,
    };
    let n = g.voxel_count();
    let cases = p.load_cases.len();
    let lane_bytes =
        bytes_per_voxel(scheme, p.solver == Solver::Cg, std::mem::size_of::<T>()) * n as f64;
    let lanes = concurrent_cases(cases, lane_bytes as u64).min(max_lanes.max(1));
    let scheme_name = format!("{:?}", p.discretization).to_lowercase();
    // Progress by each load case's residual against the tolerance, and a stop flag set on
    // cancellation or on the first failure.
    let residuals = ResidualProgress::new(cases, p.tolerance);
    let stop = AtomicBool::new(false);
    let report = |ci: usize, residual: f64| {
        if ctx.residual_progress(&residuals, ci, residual).is_err() {
            stop.store(true, Ordering::Relaxed);
        }
        !stop.load(Ordering::Relaxed)
    };
    type Outcome = Result<CaseResult, (SolveError, Vec<f64>)>;
    let per_lane: Vec<Vec<(usize, Outcome)>> = (0..lanes)
        .into_par_iter()
        .map(|lane| {
            let t0 = Instant::now();
            let mut problem = Elastic::<T>::new(
                g.dims,
                g.spacing,
                image.labels.clone(),
                table,
                scheme,
                reference,
            );
            if let Some(c) = &composite {
                problem.set_composite(c.clone());
            }
            if lane == 0 {
                ctx.info(&format!(
                    "{}x{}x{} voxels, {:?} + {:?}, setup {:.2} s, {lanes} load case(s) at a time",
                    g.dims[0],
                    g.dims[1],
                    g.dims[2],
                    p.discretization,
                    p.solver,
                    t0.elapsed().as_secs_f64()
                ));
            }
            let mut out = vec![];
            for ci in (lane..cases).step_by(lanes) {
                if stop.load(Ordering::Relaxed) {
                    out.push((ci, Err((SolveError::Cancelled, vec![]))));
                    break;
                }
                let mut load = [0.0; 6];
                load[p.load_cases[ci].column()] = 1.0;
                let t = Instant::now();
                let mut progress = |_it: usize, residual: f64| report(ci, residual);
                match solve(&mut problem, &load, &opt, &mut progress) {
                    Ok(sol) => {
                        let secs = t.elapsed().as_secs_f64();
                        residuals.finish(ci);
                        let mut fields = if p.fields {
                            Some((vec![0.0; 6 * n], vec![0.0; 6 * n]))
                        } else {
                            None
                        };
                        let stats = problem.stress_stats(
                            &sol.u,
                            &load,
                            fields
                                .as_mut()
                                .map(|(a, b)| (a.as_mut_slice(), b.as_mut_slice())),
                        );
                        out.push((
                            ci,
                            Ok(CaseResult {
                                history: sol.history,
                                stats,
                                fields,
                                secs,
                            }),
                        ));
                    }
                    Err(e) => {
                        if e.0 != SolveError::Cancelled {
                            stop.store(true, Ordering::Relaxed);
                        }
                        out.push((ci, Err(e)));
                        break;
                    }
                }
            }
            out
        })
        .collect();
    let mut by_case: Vec<Option<Outcome>> = (0..cases).map(|_| None).collect();
    for (ci, o) in per_lane.into_iter().flatten() {
        by_case[ci] = Some(o);
    }
    // A real failure (in load-case order) explains the run better than the cancellations it
    // caused in the other lanes.
    let failure = by_case
        .iter()
        .enumerate()
        .find(|(_, o)| matches!(o, Some(Err((e, _))) if *e != SolveError::Cancelled))
        .or_else(|| {
            by_case
                .iter()
                .enumerate()
                .find(|(_, o)| !matches!(o, Some(Ok(_))))
        });
    if let Some((ci, o)) = failure {
        let case = p.load_cases[ci];
        let (e, history) = match o {
            Some(Err((e, h))) => (e.clone(), h.as_slice()),
            _ => (SolveError::Cancelled, &[][..]),
        };
        if e != SolveError::Cancelled {
            let last = history.last().copied().unwrap_or(f64::NAN);
            ctx.warn(&format!(
                "load case {}: {} iterations, last residual {last:.3e}",
                case.name(),
                history.len().saturating_sub(1)
            ));
        }
        return Err(CaseFailure {
            error: solve_failure(case.name(), &scheme_name, &e),
            stagnated: matches!(e, SolveError::Stagnated { .. }),
        });
    }
    let mut res = ElasticResult {
        stiffness: [[0.0; 6]; 6],
        history: vec![],
        phase_stress: vec![],
        fields: vec![],
    };
    for (ci, o) in by_case.into_iter().enumerate() {
        let Some(Ok(r)) = o else {
            unreachable!("failures returned above")
        };
        let case = p.load_cases[ci];
        let iters = r.history.len() - 1;
        for (i, h) in r.history.iter().enumerate() {
            res.history.push((case.name().to_string(), i, *h));
        }
        // eq. (3.4): the apparent stress is the cell average; eq. (3.5): its column.
        let mut mean = [0.0; 6];
        for (l, (sum, count)) in r.stats.iter().enumerate() {
            for k in 0..6 {
                mean[k] += sum[k];
            }
            if *count > 0 {
                res.phase_stress.push((
                    case.name().to_string(),
                    l as u8,
                    *count,
                    sum.map(|s| s / *count as f64),
                ));
            }
        }
        for k in 0..6 {
            res.stiffness[k][case.column()] = mean[k] / n as f64;
        }
        if let Some((e, s)) = r.fields {
            res.fields.push((case.name().to_string(), e, s));
        }
        ctx.info(&format!(
            "load case {}: {iters} iterations, residual {:.2e}, {:.2} s ({:.3} s/iteration{})",
            case.name(),
            r.history.last().unwrap(),
            r.secs,
            r.secs / iters.max(1) as f64,
            if lanes > 1 {
                format!(", {lanes} load cases at a time")
            } else {
                String::new()
            }
        ));
    }
    Ok(res)
}

fn outputs(
    p: &ElasticityParams,
    image: &PhaseImage,
    r: ElasticResult,
) -> Result<Outputs, StageError> {
    let c = r.stiffness;
    let mut out = Outputs::new();
    out.insert(
        "stiffness".into(),
        Artifact::Tensor(Tensor {
            name: "stiffness".into(),
            unit: "Pa".into(),
            shape: vec![6, 6],
            values: c.iter().flatten().copied().collect(),
            convention: TensorConvention::Voigt,
        }),
    );
    // Constants (Cowin 1985) of the symmetrized apparent stiffness and its projections
    // (Table 7); NaN unless all six load cases ran, except the orthotropic E and nu (the
    // three normal cases suffice) and its shear moduli (each its own case).
    let full = p.load_cases.len() == 6;
    let cs = constants::symmetrize(&c);
    let mut rows: Vec<(String, [f64; 12], f64)> = vec![];
    let nan = [f64::NAN; 12];
    rows.push((
        "apparent".into(),
        if full {
            constants::engineering(&cs)
        } else {
            nan
        },
        if full { 0.0 } else { f64::NAN },
    ));
    for (name, class) in [
        ("orthotropic", Class::Orthotropic),
        ("transversely_isotropic_z", Class::TransverselyIsotropicZ),
        ("isotropic", Class::Isotropic),
    ] {
        if !full && class == Class::Orthotropic {
            // E and nu of the orthotropic projection need only the normal load cases, each
            // shear modulus its own shear case (`orthotropic_from_columns`); the distance to
            // orthotropy needs all six.
            let mut ran = [false; 6];
            for case in &p.load_cases {
                ran[case.column()] = true;
            }
            rows.push((
                name.into(),
                constants::orthotropic_from_columns(&cs, ran),
                f64::NAN,
            ));
        } else if full {
            let (pc, err) = constants::project(&cs, class);
            rows.push((name.into(), constants::engineering(&pc), err));
        } else {
            rows.push((name.into(), nan, f64::NAN));
        }
    }
    let mut t = Table::new("constants")
        .with_str("approximation", rows.iter().map(|r| r.0.clone()).collect());
    for (k, name) in ENGINEERING_NAMES.iter().enumerate() {
        let unit = if k < 6 { "Pa" } else { "" };
        t = t.with_f64(name, unit, rows.iter().map(|r| r.1[k]).collect());
    }
    t = t.with_f64("relative_error", "", rows.iter().map(|r| r.2).collect());
    // The stacking-direction anisotropy of section 4.2 (E_z below E_x, E_y), per row, so a
    // sweep averages it per realization (issue 31).
    t = t.with_f64(
        "anisotropy_z",
        "1",
        rows.iter()
            .map(|r| r.1[2] / (0.5 * (r.1[0] + r.1[1])) - 1.0)
            .collect(),
    );
    out.insert("constants".into(), Artifact::Table(t));
    let name_of = |l: u8| {
        image
            .phases
            .iter()
            .find(|p| p.id == l)
            .map(|p| p.name.clone())
            .unwrap_or_else(|| l.to_string())
    };
    let n = image.labels.len() as f64;
    let mut ps = Table::new("phase_stress")
        .with_str(
            "load_case",
            r.phase_stress.iter().map(|x| x.0.clone()).collect(),
        )
        .with_str(
            "phase",
            r.phase_stress.iter().map(|x| name_of(x.1)).collect(),
        )
        .with_i64(
            "label",
            "",
            r.phase_stress.iter().map(|x| x.1 as i64).collect(),
        )
        .with_f64(
            "fraction",
            "",
            r.phase_stress.iter().map(|x| x.2 as f64 / n).collect(),
        );
    for (k, name) in ["s_xx", "s_yy", "s_zz", "s_yz", "s_xz", "s_xy"]
        .iter()
        .enumerate()
    {
        ps = ps.with_f64(name, "Pa", r.phase_stress.iter().map(|x| x.3[k]).collect());
    }
    out.insert("phase_stress".into(), Artifact::Table(ps));
    out.insert(
        "history".into(),
        Artifact::Table(
            Table::new("history")
                .with_str("load_case", r.history.iter().map(|h| h.0.clone()).collect())
                .with_i64(
                    "iteration",
                    "",
                    r.history.iter().map(|h| h.1 as i64).collect(),
                )
                .with_f64("residual", "", r.history.iter().map(|h| h.2).collect()),
        ),
    );
    if p.fields {
        let mut strain = Collection::default();
        let mut stress = Collection::default();
        for (case, e, s) in r.fields {
            let fe = Field::new(
                image.grid.clone(),
                format!("strain_{case}"),
                "1",
                ComponentConvention::Voigt,
                FieldData::F64(e),
            )
            .map_err(StageError::failed)?;
            let fs = Field::new(
                image.grid.clone(),
                format!("stress_{case}"),
                "Pa",
                ComponentConvention::Voigt,
                FieldData::F64(s),
            )
            .map_err(StageError::failed)?;
            strain.items.push((case.clone(), Artifact::Field(fe)));
            stress.items.push((case, Artifact::Field(fs)));
        }
        out.insert("strain".into(), Artifact::Collection(strain));
        out.insert("stress".into(), Artifact::Collection(stress));
    }
    Ok(out)
}
