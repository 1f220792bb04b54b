//! The run directory: `run.json` (what ran, how long, how much memory, what was written,
//! how it ended) and `report-data/` (what the report shows, drawn from the in-memory
//! results), written by `pipe run` so `pipe report DIR` can render the page at any time.

use crate::data::{self, ReportData};
use grainpipe_core::engine::{Plan, RunResult};
use grainpipe_core::fsutil::{atomic_write, atomic_write_bytes};
use grainpipe_core::pipeline::PipelineDoc;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub const RUN_FILE: &str = "run.json";
pub const DATA_DIR: &str = "report-data";
pub const DATA_FILE: &str = "data.json";
pub const REPORT_FILE: &str = "report.html";

/// One executed step.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StepRecord {
    pub step: String,
    pub stage: String,
    pub wall_s: f64,
    pub from_cache: bool,
    /// Peak heap growth during the step over what was live when it started [bytes].
    pub peak_bytes: Option<u64>,
    /// Peak live heap of the process during the step [bytes].
    pub peak_heap_bytes: Option<u64>,
    /// The step's preflight memory estimate, exports of its outputs included (what `pipe
    /// validate` sums and Slurm's `--mem` is sized from), to compare with `peak_bytes`
    /// [bytes] (absent in records written before it was recorded).
    #[serde(default)]
    pub estimate_bytes: Option<u64>,
}

/// Provenance of one planned step.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StepProvenance {
    pub step: String,
    pub stage: String,
    pub stage_version: String,
    pub origin: String,
    pub seed: u64,
    pub cache_key: String,
    pub params: serde_json::Value,
    pub inputs: Vec<(String, String)>,
    pub input_files: Vec<(String, String)>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ExportRecord {
    pub from: String,
    pub path: String,
    pub format: String,
    pub written: bool,
}

/// `run.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunRecord {
    pub grainpipe_version: String,
    pub pipeline_file: String,
    pub pipeline_name: String,
    pub description: String,
    pub seed: u64,
    /// `--set` overrides given on the command line.
    pub overrides: Vec<String>,
    /// The pipeline as run (overrides applied, exports redirected), as YAML.
    pub effective_yaml: String,
    /// The pipeline file as written.
    pub source_yaml: String,
    /// Seconds since the Unix epoch when the run started.
    pub started_unix_s: f64,
    pub wall_s: f64,
    /// "ok" or "failed".
    pub status: String,
    pub error: Option<String>,
    pub steps: Vec<StepRecord>,
    pub exports: Vec<ExportRecord>,
    pub provenance: Vec<StepProvenance>,
    pub host: String,
    pub threads: usize,
    /// Every warning the stages gave, in order (absent in records written before it was
    /// recorded).
    #[serde(default)]
    pub warnings: Vec<WarningRecord>,
    /// The pipeline's `reference:` values against this run's results (absent when the
    /// pipeline declares none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference: Option<ReferenceRecord>,
    /// `voxel_size: auto`: the levels run, the estimates, the order and the choice.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auto_voxel: Option<serde_json::Value>,
}

/// A pipeline's `reference:` block as compared with the run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReferenceRecord {
    pub source: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
    pub rows: Vec<grainpipe_core::values::Comparison>,
}

impl ReferenceRecord {
    /// The comparison of `doc`'s reference block with a run's results (every row missing
    /// for a failed run, `None`).
    pub fn of(doc: &PipelineDoc, result: Option<&RunResult>) -> Option<Self> {
        let r = doc.reference.as_ref()?;
        let empty = indexmap::IndexMap::new();
        let outputs = result.map_or(&empty, |r| &r.outputs);
        Some(ReferenceRecord {
            source: r.source.clone(),
            note: r.note.clone(),
            rows: grainpipe_core::values::compare(r, outputs),
        })
    }
}

/// One warning of a run: the step that gave it and its text.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WarningRecord {
    pub step: String,
    pub text: String,
}

/// What `pipe run` knows when a run ends.
pub struct RunEnd<'a> {
    pub doc: &'a PipelineDoc,
    pub plan: &'a Plan,
    pub overrides: &'a [String],
    pub steps: Vec<StepRecord>,
    pub started: std::time::SystemTime,
    pub wall_s: f64,
    /// The results, or the error message of a failed run.
    pub result: Result<&'a RunResult, String>,
    /// Paths the run wrote.
    pub written: Vec<PathBuf>,
    /// The warnings the steps gave, as (step, text).
    pub warnings: Vec<(String, String)>,
    /// The `voxel_size: auto` decision, when the run had one.
    pub auto_voxel: Option<serde_json::Value>,
    /// The `reference:` comparison ([`ReferenceRecord::of`]), computed once by the caller,
    /// which also prints it.
    pub reference: Option<ReferenceRecord>,
}

