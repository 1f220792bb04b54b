//! `voxel_size: auto`: the runner picks an image maker's resolution before the real run.
//!
//! The step's cheap levels (`auto_levels`, voxels per mean grain diameter) run as a
//! `pipe study` does: a one-realization sweep of child processes up to the steps of the
//! `auto_quantities` (no exports), here with the pipeline's own seed so the levels see the
//! microstructure of the run they decide for. Each quantity is extrapolated (Richardson:
//! the order observed from the three finest levels, [`richardson`], capped at the formal
//! order `auto_order`; with two levels that order assumed, [`richardson_assumed`]); the
//! estimated error of a level is Roache's safety factor (1.25 observed, 3 assumed) times its
//! distance to the extrapolation, which gives the error model e(n) = e_f (n_f / n)^p of a
//! run at n voxels per diameter from the finest level's estimate e_f. The chosen resolution
//! is the coarsest n with e(n) <= target_error for every quantity, never at or below a level
//! that misses the target by its own estimate. A choice whose run does not fit in memory,
//! or levels that do not converge monotonically, fail loudly: there is no silent fallback.
//!
//! The core only declares the parameters ([`grainpipe_core::resolution`]); a stage opts in
//! by flattening [`AutoVoxel`] beside its `voxel_size` and `voxels_per_diameter`.

use crate::runner::{self, Launcher, LocalOptions};
use crate::spec::{self, CollectSpec, PluginLoad};
use crate::study::{richardson, richardson_assumed};
use crate::{prepare, SetupArgs};
use grainpipe_core::engine::{self, human_bytes};
use grainpipe_core::params::Params;
use grainpipe_core::pipeline::{PipelineDoc, PipelineError};
use grainpipe_core::resolution::{AutoVoxel, AUTO, LEVEL_KEY, SIZE_KEY};
use grainpipe_core::Registry;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// The step whose voxel size is `auto`, with its settings.
#[derive(Clone, Debug)]
pub struct AutoStep {
    pub step: String,
    pub stage: String,
    pub settings: AutoVoxel,
}

impl AutoStep {
    /// The overrides that run this step at `n` voxels per diameter.
    pub fn overrides(&self, n: f64) -> Vec<String> {
        vec![
            format!("{}.{SIZE_KEY}=0", self.step),
            format!("{}.{LEVEL_KEY}={}", self.step, fmt_level(n)),
        ]
    }
}

/// A level as text: the shortest decimal that reads back as `n`.
fn fmt_level(n: f64) -> String {
    format!("{n}")
}

/// Rounds a voxel count per diameter up to three significant digits, so the choice reads
/// (and reproduces with `--set`) cleanly and never gets coarser than predicted.
pub fn round_up_3(n: f64) -> f64 {
    if !(n.is_finite() && n > 0.0) {
        return n;
    }
    let scale = 10f64.powi(2 - n.log10().floor() as i32);
    let r = (n * scale - 1e-9).ceil() / scale;
    // Back through text so the value is the decimal it prints as.
    format!("{r:.6}").parse().unwrap_or(r)
}

