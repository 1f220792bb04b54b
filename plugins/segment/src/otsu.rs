//! Histogram thresholds: Otsu (1979) and multi-Otsu for three classes (Liao, Chen & Chung
//! 2001), plus the histogram of a grey-value field they work on.
//!
//! Both work on a histogram `h` of `L` bins, bin `k` standing for the grey level `k`
//! (the bin centre is an affine function of `k`, which leaves the arg max unchanged). A
//! threshold index `k` puts bins `0..=k` in the lower class.

use rayon::prelude::*;

/// A histogram of `values` over `[lo, hi]` in `bins` equal bins: the value `v` goes into
/// bin `floor((v - lo) / (hi - lo) * bins)`, clamped to the last bin (so `hi` itself is in
/// it). Values that are not finite are skipped. When `hi <= lo` every value is in bin 0.
pub fn histogram(values: &[f64], lo: f64, hi: f64, bins: usize) -> Vec<u64> {
    let scale = if hi > lo {
        bins as f64 / (hi - lo)
    } else {
        0.0
    };
    values
        .par_chunks(1 << 16)
        .fold(
            || vec![0u64; bins],
            |mut h, c| {
                for &v in c {
                    if v.is_finite() {
                        h[bin_of(v, lo, scale, bins)] += 1;
                    }
                }
                h
            },
        )
        .reduce(
            || vec![0u64; bins],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x += y;
                }
                a
            },
        )
}

/// The bin of `v` in a histogram from `lo` with `scale` bins per unit.
pub fn bin_of(v: f64, lo: f64, scale: f64, bins: usize) -> usize {
    (((v - lo) * scale).floor().max(0.0) as usize).min(bins - 1)
}

/// The smallest and largest finite values (`None` when there are none).
pub fn finite_range(values: &[f64]) -> Option<(f64, f64)> {
    let (lo, hi) = values
        .par_chunks(1 << 16)
        .map(|c| {
            c.iter()
                .filter(|v| v.is_finite())
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                    (a.min(v), b.max(v))
                })
        })
        .reduce(
            || (f64::INFINITY, f64::NEG_INFINITY),
            |(a, b), (c, d)| (a.min(c), b.max(d)),
        );
    (lo <= hi).then_some((lo, hi))
}

/// Otsu's threshold index: the `k` in `0..L-1` that maximises the between-class variance
/// `sigma_B^2(k) = (mu_T omega(k) - mu(k))^2 / (omega(k) (1 - omega(k)))` (Otsu 1979, eq.
/// 18), with `omega(k)` the probability of bins `0..=k`, `mu(k)` their first moment and
/// `mu_T` the total mean. Ties go to the smallest `k`; a `k` that leaves a class empty has
/// `sigma_B^2 = 0`. `None` for a histogram of fewer than two bins or no counts.
pub fn otsu(h: &[u64]) -> Option<usize> {
    let total: u64 = h.iter().sum();
    if h.len() < 2 || total == 0 {
        return None;
    }
    let n = total as f64;
    let mu_t: f64 = h
        .iter()
        .enumerate()
        .map(|(i, &c)| i as f64 * c as f64)
        .sum::<f64>()
        / n;
    let (mut best, mut best_k) = (-1.0f64, 0usize);
    let (mut omega, mut mu) = (0.0f64, 0.0f64);
    for (k, &c) in h[..h.len() - 1].iter().enumerate() {
        omega += c as f64 / n;
        mu += k as f64 * c as f64 / n;
        let denom = omega * (1.0 - omega);
        let s = if denom > 0.0 {
            (mu_t * omega - mu).powi(2) / denom
        } else {
            0.0
        };
        if s > best {
            best = s;
            best_k = k;
        }
    }
    Some(best_k)
}

/// Three-class Otsu: the pair `k1 < k2` (classes `0..=k1`, `k1+1..=k2`, `k2+1..L-1`) that
/// maximises `sum_c omega_c mu_c^2` (Liao et al. 2001, eq. 8, equivalent to the
/// between-class variance since the total mean is fixed), where `omega_c mu_c^2 =
/// S(u,v)^2 / P(u,v)` from the zeroth and first moments of the class's bins (their lookup
/// tables, here as prefix sums). Exhaustive over every pair; ties go to the smallest `k1`,
/// then the smallest `k2`. `None` for fewer than three bins or no counts.
pub fn multi_otsu3(h: &[u64]) -> Option<[usize; 2]> {
    let l = h.len();
    let total: u64 = h.iter().sum();
    if l < 3 || total == 0 {
        return None;
    }
    let n = total as f64;
    // p[i], s[i]: probability and first moment of bins 0..i (exclusive).
    let mut p = vec![0.0f64; l + 1];
    let mut s = vec![0.0f64; l + 1];
    for i in 0..l {
        p[i + 1] = p[i] + h[i] as f64 / n;
        s[i + 1] = s[i] + i as f64 * h[i] as f64 / n;
    }
    // The class of bins u..=v.
    let term = |u: usize, v: usize| {
        let w = p[v + 1] - p[u];
        if w > 0.0 {
            (s[v + 1] - s[u]).powi(2) / w
        } else {
            0.0
        }
    };
    // Rows k1 in parallel; each keeps its first maximum, then the first row wins ties.
    let rows: Vec<(f64, usize)> = (0..l - 2)
        .into_par_iter()
        .map(|k1| {
            let head = term(0, k1);
            let (mut best, mut best_k2) = (f64::NEG_INFINITY, k1 + 1);
            for k2 in k1 + 1..l - 1 {
                let v = head + term(k1 + 1, k2) + term(k2 + 1, l - 1);
                if v > best {
                    best = v;
                    best_k2 = k2;
                }
            }
            (best, best_k2)
        })
        .collect();
    let mut best = (f64::NEG_INFINITY, [0, 1]);
    for (k1, &(v, k2)) in rows.iter().enumerate() {
        if v > best.0 {
            best = (v, [k1, k2]);
        }
    }
    Some(best.1)
}
