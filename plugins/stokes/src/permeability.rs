//! `stokes.permeability`: apparent permeability tensor of a periodic voxel pore space
//! (Donval et al. 2025, section 3.3, eq. 3.6-3.8).

use crate::mac::{Dims, Percolation};
use crate::multigrid::CycleSettings;
use crate::solver::{
    permeability, permeability_composite, symmetry_error, SolveError, SolverSettings,
    BYTES_PER_VOXEL, FIELD_BYTES_PER_VOXEL, LABEL_BYTES_PER_VOXEL,
};
use crate::walls::{WallsLayout, MIN_BUFFER};
use grainpipe_core::boundary::{crop_lower, mirror, Boundary, BoundaryParams, ResolvedBoundary};
use grainpipe_core::subvoxel::{InterfaceParams, Interfaces};
use grainpipe_core::units::{Pressure, Viscosity, Q};
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, Collection, ComponentConvention, Field,
    FieldData, Grid, InputMetas, Inputs, Outputs, ParamChoice, PortSpec, Preflight,
    ResidualProgress, RunContext, StageError, StageInfo, Table, Tensor, TensorConvention,
    TypedStage,
};
use serde::{Deserialize, Serialize};

/// A load direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Axis {
    /// Body force along x.
    X,
    /// Body force along y.
    Y,
    /// Body force along z.
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
    pub fn name(self) -> &'static str {
        ["x", "y", "z"][self.index()]
    }
}

/// Which load directions' fields `fields: true` outputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum FieldDirections {
    /// The first listed direction, as the fields `velocity` and `pressure`.
    First,
    /// Every listed direction, as the collections `velocities` and `pressures` (members x, y,
    /// z); 16 B per voxel more for each direction beyond the first.
    All,
}

#[params]
pub struct PermeabilityParams {
    /// Load cases: the body force f = e_i for each listed axis (eq. 3.8); three give the full tensor.
    #[param(default = vec![Axis::X, Axis::Y, Axis::Z])]
    pub directions: Vec<Axis>,
    /// Image labels that are fluid (pore space); every other label is solid.
    #[param(default = vec![0])]
    pub fluid: Vec<u8>,
    /// Shear viscosity of the fluid; kappa does not depend on it, the velocities do (air, section 4.4).
    #[param(default = Q::new(1.8e-5))]
    pub viscosity: Q<Viscosity>,
    /// Pressure drop across the cell along the load direction; the body force is f = drop / cell length.
    #[param(default = Q::new(100.0))]
    pub pressure_drop: Q<Pressure>,
    /// MINRES stops when the preconditioned residual has fallen by this factor (1e-5 leaves kappa within about 1e-6 of converged).
    #[param(default = 1e-5)]
    pub tolerance: f64,
    /// MINRES iteration limit per load case; the stage fails, naming the residual, beyond it.
    #[param(default = 2000, ty = "integer 1..100000")]
    pub max_iterations: u32,
    /// Also output the velocity and pressure fields (voxel centred) of the first load direction
    /// (or of every direction, `field_directions: all`).
    #[param(default = false)]
    pub fields: bool,
    /// With fields: true, the first direction's fields (`velocity`, `pressure`) or every
    /// direction's (`velocities`, `pressures`: collections by direction).
    #[param(default = FieldDirections::First)]
    pub field_directions: FieldDirections,
    /// Memory the solve may use, in GiB; 0 = the available memory of this machine.
    #[param(default = 0.0)]
    pub memory_limit_gib: f64,
    /// Multigrid coarse-correction scale (piecewise-constant prolongation undershoots; 1 to 2).
    /// 1.8 measured 10-14 % fewer iterations than 1.5 on random packings at 64^3 and 96^3.
    #[param(default = 1.8)]
    pub over_correction: f64,
    /// Walls with `interfaces: composite` (see the shared `interfaces` / `coarsen` below):
    /// inside the boundary voxels from their fluid volume fraction (sum of the fractions of
    /// the `fluid` phases): voxels at least half fluid carry the unknowns and each velocity
    /// next to the solid sees the wall at the distance the fractions give (symmetric wall
    /// rule of Gibou et al. 2002; see docs/stages/stokes.md).
    #[param(flatten)]
    pub interface: InterfaceParams,
    #[param(flatten)]
    pub boundary: BoundaryParams,
    /// With `boundary: walls` along a non-periodic flow axis: fluid layers (the inlet and
    /// outlet reservoirs, joined through the periodic wrap) between the outlet and the
    /// inlet face, in voxels; the face pressures are extrapolated from the two layers next
    /// to each face.
    #[param(default = 6, ty = "integer 2..1000")]
    pub buffer_voxels: usize,
}

pub struct PermeabilityStage;

/// Every boundary: the permeameter is a flow boundary.
const BOUNDARIES: [Boundary; 3] = [Boundary::Periodic, Boundary::Mirror, Boundary::Walls];

/// One darcy [m^2].
pub const DARCY: f64 = 9.869_233e-13;

