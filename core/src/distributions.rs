//! Size (radius, diameter, length) distributions shared by every packing stage.
//!
//! One serde enum, internally tagged by `kind`, covers the laws Matlab's `makedist` users
//! need for powder sizes: `fixed`, `uniform`, `normal`, `lognormal`, `weibull`, `gamma`,
//! `exponential`, `beta` (on `[min, max]`), `triangular` and `tabulated` (a piecewise-linear
//! CDF). Unbounded laws accept optional `min` / `max` truncation bounds. In YAML:
//!
//! ```yaml
//! radius: { kind: weibull, scale: 15.7 um, shape: 3.55 }
//! radius: { kind: normal, mean: 20 um, std_dev: 4 um, min: 10 um }
//! radius: { kind: tabulated, points: [[10 um, 0.0], [14 um, 0.5], [25 um, 1.0]] }
//! ```
//!
//! Sizes are positive: every law is additionally truncated to `x > 0` (this only matters for
//! a normal law whose mean is within a few standard deviations of 0).
//!
//! Sampling is by inversion of the (truncated) CDF, so a draw costs one uniform number,
//! truncation is exact (no rejection loop) and equal seeds give equal sizes on every platform.

use crate::units::{Length, Q};
use rand::Rng;
use serde::{Deserialize, Serialize};
use statrs::distribution::{Beta as SBeta, ContinuousCDF, Gamma as SGamma};
use statrs::function::{erf, gamma as gfn};
use std::cmp::Ordering;

type Len = Q<Length>;

fn is_none<T>(o: &Option<T>) -> bool {
    o.is_none()
}

/// A size distribution (values in metres). See the module documentation for the YAML form.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum SizeDistribution {
    /// Every draw equals `value`.
    Fixed { value: Len },
    /// Uniform on `[min, max]`.
    Uniform { min: Len, max: Len },
    /// Normal with `mean` and `std_dev`, optionally truncated to `[min, max]`.
    Normal {
        mean: Len,
        std_dev: Len,
        #[serde(default, skip_serializing_if = "is_none")]
        min: Option<Len>,
        #[serde(default, skip_serializing_if = "is_none")]
        max: Option<Len>,
    },
    /// Log-normal: `ln x` is normal with mean `ln(median)` and standard deviation `sigma`
    /// (Matlab's `mu` is `ln(median)` in the unit of the data).
    Lognormal {
        median: Len,
        sigma: f64,
        #[serde(default, skip_serializing_if = "is_none")]
        min: Option<Len>,
        #[serde(default, skip_serializing_if = "is_none")]
        max: Option<Len>,
    },
    /// Weibull, CDF `1 - exp(-(x/scale)^shape)` (Matlab `makedist('Weibull','a',scale,'b',shape)`).
    Weibull {
        scale: Len,
        shape: f64,
        #[serde(default, skip_serializing_if = "is_none")]
        min: Option<Len>,
        #[serde(default, skip_serializing_if = "is_none")]
        max: Option<Len>,
    },
    /// Gamma with shape `k` and scale `theta`, mean `k theta` (Matlab `'a'` = shape, `'b'` = scale).
    Gamma {
        shape: f64,
        scale: Len,
        #[serde(default, skip_serializing_if = "is_none")]
        min: Option<Len>,
        #[serde(default, skip_serializing_if = "is_none")]
        max: Option<Len>,
    },
    /// Exponential with the given `mean`.
    Exponential {
        mean: Len,
        #[serde(default, skip_serializing_if = "is_none")]
        min: Option<Len>,
        #[serde(default, skip_serializing_if = "is_none")]
        max: Option<Len>,
    },
    /// Beta(`alpha`, `beta`) stretched onto `[min, max]`.
    Beta {
        alpha: f64,
        beta: f64,
        min: Len,
        max: Len,
    },
    /// Triangular on `[min, max]` with peak at `mode`.
    Triangular { min: Len, mode: Len, max: Len },
    /// Piecewise-linear CDF through `points` = `[[size, cumulative probability], ...]`,
    /// sizes increasing, probabilities non-decreasing from 0 to 1.
    Tabulated {
        points: Vec<(Len, f64)>,
        #[serde(default, skip_serializing_if = "is_none")]
        min: Option<Len>,
        #[serde(default, skip_serializing_if = "is_none")]
        max: Option<Len>,
    },
}

