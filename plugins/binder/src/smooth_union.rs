//! The level-set binder of Donval et al. (2025), section 2.3, on a voxel grid, with the
//! phase fractions made exact by selection instead of repeated re-voxelization.
//!
//! Signed distances to the spheres (eq. 2.11, negative inside, periodic where the cell is,
//! eq. 2.9) are combined by the scaled LogSumExp over the `k` smallest (eq. 2.14-2.15). Two
//! facts turn both fraction corrections of the paper's last paragraph of 2.3 into order
//! statistics of per-voxel numbers:
//! - growing every radius by `delta` shifts every distance by `-delta`, so a voxel is grain
//!   for the corrected radii iff its (sub-sampled median) smallest distance is `<= delta`;
//!   the grain count is hit by choosing `delta` as the right order statistic;
//! - `LSE_a(d)` decreases monotonically in `a` (its derivative is minus the entropy of the
//!   softmax weights), so each non-grain voxel has one threshold `a*` at which it joins the
//!   smoothed union, `LSE_{a*}(d - delta) = 0`; the binder count is hit by choosing `a` as an
//!   order statistic of `a*` (the bracketing root finder runs per voxel, on `a*`).
//!
//! Memory: one byte per voxel (the labels double as quantized thresholds between passes)
//! plus the sphere bins; the values near the selected rank are recomputed, not stored.

use grainpipe_core::raster::{
    min_distance, smallest_distances, Candidate, Over, RasterError, SphereRaster,
};
use grainpipe_core::{Grid, WorldSphere};

/// Smallest distances combined in eq. (2.15) at most.
pub const MAX_K: usize = 16;
/// Spheres further than `TRUNCATION * a` beyond the nearest contribute less than
/// e^-8 = 3.4e-4 of the nearest's weight to eq. (2.14) and are left out: with k = 5 terms
/// that moves the level set by less than 0.002 a.
const TRUNCATION: f64 = 8.0;
/// Half-width of the band of radius corrections searched, in voxels.
const BAND_VOXELS: f64 = 4.0;
/// Sphere-block pairs allowed in the bins (8 bytes each: 2 GiB).
const MAX_BIN_ENTRIES: u64 = 1 << 28;

const GRAIN: u8 = 255;
const NONE: u8 = 254;
const THRESHOLD_CODES: f64 = 254.0;

/// What fixes the smoothing scale `a`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BinderTarget {
    /// Choose `a` so that this many voxels are binder.
    Voxels(u64),
    /// Use this `a` [m].
    Scale(f64),
}

#[derive(Clone, Debug, PartialEq)]
pub struct SmoothUnionSpec {
    /// Distances combined by eq. (2.15).
    pub k: usize,
    /// Combine the distances to the k nearest bodies (each the exact distance to its union
    /// of spheres) instead of the k nearest spheres.
    pub per_body: bool,
    /// Sub-samples per axis in voxels cut by a grain surface.
    pub supersampling: usize,
    /// Grain voxels to hit by a uniform radius correction, or `None` to keep the radii.
    pub grain_voxels: Option<u64>,
    pub binder: BinderTarget,
    /// First upper bound of the search for `a` [m]; doubled while the target is not reached.
    pub initial_scale_bound: f64,
    /// The search for `a` gives up above this [m].
    pub max_scale: f64,
}

#[derive(Clone, Debug, PartialEq)]
pub struct SmoothUnion {
    /// 0 pore, 1 grain, 2 binder.
    pub labels: Vec<u8>,
    /// Radius correction applied to every sphere [m].
    pub delta: f64,
    /// Smoothing scale of eq. (2.14) [m].
    pub scale: f64,
    /// Full scans of the grid.
    pub passes: u32,
    /// Sphere-block pairs in the bins of the last scan.
    pub bin_entries: usize,
}

