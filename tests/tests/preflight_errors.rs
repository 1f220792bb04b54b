//! Preflight reports: the real line and column of malformed YAML, every independent fault of
//! a file at once, `--set` errors located in the override, overrides in the provenance, the
//! seed message, and an interrupted run that names its step.

use grainpipe_core::engine::{execute, plan, PlanOptions, RunOptions, SilentObserver};
use grainpipe_core::pipeline::{ErrorClass, PipelineDoc, PipelineError};
use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, InputMetas, Inputs, Outputs, PortSpec, Preflight,
    Registry, RunContext, StageError, StageInfo, Table, TypedStage,
};
use std::path::Path;

fn parse_err(yaml: &str) -> PipelineError {
    match PipelineDoc::parse(Path::new("p.yaml"), yaml.to_string()) {
        Ok(_) => panic!("parsed although malformed:\n{yaml}"),
        Err(e) => e,
    }
}

/// (line, column) of an error, and the text its byte span starts with.
fn place(e: &PipelineError, src: &str) -> (u64, u64, String) {
    let l = e.loc.unwrap_or_else(|| panic!("no location: {e}"));
    let rest: String = src[l.offset..].chars().take(8).collect();
    (l.line, l.col, rest)
}

fn plan_err(yaml: &str) -> PipelineError {
    let d = PipelineDoc::parse(Path::new("p.yaml"), yaml.to_string()).unwrap();
    match plan(&d, &registry(), &PlanOptions::default()) {
        Ok(_) => panic!("planned although wrong:\n{yaml}"),
        Err(e) => e,
    }
}

#[test]
fn malformed_yaml_is_reported_where_the_fault_is() {
    // A tab in the indentation of line 4 (YAML forbids tabs there).
    let tab = "name: t\nstages:\n  - id: a\n\tuse: packing.rsa\n";
    let e = parse_err(tab);
    let (line, col, at) = place(&e, tab);
    assert_eq!((line, col), (4, 1), "{e}");
    assert!(at.starts_with('\t'), "span starts at {at:?}: {e}");

    // An unclosed flow sequence: the scanner finds the fault where the next key's `:` is.
    let open = "name: t\nseed: 1\nstages:\n  - id: a\n    use: packing.rsa\n    with:\n      size: [400 um, 400 um\n      volume_fraction: 0.3\n";
    let e = parse_err(open);
    let l = e.loc.unwrap();
    assert!(l.line >= 7 && l.offset > 0, "{e}");

    // An unterminated quoted string runs to the end of the file.
    let quote = "name: t\nstages:\n  - id: a\n    use: \"packing.rsa\n";
    let e = parse_err(quote);
    assert!(e.loc.unwrap().line >= 4, "{e}");
    assert_ne!(e.loc.unwrap().offset, 0, "{e}");

    // A key at a wrong indentation.
    let indent = "name: t\nstages:\n  - id: a\n    use: packing.rsa\n   with: {}\n";
    let e = parse_err(indent);
    assert_eq!(e.loc.unwrap().line, 5, "{e}");
}

const FOUR_FAULTS: &str = "\
name: four
stages:
  - id: pack
    use: packing.rsaa
    with: { volume_fraction: 0.3 }
  - id: vox
    use: voxelize.packing
    in: { packing: pack.packing }
  - id: other
    use: packing.rsa
    with:
      size: [400 um, 400 um, 400 um]
      radius: { kind: fixed, value: 25 W }
  - id: third
    use: packing.rsa
    with: { volume_fractoin: 0.3 }
export:
  - { from: other.packing, to: out/x.vti }
";

#[test]
fn every_independent_fault_is_reported_with_its_line() {
    let e = plan_err(FOUR_FAULTS);
    let all: Vec<(u64, String)> = e
        .all()
        .map(|x| (x.loc.map_or(0, |l| l.line), x.message.clone()))
        .collect();
    let text = format!("{all:#?}");
    // The unknown stage (line 4), whose dependant `vox` adds no noise; the bad unit (13);
    // the unknown parameter (16); the export format that cannot hold a packing (18).
    assert_eq!(
        all.iter().map(|a| a.0).collect::<Vec<_>>(),
        vec![4, 13, 16, 18],
        "{text}"
    );
    assert!(all[0].1.contains("unknown stage `packing.rsaa`"), "{text}");
    assert!(all[1].1.contains("radius"), "{text}");
    assert!(all[2].1.contains("volume_fractoin"), "{text}");
    assert!(all[3].1.contains("cannot hold a Packing"), "{text}");
    assert_eq!(e.exit_code(), 2);
    // The rendered text names every place.
    let shown = e.to_string();
    for line in ["p.yaml:4:", "p.yaml:13:", "p.yaml:16:", "p.yaml:18:"] {
        assert!(shown.contains(line), "{line} missing in:\n{shown}");
    }
}

