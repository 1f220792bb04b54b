//! The sweep table (`DIR/sweep.csv`, `DIR/sweep.h5`): one row per run, and its summary
//! (`DIR/summary.csv`, computed by `analysis.ensemble`'s functions).

use crate::runner::{load_result, RunResult};
use crate::spec::Manifest;
use grainpipe_analysis::ensemble;
use grainpipe_core::units::parse_quantity;
use grainpipe_core::{Artifact, Provenance, Table};
use std::path::Path;

/// Counts of a collected sweep.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counts {
    pub ok: usize,
    pub failed: usize,
    /// Runs without a result yet (not run, running, or killed without a trace).
    pub missing: usize,
}

/// The parameter columns: numbers (or quantities with a unit, in SI) as numbers, anything
/// else as text. Returns (name, unit, numeric values or None, text values).
fn parameter_column(m: &Manifest, k: usize) -> (Option<(Vec<f64>, String)>, Vec<String>) {
    let text: Vec<String> = m.runs.iter().map(|r| m.value(r, k).to_string()).collect();
    let parsed: Option<Vec<(f64, String)>> = text
        .iter()
        .map(|t| {
            let q = parse_quantity(t.trim_matches(|c| c == '"' || c == '\'')).ok()?;
            let unit = if q.dim == grainpipe_core::units::Dimension::NONE {
                "1".to_string()
            } else {
                q.dim.to_string()
            };
            Some((q.value, unit))
        })
        .collect();
    let numeric = parsed.and_then(|p| {
        let unit = p.first().map(|x| x.1.clone()).unwrap_or_default();
        p.iter()
            .all(|x| x.1 == unit)
            .then(|| (p.iter().map(|x| x.0).collect(), unit))
    });
    (numeric, text)
}

/// The volume of a box written `[Lx, Ly, Lz]` with lengths; `None` for anything else.
pub fn box_volume(text: &str) -> Option<f64> {
    let inner = text.trim().strip_prefix('[')?.strip_suffix(']')?;
    let parts: Vec<&str> = inner.split(',').collect();
    if parts.len() != 3 {
        return None;
    }
    let mut v = 1.0;
    for p in parts {
        let q = parse_quantity(p.trim().trim_matches(|c| c == '"' || c == '\'')).ok()?;
        if q.dim != grainpipe_core::units::Dimension::LENGTH {
            return None;
        }
        v *= q.value;
    }
    Some(v)
}

/// Reads every run's result into the tidy table, in run order. Columns: `run`, `point`,
/// `realization`, one per `--vary` key (SI numbers when every value is a number or a
/// quantity, else text), one per collected value (with its unit; NaN when the run failed),
/// `seed`, `wall_time` [s], `peak_memory` [B], `status` (ok, failed, missing), `error`.
pub fn sweep_table(dir: &Path, m: &Manifest) -> (Table, Counts) {
    let results: Vec<Option<RunResult>> = m.runs.iter().map(|r| load_result(dir, &r.id)).collect();
    let mut t = Table::new(format!("sweep-{}", m.pipeline_name))
        .with_str("run", m.runs.iter().map(|r| r.id.clone()).collect())
        .with_i64(
            "point",
            "1",
            m.runs.iter().map(|r| r.point as i64).collect(),
        )
        .with_i64(
            "realization",
            "1",
            m.runs.iter().map(|r| r.realization as i64).collect(),
        );
    for (k, v) in m.vary.iter().enumerate() {
        t = match parameter_column(m, k) {
            (Some((x, unit)), _) => t.with_f64(&v.key, &unit, x),
            (None, text) => {
                // A varied box size `[Lx, Ly, Lz]` also gives the cell volume, the abscissa of
                // the RVE analysis (eq. 3.15).
                let vols: Option<Vec<f64>> = text.iter().map(|s| box_volume(s)).collect();
                let t = t.with_str(&v.key, text);
                match vols {
                    Some(vols) => t.with_f64(&format!("{}.volume", v.key), "m^3", vols),
                    None => t,
                }
            }
        };
    }
    // Collected columns, in first-seen order over the runs.
    let mut names: Vec<(String, String)> = Vec::new();
    for r in results.iter().flatten() {
        for v in &r.values {
            if !names.iter().any(|(n, _)| *n == v.name) {
                names.push((v.name.clone(), v.unit.clone()));
            }
        }
    }
    for (name, unit) in &names {
        let col = results
            .iter()
            .map(|r| {
                r.as_ref()
                    .and_then(|r| r.values.iter().find(|v| v.name == *name))
                    .and_then(|v| v.value)
                    .unwrap_or(f64::NAN)
            })
            .collect();
        t = t.with_f64(name, unit, col);
    }
    let mut counts = Counts::default();
    let status: Vec<String> = results
        .iter()
        .map(|r| match r {
            Some(r) if r.status == "ok" => {
                counts.ok += 1;
                "ok".to_string()
            }
            Some(r) => {
                counts.failed += 1;
                r.status.clone()
            }
            None => {
                counts.missing += 1;
                "missing".to_string()
            }
        })
        .collect();
    let get = |f: &dyn Fn(&RunResult) -> f64| -> Vec<f64> {
        results
            .iter()
            .map(|r| r.as_ref().map_or(f64::NAN, f))
            .collect()
    };
    t = t
        .with_i64("seed", "1", m.runs.iter().map(|r| r.seed as i64).collect())
        .with_f64("wall_time", "s", get(&|r| r.wall_time))
        .with_f64("peak_memory", "B", get(&|r| r.peak_memory as f64))
        .with_str("status", status)
        .with_str(
            "error",
            results
                .iter()
                .map(|r| {
                    r.as_ref()
                        .map(|r| r.error.replace(['\n', '\r'], " "))
                        .unwrap_or_default()
                })
                .collect(),
        );
    (t, counts)
}

