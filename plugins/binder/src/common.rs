//! What the two binder stages share: the image parameters, the grid a packing gets, the
//! target counts, the three-phase image and its report.

use crate::components::count_components;
use grainpipe_core::raster::SphereRaster;
use grainpipe_core::resolution::{AutoVoxel, VoxelSize, UNRESOLVED};
use grainpipe_core::{
    params, ArtifactKind, ArtifactMeta, Grid, InputMetas, Packing, Phase, PhaseImage, PortSpec,
    Preflight, RunContext, StageError, StageInfo, Table,
};

/// The input and the two outputs both stages have; `report` says what the report adds.
pub fn ports(info: StageInfo, report: &'static str) -> StageInfo {
    info.inputs(vec![PortSpec::new(
        "packing",
        ArtifactKind::Packing,
        "spheres or clumps (a periodic box wraps)",
    )])
    .outputs(vec![
        PortSpec::new(
            "image",
            ArtifactKind::PhaseImage,
            "0 = pore, 1 = grain, 2 = binder (names: sand_phase, binder_phase)",
        ),
        PortSpec::new("report", ArtifactKind::Table, report),
    ])
}
use std::sync::atomic::{AtomicU64, Ordering};

/// The image and fraction settings of both binder stages.
#[params]
pub struct BinderImage {
    /// Voxel edge (adjusted so voxels tile the box); 0 = use voxels_per_diameter. Give it to
    /// have the grid known before running (downstream memory estimates need it). `auto`:
    /// the runner picks the coarsest voxel whose estimated error on auto_quantities meets
    /// target_error (cheap levels at auto_levels voxels per diameter, Richardson
    /// extrapolation; docs/sweeps.md).
    #[param(default = VoxelSize::default())]
    pub voxel_size: VoxelSize,
    /// Voxels across the mean volume-equivalent grain diameter when voxel_size is 0 (the
    /// paper's 4 um for a D50 of 140 um is 35).
    #[param(default = 35.0)]
    pub voxels_per_diameter: f64,
    /// Sub-samples per axis in voxels cut by a grain surface (a voxel is grain when at least
    /// half of its sub-samples are).
    #[param(default = 2, ty = "integer 1..8")]
    pub supersampling: u32,
    /// Binder volume fraction of the whole cell.
    #[param(default = 0.02)]
    pub binder_fraction: f64,
    /// Correct the sphere radii (sand) and the binder size after discretisation so the
    /// image's fractions equal the packing's analytic sand fraction and binder_fraction to
    /// within one voxel (paper, end of section 2.3).
    #[param(default = true)]
    pub exact_fractions: bool,
    /// Name of phase 1, the sand grains (the phase vocabulary's `grain`; it was `sand`
    /// before levelset 1.2.0 / closing 1.1.0).
    #[param(default = grainpipe_core::phases::GRAIN.into())]
    pub sand_phase: String,
    /// Name of phase 2.
    #[param(default = grainpipe_core::phases::BINDER.into())]
    pub binder_phase: String,
    #[param(flatten)]
    pub auto: AutoVoxel,
}

/// More voxels than this are refused at preflight (a typo in voxel_size, not a study).
const MAX_VOXELS: f64 = 4e9;

impl BinderImage {
    pub fn check(&self) -> Result<(), StageError> {
        if self.voxel_size.is_auto() {
            return Err(StageError::param("voxel_size", UNRESOLVED));
        }
        let v = self.voxel_size.si();
        if !v.is_finite() || v < 0.0 {
            return Err(StageError::param(
                "voxel_size",
                "must be a positive length, or 0",
            ));
        }
        if v == 0.0 && !(self.voxels_per_diameter >= 2.0 && self.voxels_per_diameter <= 1e4) {
            return Err(StageError::param(
                "voxels_per_diameter",
                "must be between 2 and 10000",
            ));
        }
        if !(1..=8).contains(&self.supersampling) {
            return Err(StageError::param(
                "supersampling",
                "must be between 1 and 8",
            ));
        }
        if !(0.0..1.0).contains(&self.binder_fraction) {
            return Err(StageError::param(
                "binder_fraction",
                "must be at least 0 and below 1 (0.02 is 2 % of the cell)",
            ));
        }
        for (key, name) in [
            ("sand_phase", &self.sand_phase),
            ("binder_phase", &self.binder_phase),
        ] {
            if name.trim().is_empty() || name == grainpipe_core::phases::PORE {
                return Err(StageError::param(key, "must be a name other than `pore`"));
            }
        }
        if self.sand_phase == self.binder_phase {
            return Err(StageError::param(
                "binder_phase",
                "must differ from sand_phase",
            ));
        }
        Ok(())
    }