#[derive(Debug, Clone, PartialEq)]
pub enum BinderError {
    Raster(RasterError),
    /// The grain count is not reachable within the searched band of radius corrections.
    RadiusCorrection {
        target: u64,
        band: f64,
        side: &'static str,
    },
    /// Even `max_scale` does not give the binder asked for.
    Unreachable {
        target: u64,
        reached: u64,
        scale: f64,
    },
}

impl std::fmt::Display for BinderError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BinderError::Raster(e) => write!(f, "{e}"),
            BinderError::RadiusCorrection { target, band, side } => write!(
                f,
                "hitting the packing's analytic grain volume ({target} voxels) would need a \
                 radius correction {side} than {band:.3e} m ({BAND_VOXELS} voxels): the bodies \
                 overlap each other or the packing's volumes are wrong; set \
                 exact_fractions: false to keep the radii"
            ),
            BinderError::Unreachable {
                target,
                reached,
                scale,
            } => write!(
                f,
                "the binder fraction asked for needs {target} voxels, but even a = {scale:.3e} m \
                 gives only {reached}: the grains are too far apart for a smoothed union to \
                 fill that much; lower binder_fraction or raise k"
            ),
        }
    }
}

/// Converts a progress callback's error or a method failure into the caller's error type.
pub trait BinderFailure: From<BinderError> + Send {}
impl<E: From<BinderError> + Send> BinderFailure for E {}

/// Eq. (2.14) with distances shifted by nothing: `-a ln sum exp(-d_j / a)`, stably.
pub fn log_sum_exp(a: f64, d: &[f64]) -> f64 {
    let m = d.iter().copied().fold(f64::INFINITY, f64::min);
    m - a * d.iter().map(|&x| (-(x - m) / a).exp()).sum::<f64>().ln()
}

/// The scale `a*` at which `LSE_a(e) = 0` (eq. 2.14), for ascending `e` with `e[0] > 0`;
/// `None` above `cap`. In `u = 1/a`, `sum exp(-e_j u) - 1` is convex and decreasing, so
/// Newton's method from `u = 0` climbs monotonically to the root.
pub fn threshold_scale(e: &[f64], cap: f64) -> Option<f64> {
    if e.len() < 2 {
        return None;
    }
    let f = |u: f64| {
        let (mut s, mut ds) = (0.0, 0.0);
        for &x in e {
            let w = (-x * u).exp();
            s += w;
            ds -= x * w;
        }
        (s - 1.0, ds)
    };
    if f(1.0 / cap).0 < 0.0 {
        return None;
    }
    let mut u = 0.0f64;
    for _ in 0..200 {
        let (v, dv) = f(u);
        let next = u - v / dv;
        if next.is_nan() || next <= u || (next - u) <= 1e-15 * next {
            u = next.max(u);
            break;
        }
        u = next;
    }
    Some(1.0 / u)
}

/// Geometry shared by the passes.
struct Sampler {
    spacing: [f64; 3],
    half_diagonal: f64,
    band: f64,
    supersampling: usize,
}

impl Sampler {
    fn new(grid: &Grid, supersampling: usize) -> Self {
        let h = grid.spacing.iter().copied().fold(0.0, f64::max);
        Sampler {
            spacing: grid.spacing,
            half_diagonal: 0.5 * grid.spacing.iter().map(|s| s * s).sum::<f64>().sqrt(),
            band: BAND_VOXELS * h,
            supersampling,
        }
    }

    /// The grain statistic of a voxel: its smallest signed distance, or for voxels cut by a
    /// surface the median over sub-samples (a voxel is grain when at least half its
    /// sub-samples are). Exact within the band; clamped outside it.
    fn grain_statistic(&self, cands: &[Candidate], p: [f64; 3], buf: &mut Vec<f64>) -> f64 {
        let outer = self.band + self.half_diagonal;
        let centre = min_distance(cands, p, -outer, outer);
        let s = self.supersampling;
        if s <= 1 || centre.abs() > self.half_diagonal {
            return centre;
        }
        buf.clear();
        for k in 0..s * s * s {
            let sub = [k % s, (k / s) % s, k / (s * s)];
            let q: [f64; 3] = std::array::from_fn(|a| {
                p[a] + ((sub[a] as f64 + 0.5) / s as f64 - 0.5) * self.spacing[a]
            });
            buf.push(min_distance(cands, q, -outer, outer));
        }
        buf.sort_by(f64::total_cmp);
        buf[buf.len().div_ceil(2) - 1]
    }

