//! The report of a sweep directory, read generically from `DIR/sweep.csv` (one row per run,
//! columns by header `name [unit]`) and, when present, the varied keys of `DIR/sweep.json`:
//! the table of runs, per collected column a violin plot per parameter point with the mean
//! and its 90 % confidence interval, and the table of those intervals.

use crate::html::{self, esc, num, table};
use crate::numbers::summary;
use std::collections::HashMap;
use std::fmt::Write;
use std::path::Path;

/// Columns that describe a run rather than a result.
const META: &[&str] = &["run", "point", "realization", "seed", "status", "error"];

/// A CSV file's header and records (RFC 4180 quoting, by the `csv` crate; `#` comment lines
/// and empty lines skipped, rows of any length). A record that does not parse ends the
/// table.
pub fn parse_csv(text: &str) -> Vec<Vec<String>> {
    csv::ReaderBuilder::new()
        .has_headers(false)
        .comment(Some(b'#'))
        .flexible(true)
        .from_reader(text.as_bytes())
        .records()
        .map_while(Result::ok)
        .map(|r| r.iter().map(String::from).collect::<Vec<_>>())
        .filter(|r| !(r.len() == 1 && r[0].is_empty()))
        .collect()
}

/// `name [unit]` -> (name, unit).
fn split_header(h: &str) -> (String, String) {
    match h.strip_suffix(']').and_then(|x| x.rsplit_once(" [")) {
        Some((n, u)) => (n.to_string(), u.to_string()),
        None => (h.to_string(), String::new()),
    }
}

/// A sweep table.
pub struct Sweep {
    pub names: Vec<String>,
    pub units: Vec<String>,
    pub rows: Vec<Vec<String>>,
    /// Names of the varied parameters (from sweep.json).
    pub params: Vec<String>,
    pub pipeline: String,
    /// Component names of collected values (`kappa_xx` for `flow.permeability[0]`), from the
    /// runs' result.json.
    pub components: HashMap<String, String>,
}

/// The component names the runs recorded for their collected values (`runs/*/result.json`:
/// `values[].component`).
fn component_names(dir: &Path) -> HashMap<String, String> {
    let mut out = HashMap::new();
    let Ok(runs) = std::fs::read_dir(dir.join("runs")) else {
        return out;
    };
    let mut runs: Vec<_> = runs.flatten().map(|e| e.path()).collect();
    runs.sort();
    for r in runs {
        let Some(v) = std::fs::read_to_string(r.join("result.json"))
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        else {
            continue;
        };
        for x in v
            .get("values")
            .and_then(|x| x.as_array())
            .into_iter()
            .flatten()
        {
            if let (Some(n), Some(c)) = (
                x.get("name").and_then(|n| n.as_str()),
                x.get("component").and_then(|c| c.as_str()),
            ) {
                out.entry(n.to_string()).or_insert_with(|| c.to_string());
            }
        }
        if !out.is_empty() {
            break;
        }
    }
    out
}

