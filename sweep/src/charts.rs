//! Charts of sweeps and studies, drawn with plotters as PNG (bitmap backend) and SVG:
//! violin plots of each collected quantity per parameter point (Donval et al. 2025, Figs. 6,
//! 7, 10), the quantity against a varied parameter with confidence-interval error bars
//! (Figs. 11-13), the variance against the cell volume with the fit of eq. (3.15) (Fig. 9a),
//! the realizations-against-volume trade-off (Fig. 9b), and a study's error against its cost.
//!
//! Text is rendered with ab_glyph (pure Rust) from a TrueType font found on the system
//! (DejaVu Sans, Debian package fonts-dejavu-core, or Liberation Sans); without one the
//! charts are drawn without text rather than not at all.

use crate::spec::Manifest;
use grainpipe_analysis::ensemble::{self, summarize, RveFit};
use grainpipe_core::{ColumnData, Table};
use std::path::Path;

pub use grainpipe_charts::{violin_figure, Figure, Group, HLine, Series};

/// Writes `<stem>.png` and `<stem>.svg` (each atomically).
pub fn save(f: &Figure, stem: &Path) -> Result<(), String> {
    f.save(stem)
}

/// Violins of `groups` (label, values), each with its mean and the 90 % confidence interval
/// of the mean (Student t) as a whisker on the violin's centre line, on one y axis.
pub fn violin_ci_figure(title: &str, y_label: &str, groups: &[(String, Vec<f64>)]) -> Figure {
    let g: Vec<Group> = groups
        .iter()
        .map(|(l, v)| {
            let s = summarize(v, 0.9);
            Group {
                label: l.clone(),
                values: v.clone(),
                mean: s.mean,
                ci: Some((s.ci_low, s.ci_high)),
            }
        })
        .collect();
    let mut f = grainpipe_charts::violins(title, y_label, &g);
    f.x_label = "parameter point".into();
    f.size = Some((960, 640));
    f
}

/// The variance of a quantity against the cell volume, log-log, with the 90 % confidence
/// interval of each variance and the fitted power law of eq. (3.15) (Fig. 9a).
pub fn rve_figure(name: &str, points: &[(f64, f64, f64, f64)], fit: &RveFit) -> Figure {
    let data = Series {
        name: "sample variance (90 % CI)".into(),
        points: points.iter().map(|p| (p.0, p.1)).collect(),
        err: points.iter().map(|p| (p.2, p.3)).collect(),
        markers: true,
        ..Default::default()
    };
    let (lo, hi) = points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
            (a.0.min(p.0), a.1.max(p.0))
        });
    let line = Series {
        name: format!("fit: alpha = {:.3}", fit.alpha),
        points: (0..=20)
            .map(|k| {
                let v = lo * (hi / lo).powf(k as f64 / 20.0);
                (v, fit.variance(v))
            })
            .collect(),
        line: true,
        ..Default::default()
    };
    Figure {
        title: format!("Var({name}) against cell volume, eq. (3.15)"),
        x_label: "cell volume [m³]".into(),
        y_label: format!("Var({name})"),
        series: vec![data, line],
        x_log: true,
        y_log: true,
        ..Default::default()
    }
}

