//! The pipeline document: parsing YAML into steps and exports while keeping the source
//! location of every key, so that every later error can point at file:line:col.

use indexmap::IndexMap;
use serde::Deserialize;
use serde_saphyr::Spanned;
use std::fmt;
use std::path::{Path, PathBuf};

/// A position in the pipeline file (1-based line and column; byte span for snippets).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Loc {
    pub line: u64,
    pub col: u64,
    pub offset: usize,
    pub len: usize,
}

impl Loc {
    fn of<T>(s: &Spanned<T>) -> Loc {
        Loc::from_location(s.referenced)
    }

    fn from_location(l: serde_saphyr::Location) -> Loc {
        let span = l.span();
        Loc {
            line: l.line(),
            col: l.column(),
            offset: span.byte_offset().unwrap_or(0) as usize,
            len: span.byte_len().unwrap_or(1).max(1) as usize,
        }
    }

    /// A location known by line and column only (serde-saphyr's syntax errors carry no
    /// byte span): the byte offset is found in `source`, so the snippet shows the fault and
    /// not the first line of the file.
    pub fn at(source: &str, line: u64, col: u64) -> Loc {
        let mut offset = 0;
        for (n, l) in source.split_inclusive('\n').enumerate() {
            if n as u64 + 1 == line {
                let chars = col.saturating_sub(1) as usize;
                let within = l
                    .char_indices()
                    .nth(chars)
                    .map(|(b, _)| b)
                    .unwrap_or(l.trim_end_matches('\n').len());
                offset += within;
                break;
            }
            offset += l.len();
        }
        let len = source[offset.min(source.len())..]
            .chars()
            .next()
            .map_or(1, |c| c.len_utf8());
        Loc {
            line,
            col,
            offset: offset.min(source.len()),
            len,
        }
    }
}

/// How bad a pipeline error is, which decides the exit code.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ErrorClass {
    /// The input is wrong (YAML, keys, types, references, impossible parameters): exit 2.
    Input,
    /// A stage failed while running, or an output could not be written: exit 1.
    Run,
    /// The user interrupted the run (Ctrl-C): exit 130, as a shell reports SIGINT.
    Interrupted,
}

/// An error about a pipeline, with the place in the file it concerns.
#[derive(Clone, Debug)]
pub struct PipelineError {
    pub class: ErrorClass,
    pub file: PathBuf,
    pub loc: Option<Loc>,
    pub message: String,
    /// "did you mean ..." or another hint.
    pub help: Option<String>,
    /// Further independent errors found in the same check (preflight reports every fault of
    /// a file at once); this error is the first of them in file order of the checks.
    pub related: Vec<PipelineError>,
    /// The text `loc` points into when it is not the content of `file` (a `--set`
    /// assignment); `None` means: read `file`.
    pub source_text: Option<String>,
}

impl PipelineError {
    pub fn input(file: &Path, loc: Option<Loc>, message: impl Into<String>) -> Self {
        PipelineError {
            class: ErrorClass::Input,
            file: file.to_path_buf(),
            loc,
            message: message.into(),
            help: None,
            related: Vec::new(),
            source_text: None,
        }
    }
    pub fn run(file: &Path, loc: Option<Loc>, message: impl Into<String>) -> Self {
        PipelineError {
            class: ErrorClass::Run,
            ..Self::input(file, loc, message)
        }
    }
    pub fn with_help(mut self, help: Option<String>) -> Self {
        self.help = help;
        self
    }
    /// One error carrying all of `errors` (the first as the main one); `Ok` when empty.
    pub fn collect(mut errors: Vec<PipelineError>) -> Result<(), PipelineError> {
        if errors.is_empty() {
            return Ok(());
        }
        let mut first = errors.remove(0);
        for mut e in errors {
            let mut nested = std::mem::take(&mut e.related);
            first.related.push(e);
            first.related.append(&mut nested);
        }
        Err(first)
    }
    /// This error and every related one, in the order found.
    pub fn all(&self) -> impl Iterator<Item = &PipelineError> {
        std::iter::once(self).chain(self.related.iter())
    }
    pub fn exit_code(&self) -> i32 {
        match self.class {
            ErrorClass::Input => 2,
            ErrorClass::Run => 1,
            ErrorClass::Interrupted => 130,
        }
    }
}

impl PipelineError {
    fn fmt_one(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.loc {
            Some(l) => write!(
                f,
                "{}:{}:{}: {}",
                self.file.display(),
                l.line,
                l.col,
                self.message
            )?,
            None => write!(f, "{}: {}", self.file.display(), self.message)?,
        }
        if let Some(h) = &self.help {
            write!(f, "\n  help: {h}")?;
        }
        Ok(())
    }
}

