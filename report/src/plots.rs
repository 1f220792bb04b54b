//! The charts of the pages, drawn with grainpipe-charts (plotters, one look with the sweep
//! charts): histograms, convergence and time histories, the frames of slices (axes in µm,
//! scale bar, colour bar) and violins.

use crate::data::{Body, Col, Item, Picture};
use crate::html::{self, esc};
use grainpipe_charts::slice::{self, ColorBar, Slice};
use grainpipe_charts::style::{self, axis_label};
use grainpipe_charts::{Figure, HLine, Secondary, Series};
use std::fmt::Write;

/// A figure as inline SVG with `class` and extra attributes; a note when it cannot be drawn.
pub fn svg(f: &Figure, class: &str, attrs: &[(&str, String)]) -> String {
    match f.svg(class) {
        Ok(s) => {
            // A log y axis says so (the browser tests and readers of the page look for it).
            let mut a = String::from(if f.y_log { " data-y-scale=\"log\"" } else { "" });
            for (k, v) in attrs {
                let _ = write!(a, " {k}=\"{}\"", esc(v));
            }
            let head = format!("<svg class=\"{class}\"");
            s.replacen(&head, &format!("{head}{a}"), 1)
        }
        Err(e) => format!("<p class=\"bad\">chart not drawn: {}</p>", esc(&e)),
    }
}

/// A histogram: bars of `counts` over `edges` (display units), with an optional cumulative
/// curve in percent on the right axis.
pub fn histogram(
    edges: &[f64],
    counts: &[f64],
    cumulative: Option<&[f64]>,
    xlabel: &str,
    ylabel: &str,
) -> String {
    let bars: Vec<(f64, f64, f64)> = counts
        .iter()
        .enumerate()
        .map(|(k, &c)| (edges[k], edges[k + 1], c))
        .collect();
    let secondary = cumulative.map(|cum| Secondary {
        label: "cumulative volume [%]".into(),
        range: (0.0, 100.0),
        series: vec![Series {
            points: std::iter::once((edges[0], 0.0))
                .chain(cum.iter().enumerate().map(|(k, &c)| (edges[k + 1], c)))
                .collect(),
            line: true,
            color: Some(style::PALETTE[0]),
            ..Default::default()
        }],
    });
    let f = Figure {
        x_label: xlabel.into(),
        y_label: ylabel.into(),
        bars,
        secondary,
        x_range: Some((edges[0], edges[edges.len() - 1])),
        size: Some((600, 280)),
        ..Default::default()
    };
    svg(
        &f,
        "chart histogram",
        &[("data-bars", counts.len().to_string())],
    )
}

fn numbers(c: &Col) -> Vec<f64> {
    c.values
        .iter()
        .map(|v| v.as_f64().unwrap_or(f64::NAN))
        .collect()
}

fn strings(c: &Col) -> Option<Vec<String>> {
    c.values
        .iter()
        .map(|v| v.as_str().map(String::from))
        .collect()
}

/// Points of `y` against `x`, one series per value of `group` (in order of appearance).
fn grouped(
    x: &[f64],
    y: &[f64],
    group: Option<&[String]>,
    keep: &dyn Fn(f64) -> bool,
) -> Vec<Series> {
    let mut out: Vec<Series> = vec![];
    for i in 0..x.len().min(y.len()) {
        if !x[i].is_finite() || !keep(y[i]) {
            continue;
        }
        let g = group.map(|g| g[i].as_str()).unwrap_or("");
        let s = match out.iter().position(|s| s.name == g) {
            Some(k) => &mut out[k],
            None => {
                out.push(Series {
                    name: g.to_string(),
                    line: true,
                    ..Default::default()
                });
                out.last_mut().expect("pushed")
            }
        };
        s.points.push((x[i], y[i]));
    }
    // A single point draws no line: mark it.
    for s in &mut out {
        s.markers = s.points.len() < 2;
    }
    out
}