/// Extra bytes per voxel of the sub-voxel walls: f32 diagonals and force weights (24 in place
/// of the 3 diagonal bytes) and the fluid fractions (4).
/// The decoded sub-voxel geometry (4 (P + 3) bytes, up to five phases) is held while the
/// fractions are summed: 32 more.
pub const COMPOSITE_BYTES_PER_VOXEL: f64 = 24.0 - 3.0 + 4.0 + 32.0;

/// Bytes per voxel the stage holds at its peak when it keeps the solutions (and fields) of
/// `kept` load directions.
pub fn bytes_per_voxel(kept: usize, composite: bool) -> f64 {
    let extra = if composite {
        COMPOSITE_BYTES_PER_VOXEL
    } else {
        0.0
    };
    let solve = (BYTES_PER_VOXEL + extra).max(LABEL_BYTES_PER_VOXEL);
    // Kept solutions (16 B each): the earlier ones are held through the last solve; then
    // each becomes its fields (16 B) before it is dropped, the last one converted last.
    if kept > 0 {
        let k = kept as f64;
        (solve + 16.0 * (k - 1.0)).max(16.0 + FIELD_BYTES_PER_VOXEL * k) + 1.0
    } else {
        solve + 1.0
    }
}

fn available_memory() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = s.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

fn check_params(p: &PermeabilityParams) -> Result<(), StageError> {
    if p.directions.is_empty() {
        return Err(StageError::param(
            "directions",
            "give at least one of x, y, z",
        ));
    }
    for (i, a) in p.directions.iter().enumerate() {
        if p.directions[..i].contains(a) {
            return Err(StageError::param(
                "directions",
                format!("`{}` is listed twice", a.name()),
            ));
        }
    }
    if p.fluid.is_empty() {
        return Err(StageError::param("fluid", "give at least one fluid label"));
    }
    if !(p.viscosity.si() > 0.0 && p.viscosity.si().is_finite()) {
        return Err(StageError::param("viscosity", "must be positive"));
    }
    if !(p.pressure_drop.si() > 0.0 && p.pressure_drop.si().is_finite()) {
        return Err(StageError::param("pressure_drop", "must be positive"));
    }
    if !(p.tolerance >= crate::minres::MIN_TOLERANCE && p.tolerance < 1.0) {
        return Err(StageError::param(
            "tolerance",
            format!(
                "must be in [{:.0e}, 1); 1e-5 is usual (the solver's vectors are single \
                 precision: below about 1e-7 the residual is round-off)",
                crate::minres::MIN_TOLERANCE
            ),
        ));
    }
    if p.max_iterations == 0 || p.max_iterations > 100_000 {
        return Err(StageError::param("max_iterations", "must be in 1..100000"));
    }
    if !(p.memory_limit_gib >= 0.0 && p.memory_limit_gib.is_finite()) {
        return Err(StageError::param(
            "memory_limit_gib",
            "must be 0 (available memory) or positive",
        ));
    }
    if !(p.over_correction >= 1.0 && p.over_correction <= 2.0) {
        return Err(StageError::param("over_correction", "must be in [1, 2]"));
    }
    if !(MIN_BUFFER..=1000).contains(&p.buffer_voxels) {
        return Err(StageError::param(
            "buffer_voxels",
            format!(
                "must be in {MIN_BUFFER}..1000 (each face pressure is extrapolated from two \
                 buffer layers), got {}",
                p.buffer_voxels
            ),
        ));
    }
    Ok(())
}

/// Voxels of the largest cell solved: the image, mirrored or padded for the permeameter.
fn solved_voxels(p: &PermeabilityParams, bc: &ResolvedBoundary, grid: &Grid) -> u64 {
    match bc.boundary {
        Boundary::Walls => p
            .directions
            .iter()
            .map(|a| {
                WallsLayout::new(grid.dims, grid.periodic, a.index(), p.buffer_voxels).padded_len()
                    as u64
            })
            .max()
            .unwrap_or(0),
        _ => bc.solved_grid(grid).voxel_count() as u64,
    }
}

fn check_grid(grid: &Grid) -> Result<(), StageError> {
    let h = grid.spacing[0];
    if grid.spacing.iter().any(|&s| (s / h - 1.0).abs() > 1e-6) {
        return Err(StageError::input(
            "image",
            format!(
                "voxels must be cubes for the MAC scheme, got spacing {:?} m",
                grid.spacing
            ),
        ));
    }
    if grid.voxel_count() == 0 {
        return Err(StageError::input("image", "the image has no voxels"));
    }
    if grid.voxel_count() >= u32::MAX as usize {
        return Err(StageError::input(
            "image",
            "more than 2^32 voxels; coarsen the voxel size",
        ));
    }
    Ok(())
}