impl fmt::Display for PipelineError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.fmt_one(f)?;
        for r in &self.related {
            writeln!(f)?;
            r.fmt_one(f)?;
        }
        Ok(())
    }
}

impl std::error::Error for PipelineError {}

/// `step` or `step.port`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PortRef {
    pub step: String,
    pub port: Option<String>,
}

impl PortRef {
    pub fn parse(s: &str) -> PortRef {
        match s.split_once('.') {
            Some((a, b)) => PortRef {
                step: a.to_string(),
                port: Some(b.to_string()),
            },
            None => PortRef {
                step: s.to_string(),
                port: None,
            },
        }
    }
}

impl fmt::Display for PortRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.port {
            Some(p) => write!(f, "{}.{p}", self.step),
            None => write!(f, "{}", self.step),
        }
    }
}

/// One input connection of a step.
#[derive(Clone, Debug)]
pub struct InputRef {
    pub source: PortRef,
    pub key_loc: Loc,
    pub value_loc: Loc,
}

/// One `stages:` entry.
#[derive(Clone, Debug)]
pub struct Step {
    pub id: String,
    pub id_loc: Loc,
    /// The stage id (`use:`).
    pub uses: String,
    pub uses_loc: Loc,
    pub inputs: IndexMap<String, InputRef>,
    /// Parameters as written (units not yet converted).
    pub params: serde_json::Map<String, serde_json::Value>,
    pub param_locs: IndexMap<String, Loc>,
}

/// One `export:` entry.
#[derive(Clone, Debug)]
pub struct Export {
    pub from: PortRef,
    pub from_loc: Loc,
    pub to: PathBuf,
    pub to_loc: Loc,
    pub format: Option<String>,
    pub format_loc: Option<Loc>,
    /// Writer options (`with:`) as written, with the location of each key.
    pub options: serde_json::Map<String, serde_json::Value>,
    pub option_locs: IndexMap<String, Loc>,
}

