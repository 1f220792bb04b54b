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
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;
use std::sync::OnceLock;

const FONT_CANDIDATES: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation/LiberationSans-Regular.ttf",
];

/// Registers a system font once; false when none is available.
fn font_available() -> bool {
    static OK: OnceLock<bool> = OnceLock::new();
    *OK.get_or_init(|| {
        for p in FONT_CANDIDATES {
            if let Ok(bytes) = std::fs::read(p) {
                // plotters keeps fonts for the life of the process.
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok() {
                    return true;
                }
            }
        }
        false
    })
}

/// A series of points, with optional vertical error bars (low, high) and a connecting line.
#[derive(Clone, Debug, Default)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    pub err: Vec<(f64, f64)>,
    pub line: bool,
    pub markers: bool,
}

/// One chart.
#[derive(Clone, Debug, Default)]
pub struct Figure {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    /// Filled polygons (violins), with a palette index.
    pub polygons: Vec<(Vec<(f64, f64)>, usize)>,
    /// Category names at x = 0, 1, 2, ... (violin plots).
    pub categories: Vec<String>,
}

fn bounds(f: &Figure) -> ((f64, f64), (f64, f64)) {
    let mut xs: Vec<f64> = Vec::new();
    let mut ys: Vec<f64> = Vec::new();
    for s in &f.series {
        xs.extend(s.points.iter().map(|p| p.0));
        ys.extend(s.points.iter().map(|p| p.1));
        ys.extend(s.err.iter().flat_map(|e| [e.0, e.1]));
    }
    for (p, _) in &f.polygons {
        xs.extend(p.iter().map(|q| q.0));
        ys.extend(p.iter().map(|q| q.1));
    }
    let range = |v: &[f64]| {
        let v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
        let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if !lo.is_finite() {
            return (0.0, 1.0);
        }
        let pad = if hi > lo {
            0.06 * (hi - lo)
        } else {
            0.5 * lo.abs().max(1e-12)
        };
        (lo - pad, hi + pad)
    };
    let mut x = range(&xs);
    if !f.categories.is_empty() {
        x = (-0.6, f.categories.len() as f64 - 0.4);
    }
    (x, range(&ys))
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    f: &Figure,
    text: bool,
) -> Result<(), String>
where
    DB::ErrorType: 'static,
{
    let e = |x: DrawingAreaErrorKind<DB::ErrorType>| x.to_string();
    root.fill(&WHITE).map_err(e)?;
    let ((x0, x1), (y0, y1)) = bounds(f);
    let mut b = ChartBuilder::on(&root);
    b.margin(16);
    if text {
        b.caption(&f.title, ("sans-serif", 20))
            .x_label_area_size(48)
            .y_label_area_size(80);
    }
    let mut chart = b.build_cartesian_2d(x0..x1, y0..y1).map_err(e)?;
    let cats = f.categories.clone();
    let fmt_x = move |x: &f64| {
        if cats.is_empty() {
            short(*x)
        } else {
            let k = x.round();
            if (x - k).abs() < 1e-6 && k >= 0.0 && (k as usize) < cats.len() {
                cats[k as usize].clone()
            } else {
                String::new()
            }
        }
    };
    let fmt_y = |y: &f64| short(*y);
    let mut mesh = chart.configure_mesh();
    if text {
        mesh.x_desc(&f.x_label)
            .y_desc(&f.y_label)
            .x_label_formatter(&fmt_x)
            .y_label_formatter(&fmt_y)
            .label_style(("sans-serif", 14));
        if !f.categories.is_empty() {
            mesh.x_labels(f.categories.len() * 2 + 1);
        }
    } else {
        mesh.x_labels(0).y_labels(0);
    }
    mesh.light_line_style(RGBColor(235, 235, 235))
        .draw()
        .map_err(e)?;
    for (poly, c) in &f.polygons {
        let col = Palette99::pick(*c);
        chart
            .draw_series(std::iter::once(Polygon::new(
                poly.clone(),
                col.mix(0.45).filled(),
            )))
            .map_err(e)?;
        chart
            .draw_series(std::iter::once(PathElement::new(
                poly.clone(),
                col.stroke_width(1),
            )))
            .map_err(e)?;
    }
    for (k, s) in f.series.iter().enumerate() {
        let col = if f.polygons.is_empty() {
            Palette99::pick(k).to_rgba()
        } else {
            BLACK.to_rgba()
        };
        let pts: Vec<(f64, f64)> = s
            .points
            .iter()
            .copied()
            .filter(|p| p.0.is_finite() && p.1.is_finite())
            .collect();
        if s.line && pts.len() > 1 {
            let a = chart
                .draw_series(LineSeries::new(pts.clone(), col.stroke_width(2)))
                .map_err(e)?;
            if text && !s.name.is_empty() {
                a.label(&s.name).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], col.stroke_width(2))
                });
            }
        }
        for (p, er) in s.points.iter().zip(&s.err) {
            if p.0.is_finite() && er.0.is_finite() && er.1.is_finite() {
                chart
                    .draw_series(std::iter::once(PathElement::new(
                        vec![(p.0, er.0), (p.0, er.1)],
                        col.stroke_width(2),
                    )))
                    .map_err(e)?;
            }
        }
        if s.markers {
            let white = !f.polygons.is_empty();
            let a =
                chart
                    .draw_series(pts.iter().map(|&p| {
                        Circle::new(p, 4, if white { WHITE.filled() } else { col.filled() })
                    }))
                    .map_err(e)?;
            if text && !s.name.is_empty() && !s.line {
                a.label(&s.name)
                    .legend(move |(x, y)| Circle::new((x + 9, y), 4, col.filled()));
            }
        }
    }
    if text && f.series.iter().any(|s| !s.name.is_empty()) {
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(e)?;
    }
    root.present().map_err(e)?;
    Ok(())
}