/// The run directory of a pipeline run without `--out`: the deepest directory containing
/// every export (out/sandcore/ for sandcore); `None` when that is the working directory or
/// there are no exports (a record there would litter the working directory).
pub fn default_run_dir(doc: &PipelineDoc) -> Option<PathBuf> {
    let mut common: Option<PathBuf> = None;
    for e in &doc.exports {
        let parent = e.to.parent().unwrap_or(Path::new("")).to_path_buf();
        common = Some(match common {
            None => parent,
            Some(c) => {
                let mut out = PathBuf::new();
                for (a, b) in c.components().zip(parent.components()) {
                    if a != b {
                        break;
                    }
                    out.push(a);
                }
                out
            }
        });
    }
    common.filter(|c| !c.as_os_str().is_empty() && c != Path::new("."))
}

/// The pipeline as a plain mapping in the YAML layout of pipeline files.
fn effective(doc: &PipelineDoc) -> serde_json::Value {
    use serde_json::{json, Map, Value};
    let stages: Vec<Value> = doc
        .steps
        .iter()
        .map(|s| {
            let mut m = Map::new();
            m.insert("id".into(), s.id.clone().into());
            m.insert("use".into(), s.uses.clone().into());
            if !s.inputs.is_empty() {
                let ins: Map<String, Value> = s
                    .inputs
                    .iter()
                    .map(|(k, v)| {
                        let r = match &v.source.port {
                            Some(p) => format!("{}.{p}", v.source.step),
                            None => v.source.step.clone(),
                        };
                        (k.clone(), r.into())
                    })
                    .collect();
                m.insert("in".into(), Value::Object(ins));
            }
            if !s.params.is_empty() {
                m.insert("with".into(), Value::Object(s.params.clone()));
            }
            Value::Object(m)
        })
        .collect();
    let exports: Vec<Value> = doc
        .exports
        .iter()
        .map(|e| {
            let from = match &e.from.port {
                Some(p) => format!("{}.{p}", e.from.step),
                None => e.from.step.clone(),
            };
            let mut m = Map::new();
            m.insert("from".into(), from.into());
            m.insert("to".into(), e.to.display().to_string().into());
            if let Some(f) = &e.format {
                m.insert("format".into(), f.clone().into());
            }
            Value::Object(m)
        })
        .collect();
    json!({
        "name": doc.name,
        "description": doc.description,
        "seed": doc.seed,
        "stages": stages,
        "export": exports,
    })
}

fn effective_yaml(doc: &PipelineDoc) -> String {
    let v = effective(doc);
    serde_saphyr::to_string(&v).unwrap_or_else(|_| {
        // JSON is YAML too; the fallback keeps the record complete.
        serde_json::to_string_pretty(&v).unwrap_or_default()
    })
}

/// Builds the record of a finished (or failed) run.
pub fn record(end: &RunEnd) -> RunRecord {
    let doc = end.doc;
    let provenance = end
        .plan
        .order
        .iter()
        .filter_map(|&i| end.plan.steps[i].as_ref())
        .map(|s| {
            let info = s.stage.info();
            StepProvenance {
                step: s.id.clone(),
                stage: info.id.to_string(),
                stage_version: info.version.to_string(),
                origin: s.origin.clone(),
                seed: s.seed,
                cache_key: s.cache_key.clone(),
                params: s.params.clone(),
                inputs: s
                    .inputs
                    .iter()
                    .map(|(port, w)| {
                        let producer = end.plan.steps[w.producer]
                            .as_ref()
                            .map(|p| p.id.clone())
                            .unwrap_or_default();
                        (port.clone(), format!("{producer}.{}", w.port))
                    })
                    .collect(),
                input_files: s.input_files.clone(),
            }
        })
        .collect();
    let exports = end
        .plan
        .exports
        .iter()
        .map(|e| {
            let producer = end.plan.steps[e.producer]
                .as_ref()
                .map(|p| p.id.clone())
                .unwrap_or_default();
            ExportRecord {
                from: format!("{producer}.{}", e.port),
                path: e.path.display().to_string(),
                format: e.exporter.name().to_string(),
                written: end.written.iter().any(|w| w == &e.path),
            }
        })
        .collect();
    RunRecord {
        grainpipe_version: grainpipe_core::VERSION.to_string(),
        pipeline_file: doc.file.display().to_string(),
        pipeline_name: doc.name.clone(),
        description: doc.description.clone(),
        seed: end.plan.seed,
        overrides: end.overrides.to_vec(),
        effective_yaml: effective_yaml(doc),
        source_yaml: doc.source.clone(),
        started_unix_s: end
            .started
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs_f64())
            .unwrap_or(0.0),
        wall_s: end.wall_s,
        status: if end.result.is_ok() { "ok" } else { "failed" }.into(),
        error: end.result.as_ref().err().cloned(),
        steps: end.steps.clone(),
        exports,
        provenance,
        host: std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|s| s.trim().to_string())
            .unwrap_or_default(),
        threads: std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1),
        warnings: end
            .warnings
            .iter()
            .map(|(step, text)| WarningRecord {
                step: step.clone(),
                text: text.clone(),
            })
            .collect(),
        reference: end.reference.clone(),
        auto_voxel: end.auto_voxel.clone(),
    }
}

