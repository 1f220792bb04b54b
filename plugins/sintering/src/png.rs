//! `png` exporter: a top view (x-y) of a contact graph, drawn with plotters' bitmap backend.
//! Particles are circles at their positions (filled when bonded), bonds are lines between
//! centres, coloured by when they formed when the graph says so. A band below the view holds
//! a scale bar and the colour legend; their text needs a TrueType font from the system
//! (DejaVu Sans or Liberation Sans) and is left out without one. The file is written
//! palette-indexed (8 bit) at the strongest deflate level.

use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::model::{Artifact, ArtifactKind, ContactGraph, Provenance};
use grainpipe_core::Exporter;
use plotters::prelude::*;
use std::path::Path;

pub struct BondGraphPng;

/// Longest side of the view [px].
const SIZE: u32 = 1600;
const MARGIN: u32 = 20;
/// Height of the legend band below the view [px].
pub const LEGEND: u32 = 80;

/// The system font of every grainpipe chart (grainpipe-charts registers it once); false
/// when none is installed.
fn font_available() -> bool {
    grainpipe_charts::style::font_available()
}

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
            height: (ext[1] * scale).ceil() as u32 + 2 * MARGIN + LEGEND,
            lo,
            scale,
        }
    }

    /// Edge of one pixel in the world [m].
    pub fn pixel_size(&self) -> f64 {
        1.0 / self.scale
    }

    pub fn pixel(&self, p: [f64; 3]) -> (i32, i32) {
        let x = MARGIN as f64 + (p[0] - self.lo[0]) * self.scale;
        let y = (self.height - MARGIN - LEGEND) as f64 - (p[1] - self.lo[1]) * self.scale;
        (x.round() as i32, y.round() as i32)
    }
}

/// The scale bar: a round length (1, 2 or 5 times a power of ten) near a fifth of the view's
/// width, drawn from (`x`, `y`) to the right over `pixels` pixels (3 rows thick, centred on
/// `y`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScaleBar {
    /// Length in the world [m].
    pub length: f64,
    pub pixels: u32,
    pub x: i32,
    pub y: i32,
}

impl ScaleBar {
    pub fn new(view: &View) -> ScaleBar {
        let target = 0.2 * (view.width - 2 * MARGIN) as f64 * view.pixel_size();
        let decade = 10f64.powf(target.log10().floor());
        let length = [5.0, 2.0, 1.0]
            .into_iter()
            .map(|m| m * decade)
            .find(|&l| l <= target)
            .unwrap_or(decade);
        ScaleBar {
            length,
            pixels: (length / view.pixel_size()).round() as u32,
            x: MARGIN as i32,
            y: (view.height - LEGEND + 25) as i32,
        }
    }

    /// The length in micrometres, as printed.
    pub fn label(&self) -> String {
        format!("{} µm", fmt_round(self.length * 1e6))
    }
}

fn fmt_round(v: f64) -> String {
    if v >= 1.0 && v.fract() == 0.0 {
        format!("{v:.0}")
    } else {
        format!("{v}")
    }
}

/// Eight steps of a perceptually ordered colour map (viridis), early to late.
const RAMP: [RGBColor; 8] = [
    RGBColor(68, 1, 84),
    RGBColor(70, 50, 126),
    RGBColor(54, 92, 141),
    RGBColor(39, 127, 142),
    RGBColor(31, 161, 135),
    RGBColor(74, 193, 109),
    RGBColor(160, 218, 57),
    RGBColor(253, 231, 37),
];

/// Bond colours by formation time [s] when the graph carries one per bond (with a spread),
/// with the time range; black otherwise.
fn bond_colours(g: &ContactGraph) -> (Vec<RGBColor>, Option<(f64, f64)>) {
    let times = g
        .bond_attributes
        .get("bond_time")
        .map(|a| &a.values)
        .filter(|v| v.len() == g.bonds.len() && v.iter().all(|t| t.is_finite()));
    let Some(times) = times else {
        return (vec![BLACK; g.bonds.len()], None);
    };
    let lo = times.iter().cloned().fold(f64::INFINITY, f64::min);
    let hi = times.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    // finite times (filtered above) or none: lo = inf > hi = -inf, so no NaN here
    if hi <= lo {
        return (vec![BLACK; g.bonds.len()], None);
    }
    let step = |t: f64| (((t - lo) / (hi - lo) * RAMP.len() as f64) as usize).min(RAMP.len() - 1);
    (
        times.iter().map(|&t| RAMP[step(t)]).collect(),
        Some((lo, hi)),
    )
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

const GREY: RGBColor = RGBColor(150, 150, 150);
const ORANGE: RGBColor = RGBColor(230, 120, 30);

/// Renders the top view and its legend into an RGB buffer.
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
        for (i, p) in g.positions.iter().enumerate() {
            let c = view.pixel(*p);
            let style = if bonded[i] {
                ORANGE.filled()
            } else {
                GREY.stroke_width(1)
            };
            root.draw(&Circle::new(c, r, style)).map_err(e)?;
        }
        let (colours, range) = bond_colours(g);
        for (b, colour) in g.bonds.iter().zip(&colours) {
            let (a, c) = (view.pixel(g.positions[b[0]]), view.pixel(g.positions[b[1]]));
            root.draw(&PathElement::new(vec![a, c], colour.stroke_width(2)))
                .map_err(e)?;
        }
        legend(&root, &view, range).map_err(e)?;
        root.present().map_err(e)?;
    }
    Ok((w, h, buf))
}

