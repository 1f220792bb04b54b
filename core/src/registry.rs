//! The registry of stages and exporters. Each plugin crate fills it in its
//! `register(&mut Registry)`; the core knows no plugin by name.

use crate::model::{Artifact, ArtifactKind, ArtifactMeta, Provenance};
use crate::params::RUST_TYPE_WORDS;
use crate::stage::{Stage, Typed, TypedStage};
pub use crate::suggest::closest;
use indexmap::IndexMap;
use std::path::Path;
use std::sync::Arc;

/// One option of an exporter, written under an export's `with:` (e.g. `compression: 0`).
#[derive(Clone, Debug)]
pub struct ExportOption {
    pub name: &'static str,
    /// Shown by `pipe describe FORMAT`.
    pub doc: &'static str,
    /// The value used when the export does not set the option.
    pub default: serde_json::Value,
}

/// The options an export passes to its writer: every declared option, the export's value
/// or else the declared default.
pub type ExportOptions = serde_json::Map<String, serde_json::Value>;

/// One file or directory an export writes: the target itself, or a file written beside it
/// (the `.raw` of a `.mhd`, a `.csv.json` sidecar), or a directory replaced as a whole (the
/// slices of a TIFF directory stack). The engine compares these, normalised, across every
/// export of a pipeline at preflight, so two exports never write the same file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WrittenPath {
    pub path: std::path::PathBuf,
    /// A directory the export replaces as a whole: no other export may write into it.
    pub directory: bool,
}

impl WrittenPath {
    pub fn file(path: impl Into<std::path::PathBuf>) -> Self {
        WrittenPath {
            path: path.into(),
            directory: false,
        }
    }
    pub fn directory(path: impl Into<std::path::PathBuf>) -> Self {
        WrittenPath {
            path: path.into(),
            directory: true,
        }
    }
}

/// Peak memory of an exporter that builds its whole file in memory before writing it: about
/// twice the artifact's size (the encoded copy and the compressed/encoded text), from what
/// preflight announced. Voxel artifacts count 1 byte per voxel for images and 8 per value
/// for fields; other kinds 256 bytes per item.
pub fn in_memory_export_bytes(meta: &ArtifactMeta) -> u64 {
    let per_item: u64 = match meta.kind {
        ArtifactKind::PhaseImage => 2,
        ArtifactKind::Field => 16,
        _ => 512,
    };
    let items = match &meta.grid {
        Some(g) => g.checked_voxel_count().map_or(u64::MAX, |n| n as u64),
        None => meta.count_estimate,
    };
    items.saturating_mul(per_item)
}

/// Writes artifacts of some kinds to one file format.
pub trait Exporter: Send + Sync {
    /// Format name as written in YAML `format:` (e.g. `vti`, `vtkhdf`, `h5`, `nc`, `csv`).
    fn name(&self) -> &'static str;
    /// File extensions (without dot) that select this exporter when `format:` is omitted.
    fn extensions(&self) -> &'static [&'static str];
    fn accepts(&self, kind: ArtifactKind) -> bool;
    fn doc(&self) -> &'static str;
    /// The options this format takes under an export's `with:`; none by default.
    fn options(&self) -> Vec<ExportOption> {
        Vec::new()
    }
    /// Checks option values at preflight (before any step runs). `options` holds every
    /// declared option (defaults filled in). On error: the offending option and why.
    fn check_options(&self, _options: &ExportOptions) -> Result<(), (String, String)> {
        Ok(())
    }
    /// Checks an export against what preflight knows of the artifact (its announced
    /// [`ArtifactMeta`]: kind, grid, phase table, counts) and returns the memory the write
    /// needs beyond the artifact itself [bytes], which the engine adds to the producing
    /// step's estimate. On error: the option (or `to` when no option is at fault) and why.
    /// By default nothing is checked and the memory is [`Exporter::memory_bytes`].
    fn preflight(
        &self,
        meta: &crate::model::ArtifactMeta,
        options: &ExportOptions,
    ) -> Result<u64, (String, String)> {
        Ok(self.memory_bytes(meta, options))
    }
    /// Writes atomically: a crash never leaves a partial file at `path`. `options` holds
    /// every declared option, the export's value or else the default (the engine fills it;
    /// other callers pass [`Exporter::default_options`] or use [`Exporter::write_defaults`]).
    fn write(
        &self,
        artifact: &Artifact,
        path: &Path,
        provenance: &Provenance,
        options: &ExportOptions,
    ) -> Result<(), String>;
    /// Every file and directory an export to `path` with `options` writes, the target
    /// included (by default: the target alone). Formats that write beside the target (a
    /// `.raw` next to a `.mhd`, a `.csv.json` sidecar, a directory of slices) list those too,
    /// so that preflight can refuse two exports writing one file.
    fn written_paths(&self, path: &Path, _options: &ExportOptions) -> Vec<WrittenPath> {
        vec![WrittenPath::file(path)]
    }
    /// Peak memory [bytes] of writing an artifact that preflight announced as `meta`, beyond
    /// the artifact itself; part of the pipeline's memory estimate. By default the size of a
    /// file built in memory ([`in_memory_export_bytes`]); formats that stream say less.
    fn memory_bytes(&self, meta: &ArtifactMeta, _options: &ExportOptions) -> u64 {
        in_memory_export_bytes(meta)
    }
    /// Every declared option at its default: what an export without `with:` gets.
    fn default_options(&self) -> ExportOptions {
        self.options()
            .into_iter()
            .map(|o| (o.name.to_string(), o.default))
            .collect()
    }
    /// [`Exporter::write`] with every option at its default.
    fn write_defaults(
        &self,
        artifact: &Artifact,
        path: &Path,
        provenance: &Provenance,
    ) -> Result<(), String> {
        self.write(artifact, path, provenance, &self.default_options())
    }
}

