//! `stokes.permeability`: apparent permeability tensor of a periodic voxel pore space
//! (Donval et al. 2025, section 3.3, eq. 3.6-3.8).

use crate::mac::Dims;
use crate::multigrid::CycleSettings;
use crate::solver::{
    permeability, permeability_composite, symmetry_error, SolveError, SolverSettings,
    BYTES_PER_VOXEL, FIELD_BYTES_PER_VOXEL, LABEL_BYTES_PER_VOXEL,
};
use grainpipe_core::subvoxel::{InterfaceParams, Interfaces};
use grainpipe_core::units::{Pressure, Viscosity, Q};
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, ComponentConvention, Field, FieldData,
    Grid, InputMetas, Inputs, Outputs, ParamChoice, PortSpec, Preflight, RunContext, StageError,
    StageInfo, Table, Tensor, TensorConvention, TypedStage,
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
    /// Also output the velocity and pressure fields (voxel centred) of the first load direction.
    #[param(default = false)]
    pub fields: bool,
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
}

pub struct PermeabilityStage;

/// One darcy [m^2].
pub const DARCY: f64 = 9.869_233e-13;

/// Extra bytes per voxel of the sub-voxel walls: f32 diagonals and force weights (24 in place
/// of the 3 diagonal bytes) and the fluid fractions (4).
/// The decoded sub-voxel geometry (4 (P + 3) bytes, up to five phases) is held while the
/// fractions are summed: 32 more.
pub const COMPOSITE_BYTES_PER_VOXEL: f64 = 24.0 - 3.0 + 4.0 + 32.0;