/// Finds the step with `voxel_size: auto` and checks its settings; errors point at the key.
/// `None` when no step asks for it.
pub fn find(doc: &PipelineDoc, registry: &Registry) -> Result<Option<AutoStep>, PipelineError> {
    let mut found: Option<AutoStep> = None;
    for step in &doc.steps {
        let is_auto = step
            .params
            .get(SIZE_KEY)
            .and_then(|v| v.as_str())
            .is_some_and(|s| s.trim() == AUTO);
        if !is_auto {
            continue;
        }
        let at = |key: &str| step.param_locs.get(key).copied();
        let err = |key: &str, m: String| PipelineError::input(&doc.file, at(key), m);
        let Some(reg) = registry.stage(&step.uses) else {
            // An unknown stage: the planner reports it with a suggestion.
            continue;
        };
        let defaults = reg.stage.default_params();
        if defaults.get("target_error").is_none() || defaults.get(LEVEL_KEY).is_none() {
            return Err(err(
                SIZE_KEY,
                format!(
                    "step `{}`: {} does not choose its voxel size automatically; give a length",
                    step.id, step.uses
                ),
            )
            .with_help(Some(
                "voxel_size: auto is for the image makers (voxelize.packing, binder.levelset, \
                 binder.closing)"
                    .into(),
            )));
        }
        if let Some(first) = &found {
            return Err(err(
                SIZE_KEY,
                format!(
                    "step `{}`: only one step may have voxel_size: auto (`{}` has it too)",
                    step.id, first.step
                ),
            ));
        }
        let given = serde_json::Value::Object(step.params.clone());
        for key in [
            "target_error",
            "auto_quantities",
            "auto_levels",
            "auto_order",
        ] {
            if let Some(v) = step.params.get(key) {
                if let Some(Err((path, m))) = AutoVoxel::check_value(key, v) {
                    return Err(err(key, format!("step `{}`, `{path}`: {m}", step.id)));
                }
            }
        }
        let settings: AutoVoxel = serde_json::from_value(given)
            .map_err(|e| err(SIZE_KEY, format!("step `{}`: {e}", step.id)))?;
        settings
            .check(&grainpipe_core::resolution::VoxelSize::Auto)
            .map_err(|(k, m)| err(&k, format!("step `{}`, `{k}`: {m}", step.id)))?;
        found = Some(AutoStep {
            step: step.id.clone(),
            stage: step.uses.clone(),
            settings,
        });
    }
    Ok(found)
}

/// The quantities as `--collect` specifications; errors point at `auto_quantities`.
fn quantity_specs(doc: &PipelineDoc, a: &AutoStep) -> Result<Vec<CollectSpec>, PipelineError> {
    a.settings
        .auto_quantities
        .iter()
        .map(|q| {
            spec::parse_collect(q).map_err(|m| {
                PipelineError::input(&doc.file, quantity_loc(doc, a), m.replace("--collect", ""))
            })
        })
        .collect()
}

fn quantity_loc(doc: &PipelineDoc, a: &AutoStep) -> Option<grainpipe_core::pipeline::Loc> {
    doc.step(&a.step)
        .and_then(|(_, s)| s.param_locs.get("auto_quantities").copied())
}

/// A plan error about the quantities (reported against `--collect` by the sweep code) moved
/// onto the `auto_quantities` key of the file.
fn at_quantities(doc: &PipelineDoc, a: &AutoStep, mut e: PipelineError) -> PipelineError {
    if e.file == Path::new("--collect") {
        e.file = doc.file.clone();
        e.loc = quantity_loc(doc, a);
        e.message = format!("step `{}`, `auto_quantities`: {}", a.step, e.message);
    }
    e
}

/// Plans `doc` (overrides applied) with the step at `n` voxels per diameter, computing only
/// what the quantities need.
pub fn plan_level(
    doc: &PipelineDoc,
    a: &AutoStep,
    n: f64,
    registry: &Registry,
    memory_limit: Option<u64>,
) -> Result<engine::Plan, PipelineError> {
    let mut d = doc.clone();
    for o in a.overrides(n) {
        d.apply_override(&o)?;
    }
    d.exports.clear();
    let specs = quantity_specs(doc, a)?;
    spec::plan_run(&d, registry, &specs, memory_limit).map_err(|e| at_quantities(doc, a, e))
}

/// What `pipe validate` says about an auto step (after checking every level plans).
pub fn explain(
    doc: &PipelineDoc,
    a: &AutoStep,
    registry: &Registry,
) -> Result<String, PipelineError> {
    let s = &a.settings;
    let mut finest_memory = 0;
    for &n in &s.auto_levels {
        finest_memory = plan_level(doc, a, n, registry, engine::available_memory())?.memory_bytes;
    }
    let order = if s.auto_levels.len() >= 3 {
        format!(
            "the order observed from the three finest levels, at most {}; safety factor 1.25",
            s.auto_order
        )
    } else {
        format!(
            "an assumed order {} (two levels); safety factor 3",
            s.auto_order
        )
    };
    Ok(format!(
        "{}.voxel_size: auto: first runs the levels {} voxels per diameter up to {} (finest \
         ~{}), extrapolates each value (Richardson, {order}), then runs the pipeline at the \
         coarsest voxel predicted to keep every error below {} %",
        a.step,
        s.auto_levels
            .iter()
            .map(|&n| fmt_level(n))
            .collect::<Vec<_>>()
            .join(", "),
        s.auto_quantities.join(", "),
        human_bytes(finest_memory),
        100.0 * s.target_error
    ))
}