/// A quantity name as a file name stem (the charts are `violin_<stem>.png`).
pub fn sanitize(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Every chart of a sweep table under `DIR/charts/`.
pub fn sweep_charts(dir: &Path, t: &Table, m: &Manifest) -> Result<(), String> {
    let group_by = crate::table::point_columns(t, m);
    let quantities = ensemble::value_columns(t, &group_by);
    if quantities.is_empty() {
        return Ok(());
    }
    let status = match t.column("status").map(|c| &c.data) {
        Some(ColumnData::Str(s)) => s.clone(),
        _ => vec!["ok".into(); t.rows()],
    };
    let groups = ensemble::groups(t, &group_by)?;
    // A point is labelled by its varied values as given on the command line (table rows are
    // in run order).
    let label = |rows: &[usize]| -> String {
        let run = &m.runs[rows[0]];
        let text = if run.overrides.is_empty() {
            format!("p{}", run.point)
        } else {
            run.overrides
                .iter()
                .map(|o| o.split_once('=').map_or(o.as_str(), |x| x.1))
                .collect::<Vec<_>>()
                .join(" / ")
        };
        if text.chars().count() > 28 {
            format!("p{}", run.point)
        } else {
            text
        }
    };
    let charts = dir.join("charts");
    // Quantities by their component names (`flow.permeability kappa_zz`, not `[8]`), as the
    // runs recorded them.
    let mut components: std::collections::HashMap<String, String> = Default::default();
    for run in &m.runs {
        for v in crate::runner::load_result(dir, &run.id)
            .map(|r| r.values)
            .unwrap_or_default()
        {
            if let Some(c) = v.component {
                components.entry(v.name).or_insert(c);
            }
        }
    }
    let shown =
        |q: &str| grainpipe_core::values::display_name(q, components.get(q).map(String::as_str));
    // The first numeric varied parameter is the x axis of the property-against-parameter charts.
    let xparam = group_by[1..]
        .iter()
        .find(|k| t.f64_column(k).is_some())
        .cloned();
    for q in &quantities {
        let c = t.column(q).expect("listed");
        let v = ensemble::numeric(c).expect("numeric");
        let unit = if c.unit.is_empty() {
            String::new()
        } else {
            format!(" [{}]", c.unit)
        };
        let samples: Vec<(String, Vec<f64>)> = groups
            .iter()
            .map(|(_, rows)| {
                (
                    label(rows),
                    rows.iter()
                        .filter(|&&r| status[r] == "ok")
                        .map(|&r| v[r])
                        .collect(),
                )
            })
            .collect();
        if m.realizations > 1 {
            let f = violin_ci_figure(
                &format!("{}: distribution per point (mean, 90 % CI)", shown(q)),
                &format!("{}{unit}", shown(q)),
                &samples,
            );
            save(&f, &charts.join(format!("violin_{}", sanitize(q))))?;
        }
        if let (Some(xp), true) = (&xparam, groups.len() > 1) {
            let xs = t.f64_column(xp).expect("numeric");
            // One series per combination of the other varied parameters.
            let others: Vec<String> = m
                .vary
                .iter()
                .map(|v| v.key.clone())
                .filter(|k| k != xp && !xp.starts_with(&format!("{k}.")))
                .collect();
            let other_groups = ensemble::groups(t, &others)?;
            let mut f = Figure {
                title: format!("{} against {xp} (mean, 90 % CI)", shown(q)),
                x_label: format!(
                    "{xp} [{}]",
                    t.column(xp).map(|c| c.unit.as_str()).unwrap_or("")
                ),
                y_label: format!("{}{unit}", shown(q)),
                ..Default::default()
            };
            for (okey, orows) in &other_groups {
                let mut s = Series {
                    name: okey.join(" / "),
                    line: true,
                    markers: true,
                    ..Default::default()
                };
                let mut pts: Vec<((f64, f64), (f64, f64))> = Vec::new();
                for (_, rows) in &groups {
                    if !orows.contains(&rows[0]) {
                        continue;
                    }
                    let ok: Vec<f64> = rows
                        .iter()
                        .filter(|&&r| status[r] == "ok")
                        .map(|&r| v[r])
                        .collect();
                    let st = summarize(&ok, 0.9);
                    pts.push(((xs[rows[0]], st.mean), (st.ci_low, st.ci_high)));
                }
                pts.sort_by(|a, b| a.0 .0.total_cmp(&b.0 .0));
                (s.points, s.err) = pts.into_iter().unzip();
                f.series.push(s);
            }
            save(
                &f,
                &charts.join(format!("{}_vs_{}", sanitize(q), sanitize(xp))),
            )?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn violins_with_intervals_are_written_as_png_and_svg() {
        let d = tempfile::tempdir().unwrap();
        let f = violin_ci_figure(
            "E_x",
            "E_x [Pa]",
            &[
                ("a".into(), vec![1.0, 2.0, 3.0]),
                ("b".into(), vec![2.0, 2.5, 4.0]),
            ],
        );
        // The whisker of each point on its violin's centre line.
        assert_eq!(f.series[1].points[1].0, 1.0);
        assert!(f.series[1].err.iter().all(|e| e.0.is_finite()));
        save(&f, &d.path().join("v")).unwrap();
        let png = std::fs::read(d.path().join("v.png")).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let svg = std::fs::read_to_string(d.path().join("v.svg")).unwrap();
        assert!(svg.contains("<svg") && svg.contains("polygon"));
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 2);
    }
}
