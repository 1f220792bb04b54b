//! `packing.rsa`: random sequential addition of non-overlapping spheres in a box.

use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::spatial::CellList;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    params, ArtifactKind, ArtifactMeta, Body, BodyShape, Domain, InputMetas, Inputs, Outputs,
    Packing, PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
};
use rand::RngExt;
use std::f64::consts::PI;

/// Jamming limit of monodisperse RSA in 3-D (Torquato, Uche & Stillinger 2006: 0.38278).
pub const RSA_JAMMING_LIMIT: f64 = 0.38278;

#[params]
pub struct RsaParams {
    /// Box edge lengths.
    #[param(default = [Q::new(500e-6); 3])]
    pub size: [Q<Length>; 3],
    /// Sphere radius law, e.g. {kind: fixed, value: 25 um}.
    #[param(default = SizeDistribution::Fixed { value: Q::new(25e-6) })]
    pub radius: SizeDistribution,
    /// Target solid volume fraction, in (0, 1); monodisperse RSA jams at 0.383.
    #[param(default = 0.30)]
    pub volume_fraction: f64,
    /// Periodic axes; other axes keep spheres entirely inside the box.
    #[param(default = [true; 3])]
    pub periodic: [bool; 3],
    /// Random positions tried for one sphere before the stage fails.
    #[param(default = 200_000)]
    pub max_attempts_per_sphere: u64,
}

pub struct Rsa;

/// Whether a sphere (c, r) overlaps any sphere of `packing` stored in `cells`, whose cells are
/// at least one largest diameter wide (so the 27 adjacent cells hold every candidate).
fn overlaps(cells: &CellList, c: [f64; 3], r: f64, packing: &Packing) -> bool {
    !cells.visit_adjacent(c, |id| {
        let b = &packing.bodies[id as usize];
        let rb = match b.shape {
            BodyShape::Sphere { radius } => radius,
            BodyShape::Clump { .. } => unreachable!("RSA places spheres only"),
        };
        let d = cells.separation(c, b.position);
        let d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        d2 >= (r + rb) * (r + rb)
    })
}

/// Radii drawn for a target volume: draws until the summed volume reaches `target_volume`.
fn draw_radii(p: &RsaParams, ctx_rng: &mut impl rand::Rng, target_volume: f64) -> Vec<f64> {
    let mut radii = Vec::new();
    let mut v = 0.0;
    while v < target_volume {
        let r = p.radius.sample(ctx_rng);
        v += 4.0 / 3.0 * PI * r.powi(3);
        radii.push(r);
    }
    radii
}

/// Bytes of one empty cell of the cell list (a `Vec` header).
const CELL_BYTES: u64 = 24;

/// The cell edge for `count` spheres of largest radius `rmax` in a box of `size`: at least one
/// largest diameter (the 27 adjacent cells must hold every overlap candidate), and no smaller
/// than the box volume per sphere, so the cells are about as many as the spheres. Sized from
/// the diameter alone, a sparse box (`volume_fraction: 1e-9` in a 25 cm box of 25 um spheres)
/// would get the largest cell list allowed for a single sphere.
fn cell_edge(size: [f64; 3], rmax: f64, count: f64) -> f64 {
    let per_sphere = (size.iter().product::<f64>() / count.max(1.0)).cbrt();
    (2.0 * rmax).max(per_sphere)
}

/// How many cells [`cell_edge`] gives (before the cell list's own caps).
fn cell_count(size: [f64; 3], rmax: f64, count: f64) -> u64 {
    let edge = cell_edge(size, rmax, count);
    size.iter()
        .map(|&l| (l / edge).floor().clamp(1.0, 1024.0) as u64)
        .product()
}

/// Expected sphere volume, estimated from 4096 quantiles (deterministic, cheap).
fn mean_sphere_volume(d: &SizeDistribution) -> f64 {
    let n = 4096;
    (0..n)
        .map(|i| {
            let r = d.quantile((i as f64 + 0.5) / n as f64);
            4.0 / 3.0 * PI * r.powi(3)
        })
        .sum::<f64>()
        / n as f64
}

