//! `png` exporter: a top view (x-y) of a contact graph, drawn with plotters' bitmap backend
//! (no text, so no system fonts are needed). Particles are circles at their positions
//! (filled when bonded), bonds are lines between centres.

use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::model::{Artifact, ArtifactKind, ContactGraph, Provenance};
use grainpipe_core::Exporter;
use plotters::prelude::*;
use std::path::Path;

pub struct BondGraphPng;

/// Longest image side [px].
const SIZE: u32 = 1600;
const MARGIN: u32 = 20;

/// Image size and the map from world x-y [m] to pixels (y up).
pub struct View {
    pub width: u32,
    pub height: u32,
    lo: [f64; 2],
    scale: f64,
}

impl View {
    pub fn new(g: &ContactGraph) -> View {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in &g.positions {
            for a in 0..2 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let ext = [0, 1].map(|a| (hi[a] - lo[a]).max(1e-12));
        let inner = (SIZE - 2 * MARGIN) as f64;
        let scale = inner / ext[0].max(ext[1]);
        View {
            width: (ext[0] * scale).ceil() as u32 + 2 * MARGIN,
            height: (ext[1] * scale).ceil() as u32 + 2 * MARGIN,
            lo,
            scale,
        }
    }

    pub fn pixel(&self, p: [f64; 3]) -> (i32, i32) {
        let x = MARGIN as f64 + (p[0] - self.lo[0]) * self.scale;
        let y = self.height as f64 - MARGIN as f64 - (p[1] - self.lo[1]) * self.scale;
        (x.round() as i32, y.round() as i32)
    }
}

/// Particle radius in pixels: half the median centre distance of contacting pairs (the
/// graph carries no radii), at least one pixel.
fn marker_radius(g: &ContactGraph, view: &View) -> i32 {
    let mut d: Vec<f64> = g
        .contacts
        .iter()
        .filter(|c| c.i < g.positions.len() && c.j < g.positions.len())
        .map(|c| {
            let (a, b) = (g.positions[c.i], g.positions[c.j]);
            ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
        })
        .collect();
    if d.is_empty() {
        return 2;
    }
    d.sort_by(f64::total_cmp);
    ((0.5 * d[d.len() / 2] * view.scale).round() as i32).max(1)
}

/// Renders the top view into an RGB buffer.
pub fn render(g: &ContactGraph) -> Result<(u32, u32, Vec<u8>), String> {
    if g.positions.is_empty() {
        return Err("the contact graph has no positions to draw".into());
    }
    let n = g.positions.len();
    if let Some(b) = g.bonds.iter().find(|b| b[0] >= n || b[1] >= n) {
        return Err(format!(
            "bond ({}, {}) refers past {n} positions",
            b[0], b[1]
        ));
    }
    let view = View::new(g);
    let (w, h) = (view.width, view.height);
    let mut buf = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        let e = |e: DrawingAreaErrorKind<_>| e.to_string();
        root.fill(&WHITE).map_err(e)?;
        let r = marker_radius(g, &view);
        let mut bonded = vec![false; n];
        for b in &g.bonds {
            bonded[b[0]] = true;
            bonded[b[1]] = true;
        }
        let grey = RGBColor(150, 150, 150);
        let orange = RGBColor(230, 120, 30);
        for (i, p) in g.positions.iter().enumerate() {
            let c = view.pixel(*p);
            let style = if bonded[i] {
                orange.filled()
            } else {
                grey.stroke_width(1)
            };
            root.draw(&Circle::new(c, r, style)).map_err(e)?;
        }
        for b in &g.bonds {
            let (a, c) = (view.pixel(g.positions[b[0]]), view.pixel(g.positions[b[1]]));
            root.draw(&PathElement::new(vec![a, c], BLACK.stroke_width(2)))
                .map_err(e)?;
        }
        root.present().map_err(e)?;
    }
    Ok((w, h, buf))
}

impl Exporter for BondGraphPng {
    fn name(&self) -> &'static str {
        "png"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["png"]
    }
    fn accepts(&self, kind: ArtifactKind) -> bool {
        kind == ArtifactKind::ContactGraph
    }
    fn doc(&self) -> &'static str {
        "top view (x-y) of a contact graph: particles as circles (filled orange when bonded), \
         bonds as black lines; PNG, 1600 px on the longer side"
    }
    fn write(
        &self,
        artifact: &Artifact,
        path: &Path,
        provenance: &Provenance,
    ) -> Result<(), String> {
        let g = artifact
            .as_contact_graph()
            .ok_or_else(|| format!("png exports a ContactGraph, got a {}", artifact.kind()))?;
        let (w, h, buf) = render(g)?;
        if buf.len() != (w as usize) * (h as usize) * 3 {
            return Err("image buffer size mismatch".into());
        }
        atomic_write(path, |tmp| -> Result<(), String> {
            let file = std::fs::File::create(tmp).map_err(|e| e.to_string())?;
            let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            // Provenance as text chunks, as every exported file carries it: iTXt, since
            // values (the pipeline YAML, paths) may hold characters outside Latin-1.
            for (k, v) in &provenance.entries {
                let keyword: String = k
                    .chars()
                    .filter(|c| c.is_ascii_graphic())
                    .take(79)
                    .collect();
                if !keyword.is_empty() {
                    enc.add_itxt_chunk(keyword, v.clone())
                        .map_err(|e| e.to_string())?;
                }
            }
            let mut writer = enc.write_header().map_err(|e| e.to_string())?;
            writer.write_image_data(&buf).map_err(|e| e.to_string())?;
            writer.finish().map_err(|e| e.to_string())
        })
    }
}