    fn grain_code(&self, stat: f64) -> u8 {
        if stat < -self.band {
            0
        } else if stat > self.band {
            255
        } else {
            (1.0 + ((stat + self.band) / (2.0 * self.band) * 253.999).floor()).min(254.0) as u8
        }
    }
}

fn scale_code(a: f64, cap: f64) -> u8 {
    ((a / cap * THRESHOLD_CODES).floor()).min(THRESHOLD_CODES - 1.0) as u8
}

/// Which distances eq. (2.15) combines: the `k` smallest, over spheres or over bodies.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Smoothing {
    pub k: usize,
    pub per_body: bool,
}

/// Scratch for the smallest distances at one point.
pub struct Nearest {
    d: [f64; MAX_K],
    bodies: [u32; MAX_K],
}

impl Default for Nearest {
    fn default() -> Self {
        Nearest {
            d: [0.0; MAX_K],
            bodies: [0; MAX_K],
        }
    }
}

impl Nearest {
    /// Fills the smallest distances (ascending) within `window` of the nearest; returns how
    /// many. Nothing is searched beyond `beyond` when nothing closer was found; the search
    /// gives up (returning 0) when `give_up` says so.
    fn find(
        &mut self,
        cands: &[Candidate],
        p: [f64; 3],
        sm: Smoothing,
        (window, beyond): (f64, f64),
        give_up: impl Fn(&[f64], f64) -> bool,
    ) -> usize {
        let over = if sm.per_body {
            Over::Bodies
        } else {
            Over::Spheres
        };
        smallest_distances(
            cands,
            p,
            over,
            (window, beyond),
            (&mut self.d[..sm.k], &mut self.bodies[..sm.k]),
            give_up,
        )
    }
}

/// Threshold `a*` at one point for radius correction `delta`: 0 inside a corrected sphere,
/// `None` when above `cap`.
fn point_threshold(
    cands: &[Candidate],
    p: [f64; 3],
    sm: Smoothing,
    delta: f64,
    cap: f64,
    near: &mut Nearest,
) -> Option<f64> {
    let ln_k = (sm.k as f64).ln();
    // Every distance still to come is at least `bound`, so the k terms of eq. (2.14) at
    // a = cap sum to at most the found ones (each capped at the bound's weight) plus the
    // bound's weight for the missing ones. Below 1 the point joins the union only above
    // cap: stop there (most points near a lone grain surface end here).
    let give_up = |found: &[f64], bound: f64| {
        let w = |d: f64| (-(d - delta) / cap).exp();
        let wb = w(bound);
        let most: f64 =
            found.iter().map(|&d| w(d).max(wb)).sum::<f64>() + (sm.k - found.len()) as f64 * wb;
        most < 1.0
    };
    let n = near.find(
        cands,
        p,
        sm,
        (TRUNCATION * cap, delta + cap * ln_k),
        give_up,
    );
    if n == 0 || near.d[0] - delta > cap * ln_k {
        return None;
    }
    let e = &mut near.d[..n];
    e.iter_mut().for_each(|d| *d -= delta);
    if e[0] <= 0.0 {
        return Some(0.0);
    }
    threshold_scale(e, cap)
}