impl crate::params::ParamType for SizeDistribution {
    fn type_name() -> String {
        "size distribution ({kind: fixed | uniform | normal | lognormal | weibull | gamma | \
         exponential | beta | triangular | tabulated, ...})"
            .to_string()
    }
    fn unit() -> &'static str {
        "m"
    }
    fn schema() -> serde_json::Value {
        serde_json::json!({
            "type": "object",
            "required": ["kind"],
            "properties": {"kind": {"enum": [
                "fixed", "uniform", "normal", "lognormal", "weibull", "gamma", "exponential",
                "beta", "triangular", "tabulated"
            ]}}
        })
    }
}

impl Default for SizeDistribution {
    /// The 316L powder radius law of the sphere-filling paper, eq. (2.4):
    /// Weibull with scale 15.7 um and shape 3.55 (mean radius 14.14 um).
    fn default() -> Self {
        SizeDistribution::Weibull {
            scale: Q::new(15.7e-6),
            shape: 3.55,
            min: None,
            max: None,
        }
    }
}

fn opt(v: &Option<Len>) -> Option<f64> {
    v.map(|q| q.si())
}

fn std_normal_cdf(z: f64) -> f64 {
    0.5 * erf::erfc(-z / std::f64::consts::SQRT_2)
}

fn std_normal_quantile(p: f64) -> f64 {
    -std::f64::consts::SQRT_2 * erf::erfc_inv(2.0 * p)
}

