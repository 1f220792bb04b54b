//! `voxelize.packing`: spheres and clumps -> a phase image, with sub-voxel supersampling.

use grainpipe_core::raster::{min_distance, SphereRaster};
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, Grid, InputMetas, Inputs, Outputs, Phase,
    PhaseImage, PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
    WorldSphere,
};

#[params]
pub struct VoxelizeParams {
    /// Voxel edge (adjusted so voxels tile the box); 0 = use voxels_per_diameter. Give it to
    /// have the grid known before running (downstream memory estimates need it).
    #[param(default = Q::new(0.0))]
    pub voxel_size: Q<Length>,
    /// Voxels across the mean volume-equivalent body diameter when voxel_size is 0.
    #[param(default = 10.0)]
    pub voxels_per_diameter: f64,
    /// Sub-samples per axis in voxels cut by a surface.
    #[param(default = 4, ty = "integer 1..16")]
    pub supersampling: u32,
    /// Name of the solid phase (label 1).
    #[param(default = "grain".into())]
    pub phase_name: String,
}

pub struct Voxelize;

/// Upper bound on voxels, so a typo in voxel_size is refused instead of swapping.
const MAX_VOXELS: f64 = 4e9;

fn voxel_size(p: &VoxelizeParams, mean_diameter: f64) -> f64 {
    if p.voxel_size.si() > 0.0 {
        p.voxel_size.si()
    } else {
        mean_diameter / p.voxels_per_diameter
    }
}