impl Sweep {
    pub fn read(dir: &Path) -> Result<Sweep, String> {
        let p = dir.join("sweep.csv");
        let text =
            std::fs::read_to_string(&p).map_err(|e| format!("cannot read {}: {e}", p.display()))?;
        let mut rows = parse_csv(&text);
        if rows.is_empty() {
            return Err(format!("{} is empty", p.display()));
        }
        let head = rows.remove(0);
        let (names, units) = head.iter().map(|h| split_header(h)).unzip();
        let manifest: Option<serde_json::Value> = std::fs::read_to_string(dir.join("sweep.json"))
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok());
        let params = manifest
            .as_ref()
            .and_then(|m| m.get("vary"))
            .and_then(|v| v.as_array())
            .map(|a| {
                a.iter()
                    .filter_map(|x| x.get("key").and_then(|k| k.as_str()).map(String::from))
                    .collect()
            })
            .unwrap_or_default();
        let pipeline = manifest
            .as_ref()
            .and_then(|m| m.get("pipeline_name"))
            .and_then(|v| v.as_str())
            .unwrap_or("")
            .to_string();
        Ok(Sweep {
            names,
            units,
            rows,
            params,
            pipeline,
            components: component_names(dir),
        })
    }

    pub fn col(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    fn value(&self, r: usize, c: usize) -> f64 {
        self.rows[r]
            .get(c)
            .and_then(|v| v.trim().parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    }

    /// Numeric result columns: every column that is not a run descriptor or a parameter
    /// and has at least one number.
    pub fn value_columns(&self) -> Vec<usize> {
        (0..self.names.len())
            .filter(|&c| {
                let n = self.names[c].as_str();
                !META.contains(&n)
                    && !self.params.iter().any(|p| p == n)
                    && (0..self.rows.len()).any(|r| self.value(r, c).is_finite())
            })
            .collect()
    }

    /// Rows grouped by parameter point: (label, rows). The `point` column when present,
    /// else the parameter values, else one group.
    pub fn groups(&self) -> Vec<(String, Vec<usize>)> {
        let pcols: Vec<usize> = self.params.iter().filter_map(|p| self.col(p)).collect();
        let key = |r: usize| -> String {
            if pcols.is_empty() {
                match self.col("point") {
                    Some(c) => {
                        format!("point {}", self.rows[r].get(c).cloned().unwrap_or_default())
                    }
                    None => "all runs".into(),
                }
            } else {
                pcols
                    .iter()
                    .map(|&c| {
                        let u = &self.units[c];
                        let v = self.rows[r].get(c).cloned().unwrap_or_default();
                        if u.is_empty() || u == "1" {
                            format!("{} = {v}", self.names[c])
                        } else {
                            format!("{} = {v} {u}", self.names[c])
                        }
                    })
                    .collect::<Vec<_>>()
                    .join(", ")
            }
        };
        let mut groups: Vec<(String, Vec<usize>)> = vec![];
        for r in 0..self.rows.len() {
            let k = key(r);
            match groups.iter_mut().find(|g| g.0 == k) {
                Some(g) => g.1.push(r),
                None => groups.push((k, vec![r])),
            }
        }
        groups
    }

    /// The finite values of column `c` over `rows`, runs that failed left out.
    pub fn sample(&self, c: usize, rows: &[usize]) -> Vec<f64> {
        let status = self.col("status");
        rows.iter()
            .filter(|&&r| status.is_none_or(|s| self.rows[r].get(s).is_none_or(|v| v == "ok")))
            .map(|&r| self.value(r, c))
            .filter(|v| v.is_finite())
            .collect()
    }
}

/// The name a column is shown by ([`grainpipe_core::values::display_name`]).
fn display(s: &Sweep, c: usize) -> String {
    let n = &s.names[c];
    grainpipe_core::values::display_name(n, s.components.get(n).map(String::as_str))
}

fn label(s: &Sweep, c: usize) -> String {
    let u = &s.units[c];
    if u.is_empty() || u == "1" {
        display(s, c)
    } else {
        format!("{} [{u}]", display(s, c))
    }
}

/// An SVG file written by grainpipe-charts, for inline use: the XML prolog dropped, scaled to
/// the page's width.
fn inline_svg_file(path: &Path, class: &str) -> Option<String> {
    let t = std::fs::read_to_string(path).ok()?;
    let t = t.trim_start();
    let t = t
        .strip_prefix("<?xml version=\"1.0\" encoding=\"UTF-8\"?>")
        .unwrap_or(t)
        .trim_start();
    let rest = t.strip_prefix("<svg")?;
    Some(format!(
        "<svg class=\"{class}\" style=\"max-width:100%;height:auto\" data-file=\"{}\"{rest}",
        esc(&path.file_name()?.to_string_lossy())
    ))
}

/// The charts `pipe sweep` drew of the means against a varied parameter (`charts/*_vs_*.svg`)
/// and of the RVE analysis, inline.
fn charts_section(dir: &Path) -> String {
    let Ok(rd) = std::fs::read_dir(dir.join("charts")) else {
        return String::new();
    };
    let mut files: Vec<_> = rd
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            let n = p
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            n.ends_with(".svg") && !n.starts_with("violin_") && !n.starts_with('.')
        })
        .collect();
    files.sort();
    let charts: Vec<String> = files
        .iter()
        .filter_map(|p| inline_svg_file(p, "chart sweep-chart"))
        .collect();
    if charts.is_empty() {
        return String::new();
    }
    format!(
        "<section id=\"charts\"><h2>Means against the varied parameters</h2><p class=\"note\">\
         From the sweep's charts/ directory: each quantity's mean with its 90 % confidence \
         interval against the first numeric varied parameter (and the RVE analysis when it \
         ran).</p>{}</section>",
        charts.join("\n")
    )
}