/// The band below the view: scale bar, particle keys and, for coloured bonds, the colour
/// steps with the bond time range in ms.
fn legend<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    view: &View,
    range: Option<(f64, f64)>,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let text = font_available();
    let font = (grainpipe_charts::style::FONT, 18)
        .into_font()
        .color(&BLACK);
    let label = |s: &str, at: (i32, i32)| -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        if text {
            root.draw(&Text::new(s.to_string(), at, font.clone()))?;
        }
        Ok(())
    };
    // Markers near the bottom edge may reach into the band.
    let top = (view.height - LEGEND) as i32;
    root.draw(&Rectangle::new(
        [(0, top), (view.width as i32, view.height as i32)],
        WHITE.filled(),
    ))?;
    let bar = ScaleBar::new(view);
    // plotters fills a rectangle up to, not including, its second corner
    let end = bar.x + bar.pixels as i32;
    root.draw(&Rectangle::new(
        [(bar.x, bar.y - 1), (end, bar.y + 1)],
        BLACK.filled(),
    ))?;
    label(&bar.label(), (end + 10, bar.y - 9))?;
    // Second line: particle keys, then the bond colours.
    let y = bar.y + 30;
    let mut x = MARGIN as i32 + 8;
    root.draw(&Circle::new((x, y), 7, ORANGE.filled()))?;
    label("bonded particle", (x + 14, y - 9))?;
    x += 180;
    root.draw(&Circle::new((x, y), 7, GREY.stroke_width(1)))?;
    label("unbonded particle", (x + 14, y - 9))?;
    x += 200;
    match range {
        Some((lo, hi)) => {
            label(&format!("bond time [ms]: {:.3}", lo * 1e3), (x, y - 9))?;
            x += if text { 220 } else { 0 };
            for (k, c) in RAMP.iter().enumerate() {
                let x0 = x + 24 * k as i32;
                root.draw(&Rectangle::new([(x0, y - 8), (x0 + 23, y + 8)], c.filled()))?;
            }
            label(
                &format!("{:.3}", hi * 1e3),
                (x + 24 * RAMP.len() as i32 + 8, y - 9),
            )?;
        }
        None => {
            root.draw(&PathElement::new(
                vec![(x, y), (x + 30, y)],
                BLACK.stroke_width(2),
            ))?;
            label("bond", (x + 40, y - 9))?;
        }
    }
    Ok(())
}

/// The image as a palette of its 256 most frequent colours and one index per pixel. Every
/// colour drawn on purpose (background, particles, bonds, ramp) is among them; beyond 256,
/// the rarest, the anti-aliased edges of the legend's text, take the nearest palette colour.
fn indexed(buf: &[u8]) -> (Vec<u8>, Vec<u8>) {
    let mut count: std::collections::HashMap<[u8; 3], u64> = std::collections::HashMap::new();
    for px in buf.chunks_exact(3) {
        *count.entry([px[0], px[1], px[2]]).or_default() += 1;
    }
    let mut colours: Vec<([u8; 3], u64)> = count.into_iter().collect();
    // Most frequent first, ties by colour, so the palette does not depend on hash order.
    colours.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    colours.truncate(256);
    let palette: Vec<[u8; 3]> = colours.iter().map(|c| c.0).collect();
    let lookup: std::collections::HashMap<[u8; 3], u8> = palette
        .iter()
        .enumerate()
        .map(|(i, &c)| (c, i as u8))
        .collect();
    let nearest = |c: [u8; 3]| {
        let d = |p: &[u8; 3]| {
            (0..3)
                .map(|a| (p[a] as i32 - c[a] as i32).pow(2))
                .sum::<i32>()
        };
        (0..palette.len())
            .min_by_key(|&i| d(&palette[i]))
            .unwrap_or(0) as u8
    };
    let index = buf
        .chunks_exact(3)
        .map(|px| {
            let c = [px[0], px[1], px[2]];
            lookup.get(&c).copied().unwrap_or_else(|| nearest(c))
        })
        .collect();
    (palette.concat(), index)
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
         bonds as lines (coloured by bond_time when the graph has it, else black), a scale bar \
         in um and a colour legend below; PNG, 1600 px on the longer side of the view, \
         palette-indexed and fully compressed"
    }
    fn write(
        &self,
        artifact: &Artifact,
        path: &Path,
        provenance: &Provenance,
        _options: &grainpipe_core::registry::ExportOptions,
    ) -> Result<(), String> {
        let g = artifact
            .as_contact_graph()
            .ok_or_else(|| format!("png exports a ContactGraph, got a {}", artifact.kind()))?;
        let (w, h, buf) = render(g)?;
        if buf.len() != (w as usize) * (h as usize) * 3 {
            return Err("image buffer size mismatch".into());
        }
        let (palette, index) = indexed(&buf);
        atomic_write(path, |tmp| -> Result<(), String> {
            let file = std::fs::File::create(tmp).map_err(|e| e.to_string())?;
            let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
            enc.set_depth(png::BitDepth::Eight);
            enc.set_compression(png::Compression::Best);
            enc.set_color(png::ColorType::Indexed);
            enc.set_palette(palette.clone());
            // Row filters rarely help palette indices (PNG specification, section 12.8).
            enc.set_filter(png::FilterType::NoFilter);
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
            writer.write_image_data(&index).map_err(|e| e.to_string())?;
            writer.finish().map_err(|e| e.to_string())
        })
    }
}