impl SizeDistribution {
    /// Checks the parameters. On error returns the offending key (`"scale"`, `"points"`,
    /// `"min"`, ...) and a message saying what would work; stages report it as
    /// `StageError::param(&format!("{their_key}.{key}"), message)`.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        use SizeDistribution::*;
        fn pos(key: &'static str, v: f64) -> Result<(), (&'static str, String)> {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err((key, format!("must be a positive finite number, got {v}")))
            }
        }
        fn nonneg(key: &'static str, v: f64) -> Result<(), (&'static str, String)> {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err((key, format!("must be a finite size >= 0, got {v} m")))
            }
        }
        fn ordered(lo: f64, hi: f64) -> Result<(), (&'static str, String)> {
            if hi > lo {
                Ok(())
            } else {
                Err(("max", format!("max ({hi} m) must exceed min ({lo} m)")))
            }
        }
        match self {
            Fixed { value } => pos("value", value.si())?,
            Uniform { min, max } | Beta { min, max, .. } => {
                nonneg("min", min.si())?;
                pos("max", max.si())?;
                ordered(min.si(), max.si())?;
                if let Beta { alpha, beta, .. } = self {
                    pos("alpha", *alpha)?;
                    pos("beta", *beta)?;
                }
            }
            Triangular { min, mode, max } => {
                nonneg("min", min.si())?;
                pos("max", max.si())?;
                ordered(min.si(), max.si())?;
                let m = mode.si();
                if !(m >= min.si() && m <= max.si()) {
                    return Err(("mode", format!("mode ({m} m) must lie in [min, max]")));
                }
            }
            Normal { mean, std_dev, .. } => {
                if !mean.si().is_finite() {
                    return Err(("mean", "must be finite".into()));
                }
                pos("std_dev", std_dev.si())?;
            }
            Lognormal { median, sigma, .. } => {
                pos("median", median.si())?;
                pos("sigma", *sigma)?;
            }
            Weibull { scale, shape, .. } => {
                pos("scale", scale.si())?;
                pos("shape", *shape)?;
            }
            Gamma { shape, scale, .. } => {
                pos("shape", *shape)?;
                pos("scale", scale.si())?;
            }
            Exponential { mean, .. } => pos("mean", mean.si())?,
            Tabulated { points, .. } => {
                if points.len() < 2 {
                    return Err((
                        "points",
                        "needs at least two [size, probability] points".into(),
                    ));
                }
                for (i, w) in points.windows(2).enumerate() {
                    if w[1].0.si().partial_cmp(&w[0].0.si()) != Some(Ordering::Greater) {
                        return Err((
                            "points",
                            format!("sizes must increase strictly (point {} vs {})", i, i + 1),
                        ));
                    }
                    if !matches!(
                        w[1].1.partial_cmp(&w[0].1),
                        Some(Ordering::Greater | Ordering::Equal)
                    ) {
                        return Err((
                            "points",
                            format!("probabilities must not decrease (point {} vs {})", i, i + 1),
                        ));
                    }
                }
                nonneg("points", points[0].0.si())?;
                let (p0, p1) = (points[0].1, points[points.len() - 1].1);
                if p0 != 0.0 || p1 != 1.0 {
                    return Err((
                        "points",
                        format!("the CDF must run from 0 to 1, got {p0} .. {p1}"),
                    ));
                }
            }
        }
        if let Some((lo, hi)) = self.user_bounds() {
            if let Some(l) = lo {
                if !l.is_finite() {
                    return Err(("min", "must be finite".into()));
                }
            }
            if let Some(h) = hi {
                if !(h.is_finite() && h > 0.0) {
                    return Err(("max", format!("must be a positive finite size, got {h} m")));
                }
            }
            if let (Some(l), Some(h)) = (lo, hi) {
                ordered(l, h)?;
            }
        }
        let (lo, hi) = self.bounds();
        if hi.partial_cmp(&lo) != Some(Ordering::Greater) && !matches!(self, Fixed { .. }) {
            return Err((
                "min",
                format!("the truncation interval [{lo}, {hi}] m (sizes are also > 0) is empty"),
            ));
        }
        let mass = self.base_cdf(hi) - self.base_cdf(lo);
        if mass.partial_cmp(&1e-12) != Some(Ordering::Greater) && !matches!(self, Fixed { .. }) {
            return Err((
                "min",
                format!(
                    "the truncation interval [{lo}, {hi}] m holds probability {mass:e}: \
                     widen min/max towards the bulk of the distribution"
                ),
            ));
        }
        Ok(())
    }

    /// The user's optional truncation bounds (only for unbounded laws).
    fn user_bounds(&self) -> Option<(Option<f64>, Option<f64>)> {
        use SizeDistribution::*;
        match self {
            Normal { min, max, .. }
            | Lognormal { min, max, .. }
            | Weibull { min, max, .. }
            | Gamma { min, max, .. }
            | Exponential { min, max, .. }
            | Tabulated { min, max, .. } => Some((opt(min), opt(max))),
            _ => None,
        }
    }

    /// Natural support of the untruncated law.
    fn natural_support(&self) -> (f64, f64) {
        use SizeDistribution::*;
        match self {
            Fixed { value } => (value.si(), value.si()),
            Uniform { min, max } | Beta { min, max, .. } | Triangular { min, max, .. } => {
                (min.si(), max.si())
            }
            Normal { .. } => (f64::NEG_INFINITY, f64::INFINITY),
            Lognormal { .. } | Weibull { .. } | Gamma { .. } | Exponential { .. } => {
                (0.0, f64::INFINITY)
            }
            Tabulated { points, .. } => (points[0].0.si(), points[points.len() - 1].0.si()),
        }
    }

    /// Effective support `[lo, hi]` after truncation (user bounds and `x > 0`).
    pub fn bounds(&self) -> (f64, f64) {
        let (mut lo, mut hi) = self.natural_support();
        if let Some((l, h)) = self.user_bounds() {
            if let Some(l) = l {
                lo = lo.max(l);
            }
            if let Some(h) = h {
                hi = hi.min(h);
            }
        }
        (lo.max(0.0), hi)
    }

    /// CDF of the untruncated law.
    fn base_cdf(&self, x: f64) -> f64 {
        use SizeDistribution::*;
        if x == f64::INFINITY {
            return 1.0;
        }
        if x == f64::NEG_INFINITY {
            return 0.0;
        }
        match self {
            Fixed { value } => {
                if x >= value.si() {
                    1.0
                } else {
                    0.0
                }
            }
            Uniform { min, max } => ((x - min.si()) / (max.si() - min.si())).clamp(0.0, 1.0),
            Normal { mean, std_dev, .. } => std_normal_cdf((x - mean.si()) / std_dev.si()),
            Lognormal { median, sigma, .. } => {
                if x <= 0.0 {
                    0.0
                } else {
                    std_normal_cdf((x / median.si()).ln() / sigma)
                }
            }
            Weibull { scale, shape, .. } => {
                if x <= 0.0 {
                    0.0
                } else {
                    // F = 1 - exp(-(x/lambda)^k), written with exp_m1 for small x.
                    -(-(x / scale.si()).powf(*shape)).exp_m1()
                }
            }
            Gamma { shape, scale, .. } => {
                if x <= 0.0 {
                    0.0
                } else {
                    gfn::gamma_lr(*shape, x / scale.si())
                }
            }
            Exponential { mean, .. } => {
                if x <= 0.0 {
                    0.0
                } else {
                    -(-x / mean.si()).exp_m1()
                }
            }
            Beta {
                alpha,
                beta,
                min,
                max,
            } => {
                let t = (x - min.si()) / (max.si() - min.si());
                if t <= 0.0 {
                    0.0
                } else if t >= 1.0 {
                    1.0
                } else {
                    statrs::function::beta::beta_reg(*alpha, *beta, t)
                }
            }
            Triangular { min, mode, max } => {
                let (a, c, b) = (min.si(), mode.si(), max.si());
                if x <= a {
                    0.0
                } else if x >= b {
                    1.0
                } else if x <= c {
                    (x - a) * (x - a) / ((b - a) * (c - a))
                } else {
                    1.0 - (b - x) * (b - x) / ((b - a) * (b - c))
                }
            }
            Tabulated { points, .. } => {
                if x <= points[0].0.si() {
                    return 0.0;
                }
                if x >= points[points.len() - 1].0.si() {
                    return 1.0;
                }
                let k = points.partition_point(|p| p.0.si() <= x);
                let (x0, p0) = (points[k - 1].0.si(), points[k - 1].1);
                let (x1, p1) = (points[k].0.si(), points[k].1);
                p0 + (p1 - p0) * (x - x0) / (x1 - x0)
            }
        }
    }

    /// Quantile of the untruncated law, `p` in [0, 1].
    fn base_quantile(&self, p: f64) -> f64 {
        use SizeDistribution::*;
        let p = p.clamp(0.0, 1.0);
        match self {
            Fixed { value } => value.si(),
            Uniform { min, max } => min.si() + p * (max.si() - min.si()),
            Normal { mean, std_dev, .. } => mean.si() + std_dev.si() * std_normal_quantile(p),
            Lognormal { median, sigma, .. } => median.si() * (sigma * std_normal_quantile(p)).exp(),
            // x = lambda (-ln(1-p))^(1/k), with ln_1p for accuracy at small p.
            Weibull { scale, shape, .. } => scale.si() * (-(-p).ln_1p()).powf(1.0 / shape),
            Gamma { shape, scale, .. } => {
                // Unit scale keeps statrs' bracketing (which starts at 1) well conditioned.
                let g = SGamma::new(*shape, 1.0).expect("validated gamma");
                scale.si() * g.inverse_cdf(p)
            }
            Exponential { mean, .. } => -mean.si() * (-p).ln_1p(),
            Beta {
                alpha,
                beta,
                min,
                max,
            } => {
                let b = SBeta::new(*alpha, *beta).expect("validated beta");
                min.si() + (max.si() - min.si()) * b.inverse_cdf(p)
            }
            Triangular { min, mode, max } => {
                let (a, c, b) = (min.si(), mode.si(), max.si());
                if p * (b - a) < c - a {
                    a + (p * (b - a) * (c - a)).sqrt()
                } else {
                    b - ((1.0 - p) * (b - a) * (b - c)).sqrt()
                }
            }
            Tabulated { points, .. } => {
                // First segment whose upper probability reaches p (skips flat pieces).
                let k = points
                    .partition_point(|q| q.1 < p)
                    .clamp(1, points.len() - 1);
                let (x0, p0) = (points[k - 1].0.si(), points[k - 1].1);
                let (x1, p1) = (points[k].0.si(), points[k].1);
                if p1 > p0 {
                    x0 + (x1 - x0) * (p - p0) / (p1 - p0)
                } else {
                    x0
                }
            }
        }
    }

    /// CDF mass of the untruncated law below the effective bounds and inside them.
    fn trunc(&self) -> (f64, f64) {
        let (lo, hi) = self.bounds();
        let f_lo = self.base_cdf(lo);
        (f_lo, self.base_cdf(hi) - f_lo)
    }

    /// Cumulative distribution function of the (truncated) law at `x` [m].
    pub fn cdf(&self, x: f64) -> f64 {
        if let SizeDistribution::Fixed { .. } = self {
            return self.base_cdf(x);
        }
        let (lo, hi) = self.bounds();
        if x <= lo {
            return 0.0;
        }
        if x >= hi {
            return 1.0;
        }
        let (f_lo, mass) = self.trunc();
        ((self.base_cdf(x) - f_lo) / mass).clamp(0.0, 1.0)
    }

    /// Quantile (inverse CDF) of the (truncated) law, `u` in [0, 1] [m].
    pub fn quantile(&self, u: f64) -> f64 {
        if let SizeDistribution::Fixed { value } = self {
            return value.si();
        }
        let (lo, hi) = self.bounds();
        let (f_lo, mass) = self.trunc();
        // Truncated inverse: Q_t(u) = Q(F(lo) + u (F(hi) - F(lo))), clamped against round-off.
        self.base_quantile(f_lo + u.clamp(0.0, 1.0) * mass)
            .clamp(lo, hi)
    }

    /// One draw by inversion of the CDF. Consumes exactly one `u64` from `rng`.
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        // 53 random bits mapped to the open interval (0, 1): never exactly 0 or 1, so
        // unbounded laws never return 0 or infinity.
        let u = ((rng.next_u64() >> 11) as f64 + 0.5) * (1.0 / (1u64 << 53) as f64);
        self.quantile(u)
    }

    /// Mean of the (truncated) law [m]. Closed forms without truncation; otherwise
    /// `lo + integral_lo^hi (1 - F_t(x)) dx` by composite Gauss-Legendre quadrature.
    pub fn mean(&self) -> f64 {
        use SizeDistribution::*;
        let (f_lo, mass) = self.trunc();
        let untruncated = f_lo == 0.0 && mass == 1.0;
        match self {
            Fixed { value } => return value.si(),
            Uniform { min, max } => return 0.5 * (min.si() + max.si()),
            Triangular { min, mode, max } => return (min.si() + mode.si() + max.si()) / 3.0,
            Beta {
                alpha,
                beta,
                min,
                max,
            } => return min.si() + (max.si() - min.si()) * alpha / (alpha + beta),
            Tabulated { points, .. } if untruncated => {
                // Piecewise-uniform density: each segment contributes its probability times
                // its midpoint.
                return points
                    .windows(2)
                    .map(|w| (w[1].1 - w[0].1) * 0.5 * (w[0].0.si() + w[1].0.si()))
                    .sum();
            }
            Normal { mean, .. } if untruncated => return mean.si(),
            Lognormal { median, sigma, .. } if untruncated => {
                return median.si() * (0.5 * sigma * sigma).exp()
            }
            // eq. (2.3) of the sphere-filling paper: mean = lambda Gamma(1 + 1/k).
            Weibull { scale, shape, .. } if untruncated => {
                return scale.si() * gfn::gamma(1.0 + 1.0 / shape)
            }
            // eq. (3.7): mean = k theta.
            Gamma { shape, scale, .. } if untruncated => return shape * scale.si(),
            Exponential { mean, .. } if untruncated => return mean.si(),
            _ => {}
        }
        let (lo, hi) = self.bounds();
        let hi = if hi.is_finite() {
            hi
        } else {
            // Beyond this quantile the tail adds < 1e-13 of the mean for the laws offered.
            self.quantile(1.0 - 1e-14)
        };
        lo + integrate(|x| 1.0 - self.cdf(x), lo, hi, 256)
    }

    /// A size below which a fraction `1 - 1e-9` of draws fall: a practical maximum for
    /// sizing cell lists (exact `max` for bounded laws).
    pub fn practical_max(&self) -> f64 {
        let (_, hi) = self.bounds();
        if hi.is_finite() {
            hi
        } else {
            self.quantile(1.0 - 1e-9)
        }
    }
}

