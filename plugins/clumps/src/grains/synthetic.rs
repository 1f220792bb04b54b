//! `grains.synthetic`: random star-shaped grains with the statistics of the real ones.

use super::{
    check_nonempty, check_voxel, grain_output_ports, grain_outputs, preflight_grains, GrainMask,
};
use crate::shape::{gaussian_random_field, StarShape, VoxelizeError};
use grainpipe_core::distributions::{SampleCheck, SizeDistribution};
use grainpipe_core::spatial::random_quaternion;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::*;
use nalgebra::{Matrix3, Quaternion, UnitQuaternion};
use rand::SeedableRng;
use rayon::prelude::*;

#[params]
pub struct SyntheticParams {
    /// number of grains
    #[param(default = 50)]
    pub count: usize,
    /// law of the volume-equivalent diameter (median = D50); drawn truncated at the grain-size limit 5e7^(1/3) voxel_size / (2 length_to_thickness), 405 um by default (a law cut by more than 0.1 % there is refused)
    // Silica foundry sand: D50 = 140 um (paper, GS14); log-normal width assumed.
    #[param(default = SizeDistribution::Lognormal {
        median: Q::new(140e-6),
        sigma: 0.25,
        min: None,
        max: None,
    })]
    pub size: SizeDistribution,
    /// voxel edge of the masks
    #[param(default = Q::new(4e-6))]
    pub voxel_size: Q<Length>,
    /// median L/T stretch (VCCTL MA107-6: 1.819)
    // VCCTL MA107-6 set statistics: mean L/T = 1.819 +- 0.427, W/T = 1.373 +- 0.289.
    #[param(ty = "number >= 1", default = 1.819)]
    pub length_to_thickness: f64,
    /// median W/T stretch (VCCTL MA107-6: 1.373)
    #[param(ty = "number >= 1", default = 1.373)]
    pub width_to_thickness: f64,
    /// log-normal spread of both ratios (MA107-6: about 0.2)
    #[param(ty = "number >= 0", default = 0.2)]
    pub aspect_spread: f64,
    /// standard deviation of ln r over the sphere (angularity)
    #[param(ty = "number >= 0", default = FIT_ROUGHNESS)]
    pub roughness: f64,
    /// beta of the angular power spectrum C_n ~ n^-beta
    #[param(default = FIT_SPECTRAL_EXPONENT)]
    pub spectral_exponent: f64,
    /// lowest random degree (2 would add random elongation on top of the stretch)
    #[param(ty = "integer >= 1", default = 3)]
    pub min_degree: usize,
    /// highest degree (the real grains' files stop at 30)
    #[param(default = 30)]
    pub max_degree: usize,
}

/// Defaults from the 30 real grains of data/sand-grains (examples/fit_synthetic.rs,
/// docs/stages/clumps.md): the point deviation of the relative radius over degrees 3..30 is
/// 0.1325; the least-squares spectral slope is 3.99, but with it the synthetic grains are
/// rougher than the real ones (sphericity 0.77 vs 0.84), so the exponent is set to 5, which
/// reproduces the real sphericity (0.83).
pub const FIT_ROUGHNESS: f64 = 0.13;
pub const FIT_SPECTRAL_EXPONENT: f64 = 5.0;

pub struct Synthetic;

/// One synthetic grain shape (reference size: unit equivalent diameter not yet imposed).
/// Returns the shape and its surface area [m^2].
pub fn synthetic_shape(
    p: &SyntheticParams,
    rng: &mut rand_chacha::ChaCha8Rng,
    d_eq: f64,
) -> (StarShape, f64) {
    use rand_distr::{Distribution, StandardNormal};
    let g = gaussian_random_field(
        rng,
        p.min_degree,
        p.max_degree,
        p.spectral_exponent,
        p.roughness,
    );
    let nt = (4 * p.max_degree).max(60);
    let mut table = g.tabulate(nt, 2 * nt);
    for v in &mut table.r {
        *v = v.exp(); // r = exp(g) keeps the radius positive
    }
    let e1: f64 = StandardNormal.sample(rng);
    let e2: f64 = StandardNormal.sample(rng);
    let lt = (p.length_to_thickness * (p.aspect_spread * e1).exp()).max(1.0);
    let wt = (p.width_to_thickness * (p.aspect_spread * e2).exp()).clamp(1.0, lt);
    let [w, x, y, z] = random_quaternion(rng);
    let rot = *UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
        .to_rotation_matrix()
        .matrix();
    let stretch = Matrix3::from_diagonal(&nalgebra::Vector3::new(lt, wt, 1.0));
    let shape = StarShape {
        table,
        transform: rot * stretch,
    };
    let (v, a) = shape.volume_area();
    let s = (std::f64::consts::PI / 6.0 * d_eq.powi(3) / v).cbrt();
    (
        StarShape {
            table: shape.table,
            transform: shape.transform * s,
        },
        a * s * s,
    )
}