impl TypedStage for PermeabilityStage {
    type Params = PermeabilityParams;
    type Plan = Grid;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "stokes.permeability",
            "1.4.0",
            "Apparent permeability tensor of a periodic voxel pore space (Donval et al. 2025, \
             section 3.3, eq. 3.6-3.8): for a body force f along each load direction, the \
             periodic Stokes flow mu Lap u - grad p = -f, div u = 0 with u = 0 on the solid is \
             solved and kappa follows from the cell average <u>_Y = kappa f / mu. Staggered \
             (MAC) finite volumes on the voxels: a face carries a velocity when both voxels \
             beside it are fluid; u = 0 on every face touching a solid voxel, and where the \
             faces beside a velocity lie inside the solid the wall is the voxel face half a \
             cell away (ghost value -u). The symmetric saddle-point system is solved by MINRES \
             with a block-diagonal preconditioner: one symmetric geometric-multigrid V-cycle \
             (Galerkin 2x2x2 aggregation, red-black Gauss-Seidel) per velocity component and \
             for the Schur complement the pressure mass matrix / mu plus one V-cycle of a \
             pressure Laplacian weighted by the local wall resistance (Cahouet-Chabard); \
             iteration counts grow only slowly under refinement. Pore components that connect to no periodic \
             image of themselves are excluded; a direction along which nothing percolates \
             gets kappa = 0 with a note, without a solve. With interfaces: composite the walls \
             sit inside the voxels from their fluid fractions (subvoxel input, or coarsen: 2|4 \
             of the image): the wall distance of each velocity next to the solid enters the \
             diagonal (symmetric rule of Gibou et al. 2002) and the body force is weighted by \
             the dual-cell extent, the system staying symmetric. Memory: about 117 bytes per \
             voxel (142 with composite walls; f32 vectors); the stage refuses an image that \
             does not fit. An image that is not periodic (a scan) needs a boundary: walls (the \
             permeameter: no-slip walls beside the flow, inlet and outlet buffer layers, kappa \
             from the flow rate and the pressure drop between the faces), mirror (the image \
             reflected across its non-periodic axes) or periodic (faces glued, warned).",
        )
        .inputs(vec![
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "phase image with cubic voxels, periodic or with `boundary:`; `fluid` labels are pore",
            ),
            PortSpec::optional(
                "subvoxel",
                ArtifactKind::Field,
                "with interfaces: composite, the image's sub-voxel field (phase fractions and \
                 normals, P + 3 components) from which the fluid fractions are summed",
            ),
        ])
        .outputs(vec![
            PortSpec::new(
                "permeability",
                ArtifactKind::Tensor,
                "3x3 apparent permeability kappa_ij = mu <u_i>_Y / f_j in m^2 (columns of \
                 directions not solved are NaN)",
            ),
            PortSpec::new(
                "report",
                ArtifactKind::Table,
                "per load direction: kappa (m^2, darcy), Darcy and mean pore velocity, \
                 iterations, residuals, mass error, porosity, the anisotropy kappa_zz / \
                 mean(kappa_xx, kappa_yy) - 1 (NaN unless x, y and z ran), note",
            ),
            PortSpec::new(
                "history",
                ArtifactKind::Table,
                "relative MINRES residual per iteration and load direction",
            ),
            PortSpec::optional(
                "velocity",
                ArtifactKind::Field,
                "with fields: true, the voxel-centred velocity (m/s) of the first direction",
            ),
            PortSpec::optional(
                "pressure",
                ArtifactKind::Field,
                "with fields: true, the periodic pressure (Pa) of the first direction (walls: the total pressure, relative to the outlet face)",
            ),
            PortSpec::optional(
                "velocities",
                ArtifactKind::Collection,
                "with fields: true and field_directions: all, the velocity field (m/s) of every \
                 direction solved, members named x, y, z",
            ),
            PortSpec::optional(
                "pressures",
                ArtifactKind::Collection,
                "with fields: true and field_directions: all, the pressure field (Pa) of every \
                 direction solved, members named x, y, z",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &PermeabilityParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<Grid>, StageError> {
        check_params(p)?;
        let fine = grainpipe_core::announced_grid(inputs, "image")?;
        check_grid(&fine)?;
        // The grid solved on (coarsened or not), the sub-voxel settings checked.
        let grid = p.interface.check(inputs.get("subvoxel"), &fine)?;
        let bc = p.boundary.resolve(grid.periodic, &BOUNDARIES)?;
        let solved = solved_voxels(p, &bc, &grid);
        if solved >= u32::MAX as u64 {
            return Err(StageError::param(
                "boundary",
                format!(
                    "`{}` solves a cell of {solved} voxels, more than the solver's 2^32; \
                     coarsen the voxel size or crop the image",
                    bc.boundary.name()
                ),
            ));
        }
        let n = solved as f64;
        let composite = p.interface.interfaces == Interfaces::Composite;
        // The permeameter keeps each direction's solution to read its faces (one at a time).
        let kept = match (p.fields, p.field_directions) {
            (true, FieldDirections::All) => p.directions.len(),
            (true, FieldDirections::First) => 1,
            (false, _) => usize::from(bc.boundary == Boundary::Walls),
        };
        let bpv = bytes_per_voxel(kept, composite);
        // Coarsening holds the fine image while the coarse one and its fractions are built;
        // the mirrored or padded pore space (4 bytes a voxel) is built beside the image's.
        let bytes = bpv * n
            + if p.interface.coarsen > 1 {
                fine.voxel_count() as f64
            } else {
                0.0
            }
            + if n > grid.voxel_count() as f64 {
                4.0 * n
            } else {
                0.0
            };
        let limit = if p.memory_limit_gib > 0.0 {
            Some(p.memory_limit_gib * (1u64 << 30) as f64)
        } else {
            available_memory().map(|b| b as f64)
        };
        if let Some(limit) = limit {
            if bytes > limit {
                let fit = limit / bpv;
                let s = (fit / n).cbrt();
                let dims = grid.dims.map(|d| ((d as f64 * s).floor() as usize).max(1));
                return Err(StageError::input(
                    "image",
                    format!(
                        "{}x{}x{} voxels need {:.1} GiB ({bpv:.0} bytes per voxel) but {:.1} GiB \
                         are available; a voxel size of {:.3e} m or more ({}x{}x{} voxels) fits",
                        grid.dims[0],
                        grid.dims[1],
                        grid.dims[2],
                        bytes / (1u64 << 30) as f64,
                        limit / (1u64 << 30) as f64,
                        grid.spacing[0] / s,
                        dims[0],
                        dims[1],
                        dims[2]
                    ),
                ));
            }
        }
        let cases = p.directions.len() as u64;
        let mut pf = Preflight::from_info(&self.info(), bytes as u64)
            .announce(
                "permeability",
                ArtifactMeta::of(ArtifactKind::Tensor).with_count(9, Some([9, 9])),
            )
            .announce(
                "report",
                ArtifactMeta::of(ArtifactKind::Table).with_count(cases, Some([cases, cases])),
            )
            .announce(
                "history",
                ArtifactMeta::of(ArtifactKind::Table)
                    .with_count(cases * 60, Some([0, cases * p.max_iterations as u64])),
            );
        let (single, every) = match (p.fields, p.field_directions) {
            (false, _) => (false, false),
            (true, FieldDirections::First) => (true, false),
            (true, FieldDirections::All) => (false, true),
        };
        if single {
            pf = pf
                .announce(
                    "velocity",
                    ArtifactMeta::on_grid(ArtifactKind::Field, grid.clone()),
                )
                .announce(
                    "pressure",
                    ArtifactMeta::on_grid(ArtifactKind::Field, grid.clone()),
                );
        } else {
            pf.outputs.retain(|k, _| k != "velocity" && k != "pressure");
        }
        if every {
            let n = cases;
            for port in ["velocities", "pressures"] {
                pf = pf.announce(
                    port,
                    ArtifactMeta::of(ArtifactKind::Collection).with_count(n, Some([n, n])),
                );
            }
        } else {
            pf.outputs
                .retain(|k, _| k != "velocities" && k != "pressures");
        }
        Ok(pf.with_plan(grid))
    }

    fn run(
        &self,
        p: &PermeabilityParams,
        _grid: &Grid,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let image_in = input(inputs, "image", Artifact::as_phase_image)?;
        check_grid(&image_in.grid)?;
        // Sub-voxel walls: the fluid fraction per voxel, on the grid solved on.
        let field = InterfaceParams::subvoxel_input(inputs)?;
        let (image, subvoxel) = p
            .interface
            .prepare(image_in, field)
            .map_err(|e| StageError::input("subvoxel", e))?;
        let fraction: Option<Vec<f32>> = if let Some(sv) = subvoxel {
            let img = image.as_ref();
            let fluid_phase: Vec<bool> = img
                .phases
                .iter()
                .map(|ph| p.fluid.contains(&ph.id))
                .collect();
            let np = sv.phases;
            let f: Vec<f32> = sv
                .fractions
                .chunks(np)
                .map(|fr| {
                    fr.iter()
                        .zip(&fluid_phase)
                        .filter(|(_, &fl)| fl)
                        .map(|(&x, _)| x)
                        .sum::<f32>()
                        .clamp(0.0, 1.0)
                })
                .collect();
            let mixed = f.iter().filter(|&&x| x > 0.0 && x < 1.0).count();
            ctx.info(&format!(
                "sub-voxel walls: {mixed} of {} voxels hold fluid and solid{}",
                f.len(),
                if p.interface.coarsen > 1 {
                    format!(" (image coarsened by {})", p.interface.coarsen)
                } else {
                    String::new()
                }
            ));
            Some(f)
        } else {
            if inputs.contains_key("subvoxel") {
                ctx.info("interfaces: labels: the subvoxel input is not used");
            }
            None
        };
        let image = image.as_ref();
        let grid = &image.grid;
        let bc = p.boundary.resolve(grid.periodic, &BOUNDARIES)?;
        if let Some(w) = bc.warning() {
            ctx.warn(&w);
        }
        let pore = match fraction {
            Some(f) => PoreSpace::Fractions(f),
            None => {
                let mut lut = [false; 256];
                for &l in &p.fluid {
                    lut[l as usize] = true;
                }
                PoreSpace::Labels(image.labels.iter().map(|&l| lut[l as usize]).collect())
            }
        };
        let axes: Vec<usize> = p.directions.iter().map(|a| a.index()).collect();
        let settings = SolverSettings {
            tolerance: p.tolerance,
            max_iterations: p.max_iterations as usize,
            cycle: CycleSettings {
                over_correction: p.over_correction as f32,
                ..CycleSettings::default()
            },
        };
        // Progress by each direction's residual against the tolerance (the cases may run
        // out of order: the one whose fields are kept runs last).
        let residuals = ResidualProgress::new(axes.len(), p.tolerance);
        let field_axes: &[usize] = match (p.fields, p.field_directions) {
            (false, _) => &[],
            (true, FieldDirections::First) => &axes[..1],
            (true, FieldDirections::All) => &axes,
        };
        let mut monitor = |case: usize, _it: usize, residual: f64| {
            ctx.residual_progress(&residuals, case, residual)
        };
        let flow = match bc.boundary {
            Boundary::Walls => solve_walls(
                &pore,
                grid,
                &axes,
                p.buffer_voxels,
                settings,
                field_axes,
                ctx,
                &mut monitor,
            )?,
            _ => solve_cell(
                pore,
                grid,
                &bc,
                &axes,
                settings,
                field_axes,
                ctx,
                &mut monitor,
            )?,
        };
        let h = grid.spacing[0];
        let extent = grid.extent();
        let mu = p.viscosity.si();
        // kappa in voxel units times h^2 (eq. (3.8) with mu = f = h = 1).
        let mut tensor = [[f64::NAN; 3]; 3];
        for c in &flow.cases {
            for (i, row) in tensor.iter_mut().enumerate() {
                row[c.axis] = flow.kappa[i][c.axis] * h * h;
            }
        }
        // The permeameter measures no off-diagonal entries.
        let sym = if axes.len() == 3 && bc.boundary != Boundary::Walls {
            symmetry_error(&tensor)
        } else {
            f64::NAN
        };
        // kappa_zz below the in-plane permeabilities (Donval et al. 2025, section 4.4); NaN
        // unless x, y and z were solved (unsolved columns are NaN).
        let anisotropy_z = tensor[2][2] / (0.5 * (tensor[0][0] + tensor[1][1])) - 1.0;
        let mut names = Vec::new();
        let (mut k_si, mut k_d, mut u_darcy, mut u_pore) = (vec![], vec![], vec![], vec![]);
        let (mut iters, mut resid, mut true_res, mut mass, mut perc, mut notes) =
            (vec![], vec![], vec![], vec![], vec![], vec![]);
        let (mut flow_rate, mut imbalance) = (vec![], vec![]);
        let (mut h_dir, mut h_it, mut h_res) = (vec![], vec![], vec![]);
        for (ci, c) in flow.cases.iter().enumerate() {
            let a = c.axis;
            let kappa = tensor[a][a];
            // eq. (3.8): <u>_Y = kappa f / mu with f = pressure drop / cell length.
            let f = p.pressure_drop.si() / extent[a];
            let ud = kappa * f / mu;
            if !ud.is_finite() {
                return Err(StageError::failed(format!(
                    "the Darcy velocity along {} is {ud} m/s for kappa = {kappa:.3e} m^2: check \
                     the units of `viscosity` ({mu:.3e} Pa s) and `pressure_drop`",
                    ["x", "y", "z"][a]
                )));
            }
            names.push(["x", "y", "z"][a].to_string());
            k_si.push(kappa);
            k_d.push(kappa / DARCY);
            u_darcy.push(ud);
            // Through the sample's cross-section (the cell's, for periodic and mirror).
            flow_rate.push(ud * extent[(a + 1) % 3] * extent[(a + 2) % 3]);
            imbalance.push(flow.permeameter[ci].map_or(f64::NAN, |m| m.imbalance));
            u_pore.push(if flow.connected_porosity > 0.0 {
                ud / flow.connected_porosity
            } else {
                0.0
            });
            iters.push(c.iterations as i64);
            resid.push(c.residual);
            true_res.push(c.true_residual);
            mass.push(c.mass_error);
            perc.push(i64::from(flow.percolation.percolates[a]));
            notes.push(c.note.clone().unwrap_or_default());
            if let Some(n) = &c.note {
                ctx.warn(n);
            }
            for &(it, r) in &c.history {
                h_dir.push(["x", "y", "z"][a].to_string());
                h_it.push(it as i64);
                h_res.push(r);
            }
            ctx.info(&format!(
                "{}: kappa = {kappa:.4e} m^2 ({:.4} darcy) in {} iterations, residual {:.2e}, \
                 mass error {:.2e}{}",
                ["x", "y", "z"][a],
                kappa / DARCY,
                c.iterations,
                c.true_residual,
                c.mass_error,
                flow.permeameter[ci].map_or(String::new(), |m| format!(
                    ", permeameter: inlet/outlet flow rates differ by {:.2e}",
                    m.imbalance
                ))
            ));
        }
        if flow.percolation.isolated > 0 {
            ctx.info(&format!(
                "{} of {} fluid voxels lie in pore components that do not percolate and were \
                 excluded",
                flow.percolation.isolated,
                flow.percolation.isolated + flow.percolation.kept
            ));
        }
        let ncase = names.len();
        let report = Table::new("permeability")
            .with_str("direction", names)
            .with_f64("kappa", "m^2", k_si)
            .with_f64("kappa_darcy", "D", k_d)
            .with_f64("darcy_velocity", "m/s", u_darcy)
            .with_f64("pore_velocity", "m/s", u_pore)
            .with_f64("flow_rate", "m^3/s", flow_rate)
            .with_f64("mass_balance", "1", imbalance)
            .with_i64("iterations", "1", iters)
            .with_f64("residual", "1", resid)
            .with_f64("true_residual", "1", true_res)
            .with_f64("mass_error", "1", mass)
            .with_f64("porosity", "1", vec![flow.porosity; ncase])
            .with_f64(
                "connected_porosity",
                "1",
                vec![flow.connected_porosity; ncase],
            )
            .with_i64("percolates", "1", perc)
            .with_f64("symmetry_error", "1", vec![sym; ncase])
            .with_f64("anisotropy_z", "1", vec![anisotropy_z; ncase])
            .with_str("note", notes);
        let history = Table::new("history")
            .with_str("direction", h_dir)
            .with_i64("iteration", "1", h_it)
            .with_f64("residual", "1", h_res);
        let mut out = Outputs::new();
        out.insert(
            "permeability".into(),
            Artifact::Tensor(Tensor {
                name: "permeability".into(),
                unit: "m^2".into(),
                shape: vec![3, 3],
                values: tensor.iter().flatten().copied().collect(),
                convention: TensorConvention::Plain,
            }),
        );
        out.insert("report".into(), Artifact::Table(report));
        out.insert("history".into(), Artifact::Table(history));
        let field = |name: &str, unit: &str, conv, data| {
            Field::new(grid.clone(), name, unit, conv, FieldData::F32(data))
                .map_err(StageError::failed)
        };
        let (mut velocities, mut pressures) = (Collection::default(), Collection::default());
        for (a, fields) in &flow.fields {
            // Voxel units to SI: the body force f that gives the sample `pressure_drop`
            // (u scales with f h^2 / mu, p with f h).
            let f = p.pressure_drop.si() / (h * fields.pressure_drop);
            let (us, ps) =
                single_precision_scales(f * h * h / mu, f * h, &fields.velocity, &fields.pressure)?;
            let vel = fields.velocity.iter().map(|v| v * us).collect();
            let pre = fields.pressure.iter().map(|v| v * ps).collect();
            let name = ["x", "y", "z"][*a];
            let (vname, pname) = match p.field_directions {
                FieldDirections::First => ("velocity".to_string(), "pressure".to_string()),
                FieldDirections::All => (format!("velocity_{name}"), format!("pressure_{name}")),
            };
            let v = field(&vname, "m/s", ComponentConvention::Vector, vel)?;
            let pr = field(&pname, "Pa", ComponentConvention::Plain, pre)?;
            velocities
                .items
                .push((name.to_string(), Artifact::Field(v)));
            pressures
                .items
                .push((name.to_string(), Artifact::Field(pr)));
        }
        match (p.fields, p.field_directions) {
            (false, _) => {}
            (true, FieldDirections::First) => {
                let (_, v) = velocities.items.remove(0);
                let (_, pr) = pressures.items.remove(0);
                out.insert("velocity".into(), v);
                out.insert("pressure".into(), pr);
            }
            (true, FieldDirections::All) => {
                out.insert("velocities".into(), Artifact::Collection(velocities));
                out.insert("pressures".into(), Artifact::Collection(pressures));
            }
        }
        Ok(out)
    }
}

/// The factors from voxel units to m/s and Pa for the f32 fields, refused when the largest
/// value would not fit single precision (inf velocities were exported with exit 0 for a
/// viscosity of 1e-60 Pa s).
fn single_precision_scales(
    velocity_scale: f64,
    pressure_scale: f64,
    velocity: &[f32],
    pressure: &[f32],
) -> Result<(f32, f32), StageError> {
    let largest = |v: &[f32]| v.iter().fold(0.0f64, |m, x| m.max(f64::from(x.abs())));
    for (name, unit, scale, values) in [
        ("velocity", "m/s", velocity_scale, velocity),
        ("pressure", "Pa", pressure_scale, pressure),
    ] {
        let top = largest(values) * scale.abs();
        if !(scale.is_finite() && top < f64::from(f32::MAX)) {
            return Err(StageError::failed(format!(
                "the {name} field reaches {top:.3e} {unit}, beyond single precision: check the \
                 units of `viscosity` and `pressure_drop` (kappa does not depend on them)"
            )));
        }
    }
    Ok((velocity_scale as f32, pressure_scale as f32))
}

/// Voxel-centred velocity (mean of the two faces along each axis, component fastest) and
/// pressure, scaled from voxel units.
fn voxel_fields(dims: Dims, x: &[f32], u_scale: f64, p_scale: f64) -> (Vec<f32>, Vec<f32>) {
    use rayon::prelude::*;
    let n = dims.len();
    let mut vel = vec![0f32; 3 * n];
    let (us, ps) = (u_scale as f32, p_scale as f32);
    vel.par_chunks_mut(3).enumerate().for_each(|(i, v)| {
        let [cx, cy, cz] = dims.coords(i);
        let nb = dims.neighbours(cx, cy, cz);
        for a in 0..3 {
            v[a] = 0.5 * (x[a * n + i] + x[a * n + nb[2 * a]]) * us;
        }
    });
    let pre = x[3 * n..].par_iter().map(|&v| v * ps).collect();
    (vel, pre)
}

/// The pore space solved: the fluid labels or the sub-voxel fluid fractions, one value per
/// voxel.
enum PoreSpace {
    Labels(Vec<bool>),
    Fractions(Vec<f32>),
}

impl PoreSpace {
    fn porosity(&self) -> f64 {
        match self {
            PoreSpace::Labels(f) => f.iter().filter(|&&x| x).count() as f64 / f.len() as f64,
            PoreSpace::Fractions(f) => f.iter().map(|&x| x as f64).sum::<f64>() / f.len() as f64,
        }
    }

    fn mirrored(&self, dims: [usize; 3], axes: [bool; 3]) -> PoreSpace {
        match self {
            PoreSpace::Labels(f) => PoreSpace::Labels(mirror(f, 1, dims, axes)),
            PoreSpace::Fractions(f) => PoreSpace::Fractions(mirror(f, 1, dims, axes)),
        }
    }

    fn padded(&self, layout: &WallsLayout) -> PoreSpace {
        match self {
            PoreSpace::Labels(f) => PoreSpace::Labels(layout.pad(f, false, true)),
            PoreSpace::Fractions(f) => PoreSpace::Fractions(layout.pad(f, 0.0, 1.0)),
        }
    }

    fn solve<M>(
        self,
        dims: [usize; 3],
        axes: &[usize],
        settings: SolverSettings,
        keep: &[usize],
        monitor: M,
    ) -> Result<crate::solver::Permeability, StageError>
    where
        M: FnMut(usize, usize, f64) -> Result<(), StageError>,
    {
        let d = Dims::new(dims);
        let r = match self {
            PoreSpace::Labels(f) => permeability(d, f, axes, settings, keep, monitor)?,
            PoreSpace::Fractions(f) => {
                permeability_composite(d, &f, axes, settings, keep, monitor)?
            }
        };
        r.map_err(|e| match e {
            SolveError::NoSolid => StageError::input("image", e.to_string()),
            _ => StageError::failed(e.to_string()),
        })
    }
}

/// The flow solved, in voxel units (h = mu = 1), on the image's grid.
struct Flow {
    percolation: Percolation,
    /// kappa / h^2 (columns of directions not solved, and the permeameter's off-diagonal
    /// entries, are NaN).
    kappa: [[f64; 3]; 3],
    cases: Vec<crate::solver::LoadCase>,
    porosity: f64,
    connected_porosity: f64,
    /// The permeameter's reading per case (`boundary: walls`).
    permeameter: Vec<Option<crate::walls::Permeameter>>,
    /// The fields of the directions asked for, by axis, in the order of `directions`.
    fields: Vec<(usize, VoxelFields)>,
}

/// Voxel-centred velocity and pressure of one direction on the image's grid, in voxel
/// units, with the pressure drop across the sample they belong to.
struct VoxelFields {
    velocity: Vec<f32>,
    pressure: Vec<f32>,
    pressure_drop: f64,
}

/// The periodic cell problem on the image (`periodic`) or on its mirrored cell (`mirror`).
#[allow(clippy::too_many_arguments)]
fn solve_cell<M>(
    pore: PoreSpace,
    grid: &Grid,
    bc: &ResolvedBoundary,
    axes: &[usize],
    settings: SolverSettings,
    fields: &[usize],
    ctx: &RunContext,
    monitor: M,
) -> Result<Flow, StageError>
where
    M: FnMut(usize, usize, f64) -> Result<(), StageError>,
{
    let dims = grid.dims;
    let (pore, cell) = if bc.voxel_factor() > 1 {
        let cell = grainpipe_core::boundary::mirrored_dims(dims, bc.mirror);
        ctx.info(&format!(
            "boundary: mirror: the pore space reflected across {} ({}x{}x{} voxels)",
            grainpipe_core::boundary::axis_list(bc.mirror),
            cell[0],
            cell[1],
            cell[2]
        ));
        (pore.mirrored(dims, bc.mirror), cell)
    } else {
        (pore, dims)
    };
    let mut res = pore.solve(cell, axes, settings, fields, monitor)?;
    let d = Dims::new(cell);
    let fields = fields
        .iter()
        .map(|&a| {
            let solution = res
                .cases
                .iter_mut()
                .find(|c| c.axis == a)
                .and_then(|c| c.solution.take());
            let (velocity, pressure) = match solution {
                Some(x) => voxel_fields(d, &x, 1.0, 1.0),
                // A direction that does not percolate has no flow.
                None => (vec![0f32; 3 * d.len()], vec![0f32; d.len()]),
            };
            let f = VoxelFields {
                velocity: crop_lower(&velocity, 3, cell, dims),
                pressure: crop_lower(&pressure, 1, cell, dims),
                // A unit body force: the drop along the sample is its length.
                pressure_drop: dims[a] as f64,
            };
            (a, f)
        })
        .collect();
    Ok(Flow {
        permeameter: vec![None; res.cases.len()],
        percolation: res.percolation,
        kappa: res.kappa,
        cases: res.cases,
        porosity: res.porosity,
        connected_porosity: res.connected_porosity,
        fields,
    })
}

/// The permeameter (`walls`): each direction solved on its own padded cell
/// ([`WallsLayout`]) and read at the sample's inlet and outlet faces.
#[allow(clippy::too_many_arguments)]
fn solve_walls<M>(
    pore: &PoreSpace,
    grid: &Grid,
    axes: &[usize],
    buffer: usize,
    settings: SolverSettings,
    fields: &[usize],
    ctx: &RunContext,
    mut monitor: M,
) -> Result<Flow, StageError>
where
    M: FnMut(usize, usize, f64) -> Result<(), StageError>,
{
    let dims = grid.dims;
    let n = dims.iter().product::<usize>() as f64;
    let mut kappa = [[f64::NAN; 3]; 3];
    let (mut cases, mut meters) = (vec![], vec![]);
    let mut percolation: Option<Percolation> = None;
    let mut percolates = [false; 3];
    let mut out_fields = Vec::new();
    for (k, &a) in axes.iter().enumerate() {
        let layout = WallsLayout::new(dims, grid.periodic, a, buffer);
        if k == 0 {
            ctx.info(&format!(
                "boundary: walls: no-slip walls across {}{}",
                match grainpipe_core::boundary::axis_list(layout.walls) {
                    w if w.is_empty() => "no axis".to_string(),
                    w => w,
                },
                if layout.buffer > 0 {
                    format!(", {} buffer layers along the flow", layout.buffer)
                } else {
                    String::new()
                }
            ));
        }
        let padded = pore.padded(&layout);
        let mut res = padded.solve(layout.padded, &[a], settings, &[a], |_, it, r| {
            monitor(k, it, r)
        })?;
        let mut case = res.cases.remove(0);
        let meter = case.solution.take().map(|x| {
            let m = layout.apparent(&x, res.kappa[a][a]);
            if fields.contains(&a) {
                out_fields.push((a, walls_fields(&layout, &x, &m)));
            }
            m
        });
        if fields.contains(&a) && meter.is_none() {
            // The direction does not percolate: no flow.
            let n = n as usize;
            out_fields.push((
                a,
                VoxelFields {
                    velocity: vec![0.0; 3 * n],
                    pressure: vec![0.0; n],
                    pressure_drop: 1.0,
                },
            ));
        }
        kappa[a][a] = meter.map_or(0.0, |m| m.kappa);
        percolates[a] = res.percolation.percolates[a];
        // The sample's share of the kept pore space: through a percolating sample the buffer
        // belongs to the kept component.
        if percolation
            .as_ref()
            .is_none_or(|p| percolates[a] && !p.percolates[a])
        {
            let mut p = res.percolation;
            if percolates[a] {
                p.kept = p.kept.saturating_sub(layout.buffer_voxels());
            }
            percolation = Some(p);
        }
        cases.push(case);
        meters.push(meter);
    }
    let mut percolation = percolation.expect("at least one direction");
    percolation.percolates = percolates;
    Ok(Flow {
        connected_porosity: percolation.kept as f64 / n,
        percolation,
        kappa,
        cases,
        porosity: pore.porosity(),
        permeameter: meters,
        fields: out_fields,
    })
}

/// The permeameter's fields on the sample: velocity, and the total pressure P = p - f x
/// relative to the outlet face (so it reads the pressure drop at the inlet face).
fn walls_fields(layout: &WallsLayout, x: &[f32], m: &crate::walls::Permeameter) -> VoxelFields {
    let d = Dims::new(layout.padded);
    let (velocity, mut pressure) = voxel_fields(d, x, 1.0, 1.0);
    let a = layout.flow;
    for (i, p) in pressure.iter_mut().enumerate() {
        let c = d.coords(i)[a] as f64;
        *p = (*p as f64 - (c + 0.5) - m.outlet_pressure) as f32;
    }
    VoxelFields {
        velocity: crop_lower(&velocity, 3, layout.padded, layout.sample),
        pressure: crop_lower(&pressure, 1, layout.padded, layout.sample),
        pressure_drop: m.pressure_drop,
    }
}
