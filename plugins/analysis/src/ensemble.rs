//! `analysis.ensemble`: statistics of an ensemble of realizations (a sweep table, stacked
//! realizations) and the RVE analysis of Kanit et al. (2003) as used in Donval et al. (2025),
//! section 3.5.
//!
//! The kernels are plain functions on slices (no framework types) so that `pipe sweep` computes
//! its `summary.csv` with exactly the code of this stage:
//! - [`summarize`]: mean, standard deviation (n - 1), Student-t confidence interval of the mean,
//!   min, max, and the relative error of eq. (3.14) for the number of realizations at hand;
//! - [`variance_interval`]: chi-square confidence interval of a sample variance (the error bars
//!   of Fig. 9a);
//! - [`point_variance`]: D_Z^2 of eq. (3.16);
//! - [`fit_rve`]: the power law Var(Z) = D_Z^2 (A_3 / vol)^alpha of eq. (3.15) by least squares
//!   on its logarithm;
//! - [`RveFit::rve_volume`] (eq. 3.14 with eq. 3.15 solved for the volume) and
//!   [`RveFit::realizations_needed`] (the realizations-against-volume trade-off of Fig. 9b).

use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, Column, ColumnData, InputMetas, Inputs, Outputs,
    PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
};
use statrs::distribution::{ChiSquared, ContinuousCDF, StudentsT};
use std::path::Path;

/// Statistics of one sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stats {
    pub n: usize,
    pub mean: f64,
    /// Sample standard deviation (divisor n - 1); NaN for n < 2.
    pub std: f64,
    /// Confidence interval of the mean (Student t with n - 1 degrees of freedom).
    pub ci_low: f64,
    pub ci_high: f64,
    pub min: f64,
    pub max: f64,
    /// eq. (3.14): 2 sqrt(Var / n) / mean, the relative error of the ensemble mean.
    pub rel_error: f64,
}

/// Two-sided Student-t quantile t_{(1+c)/2, dof}.
pub fn t_quantile(confidence: f64, dof: f64) -> f64 {
    match StudentsT::new(0.0, 1.0, dof) {
        Ok(t) => t.inverse_cdf(0.5 + confidence / 2.0),
        Err(_) => f64::NAN,
    }
}

/// Mean, std, Student-t confidence interval of the mean, min, max of the finite values of
/// `x` (NaN entries, i.e. failed runs, are left out; they are counted by the caller).
pub fn summarize(x: &[f64], confidence: f64) -> Stats {
    let v: Vec<f64> = x.iter().copied().filter(|x| x.is_finite()).collect();
    let n = v.len();
    let nan = f64::NAN;
    if n == 0 {
        return Stats {
            n,
            mean: nan,
            std: nan,
            ci_low: nan,
            ci_high: nan,
            min: nan,
            max: nan,
            rel_error: nan,
        };
    }
    let mean = v.iter().sum::<f64>() / n as f64;
    let (std, half) = if n > 1 {
        let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1) as f64;
        let s = var.sqrt();
        (
            s,
            t_quantile(confidence, (n - 1) as f64) * s / (n as f64).sqrt(),
        )
    } else {
        (nan, nan)
    };
    Stats {
        n,
        mean,
        std,
        ci_low: mean - half,
        ci_high: mean + half,
        min: v.iter().copied().fold(f64::INFINITY, f64::min),
        max: v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        // eq. (3.14) with the n realizations at hand.
        rel_error: 2.0 * std / (n as f64).sqrt() / mean.abs(),
    }
}

/// Confidence interval of the variance of a normal sample with sample variance `var` from `n`
/// values: (n-1) s^2 / chi2_{(1+c)/2} .. (n-1) s^2 / chi2_{(1-c)/2}.
pub fn variance_interval(var: f64, n: usize, confidence: f64) -> (f64, f64) {
    if n < 2 {
        return (f64::NAN, f64::NAN);
    }
    let dof = (n - 1) as f64;
    match ChiSquared::new(dof) {
        Ok(c) => (
            dof * var / c.inverse_cdf(0.5 + confidence / 2.0),
            dof * var / c.inverse_cdf(0.5 - confidence / 2.0),
        ),
        Err(_) => (f64::NAN, f64::NAN),
    }
}

