//! `pipe list` and `pipe describe`: text generated from the registry, so the README's stage
//! list (made with `pipe list --markdown`) cannot drift from the code.

use grainpipe_core::params::object_schema;
use grainpipe_core::registry::Registered;
use grainpipe_core::Registry;
use serde_json::{json, Value};
use std::fmt::Write;
use std::path::Path;

/// First sentence of a doc paragraph: up to the first ". " followed by a capital letter,
/// outside parentheses (a citation such as "(Heinze et al., Phys. Rev. E, 2020)" does not end
/// it), that does not end an abbreviation ("et al.", "e.g.", "eq.").
fn summary(doc: &str) -> &str {
    const ABBREVIATIONS: [&str; 6] = ["al", "e.g", "i.e", "eq", "cf", "Fig"];
    let mut depth = 0i32;
    for (i, c) in doc.char_indices() {
        match c {
            '(' | '[' => depth += 1,
            ')' | ']' => depth -= 1,
            '.' if depth <= 0 && doc[i + 1..].starts_with(' ') => {
                let next_is_capital = doc[i + 2..].chars().next().is_some_and(char::is_uppercase);
                let word = doc[..i].rsplit(' ').next().unwrap_or("");
                if next_is_capital && !ABBREVIATIONS.contains(&word) {
                    return &doc[..=i];
                }
            }
            _ => {}
        }
    }
    doc.trim_end()
}

/// Columns `pipe list` lays its lines out in: the terminal's width, or 100 when standard
/// output is not a terminal (a pipe, a file).
pub fn output_width() -> usize {
    terminal_size::terminal_size_of(std::io::stdout())
        .map(|(w, _)| usize::from(w.0))
        .filter(|&w| w >= 40)
        .unwrap_or(100)
}

/// `text` cut to at most `width` characters, an ellipsis marking the cut.
fn fit(text: &str, width: usize) -> String {
    if text.chars().count() <= width {
        return text.to_string();
    }
    let mut out: String = text.chars().take(width.saturating_sub(1)).collect();
    out.truncate(out.trim_end().len());
    out.push('…');
    out
}

/// Where a stage comes from, short: nothing for built-in stages, a plugin's file name.
fn short_origin(origin: &str) -> String {
    if origin == "built-in" {
        return String::new();
    }
    let name = Path::new(origin)
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| origin.to_string());
    format!("  [{name}]")
}

/// Extensions as `.a .b`, or a note that only `format:` selects the exporter.
fn extensions(e: &dyn grainpipe_core::Exporter) -> String {
    if e.extensions().is_empty() {
        "(format: only)".to_string()
    } else {
        e.extensions()
            .iter()
            .map(|x| format!(".{x}"))
            .collect::<Vec<_>>()
            .join(" ")
    }
}

/// One line per stage (id, version, first sentence of its doc, the plugin file it comes
/// from) and per export format, each cut to the terminal's width ([`output_width`]).
pub fn list_text(r: &Registry) -> String {
    list_text_width(r, output_width())
}

/// [`list_text`] laid out in `width` columns.
pub fn list_text_width(r: &Registry, width: usize) -> String {
    let mut s = String::new();
    let id_width = r
        .stages()
        .iter()
        .map(|x| x.stage.info().id.len())
        .max()
        .unwrap_or(10);
    writeln!(s, "Stages ({}):", r.stages().len()).unwrap();
    for x in r.stages() {
        let i = x.stage.info();
        let head = format!("  {:id_width$}  {:7}  ", i.id, i.version);
        let origin = short_origin(&x.origin);
        // The origin is kept whole (it tells plugins apart); the summary gives way.
        let room = width.saturating_sub(head.chars().count() + origin.chars().count());
        writeln!(s, "{head}{}{origin}", fit(summary(i.doc), room.max(12))).unwrap();
    }
    writeln!(s, "\nExport formats:").unwrap();
    for e in r.exporters() {
        let head = format!("  {:10} {:15} ", e.name(), extensions(e.as_ref()));
        let room = width.saturating_sub(head.chars().count());
        writeln!(s, "{head}{}", fit(summary(e.doc()), room.max(12))).unwrap();
    }
    let footer = "`pipe describe <stage or format>` shows parameters, defaults, units and ports.";
    writeln!(s, "\n{}", fit(footer, width)).unwrap();
    s
}

/// The same as a Markdown table (for the README).
pub fn list_markdown(r: &Registry) -> String {
    let mut s = String::from(
        "| stage | version | inputs | outputs | what it does |\n|---|---|---|---|---|\n",
    );
    for x in r.stages() {
        let i = x.stage.info();
        let ports = |p: &[grainpipe_core::PortSpec]| {
            if p.is_empty() {
                "—".to_string()
            } else {
                p.iter()
                    .map(|p| format!("`{}` ({})", p.name, p.kind))
                    .collect::<Vec<_>>()
                    .join(", ")
            }
        };
        writeln!(
            s,
            "| `{}` | {} | {} | {} | {} |",
            i.id,
            i.version,
            ports(&i.inputs),
            ports(&i.outputs),
            summary(i.doc).replace('|', "\\|")
        )
        .unwrap();
    }
    s.push_str("\n| export format | extensions | takes |\n|---|---|---|\n");
    for e in r.exporters() {
        writeln!(
            s,
            "| `{}` | {} | {} |",
            e.name(),
            extensions(e.as_ref()),
            e.doc()
        )
        .unwrap();
    }
    s
}