/// What the report shows of a run's results: every output of every executed step.
pub fn extract(result: &RunResult) -> (ReportData, data::Pictures) {
    let mut pics = Vec::new();
    let mut items = Vec::new();
    for (step, outputs) in &result.outputs {
        for (port, a) in outputs.iter() {
            items.push(data::item(&format!("{step}.{port}"), a, &mut pics));
        }
    }
    (ReportData { items }, pics)
}

/// Writes `dir/report-data/` (when there are results) and then `dir/run.json`, each file
/// atomically; `run.json` comes last so its presence means the directory is complete.
/// Pictures of an earlier run in the same directory that this run did not draw are removed.
pub fn write_run_dir(dir: &Path, end: &RunEnd) -> Result<(), String> {
    let rec = record(end);
    let (data, pics) = match &end.result {
        Ok(r) => extract(r),
        Err(_) => (ReportData::default(), vec![]),
    };
    write_run_files(dir, &rec, &data, &pics)
}

/// Writes a run directory from a record and extracted data (what [`write_run_dir`] does
/// once it has them; also for records built elsewhere, e.g. by a sweep runner).
pub fn write_run_files(
    dir: &Path,
    rec: &RunRecord,
    data: &ReportData,
    pics: &data::Pictures,
) -> Result<(), String> {
    let data_dir = dir.join(DATA_DIR);
    for (name, bytes) in pics {
        atomic_write_bytes(&data_dir.join(name), bytes)?;
    }
    if let Ok(entries) = std::fs::read_dir(&data_dir) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.ends_with(".png") && !pics.iter().any(|(n, _)| *n == name) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    write_json(&data_dir.join(DATA_FILE), data)?;
    write_json(&dir.join(RUN_FILE), rec)
}

fn write_json<T: Serialize>(path: &Path, v: &T) -> Result<(), String> {
    atomic_write(path, |tmp| -> Result<(), String> {
        let text = serde_json::to_string_pretty(v).map_err(|e| e.to_string())?;
        std::fs::write(tmp, text + "\n").map_err(|e| e.to_string())
    })
}

/// A run directory read back: the record, the report data and the pictures by file name.
pub type RunDir = (
    RunRecord,
    ReportData,
    std::collections::HashMap<String, Vec<u8>>,
);

/// Reads `dir/run.json` and `dir/report-data/` (data and pictures).
pub fn read_run_dir(dir: &Path) -> Result<RunDir, String> {
    let run = dir.join(RUN_FILE);
    let text =
        std::fs::read_to_string(&run).map_err(|e| format!("cannot read {}: {e}", run.display()))?;
    let rec: RunRecord = serde_json::from_str(&text)
        .map_err(|e| format!("{} is not a run record: {e}", run.display()))?;
    let data_path = dir.join(DATA_DIR).join(DATA_FILE);
    let data: ReportData = match std::fs::read_to_string(&data_path) {
        Ok(t) => serde_json::from_str(&t)
            .map_err(|e| format!("{} is not report data: {e}", data_path.display()))?,
        Err(_) => ReportData::default(),
    };
    let mut pics = std::collections::HashMap::new();
    if let Ok(entries) = std::fs::read_dir(dir.join(DATA_DIR)) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.ends_with(".png") {
                if let Ok(b) = std::fs::read(e.path()) {
                    pics.insert(name, b);
                }
            }
        }
    }
    Ok((rec, data, pics))
}