/// Voxels a grain's box may hold before the stage refuses to draw it (about 100 MB of mask
/// and labels): the voxelizer's own hard limit is 8x larger.
pub const MAX_GRAIN_VOXELS: f64 = 5e7;

/// Largest size law mass the grain-size limit may cut before preflight refuses: beyond it the
/// drawn sizes would no longer follow the requested law (KS distance ~ the cut mass).
pub const MAX_CUT_MASS: f64 = 1e-3;

/// Largest volume-equivalent diameter whose grain box stays within [`MAX_GRAIN_VOXELS`].
/// The box edge of a grain of diameter d is taken as 2 d L/T: d (L/T)^(2/3) (W/T)^(-1/3)
/// is its stretched length, and the factor covers the radius spread exp(3 roughness) and
/// the aspect spread of that one grain, so the bound holds with room.
pub fn grain_size_limit(p: &SyntheticParams) -> f64 {
    MAX_GRAIN_VOXELS.cbrt() * p.voxel_size.si() / (2.0 * p.length_to_thickness)
}

/// The size law with an upper truncation at `x` added (tightening any `max` already set);
/// `None` for laws whose kind takes no `max` (bounded by construction).
pub fn truncate_above(d: &SizeDistribution, x: f64) -> Option<SizeDistribution> {
    let mut v = serde_json::to_value(d).ok()?;
    let o = v.as_object_mut()?;
    let kind = o.get("kind")?.as_str()?;
    if !matches!(
        kind,
        "normal" | "lognormal" | "weibull" | "gamma" | "exponential" | "tabulated"
    ) {
        return None;
    }
    let cur = o.get("max").and_then(|m| m.as_f64());
    o.insert("max".into(), serde_json::json!(cur.map_or(x, |c| c.min(x))));
    serde_json::from_value(v).ok()
}

/// The law the sampler draws from: `size` truncated at the grain-size limit when its tail
/// reaches beyond it, and the probability mass that truncation removed. Errors when the cut
/// exceeds [`MAX_CUT_MASS`] or the law is bounded above the limit.
pub fn sampled_law(p: &SyntheticParams) -> Result<(SizeDistribution, f64), StageError> {
    let lim = grain_size_limit(p);
    let (_, hi) = p.size.bounds();
    if hi <= lim {
        return Ok((p.size.clone(), 0.0));
    }
    let cut = 1.0 - p.size.cdf(lim);
    let vox = (2.0 * hi.min(p.size.quantile(1.0 - MAX_CUT_MASS)) * p.length_to_thickness
        / p.voxel_size.si())
    .powi(3);
    let refuse = |why: String| {
        StageError::param(
            "voxel_size",
            format!(
                "{why}; the largest grains would need ~{vox:.0} voxels (limit {MAX_GRAIN_VOXELS:.0}): \
                 use a larger voxel_size, or set size.max to at most {:.1} um",
                lim * 1e6
            ),
        )
    };
    if cut > MAX_CUT_MASS {
        return Err(refuse(format!(
            "the grain-size limit {:.1} um cuts {:.2} % of the size law (at most {} % may be cut)",
            lim * 1e6,
            cut * 100.0,
            MAX_CUT_MASS * 100.0
        )));
    }
    match truncate_above(&p.size, lim) {
        Some(t) => Ok((t, cut)),
        None => Err(refuse(format!(
            "the size law reaches {:.1} um, above the grain-size limit {:.1} um",
            hi * 1e6,
            lim * 1e6
        ))),
    }
}

/// Synthetic grain `k` drawn from `rng` (the stage's stream `k`), its diameter from `law`.
fn synthetic_grain(
    p: &SyntheticParams,
    law: &SizeDistribution,
    rng: &mut rand_chacha::ChaCha8Rng,
    k: usize,
) -> Result<(GrainMask, f64), VoxelizeError> {
    let d = law.sample(rng);
    let (shape, area) = synthetic_shape(p, rng, d);
    let (dims, origin, mask) = shape.voxelize(p.voxel_size.si())?;
    Ok((
        GrainMask {
            dims,
            voxel: p.voxel_size.si(),
            origin,
            mask,
            source: format!("synthetic #{k}"),
            area: Some(area),
        },
        d,
    ))
}