/// eq. (3.16), for any number of phases: D_Z^2 = sum phi_i Z_i^2 - (sum phi_i Z_i)^2; a phase
/// left out (the pores) has Z = 0.
pub fn point_variance(fractions: &[f64], values: &[f64]) -> f64 {
    let m1: f64 = fractions.iter().zip(values).map(|(f, z)| f * z).sum();
    let m2: f64 = fractions.iter().zip(values).map(|(f, z)| f * z * z).sum();
    m2 - m1 * m1
}

/// The fitted power law of eq. (3.15).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RveFit {
    /// Exponent alpha (1 for the CLT scaling in 3D).
    pub alpha: f64,
    /// ln(D_Z^2 A_3^alpha), the intercept of ln Var = intercept - alpha ln vol.
    pub log_prefactor: f64,
    /// Point variance D_Z^2 (eq. 3.16) when known, else NaN.
    pub point_variance: f64,
    /// Integral range A_3 [volume unit of the data] when D_Z^2 is known, else NaN.
    pub integral_range: f64,
    /// Coefficient of determination of the log-log regression.
    pub r2: f64,
}

impl RveFit {
    /// Var(Z) at cell volume `v`, eq. (3.15).
    pub fn variance(&self, v: f64) -> f64 {
        (self.log_prefactor - self.alpha * v.ln()).exp()
    }

    /// Realizations n needed at cell volume `v` for a relative error `eps` of the mean
    /// `mean`: eq. (3.14) solved for n, n = 4 Var(v) / (eps mean)^2 (Fig. 9b).
    pub fn realizations_needed(&self, v: f64, mean: f64, eps: f64) -> f64 {
        4.0 * self.variance(v) / (eps * mean).powi(2)
    }

    /// Cell volume at which `n` realizations give a relative error `eps`: eqs. (3.14) and
    /// (3.15) solved for the volume, vol = (D^2 A_3^alpha 4 / (n eps^2 mean^2))^(1/alpha).
    /// With n = 1 this is the RVE of Kanit et al.
    pub fn rve_volume(&self, mean: f64, eps: f64, n: f64) -> f64 {
        ((self.log_prefactor + (4.0 / (n * (eps * mean).powi(2))).ln()) / self.alpha).exp()
    }
}

/// Least-squares fit of ln Var = c - alpha ln vol over cell volumes (eq. 3.15 in log form, as
/// Donval et al. did); `point_variance` (eq. 3.16, NaN when unknown) turns the intercept into
/// the integral range A_3 = exp((c - ln D^2) / alpha). Needs two distinct volumes with a
/// positive variance.
pub fn fit_rve(volumes: &[f64], variances: &[f64], point_variance: f64) -> Result<RveFit, String> {
    let pts: Vec<(f64, f64)> = volumes
        .iter()
        .zip(variances)
        .filter(|(v, s)| v.is_finite() && **v > 0.0 && s.is_finite() && **s > 0.0)
        .map(|(v, s)| (v.ln(), s.ln()))
        .collect();
    let n = pts.len() as f64;
    if pts.len() < 2 {
        return Err(format!(
            "the RVE fit needs at least two cell volumes with a positive variance, got {}",
            pts.len()
        ));
    }
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let syy: f64 = pts.iter().map(|p| (p.1 - my).powi(2)).sum();
    if sxx <= 0.0 {
        return Err("the RVE fit needs at least two different cell volumes".into());
    }
    let slope = sxy / sxx;
    let c = my - slope * mx;
    let alpha = -slope;
    let integral_range = if point_variance.is_finite() && point_variance > 0.0 {
        ((c - point_variance.ln()) / alpha).exp()
    } else {
        f64::NAN
    };
    let r2 = if syy > 0.0 {
        sxy * sxy / (sxx * syy)
    } else {
        1.0
    };
    Ok(RveFit {
        alpha,
        log_prefactor: c,
        point_variance,
        integral_range,
        r2,
    })
}

