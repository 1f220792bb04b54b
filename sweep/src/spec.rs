//! What a sweep is: the varied parameters (`--vary`), the run list (cartesian product of the
//! values times the realizations), the derived seeds and the manifest `DIR/sweep.json` that
//! every run (local child process or Slurm array task) reads.

use grainpipe_core::engine::{self, PlanOptions};
use grainpipe_core::model::ArtifactKind;
use grainpipe_core::pipeline::{PipelineDoc, PipelineError};
use grainpipe_core::Registry;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Loads the plugins a pipeline names (`plugins:`), given by the `pipe` binary.
pub type PluginLoad<'a> = dyn FnMut(&mut Registry, &PipelineDoc) -> Result<(), PipelineError> + 'a;

/// One varied parameter: `step.key` and its values as YAML text.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Vary {
    pub key: String,
    pub values: Vec<String>,
}

/// Splits at commas outside brackets and braces, so `[1, 2],[3, 4]` is two values.
fn split_top_level(s: &str) -> Vec<String> {
    let (mut depth, mut cur, mut out) = (0i32, String::new(), Vec::new());
    for c in s.chars() {
        match c {
            '[' | '{' => depth += 1,
            ']' | '}' => depth -= 1,
            ',' if depth == 0 => {
                out.push(cur.trim().to_string());
                cur.clear();
                continue;
            }
            _ => {}
        }
        cur.push(c);
    }
    out.push(cur.trim().to_string());
    out
}

/// `a:b:n` with numbers a, b (optionally with the same unit) and an integer n >= 2: n evenly
/// spaced values from a to b.
fn range(s: &str) -> Option<Result<Vec<String>, String>> {
    let parts: Vec<&str> = s.split(':').collect();
    if parts.len() != 3 {
        return None;
    }
    // `0:1:1e3` is as much a count as `0:1:1000`; a count is checked before any value is
    // made (`0:1:1e9` used to allocate a billion strings and abort).
    let n: f64 = parts[2].trim().parse().ok()?;
    if n.fract() != 0.0 || n < 0.0 {
        return Some(Err(format!(
            "range `{s}`: the count `{}` is not a whole number",
            parts[2].trim()
        )));
    }
    if n > MAX_RUNS as f64 {
        return Some(Err(format!(
            "range `{s}`: {n:e} values; a sweep holds at most {MAX_RUNS} runs (split it into several sweeps)"
        )));
    }
    let n = n as usize;
    let split = |t: &str| -> Option<(f64, String)> {
        let t = t.trim();
        let end = t
            .char_indices()
            .find(|(i, c)| {
                !(c.is_ascii_digit()
                    || *c == '.'
                    || *c == '-'
                    || *c == '+'
                    || ((*c == 'e' || *c == 'E')
                        && t[i + 1..].starts_with(|d: char| d.is_ascii_digit() || d == '-')))
            })
            .map(|(i, _)| i)
            .unwrap_or(t.len());
        Some((t[..end].parse().ok()?, t[end..].trim().to_string()))
    };
    let (a, ua) = split(parts[0])?;
    let (b, ub) = split(parts[1])?;
    if ua != ub {
        return Some(Err(format!(
            "range `{s}`: both ends need the same unit (`{ua}` and `{ub}`)"
        )));
    }
    if n < 2 {
        return Some(Err(format!("range `{s}`: give at least 2 values")));
    }
    Some(Ok((0..n)
        .map(|k| {
            let x = a + (b - a) * k as f64 / (n - 1) as f64;
            // Round off the binary noise of the interpolation (0.30000000000000004).
            let x: f64 = format!("{x:.12e}").parse().unwrap_or(x);
            if ua.is_empty() {
                format!("{x}")
            } else {
                format!("{x} {ua}")
            }
        })
        .collect()))
}

/// Parses `--vary step.key=v1,v2,v3` or `--vary step.key=a:b:n`.
pub fn parse_vary(arg: &str) -> Result<Vary, String> {
    let (key, values) = arg
        .split_once('=')
        .ok_or_else(|| format!("--vary `{arg}` is not of the form step.key=v1,v2,..."))?;
    let key = key.trim().to_string();
    if !key.contains('.') {
        return Err(format!(
            "--vary `{arg}`: `{key}` is not of the form step.key"
        ));
    }
    let values = match range(values) {
        Some(r) => r?,
        None => split_top_level(values),
    };
    if values.iter().any(|v| v.is_empty()) {
        return Err(format!("--vary `{arg}`: an empty value"));
    }
    Ok(Vary { key, values })
}

