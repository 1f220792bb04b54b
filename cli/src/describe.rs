//! `pipe list` and `pipe describe`: text generated from the registry, so the README's stage
//! list (made with `pipe list --markdown`) cannot drift from the code.

use grainpipe_core::registry::Registered;
use grainpipe_core::Registry;
use std::fmt::Write;

/// First sentence of a doc paragraph: up to the first ". " followed by a capital letter that
/// does not end an abbreviation ("et al.", "e.g.", "eq.").
fn summary(doc: &str) -> &str {
    const ABBREVIATIONS: [&str; 6] = ["al", "e.g", "i.e", "eq", "cf", "Fig"];
    for (i, _) in doc.match_indices(". ") {
        let next_is_capital = doc[i + 2..].chars().next().is_some_and(char::is_uppercase);
        let word = doc[..i].rsplit(' ').next().unwrap_or("");
        if next_is_capital && !ABBREVIATIONS.contains(&word) {
            return &doc[..=i];
        }
    }
    doc.trim_end()
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

/// One line per stage (id, version, origin, summary) and the export formats.
pub fn list_text(r: &Registry) -> String {
    let mut s = String::new();
    let width = r
        .stages()
        .iter()
        .map(|x| x.stage.info().id.len())
        .max()
        .unwrap_or(10);
    writeln!(s, "Stages ({}):", r.stages().len()).unwrap();
    for x in r.stages() {
        let i = x.stage.info();
        writeln!(
            s,
            "  {:width$}  {:7}  {}  [{}]",
            i.id,
            i.version,
            summary(i.doc),
            x.origin
        )
        .unwrap();
    }
    writeln!(s, "\nExport formats:").unwrap();
    for e in r.exporters() {
        writeln!(
            s,
            "  {:10} {:15} {}",
            e.name(),
            extensions(e.as_ref()),
            e.doc()
        )
        .unwrap();
    }
    s.push_str("\n`pipe describe <stage id>` shows parameters, defaults, units and ports.\n");
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
        let unit = if p.unit.is_empty() || p.unit == "1" {
            String::new()
        } else {
            format!(" [{}]", p.unit)
        };
        writeln!(s, "  {}: {}{}  (default {})", p.name, p.ty, unit, d).unwrap();
        writeln!(s, "      {}", p.doc).unwrap();
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

/// The full description of a stage or export format; `Err` with suggestions if unknown.
pub fn describe(r: &Registry, id: &str) -> Result<String, String> {
    if let Some(x) = r.stage(id) {
        return Ok(describe_stage(x));
    }
    if let Some(e) = r.exporters().iter().find(|e| e.name() == id) {
        return Ok(format!(
            "export format `{}` ({})\n\n{}\n",
            e.name(),
            extensions(e.as_ref()),
            e.doc()
        ));
    }
    let hint = r
        .suggest_stage(id)
        .map(|s| format!("; did you mean `{s}`?"))
        .unwrap_or_default();
    Err(format!(
        "no stage or format `{id}`{hint} (`pipe list` shows all)"
    ))
}