/// A parsed pipeline file.
#[derive(Clone, Debug)]
pub struct PipelineDoc {
    pub file: PathBuf,
    pub source: String,
    pub name: String,
    pub description: String,
    pub seed: u64,
    pub steps: Vec<Step>,
    pub exports: Vec<Export>,
    /// Plugin libraries or directories (`plugins:`), with their locations.
    pub plugins: Vec<(PathBuf, Loc)>,
    /// The seed the file gives (`seed` may since have been overridden).
    pub file_seed: u64,
    /// The `--set` assignments applied, in order.
    pub overrides: Vec<Override>,
    /// Values the results are compared with (`reference:`), and where each quantity is
    /// written (for planning errors).
    pub reference: Option<crate::values::Reference>,
    pub reference_locs: Vec<Loc>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDoc {
    name: String,
    #[serde(default)]
    description: String,
    #[serde(default)]
    seed: Option<Spanned<serde_json::Value>>,
    stages: Vec<Spanned<RawStep>>,
    #[serde(default)]
    export: Vec<Spanned<RawExport>>,
    #[serde(default)]
    plugins: Vec<Spanned<String>>,
    #[serde(default)]
    reference: Option<Spanned<RawReference>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawReference {
    source: Spanned<String>,
    #[serde(default)]
    note: String,
    values: Vec<Spanned<RawReferenceValue>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawReferenceValue {
    quantity: Spanned<String>,
    value: Spanned<serde_json::Value>,
    #[serde(default)]
    tolerance: Option<Spanned<serde_json::Value>>,
    #[serde(default)]
    range: Option<Spanned<Vec<Spanned<serde_json::Value>>>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawStep {
    id: Spanned<String>,
    #[serde(rename = "use")]
    uses: Spanned<String>,
    #[serde(default, rename = "in")]
    inputs: IndexMap<Spanned<String>, Spanned<String>>,
    #[serde(default, rename = "with")]
    params: IndexMap<Spanned<String>, Spanned<serde_json::Value>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawExport {
    from: Spanned<String>,
    to: Spanned<String>,
    #[serde(default)]
    format: Option<Spanned<String>>,
    #[serde(default, rename = "with")]
    options: IndexMap<Spanned<String>, Spanned<serde_json::Value>>,
}

/// The keys a pipeline may use at each level, for suggestions on unknown keys.
const DOC_KEYS: &[&str] = &[
    "name",
    "description",
    "seed",
    "stages",
    "export",
    "plugins",
    "reference",
];
const REFERENCE_KEYS: &[&str] = &["source", "note", "values"];
const REFERENCE_VALUE_KEYS: &[&str] = &["quantity", "value", "tolerance", "range"];
const STEP_KEYS: &[&str] = &["id", "use", "in", "with"];
const EXPORT_KEYS: &[&str] = &["from", "to", "format", "with"];

impl PipelineDoc {
    pub fn load(path: &Path) -> Result<PipelineDoc, PipelineError> {
        let source = std::fs::read_to_string(path)
            .map_err(|e| PipelineError::input(path, None, format!("cannot read pipeline: {e}")))?;
        Self::parse(path, source)
    }

    pub fn parse(path: &Path, source: String) -> Result<PipelineDoc, PipelineError> {
        let raw: RawDoc = serde_saphyr::from_str_with_options(&source, yaml_options())
            .map_err(|e| yaml_error(path, &source, &e))?;
        let seed = match &raw.seed {
            None => 0,
            Some(v) => v.value.as_u64().ok_or_else(|| {
                let written = match &v.value {
                    serde_json::Value::String(t) => format!("`{t}`"),
                    other => format!("`{other}`"),
                };
                PipelineError::input(
                    path,
                    Some(Loc::of(v)),
                    format!("seed must be a whole number between 0 and 2^64-1, not {written}"),
                )
                .with_help(Some("write e.g. `seed: 42`".into()))
            })?,
        };
        let mut steps = Vec::with_capacity(raw.stages.len());
        for s in raw.stages {
            let s = s.value;
            let mut inputs = IndexMap::new();
            for (k, v) in s.inputs {
                inputs.insert(
                    k.value.clone(),
                    InputRef {
                        source: PortRef::parse(&v.value),
                        key_loc: Loc::of(&k),
                        value_loc: Loc::of(&v),
                    },
                );
            }
            let mut params = serde_json::Map::new();
            let mut param_locs = IndexMap::new();
            for (k, v) in s.params {
                param_locs.insert(k.value.clone(), Loc::of(&k));
                params.insert(k.value, v.value);
            }
            steps.push(Step {
                id_loc: Loc::of(&s.id),
                id: s.id.value,
                uses_loc: Loc::of(&s.uses),
                uses: s.uses.value,
                inputs,
                params,
                param_locs,
            });
        }
        let exports = raw
            .export
            .into_iter()
            .map(|e| {
                let e = e.value;
                let mut options = serde_json::Map::new();
                let mut option_locs = IndexMap::new();
                for (k, v) in e.options {
                    option_locs.insert(k.value.clone(), Loc::of(&k));
                    options.insert(k.value, v.value);
                }
                Export {
                    options,
                    option_locs,
                    from_loc: Loc::of(&e.from),
                    from: PortRef::parse(&e.from.value),
                    to_loc: Loc::of(&e.to),
                    to: PathBuf::from(&e.to.value),
                    format_loc: e.format.as_ref().map(Loc::of),
                    format: e.format.map(|f| f.value),
                }
            })
            .collect();
        let (reference, reference_locs) = match raw.reference {
            Some(r) => {
                let (r, locs) = parse_reference(path, r.value)?;
                (Some(r), locs)
            }
            None => (None, Vec::new()),
        };
        Ok(PipelineDoc {
            reference,
            reference_locs,
            file: path.to_path_buf(),
            source,
            name: raw.name,
            description: raw.description,
            seed,
            file_seed: seed,
            overrides: Vec::new(),
            steps,
            exports,
            plugins: raw
                .plugins
                .iter()
                .map(|p| (PathBuf::from(&p.value), Loc::of(p)))
                .collect(),
        })
    }

    pub fn step(&self, id: &str) -> Option<(usize, &Step)> {
        self.steps.iter().enumerate().find(|(_, s)| s.id == id)
    }

    /// Moves every export under `dir`: a path below `out/` keeps its part after `out/`,
    /// any other relative path is appended as it is.
    pub fn redirect_exports(&mut self, dir: &Path) {
        for e in &mut self.exports {
            let rel = e.to.strip_prefix("out").unwrap_or(&e.to).to_path_buf();
            e.to = dir.join(rel);
        }
    }

    /// Applies a command-line override `step.key=value`; the value is read as YAML
    /// (so `140 um` stays a unit string and `[1, 2]` a list). `step.key.field=value`
    /// replaces one field of a mapping parameter (`pack.radius.value=30 um`), creating the
    /// missing levels; whether the parameter may be a mapping is checked when planning, and
    /// errors found then point at this assignment (see [`PipelineDoc::overrides`]).
    pub fn apply_override(&mut self, assignment: &str) -> Result<(), PipelineError> {
        let at = |start: usize, len: usize, m: String| {
            let mut e =
                PipelineError::input(Path::new("--set"), Some(Override::loc(start, len)), m);
            e.source_text = Some(assignment.to_string());
            e
        };
        let Some(eq) = assignment.find('=') else {
            return Err(at(
                0,
                assignment.len(),
                format!("`{assignment}` is not of the form step.key=value"),
            )
            .with_help(Some("write e.g. `--set pack.volume_fraction=0.3`".into())));
        };
        let lhs = &assignment[..eq];
        let lead = lhs.len() - lhs.trim_start().len();
        let mut parts = Vec::new();
        let mut pos = lead;
        for seg in lhs.trim().split('.') {
            parts.push((pos, seg));
            pos += seg.len() + 1;
        }
        if parts.len() < 2 || parts.iter().any(|(_, p)| p.trim().is_empty()) {
            return Err(at(
                lead,
                lhs.trim().len().max(1),
                format!(
                    "`{}` is not of the form step.key (or step.key.field)",
                    lhs.trim()
                ),
            ));
        }
        let (step_pos, step_id) = parts[0];
        let Some(step_index) = self.steps.iter().position(|s| s.id == step_id) else {
            let suggestion =
                crate::registry::closest(step_id, self.steps.iter().map(|s| s.id.as_str()));
            return Err(at(
                step_pos,
                step_id.len(),
                format!("no step `{step_id}` in {}", self.file.display()),
            )
            .with_help(suggestion.map(|s| format!("did you mean `{s}`?"))));
        };
        let value_text = &assignment[eq + 1..];
        let value_pos = eq + 1 + (value_text.len() - value_text.trim_start().len());
        let value: serde_json::Value =
            serde_saphyr::from_str_with_options(value_text.trim(), yaml_options()).map_err(
                |e| {
                    at(
                        value_pos,
                        value_text.trim().len().max(1),
                        format!("value of `{}` is not valid YAML: {e}", lhs.trim()),
                    )
                },
            )?;
        let path: Vec<String> = parts[1..].iter().map(|(_, p)| p.to_string()).collect();
        let step = &mut self.steps[step_index];
        let mut slot = step
            .params
            .entry(path[0].clone())
            .or_insert(serde_json::Value::Null);
        for (depth, field) in path.iter().enumerate().skip(1) {
            if slot.is_null() {
                *slot = serde_json::Value::Object(Default::default());
            }
            let map = match slot {
                serde_json::Value::Object(map) => map,
                other => {
                    let (p, _) = parts[depth + 1];
                    let head = parts[..depth + 1]
                        .iter()
                        .map(|(_, s)| *s)
                        .collect::<Vec<_>>()
                        .join(".");
                    return Err(at(
                        step_pos,
                        p - step_pos - 1,
                        format!("`{head}` is {other}, not a mapping: it has no field `{field}`"),
                    )
                    .with_help(Some(format!("set it as a whole: `--set {head}=...`"))));
                }
            };
            slot = map.entry(field.clone()).or_insert(serde_json::Value::Null);
        }
        *slot = value;
        let (key_pos, key) = parts[1];
        self.overrides.push(Override {
            text: assignment.to_string(),
            step: step_id.to_string(),
            key: key.to_string(),
            key_loc: Override::loc(key_pos, lhs.trim_end().len() - key_pos),
            value_loc: Override::loc(value_pos, value_text.trim().len().max(1)),
        });
        Ok(())
    }

    /// The last override of parameter `key` of step `step`, if any: errors about that
    /// parameter point at the override, not at the file.
    pub fn override_of(&self, step: &str, key: &str) -> Option<&Override> {
        self.overrides
            .iter()
            .rev()
            .find(|o| o.step == step && o.key == key)
    }

    /// The pipeline as it runs: the file with every override and the seed applied, as YAML
    /// (comments are not kept; the file itself is `source`).
    pub fn effective_yaml(&self) -> String {
        use serde_json::{json, Map, Value};
        let steps: Vec<Value> = self
            .steps
            .iter()
            .map(|s| {
                let mut m = Map::new();
                m.insert("id".into(), json!(s.id));
                m.insert("use".into(), json!(s.uses));
                if !s.inputs.is_empty() {
                    let ins: Map<String, Value> = s
                        .inputs
                        .iter()
                        .map(|(k, v)| (k.clone(), json!(v.source.to_string())))
                        .collect();
                    m.insert("in".into(), Value::Object(ins));
                }
                if !s.params.is_empty() {
                    m.insert("with".into(), Value::Object(s.params.clone()));
                }
                Value::Object(m)
            })
            .collect();
        let mut doc = Map::new();
        doc.insert("name".into(), json!(self.name));
        if !self.description.is_empty() {
            doc.insert("description".into(), json!(self.description));
        }
        doc.insert("seed".into(), json!(self.seed));
        doc.insert("stages".into(), Value::Array(steps));
        if !self.exports.is_empty() {
            let ex: Vec<Value> = self
                .exports
                .iter()
                .map(|e| {
                    let mut m = Map::new();
                    m.insert("from".into(), json!(e.from.to_string()));
                    m.insert("to".into(), json!(e.to.display().to_string()));
                    if let Some(f) = &e.format {
                        m.insert("format".into(), json!(f));
                    }
                    if !e.options.is_empty() {
                        m.insert("with".into(), Value::Object(e.options.clone()));
                    }
                    Value::Object(m)
                })
                .collect();
            doc.insert("export".into(), Value::Array(ex));
        }
        if !self.plugins.is_empty() {
            let p: Vec<Value> = self
                .plugins
                .iter()
                .map(|(p, _)| json!(p.display().to_string()))
                .collect();
            doc.insert("plugins".into(), Value::Array(p));
        }
        if let Some(r) = &self.reference {
            let values: Vec<Value> = r
                .values
                .iter()
                .map(|v| {
                    let mut m = Map::new();
                    m.insert("quantity".into(), json!(v.quantity));
                    m.insert("value".into(), json!(v.written));
                    match v.tolerance {
                        Some(crate::values::Tolerance::Range(..)) => {
                            let (lo, hi) = v
                                .tolerance_written
                                .trim_start_matches("range ")
                                .split_once(" to ")
                                .unwrap_or_default();
                            m.insert("range".into(), json!([lo, hi]));
                        }
                        Some(_) => {
                            m.insert("tolerance".into(), json!(v.tolerance_written));
                        }
                        None => {}
                    }
                    Value::Object(m)
                })
                .collect();
            let mut m = Map::new();
            m.insert("source".into(), json!(r.source));
            if !r.note.is_empty() {
                m.insert("note".into(), json!(r.note));
            }
            m.insert("values".into(), Value::Array(values));
            doc.insert("reference".into(), Value::Object(m));
        }
        serde_saphyr::to_string(&Value::Object(doc)).unwrap_or_else(|e| format!("# {e}\n"))
    }
}

/// One `--set` assignment as applied, with the places of its key and value in its text.
#[derive(Clone, Debug)]
pub struct Override {
    /// `step.key=value` as given.
    pub text: String,
    pub step: String,
    /// The top-level parameter it changes.
    pub key: String,
    pub key_loc: Loc,
    pub value_loc: Loc,
}

impl Override {
    fn loc(start: usize, len: usize) -> Loc {
        Loc {
            line: 1,
            col: start as u64 + 1,
            offset: start,
            len: len.max(1),
        }
    }

    /// An input error located in this assignment's text (`value` or key).
    pub fn error(&self, at_value: bool, message: impl Into<String>) -> PipelineError {
        let loc = if at_value {
            self.value_loc
        } else {
            self.key_loc
        };
        let mut e = PipelineError::input(Path::new("--set"), Some(loc), message);
        e.source_text = Some(self.text.clone());
        e
    }
}

/// YAML 1.2 booleans only: `axis: y` must stay the string "y", not become `true`.
fn yaml_options() -> serde_saphyr::Options {
    let mut o = serde_saphyr::Options::default();
    o.strict_booleans = true;
    o
}

fn yaml_error(path: &Path, source: &str, e: &serde_saphyr::Error) -> PipelineError {
    let mut loc = e.location().filter(|l| l.line() > 0).map(|l| {
        if l.span().byte_offset().is_some() {
            Loc::from_location(l)
        } else {
            Loc::at(source, l.line(), l.column())
        }
    });
    // The scanner reports a tab at the start of the token it was reading (often the line
    // before); the fault is the tab itself.
    if let Some(l) = loc.filter(|_| e.to_string().contains("found a tab")) {
        if let Some(t) = source.get(l.offset..).and_then(|r| r.find('\t')) {
            let at = l.offset + t;
            let line = source[..at].matches('\n').count() as u64 + 1;
            let col = source[..at]
                .rsplit('\n')
                .next()
                .map_or(0, |p| p.chars().count()) as u64
                + 1;
            loc = Some(Loc::at(source, line, col));
        }
    }
    // serde-saphyr's Display includes a rendered snippet; keep the first line as the message.
    let full = e.to_string();
    let first = full
        .lines()
        .next()
        .unwrap_or(&full)
        .trim_start_matches("error: ");
    // Drop the "line N column M: " prefix: the location is reported separately.
    let message = match first.split_once(": ") {
        Some((head, rest)) if head.starts_with("line ") => rest.to_string(),
        _ => first.to_string(),
    };
    let help = crate::stage::unknown_field_name(&message).and_then(|k| {
        [
            DOC_KEYS,
            STEP_KEYS,
            EXPORT_KEYS,
            REFERENCE_KEYS,
            REFERENCE_VALUE_KEYS,
        ]
        .iter()
        .filter_map(|keys| crate::registry::closest(&k, keys.iter().copied()))
        .next()
        .map(|s| format!("did you mean `{s}`?"))
    });
    PipelineError::input(path, loc, message).with_help(help)
}

/// Reads a `reference:` block: each value a number or a unit string (`4.97 GPa`), each
/// tolerance `10 %` or a bare fraction (relative) or a quantity of the value's dimension
/// (absolute). Errors name the line of the value.
fn parse_reference(
    path: &Path,
    r: RawReference,
) -> Result<(crate::values::Reference, Vec<Loc>), PipelineError> {
    use crate::units::{parse_quantity, Quantity};
    use crate::values::{ReferenceValue, Tolerance};
    let at = |loc: Loc, m: String| PipelineError::input(path, Some(loc), m);
    let quantity_of = |v: &Spanned<serde_json::Value>,
                       key: &str|
     -> Result<(Quantity, String), PipelineError> {
        let written = match &v.value {
            serde_json::Value::Number(n) => n.to_string(),
            serde_json::Value::String(t) => t.clone(),
            other => {
                return Err(at(
                    Loc::of(v),
                    format!("reference `{key}` must be a number or a quantity such as `4.9 GPa`, not `{other}`"),
                ))
            }
        };
        let q = parse_quantity(&written)
            .map_err(|e| at(Loc::of(v), format!("reference `{key}`: {e}")))?;
        if !q.value.is_finite() {
            return Err(at(
                Loc::of(v),
                format!("reference `{key}` `{written}` is not finite"),
            ));
        }
        Ok((q, written))
    };
    if r.source.value.trim().is_empty() {
        return Err(at(
            Loc::of(&r.source),
            "reference `source` is empty: say where the values come from (paper, table, \
             independent computation)"
                .into(),
        ));
    }
    let mut values = Vec::with_capacity(r.values.len());
    let mut locs = Vec::with_capacity(r.values.len());
    for v in r.values {
        let v = v.value;
        let quantity = v.quantity.value.trim().to_string();
        if crate::values::split_quantity(&quantity).is_none() {
            return Err(at(
                Loc::of(&v.quantity),
                format!("reference quantity `{quantity}` is not of the form step.port.column, step.port[k] or step.port.<component>"),
            )
            .with_help(Some("e.g. `stiffness.constants.E_x` or `flow.permeability.kappa_zz`".into())));
        }
        let (q, written) = quantity_of(&v.value, "value")?;
        if q.value == 0.0 {
            return Err(at(
                Loc::of(&v.value),
                format!("reference value of `{quantity}` is zero: a relative difference to it has no meaning"),
            ));
        }
        let (tolerance, tolerance_written) = match (&v.tolerance, &v.range) {
            (Some(_), Some(r)) => {
                return Err(at(
                    Loc::of(r),
                    format!("reference `{quantity}` has both `tolerance` and `range`: give one"),
                ))
            }
            (None, None) => (None, String::new()),
            (None, Some(r)) => {
                let [lo, hi] = r.value.as_slice() else {
                    return Err(at(
                        Loc::of(r),
                        format!("reference `range` of `{quantity}` must be [lowest, highest]"),
                    ));
                };
                let (lq, lw) = quantity_of(lo, "range")?;
                let (hq, hw) = quantity_of(hi, "range")?;
                if lq.dim != q.dim || hq.dim != q.dim {
                    return Err(at(
                        Loc::of(r),
                        format!(
                            "reference `range` [{lw}, {hw}] is not in the dimension of `{written}`"
                        ),
                    ));
                }
                if lq.value > hq.value {
                    return Err(at(
                        Loc::of(r),
                        format!("reference `range` [{lw}, {hw}]: the lowest is above the highest"),
                    ));
                }
                (
                    Some(Tolerance::Range(lq.value, hq.value)),
                    format!("range {lw} to {hw}"),
                )
            }
            (Some(t), None) => {
                let (tq, tw) = quantity_of(t, "tolerance")?;
                let tol = if tq.dim == crate::units::Dimension::NONE {
                    Tolerance::Relative(tq.value)
                } else if tq.dim == q.dim {
                    Tolerance::Absolute(tq.value)
                } else {
                    return Err(at(
                        Loc::of(t),
                        format!(
                            "reference tolerance `{tw}` has another dimension than the value `{written}`"
                        ),
                    )
                    .with_help(Some("give it as a fraction (`10 %`, `0.1`) or in the value's unit".into())));
                };
                if tq.value < 0.0 {
                    return Err(at(
                        Loc::of(t),
                        format!("reference tolerance `{tw}` is negative"),
                    ));
                }
                (Some(tol), tw)
            }
        };
        locs.push(Loc::of(&v.quantity));
        values.push(ReferenceValue {
            quantity,
            value: q.value,
            dimension: q.dim.0,
            written,
            tolerance,
            tolerance_written,
        });
    }
    Ok((
        crate::values::Reference {
            source: r.source.value,
            note: r.note,
            values,
        },
        locs,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = "name: t\nseed: 3\nstages:\n  - id: a\n    use: packing.rsa\n    with:\n      radius: 140 um\n  - id: b\n    use: voxelize.packing\n    in: {packing: a.packing}\nexport:\n  - {from: b.image, to: out/x.vti}\n";

    #[test]
    fn parses_steps_inputs_params_and_locations() {
        let d = PipelineDoc::parse(Path::new("t.yaml"), GOOD.into()).unwrap();
        assert_eq!(d.seed, 3);
        assert_eq!(d.steps.len(), 2);
        assert_eq!(d.steps[0].params["radius"], serde_json::json!("140 um"));
        assert_eq!(d.steps[0].param_locs["radius"].line, 7);
        assert_eq!(d.steps[0].param_locs["radius"].col, 7);
        let inp = &d.steps[1].inputs["packing"];
        assert_eq!(
            inp.source,
            PortRef {
                step: "a".into(),
                port: Some("packing".into())
            }
        );
        assert_eq!(d.exports[0].to, PathBuf::from("out/x.vti"));
    }

    /// Issue 36: reference values in units, tolerances relative (`%`, a bare fraction) or in
    /// the value's unit; a tolerance in another dimension, a zero value and an empty source
    /// are errors at their line.
    #[test]
    fn reference_block_reads_units_and_tolerances() {
        use crate::values::Tolerance;
        let with =
            |values: &str| format!("{GOOD}reference:\n  source: Table 7\n  values:\n{values}");
        let d = PipelineDoc::parse(
            Path::new("t.yaml"),
            with("    - {quantity: b.x.E_x, value: 4.9 GPa, tolerance: 10 %}\n    - {quantity: \"b.x[8]\", value: 1.2e-11, tolerance: 0.05}\n    - {quantity: b.x.E_z, value: 4 GPa, tolerance: 0.5 GPa}\n    - {quantity: b.x.E_y, value: 4.63 GPa, range: [3.85 GPa, 5.35 GPa]}\n"),
        )
        .unwrap();
        let r = d.reference.unwrap();
        assert_eq!(r.values[0].value, 4.9e9);
        assert_eq!(r.values[0].tolerance, Some(Tolerance::Relative(0.1)));
        assert_eq!(r.values[1].tolerance, Some(Tolerance::Relative(0.05)));
        assert_eq!(r.values[2].tolerance, Some(Tolerance::Absolute(0.5e9)));
        assert_eq!(
            r.values[3].tolerance,
            Some(Tolerance::Range(3.85e9, 5.35e9))
        );
        assert_eq!(d.reference_locs[1].line, 17);
        for (values, says, line) in [
            (
                "    - {quantity: b.x.E_x, value: 4.9 GPa, tolerance: 2 um}\n",
                "another dimension",
                16,
            ),
            ("    - {quantity: b.x.E_x, value: 0 GPa}\n", "is zero", 16),
            ("    - {quantity: bx, value: 1}\n", "not of the form", 16),
            (
                "    - {quantity: b.x.E_x, value: 4.9 GPa, tolerence: 1 %}\n",
                "tolerance",
                16,
            ),
        ] {
            let e = PipelineDoc::parse(Path::new("t.yaml"), with(values)).unwrap_err();
            let all = format!("{e} {:?}", e.help);
            assert!(all.contains(says), "{values}: {all}");
            assert_eq!(e.loc.map(|l| l.line), Some(line), "{values}: {all}");
        }
    }

    #[test]
    fn unknown_key_has_location_and_suggestion() {
        let bad = GOOD.replace("    with:", "    wiht:");
        let e = PipelineDoc::parse(Path::new("t.yaml"), bad).unwrap_err();
        assert_eq!(e.loc.map(|l| l.line), Some(6), "{e}");
        assert!(e.help.as_deref().unwrap_or("").contains("with"), "{e}");
        assert_eq!(e.exit_code(), 2);
    }

    #[test]
    fn override_replaces_param_as_yaml() {
        let mut d = PipelineDoc::parse(Path::new("t.yaml"), GOOD.into()).unwrap();
        d.apply_override("a.radius=70 um").unwrap();
        assert_eq!(d.steps[0].params["radius"], serde_json::json!("70 um"));
        d.apply_override("a.n=[1, 2]").unwrap();
        assert_eq!(d.steps[0].params["n"], serde_json::json!([1, 2]));
        // YAML 1.2: `y`, `no`, `on` are strings, only true/false are booleans.
        d.apply_override("a.axis=y").unwrap();
        assert_eq!(d.steps[0].params["axis"], serde_json::json!("y"));
        d.apply_override("a.flag=true").unwrap();
        assert_eq!(d.steps[0].params["flag"], serde_json::json!(true));
        let e = d.apply_override("aa.radius=1").unwrap_err();
        assert!(e.help.unwrap().contains("`a`"));
    }

    #[test]
    fn syntax_errors_point_at_their_line_and_column() {
        let tab = "name: t\nstages:\n  - id: a\n\tuse: packing.rsa\n";
        let e = PipelineDoc::parse(Path::new("t.yaml"), tab.into()).unwrap_err();
        let l = e.loc.unwrap();
        assert_eq!((l.line, l.col), (4, 1), "{e}");
        assert_eq!(&tab[l.offset..l.offset + 1], "\t", "{e}");
        let open = "name: t\nstages:\n  - id: a\n    with:\n      size: [1, 2\n      x: 3\n";
        let e = PipelineDoc::parse(Path::new("t.yaml"), open.into()).unwrap_err();
        let l = e.loc.unwrap();
        // Unclosed `[`: the scanner fails at the `:` of the next line's key.
        assert_eq!((l.line, l.col), (6, 8), "{e}");
        assert_eq!(&open[l.offset..l.offset + 1], ":", "{e}");
        let seed = "name: t\nseed: forty\nstages: []\n";
        let e = PipelineDoc::parse(Path::new("t.yaml"), seed.into()).unwrap_err();
        assert_eq!(
            e.message,
            "seed must be a whole number between 0 and 2^64-1, not `forty`"
        );
        assert_eq!(e.loc.map(|l| (l.line, l.col)), Some((2, 7)), "{e}");
    }

    #[test]
    fn nested_override_and_effective_yaml() {
        let mut d = PipelineDoc::parse(Path::new("t.yaml"), GOOD.into()).unwrap();
        d.apply_override("a.dist.value=30 um").unwrap();
        assert_eq!(
            d.steps[0].params["dist"],
            serde_json::json!({"value": "30 um"})
        );
        let e = d.apply_override("a.dist.value.x=1").unwrap_err();
        let l = e.loc.unwrap();
        assert_eq!(
            &e.source_text.as_deref().unwrap()[l.offset..l.offset + l.len],
            "a.dist.value"
        );
        d.seed = 11;
        let back = PipelineDoc::parse(Path::new("b.yaml"), d.effective_yaml()).unwrap();
        assert_eq!(back.seed, 11);
        assert_eq!(
            back.steps[0].params["dist"],
            serde_json::json!({"value": "30 um"})
        );
        assert_eq!(
            back.steps[1].inputs["packing"].source.to_string(),
            "a.packing"
        );
        assert_eq!(back.exports[0].to, PathBuf::from("out/x.vti"));
        assert_eq!(
            d.override_of("a", "dist").unwrap().text,
            "a.dist.value=30 um"
        );
    }
}
