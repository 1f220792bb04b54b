//! `conductivity.fft`: apparent thermal conductivity of a periodic multi-phase voxel image,
//! the scalar analogue of `elasticity.fft` (same discretizations and solvers).

use grainpipe_core::units::{ThermalConductivity, Q};
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, Grid, InputMetas, Inputs, Outputs,
    ParamChoice, PhaseImage, PortSpec, Preflight, ResidualProgress, RunContext, StageError,
    StageInfo, Table, Tensor, TensorConvention, TypedStage,
};
use indexmap::IndexMap;
use serde::{Deserialize, Serialize};
use std::time::Instant;

use crate::common::{
    check_interfaces, check_keys, composite_table, mirrored_cell, phases_present, resolve,
    solve_failure, unused_keys, validate_solver, Discretization, Precision, Solver, FFT_BOUNDARIES,
};
use crate::kernel::composite::{laminate_conductivity, majority_pore_conductivity, Composite};
use crate::kernel::scalar::{bytes_per_voxel, Scalar};
use crate::kernel::solver::{solve, SolveOptions};
use crate::real::Real;
use grainpipe_core::boundary::BoundaryParams;
use grainpipe_core::subvoxel::{InterfaceParams, Interfaces, PoreVoxels};
use std::sync::Arc;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum GradientCase {
    /// Unit temperature gradient along x.
    X,
    /// Unit temperature gradient along y.
    Y,
    /// Unit temperature gradient along z.
    Z,
}

impl GradientCase {
    pub const ALL: [GradientCase; 3] = [GradientCase::X, GradientCase::Y, GradientCase::Z];
    pub fn name(self) -> &'static str {
        ["x", "y", "z"][self as usize]
    }
}

/// Grains (quartz sand) about 7.7 W/(m K) (the grains are mostly quartz), an inorganic (water glass)
/// binder about 1.0 W/(m K); pores (label 0) default to 0 (air, 0.026 W/(m K), may be given).
pub fn default_conductivities() -> IndexMap<String, Q<ThermalConductivity>> {
    let mut m = IndexMap::new();
    m.insert(grainpipe_core::phases::GRAIN.to_string(), Q::new(7.7));
    m.insert(grainpipe_core::phases::BINDER.to_string(), Q::new(1.0));
    m
}

#[params]
pub struct ConductivityParams {
    /// Phase name or label -> thermal conductivity. A phase left out that is label 0 is a
    /// pore of zero conductivity; any other phase of the image left out is an error.
    #[param(default = default_conductivities())]
    pub conductivities: IndexMap<String, Q<ThermalConductivity>>,
    /// Macroscopic unit temperature gradients to apply.
    #[param(default = GradientCase::ALL.to_vec())]
    pub load_cases: Vec<GradientCase>,
    /// Discretization (staggered = finite volumes with harmonic face means).
    #[param(default = Discretization::Staggered)]
    pub discretization: Discretization,
    /// Linear solver.
    #[param(default = Solver::Cg)]
    pub solver: Solver,
    /// Convergence: reference-energy norm of the preconditioned residual relative to that
    /// of the macroscopic gradient (Schneider 2021).
    #[param(default = 1e-5)]
    pub tolerance: f64,
    /// Iteration limit per load case; reaching it fails the stage with the residual.
    #[param(default = 1000)]
    pub max_iterations: usize,
    /// The stage fails as stagnated when the best residual has not dropped by 1 % over this
    /// many iterations.
    #[param(default = 200)]
    pub stagnation_window: usize,
    /// Floating-point precision of the fields.
    #[param(default = Precision::F64)]
    pub precision: Precision,
    #[param(flatten)]
    pub interface: InterfaceParams,
    #[param(flatten)]
    pub boundary: BoundaryParams,
}

pub struct ConductivityFft;

fn memory(p: &ConductivityParams, voxels: u64) -> u64 {
    let real = match p.precision {
        Precision::F64 => 8,
        Precision::F32 => 4,
    };
    // Composite table: a 4-byte slot per voxel and a 3x3 tensor (72 bytes) per mixed
    // voxel, counted for a mixed share of one half, plus the decoded sub-voxel geometry
    // (4 (P + 3) bytes, up to five phases).
    let composite = if p.interface.interfaces == Interfaces::Composite {
        4.0 + 0.5 * 72.0 + 32.0
    } else {
        0.0
    };
    ((bytes_per_voxel(p.discretization.scheme(), p.solver == Solver::Cg, real) + composite)
        * voxels as f64) as u64
}