/// A study's error against its cost (`study.svg`, `study_memory.svg`) and the level it chose
/// (`study.json`), when the directory holds a study.
fn study_section(dir: &Path) -> String {
    let Some(j) = std::fs::read_to_string(dir.join("study.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
    else {
        return String::new();
    };
    let text = |k: &str| -> String {
        match j.get(k) {
            None | Some(serde_json::Value::Null) => "–".into(),
            Some(serde_json::Value::String(s)) => esc(s),
            Some(serde_json::Value::Number(n)) => num(n.as_f64().unwrap_or(f64::NAN)),
            Some(v) => esc(&v.to_string()),
        }
    };
    let chosen = match j.get("chosen_level") {
        Some(serde_json::Value::String(s)) => {
            format!("<span class=\"ok\" id=\"chosen-level\">{}</span>", esc(s))
        }
        _ => "<span class=\"warn\" id=\"chosen-level\">none meets the target error</span>".into(),
    };
    let ev = j.get("evidence").filter(|e| !e.is_null());
    let evf = |k: &str| ev.and_then(|e| e.get(k)).and_then(|v| v.as_f64());
    let mut rows = vec![
        ("parameter", text("parameter")),
        ("metric", text("metric")),
        ("levels", text("levels")),
        ("error basis", text("error_basis")),
        ("observed order", text("observed_order")),
        ("target error", text("target_error")),
        ("chosen level", chosen),
    ];
    if let Some(e) = evf("error") {
        rows.push(("its error", html::pct(e)));
    }
    if let Some(w) = evf("wall_time_s") {
        rows.push(("its wall time", format!("{} s", num(w))));
    }
    if let Some(m) = evf("peak_memory_bytes") {
        rows.push(("its peak memory", html::bytes(m as u64)));
    }
    let charts: String = ["study.svg", "study_memory.svg"]
        .iter()
        .filter_map(|f| inline_svg_file(&dir.join(f), "chart study-front"))
        .collect::<Vec<_>>()
        .join("\n");
    format!(
        "<section id=\"study\"><h2>Study: error against cost</h2>{}<p class=\"note\">Each \
         level's relative error against its wall time and peak memory (log-log); the line is \
         the Pareto front (no other level is both cheaper and more accurate).</p>{charts}</section>",
        html::kv(&rows)
    )
}

/// The sweep report page.
pub fn sweep_page(dir: &Path, s: &Sweep) -> String {
    let groups = s.groups();
    let values = s.value_columns();
    let status = s.col("status");
    let count = |w: &str| {
        status.map_or(0, |c| {
            s.rows
                .iter()
                .filter(|r| r.get(c).is_some_and(|v| v == w))
                .count()
        })
    };
    let title = if s.pipeline.is_empty() {
        format!("sweep {}", dir.display())
    } else {
        format!("sweep of {}", s.pipeline)
    };
    let charts_html = charts_section(dir);
    let study_html = study_section(dir);
    let mut body =
        format!(
        "<header id=\"top\"><h1>{}</h1><nav><a href=\"#summary\">Summary</a><a href=\"#violins\">\
         Distributions</a>{}{}<a href=\"#intervals\">Confidence intervals</a>\
         <a href=\"#runs\">Runs</a></nav></header>",
        esc(&title),
        if charts_html.is_empty() { "" } else { "<a href=\"#charts\">Means</a>" },
        if study_html.is_empty() { "" } else { "<a href=\"#study\">Study</a>" },
    );
    let _ = write!(
        body,
        "<section id=\"summary\"><h2>Summary</h2>{}</section>",
        html::kv(&[
            ("directory", esc(&dir.display().to_string())),
            ("runs", s.rows.len().to_string()),
            (
                "status",
                format!(
                    "{} ok, {} failed, {} missing",
                    count("ok"),
                    s.rows.len() - count("ok") - count("missing"),
                    count("missing")
                )
            ),
            (
                "varied",
                if s.params.is_empty() {
                    "–".into()
                } else {
                    esc(&s.params.join(", "))
                }
            ),
            ("parameter points", groups.len().to_string()),
        ])
    );

    let mut v = String::from(
        "<section id=\"violins\"><h2>Distributions over the realizations</h2><p class=\"note\">\
         Per quantity, one violin per parameter point on one shared y axis: kernel density \
         (Gaussian, Silverman bandwidth), the runs as dots, the mean as a white dot and its 90 % \
         confidence interval (Student t) as a red whisker on the violin's centre line. Failed \
         runs are left out.</p>",
    );
    for &c in &values {
        let groups_c: Vec<grainpipe_charts::Group> = groups
            .iter()
            .filter_map(|(g, rows)| {
                let sample = s.sample(c, rows);
                if sample.is_empty() {
                    return None;
                }
                let m = summary(&sample);
                Some(grainpipe_charts::Group {
                    label: format!("{g} (n = {})", sample.len()),
                    values: sample,
                    mean: m.mean,
                    ci: m
                        .ci90
                        .is_finite()
                        .then_some((m.mean - m.ci90, m.mean + m.ci90)),
                })
            })
            .collect();
        if groups_c.is_empty() {
            continue;
        }
        let _ = write!(
            v,
            "<div class=\"violin-group\" data-column=\"{}\"><h3>{}{}</h3>{}</div>",
            esc(&s.names[c]),
            esc(&label(s, c)),
            if s.components.contains_key(&s.names[c]) {
                format!(" <span class=\"note\">({})</span>", esc(&s.names[c]))
            } else {
                String::new()
            },
            crate::plots::violins(&label(s, c), &groups_c)
        );
    }
    v.push_str("</section>");
    body.push_str(&v);
    body.push_str(&charts_html);
    body.push_str(&study_html);

    let mut rows = vec![];
    for &c in &values {
        for (g, r) in &groups {
            let sample = s.sample(c, r);
            if sample.is_empty() {
                continue;
            }
            let m = summary(&sample);
            rows.push(vec![
                esc(&label(s, c)),
                esc(g),
                m.n.to_string(),
                num(m.mean),
                num(m.std),
                format!("[{}, {}]", num(m.mean - m.ci90), num(m.mean + m.ci90)),
                if m.mean != 0.0 {
                    html::pct(m.ci90 / m.mean.abs())
                } else {
                    "–".into()
                },
                num(m.min),
                num(m.max),
            ]);
        }
    }
    let _ = write!(
        body,
        "<section id=\"intervals\"><h2>Means and 90 % confidence intervals</h2>{}</section>",
        table(
            "intervals",
            &[
                "value".into(),
                "point".into(),
                "n".into(),
                "mean".into(),
                "std".into(),
                "90 % CI of the mean".into(),
                "± relative".into(),
                "min".into(),
                "max".into()
            ],
            &rows,
            "Confidence interval: mean ± t(0.95, n − 1) s / √n."
        )
    );

    let mut head: Vec<String> = s
        .names
        .iter()
        .enumerate()
        .map(|(c, _)| esc(&label(s, c)))
        .collect();
    head.push("report".into());
    let run_col = s.col("run");
    let body_rows: Vec<Vec<String>> = s
        .rows
        .iter()
        .map(|r| {
            let mut cells: Vec<String> = r
                .iter()
                .map(|v| match v.parse::<f64>() {
                    Ok(x)
                        if !v.trim().is_empty()
                            && v.chars().any(|c| c.is_ascii_digit() || c == 'N') =>
                    {
                        num(x)
                    }
                    _ => esc(v),
                })
                .collect();
            let link = run_col
                .and_then(|c| r.get(c))
                .filter(|id| dir.join("runs").join(id).join("report.html").exists())
                .map(|id| format!("<a href=\"runs/{0}/report.html\">{0}</a>", esc(id)))
                .unwrap_or_default();
            cells.push(link);
            cells
        })
        .collect();
    let _ = write!(
        body,
        "<section id=\"runs\"><h2>Runs</h2>{}</section>",
        table(
            "runs",
            &head,
            &body_rows,
            "One row per run, as in sweep.csv."
        )
    );
    html::page(&format!("{title} — grainpipe report"), &body)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_with_quotes_and_comments() {
        let rows = parse_csv("# c\na,\"b [m]\",c\n1,\"x, \"\"y\"\"\",3\r\n2,,NaN\n");
        assert_eq!(rows.len(), 3);
        assert_eq!(rows[1], vec!["1", "x, \"y\"", "3"]);
        assert_eq!(rows[2], vec!["2", "", "NaN"]);
        assert_eq!(split_header("b [m]"), ("b".into(), "m".into()));
        assert_eq!(split_header("E_x [Pa]"), ("E_x".into(), "Pa".into()));
    }

    #[test]
    fn groups_and_samples() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("sweep.csv"),
            "run,point,realization,binder [1],E [Pa],seed,wall_time [s],peak_memory [B],status,error\n\
             p0-r0,0,0,0.02,1,7,1,10,ok,\n\
             p0-r1,0,1,0.02,3,8,1,10,ok,\n\
             p1-r0,1,0,0.04,5,7,1,10,ok,\n\
             p1-r1,1,1,0.04,NaN,8,1,10,failed,\"boom, really\"\n",
        )
        .unwrap();
        std::fs::write(
            dir.path().join("sweep.json"),
            r#"{"pipeline_name":"t","vary":[{"key":"binder","values":["0.02","0.04"]}]}"#,
        )
        .unwrap();
        let s = Sweep::read(dir.path()).unwrap();
        let vals: Vec<&str> = s
            .value_columns()
            .iter()
            .map(|&c| s.names[c].as_str())
            .collect();
        assert_eq!(vals, ["E", "wall_time", "peak_memory"]);
        let g = s.groups();
        assert_eq!(g.len(), 2);
        assert_eq!(g[0].0, "binder = 0.02");
        let e = s.col("E").unwrap();
        assert_eq!(s.sample(e, &g[0].1), vec![1.0, 3.0]);
        assert_eq!(s.sample(e, &g[1].1), vec![5.0]);
        let page = sweep_page(dir.path(), &s);
        // mean 2, s = sqrt 2, CI = t(1) sqrt2 / sqrt2 = 6.314.
        assert!(page.contains("[-4.314, 8.314]"), "{page}");
        assert!(page.contains("boom, really"));
    }
}