/// Columns a sweep table carries for bookkeeping; never summarised by default.
pub const BOOKKEEPING: &[&str] = &[
    "run",
    "point",
    "realization",
    "seed",
    "wall_time",
    "peak_memory",
    "status",
    "error",
];

/// A column's values as f64 (integers converted); `None` for text.
pub fn numeric(c: &Column) -> Option<Vec<f64>> {
    match &c.data {
        ColumnData::F64(v) => Some(v.clone()),
        ColumnData::I64(v) => Some(v.iter().map(|&x| x as f64).collect()),
        ColumnData::Str(_) => None,
    }
}

fn cell_text(c: &Column, r: usize) -> String {
    match &c.data {
        ColumnData::F64(v) => v[r].to_string(),
        ColumnData::I64(v) => v[r].to_string(),
        ColumnData::Str(v) => v[r].clone(),
    }
}

/// A group of rows: its key (the group columns' values as text) and its row indices.
pub type Group = (Vec<String>, Vec<usize>);

/// Rows grouped by the values of `group_by` (first-seen order), each group with its rows.
pub fn groups(t: &Table, group_by: &[String]) -> Result<Vec<Group>, String> {
    let cols = group_by
        .iter()
        .map(|g| column(t, g))
        .collect::<Result<Vec<_>, _>>()?;
    let mut out: Vec<Group> = Vec::new();
    for r in 0..t.rows() {
        let key: Vec<String> = cols.iter().map(|c| cell_text(c, r)).collect();
        match out.iter_mut().find(|(k, _)| *k == key) {
            Some((_, rows)) => rows.push(r),
            None => out.push((key, vec![r])),
        }
    }
    Ok(out)
}

fn column<'a>(t: &'a Table, name: &str) -> Result<&'a Column, String> {
    t.column(name).ok_or_else(|| {
        let names: Vec<&str> = t.columns.iter().map(|c| c.name.as_str()).collect();
        let hint = grainpipe_core::registry::closest(name, names.iter().copied())
            .map(|s| format!("did you mean `{s}`? "))
            .unwrap_or_default();
        format!(
            "table `{}` has no column `{name}`; {hint}it has: {}",
            t.name,
            names.join(", ")
        )
    })
}

/// The numeric columns that are neither bookkeeping nor group keys.
pub fn value_columns(t: &Table, group_by: &[String]) -> Vec<String> {
    t.columns
        .iter()
        .filter(|c| !BOOKKEEPING.contains(&c.name.as_str()) && !group_by.contains(&c.name))
        .filter(|c| !matches!(c.data, ColumnData::Str(_)))
        .map(|c| c.name.clone())
        .collect()
}