/// Compact tick text.
fn short(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else if x.abs() >= 1e4 || x.abs() < 1e-2 {
        format!("{x:.2e}")
    } else {
        let s = format!("{x:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

/// Writes `<stem>.png` and `<stem>.svg` (each atomically).
pub fn save(f: &Figure, stem: &Path) -> Result<(), String> {
    let text = font_available();
    let size = (960u32, 640u32);
    let png = stem.with_extension("png");
    if let Some(d) = png.parent() {
        std::fs::create_dir_all(d).map_err(|e| format!("{}: {e}", d.display()))?;
    }
    // The bitmap backend picks the encoder by extension: the temporary file ends in .png.
    let name = png
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = png.with_file_name(format!(".{name}.{}.tmp.png", std::process::id()));
    let r = draw(BitMapBackend::new(&tmp, size).into_drawing_area(), f, text);
    match r {
        Ok(()) => std::fs::rename(&tmp, &png).map_err(|e| format!("{}: {e}", png.display()))?,
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(format!("{}: {e}", png.display()));
        }
    }
    let mut svg = String::new();
    draw(
        SVGBackend::with_string(&mut svg, size).into_drawing_area(),
        f,
        text,
    )
    .map_err(|e| format!("{}: {e}", stem.with_extension("svg").display()))?;
    grainpipe_core::fsutil::atomic_write_bytes(&stem.with_extension("svg"), svg.as_bytes())
}

/// A violin (kernel density, Gaussian kernel with Silverman's bandwidth, clipped to the data
/// range) centred at x = `at`, half width at most 0.4.
pub fn violin(values: &[f64], at: f64) -> Vec<(f64, f64)> {
    let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    let s = summarize(&v, 0.9);
    if v.len() < 2 || s.std.is_nan() || s.std <= 0.0 {
        let y = s.mean;
        return vec![(at - 0.3, y), (at + 0.3, y), (at + 0.3, y), (at - 0.3, y)];
    }
    let h = 1.06 * s.std * (v.len() as f64).powf(-0.2);
    let m = 60;
    let ys: Vec<f64> = (0..=m)
        .map(|k| s.min + (s.max - s.min) * k as f64 / m as f64)
        .collect();
    let dens: Vec<f64> = ys
        .iter()
        .map(|y| {
            v.iter()
                .map(|x| (-0.5 * ((y - x) / h).powi(2)).exp())
                .sum::<f64>()
        })
        .collect();
    let top = dens.iter().copied().fold(0.0, f64::max);
    let mut poly: Vec<(f64, f64)> = ys
        .iter()
        .zip(&dens)
        .map(|(y, d)| (at + 0.4 * d / top, *y))
        .collect();
    poly.extend(
        ys.iter()
            .zip(&dens)
            .rev()
            .map(|(y, d)| (at - 0.4 * d / top, *y)),
    );
    poly
}

/// Violins of `groups` (label, values) with the mean as a white dot (as in Fig. 6).
pub fn violin_figure(title: &str, y_label: &str, groups: &[(String, Vec<f64>)]) -> Figure {
    let mut f = Figure {
        title: title.into(),
        x_label: "parameter point".into(),
        y_label: y_label.into(),
        categories: groups.iter().map(|g| g.0.clone()).collect(),
        ..Default::default()
    };
    let mut means = Series {
        markers: true,
        ..Default::default()
    };
    for (k, (_, v)) in groups.iter().enumerate() {
        f.polygons.push((violin(v, k as f64), k));
        means.points.push((k as f64, summarize(v, 0.9).mean));
    }
    f.series.push(means);
    f
}

/// The variance of a quantity against the cell volume, log-log, with the 90 % confidence
/// interval of each variance and the fitted power law of eq. (3.15) (Fig. 9a).
pub fn rve_figure(name: &str, points: &[(f64, f64, f64, f64)], fit: &RveFit) -> Figure {
    let lg = |x: f64| x.log10();
    let data = Series {
        name: "sample variance (90 % CI)".into(),
        points: points.iter().map(|p| (lg(p.0), lg(p.1))).collect(),
        err: points.iter().map(|p| (lg(p.2), lg(p.3))).collect(),
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
                (lg(v), lg(fit.variance(v)))
            })
            .collect(),
        line: true,
        ..Default::default()
    };
    Figure {
        title: format!("Var({name}) against cell volume, eq. (3.15)"),
        x_label: "log10 cell volume".into(),
        y_label: format!("log10 Var({name})"),
        series: vec![data, line],
        ..Default::default()
    }
}