/// The charts of a history table (convergence of a solver, time steps of a simulation): the
/// residual against the iteration on a log axis with the solver's `tolerance` as a line, one
/// line per load case or direction; the energy of a peridynamics solve; the overlap energy of
/// each MCM phase; temperatures and bonds of a sintering run against time.
pub fn history_charts(it: &Item, tolerance: Option<f64>) -> Vec<String> {
    let Body::Table { columns, curve, .. } = &it.body else {
        return vec![];
    };
    let cols = curve.as_ref().unwrap_or(columns);
    let col = |n: &str| cols.iter().find(|c| c.name == n);
    let group = ["load_case", "direction", "solver"]
        .iter()
        .find_map(|n| col(n).and_then(strings));
    let group = group.as_deref();
    let rows = cols.first().map(|c| c.values.len()).unwrap_or(0);
    let index: Vec<f64> = (0..rows).map(|i| i as f64).collect();
    let mut out = vec![];
    if let Some(res) = col("residual") {
        let (x, xl) = match col("iteration") {
            Some(c) => (numbers(c), "iteration"),
            None => (index.clone(), "row"),
        };
        let f = Figure {
            title: format!("{}: residual", it.source),
            x_label: xl.into(),
            y_label: axis_label("residual", &res.unit),
            series: grouped(&x, &numbers(res), group, &|v| v > 0.0 && v.is_finite()),
            hlines: tolerance
                .filter(|t| *t > 0.0)
                .map(|t| HLine {
                    y: t,
                    label: format!("tolerance {}", style::log_tick(t)),
                })
                .into_iter()
                .collect(),
            y_log: true,
            ..Default::default()
        };
        out.push(svg(
            &f,
            "chart convergence",
            &[("data-source", it.source.clone())],
        ));
    }
    if let (Some(en), Some(itc)) = (col("energy"), col("iteration")) {
        let f = Figure {
            title: format!("{}: energy", it.source),
            x_label: "iteration".into(),
            y_label: axis_label("energy", &en.unit),
            series: grouped(&numbers(itc), &numbers(en), group, &f64::is_finite),
            ..Default::default()
        };
        out.push(svg(
            &f,
            "chart history",
            &[("data-source", it.source.clone())],
        ));
    }
    if let Some(ov) = col("overlap_energy") {
        let f = Figure {
            title: format!("{}: overlap energy per overlap-removal phase", it.source),
            x_label: "phase".into(),
            y_label: axis_label("overlap energy", &ov.unit),
            series: grouped(&index, &numbers(ov), None, &|v| v > 0.0 && v.is_finite()),
            y_log: true,
            ..Default::default()
        };
        out.push(svg(
            &f,
            "chart convergence",
            &[("data-source", it.source.clone())],
        ));
    }
    if let Some(t) = col("time") {
        let time = numbers(t);
        let over_time = |names: &[&str], title: &str| -> Option<String> {
            let series: Vec<Series> = names
                .iter()
                .filter_map(|n| col(n))
                .enumerate()
                .map(|(k, c)| Series {
                    name: c.name.replace('_', " "),
                    points: time
                        .iter()
                        .zip(numbers(c))
                        .filter(|(a, b)| a.is_finite() && b.is_finite())
                        .map(|(a, b)| (*a, b))
                        .collect(),
                    line: true,
                    color: Some(style::pick(k)),
                    ..Default::default()
                })
                .filter(|s| !s.points.is_empty())
                .collect();
            let unit = names.iter().find_map(|n| col(n)).map(|c| c.unit.clone())?;
            (!series.is_empty()).then(|| {
                svg(
                    &Figure {
                        title: format!("{}: {title}", it.source),
                        x_label: axis_label("time", &t.unit),
                        y_label: axis_label(title, &unit),
                        series,
                        ..Default::default()
                    },
                    "chart history",
                    &[("data-source", it.source.clone())],
                )
            })
        };
        out.extend(over_time(
            &["max_temperature", "mean_temperature"],
            "temperature",
        ));
        out.extend(over_time(&["bonds"], "bonds"));
        out.extend(over_time(
            &["bonded_fraction", "bonded_particle_fraction"],
            "bonded fraction",
        ));
    }
    out
}

/// The tolerance a step was run with (its `tolerance` parameter), when it has one.
pub fn tolerance(params: &serde_json::Value) -> Option<f64> {
    match params.get("tolerance")? {
        serde_json::Value::Number(n) => n.as_f64(),
        serde_json::Value::String(s) => s.trim().parse().ok(),
        _ => None,
    }
}