/// The tidy summary: one row per (group, quantity) with n, failures, mean, std, the
/// confidence interval of the mean, min, max and the relative error of eq. (3.14). Rows whose
/// `status` column (when present) is not `ok` are counted in `n_failed` and left out.
pub fn summary_table(
    t: &Table,
    group_by: &[String],
    columns: &[String],
    confidence: f64,
) -> Result<Table, String> {
    let columns: Vec<String> = if columns.is_empty() {
        value_columns(t, group_by)
    } else {
        columns.to_vec()
    };
    if columns.is_empty() {
        return Err(format!(
            "table `{}` has no numeric column to summarise",
            t.name
        ));
    }
    let status: Option<&[String]> = match t.column("status").map(|c| &c.data) {
        Some(ColumnData::Str(s)) => Some(s),
        _ => None,
    };
    let ok = |r: usize| status.is_none_or(|s| s[r] == "ok");
    let gs = groups(t, group_by)?;
    let mut keys: Vec<Vec<String>> = vec![Vec::new(); group_by.len()];
    let (mut quantity, mut unit) = (Vec::new(), Vec::new());
    let (mut n, mut failed) = (Vec::new(), Vec::new());
    let mut s: [Vec<f64>; 8] = Default::default();
    for name in &columns {
        let c = column(t, name)?;
        let v = numeric(c).ok_or_else(|| format!("column `{name}` holds text"))?;
        for (key, rows) in &gs {
            let sample: Vec<f64> = rows.iter().filter(|&&r| ok(r)).map(|&r| v[r]).collect();
            let st = summarize(&sample, confidence);
            for (k, col) in key.iter().zip(keys.iter_mut()) {
                col.push(k.clone());
            }
            quantity.push(name.clone());
            unit.push(c.unit.clone());
            n.push(st.n as i64);
            failed.push(rows.len() as i64 - st.n as i64);
            for (dst, x) in s.iter_mut().zip([
                st.mean,
                st.std,
                st.ci_low,
                st.ci_high,
                st.min,
                st.max,
                st.rel_error,
                st.std * st.std,
            ]) {
                dst.push(x);
            }
        }
    }
    let mut out = Table::new("ensemble_summary");
    for (g, k) in group_by.iter().zip(keys) {
        // Keep numeric group keys numeric, so the summary can be plotted against them.
        let col = t.column(g).expect("grouped by it");
        out = match col.data {
            ColumnData::Str(_) => out.with_str(g, k),
            _ => out.with_f64(
                g,
                &col.unit,
                k.iter().map(|x| x.parse().unwrap_or(f64::NAN)).collect(),
            ),
        };
    }
    let pct = (confidence * 100.0).round();
    let [mean, std, lo, hi, min, max, rel, var] = s;
    Ok(out
        .with_str("quantity", quantity)
        .with_str("unit", unit)
        .with_i64("n", "1", n)
        .with_i64("n_failed", "1", failed)
        .with_f64("mean", "", mean)
        .with_f64("std", "", std)
        .with_f64("variance", "", var)
        .with_f64(&format!("ci{pct}_low"), "", lo)
        .with_f64(&format!("ci{pct}_high"), "", hi)
        .with_f64("min", "", min)
        .with_f64("max", "", max)
        .with_f64("rel_error", "1", rel))
}

