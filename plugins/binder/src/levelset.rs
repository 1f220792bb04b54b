//! `binder.levelset`: the grid-free binder of Donval et al. (2025), section 2.3.

use crate::common::{ports, report, targets, BinderImage, Passes};
use crate::smooth_union::{
    level_set, smooth_union, subvoxel_samples, BinderError, BinderTarget, SmoothUnionSpec,
    Smoothing, MAX_K,
};
use grainpipe_core::subvoxel::{self, SubvoxelOutput};
use grainpipe_core::units::{Length, Q};
use grainpipe_core::ParamChoice;
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, ComponentConvention, Field, FieldData,
    Grid, InputMetas, Inputs, Outputs, PortSpec, Preflight, RunContext, StageError, StageInfo,
    TypedStage,
};
use serde::{Deserialize, Serialize};

impl From<BinderError> for StageError {
    fn from(e: BinderError) -> Self {
        match e {
            BinderError::Raster(_)
            | BinderError::RadiusCorrection { .. }
            | BinderError::Unreachable { .. } => StageError::failed(e.to_string()),
        }
    }
}

/// What the smooth minimum of eq. (2.15) runs over.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum SmoothOver {
    /// The k nearest spheres of any grain.
    Spheres,
    /// The k nearest grains.
    Grains,
}

#[params]
pub struct LevelSetParams {
    #[param(flatten)]
    pub image: BinderImage,
    /// Smoothing scale a of the LogSumExp (eq. 2.14). Leave it out to have it found so that
    /// the binder fraction is binder_fraction; give it to keep it fixed (binder_fraction is
    /// then not used).
    #[param(default = None)]
    pub a: Option<Q<Length>>,
    /// Number of smallest sphere distances combined by the smooth minimum (eq. 2.15; the
    /// paper uses 5).
    #[param(default = 5, ty = "integer 2..16")]
    pub k: usize,
    /// Smooth over the k nearest `spheres` (the paper: binder also fills the ridges between
    /// the spheres of one clump and coats it) or the k nearest `grains` (each grain's exact
    /// distance, the minimum over its spheres: binder only between grains, so a given
    /// fraction makes wider bridges).
    #[param(default = SmoothOver::Spheres)]
    pub smooth_over: SmoothOver,
    /// Also output the smoothed level set (f32, metres, negative inside) as `level_set`.
    #[param(default = false)]
    pub level_set: bool,
    #[param(flatten)]
    pub subvoxel: SubvoxelOutput,
}

pub struct LevelSet;

impl TypedStage for LevelSet {
    type Params = LevelSetParams;
    /// The grid, when preflight could fix it.
    type Plan = Option<Grid>;

    fn info(&self) -> StageInfo {
        let mut info = ports(
            StageInfo::new(
                "binder.levelset",
                "1.2.0",
                "Adds binder bridges to a packing of spheres or clumps and images it in three \
             phases (Donval et al. 2025, section 2.3): the signed distances to the spheres \
             (periodic where the packing is) are combined by the scaled LogSumExp of the k \
             smallest (eq. 2.14-2.15); binder is the smoothed union {LSE_a <= 0} minus the \
             grains. With exact_fractions the sphere radii and a are corrected after \
             discretisation so that the image's sand fraction is the packing's analytic one \
             and the binder fraction is binder_fraction, each to within one voxel (ties \
             aside): both corrections are order statistics of per-voxel numbers (the radius \
             offset at which a voxel turns grain, the scale a at which it joins the smoothed \
             union, found per voxel by a monotone Newton root search), so no re-voxelization \
             loop runs. Memory: one byte per voxel plus 8 bytes per sphere-block pair; the \
             level set adds 4 bytes per voxel.",
            ),
            "target and achieved fractions, a, radius correction, binder bridges",
        );
        info.outputs.push(PortSpec::new(
            "level_set",
            ArtifactKind::Field,
            "the smoothed signed distance [m] at voxel centres (with level_set: true)",
        ));
        info.outputs.push(PortSpec::new(
            "subvoxel",
            ArtifactKind::Field,
            "with subvoxel: true, per voxel the fractions of pore, grain and binder and the \
             interface normal (6 components), sampled from the sphere distances and the level \
             set, for interfaces: composite in the solvers",
        ));
        info
    }