/// A stage with where it came from (`built-in` or a plugin library path).
#[derive(Clone)]
pub struct Registered {
    pub stage: Arc<dyn Stage>,
    pub origin: String,
}

#[derive(Default)]
pub struct Registry {
    stages: IndexMap<String, Registered>,
    exporters: Vec<Arc<dyn Exporter>>,
    origin: Option<String>,
}

impl Registry {
    pub fn new() -> Self {
        Self::default()
    }

    /// Sets the origin recorded for stages added from now on (plugin loaders use this).
    pub fn set_origin(&mut self, origin: Option<String>) {
        self.origin = origin;
    }

    pub fn add_stage<T: TypedStage>(&mut self, stage: T) {
        self.add_dyn_stage(Arc::new(Typed::new(stage)));
    }

    /// Adds a stage. Panics on a duplicate id: two plugins claiming one id is a packaging
    /// bug that must not be resolved silently by load order.
    pub fn add_dyn_stage(&mut self, stage: Arc<dyn Stage>) {
        let id = stage.info().id.to_string();
        let origin = self
            .origin
            .clone()
            .unwrap_or_else(|| "built-in".to_string());
        if let Some(prev) = self.stages.get(&id) {
            panic!(
                "stage `{id}` registered twice ({} and {origin})",
                prev.origin
            );
        }
        self.stages.insert(id, Registered { stage, origin });
    }

    /// Like [`Registry::add_dyn_stage`] but returns an error on a duplicate id.
    pub fn try_add_dyn_stage(&mut self, stage: Arc<dyn Stage>) -> Result<(), String> {
        let id = stage.info().id;
        if let Some(prev) = self.stages.get(id) {
            return Err(format!(
                "stage `{id}` is already provided by {}",
                prev.origin
            ));
        }
        self.add_dyn_stage(stage);
        Ok(())
    }

    pub fn add_exporter(&mut self, exporter: impl Exporter + 'static) {
        self.exporters.push(Arc::new(exporter));
    }

    pub fn stage(&self, id: &str) -> Option<&Registered> {
        self.stages.get(id)
    }

    /// Stages sorted by id.
    pub fn stages(&self) -> Vec<&Registered> {
        let mut v: Vec<_> = self.stages.values().collect();
        v.sort_by_key(|r| r.stage.info().id);
        v
    }

    pub fn exporters(&self) -> &[Arc<dyn Exporter>] {
        &self.exporters
    }

