//! The report of a sweep directory, read generically from `DIR/sweep.csv` (one row per run,
//! columns by header `name [unit]`) and, when present, the varied keys of `DIR/sweep.json`:
//! the table of runs, per collected column a violin plot per parameter point with the mean
//! and its 90 % confidence interval, and the table of those intervals.

use crate::html::{self, esc, num, table};
use crate::numbers::summary;
use std::fmt::Write;
use std::path::Path;

/// Columns that describe a run rather than a result.
const META: &[&str] = &["run", "point", "realization", "seed", "status", "error"];

/// A CSV file's header and records (RFC 4180 quoting; `#` comment lines skipped).
pub fn parse_csv(text: &str) -> Vec<Vec<String>> {
    let mut rows = vec![];
    let mut row = vec![];
    let mut field = String::new();
    let mut quoted = false;
    let mut at_line_start = true;
    let mut chars = text.chars().peekable();
    while let Some(c) = chars.next() {
        if at_line_start && c == '#' && !quoted {
            for c in chars.by_ref() {
                if c == '\n' {
                    break;
                }
            }
            continue;
        }
        at_line_start = false;
        match (quoted, c) {
            (true, '"') if chars.peek() == Some(&'"') => {
                chars.next();
                field.push('"');
            }
            (true, '"') => quoted = false,
            (true, c) => field.push(c),
            (false, '"') => quoted = true,
            (false, ',') => row.push(std::mem::take(&mut field)),
            (false, '\r') => {}
            (false, '\n') => {
                row.push(std::mem::take(&mut field));
                rows.push(std::mem::take(&mut row));
                at_line_start = true;
            }
            (false, c) => field.push(c),
        }
    }
    if !field.is_empty() || !row.is_empty() {
        row.push(field);
        rows.push(row);
    }
    rows.retain(|r| !(r.len() == 1 && r[0].is_empty()));
    rows
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

fn label(s: &Sweep, c: usize) -> String {
    let u = &s.units[c];
    if u.is_empty() || u == "1" {
        s.names[c].clone()
    } else {
        format!("{} [{u}]", s.names[c])
    }
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
    let mut body = format!(
        "<header id=\"top\"><h1>{}</h1><nav><a href=\"#summary\">Summary</a><a href=\"#violins\">\
         Distributions</a><a href=\"#intervals\">Confidence intervals</a><a href=\"#runs\">Runs</a>\
         </nav></header>",
        esc(&title)
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
         One violin per parameter point: kernel density (Gaussian, Silverman bandwidth), the \
         runs as dots, the mean as a red bar and its 90 % confidence interval (Student t) as a \
         red whisker. Failed runs are left out.</p>",
    );
    for &c in &values {
        let _ = write!(
            v,
            "<div class=\"violin-group\" data-column=\"{}\"><h3>{}</h3>",
            esc(&s.names[c]),
            esc(&label(s, c))
        );
        for (g, rows) in &groups {
            let sample = s.sample(c, rows);
            if sample.is_empty() {
                continue;
            }
            let _ = write!(
                v,
                "<figure>{}<figcaption>{} (n = {})</figcaption></figure>",
                html::violin_svg(&sample, &label(s, c)),
                esc(g),
                sample.len()
            );
        }
        v.push_str("</div>");
    }
    v.push_str("</section>");
    body.push_str(&v);

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