fn sanitize(s: &str) -> String {
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
            let f = violin_figure(
                &format!("{q}: distribution per point"),
                &format!("{q}{unit}"),
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
                title: format!("{q} against {xp} (mean, 90 % CI)"),
                x_label: format!(
                    "{xp} [{}]",
                    t.column(xp).map(|c| c.unit.as_str()).unwrap_or("")
                ),
                y_label: format!("{q}{unit}"),
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
    fn violin_is_symmetric_and_spans_the_data() {
        let v = [1.0, 2.0, 2.5, 3.0, 4.0];
        let p = violin(&v, 2.0);
        let ys: Vec<f64> = p.iter().map(|q| q.1).collect();
        assert_eq!(ys.iter().copied().fold(f64::INFINITY, f64::min), 1.0);
        assert_eq!(ys.iter().copied().fold(f64::NEG_INFINITY, f64::max), 4.0);
        let n = p.len() / 2;
        for k in 0..n {
            assert!(((p[k].0 - 2.0) + (p[p.len() - 1 - k].0 - 2.0)).abs() < 1e-12);
        }
        assert!(p.iter().all(|q| (q.0 - 2.0).abs() <= 0.4 + 1e-12));
    }

    #[test]
    fn figures_are_written_as_png_and_svg() {
        let d = tempfile::tempdir().unwrap();
        let f = violin_figure(
            "E_x",
            "E_x [Pa]",
            &[
                ("a".into(), vec![1.0, 2.0, 3.0]),
                ("b".into(), vec![2.0, 2.5, 4.0]),
            ],
        );
        save(&f, &d.path().join("v")).unwrap();
        let png = std::fs::read(d.path().join("v.png")).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let svg = std::fs::read_to_string(d.path().join("v.svg")).unwrap();
        assert!(
            svg.contains("<svg") && svg.contains("polygon"),
            "{}",
            &svg[..200.min(svg.len())]
        );
        // Only the two files: no temporary left behind.
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 2);
    }
}