impl Sampler {
    /// Threshold `a*` of a non-grain voxel: at its centre, or for a voxel cut by a grain
    /// surface the median over the same sub-samples that voted it pore, so that a voxel is
    /// in the smoothed union exactly when at least half of its sub-samples are (the rule
    /// that made it not sand). `None` above `cap`.
    fn voxel_threshold(
        &self,
        cands: &[Candidate],
        p: [f64; 3],
        (sm, delta, cap): (Smoothing, f64, f64),
        near: &mut Nearest,
        buf: &mut Vec<f64>,
    ) -> Option<f64> {
        let centre = point_threshold(cands, p, sm, delta, cap, near);
        let s = self.supersampling;
        let surface = min_distance(cands, p, f64::NEG_INFINITY, delta + self.half_diagonal);
        if s <= 1 || (surface - delta).abs() > self.half_diagonal {
            return centre;
        }
        buf.clear();
        for m in 0..s * s * s {
            let sub = [m % s, (m / s) % s, m / (s * s)];
            let q: [f64; 3] = std::array::from_fn(|a| {
                p[a] + ((sub[a] as f64 + 0.5) / s as f64 - 0.5) * self.spacing[a]
            });
            buf.push(point_threshold(cands, q, sm, delta, cap, near).unwrap_or(f64::INFINITY));
        }
        buf.sort_by(f64::total_cmp);
        Some(buf[buf.len().div_ceil(2) - 1]).filter(|t| t.is_finite())
    }
}

/// Rank selection over codes: the code whose cumulative count first reaches `rank`
/// (1-based), and the count below it.
fn crossing(
    hist: &[u64; 256],
    codes: std::ops::RangeInclusive<usize>,
    rank: u64,
) -> Option<(usize, u64)> {
    let mut below = 0u64;
    for c in codes {
        if below + hist[c] >= rank {
            return Some((c, below));
        }
        below += hist[c];
    }
    None
}

fn sum_histograms(parts: Vec<[u64; 256]>) -> [u64; 256] {
    let mut h = [0u64; 256];
    for p in parts {
        for (a, b) in h.iter_mut().zip(p) {
            *a += b;
        }
    }
    h
}

/// Builds the three-phase labels. `progress(done, total)` is called per slab of each scan.
/// The largest reach of the rasters [`smooth_union`] builds on voxels of edge `h` when the
/// binder pass smooths `k` spheres at scales up to `max_scale` (0 without a binder pass):
/// the band of radius corrections plus half a voxel diagonal, or the truncated smoothing.
pub fn max_reach(h: f64, max_scale: f64, k: usize) -> f64 {
    let grain = BAND_VOXELS * h + 0.5 * 3f64.sqrt() * h;
    let ln_k = (k.clamp(1, MAX_K) as f64).ln();
    grain.max(BAND_VOXELS * h + max_scale * (ln_k + TRUNCATION))
}