    /// The parameter that set the voxel: `voxel_size` when given, else `voxels_per_diameter`.
    fn voxel_key(&self) -> &'static str {
        if self.voxel_size.si() > 0.0 {
            "voxel_size"
        } else {
            "voxels_per_diameter"
        }
    }

    fn voxel(&self, mean_diameter: f64) -> f64 {
        if self.voxel_size.si() > 0.0 {
            self.voxel_size.si()
        } else {
            mean_diameter / self.voxels_per_diameter
        }
    }

    /// The grid when preflight can fix it (a voxel size given, or a mean diameter the
    /// packing announces exactly), and an estimate of the voxel count.
    pub fn plan(&self, inputs: &InputMetas) -> Result<(Option<Grid>, u64), StageError> {
        let meta = inputs.get("packing");
        let Some((lo, hi)) = meta.and_then(|m| m.domain_box) else {
            return Ok((None, 0));
        };
        let exact_diameter = meta.and_then(|m| m.mean_diameter);
        let scale = exact_diameter.or(meta.and_then(|m| m.length_scale));
        if self.voxel_size.si() == 0.0 && scale.is_none() {
            return Ok((None, 0));
        }
        let v = self.voxel(scale.unwrap_or(0.0));
        let key = self.voxel_key();
        Grid::check_tiling(lo, hi, v).map_err(|m| StageError::param(key, m))?;
        let n: f64 = (0..3)
            .map(|a| ((hi[a] - lo[a]) / v).round().max(1.0))
            .product();
        if n > MAX_VOXELS {
            return Err(StageError::param(
                key,
                format!("{n:.3e} voxels: more than {MAX_VOXELS:.0e}; use a larger voxel"),
            ));
        }
        let fixed = self.voxel_size.si() > 0.0 || exact_diameter.is_some();
        let grid = match meta.and_then(|m| m.periodic) {
            Some(periodic) if fixed => Some(Grid::tiling(lo, hi, periodic, v)),
            _ => None,
        };
        Ok((grid, n as u64))
    }

    /// Heap bytes of the sphere raster `smooth_union` builds over this image (see
    /// [`SphereRaster::memory_bytes`]): the packing's spheres at its mean radius, reaching
    /// the band of radius corrections and, with `scale_in_voxels` > 0, the smoothing of the
    /// binder pass of `k` spheres at that scale.
    pub fn raster_bytes(&self, inputs: &InputMetas, scale_in_voxels: f64, k: usize) -> u64 {
        let meta = inputs.get("packing");
        let (Some((lo, hi)), Some(d)) = (
            meta.and_then(|m| m.domain_box),
            meta.and_then(|m| m.mean_diameter.or(m.length_scale)),
        ) else {
            return 0;
        };
        let v = self.voxel(d);
        let dims = [0, 1, 2].map(|a| ((hi[a] - lo[a]) / v).round().max(1.0) as usize);
        let spheres = meta.map(|m| m.count_estimate).unwrap_or(0);
        let reach = crate::smooth_union::max_reach(v, v * scale_in_voxels, k);
        SphereRaster::memory_bytes(dims, [v; 3], spheres, 0.5 * d, reach)
    }

    /// The grid of a packing at run time: the planned one, or one from its mean diameter.
    pub fn grid_for(&self, planned: &Option<Grid>, packing: &Packing) -> Result<Grid, StageError> {
        if let Some(g) = planned {
            return Ok(g.clone());
        }
        let d = &packing.domain;
        let v = self.voxel(packing.mean_diameter());
        Grid::check_tiling(d.min, d.max, v).map_err(|m| StageError::param(self.voxel_key(), m))?;
        let n: f64 = (0..3)
            .map(|a| ((d.max[a] - d.min[a]) / v).round().max(1.0))
            .product();
        if n > MAX_VOXELS {
            return Err(StageError::param(
                "voxels_per_diameter",
                format!("{n:.3e} voxels: use a larger voxel"),
            ));
        }
        Ok(Grid::tiling(d.min, d.max, d.periodic, v))
    }

    /// The preflight both stages share: parameters checked, the grid planned, `image` and
    /// `report` announced, memory estimated at `bytes_per_voxel`.
    pub fn preflight(
        &self,
        info: &StageInfo,
        inputs: &InputMetas,
        bytes_per_voxel: u64,
    ) -> Result<Preflight<Option<Grid>>, StageError> {
        self.check()?;
        let (grid, voxels) = self.plan(inputs)?;
        let image = match &grid {
            Some(g) => ArtifactMeta::on_grid(ArtifactKind::PhaseImage, g.clone())
                .with_phases(self.phases()),
            None => {
                let mut m = ArtifactMeta::of(ArtifactKind::PhaseImage);
                m.count_estimate = voxels;
                // The names do not depend on the grid: announced for the downstream checks.
                m.with_phases(self.phases())
            }
        };
        Ok(Preflight::from_info(info, bytes_per_voxel * voxels)
            .announce("image", image)
            .announce(
                "report",
                ArtifactMeta::of(ArtifactKind::Table).with_count(1, Some([1, 1])),
            )
            .with_plan(grid))
    }

    /// The phase table: `pore`, then the grains and the binder under their names.
    pub fn phases(&self) -> Vec<Phase> {
        grainpipe_core::phases::pore_and(&[&self.sand_phase, &self.binder_phase])
    }

    pub fn image(&self, grid: Grid, labels: Vec<u8>) -> PhaseImage {
        PhaseImage {
            grid,
            labels,
            phases: self.phases(),
        }
    }
}