fn provenance(m: &Manifest) -> Provenance {
    let mut p = Provenance::default();
    let e = &mut p.entries;
    e.insert("grainpipe_version".into(), grainpipe_core::VERSION.into());
    e.insert("pipeline_file".into(), m.pipeline.display().to_string());
    e.insert("pipeline_blake3".into(), m.pipeline_blake3.clone());
    e.insert("pipeline_name".into(), m.pipeline_name.clone());
    e.insert("seed".into(), m.base_seed.to_string());
    e.insert(
        "seed_rule".into(),
        "realization r: BLAKE3(seed, \"realization\", r) >> 1, the same at every point".into(),
    );
    e.insert(
        "vary".into(),
        m.vary
            .iter()
            .map(|v| format!("{}={}", v.key, v.values.join(",")))
            .collect::<Vec<_>>()
            .join("; "),
    );
    e.insert("realizations".into(), m.realizations.to_string());
    p
}

/// Writes `sweep.csv`, `sweep.h5` and (when some run succeeded and values were collected)
/// `summary.csv`; all atomically. Returns the table and counts.
pub fn write_tables(dir: &Path, m: &Manifest) -> Result<(Table, Counts), String> {
    let (t, counts) = sweep_table(dir, m);
    let prov = provenance(m);
    let a = Artifact::Table(t);
    grainpipe_formats::write_csv(&a, &dir.join("sweep.csv"), &prov)?;
    grainpipe_formats::write_h5(&a, &dir.join("sweep.h5"), &prov)?;
    let Artifact::Table(t) = a else {
        unreachable!()
    };
    if let Some(s) = summary(&t, m)? {
        grainpipe_formats::write_csv(&Artifact::Table(s), &dir.join("summary.csv"), &prov)?;
    }
    Ok((t, counts))
}

/// The columns that describe a parameter point rather than a result: `point`, each varied key
/// and the box volumes derived from varied sizes.
pub fn point_columns(t: &Table, m: &Manifest) -> Vec<String> {
    let mut g = vec!["point".to_string()];
    for v in &m.vary {
        g.push(v.key.clone());
        let vol = format!("{}.volume", v.key);
        if t.column(&vol).is_some() {
            g.push(vol);
        }
    }
    g
}

/// Per parameter point and collected quantity: n, failures, mean, std, 90 % CI, min, max
/// (`analysis.ensemble`). `None` when nothing was collected.
pub fn summary(t: &Table, m: &Manifest) -> Result<Option<Table>, String> {
    let group_by = point_columns(t, m);
    let values = ensemble::value_columns(t, &group_by);
    if values.is_empty() {
        return Ok(None);
    }
    ensemble::summary_table(t, &group_by, &values, 0.9).map(Some)
}