/// One run of the sweep.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunSpec {
    /// `p<point>-r<realization>`, also the folder name under `DIR/runs/`.
    pub id: String,
    pub point: usize,
    pub realization: usize,
    /// The varied values of this point, one per `--vary`, as `step.key=value`.
    pub overrides: Vec<String>,
    /// The pipeline seed of this run (see [`realization_seed`]).
    pub seed: u64,
    /// Preflight memory estimate of the whole run [bytes].
    pub memory_bytes: u64,
}

/// Everything that defines a sweep; stored as `DIR/sweep.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: u32,
    /// Absolute path of the pipeline file.
    pub pipeline: PathBuf,
    /// BLAKE3 of the pipeline file's content: a run refuses to start if the file changed.
    pub pipeline_blake3: String,
    pub pipeline_name: String,
    /// The seed the realization seeds derive from (the pipeline's, or `--seed`).
    pub base_seed: u64,
    /// `--set` overrides applied to every run, before the varied ones.
    pub fixed: Vec<String>,
    pub vary: Vec<Vary>,
    pub realizations: usize,
    /// `--collect` specifications, `step.port[.column]`.
    pub collect: Vec<String>,
    /// Step cache shared by the runs (absolute), or none.
    pub cache_dir: Option<PathBuf>,
    /// Worker threads of each run (`--threads`); results do not depend on it.
    pub threads: Option<usize>,
    /// RVE analysis of the table after collect (`--rve-volume`), if asked for.
    #[serde(default)]
    pub rve: Option<RveSpec>,
    /// The runs write no exports (the levels of `voxel_size: auto` want only the values).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub no_exports: bool,
    pub runs: Vec<RunSpec>,
}

/// The RVE analysis asked for: the table column with each run's cell volume and, optionally,
/// the point variance D_Z^2 of eq. (3.16) for the integral range.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RveSpec {
    pub volume_column: String,
    pub point_variance: Option<f64>,
}

pub const MANIFEST_FORMAT: u32 = 1;

impl Manifest {
    pub fn path(dir: &Path) -> PathBuf {
        dir.join("sweep.json")
    }
    pub fn load(dir: &Path) -> Result<Manifest, String> {
        let p = Manifest::path(dir);
        let text = std::fs::read_to_string(&p).map_err(|e| {
            format!(
                "{}: {e} (is {} a sweep directory?)",
                p.display(),
                dir.display()
            )
        })?;
        serde_json::from_str(&text).map_err(|e| format!("{}: {e}", p.display()))
    }
    pub fn save(&self, dir: &Path) -> Result<(), String> {
        let text = serde_json::to_string_pretty(self).map_err(|e| e.to_string())?;
        grainpipe_core::fsutil::atomic_write_bytes(&Manifest::path(dir), text.as_bytes())
    }
    /// Whether `other` describes the same sweep (runs, seeds, collected values); the cache
    /// directory and thread count may differ between invocations.
    pub fn same_sweep(&self, other: &Manifest) -> bool {
        self.same_points(other) && self.realizations == other.realizations
    }
    /// Whether `other` is this sweep with possibly another number of realizations: the same
    /// pipeline content, seed, `--set`, `--vary` and `--collect`. Realization r has the same
    /// seed in both ([`realization_seed`] depends on r only), so their common runs are the
    /// same runs.
    pub fn same_points(&self, other: &Manifest) -> bool {
        self.pipeline_blake3 == other.pipeline_blake3
            && self.base_seed == other.base_seed
            && self.fixed == other.fixed
            && self.vary == other.vary
            && self.collect == other.collect
    }
    /// This sweep (on disk, `self`) grown to the realizations of `wider` (the same points,
    /// more realizations): every run of `self` keeps its id, so its results are reused, and
    /// the new realizations get ids of `wider`'s width (`p000-r100` beside `p000-r99`). The
    /// run order is `wider`'s (point-major, then realization).
    pub fn extended_to(&self, wider: &Manifest) -> Manifest {
        let mut m = wider.clone();
        for run in &mut m.runs {
            if let Some(old) = self
                .runs
                .iter()
                .find(|o| o.point == run.point && o.realization == run.realization)
            {
                debug_assert_eq!(old.seed, run.seed);
                run.id = old.id.clone();
            }
        }
        m
    }
    pub fn run(&self, id: &str) -> Option<&RunSpec> {
        self.runs.iter().find(|r| r.id == id)
    }
    /// The varied value of `key` at a run.
    pub fn value<'a>(&self, run: &'a RunSpec, k: usize) -> &'a str {
        run.overrides[k]
            .split_once('=')
            .map(|(_, v)| v)
            .unwrap_or("")
    }
}