fn describe_stage(x: &Registered) -> String {
    let i = x.stage.info();
    let defaults = x.stage.default_params();
    let mut s = String::new();
    writeln!(s, "{} {}  ({})\n", i.id, i.version, x.origin).unwrap();
    writeln!(s, "{}\n", textwrap(i.doc, 90)).unwrap();
    writeln!(
        s,
        "Parameters (YAML `with:`; numbers are SI, strings may carry units):"
    )
    .unwrap();
    if i.params.is_empty() {
        writeln!(s, "  none").unwrap();
    }
    for p in &i.params {
        let d = defaults
            .get(p.name)
            .map(|v| v.to_string())
            .unwrap_or_default();
        let unit = if p.unit.is_empty() {
            String::new()
        } else {
            format!(" [{}]", p.unit)
        };
        let file = if p.reads_file {
            "; an input file, the cache follows its content"
        } else {
            ""
        };
        writeln!(s, "  {}: {}{}  (default {}{file})", p.name, p.ty, unit, d).unwrap();
        writeln!(s, "      {}", textwrap(p.doc, 84).replace('\n', "\n      ")).unwrap();
    }
    writeln!(s, "\nInputs (YAML `in:`):").unwrap();
    if i.inputs.is_empty() {
        writeln!(s, "  none").unwrap();
    }
    for p in &i.inputs {
        let opt = if p.optional { ", optional" } else { "" };
        writeln!(s, "  {}: {}{}  {}", p.name, p.kind, opt, p.doc).unwrap();
    }
    writeln!(s, "\nOutputs:").unwrap();
    for p in &i.outputs {
        writeln!(s, "  {}: {}  {}", p.name, p.kind, p.doc).unwrap();
    }
    s
}

fn textwrap(text: &str, width: usize) -> String {
    let mut out = String::new();
    let mut line = String::new();
    for w in text.split_whitespace() {
        if !line.is_empty() && line.len() + 1 + w.len() > width {
            out.push_str(&line);
            out.push('\n');
            line.clear();
        }
        if !line.is_empty() {
            line.push(' ');
        }
        line.push_str(w);
    }
    out.push_str(&line);
    out
}

fn ports_json(ports: &[grainpipe_core::PortSpec]) -> Value {
    Value::Array(
        ports
            .iter()
            .map(|p| {
                json!({"name": p.name, "kind": p.kind.to_string(), "doc": p.doc,
                       "optional": p.optional})
            })
            .collect(),
    )
}

/// A stage's self-description as JSON (`pipe describe --json ID`).
pub fn stage_json(x: &Registered) -> Value {
    let i = x.stage.info();
    json!({
        "id": i.id,
        "version": i.version,
        "origin": x.origin,
        "doc": i.doc,
        "params": i.params,
        "inputs": ports_json(&i.inputs),
        "outputs": ports_json(&i.outputs),
        "with_schema": object_schema(&i.params),
    })
}

/// Every stage and export format as JSON (`pipe describe --json` without an id).
pub fn registry_json(r: &Registry) -> Value {
    json!({
        "grainpipe_version": grainpipe_core::VERSION,
        "stages": r.stages().into_iter().map(stage_json).collect::<Vec<_>>(),
        "export_formats": r.exporters().iter().map(|e| json!({
            "name": e.name(), "extensions": e.extensions(), "doc": e.doc(),
            "options": e.options().iter().map(|o| json!({
                "name": o.name, "doc": o.doc, "default": o.default
            })).collect::<Vec<_>>(),
        })).collect::<Vec<_>>(),
    })
}

