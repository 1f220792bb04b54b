//! The `html` export format: one self-contained page for any single artifact.

use crate::html::{self, esc};
use crate::page::{item_html, Pics};
use grainpipe_core::model::{Artifact, ArtifactKind, Provenance};
use grainpipe_core::registry::Exporter;
use std::fmt::Write;
use std::path::Path;

pub struct HtmlExporter;

/// The page of one artifact; `source` names it (e.g. `binder.image`).
pub fn artifact_page(source: &str, a: &Artifact, prov: &Provenance) -> String {
    let mut pics = Vec::new();
    let item = crate::data::item(source, a, &mut pics);
    let pics: Pics = pics.into_iter().collect();
    let mut body = format!(
        "<header id=\"top\"><h1>{} <span class=\"note\">({})</span></h1>",
        esc(source),
        a.kind()
    );
    if let Some(p) = prov.entries.get("pipeline_name") {
        let _ = write!(
            body,
            "<p>From pipeline <b>{}</b> ({}), seed {}.</p>",
            esc(p),
            esc(prov
                .entries
                .get("pipeline_file")
                .map(String::as_str)
                .unwrap_or("")),
            esc(prov.entries.get("seed").map(String::as_str).unwrap_or(""))
        );
    }
    body.push_str("</header>");
    let _ = write!(
        body,
        "<section id=\"artifact\">{}</section>",
        item_html(&item, &pics)
    );
    let mut rows = String::new();
    for (k, v) in &prov.entries {
        if k == "pipeline_yaml" {
            continue;
        }
        let _ = write!(
            rows,
            "<tr><th>{}</th><td class=\"l\">{}</td></tr>",
            esc(k),
            esc(v)
        );
    }
    let _ = write!(
        body,
        "<section id=\"provenance\"><h2>Provenance</h2><details><summary>where this artifact \
         comes from</summary><table class=\"kv\"><tbody>{rows}</tbody></table>{}</details></section>",
        prov.entries
            .get("pipeline_yaml")
            .map(|y| format!("<h4>Pipeline</h4><pre>{}</pre>", esc(y)))
            .unwrap_or_default()
    );
    html::page(&format!("{source} — grainpipe"), &body)
}

impl Exporter for HtmlExporter {
    fn name(&self) -> &'static str {
        "html"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["html", "htm"]
    }
    fn accepts(&self, _kind: ArtifactKind) -> bool {
        true
    }
    fn doc(&self) -> &'static str {
        "One self-contained HTML page (no network) showing the artifact for a person: phase \
         images as x-y, x-z and y-z mid-plane slices with a phase legend and fractions; fields \
         as slices of their magnitude (von Mises for stresses) with a colour bar; packings \
         rendered from the top and the side with their size distribution; tables; tensors as \
         matrices with symmetry error (and engineering constants for a 6x6 stiffness); \
         collections member by member. PNGs are embedded as data URIs; the provenance is in a \
         <details> block. For the report of a whole run see `pipe report`."
    }
    fn write(
        &self,
        artifact: &Artifact,
        path: &Path,
        provenance: &Provenance,
        _options: &grainpipe_core::registry::ExportOptions,
    ) -> Result<(), String> {
        let source = provenance
            .entries
            .get("step")
            .cloned()
            .unwrap_or_else(|| artifact.kind().to_string());
        let page = artifact_page(&source, artifact, provenance);
        grainpipe_core::fsutil::atomic_write_bytes(path, page.as_bytes())
    }
}