pub fn smooth_union<E, P>(
    grid: &Grid,
    spheres: &[WorldSphere],
    spec: &SmoothUnionSpec,
    progress: &P,
) -> Result<SmoothUnion, E>
where
    E: BinderFailure,
    P: Fn(u64, u64) -> Result<(), E> + Sync,
{
    let sm = Smoothing {
        k: spec.k.clamp(1, MAX_K),
        per_body: spec.per_body,
    };
    let ln_k = (sm.k as f64).ln();
    let sampler = Sampler::new(grid, spec.supersampling);
    let n = grid.voxel_count();
    let mut labels = vec![0u8; n];
    let mut passes = 0u32;
    let build = |reach: f64| {
        SphereRaster::with_budget(grid, spheres, reach, MAX_BIN_ENTRIES)
            .map_err(|e| E::from(BinderError::Raster(e)))
    };

    // Pass 1: grain statistics, quantized into the labels, and the radius correction.
    let grain_reach = sampler.band + sampler.half_diagonal;
    let mut delta = 0.0;
    let mut grain_split: Option<(u8, f64)> = None;
    if let Some(target) = spec.grain_voxels {
        let raster = build(grain_reach)?;
        let hists = raster.scan(
            &mut labels,
            || (Vec::new(), [0u64; 256]),
            |(buf, hist), cands, _, p, code| {
                *code = sampler.grain_code(sampler.grain_statistic(cands, p, buf));
                hist[*code as usize] += 1;
            },
            progress,
        )?;
        passes += 1;
        let hist = sum_histograms(hists.into_iter().map(|h| h.1).collect());
        if target == 0 {
            delta = -sampler.band;
            grain_split = Some((0, f64::NEG_INFINITY));
        } else {
            let (c, below) = crossing(&hist, 0..=255, target).expect("target <= voxel count");
            if c == 0 || c == 255 {
                return Err(E::from(BinderError::RadiusCorrection {
                    target,
                    band: sampler.band,
                    side: if c == 0 { "smaller" } else { "larger" },
                }));
            }
            // The exact statistic of the voxels in the crossing code, recomputed.
            let vals = raster.scan(
                &mut labels,
                || (Vec::new(), Vec::new()),
                |(buf, vals): &mut (Vec<f64>, Vec<f64>), cands, _, p, code| {
                    if *code as usize == c {
                        vals.push(sampler.grain_statistic(cands, p, buf));
                    }
                },
                progress,
            )?;
            let mut vals: Vec<f64> = vals.into_iter().flat_map(|v| v.1).collect();
            vals.sort_by(f64::total_cmp);
            delta = vals[(target - below - 1) as usize];
            grain_split = Some((c as u8, delta));
        }
    }
    let is_grain =
        |cands: &[Candidate], p: [f64; 3], code: u8, buf: &mut Vec<f64>| match grain_split {
            Some((c, d)) => code < c || (code == c && sampler.grain_statistic(cands, p, buf) <= d),
            None => sampler.grain_statistic(cands, p, buf) <= 0.0,
        };

    // Pass 2: grains, and each other voxel's threshold scale, quantized.
    let target = match spec.binder {
        BinderTarget::Voxels(0) => {
            let raster = build(grain_reach)?;
            raster.scan(
                &mut labels,
                Vec::new,
                |buf, cands, _, p, code| *code = u8::from(is_grain(cands, p, *code, buf)),
                progress,
            )?;
            passes += 1;
            return Ok(SmoothUnion {
                labels,
                delta,
                scale: 0.0,
                passes,
                bin_entries: raster.entries(),
            });
        }
        BinderTarget::Scale(a) => {
            let raster = build(grain_reach.max(delta + a * (ln_k + TRUNCATION)))?;
            raster.scan(
                &mut labels,
                || (Vec::new(), Nearest::default()),
                |(buf, dist), cands, _, p, code| {
                    *code = if is_grain(cands, p, *code, buf) {
                        1
                    } else if sampler
                        .voxel_threshold(cands, p, (sm, delta, a), dist, buf)
                        .is_some_and(|t| t <= a)
                    {
                        2
                    } else {
                        0
                    };
                },
                progress,
            )?;
            passes += 1;
            return Ok(SmoothUnion {
                labels,
                delta,
                scale: a,
                passes,
                bin_entries: raster.entries(),
            });
        }
        BinderTarget::Voxels(t) => t,
    };
    let mut cap = spec.initial_scale_bound.min(spec.max_scale);
    let mut first = true;
    loop {
        let raster = build(grain_reach.max(delta + cap * (ln_k + TRUNCATION)))?;
        let hists = raster.scan(
            &mut labels,
            || (Vec::new(), Nearest::default(), [0u64; 256]),
            |(buf, dist, hist), cands, _, p, code| {
                let grain = if first {
                    is_grain(cands, p, *code, buf)
                } else {
                    *code == GRAIN
                };
                *code = if grain {
                    GRAIN
                } else {
                    match sampler.voxel_threshold(cands, p, (sm, delta, cap), dist, buf) {
                        Some(t) => scale_code(t, cap),
                        None => NONE,
                    }
                };
                hist[*code as usize] += 1;
            },
            progress,
        )?;
        passes += 1;
        first = false;
        let hist = sum_histograms(hists.into_iter().map(|h| h.2).collect());
        let Some((c, below)) = crossing(&hist, 0..=(NONE as usize - 1), target) else {
            let reached: u64 = hist[..NONE as usize].iter().sum();
            if cap >= spec.max_scale {
                return Err(E::from(BinderError::Unreachable {
                    target,
                    reached,
                    scale: cap,
                }));
            }
            cap = (2.0 * cap).min(spec.max_scale);
            continue;
        };
        let vals = raster.scan(
            &mut labels,
            || (Nearest::default(), Vec::new(), Vec::new()),
            |(dist, vals, buf), cands, _, p, code| {
                if *code as usize == c {
                    vals.push(
                        sampler
                            .voxel_threshold(cands, p, (sm, delta, cap), dist, buf)
                            .unwrap_or(f64::INFINITY),
                    );
                }
            },
            progress,
        )?;
        let mut vals: Vec<f64> = vals.into_iter().flat_map(|v| v.1).collect();
        vals.sort_by(f64::total_cmp);
        let a = vals[(target - below - 1) as usize];
        // Pass 3: final labels.
        raster.scan(
            &mut labels,
            || (Nearest::default(), Vec::new()),
            |(dist, buf), cands, _, p, code| {
                *code = match *code {
                    GRAIN => 1,
                    NONE => 0,
                    x if (x as usize) < c => 2,
                    x if x as usize == c
                        && sampler
                            .voxel_threshold(cands, p, (sm, delta, cap), dist, buf)
                            .is_some_and(|t| t <= a) =>
                    {
                        2
                    }
                    _ => 0,
                };
            },
            progress,
        )?;
        passes += 1;
        return Ok(SmoothUnion {
            labels,
            delta,
            scale: a,
            passes,
            bin_entries: raster.entries(),
        });
    }
}