impl TypedStage for Rsa {
    type Params = RsaParams;
    type Plan = ();

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "packing.rsa",
            "1.0.0",
            "Random sequential addition of non-overlapping spheres. Radii are drawn from the \
             distribution until their summed volume reaches the target fraction of the box, \
             sorted largest first, then each sphere is placed at uniformly random positions \
             until one does not overlap any placed sphere (cell-list test, periodic images on \
             periodic axes). RSA saturates: monodisperse spheres jam at a volume fraction of \
             0.383 (Torquato et al. 2006), so higher targets are refused before running and a \
             sphere that finds no place within max_attempts_per_sphere stops the stage with \
             the fraction reached.",
        )
        .outputs(vec![
            PortSpec::new("packing", ArtifactKind::Packing, "the spheres"),
            PortSpec::new(
                "report",
                ArtifactKind::Table,
                "target and achieved volume fraction, spheres, attempts",
            ),
        ])
    }

    fn preflight(&self, p: &RsaParams, _inputs: &InputMetas) -> Result<Preflight, StageError> {
        let size = p.size.map(|q| q.si());
        if size.iter().any(|s| !s.is_finite() || *s <= 0.0) {
            return Err(StageError::param(
                "size",
                "every box edge must be a positive length",
            ));
        }
        p.radius
            .validate()
            .map_err(|(k, m)| StageError::param(&format!("radius.{k}"), m))?;
        if !(p.volume_fraction > 0.0 && p.volume_fraction < 1.0) {
            return Err(StageError::param("volume_fraction", "must be in (0, 1)"));
        }
        if matches!(p.radius, SizeDistribution::Fixed { .. })
            && p.volume_fraction > RSA_JAMMING_LIMIT
        {
            return Err(StageError::param(
                "volume_fraction",
                format!(
                    "{} is above the RSA jamming limit of monodisperse spheres ({RSA_JAMMING_LIMIT}); \
                     use a polydisperse radius law or a dense packing method (mcm.classic)",
                    p.volume_fraction
                ),
            ));
        }
        if p.max_attempts_per_sphere == 0 {
            return Err(StageError::param(
                "max_attempts_per_sphere",
                "must be at least 1",
            ));
        }
        let (_, rmax) = p.radius.bounds();
        let rmax = if rmax.is_finite() {
            rmax
        } else {
            p.radius.practical_max()
        };
        for (a, (&len, &periodic)) in size.iter().zip(&p.periodic).enumerate() {
            if !periodic && 2.0 * rmax >= len {
                return Err(StageError::param(
                    "size",
                    format!(
                        "axis {a} is {len:.3e} m, not larger than the largest sphere diameter {:.3e} m",
                        2.0 * rmax
                    ),
                ));
            }
            // A sphere wider than the period overlaps its own image: a 25 mm radius in a
            // 400 um periodic box was "packed" at a volume fraction of 1 022 653.
            if periodic && 2.0 * rmax > len {
                return Err(StageError::param(
                    "radius",
                    format!(
                        "the largest sphere ({} across) is wider than the periodic box along {} \
                         ({}) and would overlap its own image; check the unit of the radius \
                         or enlarge `size`",
                        grainpipe_core::units::format_length(2.0 * rmax),
                        ["x", "y", "z"][a],
                        grainpipe_core::units::format_length(len)
                    ),
                ));
            }
        }
        let volume: f64 = size.iter().product();
        let count = (p.volume_fraction * volume / mean_sphere_volume(&p.radius)).ceil();
        if count > 5e7 {
            return Err(StageError::param("size", format!(
                "about {count:.0} spheres: more than the 50 million this stage handles; shrink the box"
            )));
        }
        let cells = cell_count(size, rmax, count);
        let packing =
            ArtifactMeta::packing([0.0; 3], size, p.periodic).with_count(count as u64, None);
        let packing = match p.radius {
            SizeDistribution::Fixed { value } => packing.with_mean_diameter(2.0 * value.si()),
            _ => packing.with_length_scale(2.0 * p.radius.mean()),
        };
        let report = ArtifactMeta::of(ArtifactKind::Table).with_count(1, Some([1, 1]));
        // Bodies (~200 bytes each with their cell entry), the cell list's empty cells and
        // the report.
        let memory = (count as u64)
            .saturating_mul(200)
            .saturating_add(cells.saturating_mul(CELL_BYTES))
            .saturating_add(64 << 10);
        Ok(Preflight::from_info(&self.info(), memory)
            .announce("packing", packing)
            .announce("report", report))
    }

    fn run(
        &self,
        p: &RsaParams,
        _plan: &(),
        _inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let size = p.size.map(|q| q.si());
        let volume: f64 = size.iter().product();
        let mut rng = ctx.rng();
        let mut radii = draw_radii(p, &mut rng, p.volume_fraction * volume);
        // Largest first: small spheres still fit into the gaps left by large ones.
        radii.sort_by(|a, b| b.total_cmp(a));
        let rmax = radii[0];
        let mut cells = CellList::new(
            [0.0; 3],
            size,
            p.periodic,
            cell_edge(size, rmax, radii.len() as f64),
        );
        let mut packing = Packing::new(Domain::boxed([0.0; 3], size, p.periodic));
        let mut attempts_total = 0u64;
        let mut placed_volume = 0.0;
        let n = radii.len();
        for (k, &r) in radii.iter().enumerate() {
            let mut placed = false;
            for attempt in 0..p.max_attempts_per_sphere {
                attempts_total += 1;
                // Near jamming one sphere can take millions of attempts: Ctrl-C must not wait
                // for the next progress report.
                if attempt % 4096 == 4095 {
                    ctx.check_cancelled()?;
                }
                let c: [f64; 3] = std::array::from_fn(|a| {
                    if p.periodic[a] {
                        rng.random::<f64>() * size[a]
                    } else {
                        r + rng.random::<f64>() * (size[a] - 2.0 * r)
                    }
                });
                if !overlaps(&cells, c, r, &packing) {
                    cells.insert(packing.bodies.len() as u32, c);
                    packing.bodies.push(Body::sphere(c, r));
                    placed_volume += 4.0 / 3.0 * PI * r.powi(3);
                    placed = true;
                    break;
                }
            }
            if !placed {
                return Err(StageError::failed(format!(
                    "RSA jammed: sphere {} of {n} (radius {r:.3e} m) found no free place in {} \
                     attempts; volume fraction reached {:.4} of the {:.4} asked. Lower \
                     volume_fraction or use a dense packing stage.",
                    k + 1,
                    p.max_attempts_per_sphere,
                    placed_volume / volume,
                    p.volume_fraction
                )));
            }
            if k % 256 == 0 {
                ctx.progress(k as u64, n as u64)?;
            }
        }
        let achieved = placed_volume / volume;
        ctx.info(&format!(
            "{n} spheres, volume fraction {achieved:.4}, {attempts_total} attempts"
        ));
        let report = Table::new("rsa")
            .with_f64("target_volume_fraction", "1", vec![p.volume_fraction])
            .with_f64("volume_fraction", "1", vec![achieved])
            .with_i64("spheres", "1", vec![n as i64])
            .with_i64("attempts", "1", vec![attempts_total as i64]);
        let mut out = Outputs::new();
        out.insert("packing".into(), grainpipe_core::Artifact::Packing(packing));
        out.insert("report".into(), grainpipe_core::Artifact::Table(report));
        Ok(out)
    }
}