/// The RVE analysis over the cell volumes of a sweep (eqs. 3.14-3.16): `rve.csv` (alpha,
/// integral range, RVE volumes per relative error), `rve_tradeoff.csv` (volume needed per
/// realization count, Fig. 9b), and per quantity the charts `charts/rve_variance_<q>` (Fig.
/// 9a, variances with their 90 % confidence intervals and the fit) and
/// `charts/rve_tradeoff_<q>` (Fig. 9b). Returns a short text report.
pub fn rve_outputs(
    dir: &Path,
    t: &Table,
    m: &Manifest,
    r: &crate::spec::RveSpec,
) -> Result<String, String> {
    use crate::charts::{self, Figure, Series};
    let mut group_by = point_columns(t, m);
    group_by.push(r.volume_column.clone());
    let quantities = ensemble::value_columns(t, &group_by);
    let d2 = r.point_variance.unwrap_or(f64::NAN);
    let (errors, counts) = ([0.05, 0.025, 0.01], [1u64, 5, 10, 30]);
    let (rve, trade) =
        ensemble::rve_tables(t, &r.volume_column, &quantities, d2, &errors, &counts, 0.9)?;
    let prov = provenance(m);
    grainpipe_formats::write_csv(&Artifact::Table(rve.clone()), &dir.join("rve.csv"), &prov)?;
    grainpipe_formats::write_csv(
        &Artifact::Table(trade),
        &dir.join("rve_tradeoff.csv"),
        &prov,
    )?;
    let vols = ensemble::numeric(t.column(&r.volume_column).expect("checked")).expect("checked");
    let status = match t.column("status").map(|c| &c.data) {
        Some(grainpipe_core::ColumnData::Str(s)) => s.clone(),
        _ => vec!["ok".into(); t.rows()],
    };
    let groups = ensemble::groups(t, std::slice::from_ref(&r.volume_column))?;
    let mut text = String::new();
    for (k, q) in quantities.iter().enumerate() {
        let v = ensemble::numeric(t.column(q).expect("listed")).expect("numeric");
        let mut pts = Vec::new();
        for (_, rows) in &groups {
            let ok: Vec<f64> = rows
                .iter()
                .filter(|&&i| status[i] == "ok")
                .map(|&i| v[i])
                .collect();
            let s = ensemble::summarize(&ok, 0.9);
            let var = s.std * s.std;
            let (lo, hi) = ensemble::variance_interval(var, s.n, 0.9);
            pts.push((vols[rows[0]], var, lo, hi));
        }
        let col = |name: &str| rve.f64_column(name).map_or(f64::NAN, |c| c[k]);
        let fit = ensemble::RveFit {
            alpha: col("alpha"),
            log_prefactor: col("log_prefactor"),
            point_variance: col("point_variance"),
            integral_range: col("integral_range"),
            r2: col("r2"),
        };
        let mean = col("mean_largest_cell");
        let stem = q.replace(|c: char| !c.is_ascii_alphanumeric() && c != '-', "_");
        charts::save(
            &charts::rve_figure(q, &pts, &fit),
            &dir.join("charts").join(format!("rve_variance_{stem}")),
        )?;
        // Fig. 9b: the relative error against the realization count at each measured volume.
        let mut f = Figure {
            title: format!("{q}: expected relative error, eq. (3.14)"),
            x_label: "realizations n".into(),
            y_label: "relative error [%]".into(),
            ..Default::default()
        };
        for (vol, _, _, _) in &pts {
            f.series.push(Series {
                name: format!("volume {vol:.3e}"),
                points: (1..=40)
                    .map(|n| {
                        let n = n as f64;
                        (
                            n,
                            100.0 * 2.0 * (fit.variance(*vol) / n).sqrt() / mean.abs(),
                        )
                    })
                    .collect(),
                line: true,
                ..Default::default()
            });
        }
        charts::save(&f, &dir.join("charts").join(format!("rve_tradeoff_{stem}")))?;
        text += &format!(
            "RVE {q}: alpha = {:.3}, A_3 = {:.4e}, RVE volume for 5 % = {:.4e} (r^2 = {:.3})\n",
            fit.alpha,
            fit.integral_range,
            col("rve_volume_eps0.05"),
            fit.r2
        );
    }
    Ok(text)
}