/// Composite 8-point Gauss-Legendre quadrature of `f` on `[a, b]` with `panels` panels.
fn integrate(f: impl Fn(f64) -> f64, a: f64, b: f64, panels: usize) -> f64 {
    const X: [f64; 4] = [
        0.183_434_642_495_649_8,
        0.525_532_409_916_329,
        0.796_666_477_413_626_7,
        0.960_289_856_497_536_3,
    ];
    const W: [f64; 4] = [
        0.362_683_783_378_362,
        0.313_706_645_877_887_3,
        0.222_381_034_453_374_5,
        0.101_228_536_290_376_3,
    ];
    let h = (b - a) / panels as f64;
    let mut s = 0.0;
    for i in 0..panels {
        let c = a + (i as f64 + 0.5) * h;
        for k in 0..4 {
            let d = 0.5 * h * X[k];
            s += W[k] * (f(c - d) + f(c + d));
        }
    }
    0.5 * h * s
}

/// Kolmogorov-Smirnov distance `sup_x |F_n(x) - F(x)|` between the empirical CDF of
/// `samples` and `dist`. Returns 0 for an empty sample.
pub fn ks_distance(samples: &[f64], dist: &SizeDistribution) -> f64 {
    let mut s: Vec<f64> = samples.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len() as f64;
    let mut d: f64 = 0.0;
    for (i, &x) in s.iter().enumerate() {
        let f = dist.cdf(x);
        d = d.max(f - i as f64 / n).max((i + 1) as f64 / n - f);
    }
    d
}