const GOOD: &str = "\
name: small
seed: 5
stages:
  - id: pack
    use: packing.rsa
    with:
      size: [200 um, 200 um, 200 um]
      radius: { kind: fixed, value: 25 um }
      volume_fraction: 0.1
export:
  - { from: pack.packing, to: out/p.prov }
";

/// Writes only the provenance an exporter receives, as a JSON object.
struct ProvenanceJson;
impl grainpipe_core::Exporter for ProvenanceJson {
    fn name(&self) -> &'static str {
        "provenance-json"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["prov"]
    }
    fn accepts(&self, _: ArtifactKind) -> bool {
        true
    }
    fn doc(&self) -> &'static str {
        "test: the provenance of an export"
    }
    fn write(
        &self,
        _: &Artifact,
        path: &Path,
        provenance: &grainpipe_core::Provenance,
        _options: &grainpipe_core::registry::ExportOptions,
    ) -> Result<(), String> {
        let v = serde_json::to_vec(&provenance.entries).map_err(|e| e.to_string())?;
        grainpipe_core::fsutil::atomic_write_bytes(path, &v)
    }
}

fn good_doc() -> PipelineDoc {
    PipelineDoc::parse(Path::new("p.yaml"), GOOD.to_string()).unwrap()
}

/// The built-in stages and formats plus the `.prov` test exporter GOOD writes to.
fn registry() -> grainpipe_core::Registry {
    let mut reg = grainpipe_cli::builtin_registry();
    reg.add_exporter(ProvenanceJson);
    reg
}

#[test]
fn a_wrong_override_key_points_at_the_override() {
    let mut d = good_doc();
    d.apply_override("pack.nonsense=3").unwrap();
    let e = plan(&d, &registry(), &PlanOptions::default())
        .err()
        .expect("unknown key refused");
    assert_eq!(e.file, Path::new("--set"), "{e}");
    let src = e.source_text.as_deref().expect("the override's text");
    assert_eq!(src, "pack.nonsense=3");
    let l = e.loc.unwrap();
    assert_eq!(&src[l.offset..l.offset + l.len], "nonsense", "{e}");
    assert_eq!(e.all().count(), 1, "{e}");
}

#[test]
fn a_bad_override_unit_points_at_the_override_value() {
    let mut d = good_doc();
    d.apply_override("pack.volume_fraction=3 um").unwrap();
    let e = plan(&d, &registry(), &PlanOptions::default())
        .err()
        .expect("a length for a fraction is refused");
    let src = e.source_text.as_deref().expect("the override's text");
    let l = e.loc.unwrap();
    assert_eq!(&src[l.offset..l.offset + l.len], "3 um", "{e}");
    assert_eq!(l.col, 22, "{e}");

    // Unknown step: located at the step name, with a suggestion.
    let e = good_doc().apply_override("pakc.radius=3 um").unwrap_err();
    let l = e.loc.unwrap();
    assert_eq!((l.offset, l.len), (0, 4), "{e}");
    assert_eq!(e.help.as_deref(), Some("did you mean `pack`?"));
}

#[test]
fn nested_override_replaces_one_field_of_a_mapping() {
    let mut d = good_doc();
    d.apply_override("pack.radius.value=30 um").unwrap();
    assert_eq!(
        d.steps[0].params["radius"],
        serde_json::json!({"kind": "fixed", "value": "30 um"})
    );
    let p = plan(&d, &registry(), &PlanOptions::default()).unwrap();
    let r = &p.steps[0].as_ref().unwrap().params["radius"]["value"];
    assert!((r.as_f64().unwrap() - 30e-6).abs() < 1e-15, "{r}");
    // A scalar parameter has no fields.
    let e = good_doc()
        .apply_override("pack.volume_fraction.value=0.2")
        .unwrap_err();
    assert!(e.message.contains("not a mapping"), "{e}");
    let l = e.loc.unwrap();
    assert_eq!(
        &e.source_text.as_deref().unwrap()[l.offset..l.offset + l.len],
        "pack.volume_fraction"
    );
}