/// One quantity's analysis.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct QuantityEstimate {
    pub name: String,
    /// The value at each level.
    pub values: Vec<f64>,
    /// Order of convergence used: the observed one (three or more levels converging
    /// monotonically) capped at `auto_order`, or `auto_order` assumed (two levels).
    pub order: f64,
    /// The observed order (`None` with two levels).
    pub observed_order: Option<f64>,
    pub order_basis: &'static str,
    /// Safety factor on the error estimates (1.25 observed, 3 assumed; Roache's GCI).
    pub safety_factor: f64,
    /// Richardson extrapolation.
    pub extrapolated: f64,
    /// Estimated relative error of each level: safety factor x |value - extrapolated| /
    /// |extrapolated|.
    pub errors: Vec<f64>,
    /// The voxel count per diameter this quantity needs for the target.
    pub needed: f64,
    /// Predicted relative error at the chosen resolution.
    pub predicted_error: f64,
}

/// The decision, as recorded in run.json (`auto_voxel`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Choice {
    pub step: String,
    pub target_error: f64,
    /// The levels run, in voxels per mean diameter.
    pub levels: Vec<f64>,
    pub level_wall_time_s: Vec<f64>,
    pub level_peak_memory_bytes: Vec<f64>,
    pub quantities: Vec<QuantityEstimate>,
    /// The chosen voxels per mean diameter.
    pub voxels_per_diameter: f64,
    /// The chosen voxel edge [m] when the plan knows it (a packing with an exact mean
    /// diameter), else `None`: it is then the mean diameter / voxels_per_diameter of the run.
    pub voxel_size: Option<f64>,
    /// Preflight memory estimate of the chosen run [bytes].
    pub memory_bytes: u64,
    /// The overrides that reproduce the run with `pipe run --set`.
    pub overrides: Vec<String>,
    /// Where the levels ran.
    pub levels_dir: PathBuf,
}

/// Analyses the levels (voxels per diameter `n`, values `z` of one quantity) for a target:
/// the extrapolation, each level's error, and the resolution this quantity needs. Errors
/// say why no estimate is possible.
pub fn estimate(
    name: &str,
    n: &[f64],
    z: &[f64],
    target: f64,
    formal_order: f64,
) -> Result<QuantityEstimate, String> {
    let h: Vec<f64> = n.iter().map(|v| 1.0 / v).collect();
    let list = || {
        n.iter()
            .zip(z)
            .map(|(n, z)| format!("{} -> {z:.6e}", fmt_level(*n)))
            .collect::<Vec<_>>()
            .join(", ")
    };
    if let Some(k) = z.iter().position(|v| !v.is_finite()) {
        return Err(format!(
            "`{name}` is not finite at {} voxels per diameter",
            fmt_level(n[k])
        ));
    }
    // The order used: the observed one, but never above the formal order `formal_order`
    // (p = min(p_observed, p_formal), Celik et al., J. Fluids Eng. 130 (2008) 078001): an
    // observed order above the formal one means pre-asymptotic coarse levels, which would
    // extrapolate too close to the finest level and underestimate its error. With two levels
    // the formal order is assumed.
    let (observed, order, basis) = if n.len() >= 3 {
        let (p, _) = richardson(&h, z).ok_or_else(|| {
            format!(
                "`{name}` does not converge monotonically over the levels ({}), or its \
                 observed order is outside 0.25..8: no error estimate; give finer \
                 auto_levels (or a voxel_size)",
                list()
            )
        })?;
        if p > formal_order {
            (
                Some(p),
                formal_order,
                "observed above the formal order, capped",
            )
        } else {
            (Some(p), p, "observed")
        }
    } else {
        (None, formal_order, "assumed")
    };
    let zs = richardson_assumed(&h, z, order)
        .ok_or_else(|| format!("`{name}`: two distinct levels are needed ({})", list()))?;
    if zs == 0.0 || !zs.is_finite() {
        return Err(format!(
            "`{name}` extrapolates to {zs}: a relative error is undefined ({})",
            list()
        ));
    }
    // Roache's safety factor of the grid convergence index (Roache, J. Fluids Eng. 116 (1994)
    // 405-413): 1.25 with an observed order (three levels or more), 3 with an assumed one.
    let safety = if observed.is_some() { 1.25 } else { 3.0 };
    let errors: Vec<f64> = z
        .iter()
        .map(|v| safety * (v - zs).abs() / zs.abs())
        .collect();
    let k = n.len() - 1;
    let (nf, ef) = (n[k], errors[k]);
    // e(n) = e_f (n_f / n)^p  =>  n = n_f (e_f / target)^(1/p).
    let model = nf * (ef / target).powf(1.0 / order);
    let needed = if ef > target {
        model
    } else {
        // The coarsest level from which on every run level meets the target by its own
        // estimate. The model may choose between it and the next coarser level (which
        // misses the target), but not at or below that one: the model is asymptotic, the
        // coarse levels may not be.
        let mut first = k;
        while first > 0 && errors[first - 1] <= target {
            first -= 1;
        }
        match first {
            0 => model.max(n[0]).min(nf),
            _ if model > n[first - 1] => model.min(n[first]),
            _ => n[first],
        }
    };
    Ok(QuantityEstimate {
        name: name.to_string(),
        values: z.to_vec(),
        order,
        observed_order: observed,
        order_basis: basis,
        safety_factor: safety,
        extrapolated: zs,
        errors,
        needed,
        predicted_error: f64::NAN,
    })
}