/// Asymptotic critical value of the one-sample KS distance for `n` independent draws at
/// significance `alpha`: `sqrt(-ln(alpha/2) / 2) / sqrt(n)` (1.358/sqrt(n) at alpha = 0.05).
pub fn ks_critical_value(n: usize, alpha: f64) -> f64 {
    (-(alpha / 2.0).ln() / 2.0).sqrt() / (n.max(1) as f64).sqrt()
}

/// A drawn sample checked against the law it was meant to follow, with what explains a
/// failure: draws rejected by the caller (a sphere that does not fit, a grain too large) and
/// an upper size limit that cut the law's tail. Rejections and limits bias a sample in a way
/// the KS distance alone does not explain to a user; the warning says why and by how much
/// the mean moved.
#[derive(Clone, Debug, PartialEq)]
pub struct SampleCheck {
    pub n: usize,
    /// KS distance of the sample against the law.
    pub ks: f64,
    /// 5 % critical value for `n` independent draws.
    pub critical: f64,
    /// Mean of the law and of the sample [m].
    pub mean_law: f64,
    pub mean_drawn: f64,
    /// Draws the caller rejected, out of `draws` made.
    pub rejected: u64,
    pub draws: u64,
    /// An upper size limit [m] and the law's probability mass above it.
    pub limit: Option<(f64, f64)>,
}