/// The RVE analysis of each quantity over groups that differ by cell volume: the fit of
/// eq. (3.15), RVE volumes for `relative_errors` (eq. 3.14, n = 1) and, for the
/// trade-off of Fig. 9b, the volume needed with each count of `realizations`.
/// Returns (rve table, trade-off table). The mean used for relative errors is that of the
/// largest cells (least biased, eq. 3.10).
#[allow(clippy::too_many_arguments)]
pub fn rve_tables(
    t: &Table,
    volume_column: &str,
    columns: &[String],
    point_variance: f64,
    relative_errors: &[f64],
    realizations: &[u64],
    confidence: f64,
) -> Result<(Table, Table), String> {
    let vol_col = column(t, volume_column)?;
    let vols = numeric(vol_col).ok_or_else(|| format!("column `{volume_column}` holds text"))?;
    let group_by = vec![volume_column.to_string()];
    let columns: Vec<String> = if columns.is_empty() {
        value_columns(t, &group_by)
    } else {
        columns.to_vec()
    };
    let gs = groups(t, &group_by)?;
    let status: Option<&[String]> = match t.column("status").map(|c| &c.data) {
        Some(ColumnData::Str(s)) => Some(s),
        _ => None,
    };
    let ok = |r: usize| status.is_none_or(|s| s[r] == "ok");
    let mut rve = Table::new("rve");
    let mut cols: Vec<(String, String, Vec<f64>)> = vec![
        ("alpha".into(), "1".into(), vec![]),
        ("log_prefactor".into(), "".into(), vec![]),
        ("point_variance".into(), "".into(), vec![]),
        ("integral_range".into(), vol_col.unit.clone(), vec![]),
        ("r2".into(), "1".into(), vec![]),
        ("mean_largest_cell".into(), "".into(), vec![]),
    ];
    for e in relative_errors {
        cols.push((format!("rve_volume_eps{e}"), vol_col.unit.clone(), vec![]));
    }
    let mut names = Vec::new();
    let (mut tq, mut te, mut tn, mut tv) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for name in &columns {
        let v = numeric(column(t, name)?).ok_or_else(|| format!("column `{name}` holds text"))?;
        let mut volumes = Vec::new();
        let mut variances = Vec::new();
        let mut means = Vec::new();
        for (_, rows) in &gs {
            let sample: Vec<f64> = rows.iter().filter(|&&r| ok(r)).map(|&r| v[r]).collect();
            let st = summarize(&sample, confidence);
            volumes.push(vols[rows[0]]);
            variances.push(st.std * st.std);
            means.push(st.mean);
        }
        let fit = fit_rve(&volumes, &variances, point_variance)
            .map_err(|e| format!("quantity `{name}`: {e}"))?;
        let largest = (0..volumes.len())
            .max_by(|&a, &b| volumes[a].total_cmp(&volumes[b]))
            .expect("two volumes");
        let mean = means[largest];
        names.push(name.clone());
        let mut row = vec![
            fit.alpha,
            fit.log_prefactor,
            fit.point_variance,
            fit.integral_range,
            fit.r2,
            mean,
        ];
        row.extend(
            relative_errors
                .iter()
                .map(|&e| fit.rve_volume(mean, e, 1.0)),
        );
        for (c, x) in cols.iter_mut().zip(row) {
            c.2.push(x);
        }
        for &e in relative_errors {
            for &n in realizations {
                tq.push(name.clone());
                te.push(e);
                tn.push(n as i64);
                tv.push(fit.rve_volume(mean, e, n as f64));
            }
        }
    }
    rve = rve.with_str("quantity", names);
    for (n, u, v) in cols {
        rve = rve.with_f64(&n, &u, v);
    }
    let trade = Table::new("rve_tradeoff")
        .with_str("quantity", tq)
        .with_f64("relative_error", "1", te)
        .with_i64("realizations", "1", tn)
        .with_f64("volume", &vol_col.unit, tv);
    Ok((rve, trade))
}

#[params]
pub struct EnsembleParams {
    /// Columns whose values define a parameter point (rows with equal values are realizations
    /// of one point); empty: the whole table is one point.
    pub group_by: Vec<String>,
    /// Numeric columns to summarise (default: every numeric column that is not a group key
    /// nor bookkeeping: run, point, realization, seed, wall_time, peak_memory).
    pub columns: Vec<String>,
    /// Confidence level of the intervals of the mean (Student t) and of the variances.
    #[param(default = 0.9)]
    pub confidence: f64,
    /// A CSV table to read instead of the `table` input (e.g. a `pipe sweep` table,
    /// DIR/sweep.csv); its content is part of the cache key.
    #[param(file)]
    pub file: String,
    /// Column holding each row's cell volume; when set, the Kanit et al. RVE analysis
    /// (eq. 3.15 fit over the cell volumes) is done and the `rve` and `tradeoff` tables given.
    pub volume_column: String,
    /// Volume fractions of the phases for the point variance D_Z^2 (eq. 3.16), e.g. sand and
    /// binder; the pores (value 0) may be left out.
    pub phase_fractions: Vec<f64>,
    /// The local value of the quantity in each phase, in the order of `phase_fractions` (e.g.
    /// the Young's moduli of sand and binder).
    pub phase_values: Vec<f64>,
    /// Relative errors for which the RVE volume is given (eq. 3.14).
    #[param(default = vec![0.05, 0.025, 0.01])]
    pub relative_errors: Vec<f64>,
    /// Realization counts of the realizations-against-volume trade-off (Fig. 9b).
    #[param(default = vec![1, 5, 10, 30])]
    pub realizations: Vec<u64>,
}

pub struct Ensemble;