/// The seed of realization `r`: BLAKE3(base seed, "realization", r) truncated to 63 bits (so it
/// fits the signed integer columns of CSV/HDF5 and `pipe run --seed` reproduces the run). It
/// does not depend on the parameter point: realization r of every point starts from the same
/// random numbers (common random numbers), so differences between points are not blurred by
/// sampling noise.
pub fn realization_seed(base: u64, r: usize) -> u64 {
    let mut label = b"realization".to_vec();
    label.extend_from_slice(&(r as u64).to_le_bytes());
    grainpipe_core::derive_seed(base, &label) >> 1
}

/// The most runs one sweep plans (points x realizations). Every point is preflighted before
/// anything runs (~0.4 ms each) and every run gets a folder, a manifest entry and a table
/// row; beyond this a sweep is better split (Slurm's default MaxArraySize is 1001).
pub const MAX_RUNS: usize = 100_000;

/// The number of runs of a sweep, or why it is refused: checked products, so that
/// `--realizations 1000000000000` is an error with the number instead of an allocation abort.
pub fn run_count(vary: &[Vary], realizations: usize) -> Result<usize, String> {
    let points = vary
        .iter()
        .try_fold(1usize, |acc, v| acc.checked_mul(v.values.len()));
    let total = points.and_then(|p| p.checked_mul(realizations));
    match total {
        Some(n) if n <= MAX_RUNS => Ok(n),
        _ => {
            let points: f64 = vary.iter().map(|v| v.values.len() as f64).product();
            Err(format!(
                "{points} parameter point{} x {realizations} realization{} = {:e} runs; a sweep \
                 holds at most {MAX_RUNS} (split it into several sweeps, or fewer values)",
                if points == 1.0 { "" } else { "s" },
                if realizations == 1 { "" } else { "s" },
                points * realizations as f64,
            ))
        }
    }
}

/// The run list: every combination of the varied values (the last `--vary` fastest) times
/// the realizations.
pub fn runs(vary: &[Vary], realizations: usize, base_seed: u64) -> Vec<RunSpec> {
    let points: usize = vary.iter().map(|v| v.values.len()).product();
    let pw = (points.max(1) - 1).to_string().len().max(3);
    let rw = (realizations.max(1) - 1).to_string().len().max(2);
    let mut out = Vec::with_capacity(points * realizations);
    for p in 0..points {
        let mut rest = p;
        let mut overrides = vec![String::new(); vary.len()];
        for (k, v) in vary.iter().enumerate().rev() {
            overrides[k] = format!("{}={}", v.key, v.values[rest % v.values.len()]);
            rest /= v.values.len();
        }
        for r in 0..realizations {
            out.push(RunSpec {
                id: format!("p{p:0pw$}-r{r:0rw$}"),
                point: p,
                realization: r,
                overrides: overrides.clone(),
                seed: realization_seed(base_seed, r),
                memory_bytes: 0,
            });
        }
    }
    out
}

/// A `--collect` specification: `step.port` or `step.port.column`.
#[derive(Clone, Debug, PartialEq)]
pub struct CollectSpec {
    pub step: String,
    pub port: String,
    pub column: Option<String>,
}

pub fn parse_collect(s: &str) -> Result<CollectSpec, String> {
    let mut it = s.splitn(3, '.');
    match (it.next(), it.next(), it.next()) {
        (Some(st), Some(p), c) if !st.is_empty() && !p.is_empty() => Ok(CollectSpec {
            step: st.into(),
            port: p.into(),
            column: c.map(String::from),
        }),
        _ => Err(format!(
            "--collect `{s}` is not of the form step.port or step.port.column"
        )),
    }
}