impl TypedStage for Voxelize {
    type Params = VoxelizeParams;
    /// The voxel size, when preflight could fix it.
    type Plan = Option<f64>;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "voxelize.packing",
            "1.0.0",
            "Voxelizes a packing of spheres or clumps into a two-phase image (0 = pore, 1 = \
             solid). A voxel entirely inside a sphere is solid, one entirely outside every \
             sphere is pore, and a voxel cut by a surface is sampled at supersampling^3 points \
             against the union of the spheres that reach it and is solid when at least half \
             of its points are. Periodic axes wrap. The report compares the image's solid \
             fraction and the sub-voxel coverage with the analytic volume fraction of the \
             packing.",
        )
        .inputs(vec![PortSpec::new(
            "packing",
            ArtifactKind::Packing,
            "spheres or clumps to voxelize",
        )])
        .outputs(vec![
            PortSpec::new("image", ArtifactKind::PhaseImage, "0 = pore, 1 = solid"),
            PortSpec::new(
                "report",
                ArtifactKind::Table,
                "analytic, image and coverage volume fractions",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &VoxelizeParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<Option<f64>>, StageError> {
        if p.voxel_size.si() < 0.0 || !p.voxel_size.si().is_finite() {
            return Err(StageError::param(
                "voxel_size",
                "must be a positive length, or 0",
            ));
        }
        if p.voxel_size.si() == 0.0
            && (p.voxels_per_diameter.is_nan() || p.voxels_per_diameter < 1.0)
        {
            return Err(StageError::param(
                "voxels_per_diameter",
                "must be at least 1",
            ));
        }
        if !(1..=16).contains(&p.supersampling) {
            return Err(StageError::param(
                "supersampling",
                "must be between 1 and 16",
            ));
        }
        let meta = inputs.get("packing");
        let mut out = ArtifactMeta::of(ArtifactKind::PhaseImage);
        let mut memory = 0;
        let mut voxel = None;
        if let Some((lo, hi)) = meta.and_then(|m| m.domain_box) {
            let scale = meta.and_then(|m| m.mean_diameter.or(m.length_scale));
            if p.voxel_size.si() > 0.0 || scale.is_some() {
                let v = voxel_size(p, scale.unwrap_or(0.0));
                let n: f64 = (0..3)
                    .map(|a| ((hi[a] - lo[a]) / v).round().max(1.0))
                    .product();
                if n > MAX_VOXELS {
                    return Err(StageError::param(
                        "voxel_size",
                        format!("{n:.3e} voxels: more than {MAX_VOXELS:.0e}; use a larger voxel"),
                    ));
                }
                memory = n as u64;
                // The grid is known when the voxel size is: given, or derived from a mean
                // diameter the packing fixes exactly (a length scale is only an estimate of the
                // diameter the run measures). The run then uses this voxel size.
                let exact = p.voxel_size.si() > 0.0 || meta.and_then(|m| m.mean_diameter).is_some();
                match meta.and_then(|m| m.periodic) {
                    Some(periodic) if exact => {
                        out = ArtifactMeta::on_grid(
                            ArtifactKind::PhaseImage,
                            Grid::tiling(lo, hi, periodic, v),
                        );
                        voxel = Some(v);
                    }
                    _ => out.count_estimate = n as u64,
                }
            }
        }
        Ok(Preflight::from_info(&self.info(), memory)
            .announce("image", out)
            .announce(
                "report",
                ArtifactMeta::of(ArtifactKind::Table).with_count(1, Some([1, 1])),
            )
            .with_plan(voxel))
    }

    fn run(
        &self,
        p: &VoxelizeParams,
        planned_voxel: &Option<f64>,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let packing = input(inputs, "packing", Artifact::as_packing)?;
        if packing.bodies.is_empty() {
            return Err(StageError::input("packing", "the packing has no bodies"));
        }
        let d = &packing.domain;
        let v = planned_voxel.unwrap_or_else(|| voxel_size(p, packing.mean_diameter()));
        let n: f64 = (0..3)
            .map(|a| ((d.max[a] - d.min[a]) / v).round().max(1.0))
            .product();
        if n > MAX_VOXELS {
            return Err(StageError::param(
                "voxel_size",
                format!("{n:.3e} voxels: use a larger voxel"),
            ));
        }
        let grid = Grid::tiling(d.min, d.max, d.periodic, v);
        let spheres = packing.world_spheres();
        let (labels, coverage) =
            voxelize(&grid, &spheres, d.periodic, p.supersampling as usize, ctx)?;
        let image = PhaseImage {
            grid: grid.clone(),
            labels,
            phases: vec![
                Phase {
                    id: 0,
                    name: "pore".into(),
                },
                Phase {
                    id: 1,
                    name: p.phase_name.clone(),
                },
            ],
        };
        let analytic = packing.volume_fraction();
        let img = image.fraction(1);
        ctx.info(&format!(
            "{}x{}x{} voxels of {:.3e} m: solid fraction {img:.5} (coverage {coverage:.5}) vs analytic {analytic:.5}",
            grid.dims[0], grid.dims[1], grid.dims[2], grid.spacing[0]
        ));
        let report = Table::new("voxelize")
            .with_f64("analytic_fraction", "1", vec![analytic])
            .with_f64("image_fraction", "1", vec![img])
            .with_f64("coverage_fraction", "1", vec![coverage])
            .with_f64("relative_error", "1", vec![(img - analytic) / analytic])
            .with_f64("voxel_size", "m", vec![grid.spacing[0]])
            .with_i64("voxels", "1", vec![grid.voxel_count() as i64]);
        let mut out = Outputs::new();
        out.insert("image".into(), Artifact::PhaseImage(image));
        out.insert("report".into(), Artifact::Table(report));
        Ok(out)
    }
}

/// Labels every voxel; returns the labels and the mean sub-voxel coverage. Spheres are
/// binned into blocks of voxels (`core::raster`), so each voxel looks only at the spheres
/// that reach its block, nearest first.
pub fn voxelize(
    grid: &Grid,
    spheres: &[WorldSphere],
    periodic: [bool; 3],
    supersampling: usize,
    ctx: &RunContext,
) -> Result<(Vec<u8>, f64), StageError> {
    let grid = Grid {
        periodic,
        ..grid.clone()
    };
    let half_diag = 0.5 * grid.spacing.iter().map(|s| s * s).sum::<f64>().sqrt();
    let raster = SphereRaster::new(&grid, spheres, half_diag)
        .map_err(|e| StageError::failed(e.to_string()))?;
    let s = supersampling;
    let mut labels = vec![0u8; grid.voxel_count()];
    let coverage: Vec<f64> = raster.scan(
        &mut labels,
        || 0.0f64,
        |cov, cands, _, c, label| {
            let centre = min_distance(cands, c, -half_diag, half_diag);
            let f = if centre <= -half_diag {
                1.0
            } else if centre > half_diag {
                0.0
            } else {
                let mut inside = 0usize;
                for k in 0..s * s * s {
                    let sub = [k % s, (k / s) % s, k / (s * s)];
                    let q: [f64; 3] = std::array::from_fn(|a| {
                        c[a] + ((sub[a] as f64 + 0.5) / s as f64 - 0.5) * grid.spacing[a]
                    });
                    if min_distance(cands, q, 0.0, 0.0) <= 0.0 {
                        inside += 1;
                    }
                }
                inside as f64 / (s * s * s) as f64
            };
            *cov += f;
            *label = u8::from(f >= 0.5);
        },
        |done, total| ctx.progress(done, total),
    )?;
    Ok((
        labels,
        coverage.iter().sum::<f64>() / grid.voxel_count() as f64,
    ))
}