impl TypedStage for Ensemble {
    type Params = EnsembleParams;
    type Plan = ();

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "analysis.ensemble",
            "1.0.0",
            "Ensemble statistics of a table of realizations (a `pipe sweep` table or stacked \
             realizations): per parameter point and quantity the count, failures (rows whose \
             `status` is not ok), mean, standard deviation, Student-t confidence interval of \
             the mean, min, max and the relative error 2 std / (sqrt(n) mean) (Donval et al. \
             2025, eq. 3.14). With `volume_column`, the RVE analysis of Kanit et al. (2003): \
             the power law Var(Z) = D_Z^2 (A_3/vol)^alpha (eq. 3.15) fitted by least squares \
             on its logarithm over the cell volumes, the integral range A_3 from the point \
             variance of eq. (3.16), the RVE volume for each relative error (n = 1) and the \
             cell volume needed with n realizations (Fig. 9b). Assumes the bias is small \
             against the dispersion (Kanit et al.).",
        )
        .inputs(vec![PortSpec::optional(
            "table",
            ArtifactKind::Table,
            "one row per realization (or give `file`)",
        )])
        .outputs(vec![
            PortSpec::new(
                "summary",
                ArtifactKind::Table,
                "one row per point and quantity",
            ),
            PortSpec::new(
                "rve",
                ArtifactKind::Table,
                "one row per quantity: alpha, A_3, RVE volumes (with volume_column)",
            ),
            PortSpec::new(
                "tradeoff",
                ArtifactKind::Table,
                "volume needed per relative error and realization count (with volume_column)",
            ),
        ])
    }

    fn preflight(&self, p: &EnsembleParams, i: &InputMetas) -> Result<Preflight, StageError> {
        match (i.contains_key("table"), p.file.is_empty()) {
            (true, false) => {
                return Err(StageError::param(
                    "file",
                    "give either the `table` input or `file`, not both",
                ))
            }
            (false, true) => {
                return Err(StageError::input(
                    "table",
                    "not connected: connect a table or give `file`",
                ))
            }
            _ => {}
        }
        if !(p.confidence > 0.0 && p.confidence < 1.0) {
            return Err(StageError::param("confidence", "must be in (0, 1)"));
        }
        if p.phase_fractions.len() != p.phase_values.len() {
            return Err(StageError::param(
                "phase_values",
                format!(
                    "{} values for {} phase fractions",
                    p.phase_values.len(),
                    p.phase_fractions.len()
                ),
            ));
        }
        if let Some(e) = p
            .relative_errors
            .iter()
            .find(|e| !e.is_finite() || **e <= 0.0)
        {
            return Err(StageError::param(
                "relative_errors",
                format!("{e} is not a positive relative error"),
            ));
        }
        if p.realizations.contains(&0) {
            return Err(StageError::param("realizations", "counts must be >= 1"));
        }
        let mut pf = Preflight::from_info(&self.info(), 1 << 20)
            .announce("summary", ArtifactMeta::of(ArtifactKind::Table));
        if p.volume_column.is_empty() {
            // No RVE fit without cell volumes: these outputs are not given, so they are not
            // announced (an export of them is refused at preflight).
            pf.outputs.shift_remove("rve");
            pf.outputs.shift_remove("tradeoff");
        } else {
            pf = pf
                .announce("rve", ArtifactMeta::of(ArtifactKind::Table))
                .announce("tradeoff", ArtifactMeta::of(ArtifactKind::Table));
        }
        Ok(pf)
    }

    fn run(
        &self,
        p: &EnsembleParams,
        _: &(),
        inputs: &Inputs,
        _ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let read;
        let t = if p.file.is_empty() {
            grainpipe_core::input(inputs, "table", Artifact::as_table)?
        } else {
            read = grainpipe_formats::read_table_csv(Path::new(&p.file))
                .map_err(|e| StageError::param("file", e))?;
            &read
        };
        let bad = |e: String| {
            if e.contains("no column") {
                StageError::param("columns", e)
            } else {
                StageError::failed(e)
            }
        };
        let summary = summary_table(t, &p.group_by, &p.columns, p.confidence).map_err(bad)?;
        let mut out = Outputs::new();
        out.insert("summary".into(), Artifact::Table(summary));
        if !p.volume_column.is_empty() {
            let d2 = if p.phase_fractions.is_empty() {
                f64::NAN
            } else {
                point_variance(&p.phase_fractions, &p.phase_values)
            };
            let (rve, trade) = rve_tables(
                t,
                &p.volume_column,
                &p.columns,
                d2,
                &p.relative_errors,
                &p.realizations,
                p.confidence,
            )
            .map_err(bad)?;
            out.insert("rve".into(), Artifact::Table(rve));
            out.insert("tradeoff".into(), Artifact::Table(trade));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    #[test]
    fn summary_matches_hand_computation() {
        // Five values; mean 3, sample variance 2.5, t_{0.95, 4} = 2.131847 (tables).
        let s = summarize(&[1.0, 2.0, 3.0, 4.0, 5.0, f64::NAN], 0.9);
        assert_eq!(s.n, 5);
        assert!((s.mean - 3.0).abs() < 1e-12);
        assert!((s.std - 2.5f64.sqrt()).abs() < 1e-12);
        let half = 2.131847 * 2.5f64.sqrt() / 5f64.sqrt();
        assert!((s.ci_high - 3.0 - half).abs() < 1e-5, "{s:?}");
        assert!((s.ci_low - 3.0 + half).abs() < 1e-5);
        assert_eq!((s.min, s.max), (1.0, 5.0));
        assert!((s.rel_error - 2.0 * 2.5f64.sqrt() / 5f64.sqrt() / 3.0).abs() < 1e-12);
        // chi2_{0.05,4} = 0.710723, chi2_{0.95,4} = 9.487729 (tables).
        let (lo, hi) = variance_interval(2.5, 5, 0.9);
        assert!((lo - 4.0 * 2.5 / 9.487729).abs() < 1e-5, "{lo}");
        assert!((hi - 4.0 * 2.5 / 0.710723).abs() < 1e-4, "{hi}");
    }

    #[test]
    fn point_variance_of_two_phases() {
        // Sand 50 % at 70 GPa, binder 2 % at 10 GPa, pores 0: eq. (3.16) by hand.
        let d2 = point_variance(&[0.5, 0.02], &[70e9, 10e9]);
        let expect = 0.5 * 70e9f64.powi(2) + 0.02 * 1e20 - (0.5 * 70e9 + 0.02 * 10e9f64).powi(2);
        assert!((d2 - expect).abs() / expect < 1e-12);
    }

    /// Synthetic ensembles drawn with a known variance law: the fit recovers alpha and A_3,
    /// and the RVE volume inverts the law.
    #[test]
    fn rve_fit_recovers_alpha_and_integral_range() {
        let (alpha, a3, d2, mean): (f64, f64, f64, f64) = (1.1, 2.6e-11, 4.0e18, 5e9);
        let volumes: [f64; 5] = [2.2e-11, 5e-11, 8.8e-11, 2e-10, 3.5e-10];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut vol_col = Vec::new();
        let mut z = Vec::new();
        for &v in &volumes {
            let sd = (d2 * (a3 / v).powf(alpha)).sqrt();
            let normal = Normal::new(mean, sd).unwrap();
            for _ in 0..4000 {
                vol_col.push(v);
                z.push(normal.sample(&mut rng));
            }
        }
        let t = Table::new("synthetic")
            .with_f64("volume", "m^3", vol_col)
            .with_f64("E_x", "Pa", z);
        let (rve, trade) = rve_tables(&t, "volume", &[], d2, &[0.05], &[1, 30], 0.9).unwrap();
        let got_alpha = rve.f64_column("alpha").unwrap()[0];
        let got_a3 = rve.f64_column("integral_range").unwrap()[0];
        assert!((got_alpha - alpha).abs() < 0.05, "alpha {got_alpha}");
        assert!((got_a3 / a3 - 1.0).abs() < 0.15, "A3 {got_a3}");
        // eq. (3.14) with n = 1 at the RVE volume: 2 sqrt(Var) / mean = eps.
        let v_rve = rve.f64_column("rve_volume_eps0.05").unwrap()[0];
        let var = d2 * (a3 / v_rve).powf(alpha);
        assert!(((2.0 * var.sqrt() / mean) / 0.05 - 1.0).abs() < 0.2);
        // 30 realizations need a smaller cell than one.
        let tv = trade.f64_column("volume").unwrap();
        assert!(tv[1] < tv[0] / 10.0, "{tv:?}");
        // The exact law is recovered exactly without noise.
        let vars: Vec<f64> = volumes.iter().map(|v| d2 * (a3 / v).powf(alpha)).collect();
        let fit = fit_rve(&volumes, &vars, d2).unwrap();
        assert!((fit.alpha - alpha).abs() < 1e-10);
        assert!((fit.integral_range / a3 - 1.0).abs() < 1e-9);
        let n = fit.realizations_needed(volumes[0], mean, 0.05);
        assert!((fit.rve_volume(mean, 0.05, n) / volumes[0] - 1.0).abs() < 1e-9);
    }

    #[test]
    fn summary_table_groups_and_counts_failures() {
        let t = Table::new("sweep")
            .with_f64("phi", "1", vec![0.1, 0.1, 0.2, 0.2, 0.2])
            .with_f64("E", "Pa", vec![1.0, 3.0, 5.0, f64::NAN, 7.0])
            .with_i64("seed", "1", vec![1, 2, 1, 2, 3])
            .with_str(
                "status",
                ["ok", "ok", "ok", "failed", "ok"]
                    .map(String::from)
                    .to_vec(),
            );
        let s = summary_table(&t, &["phi".to_string()], &[], 0.9).unwrap();
        assert_eq!(s.rows(), 2, "only E is summarised, per phi");
        assert_eq!(s.f64_column("mean").unwrap(), &[2.0, 6.0]);
        match &s.column("n_failed").unwrap().data {
            ColumnData::I64(v) => assert_eq!(v, &[0, 1]),
            _ => panic!(),
        }
        let e = summary_table(&t, &["phy".to_string()], &[], 0.9).unwrap_err();
        assert!(e.contains("did you mean `phi`"), "{e}");
    }

    #[test]
    fn stage_reads_a_sweep_csv_and_describes_itself() {
        let mut r = grainpipe_core::Registry::new();
        crate::register(&mut r);
        r.check_consistency().unwrap();
        let d = tempfile::tempdir().unwrap();
        let csv = d.path().join("sweep.csv");
        std::fs::write(
            &csv,
            "run,vol [m^3],E [Pa],status\na,1,10,ok\nb,1,14,ok\nc,8,11,ok\nd,8,12,ok\ne,8,0,failed\n",
        )
        .unwrap();
        let yaml = format!(
            "name: e\nstages:\n  - id: ens\n    use: analysis.ensemble\n    with: {{ file: {}, \
             group_by: [vol], columns: [E], volume_column: vol }}\n",
            csv.display()
        );
        let res = grainpipe_core::testing::run_yaml(&r, &yaml).unwrap();
        assert_eq!(res.column("ens.summary", "mean"), [12.0, 11.5]);
        assert_eq!(res.column("ens.summary", "n_failed"), [0.0, 1.0]);
        // Variances 8 and 0.5 over volumes 1 and 8: alpha = ln(16) / ln(8) = 4/3.
        let alpha = res.value("ens.rve", "alpha");
        assert!((alpha - 16f64.ln() / 8f64.ln()).abs() < 1e-12, "{alpha}");
        // Both a table input and a file: refused before running.
        let bad = yaml.replace("group_by", "confidence: 1.5, group_by");
        let Err(e) = grainpipe_core::testing::run_yaml(&r, &bad) else {
            panic!("confidence 1.5 was accepted");
        };
        assert!(e.message.contains("confidence"), "{e}");
    }
}