/// JSON Schema (draft 2020-12) of a pipeline file with the stages of this registry: editors
/// (VS Code's YAML extension, via `# yaml-language-server: $schema=...`) complete and check
/// `use:` ids and each stage's `with:` keys, types and defaults.
pub fn pipeline_schema(r: &Registry) -> Value {
    let ids: Vec<&str> = r.stages().iter().map(|x| x.stage.info().id).collect();
    let per_stage: Vec<Value> = r
        .stages()
        .iter()
        .map(|x| {
            let i = x.stage.info();
            json!({
                "if": {"properties": {"use": {"const": i.id}}, "required": ["use"]},
                "then": {"properties": {"with": object_schema(&i.params)}}
            })
        })
        .collect();
    let formats: Vec<&str> = r.exporters().iter().map(|e| e.name()).collect();
    json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "grainpipe pipeline",
        "type": "object",
        "required": ["name", "stages"],
        "additionalProperties": false,
        "properties": {
            "name": {"type": "string", "description": "pipeline name (recorded in every output)"},
            "description": {"type": "string"},
            "seed": {"type": "integer", "minimum": 0, "description": "pipeline seed; each step derives its own stream from it and its id"},
            "plugins": {"type": "array", "items": {"type": "string"}, "description": "plugin libraries or directories to load"},
            "reference": {
                "type": "object",
                "description": "published or independent values the results are compared with after the run (docs/report.md)",
                "required": ["source", "values"],
                "additionalProperties": false,
                "properties": {
                    "source": {"type": "string", "description": "where the values come from"},
                    "note": {"type": "string"},
                    "values": {"type": "array", "items": {
                        "type": "object",
                        "required": ["quantity", "value"],
                        "additionalProperties": false,
                        "properties": {
                            "quantity": {"type": "string", "description": "step.port.column, step.port.column[row], step.port[k] or step.port.<component>"},
                            "value": {"type": ["number", "string"], "description": "a number or a quantity with units"},
                            "tolerance": {"type": ["number", "string"], "description": "relative (10 %, 0.1) or in the value's unit"},
                            "range": {"type": "array", "minItems": 2, "maxItems": 2, "items": {"type": ["number", "string"]}, "description": "[lowest, highest] the result is judged against"}
                        }
                    }}
                }
            },
            "stages": {
                "type": "array",
                "items": {
                    "type": "object",
                    "required": ["id", "use"],
                    "additionalProperties": false,
                    "properties": {
                        "id": {"type": "string", "pattern": "^[^.]+$"},
                        "use": {"enum": ids},
                        "in": {"type": "object", "additionalProperties": {"type": "string"}},
                        "with": {"type": "object"}
                    },
                    "allOf": per_stage
                }
            },
            "export": {
                "type": "array",
                "items": {
                    "type": "object",
                    "required": ["from", "to"],
                    "additionalProperties": false,
                    "properties": {
                        "from": {"type": "string", "description": "step or step.port"},
                        "to": {"type": "string", "description": "output path; the extension selects the format"},
                        "format": {"enum": formats},
                        "with": {"type": "object", "description": "writer options of the format (`pipe describe FORMAT`)"}
                    }
                }
            }
        }
    })
}

/// The full description of a stage or export format; `Err` with suggestions if unknown.
pub fn describe(r: &Registry, id: &str) -> Result<String, String> {
    if let Some(x) = r.stage(id) {
        return Ok(describe_stage(x));
    }
    if let Some(e) = r.exporters().iter().find(|e| e.name() == id) {
        let mut text = format!(
            "export format `{}` ({})\n\n{}\n",
            e.name(),
            extensions(e.as_ref()),
            textwrap(e.doc(), 90)
        );
        let options = e.options();
        if !options.is_empty() {
            text.push_str("\nOptions (export `with:`):\n");
            for o in options {
                text.push_str(&format!(
                    "  {}  (default {})\n      {}\n",
                    o.name,
                    o.default,
                    textwrap(o.doc, 84).replace('\n', "\n      ")
                ));
            }
        }
        return Ok(text);
    }
    let hint = r
        .suggest_stage(id)
        .map(|s| format!("; did you mean `{s}`?"))
        .unwrap_or_default();
    Err(format!(
        "no stage or format `{id}`{hint} (`pipe list` shows all)"
    ))
}

/// What preflight announced about an output, in a line (`pipe validate`); `None` when
/// nothing beyond its kind is known.
pub fn announced(m: &grainpipe_core::ArtifactMeta) -> Option<String> {
    let mut parts = Vec::new();
    if let Some(g) = &m.grid {
        let per: String = ["x", "y", "z"]
            .iter()
            .zip(g.periodic)
            .filter(|(_, p)| *p)
            .map(|(a, _)| *a)
            .collect();
        parts.push(format!(
            "grid {}x{}x{} of {:.4} x {:.4} x {:.4} um{}",
            g.dims[0],
            g.dims[1],
            g.dims[2],
            g.spacing[0] * 1e6,
            g.spacing[1] * 1e6,
            g.spacing[2] * 1e6,
            if per.is_empty() {
                String::new()
            } else {
                format!(", periodic in {per}")
            }
        ));
    }
    if let Some((lo, hi)) = m.domain_box {
        parts.push(format!(
            "box {:.1} x {:.1} x {:.1} um",
            (hi[0] - lo[0]) * 1e6,
            (hi[1] - lo[1]) * 1e6,
            (hi[2] - lo[2]) * 1e6
        ));
    }
    if let (Some(p), None) = (m.periodic, &m.grid) {
        parts.push(format!("periodic {p:?}"));
    }
    match m.count_bounds {
        Some([1, 1]) => parts.push("1 item".to_string()),
        Some([lo, hi]) if lo == hi => parts.push(format!("{lo} items")),
        Some([lo, hi]) => parts.push(format!("{lo}..{hi} items")),
        None if m.count_estimate > 0 && m.grid.is_none() => {
            parts.push(format!("~{} items", m.count_estimate))
        }
        None => {}
    }
    (!parts.is_empty()).then(|| format!("{} ({})", m.kind, parts.join(", ")))
}