#[test]
fn provenance_records_the_effective_yaml_and_the_overrides() {
    let dir = tempfile::tempdir().unwrap();
    let mut d = good_doc();
    d.redirect_exports(dir.path());
    d.apply_override("pack.volume_fraction=0.05").unwrap();
    d.seed = 9;
    let mut reg = grainpipe_cli::builtin_registry();
    reg.add_exporter(ProvenanceJson);
    let p = plan(&d, &reg, &PlanOptions::default()).unwrap();
    execute(&d, &p, &RunOptions { cache_dir: None }, &mut SilentObserver).unwrap();
    let text = std::fs::read_to_string(dir.path().join("p.prov")).unwrap();
    let prov: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(
        prov["overrides"], "--set pack.volume_fraction=0.05",
        "{prov}"
    );
    assert_eq!(
        prov["seed_override"], "--seed 9 (the file says 5)",
        "{prov}"
    );
    // The recorded YAML is what ran: parsed back, it has the override and the seed.
    let yaml = prov["pipeline_yaml"].as_str().unwrap();
    let back = PipelineDoc::parse(Path::new("back.yaml"), yaml.to_string()).unwrap();
    assert_eq!(back.seed, 9);
    assert_eq!(
        back.steps[0].params["volume_fraction"],
        serde_json::json!(0.05)
    );
    assert_eq!(
        back.steps[0].params["radius"],
        serde_json::json!({"kind": "fixed", "value": "25 um"})
    );
}

#[test]
fn a_seed_that_is_not_a_whole_number_is_explained() {
    for (seed, shown) in [("forty", "`forty`"), ("-3", "`-3`"), ("2.5", "`2.5`")] {
        let yaml = format!("name: t\nseed: {seed}\nstages:\n  - id: a\n    use: packing.rsa\n");
        let e = parse_err(&yaml);
        assert_eq!(
            e.message,
            format!("seed must be a whole number between 0 and 2^64-1, not {shown}")
        );
        assert_eq!(e.loc.map(|l| (l.line, l.col)), Some((2, 7)), "{e}");
    }
    let max = "name: t\nseed: 18446744073709551615\nstages:\n  - id: a\n    use: packing.rsa\n";
    let d = PipelineDoc::parse(Path::new("p.yaml"), max.into()).unwrap();
    assert_eq!(d.seed, u64::MAX);
}

#[params]
struct StopParams {
    /// Whether this step stops as if the user pressed Ctrl-C.
    cancel: bool,
}

/// One-row table, or the cancellation a stage returns when its reporter says so.
struct Stops;
impl TypedStage for Stops {
    type Params = StopParams;
    type Plan = ();
    fn info(&self) -> StageInfo {
        StageInfo::new("test.stops", "1", "stops on request").outputs(vec![PortSpec::new(
            "table",
            ArtifactKind::Table,
            "a row",
        )])
    }
    fn preflight(&self, _: &StopParams, _: &InputMetas) -> Result<Preflight, StageError> {
        Ok(Preflight::from_info(&self.info(), 8)
            .announce("table", ArtifactMeta::of(ArtifactKind::Table)))
    }
    fn run(
        &self,
        p: &StopParams,
        _: &(),
        _: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        if p.cancel {
            return Err(StageError::Cancelled);
        }
        let mut o = Outputs::new();
        o.insert(
            "table".into(),
            Artifact::Table(Table::new("t").with_f64("x", "1", vec![1.0])),
        );
        Ok(o)
    }
}

#[test]
fn an_interrupted_run_names_its_step_and_keeps_what_finished() {
    let yaml = "name: h\nstages:\n  - id: first\n    use: test.stops\n    with: { cancel: false }\n  - id: second\n    use: test.stops\n    with: { cancel: true }\n";
    let d = PipelineDoc::parse(Path::new("h.yaml"), yaml.into()).unwrap();
    let mut reg = Registry::new();
    reg.add_stage(Stops);
    let p = plan(&d, &reg, &PlanOptions::default()).unwrap();
    let cache = tempfile::tempdir().unwrap();
    let e = execute(
        &d,
        &p,
        &RunOptions {
            cache_dir: Some(cache.path().to_path_buf()),
        },
        &mut SilentObserver,
    )
    .err()
    .expect("cancelled");
    assert_eq!((e.class, e.exit_code()), (ErrorClass::Interrupted, 130));
    assert!(
        e.loc.is_none(),
        "no YAML snippet for an interruption: {e:?}"
    );
    assert!(
        e.message
            .starts_with("interrupted during step `second` after "),
        "{e}"
    );
    // The step that finished is in the cache, under its key, written by `first`.
    let entries = grainpipe_core::cache::entries(cache.path()).unwrap();
    assert_eq!(entries.len(), 1);
    assert_eq!(entries[0].key, p.steps[0].as_ref().unwrap().cache_key);
    assert_eq!(entries[0].header.as_ref().unwrap().step, "first");
}