impl SampleCheck {
    pub fn new(samples: &[f64], law: &SizeDistribution, rejected: u64, draws: u64) -> Self {
        let n = samples.len();
        SampleCheck {
            n,
            ks: ks_distance(samples, law),
            critical: ks_critical_value(n, 0.05),
            mean_law: law.mean(),
            mean_drawn: samples.iter().sum::<f64>() / n.max(1) as f64,
            rejected,
            draws,
            limit: None,
        }
    }

    pub fn with_limit(mut self, limit: f64, mass_above: f64) -> Self {
        if mass_above > 0.0 {
            self.limit = Some((limit, mass_above));
        }
        self
    }

    pub fn passes(&self) -> bool {
        self.n == 0 || self.ks <= self.critical
    }

    /// Relative change of the mean, `mean_drawn / mean_law - 1`.
    pub fn mean_shift(&self) -> f64 {
        self.mean_drawn / self.mean_law - 1.0
    }

    /// The warning for a sample that fails the test (`None` when it passes); `what` names
    /// the sample ("radii of the unit brick").
    pub fn warning(&self, what: &str) -> Option<String> {
        if self.passes() {
            return None;
        }
        let mut why = Vec::new();
        if self.rejected > 0 {
            let side = if self.mean_shift() < 0.0 {
                "large draws were rejected more often than small ones"
            } else {
                "small draws were rejected more often than large ones"
            };
            why.push(format!(
                "{:.0} % of the draws ({} of {}) were rejected and {side}",
                100.0 * self.rejected as f64 / self.draws.max(1) as f64,
                self.rejected,
                self.draws
            ));
        }
        if let Some((x, mass)) = self.limit {
            why.push(format!(
                "the size limit {x:.4e} m cut the law's tail above it ({:.3} % of its mass)",
                100.0 * mass
            ));
        }
        if why.is_empty() {
            why.push(
                "no draw was rejected and no limit applies: the sizes were not drawn \
                 independently from this law"
                    .into(),
            );
        }
        Some(format!(
            "{what} fail the Kolmogorov-Smirnov test against the requested law: distance \
             {:.3} > critical {:.3} (5 %, n = {}), because {}; the mean moved from {:.4e} m to \
             {:.4e} m ({:+.1} %)",
            self.ks,
            self.critical,
            self.n,
            why.join(", and "),
            self.mean_law,
            self.mean_drawn,
            100.0 * self.mean_shift()
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn um(x: f64) -> Len {
        Q::new(x * 1e-6)
    }

    fn weibull() -> SizeDistribution {
        SizeDistribution::default()
    }

    fn draws(d: &SizeDistribution, n: usize, seed: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| d.sample(&mut rng)).collect()
    }

    #[test]
    fn weibull_mean_and_cdf_match_closed_forms() {
        let d = weibull();
        // Paper eq. (2.4): lambda = 15.7 um, k = 3.55 gives mean ~ 14.14 um (3 digits).
        // Independent reference: Gamma(1 + 1/3.55) = 0.900427542778803 (Python math.gamma),
        // so mean = 14.13671242 um; statrs' Lanczos gamma is accurate to ~1e-15 relative.
        let m = d.mean();
        assert!((m / 14.136_712_42e-6 - 1.0).abs() < 1e-9, "mean {m}");
        assert!((m / 14.14e-6 - 1.0).abs() < 5e-4, "paper value");
        // CDF at the scale is 1 - 1/e for every shape.
        assert!((d.cdf(15.7e-6) - (1.0 - (-1.0f64).exp())).abs() < 1e-14);
        // Quantile inverts the CDF to round-off.
        for u in [1e-6, 0.1, 0.5, 0.9, 0.999_999] {
            let x = d.quantile(u);
            assert!((d.cdf(x) - u).abs() < 1e-12, "u {u}");
        }
    }

    #[test]
    fn truncation_mass_and_truncated_mean_are_exact() {
        // Exponential(mean 1) truncated to [0.5, 2]: closed-form CDF and mean
        // E = a + theta - (b-a) e^{-(b-a)/theta} / (1 - e^{-(b-a)/theta}).
        let d = SizeDistribution::Exponential {
            mean: Q::new(1.0),
            min: Some(Q::new(0.5)),
            max: Some(Q::new(2.0)),
        };
        d.validate().unwrap();
        let (a, b) = (0.5f64, 2.0f64);
        let mass = (-a).exp() - (-b).exp();
        let x: f64 = 1.2;
        let expect = ((-a).exp() - (-x).exp()) / mass;
        assert!((d.cdf(x) - expect).abs() < 1e-14);
        let l = b - a;
        let mean = a + 1.0 - l * (-l).exp() / (1.0 - (-l).exp());
        // 256 panels of 8-point Gauss-Legendre on a smooth integrand: error << 1e-12.
        assert!((d.mean() - mean).abs() < 1e-12, "{} vs {mean}", d.mean());
        // All draws inside the truncation interval, none rejected.
        for r in draws(&d, 10_000, 3) {
            assert!((a..=b).contains(&r));
        }
    }

    #[test]
    fn truncated_weibull_mean_matches_sample_mean() {
        let d = SizeDistribution::Weibull {
            scale: um(15.7),
            shape: 3.55,
            min: Some(um(8.0)),
            max: Some(um(20.0)),
        };
        let n = 200_000;
        let s = draws(&d, n, 11);
        let sm = s.iter().sum::<f64>() / n as f64;
        let var = s.iter().map(|x| (x - sm).powi(2)).sum::<f64>() / n as f64;
        // 5 standard errors of the sample mean: fails by chance with probability < 1e-6.
        let tol = 5.0 * (var / n as f64).sqrt();
        assert!(
            (d.mean() - sm).abs() < tol,
            "{} vs {sm} (tol {tol})",
            d.mean()
        );
        assert!(d.mean() > 8e-6 && d.mean() < 20e-6);
    }

    #[test]
    fn gamma_and_other_laws_have_closed_form_moments() {
        // Paper eq. (3.8): theta = 7 um, k = 2, mean = k theta = 14 um (eq. 3.7).
        let g = SizeDistribution::Gamma {
            shape: 2.0,
            scale: um(7.0),
            min: None,
            max: None,
        };
        assert!((g.mean() - 14e-6).abs() < 1e-18);
        // Gamma(2, theta) CDF: 1 - (1 + x/theta) e^{-x/theta}.
        let x = 10e-6;
        let t: f64 = x / 7e-6;
        assert!((g.cdf(x) - (1.0 - (1.0 + t) * (-t).exp())).abs() < 1e-12);
        let q = g.quantile(0.3);
        assert!((g.cdf(q) - 0.3).abs() < 1e-10);
        let ln = SizeDistribution::Lognormal {
            median: um(10.0),
            sigma: 0.5,
            min: None,
            max: None,
        };
        assert!((ln.mean() - 10e-6 * (0.125f64).exp()).abs() < 1e-18);
        assert!((ln.cdf(10e-6) - 0.5).abs() < 1e-15);
        let tri = SizeDistribution::Triangular {
            min: um(1.0),
            mode: um(2.0),
            max: um(4.0),
        };
        // CDF at the mode is (c-a)/(b-a) = 1/3.
        assert!((tri.cdf(2e-6) - 1.0 / 3.0).abs() < 1e-14);
        assert!((tri.quantile(1.0 / 3.0) - 2e-6).abs() < 1e-18);
        let be = SizeDistribution::Beta {
            alpha: 2.0,
            beta: 2.0,
            min: um(0.0),
            max: um(2.0),
        };
        // Beta(2,2) is symmetric: median at the midpoint, CDF 3t^2 - 2t^3.
        assert!((be.cdf(1e-6) - 0.5).abs() < 1e-14);
        assert!((be.cdf(0.5e-6) - (3.0 * 0.0625 - 2.0 * 0.015625)).abs() < 1e-14);
        assert!((be.quantile(0.5) - 1e-6).abs() < 1e-15);
        let tab = SizeDistribution::Tabulated {
            points: vec![(um(10.0), 0.0), (um(20.0), 0.5), (um(30.0), 1.0)],
            min: None,
            max: None,
        };
        // Uniform on [10, 30] um written as a table.
        assert!((tab.mean() - 20e-6).abs() < 1e-18);
        assert!((tab.quantile(0.75) - 25e-6).abs() < 1e-18);
        // Normal truncated only by x > 0 when the mean is 5 sigma away: mean unchanged to
        // the mass below 0 (~3e-7).
        let n = SizeDistribution::Normal {
            mean: um(10.0),
            std_dev: um(2.0),
            min: None,
            max: None,
        };
        assert!((n.mean() / 10e-6 - 1.0).abs() < 1e-6);
    }

    #[test]
    fn sample_check_explains_a_ks_failure_by_rejected_large_draws() {
        // Draws of the default Weibull above 16 um are rejected (as a too-small room rejects
        // large spheres). The kept sample then follows the law truncated at 16 um, whose mean
        // the law computes independently (quadrature of 1 - F): the reported mean must match
        // it within 4 standard errors, the rejected share must be P(X > 16 um) within 4
        // binomial standard errors, and the KS distance must be far above the critical value.
        let law = weibull();
        let lim = 16e-6;
        let all = draws(&law, 20_000, 3);
        let kept: Vec<f64> = all.iter().copied().filter(|&x| x <= lim).collect();
        let rejected = (all.len() - kept.len()) as u64;
        let c = SampleCheck::new(&kept, &law, rejected, all.len() as u64);
        let p_rej = 1.0 - law.cdf(lim);
        let se_p = (p_rej * (1.0 - p_rej) / all.len() as f64).sqrt();
        assert!((rejected as f64 / all.len() as f64 - p_rej).abs() < 4.0 * se_p);
        let trunc = SizeDistribution::Weibull {
            scale: um(15.7),
            shape: 3.55,
            min: None,
            max: Some(Q::new(lim)),
        };
        let sd = (kept.iter().map(|x| (x - c.mean_drawn).powi(2)).sum::<f64>() / kept.len() as f64)
            .sqrt();
        let se = sd / (kept.len() as f64).sqrt();
        assert!((c.mean_drawn - trunc.mean()).abs() < 4.0 * se, "{c:?}");
        assert!((c.mean_shift() - (trunc.mean() / law.mean() - 1.0)).abs() < 4.0 * se / law.mean());
        assert!(!c.passes() && c.ks > 5.0 * c.critical, "{c:?}");
        let w = c.warning("radii").unwrap();
        assert!(w.contains("large draws were rejected"), "{w}");
        assert!(
            w.contains(&format!("{:+.1} %", 100.0 * c.mean_shift())),
            "{w}"
        );
        // The untouched sample passes and gives no warning.
        let c2 = SampleCheck::new(&all[..2000], &law, 0, 2000);
        assert!(c2.passes() && c2.warning("radii").is_none(), "{c2:?}");
    }

    #[test]
    fn ks_distance_of_a_large_sample_is_small_and_detects_a_wrong_law() {
        let d = weibull();
        let n = 20_000;
        let s = draws(&d, n, 7);
        let ks = ks_distance(&s, &d);
        // Sample from the law itself: D < 1.63/sqrt(n) (alpha = 0.01) except with prob 1%;
        // the seed is fixed, so this is a deterministic check of the sampler.
        assert!(ks < ks_critical_value(n, 0.01), "ks {ks}");
        assert!((ks_critical_value(100, 0.05) - 0.1358).abs() < 1e-3);
        // Against a Weibull with 10 % larger scale the distance is large (the CDFs differ by
        // ~0.2 near the mode).
        let wrong = SizeDistribution::Weibull {
            scale: um(17.27),
            shape: 3.55,
            min: None,
            max: None,
        };
        assert!(ks_distance(&s, &wrong) > 0.1);
    }

    #[test]
    fn yaml_like_json_parses_units_and_rejects_typos() {
        let d: SizeDistribution =
            serde_json::from_str(r#"{"kind":"weibull","scale":"15.7 um","shape":3.55}"#).unwrap();
        assert_eq!(d, weibull());
        let e = serde_json::from_str::<SizeDistribution>(
            r#"{"kind":"weibull","scale":"15.7 um","shpe":3.55}"#,
        );
        assert!(e.is_err());
        let bad = SizeDistribution::Weibull {
            scale: um(15.7),
            shape: 3.55,
            min: Some(um(100.0)),
            max: Some(um(200.0)),
        };
        // Mass of [100, 200] um under this Weibull is exp(-(100/15.7)^3.55) ~ 1e-316.
        assert_eq!(bad.validate().unwrap_err().0, "min");
        let tri = SizeDistribution::Triangular {
            min: um(1.0),
            mode: um(5.0),
            max: um(4.0),
        };
        assert_eq!(tri.validate().unwrap_err().0, "mode");
    }

    #[test]
    fn sampling_is_deterministic() {
        let d = weibull();
        assert_eq!(draws(&d, 100, 5), draws(&d, 100, 5));
    }
}