/// Voxel counts the image should reach.
pub struct Targets {
    /// The packing's analytic solid fraction.
    pub sand_fraction: f64,
    pub sand_voxels: u64,
    pub binder_voxels: u64,
}

pub fn targets(p: &BinderImage, packing: &Packing, grid: &Grid) -> Result<Targets, StageError> {
    if packing.bodies.is_empty() {
        return Err(StageError::input("packing", "the packing has no bodies"));
    }
    let n = grid.voxel_count() as f64;
    let sand_fraction = packing.solid_volume() / (grid.voxel_volume() * n);
    if sand_fraction + p.binder_fraction >= 1.0 {
        return Err(StageError::param(
            "binder_fraction",
            format!(
                "sand ({sand_fraction:.4}) and binder ({}) would fill the whole cell",
                p.binder_fraction
            ),
        ));
    }
    Ok(Targets {
        sand_fraction,
        sand_voxels: (sand_fraction * n).round() as u64,
        binder_voxels: (p.binder_fraction * n).round() as u64,
    })
}

/// Progress over several scans of the grid, as one bar that never goes back.
pub struct Passes<'a> {
    ctx: &'a RunContext<'a>,
    done: AtomicU64,
    total: u64,
}

impl<'a> Passes<'a> {
    pub fn new(ctx: &'a RunContext<'a>, expected_scans: u64, grid: &Grid) -> Self {
        let slabs = grid.dims[2].div_ceil(grainpipe_core::raster::BLOCK) as u64;
        Passes {
            ctx,
            done: AtomicU64::new(0),
            total: expected_scans * slabs,
        }
    }

    pub fn step(&self, _: u64, _: u64) -> Result<(), StageError> {
        let d = self.done.fetch_add(1, Ordering::Relaxed) + 1;
        self.ctx
            .progress(d.min(self.total.saturating_sub(1)), self.total)
    }

    pub fn finish(&self) -> Result<(), StageError> {
        self.ctx.progress(self.total, self.total)
    }
}

/// The report row shared by both stages; `extra` adds stage-specific columns.
pub fn report(
    name: &str,
    image: &PhaseImage,
    t: &Targets,
    p: &BinderImage,
    extra: impl FnOnce(Table) -> Table,
) -> Table {
    let bridges = count_components(&image.grid, &image.labels, 2);
    let table = Table::new(name)
        .with_f64("sand_fraction_target", "1", vec![t.sand_fraction])
        .with_f64("sand_fraction", "1", vec![image.fraction(1)])
        .with_f64("binder_fraction_target", "1", vec![p.binder_fraction])
        .with_f64("binder_fraction", "1", vec![image.fraction(2)])
        .with_f64("pore_fraction", "1", vec![image.fraction(0)])
        .with_i64("binder_bridges", "1", vec![bridges as i64])
        .with_f64("voxel_size", "m", vec![image.grid.spacing[0]])
        .with_i64("voxels", "1", vec![image.grid.voxel_count() as i64]);
    extra(table)
}