/// The two distances of eq. (2.15) at a point, shared by the level set and the sub-voxel
/// sampling: the k nearest corrected sphere distances within `window` of the nearest,
/// searched out to `beyond` (= clamp + delta) from the point.
struct SmoothedDistance {
    sm: Smoothing,
    delta: f64,
    a: f64,
    window: f64,
    beyond: f64,
}

impl SmoothedDistance {
    fn new(sm: Smoothing, delta: f64, a: f64, clamp: f64) -> Self {
        SmoothedDistance {
            sm: Smoothing {
                k: sm.k.clamp(1, MAX_K),
                ..sm
            },
            delta,
            a,
            window: if a > 0.0 { TRUNCATION * a } else { 0.0 },
            beyond: clamp + delta,
        }
    }

    /// The block raster that holds every sphere this search can reach.
    fn raster<E: BinderFailure>(
        &self,
        grid: &Grid,
        spheres: &[WorldSphere],
    ) -> Result<SphereRaster, E> {
        SphereRaster::with_budget(grid, spheres, self.beyond + self.window, MAX_BIN_ENTRIES)
            .map_err(|e| E::from(BinderError::Raster(e)))
    }

    /// `(d_min - delta, LSE_a(d - delta))` at `p` (the second is `d_min - delta` for
    /// `a = 0`), `None` when no sphere is within `beyond`.
    fn at(&self, cands: &[Candidate], p: [f64; 3], near: &mut Nearest) -> Option<(f64, f64)> {
        let n = near.find(cands, p, self.sm, (self.window, self.beyond), |_, _| false);
        if n == 0 {
            return None;
        }
        let nearest = near.d[0] - self.delta;
        let smoothed = if self.a > 0.0 {
            log_sum_exp(self.a, &near.d[..n]) - self.delta
        } else {
            nearest
        };
        Some((nearest, smoothed))
    }
}