impl TypedStage for ConductivityFft {
    type Params = ConductivityParams;
    type Plan = Grid;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "conductivity.fft",
            "1.3.0",
            "Apparent thermal conductivity of a periodic voxel image (an image that is not \
             periodic, a scan, needs boundary: mirror, the image reflected across its \
             non-periodic axes, or periodic, its faces glued): for each macroscopic \
             unit temperature gradient G the periodic fluctuation t solving \
             div k(x)(G + grad t) = 0 is computed by FFT-preconditioned conjugate gradients \
             (or the basic fixed-point scheme) with the staggered (finite-volume, harmonic \
             face means), hex8, rotated or spectral discretization; the columns of the 3x3 \
             conductivity are the mean fluxes. Pores (label 0 without a value) do not \
             conduct. Fails, naming the residual, on stagnation, divergence or the \
             iteration limit. Memory: about 100 bytes per voxel for staggered CG in double precision.",
        )
        .inputs(vec![
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "phase image, periodic or with `boundary:` (label 0 = pore unless given a value)",
            ),
            PortSpec::optional(
                "subvoxel",
                ArtifactKind::Field,
                "with interfaces: composite, the image maker's sub-voxel geometry (phase \
                 fractions and interface normals)",
            ),
        ])
        .outputs(vec![
            PortSpec::new(
                "conductivity",
                ArtifactKind::Tensor,
                "3x3 apparent conductivity (rows x, y, z), W/(m K)",
            ),
            PortSpec::new(
                "history",
                ArtifactKind::Table,
                "residual per iteration and load case",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &ConductivityParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<Grid>, StageError> {
        validate_solver(p.tolerance, p.max_iterations, p.stagnation_window)?;
        check_keys(
            "conductivities",
            &p.conductivities,
            inputs.get("image").and_then(|m| m.phases.as_deref()),
        )?;
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
        for (k, v) in &p.conductivities {
            if !(v.si() >= 0.0 && v.si().is_finite()) {
                return Err(StageError::param(
                    "conductivities",
                    format!(
                        "`{k}`: must be a non-negative conductivity, got {} W/(m K)",
                        v.si()
                    ),
                ));
            }
        }
        let grid = grainpipe_core::announced_grid(inputs, "image")?;
        let bc = p.boundary.resolve(grid.periodic, &FFT_BOUNDARIES)?;
        let grid = check_interfaces(&p.interface, p.discretization.scheme(), inputs, &grid)?;
        // The mirrored cell is what the solver holds, with its labels.
        let n = bc.solved_grid(&grid).voxel_count() as u64;
        let mirrored_labels = if bc.voxel_factor() > 1 { n } else { 0 };
        let cases = p.load_cases.len() as u64;
        // Per rayon task, the transform of one plane (complex, in and out: 4 reals per plane
        // voxel; twice the threads counted, as in elasticity.fft), and the tables.
        let solved = bc.solved_grid(&grid);
        let plane = (solved.dims[0] * solved.dims[1]) as u64;
        let real = if p.precision == Precision::F64 { 8 } else { 4 };
        let threads = rayon::current_num_threads() as u64;
        let extra = 2 * threads * plane * 4 * real + (64 << 10);
        Ok(
            Preflight::from_info(&self.info(), memory(p, n) + mirrored_labels + extra)
                .announce(
                    "conductivity",
                    ArtifactMeta::of(ArtifactKind::Tensor).with_count(9, Some([9, 9])),
                )
                .announce(
                    "history",
                    ArtifactMeta::of(ArtifactKind::Table).with_count(
                        cases * 50,
                        Some([cases, cases * (p.max_iterations as u64 + 1)]),
                    ),
                )
                .with_plan(grid),
        )
    }

    fn run(
        &self,
        p: &ConductivityParams,
        _grid: &Grid,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let input_image = input(inputs, "image", Artifact::as_phase_image)?;
        let field = InterfaceParams::subvoxel_input(inputs)?;
        let (tensor, history) = solve_image(p, input_image, field, ctx)?;
        let mut out = Outputs::new();
        out.insert(
            "conductivity".into(),
            Artifact::Tensor(Tensor {
                name: "conductivity".into(),
                unit: "W/(m K)".into(),
                shape: vec![3, 3],
                values: tensor.iter().flatten().copied().collect(),
                convention: TensorConvention::Plain,
            }),
        );
        out.insert(
            "history".into(),
            Artifact::Table(
                Table::new("history")
                    .with_str("load_case", history.iter().map(|h| h.0.clone()).collect())
                    .with_i64(
                        "iteration",
                        "",
                        history.iter().map(|h| h.1 as i64).collect(),
                    )
                    .with_f64("residual", "", history.iter().map(|h| h.2).collect()),
            ),
        );
        Ok(out)
    }
}

/// The conductivity of an input image with the interface settings applied (composite
/// voxels from `field` or from coarsening) and the residual history.
#[allow(clippy::type_complexity)]
pub fn solve_image(
    p: &ConductivityParams,
    input_image: &PhaseImage,
    field: Option<&grainpipe_core::Field>,
    ctx: &RunContext,
) -> Result<([[f64; 3]; 3], Vec<(String, usize, f64)>), StageError> {
    let (image, subvoxel) = p
        .interface
        .prepare(input_image, field)
        .map_err(|m| StageError::input("subvoxel", m))?;
    let (_, mirrored, subvoxel) = mirrored_cell(&p.boundary, image.as_ref(), subvoxel, ctx)?;
    let image = mirrored.as_ref().unwrap_or(image.as_ref());
    let k = resolve(
        "conductivities",
        &p.conductivities,
        &phases_present(image, subvoxel.as_ref()),
        0.0,
        |q| Ok(q.si()),
    )?;
    let law = match p.interface.pore_voxels {
        PoreVoxels::Majority => majority_pore_conductivity,
        PoreVoxels::Laminate => laminate_conductivity,
    };
    let composite = subvoxel.map(|sv| {
        let (table, summary) = composite_table(image, &sv, &k, law);
        summary.report(ctx, image.labels.len());
        Arc::new(table)
    });
    let unused = unused_keys(&p.conductivities, image);
    if !unused.is_empty() {
        ctx.warn(&format!(
            "conductivities {unused:?} match no phase of the image"
        ));
    }
    let out = match p.precision {
        Precision::F64 => solve_all::<f64>(p, image, &k, composite, ctx)?,
        Precision::F32 => solve_all::<f32>(p, image, &k, composite, ctx)?,
    };
    Ok(out)
}

/// The 3x3 apparent conductivity (column j = mean flux under unit gradient j) and the
/// residual history.
#[allow(clippy::type_complexity)]
pub fn solve_all<T: Real>(
    p: &ConductivityParams,
    image: &PhaseImage,
    k: &[f64],
    composite: Option<Arc<Composite<[[f64; 3]; 3]>>>,
    ctx: &RunContext,
) -> Result<([[f64; 3]; 3], Vec<(String, usize, f64)>), StageError> {
    let g = &image.grid;
    let mut present = [false; 256];
    for &l in &image.labels {
        present[l as usize] = true;
    }
    let used: Vec<f64> = (0..256).filter(|&l| present[l]).map(|l| k[l]).collect();
    let hi = used.iter().cloned().fold(0.0, f64::max);
    if hi <= 0.0 {
        return Err(StageError::failed(
            "no voxel of the image conducts: the conductivity is zero",
        ));
    }
    let lo_solid = used
        .iter()
        .cloned()
        .filter(|&v| v > 0.0)
        .fold(f64::INFINITY, f64::min);
    let lo_all = used.iter().cloned().fold(f64::INFINITY, f64::min);
    // CG: any positive reference (its scale drops out). Fixed point: the mean of the
    // extreme conductivities, the optimal basic-scheme reference.
    let reference = match p.solver {
        Solver::Cg => 0.5 * (hi + lo_solid),
        Solver::FixedPoint => 0.5 * (hi + lo_all),
    };
    let mut table = [0.0; 256];
    table.copy_from_slice(&k[..256]);
    let mut problem = Scalar::<T>::new(
        g.dims,
        g.spacing,
        image.labels.clone(),
        table,
        p.discretization.scheme(),
        reference,
    );
    if let Some(c) = composite {
        problem.set_composite(c);
    }
    let opt = SolveOptions {
        method: p.solver.method(),
        tolerance: p.tolerance,
        max_iterations: p.max_iterations,
        stagnation_window: p.stagnation_window,
    };
    let n = g.voxel_count() as f64;
    let mut tensor = [[0.0; 3]; 3];
    let mut history = vec![];
    let residuals = ResidualProgress::new(p.load_cases.len(), p.tolerance);
    let scheme = format!("{:?}", p.discretization).to_lowercase();
    for (ci, case) in p.load_cases.iter().enumerate() {
        let mut load = [0.0; 3];
        load[*case as usize] = 1.0;
        let t = Instant::now();
        let mut progress =
            |_it: usize, residual: f64| ctx.residual_progress(&residuals, ci, residual).is_ok();
        let sol = solve(&mut problem, &load, &opt, &mut progress)
            .map_err(|(e, _)| solve_failure(case.name(), &scheme, &e))?;
        residuals.finish(ci);
        for (i, r) in sol.history.iter().enumerate() {
            history.push((case.name().to_string(), i, *r));
        }
        let stats = problem.flux_stats(&sol.u, &load);
        let mut mean = [0.0; 3];
        for (q, _) in &stats {
            for d in 0..3 {
                mean[d] += q[d];
            }
        }
        for d in 0..3 {
            tensor[d][*case as usize] = mean[d] / n;
        }
        ctx.info(&format!(
            "gradient {}: {} iterations, residual {:.2e}, {:.2} s",
            case.name(),
            sol.history.len() - 1,
            sol.history.last().unwrap(),
            t.elapsed().as_secs_f64()
        ));
    }
    Ok((tensor, history))
}