/// The document of one run: fixed then varied overrides, the run's seed, exports under
/// `DIR/runs/<id>/`.
pub fn run_doc(m: &Manifest, run: &RunSpec, dir: &Path) -> Result<PipelineDoc, PipelineError> {
    let mut doc = PipelineDoc::load(&m.pipeline)?;
    for o in &m.fixed {
        doc.apply_override(o)?;
    }
    for o in &run.overrides {
        doc.apply_override(o).map_err(|mut e| {
            // The varied keys come from --vary, not --set.
            if e.file == Path::new("--set") {
                e.file = PathBuf::from("--vary");
            }
            e
        })?;
    }
    doc.seed = run.seed;
    if m.no_exports {
        doc.exports.clear();
    }
    doc.redirect_exports(&dir.join("runs").join(&run.id));
    Ok(doc)
}

/// Plans a run document: the collected steps are targets (computed even when nothing exports
/// them), and each `--collect` names a step and output port that exist.
pub fn plan_run(
    doc: &PipelineDoc,
    registry: &Registry,
    collect: &[CollectSpec],
    memory_limit: Option<u64>,
) -> Result<engine::Plan, PipelineError> {
    let cli = |m: String| PipelineError::input(Path::new("--collect"), None, m);
    for c in collect {
        let Some((_, step)) = doc.step(&c.step) else {
            return Err(
                cli(format!("no step `{}` in {}", c.step, doc.file.display())).with_help(
                    grainpipe_core::registry::closest(
                        &c.step,
                        doc.steps.iter().map(|s| s.id.as_str()),
                    )
                    .map(|s| format!("did you mean `{s}`?")),
                ),
            );
        };
        if let Some(reg) = registry.stage(&step.uses) {
            let outs: Vec<&str> = reg.stage.info().outputs.iter().map(|p| p.name).collect();
            if !outs.contains(&c.port.as_str()) {
                return Err(cli(format!(
                    "step `{}` ({}) has no output `{}`",
                    c.step, step.uses, c.port
                ))
                .with_help(Some(
                    grainpipe_core::registry::closest(&c.port, outs.iter().copied())
                        .map(|s| format!("did you mean `{}.{s}`?", c.step))
                        .unwrap_or_else(|| format!("its outputs are: {}", outs.join(", "))),
                )));
            }
            // Only tables and tensors have values to put in the sweep table; refusing an image
            // here, before any run, saves computing every run to fail at the collect.
            let info = reg.stage.info();
            if let Some(port) = info.outputs.iter().find(|p| p.name == c.port) {
                if !matches!(port.kind, ArtifactKind::Table | ArtifactKind::Tensor) {
                    let collectable: Vec<&str> = info
                        .outputs
                        .iter()
                        .filter(|p| matches!(p.kind, ArtifactKind::Table | ArtifactKind::Tensor))
                        .map(|p| p.name)
                        .collect();
                    return Err(cli(format!(
                        "--collect `{}.{}`: a {} has no values to collect (collect a table or a tensor)",
                        c.step, c.port, port.kind
                    ))
                    .with_help(Some(if collectable.is_empty() {
                        format!("step `{}` ({}) outputs no table or tensor", c.step, step.uses)
                    } else {
                        format!(
                            "its tables and tensors: {}",
                            collectable
                                .iter()
                                .map(|p| format!("{}.{p}", c.step))
                                .collect::<Vec<_>>()
                                .join(", ")
                        )
                    })));
                }
            }
        }
    }
    let mut targets: Vec<String> = collect.iter().map(|c| c.step.clone()).collect();
    targets.dedup();
    engine::plan(
        doc,
        registry,
        &PlanOptions {
            targets,
            memory_limit,
        },
    )
}