/// Bytes per voxel the stage holds at its peak.
pub fn bytes_per_voxel(fields: bool, composite: bool) -> f64 {
    let extra = if composite {
        COMPOSITE_BYTES_PER_VOXEL
    } else {
        0.0
    };
    let solve = (BYTES_PER_VOXEL + extra).max(LABEL_BYTES_PER_VOXEL);
    // The kept solution (16 B) and the fields (16 B) outlive the other solver vectors.
    if fields {
        solve.max(16.0 + FIELD_BYTES_PER_VOXEL) + 1.0
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
    if !(p.tolerance > 0.0 && p.tolerance < 1.0) {
        return Err(StageError::param(
            "tolerance",
            "must be in (0, 1); 1e-5 is usual (f32 vectors reach about 1e-7)",
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
    Ok(())
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
            "1.2.0",
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
             does not fit.",
        )
        .inputs(vec![
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "phase image with cubic voxels, treated as periodic; `fluid` labels are pore",
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
                "with fields: true, the periodic pressure (Pa) of the first direction",
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
        let n = grid.voxel_count() as f64;
        let composite = p.interface.interfaces == Interfaces::Composite;
        let bpv = bytes_per_voxel(p.fields, composite);
        // Coarsening holds the fine image while the coarse one and its fractions are built.
        let bytes = bpv * n
            + if p.interface.coarsen > 1 {
                fine.voxel_count() as f64
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
        if p.fields {
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
        if !grid.periodic.iter().all(|&b| b) {
            ctx.warn(&format!(
                "the image is periodic along {:?} only; the cell problem treats it as periodic \
                 along every axis",
                grid.periodic
            ));
        }
        let dims = Dims::new(grid.dims);
        let axes: Vec<usize> = p.directions.iter().map(|a| a.index()).collect();
        let settings = SolverSettings {
            tolerance: p.tolerance,
            max_iterations: p.max_iterations as usize,
            cycle: CycleSettings {
                over_correction: p.over_correction as f32,
                ..CycleSettings::default()
            },
        };
        let total = (axes.len() * p.max_iterations as usize) as u64;
        let maxit = p.max_iterations as u64;
        let keep = if p.fields { Some(axes[0]) } else { None };
        // Cases may run out of order (the one whose fields are kept runs last): count them.
        let mut seen: (Option<usize>, u64) = (None, 0);
        let monitor = |case: usize, it: usize, _: f64| {
            if seen.0 != Some(case) {
                seen = (Some(case), seen.1 + 1);
            }
            ctx.progress((seen.1 - 1) * maxit + it as u64, total)
        };
        let result = match &fraction {
            Some(f) => permeability_composite(dims, f, &axes, settings, keep, monitor)?,
            None => {
                let mut lut = [false; 256];
                for &l in &p.fluid {
                    lut[l as usize] = true;
                }
                let is_fluid: Vec<bool> = image.labels.iter().map(|&l| lut[l as usize]).collect();
                permeability(dims, is_fluid, &axes, settings, keep, monitor)?
            }
        };
        drop(fraction);
        let res = result.map_err(|e| match e {
            SolveError::NoSolid => StageError::input("image", e.to_string()),
            _ => StageError::failed(e.to_string()),
        })?;
        let h = grid.spacing[0];
        let extent = grid.extent();
        let mu = p.viscosity.si();
        // kappa in voxel units times h^2 (eq. (3.8) with mu = f = h = 1).
        let mut tensor = [[f64::NAN; 3]; 3];
        for c in &res.cases {
            for (i, row) in tensor.iter_mut().enumerate() {
                row[c.axis] = res.kappa[i][c.axis] * h * h;
            }
        }
        let sym = if axes.len() == 3 {
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
        let (mut h_dir, mut h_it, mut h_res) = (vec![], vec![], vec![]);
        for c in &res.cases {
            let a = c.axis;
            let kappa = tensor[a][a];
            // eq. (3.8): <u>_Y = kappa f / mu with f = pressure drop / cell length.
            let f = p.pressure_drop.si() / extent[a];
            let ud = kappa * f / mu;
            names.push(["x", "y", "z"][a].to_string());
            k_si.push(kappa);
            k_d.push(kappa / DARCY);
            u_darcy.push(ud);
            u_pore.push(if res.connected_porosity > 0.0 {
                ud / res.connected_porosity
            } else {
                0.0
            });
            iters.push(c.iterations as i64);
            resid.push(c.residual);
            true_res.push(c.true_residual);
            mass.push(c.mass_error);
            perc.push(i64::from(res.percolation.percolates[a]));
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
                 mass error {:.2e}",
                ["x", "y", "z"][a],
                kappa / DARCY,
                c.iterations,
                c.true_residual,
                c.mass_error
            ));
        }
        if res.percolation.isolated > 0 {
            ctx.info(&format!(
                "{} of {} fluid voxels lie in pore components that do not percolate and were \
                 excluded",
                res.percolation.isolated,
                res.percolation.isolated + res.percolation.kept
            ));
        }
        let ncase = names.len();
        let report = Table::new("permeability")
            .with_str("direction", names)
            .with_f64("kappa", "m^2", k_si)
            .with_f64("kappa_darcy", "D", k_d)
            .with_f64("darcy_velocity", "m/s", u_darcy)
            .with_f64("pore_velocity", "m/s", u_pore)
            .with_i64("iterations", "1", iters)
            .with_f64("residual", "1", resid)
            .with_f64("true_residual", "1", true_res)
            .with_f64("mass_error", "1", mass)
            .with_f64("porosity", "1", vec![res.porosity; ncase])
            .with_f64(
                "connected_porosity",
                "1",
                vec![res.connected_porosity; ncase],
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
        if p.fields {
            let a = axes[0];
            let f = p.pressure_drop.si() / extent[a];
            let n = dims.len();
            let (vel, pre) = match res.cases.iter().find_map(|c| c.solution.as_ref()) {
                Some(x) => voxel_fields(dims, x, f * h * h / mu, f * h),
                // A direction that was not solved has no flow.
                None => (vec![0f32; 3 * n], vec![0f32; n]),
            };
            let field = |name: &str, unit: &str, conv, data| {
                Field::new(grid.clone(), name, unit, conv, FieldData::F32(data))
                    .map_err(StageError::failed)
            };
            out.insert(
                "velocity".into(),
                Artifact::Field(field("velocity", "m/s", ComponentConvention::Vector, vel)?),
            );
            out.insert(
                "pressure".into(),
                Artifact::Field(field("pressure", "Pa", ComponentConvention::Plain, pre)?),
            );
        }
        Ok(out)
    }
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