/// The smoothed level set `LSE_a(d - delta)` (eq. 2.15) at every voxel centre, clamped to
/// `[-clamp, clamp]` (voxels with no sphere within `clamp` get `clamp`).
pub fn level_set<E, P>(
    grid: &Grid,
    spheres: &[WorldSphere],
    sm: Smoothing,
    delta: f64,
    a: f64,
    clamp: f64,
    progress: &P,
) -> Result<Vec<f32>, E>
where
    E: BinderFailure,
    P: Fn(u64, u64) -> Result<(), E> + Sync,
{
    let search = SmoothedDistance::new(sm, delta, a, clamp);
    let raster = search.raster::<E>(grid, spheres)?;
    let mut field = vec![0f32; grid.voxel_count()];
    raster.scan(
        &mut field,
        Nearest::default,
        |near, cands, _, p, v| {
            let value = search.at(cands, p, near).map_or(clamp, |(_, lse)| lse);
            *v = value.clamp(-clamp, clamp) as f32;
        },
        progress,
    )?;
    Ok(field)
}

/// Sub-voxel samples (see `grainpipe_core::subvoxel`) of the three-phase image at the
/// voxels flagged in `which`: each sub-sample is sand inside a corrected sphere
/// (`d - delta <= 0`), binder in the smoothed union (`LSE_a(d - delta) <= 0`, eq. 2.15),
/// else pore — the rules the labels follow at voxel centres. Phase indices 0 pore, 1 sand,
/// 2 binder.
#[allow(clippy::too_many_arguments)]
pub fn subvoxel_samples<E, P>(
    grid: &Grid,
    spheres: &[WorldSphere],
    sm: Smoothing,
    delta: f64,
    a: f64,
    which: &[bool],
    samples: usize,
    progress: &P,
) -> Result<Vec<grainpipe_core::subvoxel::VoxelSamples>, E>
where
    E: BinderFailure,
    P: Fn(u64, u64) -> Result<(), E> + Sync,
{
    // A point further than a ln k from every corrected sphere is outside the union
    // (LSE_a >= d_min - a ln k); sub-samples lie within half a diagonal of the centre.
    let half_diagonal = 0.5 * grid.spacing.iter().map(|s| s * s).sum::<f64>().sqrt();
    let clamp = a * (sm.k.clamp(1, MAX_K) as f64).ln() + 2.0 * half_diagonal;
    let search = SmoothedDistance::new(sm, delta, a, clamp);
    let raster = search.raster::<E>(grid, spheres)?;
    let mut slots = vec![0u8; grid.voxel_count()];
    let [nx, ny, _] = grid.dims;
    let per_slab = raster.scan(
        &mut slots,
        || (Vec::new(), Nearest::default()),
        |(acc, near): &mut (Vec<grainpipe_core::subvoxel::VoxelSamples>, Nearest),
         cands,
         [x, y, z],
         p,
         _| {
            let v = x + nx * (y + ny * z);
            if which[v] {
                let s = grainpipe_core::subvoxel::sample_voxel(p, grid.spacing, samples, 3, |q| {
                    match search.at(cands, q, near) {
                        None => 0,
                        Some((nearest, _)) if nearest <= 0.0 => 1,
                        Some((_, lse)) if lse <= 0.0 => 2,
                        Some(_) => 0,
                    }
                });
                acc.push((v, s));
            }
        },
        progress,
    )?;
    Ok(per_slab.into_iter().flat_map(|(acc, _)| acc).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threshold_solves_the_log_sum_exp_root() {
        for e in [
            vec![1.0, 1.0],
            vec![0.3, 2.0, 5.0],
            vec![1e-3, 1.0, 1.0, 40.0, 41.0],
        ] {
            let a = threshold_scale(&e, 1e9).unwrap();
            assert!(
                log_sum_exp(a, &e).abs() < 1e-12 * e[0].max(a),
                "{e:?} -> {a}"
            );
        }
        // Two equal distances: LSE_a = d - a ln 2 (eq. 2.14), so a* = d / ln 2.
        let a = threshold_scale(&[2.0, 2.0], 1e9).unwrap();
        assert!((a - 2.0 / 2f64.ln()).abs() < 1e-12);
        assert_eq!(threshold_scale(&[2.0, 2.0], 1.0), None);
        assert_eq!(threshold_scale(&[2.0], 1e9), None);
    }
}