    fn preflight(
        &self,
        p: &LevelSetParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<Option<Grid>>, StageError> {
        if !(2..=MAX_K).contains(&p.k) {
            return Err(StageError::param(
                "k",
                format!("must be between 2 and {MAX_K} (1 would add no binder)"),
            ));
        }
        if let Some(a) = p.a {
            if !(a.si() > 0.0 && a.si().is_finite()) {
                return Err(StageError::param("a", "must be a positive length"));
            }
        }
        p.subvoxel
            .check()
            .map_err(|(k, m)| StageError::param(&k, m))?;
        let bytes = if p.level_set { 5 } else { 1 } + p.subvoxel.bytes_per_voxel(3);
        let mut pf = p.image.preflight(&self.info(), inputs, bytes)?;
        // The sphere raster of the binder pass, sized for a smoothing scale of one voxel (the
        // scale is found at run time: a larger one, for large binder fractions, costs more
        // bins, capped at 2^28 entries), and the thresholds of the voxels in the crossing
        // code, gathered per slab and then flattened (2 x 8 B), counted at the binder's
        // voxels.
        let voxels = pf.memory_bytes / bytes;
        let binder = (p.image.binder_fraction.clamp(0.0, 1.0) * voxels as f64) as u64;
        pf.memory_bytes += p.image.raster_bytes(inputs, 1.0, p.k) + 16 * binder + (64 << 10);
        if p.level_set {
            if let Some(g) = pf.plan.clone() {
                pf = pf.announce("level_set", ArtifactMeta::on_grid(ArtifactKind::Field, g));
            }
        } else {
            pf.outputs.retain(|k, _| k != "level_set");
        }
        if p.subvoxel.subvoxel {
            if let Some(g) = pf.plan.clone() {
                pf = pf.announce("subvoxel", ArtifactMeta::on_grid(ArtifactKind::Field, g));
            }
        } else {
            pf.outputs.retain(|k, _| k != "subvoxel");
        }
        Ok(pf)
    }

    fn run(
        &self,
        p: &LevelSetParams,
        planned: &Option<Grid>,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let packing = input(inputs, "packing", Artifact::as_packing)?;
        let grid = p.image.grid_for(planned, packing)?;
        let t = targets(&p.image, packing, &grid)?;
        let spheres = packing.world_spheres();
        let mean_diameter = packing.mean_diameter();
        let h = grid.spacing.iter().copied().fold(0.0, f64::max);
        let spec = SmoothUnionSpec {
            k: p.k,
            per_body: p.smooth_over == SmoothOver::Grains,
            supersampling: p.image.supersampling as usize,
            grain_voxels: p.image.exact_fractions.then_some(t.sand_voxels),
            binder: match p.a {
                Some(a) => BinderTarget::Scale(a.si()),
                None => BinderTarget::Voxels(t.binder_voxels),
            },
            // The search starts low and doubles: the bins' reach, and so the cost of a scan,
            // grows with the bound. The paper's 2 % at 4 um needs a = 1.2 um over spheres
            // (ridges and coatings fill first) and 7.7 um over grains (bridges only).
            initial_scale_bound: match p.smooth_over {
                SmoothOver::Spheres => 0.5 * h,
                SmoothOver::Grains => (0.5 * h).max(0.03 * mean_diameter),
            },
            max_scale: 0.5 * mean_diameter,
        };
        let passes = Passes::new(
            ctx,
            4 + u64::from(p.level_set) + u64::from(p.subvoxel.subvoxel),
            &grid,
        );
        let result =
            smooth_union::<StageError, _>(&grid, &spheres, &spec, &|d, n| passes.step(d, n))?;
        let a = result.scale;
        let smoothing = Smoothing {
            k: p.k,
            per_body: p.smooth_over == SmoothOver::Grains,
        };
        let field = if p.level_set {
            // The level set matters near its zero; further out it is clamped, which keeps
            // the bins' reach (and the cost) small.
            let clamp = 4.0 * h + a * (p.k as f64).ln();
            let values = level_set::<StageError, _>(
                &grid,
                &spheres,
                smoothing,
                result.delta,
                a,
                clamp,
                &|d, n| passes.step(d, n),
            )?;
            Some(
                Field::new(
                    grid.clone(),
                    "level_set",
                    "m",
                    ComponentConvention::Plain,
                    FieldData::F32(values),
                )
                .map_err(StageError::failed)?,
            )
        } else {
            None
        };
        let which = p
            .subvoxel
            .subvoxel
            .then(|| subvoxel::interface_candidates(&grid, &result.labels));
        let samples = match &which {
            Some(which) => Some(subvoxel_samples::<StageError, _>(
                &grid,
                &spheres,
                smoothing,
                result.delta,
                a,
                which,
                p.subvoxel.subvoxel_samples,
                &|d, n| passes.step(d, n),
            )?),
            None => None,
        };
        passes.finish()?;
        let image = p.image.image(grid, result.labels);
        let subvoxel_field = match samples {
            Some(s) => {
                let sv = subvoxel::from_samples(&image, s).map_err(StageError::failed)?;
                ctx.info(&format!(
                    "sub-voxel geometry: {} mixed voxels ({:.1} %)",
                    sv.mixed_count(),
                    100.0 * sv.mixed_count() as f64 / image.labels.len().max(1) as f64
                ));
                Some(sv.to_field(&image.grid))
            }
            None => None,
        };
        let table = report("binder.levelset", &image, &t, &p.image, |tab| {
            tab.with_f64("a", "m", vec![a])
                .with_f64("radius_correction", "m", vec![result.delta])
                .with_i64("k", "1", vec![p.k as i64])
                .with_i64("grid_scans", "1", vec![result.passes as i64])
        });
        ctx.info(&format!(
            "sand {:.5} (target {:.5}), binder {:.5} (target {}), a = {a:.3e} m, radius \
             correction {:.3e} m",
            image.fraction(1),
            t.sand_fraction,
            image.fraction(2),
            p.image.binder_fraction,
            result.delta
        ));
        let mut out = Outputs::new();
        out.insert("image".into(), Artifact::PhaseImage(image));
        out.insert("report".into(), Artifact::Table(table));
        if let Some(f) = field {
            out.insert("level_set".into(), Artifact::Field(f));
        }
        if let Some(f) = subvoxel_field {
            out.insert("subvoxel".into(), Artifact::Field(f));
        }
        Ok(out)
    }
}
