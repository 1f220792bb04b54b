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
}

impl PipelineError {
    pub fn input(file: &Path, loc: Option<Loc>, message: impl Into<String>) -> Self {
        PipelineError {
            class: ErrorClass::Input,
            file: file.to_path_buf(),
            loc,
            message: message.into(),
            help: None,
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
    pub fn exit_code(&self) -> i32 {
        match self.class {
            ErrorClass::Input => 2,
            ErrorClass::Run => 1,
            ErrorClass::Interrupted => 130,
        }
    }
}

impl fmt::Display for PipelineError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
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
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDoc {
    name: String,
    #[serde(default)]
    description: String,
    #[serde(default)]
    seed: u64,
    stages: Vec<Spanned<RawStep>>,
    #[serde(default)]
    export: Vec<Spanned<RawExport>>,
    #[serde(default)]
    plugins: Vec<Spanned<String>>,
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
}

/// The keys a pipeline may use at each level, for suggestions on unknown keys.
const DOC_KEYS: &[&str] = &["name", "description", "seed", "stages", "export", "plugins"];
const STEP_KEYS: &[&str] = &["id", "use", "in", "with"];
const EXPORT_KEYS: &[&str] = &["from", "to", "format"];

impl PipelineDoc {
    pub fn load(path: &Path) -> Result<PipelineDoc, PipelineError> {
        let source = std::fs::read_to_string(path)
            .map_err(|e| PipelineError::input(path, None, format!("cannot read pipeline: {e}")))?;
        Self::parse(path, source)
    }

    pub fn parse(path: &Path, source: String) -> Result<PipelineDoc, PipelineError> {
        let raw: RawDoc = serde_saphyr::from_str_with_options(&source, yaml_options())
            .map_err(|e| yaml_error(path, &e))?;
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
                Export {
                    from_loc: Loc::of(&e.from),
                    from: PortRef::parse(&e.from.value),
                    to_loc: Loc::of(&e.to),
                    to: PathBuf::from(&e.to.value),
                    format_loc: e.format.as_ref().map(Loc::of),
                    format: e.format.map(|f| f.value),
                }
            })
            .collect();
        Ok(PipelineDoc {
            file: path.to_path_buf(),
            source,
            name: raw.name,
            description: raw.description,
            seed: raw.seed,
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
    /// (so `140 um` stays a unit string and `[1, 2]` a list).
    pub fn apply_override(&mut self, assignment: &str) -> Result<(), PipelineError> {
        let cli = |m: String| PipelineError::input(Path::new("--set"), None, m);
        let (lhs, value) = assignment
            .split_once('=')
            .ok_or_else(|| cli(format!("`{assignment}` is not of the form step.key=value")))?;
        let (step_id, key) = lhs
            .trim()
            .split_once('.')
            .ok_or_else(|| cli(format!("`{lhs}` is not of the form step.key")))?;
        let suggestion =
            crate::registry::closest(step_id, self.steps.iter().map(|s| s.id.as_str()));
        let step = self
            .steps
            .iter_mut()
            .find(|s| s.id == step_id)
            .ok_or_else(|| {
                cli(format!("no step `{step_id}` in {}", self.file.display()))
                    .with_help(suggestion.map(|s| format!("did you mean `{s}`?")))
            })?;
        let value: serde_json::Value =
            serde_saphyr::from_str_with_options(value.trim(), yaml_options())
                .map_err(|e| cli(format!("value of `{lhs}` is not valid YAML: {e}")))?;
        step.params.insert(key.to_string(), value);
        Ok(())
    }
}

/// YAML 1.2 booleans only: `axis: y` must stay the string "y", not become `true`.
fn yaml_options() -> serde_saphyr::Options {
    let mut o = serde_saphyr::Options::default();
    o.strict_booleans = true;
    o
}

fn yaml_error(path: &Path, e: &serde_saphyr::Error) -> PipelineError {
    let loc = e.location().map(Loc::from_location);
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
        [DOC_KEYS, STEP_KEYS, EXPORT_KEYS]
            .iter()
            .filter_map(|keys| crate::registry::closest(&k, keys.iter().copied()))
            .next()
            .map(|s| format!("did you mean `{s}`?"))
    });
    PipelineError::input(path, loc, message).with_help(help)
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
}