/// Why resolving failed: an error about the file (exit 2, shown with its location), or a
/// failure already printed (levels that failed), with its exit code.
pub enum Failure {
    Pipeline(PipelineError),
    Printed(ExitCode),
}

impl From<PipelineError> for Failure {
    fn from(e: PipelineError) -> Self {
        Failure::Pipeline(e)
    }
}

/// Where the levels of an auto run go: `<parent>/auto-<step>-<hash>`, the hash over the
/// pipeline text, the overrides and the seed, so a changed pipeline never meets the levels
/// of another one, and the same YAML and seed reuse theirs.
pub fn levels_dir(parent: &Path, doc: &PipelineDoc, overrides: &[String], step: &str) -> PathBuf {
    let mut h = blake3::Hasher::new();
    h.update(doc.source.as_bytes());
    for o in overrides {
        h.update(b"\0");
        h.update(o.as_bytes());
    }
    h.update(&doc.seed.to_le_bytes());
    let hex = h.finalize().to_hex();
    parent.join(format!("auto-{step}-{}", &hex[..12]))
}

/// Settings of a resolution run.
pub struct Request<'a> {
    /// The pipeline file (levels read it, as sweep runs do).
    pub file: &'a Path,
    /// `--set` overrides of the run.
    pub overrides: &'a [String],
    /// The run's seed (the file's or `--seed`).
    pub seed: u64,
    pub levels_dir: PathBuf,
    pub cache_dir: Option<PathBuf>,
    pub threads: Option<usize>,
    pub quiet: bool,
    /// Memory the chosen run may use [bytes] (the available memory).
    pub memory_limit: Option<u64>,
}