/// Memory the system can still give, from /proc/meminfo (Linux); `None` elsewhere.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// A pipeline error as text (with its help line).
pub fn error_text(e: &PipelineError) -> String {
    e.to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest(realizations: usize) -> Manifest {
        let vary = vec![parse_vary("pack.volume_fraction=0.2,0.3").unwrap()];
        Manifest {
            format: MANIFEST_FORMAT,
            pipeline: PathBuf::from("/p.yaml"),
            pipeline_blake3: "h".into(),
            pipeline_name: "p".into(),
            base_seed: 5,
            fixed: vec![],
            runs: runs(&vary, realizations, 5),
            vary,
            realizations,
            collect: vec![],
            cache_dir: None,
            threads: None,
            rve: None,
            no_exports: false,
        }
    }

    /// Issue 36: extending 3 realizations to 101 keeps the 6 ids on record (`p000-r02`),
    /// names the new ones at the new width (`p000-r100`), and gives every run the seed and
    /// overrides of a sweep planned with 101 from the start.
    #[test]
    fn extending_a_sweep_keeps_the_runs_on_record() {
        let (old, wide) = (manifest(3), manifest(101));
        assert!(old.same_points(&wide) && !old.same_sweep(&wide));
        let m = old.extended_to(&wide);
        assert_eq!(m.runs.len(), 202);
        for o in &old.runs {
            let r = m
                .runs
                .iter()
                .find(|r| r.id == o.id)
                .expect("an old id is kept");
            assert_eq!(
                (r.point, r.realization, r.seed),
                (o.point, o.realization, o.seed)
            );
            assert_eq!(r.overrides, o.overrides);
        }
        assert_eq!(m.runs[2].id, "p000-r02");
        assert_eq!(m.runs[3].id, "p000-r003");
        assert_eq!(m.runs[100].id, "p000-r100");
        assert_eq!(m.runs[101].id, "p001-r00");
        for (r, w) in m.runs.iter().zip(&wide.runs) {
            assert_eq!(
                (r.point, r.realization, r.seed),
                (w.point, w.realization, w.seed)
            );
        }
        let mut ids: Vec<_> = m.runs.iter().map(|r| &r.id).collect();
        ids.sort();
        ids.dedup();
        assert_eq!(ids.len(), 202, "ids stay unique");
        // Another sweep (another base seed) is not extended.
        let mut other = manifest(101);
        other.base_seed = 6;
        assert!(!old.same_points(&other));
    }

    #[test]
    fn vary_lists_ranges_and_nested_values() {
        let v = parse_vary("pack.volume_fraction=0.2,0.25, 0.3").unwrap();
        assert_eq!(v.values, ["0.2", "0.25", "0.3"]);
        let v = parse_vary("img.binder_fraction=0.02:0.05:4").unwrap();
        assert_eq!(v.values, ["0.02", "0.03", "0.04", "0.05"]);
        let v = parse_vary("b.voxel_size=8um:2um:4").unwrap();
        assert_eq!(v.values, ["8 um", "6 um", "4 um", "2 um"]);
        let v = parse_vary("pack.size=[1, 2],[3, 4]").unwrap();
        assert_eq!(v.values, ["[1, 2]", "[3, 4]"]);
        assert!(parse_vary("volume_fraction=1,2").is_err());
        let v = parse_vary("a.b=0:1:1e1").unwrap();
        assert_eq!(v.values.len(), 10, "a count in exponent form");
        // Refused with the number, before any value is made.
        let e = parse_vary("a.b=0:1:1e9").unwrap_err();
        assert!(e.contains("1e9") && e.contains("100000"), "{e}");
        assert!(parse_vary("a.b=0:1:2.5")
            .unwrap_err()
            .contains("whole number"));
        assert!(parse_vary("a.b=1um:2mm:3")
            .unwrap_err()
            .contains("same unit"));
    }

    #[test]
    fn runs_are_the_product_with_common_random_numbers() {
        let vary = vec![
            parse_vary("a.x=1,2,3").unwrap(),
            parse_vary("b.y=u,v").unwrap(),
        ];
        let r = runs(&vary, 2, 42);
        assert_eq!(r.len(), 12);
        assert_eq!(r[0].overrides, ["a.x=1", "b.y=u"]);
        assert_eq!(r[2].overrides, ["a.x=1", "b.y=v"]);
        assert_eq!(r[11].overrides, ["a.x=3", "b.y=v"]);
        assert_eq!(r[3].id, "p001-r01");
        // Same seed for realization k at every point, different seeds across realizations.
        assert_eq!(r[0].seed, r[2].seed);
        assert_eq!(r[1].seed, r[11].seed);
        assert_ne!(r[0].seed, r[1].seed);
        assert!(r.iter().all(|x| x.seed < 1 << 63));
        assert_eq!(run_count(&vary, 2), Ok(12));
        // The count is checked without overflow or allocation.
        let e = run_count(&vary, 1_000_000_000_000).unwrap_err();
        assert!(e.contains("6e12 runs") && e.contains("100000"), "{e}");
        let e = run_count(&vary, usize::MAX).unwrap_err();
        assert!(e.contains("runs"), "{e}");
        assert_ne!(realization_seed(43, 0), realization_seed(42, 0));
    }
}
