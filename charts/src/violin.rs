//! Violin plots: the kernel density of a sample mirrored about its category, the sample as
//! dots, the mean as a white dot and its confidence interval as a whisker on the violin's
//! centre line. All violins of one quantity share one chart, hence one y axis.

use crate::figure::{Figure, Series};
use crate::style;

/// Percentile (linear interpolation between order statistics) of sorted values, p in [0, 1].
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let x = p.clamp(0.0, 1.0) * (sorted.len() - 1) as f64;
    let i = x.floor() as usize;
    let j = (i + 1).min(sorted.len() - 1);
    sorted[i] + (x - i as f64) * (sorted[j] - sorted[i])
}

/// Silverman's bandwidth 0.9 min(s, IQR / 1.34) n^(-1/5) of the finite values; `None` when
/// they do not spread.
pub fn bandwidth(values: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.len() < 2 {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let s = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    let iqr = percentile(&v, 0.75) - percentile(&v, 0.25);
    let spread = if iqr > 0.0 { s.min(iqr / 1.34) } else { s };
    if spread.is_nan() || spread <= 0.0 {
        return None;
    }
    Some(0.9 * spread * n.powf(-0.2))
}

/// Gaussian kernel density estimate of `values` at `at` ([`bandwidth`]); `None` when the
/// values do not spread.
pub fn kde(values: &[f64], at: &[f64]) -> Option<Vec<f64>> {
    let h = bandwidth(values)?;
    let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    let norm = 1.0 / (v.len() as f64 * h * (2.0 * std::f64::consts::PI).sqrt());
    Some(
        at.iter()
            .map(|&x| {
                norm * v
                    .iter()
                    .map(|&xi| (-0.5 * ((x - xi) / h).powi(2)).exp())
                    .sum::<f64>()
            })
            .collect(),
    )
}

/// The outline of a violin centred at x = `at`, at most `half` wide on each side: the
/// density over the data range (clipped to it), scaled to its maximum. A sample that does not
/// spread gives a flat bar at its value.
pub fn violin(values: &[f64], at: f64, half: f64) -> Vec<(f64, f64)> {
    let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let m = 60;
    let ys: Vec<f64> = (0..=m)
        .map(|k| lo + (hi - lo) * k as f64 / m as f64)
        .collect();
    let Some(dens) = (hi > lo).then(|| kde(&v, &ys)).flatten() else {
        let y = if v.is_empty() {
            f64::NAN
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        };
        let w = 0.75 * half;
        return vec![(at - w, y), (at + w, y), (at + w, y), (at - w, y)];
    };
    let top = dens
        .iter()
        .copied()
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    let mut poly: Vec<(f64, f64)> = ys
        .iter()
        .zip(&dens)
        .map(|(y, d)| (at + half * d / top, *y))
        .collect();
    poly.extend(
        ys.iter()
            .zip(&dens)
            .rev()
            .map(|(y, d)| (at - half * d / top, *y)),
    );
    poly
}

/// One violin: its category label, the sample, the mean and the confidence interval of the
/// mean (low, high) when known.
#[derive(Clone, Debug, Default)]
pub struct Group {
    pub label: String,
    pub values: Vec<f64>,
    pub mean: f64,
    pub ci: Option<(f64, f64)>,
}

impl Group {
    /// A group with the sample mean and no interval.
    pub fn new(label: &str, values: Vec<f64>) -> Group {
        let f: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        Group {
            label: label.into(),
            mean: f.iter().sum::<f64>() / f.len().max(1) as f64,
            values,
            ci: None,
        }
    }
}

/// Half width of a violin in category units.
pub const HALF: f64 = 0.4;

/// Violins of `groups` on one chart: one y axis for all, widened to nice bounds that hold
/// every value and every interval; the interval's whisker on each violin's centre line.
pub fn violins(title: &str, y_label: &str, groups: &[Group]) -> Figure {
    let mut f = Figure {
        title: title.into(),
        x_label: String::new(),
        y_label: y_label.into(),
        categories: groups.iter().map(|g| g.label.clone()).collect(),
        size: Some(((210 * groups.len() as u32 + 110).clamp(420, 1100), 320)),
        ..Default::default()
    };
    let mut dots = Series {
        color: Some((90, 90, 90)),
        markers: true,
        marker_size: 2,
        ..Default::default()
    };
    let mut means = Series {
        color: Some(style::ACCENT),
        markers: true,
        hollow: true,
        marker_size: 4,
        ..Default::default()
    };
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (k, g) in groups.iter().enumerate() {
        let at = k as f64;
        f.polygons.push((violin(&g.values, at, HALF), 0));
        for &v in g.values.iter().filter(|v| v.is_finite()) {
            dots.points.push((at, v));
            lo = lo.min(v);
            hi = hi.max(v);
        }
        means.points.push((at, g.mean));
        let ci =
            g.ci.filter(|c| c.0.is_finite() && c.1.is_finite())
                .unwrap_or((f64::NAN, f64::NAN));
        if ci.0.is_finite() {
            lo = lo.min(ci.0);
            hi = hi.max(ci.1);
        }
        means.err.push(ci);
    }
    if lo.is_finite() {
        f.y_range = Some(style::nice_range(lo, hi, 5));
    }
    f.series = vec![dots, means];
    f
}

/// Violins of (label, sample) groups with their means (no intervals).
pub fn violin_figure(title: &str, y_label: &str, groups: &[(String, Vec<f64>)]) -> Figure {
    let g: Vec<Group> = groups
        .iter()
        .map(|(l, v)| Group::new(l, v.clone()))
        .collect();
    violins(title, y_label, &g)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kde_integrates_to_one() {
        let xs: Vec<f64> = (0..=800).map(|i| -5.0 + 15.0 * i as f64 / 800.0).collect();
        let d = kde(&[1.0, 2.0, 3.0, 4.0, 5.0], &xs).unwrap();
        let area: f64 = d.iter().sum::<f64>() * 15.0 / 800.0;
        assert!((area - 1.0).abs() < 1e-3, "{area}");
        assert!(kde(&[2.0, 2.0], &xs).is_none());
        assert_eq!(percentile(&[1.0, 2.0, 3.0, 4.0], 0.5), 2.5);
    }

    #[test]
    fn violin_is_symmetric_and_spans_the_data() {
        let v = [1.0, 2.0, 2.5, 3.0, 4.0];
        let p = violin(&v, 2.0, HALF);
        let ys: Vec<f64> = p.iter().map(|q| q.1).collect();
        assert_eq!(ys.iter().copied().fold(f64::INFINITY, f64::min), 1.0);
        assert_eq!(ys.iter().copied().fold(f64::NEG_INFINITY, f64::max), 4.0);
        let n = p.len() / 2;
        for k in 0..n {
            assert!(((p[k].0 - 2.0) + (p[p.len() - 1 - k].0 - 2.0)).abs() < 1e-12);
        }
        assert!(p.iter().all(|q| (q.0 - 2.0).abs() <= HALF + 1e-12));
    }

    /// The whisker of each interval stands on its violin's centre line, and the shared y
    /// range holds every value and interval of every group.
    #[test]
    fn whiskers_are_centred_and_inside_the_shared_axis() {
        let groups = vec![
            Group {
                label: "a".into(),
                values: vec![1.0, 2.0, 3.0, 2.5],
                mean: 2.125,
                ci: Some((0.9, 3.35)),
            },
            Group {
                label: "b".into(),
                values: vec![5.0, 6.0, 7.5],
                mean: 6.17,
                ci: Some((3.0, 9.3)),
            },
        ];
        let f = violins("E", "E [Pa]", &groups);
        let (_, (lo, hi)) = f.bounds();
        let means = &f.series[1];
        for (k, (poly, _)) in f.polygons.iter().enumerate() {
            let x0 = poly.iter().map(|p| p.0).fold(f64::INFINITY, f64::min);
            let x1 = poly.iter().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
            assert!(((x0 + x1) / 2.0 - means.points[k].0).abs() < 1e-12);
            let (a, b) = means.err[k];
            assert!(a >= lo && b <= hi, "whisker {a}..{b} outside {lo}..{hi}");
        }
        assert!(lo <= 0.9 && hi >= 9.3);
        // One chart, so one y axis for both groups.
        assert_eq!(f.categories, ["a", "b"]);
        let svg = f.svg("violin").unwrap();
        assert_eq!(svg.matches("<polygon").count(), 2, "{svg}");
    }
}