/// Runs the levels, analyses them and picks the resolution (printing a table unless quiet).
/// `doc` is the pipeline with the request's overrides and seed applied.
pub fn resolve(
    doc: &PipelineDoc,
    a: &AutoStep,
    req: &Request,
    registry: &mut Registry,
    load_plugins: &mut PluginLoad,
    launch: &Launcher,
) -> Result<Choice, Failure> {
    let s = &a.settings;
    // Every level plans before any runs (quantities, wiring, memory).
    for &n in &s.auto_levels {
        plan_level(doc, a, n, registry, req.memory_limit)?;
    }
    let mut fixed = req.overrides.to_vec();
    fixed.push(format!("{}.{SIZE_KEY}=0", a.step));
    let setup = SetupArgs {
        file: Some(req.file.to_path_buf()),
        vary: vec![format!(
            "{}.{LEVEL_KEY}={}",
            a.step,
            s.auto_levels
                .iter()
                .map(|&n| fmt_level(n))
                .collect::<Vec<_>>()
                .join(",")
        )],
        realizations: 1,
        collect: s.auto_quantities.clone(),
        overrides: fixed,
        seed: Some(req.seed),
        out: Some(req.levels_dir.clone()),
        jobs: Some(1),
        threads: req.threads,
        cache_dir: req
            .cache_dir
            .clone()
            .unwrap_or_else(|| PathBuf::from(".grainpipe-cache")),
        no_cache: req.cache_dir.is_none(),
        quiet: true,
        seed_as_is: true,
        no_exports: true,
        ..Default::default()
    };
    if !req.quiet {
        eprintln!(
            "{}.voxel_size: auto: levels {} voxels per diameter -> {}",
            a.step,
            s.auto_levels
                .iter()
                .map(|&n| fmt_level(n))
                .collect::<Vec<_>>()
                .join(", "),
            req.levels_dir.display()
        );
    }
    let p = prepare(&setup, registry, load_plugins).map_err(Failure::Printed)?;
    // One level at a time: each uses every core (coarse levels are cheap; the finest is
    // 8x the cost of the one before when levels double).
    let opts = LocalOptions {
        jobs: 1,
        memory_budget: None,
        stop_after: None,
        quiet: true,
    };
    if !p.todo.is_empty() {
        runner::run_local(&p.dir, &p.manifest, &p.todo, &opts, launch);
    }
    // The levels' table (sweep.csv) for inspection; the decision does not depend on it.
    if let Err(e) = crate::table::write_tables(&p.dir, &p.manifest) {
        eprintln!("warning: levels table not written: {e}");
    }
    let mut results = Vec::new();
    for (k, r) in p.manifest.runs.iter().enumerate() {
        let n = s.auto_levels[k];
        match runner::load_result(&p.dir, &r.id) {
            Some(res) if res.status == "ok" => results.push(res),
            Some(res) => {
                return Err(Failure::Pipeline(PipelineError::run(
                    &doc.file,
                    None,
                    format!(
                        "voxel_size: auto: the level at {} voxels per diameter failed: {}",
                        fmt_level(n),
                        res.error
                    ),
                )))
            }
            None => {
                return Err(Failure::Pipeline(PipelineError::run(
                    &doc.file,
                    None,
                    format!(
                        "voxel_size: auto: the level at {} voxels per diameter left no result \
                         (see {})",
                        fmt_level(n),
                        runner::run_dir(&p.dir, &r.id).join("log.txt").display()
                    ),
                )))
            }
        }
    }
    let specs = quantity_specs(doc, a)?;
    let mut quantities = Vec::new();
    for (q, c) in s.auto_quantities.iter().zip(&specs) {
        let indexed = c
            .column
            .as_ref()
            .map(|col| format!("{}.{}[{col}]", c.step, c.port));
        let mut z = Vec::new();
        for r in &results {
            let hits: Vec<&runner::Value> = r
                .values
                .iter()
                .filter(|v| v.name == *q || Some(&v.name) == indexed.as_ref())
                .collect();
            let v = match hits.as_slice() {
                [one] => one.value.unwrap_or(f64::NAN),
                [] => {
                    let many = r
                        .values
                        .iter()
                        .filter(|v| v.name.starts_with(&format!("{q}[")))
                        .count();
                    return Err(Failure::Pipeline(PipelineError::input(
                        &doc.file,
                        quantity_loc(doc, a),
                        if many > 0 {
                            format!(
                                "auto_quantities: `{q}` has {many} values (a table of several \
                                 rows); name one quantity"
                            )
                        } else {
                            format!("auto_quantities: the levels gave no value `{q}`")
                        },
                    )));
                }
                _ => unreachable!("one name per collected value"),
            };
            z.push(v);
        }
        let e = estimate(q, &s.auto_levels, &z, s.target_error, s.auto_order).map_err(|m| {
            PipelineError::run(
                &doc.file,
                quantity_loc(doc, a),
                format!("voxel_size: auto: {m}"),
            )
        })?;
        quantities.push(e);
    }
    let chosen = round_up_3(quantities.iter().map(|q| q.needed).fold(0.0, f64::max));
    for q in &mut quantities {
        let k = q.errors.len() - 1;
        let nf = *s.auto_levels.last().expect("levels");
        q.predicted_error = q.errors[k] * (nf / chosen).powf(q.order);
    }
    let (wall, mem): (Vec<f64>, Vec<f64>) = results
        .iter()
        .map(|r| (r.wall_time, r.peak_memory as f64))
        .unzip();
    let nf = *s.auto_levels.last().expect("levels");
    let finest_estimate = p.manifest.runs.last().map_or(0, |r| r.memory_bytes);
    // The memory a run at `chosen` needs, from the finest level's preflight estimate: the
    // image arrays scale with the voxel count, (n / n_f)^3.
    let scaled = finest_estimate as f64 * (chosen / nf).max(1.0).powi(3);
    let needs = |what: String| {
        let worst = quantities
            .iter()
            .max_by(|x, y| x.needed.total_cmp(&y.needed))
            .expect("a quantity");
        PipelineError::input(
            &doc.file,
            doc.step(&a.step)
                .and_then(|(_, st)| st.param_locs.get("target_error").copied()),
            format!(
                "voxel_size: auto: target_error {} on `{}` needs {} voxels per diameter \
                 (its error at {} is {:.3} %, order {:.2} {}), {what}",
                s.target_error,
                worst.name,
                fmt_level(chosen),
                fmt_level(nf),
                100.0 * worst.errors[worst.errors.len() - 1],
                worst.order,
                worst.order_basis
            ),
        )
        .with_help(Some(
            "raise target_error, give a coarser voxel_size by hand, or run where more memory \
             is available"
                .into(),
        ))
    };
    if let Some(limit) = req.memory_limit {
        if scaled > limit as f64 {
            return Err(needs(format!(
                "a run of about {} of memory (the finest level's {} x ({} / {})^3), but {} \
                 is available",
                human_bytes(scaled as u64),
                human_bytes(finest_estimate),
                fmt_level(chosen),
                fmt_level(nf),
                human_bytes(limit)
            ))
            .into());
        }
    }
    let mut run_doc = doc.clone();
    for o in a.overrides(chosen) {
        run_doc.apply_override(&o)?;
    }
    let plan = engine::plan(
        &run_doc,
        registry,
        &engine::PlanOptions {
            targets: Vec::new(),
            memory_limit: req.memory_limit,
        },
    )
    .map_err(|e| {
        needs(format!(
            "and at that resolution the pipeline is refused (about {} of memory by the \
             finest level's estimate): {}",
            human_bytes(scaled as u64),
            e.message
        ))
    })?;
    let voxel_size = doc
        .steps
        .iter()
        .position(|st| st.id == a.step)
        .and_then(|i| {
            plan.steps[i].as_ref().and_then(|ps| {
                ps.preflight
                    .outputs
                    .values()
                    .find_map(|m| m.grid.as_ref().map(|g| g.spacing[0]))
            })
        });
    let choice = Choice {
        step: a.step.clone(),
        target_error: s.target_error,
        levels: s.auto_levels.clone(),
        level_wall_time_s: wall,
        level_peak_memory_bytes: mem,
        quantities,
        voxels_per_diameter: chosen,
        voxel_size,
        memory_bytes: plan.memory_bytes,
        overrides: a.overrides(chosen),
        levels_dir: p.dir.clone(),
    };
    if !req.quiet {
        eprint!("{}", summary(&choice));
    }
    Ok(choice)
}