/// A picture framed with axes in µm, a scale bar and (for fields) a colour bar: the
/// picture as a plain `<img>` under a transparent SVG frame.
pub fn framed(
    p: &Picture,
    png: &[u8],
    css_width: usize,
    extent_um: (f64, f64),
    axes: (&str, &str),
    colorbar: Option<ColorBar>,
) -> String {
    let w = css_width as f64;
    let h = if extent_um.0 > 0.0 && extent_um.1 > 0.0 {
        w * extent_um.1 / extent_um.0
    } else {
        w * p.height as f64 / p.width.max(1) as f64
    };
    let s = Slice {
        width: w.round() as u32,
        height: h.round().max(1.0) as u32,
        extent: extent_um,
        axes: (axes.0.into(), axes.1.into()),
        colorbar,
    };
    match slice::frame(&s) {
        Ok((svg, (tw, th), (xs, ys))) => format!(
            "<figure class=\"slice\"><div class=\"frame\" style=\"width:{tw}px;height:{th}px\">\
             {}{svg}</div><figcaption>{}</figcaption></figure>",
            html::img_at(
                png,
                &p.caption,
                xs.start,
                ys.start,
                xs.end - xs.start,
                ys.end - ys.start
            ),
            esc(&p.caption)
        ),
        Err(e) => format!(
            "<figure>{}<figcaption>{} (axes not drawn: {})</figcaption></figure>",
            html::img(png, &p.caption, p.width, p.height, css_width),
            esc(&p.caption),
            esc(&e)
        ),
    }
}

/// The violins of one quantity over the parameter points, on one chart (one y axis).
pub fn violins(label: &str, groups: &[grainpipe_charts::Group]) -> String {
    let f = grainpipe_charts::violins("", label, groups);
    let (_, (lo, hi)) = f.bounds();
    svg(
        &f,
        "violin",
        &[
            ("data-violins", groups.len().to_string()),
            (
                "data-y-range",
                format!("{} {}", style::tick(lo), style::tick(hi)),
            ),
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn col(name: &str, v: Vec<serde_json::Value>) -> Col {
        Col {
            name: name.into(),
            unit: String::new(),
            values: v,
        }
    }

    #[test]
    fn residual_history_is_plotted_on_a_log_axis_with_the_tolerance() {
        let n = 30;
        let it = Item {
            source: "stiffness.history".into(),
            body: Body::Table {
                name: "history".into(),
                rows: 2 * n,
                columns: vec![],
                curve: Some(vec![
                    col(
                        "load_case",
                        (0..2 * n)
                            .map(|i| if i < n { "xx" } else { "yy" }.into())
                            .collect(),
                    ),
                    col(
                        "iteration",
                        (0..2 * n).map(|i| ((i % n) as i64).into()).collect(),
                    ),
                    col(
                        "residual",
                        (0..2 * n)
                            .map(|i| 0.5f64.powi((i % n) as i32).into())
                            .collect(),
                    ),
                ]),
            },
        };
        let charts = history_charts(&it, Some(1e-6));
        assert_eq!(charts.len(), 1);
        let c = &charts[0];
        assert!(c.contains("data-y-scale=\"log\""), "{c}");
        assert!(c.contains("tolerance 1e-6"));
        // One line per load case, both named in the legend.
        assert!(c.contains(">\nxx\n<") || c.contains("xx"));
        assert!(c.contains("yy"));
        assert_eq!(
            tolerance(&serde_json::json!({"tolerance": 1e-4})),
            Some(1e-4)
        );
    }

    #[test]
    fn sintering_history_gives_temperature_and_bonds_over_time() {
        let t: Vec<serde_json::Value> = (0..10).map(|i| (i as f64 * 1e-3).into()).collect();
        let it = Item {
            source: "sinter.history".into(),
            body: Body::Table {
                name: "sintering_history".into(),
                rows: 10,
                columns: vec![
                    Col {
                        name: "time".into(),
                        unit: "s".into(),
                        values: t,
                    },
                    Col {
                        name: "max_temperature".into(),
                        unit: "K".into(),
                        values: (0..10).map(|i| (300.0 + 50.0 * i as f64).into()).collect(),
                    },
                    Col {
                        name: "bonds".into(),
                        unit: String::new(),
                        values: (0..10).map(|i| (i as i64 * 3).into()).collect(),
                    },
                ],
                curve: None,
            },
        };
        let charts = history_charts(&it, None);
        assert_eq!(charts.len(), 2);
        assert!(charts[0].contains("temperature [K]") && charts[0].contains("time [s]"));
        assert!(charts[1].contains("bonds"));
    }
}
