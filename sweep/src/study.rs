//! `pipe study`: a resolution (speed against accuracy) study. The levels run as a one-
//! realization sweep (same child processes, same manifest and results, one at a time so
//! their wall times and peak memories compare); then each level's error is estimated against
//! the finest level and, when the three finest levels converge monotonically with a sensible
//! observed order, against the Richardson extrapolation; the Pareto front of error against
//! wall time (and memory) is what a user picks a resolution from (Donval et al. 2025, Tables
//! 2-3).

use crate::runner::{Launcher, LocalOptions};
use crate::spec::{Manifest, PluginLoad};
use crate::{charts, fail, prepare, runner, table, SetupArgs, StudyArgs};
use grainpipe_core::units::parse_quantity;
use grainpipe_core::{Artifact, Provenance, Table};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Richardson extrapolation from levels with step sizes `h` (any order) and values `z`: uses
/// the three finest levels, solves (z1 - z2) / (z2 - z3) = (h1^p - h2^p) / (h2^p - h3^p) for
/// the observed order p (bisection; any ratios) and extrapolates z* = z3 + (z3 - z2) /
/// ((h2/h3)^p - 1). `None` when the differences change sign (no asymptotic convergence) or the
/// order falls outside [0.25, 8].
pub fn richardson(h: &[f64], z: &[f64]) -> Option<(f64, f64)> {
    let mut lv: Vec<(f64, f64)> = h.iter().copied().zip(z.iter().copied()).collect();
    lv.retain(|p| p.0.is_finite() && p.0 > 0.0 && p.1.is_finite());
    lv.sort_by(|a, b| b.0.total_cmp(&a.0));
    if lv.len() < 3 {
        return None;
    }
    let [(h1, z1), (h2, z2), (h3, z3)] = [lv[lv.len() - 3], lv[lv.len() - 2], lv[lv.len() - 1]];
    let (d12, d23) = (z1 - z2, z2 - z3);
    if d23 == 0.0 || d12 / d23 <= 0.0 {
        return None;
    }
    let target = d12 / d23;
    let g = |p: f64| (h1.powf(p) - h2.powf(p)) / (h2.powf(p) - h3.powf(p)) - target;
    let (mut lo, mut hi) = (0.25f64, 8.0f64);
    if g(lo) * g(hi) > 0.0 {
        return None;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if g(lo) * g(mid) <= 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    let p = 0.5 * (lo + hi);
    Some((p, z3 + (z3 - z2) / ((h2 / h3).powf(p) - 1.0)))
}

/// Richardson extrapolation from the two finest levels with an assumed order `p` (what two
/// levels allow: the order cannot be observed from them): z* = z2 + (z2 - z1) /
/// ((h1/h2)^p - 1), the same formula as [`richardson`]'s with p given. `None` with fewer
/// than two levels or equal steps.
pub fn richardson_assumed(h: &[f64], z: &[f64], p: f64) -> Option<f64> {
    let mut lv: Vec<(f64, f64)> = h.iter().copied().zip(z.iter().copied()).collect();
    lv.retain(|q| q.0.is_finite() && q.0 > 0.0 && q.1.is_finite());
    lv.sort_by(|a, b| b.0.total_cmp(&a.0));
    if lv.len() < 2 || p.is_nan() || p <= 0.0 {
        return None;
    }
    let [(h1, z1), (h2, z2)] = [lv[lv.len() - 2], lv[lv.len() - 1]];
    let r = (h1 / h2).powf(p);
    (r > 1.0).then(|| z2 + (z2 - z1) / (r - 1.0))
}

/// Indices of the levels on the Pareto front of (cost, error): no other level is at least as
/// cheap and at least as accurate, and strictly better in one.
pub fn pareto(cost: &[f64], error: &[f64]) -> Vec<bool> {
    (0..cost.len())
        .map(|i| {
            !(0..cost.len()).any(|j| {
                j != i
                    && cost[j] <= cost[i]
                    && error[j] <= error[i]
                    && (cost[j] < cost[i] || error[j] < error[i])
            })
        })
        .collect()
}

/// One level's analysis.
#[derive(Clone, Debug, PartialEq)]
pub struct Level {
    pub value: String,
    /// The step size h used for the order (the value when levels decrease, 1/value when they
    /// increase, e.g. voxels per diameter).
    pub h: f64,
    pub metric: f64,
    pub wall_time: f64,
    pub peak_memory: f64,
    pub error_vs_finest: f64,
    pub error_richardson: f64,
    /// The error used for decisions: Richardson when available, else against the finest.
    pub error: f64,
    pub pareto: bool,
}

/// The study's conclusions.
#[derive(Clone, Debug, PartialEq)]
pub struct Analysis {
    pub levels: Vec<Level>,
    /// (observed order, extrapolated value) when Richardson applies.
    pub richardson: Option<(f64, f64)>,
    /// Index of the coarsest level whose error is below the target.
    pub chosen: Option<usize>,
}

/// A level's error in the study table. Without an extrapolation the finest level is the
/// reference and has no error of its own (it printed "NaN%").
fn error_cell(error: f64) -> String {
    if error.is_finite() {
        format!("{:>9.3}%", 100.0 * error)
    } else {
        format!("{:>10}", "reference")
    }
}

/// Analyses levels (given coarse to fine): values as text, metric values, costs.
pub fn analyse(
    values: &[String],
    metric: &[f64],
    wall: &[f64],
    memory: &[f64],
    target_error: Option<f64>,
) -> Result<Analysis, String> {
    let x: Vec<f64> = values
        .iter()
        .map(|v| {
            parse_quantity(v.trim_matches(|c| c == '"' || c == '\''))
                .map(|q| q.value)
                .map_err(|e| format!("study level `{v}` is not a number or quantity: {e}"))
        })
        .collect::<Result<_, _>>()?;
    if x.len() < 2 {
        return Err("a study needs at least two levels".into());
    }
    let decreasing = x.windows(2).all(|w| w[1] < w[0]);
    let increasing = x.windows(2).all(|w| w[1] > w[0]);
    let h: Vec<f64> = match (decreasing, increasing) {
        (true, _) => x.clone(),
        (_, true) => x.iter().map(|v| 1.0 / v).collect(),
        _ => {
            return Err(
                "give the levels coarse to fine, monotonically (e.g. 8um,4um,2um or 10,20,40)"
                    .into(),
            )
        }
    };
    let n = x.len();
    if let Some(k) = metric.iter().position(|m| !m.is_finite()) {
        return Err(format!(
            "study level `{}` gave a non-finite metric ({}): no error can be estimated",
            values[k], metric[k]
        ));
    }
    let finest = metric[n - 1];
    let rich = richardson(&h, metric);
    let rel = |a: f64, b: f64| (a - b).abs() / b.abs();
    let mut levels: Vec<Level> = (0..n)
        .map(|k| {
            let vs_fine = if k + 1 == n {
                f64::NAN
            } else {
                rel(metric[k], finest)
            };
            let vs_rich = rich.map_or(f64::NAN, |(_, z)| rel(metric[k], z));
            Level {
                value: values[k].clone(),
                h: h[k],
                metric: metric[k],
                wall_time: wall[k],
                peak_memory: memory[k],
                error_vs_finest: vs_fine,
                error_richardson: vs_rich,
                error: if rich.is_some() { vs_rich } else { vs_fine },
                pareto: false,
            }
        })
        .collect();
    let known: Vec<usize> = (0..n).filter(|&k| levels[k].error.is_finite()).collect();
    let front = pareto(
        &known.iter().map(|&k| wall[k]).collect::<Vec<_>>(),
        &known.iter().map(|&k| levels[k].error).collect::<Vec<_>>(),
    );
    for (&k, f) in known.iter().zip(front) {
        levels[k].pareto = f;
    }
    let chosen = target_error.and_then(|t| (0..n).find(|&k| levels[k].error <= t));
    Ok(Analysis {
        levels,
        richardson: rich,
        chosen,
    })
}

fn study_table(a: &Analysis, key: &str, metric: &str) -> Table {
    let l = &a.levels;
    Table::new("study")
        .with_i64("level", "1", (0..l.len() as i64).collect())
        .with_str(key, l.iter().map(|x| x.value.clone()).collect())
        .with_f64("h", "", l.iter().map(|x| x.h).collect())
        .with_f64(metric, "", l.iter().map(|x| x.metric).collect())
        .with_f64("wall_time", "s", l.iter().map(|x| x.wall_time).collect())
        .with_f64(
            "peak_memory",
            "B",
            l.iter().map(|x| x.peak_memory).collect(),
        )
        .with_f64(
            "error_vs_finest",
            "1",
            l.iter().map(|x| x.error_vs_finest).collect(),
        )
        .with_f64(
            "error_richardson",
            "1",
            l.iter().map(|x| x.error_richardson).collect(),
        )
        .with_f64("error", "1", l.iter().map(|x| x.error).collect())
        .with_i64("pareto", "1", l.iter().map(|x| x.pareto as i64).collect())
}

/// Error against cost (log-log), one point per level, the Pareto front as a line.
fn cost_figure(
    a: &Analysis,
    cost: &dyn Fn(&Level) -> f64,
    what: &str,
    metric: &str,
) -> charts::Figure {
    let pts = |only_front: bool| -> Vec<(f64, f64)> {
        let mut p: Vec<(f64, f64)> = a
            .levels
            .iter()
            .filter(|l| l.error.is_finite() && l.error > 0.0 && (!only_front || l.pareto))
            .map(|l| (cost(l), l.error))
            .collect();
        p.sort_by(|x, y| x.0.total_cmp(&y.0));
        p
    };
    charts::Figure {
        title: format!("{metric}: error against {what}"),
        x_label: what.to_string(),
        y_label: "relative error".into(),
        x_log: true,
        y_log: true,
        series: vec![
            charts::Series {
                name: "levels".into(),
                points: pts(false),
                markers: true,
                ..Default::default()
            },
            charts::Series {
                name: "Pareto front".into(),
                points: pts(true),
                line: true,
                ..Default::default()
            },
        ],
        ..Default::default()
    }
}

/// Runs the study in `dir` (levels through `launch`), analyses it and writes study.csv,
/// study.json and the charts. Returns the analysis.
pub fn run_study(
    args: &StudyArgs,
    registry: &mut grainpipe_core::Registry,
    load_plugins: &mut PluginLoad,
    launch: &Launcher,
) -> Result<(PathBuf, Analysis), ExitCode> {
    let vary = crate::spec::parse_vary(&args.vary).map_err(|e| fail(2, e))?;
    let metric = crate::spec::parse_collect(&args.metric).map_err(|e| fail(2, e))?;
    if metric.column.is_none() {
        return Err(fail(
            2,
            format!(
                "--metric `{}`: name a column, step.port.column",
                args.metric
            ),
        ));
    }
    let name = grainpipe_core::pipeline::PipelineDoc::load(&args.file)
        .map(|d| d.name)
        .unwrap_or_default();
    let setup = SetupArgs {
        file: Some(args.file.clone()),
        vary: vec![args.vary.clone()],
        realizations: 1,
        collect: vec![args.metric.clone()],
        overrides: args.overrides.clone(),
        out: Some(
            args.out
                .clone()
                .unwrap_or_else(|| PathBuf::from("out").join(format!("study-{name}"))),
        ),
        jobs: Some(1),
        threads: args.threads,
        // Cached steps would make a level look cheaper than it is: every level is timed from
        // scratch.
        no_cache: true,
        quiet: args.quiet,
        ..Default::default()
    };
    let p = prepare(&setup, registry, load_plugins)?;
    // One level at a time, so wall times and peak memories are comparable.
    let opts = LocalOptions {
        jobs: 1,
        memory_budget: None,
        stop_after: None,
        quiet: args.quiet,
    };
    runner::run_local(&p.dir, &p.manifest, &p.todo, &opts, launch);
    let (t, counts) = table::write_tables(&p.dir, &p.manifest).map_err(|e| fail(1, e))?;
    if counts.ok != p.manifest.runs.len() {
        return Err(fail(
            1,
            format!(
                "{} of {} levels failed; see {}",
                counts.failed + counts.missing,
                p.manifest.runs.len(),
                p.dir.join("sweep.csv").display()
            ),
        ));
    }
    // A tensor component is collected as `step.port[k]` for `--metric step.port.k`.
    let tensor_name = format!(
        "{}.{}[{}]",
        metric.step,
        metric.port,
        metric.column.as_deref().unwrap_or_default()
    );
    let col = t
        .columns
        .iter()
        .find(|c| {
            c.name == args.metric
                || c.name == tensor_name
                || c.name.starts_with(&format!("{}[", args.metric))
        })
        .ok_or_else(|| fail(1, format!("no values of `{}` were collected", args.metric)))?;
    let z = grainpipe_analysis::ensemble::numeric(col).expect("collected values are numbers");
    let wall = t.f64_column("wall_time").expect("sweep table").to_vec();
    let mem = t.f64_column("peak_memory").expect("sweep table").to_vec();
    let a = analyse(&vary.values, &z, &wall, &mem, args.target_error).map_err(|e| fail(2, e))?;
    write_outputs(&p.dir, &p.manifest, &a, args).map_err(|e| fail(1, e))?;
    Ok((p.dir, a))
}

fn write_outputs(dir: &Path, m: &Manifest, a: &Analysis, args: &StudyArgs) -> Result<(), String> {
    let key = &m.vary[0].key;
    let t = study_table(a, key, &args.metric);
    let mut prov = Provenance::default();
    prov.entries
        .insert("pipeline_file".into(), m.pipeline.display().to_string());
    prov.entries
        .insert("pipeline_blake3".into(), m.pipeline_blake3.clone());
    grainpipe_formats::write_csv(&Artifact::Table(t), &dir.join("study.csv"), &prov)?;
    let summary = json!({
        "pipeline": m.pipeline,
        "parameter": key,
        "metric": args.metric,
        "levels": a.levels.iter().map(|l| &l.value).collect::<Vec<_>>(),
        "observed_order": a.richardson.map(|r| r.0),
        "extrapolated": a.richardson.map(|r| r.1),
        "error_basis": if a.richardson.is_some() { "richardson" } else { "finest level" },
        "target_error": args.target_error,
        "chosen_level": a.chosen.map(|k| &a.levels[k].value),
        "evidence": a.chosen.map(|k| json!({
            "error": a.levels[k].error,
            "wall_time_s": a.levels[k].wall_time,
            "peak_memory_bytes": a.levels[k].peak_memory,
        })),
    });
    grainpipe_core::fsutil::atomic_write_bytes(
        &dir.join("study.json"),
        serde_json::to_string_pretty(&summary)
            .map_err(|e| e.to_string())?
            .as_bytes(),
    )?;
    charts::save(
        &cost_figure(a, &|l| l.wall_time, "wall time [s]", &args.metric),
        &dir.join("study"),
    )?;
    charts::save(
        &cost_figure(a, &|l| l.peak_memory, "peak memory [B]", &args.metric),
        &dir.join("study_memory"),
    )
}

/// `pipe study`.
pub fn study_command(
    args: StudyArgs,
    registry: &mut grainpipe_core::Registry,
    load_plugins: &mut PluginLoad,
    plugin_dirs: &[PathBuf],
) -> ExitCode {
    let exe = match std::env::current_exe() {
        Ok(e) => e,
        Err(e) => return fail(2, format!("cannot locate the pipe binary: {e}")),
    };
    let launch = crate::self_launcher(exe, plugin_dirs.to_vec(), args.threads);
    match run_study(&args, registry, load_plugins, &launch) {
        Ok((dir, a)) => {
            println!(
                "{:>14} {:>14} {:>10} {:>12} {:>10}",
                "level", "metric", "wall [s]", "memory", "error"
            );
            for l in &a.levels {
                let error = error_cell(l.error);
                println!(
                    "{:>14} {:>14.6e} {:>10.2} {:>12} {error}{}",
                    l.value,
                    l.metric,
                    l.wall_time,
                    grainpipe_core::engine::human_bytes(l.peak_memory as u64),
                    if l.pareto { "  pareto" } else { "" }
                );
            }
            match a.richardson {
                Some((p, z)) => println!("observed order {p:.2}, extrapolated {z:.6e}"),
                None => println!(
                    "no Richardson extrapolation (the finest levels do not converge monotonically \
                     or the order is out of range): errors are against the finest level"
                ),
            }
            if let Some(t) = args.target_error {
                match a.chosen {
                    Some(k) => println!(
                        "target error {t}: coarsest level meeting it is {} (recorded in {})",
                        a.levels[k].value,
                        dir.join("study.json").display()
                    ),
                    None => println!("target error {t}: no level meets it; refine further"),
                }
            }
            println!("-> {}", dir.join("study.csv").display());
            ExitCode::SUCCESS
        }
        Err(code) => code,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn richardson_recovers_order_and_limit() {
        // z = 1 + 0.3 h^2 at uneven steps.
        let h = [8.0, 5.0, 3.0, 2.0];
        let z: Vec<f64> = h.iter().map(|h| 1.0 + 0.3 * h * h).collect();
        let (p, lim) = richardson(&h, &z).unwrap();
        assert!((p - 2.0).abs() < 1e-6, "{p}");
        assert!((lim - 1.0).abs() < 1e-9, "{lim}");
        // Oscillating values: no extrapolation.
        assert!(richardson(&[4.0, 2.0, 1.0], &[1.0, 1.2, 1.1]).is_none());
    }

    /// Two levels cannot show their order; with the true order assumed the limit is exact
    /// on a sequence z = z* + C h^p, and a wrong assumption errs by a known amount.
    #[test]
    fn richardson_with_two_levels_and_an_assumed_order() {
        // z = 2 - 0.5 h^1.5 at h = 1/6 and 1/12 (voxels per diameter 6, 12).
        let h = [1.0 / 6.0, 1.0 / 12.0];
        let z: Vec<f64> = h.iter().map(|h: &f64| 2.0 - 0.5 * h.powf(1.5)).collect();
        let lim = richardson_assumed(&h, &z, 1.5).unwrap();
        assert!((lim - 2.0).abs() < 1e-12, "{lim}");
        // Assuming order 1 instead: z2 - z1 = C h2^1.5 (2^1.5 - 1), so z2 + (z2 - z1) / (2 - 1)
        // = 2 + C h2^1.5 (2^1.5 - 2): a too-low order overshoots the limit (by 9.97e-3 here).
        let lim1 = richardson_assumed(&h, &z, 1.0).unwrap();
        let expected = 2.0 + 0.5 * (1.0f64 / 12.0).powf(1.5) * (2f64.powf(1.5) - 2.0);
        assert!((lim1 - expected).abs() < 1e-12, "{lim1} vs {expected}");
        // Order does not matter for the input order of the levels.
        assert_eq!(
            richardson_assumed(&[h[1], h[0]], &[z[1], z[0]], 1.5),
            Some(lim)
        );
        assert!(richardson_assumed(&[0.1], &[1.0], 1.0).is_none());
        assert!(richardson_assumed(&[0.1, 0.1], &[1.0, 1.1], 1.0).is_none());
    }

    #[test]
    fn the_reference_level_has_no_error_printed_as_nan() {
        let values: Vec<String> = ["4um", "2um", "1um"].map(String::from).to_vec();
        // Oscillating: no extrapolation, errors against the finest level.
        let a = analyse(&values, &[1.0, 1.2, 1.1], &[1.0; 3], &[1.0; 3], None).unwrap();
        assert!(a.richardson.is_none());
        assert_eq!(error_cell(a.levels[2].error).trim(), "reference");
        assert_eq!(error_cell(a.levels[0].error).trim(), "9.091%");
        let e = analyse(&values, &[1.0, f64::NAN, 1.1], &[1.0; 3], &[1.0; 3], None).unwrap_err();
        assert!(e.contains("`2um`") && e.contains("non-finite"), "{e}");
    }

    #[test]
    fn pareto_front_and_choice() {
        assert_eq!(
            pareto(&[1.0, 2.0, 3.0, 2.5], &[0.1, 0.05, 0.01, 0.08]),
            [true, true, true, false]
        );
        let values: Vec<String> = ["8um", "4um", "2um", "1um"].map(String::from).to_vec();
        let z: Vec<f64> = [8.0f64, 4.0, 2.0, 1.0]
            .iter()
            .map(|h| 10.0 + 0.01 * h * h)
            .collect();
        let a = analyse(&values, &z, &[1.0, 4.0, 16.0, 64.0], &[1.0; 4], Some(0.002)).unwrap();
        let (p, lim) = a.richardson.unwrap();
        assert!((p - 2.0).abs() < 1e-6 && (lim - 10.0).abs() < 1e-9);
        // Errors 6.4 %, 1.6 %, 0.4 %, 0.1 %: the coarsest below 0.2 % is 1 um.
        assert_eq!(a.chosen, Some(3));
        let a = analyse(&values, &z, &[1.0, 4.0, 16.0, 64.0], &[1.0; 4], Some(0.005)).unwrap();
        assert_eq!(a.chosen, Some(2));
        assert!(a.levels.iter().all(|l| l.pareto));
        assert!(analyse(
            &["1".into(), "3".into(), "2".into()],
            &[1.0; 3],
            &[1.0; 3],
            &[1.0; 3],
            None
        )
        .is_err());
    }
}