/// The levels and the decision as text.
pub fn summary(c: &Choice) -> String {
    let mut out = String::new();
    for q in &c.quantities {
        out += &format!("  {}:\n", q.name);
        for (k, n) in c.levels.iter().enumerate() {
            out += &format!(
                "    {:>8} voxels/diameter  {:>14.6e}  est. error {:>7.3} %  {:>7.2} s\n",
                fmt_level(*n),
                q.values[k],
                100.0 * q.errors[k],
                c.level_wall_time_s[k]
            );
        }
        let observed = q
            .observed_order
            .map(|o| format!(", observed {o:.2}"))
            .unwrap_or_default();
        out += &format!(
            "    extrapolated {:.6e}, order {:.2} ({}{observed}), safety factor {}, needs {:.3} voxels/diameter\n",
            q.extrapolated, q.order, q.order_basis, q.safety_factor, q.needed
        );
    }
    let voxel = c
        .voxel_size
        .map(|v| format!(" (voxel {:.4} um)", v * 1e6))
        .unwrap_or_default();
    out += &format!(
        "{}.voxel_size: auto -> {} voxels per diameter{voxel}, predicted error {} (target {} %), ~{}\n",
        c.step,
        fmt_level(c.voxels_per_diameter),
        c.quantities
            .iter()
            .map(|q| format!("{} {:.2} %", q.name, 100.0 * q.predicted_error))
            .collect::<Vec<_>>()
            .join(", "),
        100.0 * c.target_error,
        human_bytes(c.memory_bytes)
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_up_to_three_digits() {
        assert_eq!(round_up_3(17.31), 17.4);
        assert_eq!(round_up_3(17.3), 17.3);
        assert_eq!(round_up_3(6.0), 6.0);
        assert_eq!(round_up_3(123.4), 124.0);
        assert_eq!(round_up_3(0.01234), 0.0124);
    }

    /// On an exact power law z = z* (1 + c n^-p) the estimate recovers z*, p and the
    /// resolution that meets the target: e(n) = c n^-p = target <=> n = (c / target)^(1/p).
    #[test]
    fn estimate_on_a_known_sequence() {
        let (zs, c, p) = (3.0, 2.0, 1.5);
        let n = [6.0, 12.0, 24.0];
        let z: Vec<f64> = n
            .iter()
            .map(|n: &f64| zs * (1.0 + c * n.powf(-p)))
            .collect();
        // Formal order 2 >= the observed 1.5: the observed order is used, with the safety
        // factor 1.25: the estimated error is 1.25 c n^-p, so n = (1.25 c / target)^(1/p).
        let fs = 1.25;
        let e = estimate("q", &n, &z, 0.01, 2.0).unwrap();
        assert!((e.order - p).abs() < 1e-6 && e.order_basis == "observed");
        assert_eq!(e.safety_factor, fs);
        assert!((e.extrapolated - zs).abs() < 1e-9);
        let exact = (fs * c / 0.01f64).powf(1.0 / p);
        assert!(
            (e.needed - exact).abs() / exact < 1e-6,
            "{} vs {exact}",
            e.needed
        );
        // A target the middle level meets: the choice lies between the levels, never below
        // the coarsest level whose error (and every finer one's) meets it.
        let t = 1.2 * fs * c * 12f64.powf(-p);
        let e = estimate("q", &n, &z, t, 2.0).unwrap();
        let exact = (fs * c / t).powf(1.0 / p);
        assert!(exact > 6.0 && exact < 12.0);
        assert!((e.needed - exact).abs() / exact < 1e-6);
        // A target only the finest level meets: the model's 18 lies between 12 (which
        // misses it) and 24.
        let t = fs * c * 18f64.powf(-p);
        let e = estimate("q", &n, &z, t, 2.0).unwrap();
        assert!((e.needed - 18.0).abs() < 1e-6, "{}", e.needed);
        // Formal order 1 below the observed 1.5: capped at 1, which extrapolates past the
        // limit (z* = z3 - (z2 - z3)) and asks for a finer voxel than the true order would.
        let e = estimate("q", &n, &z, 0.01, 1.0).unwrap();
        assert_eq!(e.order, 1.0);
        assert_eq!(e.observed_order.map(|o| (o - p).abs() < 1e-6), Some(true));
        assert!(e.order_basis.contains("capped"));
        assert!((e.extrapolated - (2.0 * z[2] - z[1])).abs() < 1e-12);
        assert!(e.needed > (fs * c / 0.01f64).powf(1.0 / p));
        // Two levels with the true order assumed: the same limit, safety factor 3.
        let e2 = estimate("q", &n[1..], &z[1..], 0.01, p).unwrap();
        assert_eq!(e2.order_basis, "assumed");
        assert_eq!(e2.safety_factor, 3.0);
        assert!((e2.extrapolated - zs).abs() < 1e-9);
        let exact = (3.0 * c / 0.01f64).powf(1.0 / p);
        assert!((e2.needed - exact).abs() / exact < 1e-6);
        // Oscillating values: refused loudly, naming the values.
        let err = estimate("q", &n, &[1.0, 1.2, 1.1], 0.01, 1.0).unwrap_err();
        assert!(
            err.contains("monotonically") && err.contains("12 ->"),
            "{err}"
        );
    }
}