impl TypedStage for Synthetic {
    type Params = SyntheticParams;
    /// The size law the sampler draws from (`size` truncated at the grain-size limit).
    type Plan = SizeDistribution;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "grains.synthetic",
            "1.2.0",
            "Random star-shaped grains: radius exp(g) with g a Gaussian random field on \
             the sphere (power-law spectrum, fitted to the real grains of \
             data/sand-grains), stretched to random length/width/thickness ratios (VCCTL \
             MA107-6 statistics), randomly rotated, sized by a volume-equivalent diameter \
             law (default log-normal, D50 = 140 um).",
        )
        .outputs(grain_output_ports())
    }
    fn preflight(
        &self,
        p: &Self::Params,
        _: &InputMetas,
    ) -> Result<Preflight<SizeDistribution>, StageError> {
        check_voxel("voxel_size", p.voxel_size.si())?;
        p.size
            .validate()
            .map_err(|(k, m)| StageError::param(&format!("size.{k}"), m))?;
        if p.count == 0 {
            return Err(StageError::param("count", "must be at least 1"));
        }
        if !(p.length_to_thickness >= 1.0
            && p.width_to_thickness >= 1.0
            && p.width_to_thickness <= p.length_to_thickness)
        {
            return Err(StageError::param(
                "length_to_thickness",
                "need 1 <= width_to_thickness <= length_to_thickness",
            ));
        }
        for (k, v) in [
            ("aspect_spread", p.aspect_spread),
            ("roughness", p.roughness),
        ] {
            if !(v.is_finite() && (0.0..=2.0).contains(&v)) {
                return Err(StageError::param(k, format!("must be in [0, 2], got {v}")));
            }
        }
        if !p.spectral_exponent.is_finite() {
            return Err(StageError::param("spectral_exponent", "must be finite"));
        }
        if p.min_degree == 0 || p.min_degree > p.max_degree || p.max_degree > 200 {
            return Err(StageError::param(
                "max_degree",
                "need 1 <= min_degree <= max_degree <= 200",
            ));
        }
        let (law, _) = sampled_law(p)?;
        // Memory: the mean grain's box (stretched length, radius spread exp(2 roughness),
        // one empty layer each side) on every axis.
        let stretch = (p.length_to_thickness.powi(2) / p.width_to_thickness).cbrt();
        let edge = law.mean() * stretch * (2.0 * p.roughness).exp() / p.voxel_size.si() + 3.0;
        // The output labels of every grain (1 B per voxel of its box, the grain's mask is
        // dropped as its image is made) and ~1 KiB of tables per grain; per worker thread one
        // grain in flight: its mask (1 B per voxel) and its shape, the radius table of
        // (nt + 1) x 2 nt f64, a copy, and its vertices for the volume (3 f64 per entry).
        let boxes = edge.powi(3);
        let nt = (4 * p.max_degree).max(60) as f64;
        let table = (nt + 1.0) * 2.0 * nt * 8.0;
        let threads = rayon::current_num_threads() as f64;
        let memory = p.count as f64 * (boxes + 1024.0) + threads * (boxes + 5.0 * table);
        let mut pf = preflight_grains(&self.info(), Some(p.count), 0.0, Some(law.mean()));
        pf.memory_bytes = memory as u64 + (64 << 10);
        Ok(pf.with_plan(law))
    }
    fn run(
        &self,
        p: &Self::Params,
        law: &SizeDistribution,
        _: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let done = std::sync::atomic::AtomicU64::new(0);
        let drawn: Vec<(GrainMask, f64)> = (0..p.count)
            .into_par_iter()
            .map(|k| {
                let g = synthetic_grain(p, law, &mut ctx.substream(k as u64), k)
                    .map_err(|e| StageError::failed(e.to_string()))?;
                let c = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                ctx.progress(c, p.count as u64)?;
                Ok(g)
            })
            .collect::<Result<_, StageError>>()?;
        let (grains, d): (Vec<GrainMask>, Vec<f64>) = drawn.into_iter().unzip();
        check_nonempty(&grains)?;
        if let Some(w) = size_law_warning(p, law, &d) {
            ctx.warn(&w);
        }
        Ok(grain_outputs(grains))
    }
}

/// Synthetic grains without a pipeline (tests, benchmark): `count` grains from `seed`, the
/// same as the stage gives with step seed `seed`.
pub fn synthetic_grains(p: &SyntheticParams, seed: u64) -> Vec<GrainMask> {
    let law = sampled_law(p)
        .expect("size law within the grain-size limit")
        .0;
    (0..p.count)
        .into_par_iter()
        .map(|k| {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(derive_seed(
                seed,
                &(k as u64).to_le_bytes(),
            ));
            synthetic_grain(p, &law, &mut rng, k).expect("voxelize").0
        })
        .collect()
}

/// The warning the stage gives when the drawn diameters fail the KS test against the
/// requested law (the grain-size limit cut its tail): `None` when they pass.
pub fn size_law_warning(p: &SyntheticParams, law: &SizeDistribution, d: &[f64]) -> Option<String> {
    let cut = 1.0 - p.size.cdf(law.bounds().1);
    SampleCheck::new(d, &p.size, 0, d.len() as u64)
        .with_limit(law.bounds().1, cut)
        .warning("grains.synthetic: volume-equivalent diameters")
}