    /// The exporter for an explicit format name, or else for the path's extension, preferring
    /// one that accepts `kind`: several plugins may claim one extension (`png` for a contact
    /// graph and for a table), and registration order must not decide which of them writes a
    /// given artifact. When none of the matching exporters accepts `kind`, the first match is
    /// returned, so the caller can say which format was picked and that it cannot hold the
    /// artifact.
    pub fn exporter_for(
        &self,
        format: Option<&str>,
        path: &Path,
        kind: ArtifactKind,
    ) -> Option<Arc<dyn Exporter>> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase());
        let matches = |e: &Arc<dyn Exporter>| match format {
            Some(f) => e.name() == f,
            None => ext.as_deref().is_some_and(|x| e.extensions().contains(&x)),
        };
        self.exporters
            .iter()
            .find(|e| matches(e) && e.accepts(kind))
            .or_else(|| self.exporters.iter().find(|e| matches(e)))
            .cloned()
    }

    /// The closest known stage id, for "did you mean" messages.
    pub fn suggest_stage(&self, id: &str) -> Option<String> {
        closest(id, self.stages.keys().map(|s| s.as_str()))
    }

    /// Checks that export format names are unique, and every stage's self-description, so
    /// `pipe describe`, the JSON Schema and the parameters a stage accepts cannot drift
    /// apart: ids of the form `<family>.<name>`;
    /// parameter names unique, each documented, with a type in words (no Rust type names) and
    /// a unit that parses; the declared parameters are exactly the default struct's keys; the
    /// defaults normalize; port names unique.
    pub fn check_consistency(&self) -> Result<(), String> {
        // `format:` selects by name, so a second exporter of one name could never be chosen.
        for (n, e) in self.exporters.iter().enumerate() {
            if self.exporters[..n].iter().any(|f| f.name() == e.name()) {
                return Err(format!("export format `{}` is registered twice", e.name()));
            }
        }
        for r in self.stages.values() {
            let info = r.stage.info();
            let id = info.id;
            let (family, name) = id
                .split_once('.')
                .ok_or_else(|| format!("{id}: stage ids are `<family>.<name>`"))?;
            if family.is_empty() || name.is_empty() || name.contains('.') {
                return Err(format!("{id}: stage ids are `<family>.<name>`"));
            }
            if info.doc.trim().is_empty() {
                return Err(format!("{id}: the stage has no doc"));
            }
            let defaults = r.stage.default_params();
            let keys: Vec<&str> = defaults
                .as_object()
                .map(|m| m.keys().map(|k| k.as_str()).collect())
                .unwrap_or_default();
            for (n, p) in info.params.iter().enumerate() {
                if info.params[..n].iter().any(|q| q.name == p.name) {
                    return Err(format!("{id}: parameter `{}` is declared twice", p.name));
                }
                if !keys.contains(&p.name) {
                    return Err(format!(
                        "{id}: declared parameter `{}` is not a field",
                        p.name
                    ));
                }
                if p.doc.trim().is_empty() {
                    return Err(format!("{id}: parameter `{}` has no doc", p.name));
                }
                if p.ty.is_empty() || RUST_TYPE_WORDS.iter().any(|w| p.ty.contains(w)) {
                    return Err(format!(
                        "{id}: parameter `{}` has type `{}`; describe the value in words",
                        p.name, p.ty
                    ));
                }
                if !p.unit.is_empty() {
                    crate::units::parse_unit(&p.unit)
                        .map_err(|e| format!("{id}: parameter `{}`: {e}", p.name))?;
                }
            }
            for k in &keys {
                if !info.params.iter().any(|p| p.name == *k) {
                    return Err(format!("{id}: field `{k}` is not declared"));
                }
            }
            for ports in [&info.inputs, &info.outputs] {
                for (n, p) in ports.iter().enumerate() {
                    if ports[..n].iter().any(|q| q.name == p.name) {
                        return Err(format!("{id}: port `{}` is declared twice", p.name));
                    }
                }
            }
            let normalized = r
                .stage
                .normalize_params(&serde_json::json!({}))
                .map_err(|e| format!("{id}: defaults do not parse: {e}"))?;
            // What a run with no `with:` uses must be what `pipe describe` shows.
            for p in &info.params {
                if normalized.get(p.name) != Some(&p.default) {
                    return Err(format!(
                        "{id}: parameter `{}` is documented with default {} but an empty \
                         `with:` gives {}",
                        p.name,
                        p.default,
                        normalized.get(p.name).unwrap_or(&serde_json::Value::Null)
                    ));
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An exporter that writes nothing, claiming `ext` for one artifact kind.
    struct Fake(&'static str, &'static [&'static str], ArtifactKind);

    impl Exporter for Fake {
        fn name(&self) -> &'static str {
            self.0
        }
        fn extensions(&self) -> &'static [&'static str] {
            self.1
        }
        fn accepts(&self, kind: ArtifactKind) -> bool {
            kind == self.2
        }
        fn doc(&self) -> &'static str {
            "test"
        }
        fn write(
            &self,
            _: &Artifact,
            _: &Path,
            _: &Provenance,
            _: &ExportOptions,
        ) -> Result<(), String> {
            Ok(())
        }
    }

    fn two_png_exporters() -> Registry {
        let mut r = Registry::new();
        r.add_exporter(Fake("png", &["png"], ArtifactKind::ContactGraph));
        r.add_exporter(Fake("pdf-png", &["png"], ArtifactKind::Table));
        r
    }

    #[test]
    fn extension_shared_by_two_exporters_is_resolved_by_artifact_kind() {
        let r = two_png_exporters();
        let p = Path::new("out/x.PNG");
        let name = |k| r.exporter_for(None, p, k).map(|e| e.name());
        assert_eq!(name(ArtifactKind::ContactGraph), Some("png"));
        assert_eq!(name(ArtifactKind::Table), Some("pdf-png"));
        // No taker: the first match, so the error can name the format that was picked.
        assert_eq!(name(ArtifactKind::Field), Some("png"));
        assert!(r
            .exporter_for(None, Path::new("x.vti"), ArtifactKind::Table)
            .is_none());
        assert!(r
            .exporter_for(None, Path::new("png"), ArtifactKind::Table)
            .is_none());
    }

    #[test]
    fn explicit_format_wins_over_extension_and_kind() {
        let r = two_png_exporters();
        let by = |f, k| {
            r.exporter_for(Some(f), Path::new("x.dat"), k)
                .map(|e| e.name())
        };
        assert_eq!(by("pdf-png", ArtifactKind::Table), Some("pdf-png"));
        // The named format even when it cannot hold the kind (the caller reports it).
        assert_eq!(by("png", ArtifactKind::Table), Some("png"));
        assert_eq!(by("tiff", ArtifactKind::Table), None);
    }

    #[test]
    fn duplicate_export_format_names_are_inconsistent() {
        let mut r = two_png_exporters();
        assert!(r.check_consistency().is_ok());
        r.add_exporter(Fake("png", &["png"], ArtifactKind::Field));
        let e = r.check_consistency().unwrap_err();
        assert!(e.contains("`png` is registered twice"), "{e}");
    }
}
