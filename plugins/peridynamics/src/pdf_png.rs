//! `pdf-png` exporter: the per-phase stress PDFs of `analysis.stress_stats` (its `pdf` table)
//! as a PNG in the style of Heinze et al. 2020, Fig. 14d / 15: pdf of x = sigma / <sigma>
//! per phase on a log y axis, markers for the histogram bins, a dashed line for the
//! exponential-tail fit pdf ~ exp(-s x) with s in the legend.
//!
//! It takes the `png` extension too: the registry picks it for a Table and the sintering
//! plugin's `png` for a ContactGraph. Text (axis labels, legend) needs a TrueType font from
//! the system (DejaVu Sans or Liberation Sans) and is left out without one, as in the
//! sintering exporter.

use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::model::{Artifact, ArtifactKind, Provenance, Table};
use grainpipe_core::registry::{ExportOption, ExportOptions};
use grainpipe_core::Exporter;
use plotters::prelude::*;
use std::path::Path;

pub struct PdfPng;

/// Default image size [px].
pub const WIDTH: u32 = 900;
pub const HEIGHT: u32 = 600;
/// Accepted range of either edge [px]: below, the axes leave no room for the data; above, a
/// plot of at most a few hundred bins gains nothing.
const EDGE: std::ops::RangeInclusive<u32> = 200..=8000;

/// The system font of every grainpipe chart (grainpipe-charts registers it once); false
/// when none is installed.
fn font_available() -> bool {
    grainpipe_charts::style::font_available()
}

/// One phase's curves from the table.
#[derive(Clone, Debug, PartialEq)]
pub struct Curve {
    pub phase: String,
    pub pdf: Vec<f64>,
    /// The tail fit per bin (NaN outside the fitted range); None when the table has no
    /// `fit_<phase>` column.
    pub fit: Option<Vec<f64>>,
}

impl Curve {
    /// The tail exponent s, read back from two points of the fitted line.
    pub fn exponent(&self, x: &[f64]) -> Option<f64> {
        let fit = self.fit.as_ref()?;
        let pts: Vec<(f64, f64)> = x
            .iter()
            .zip(fit)
            .filter(|(_, f)| f.is_finite() && **f > 0.0)
            .map(|(&x, &f)| (x, f.ln()))
            .collect();
        let (a, b) = (pts.first()?, pts.last()?);
        (b.0 > a.0).then(|| -(b.1 - a.1) / (b.0 - a.0))
    }
}

/// The bin centres and per-phase curves of a stress PDF table: column `x`, columns
/// `pdf_<phase>`, optional `fit_<phase>`.
pub fn curves(t: &Table) -> Result<(Vec<f64>, Vec<Curve>), String> {
    let refuse = |why: &str| {
        let cols: Vec<&str> = t.columns.iter().map(|c| c.name.as_str()).collect();
        format!(
            "pdf-png draws the `pdf` table of analysis.stress_stats (columns x, pdf_<phase>, \
             fit_<phase>); table `{}` with columns {cols:?}: {why}",
            t.name
        )
    };
    t.validate().map_err(|e| refuse(&e))?;
    let x = t
        .f64_column("x")
        .ok_or_else(|| refuse("no numeric column `x`"))?
        .to_vec();
    let mut out = Vec::new();
    for c in &t.columns {
        let Some(phase) = c.name.strip_prefix("pdf_") else {
            continue;
        };
        let pdf = t
            .f64_column(&c.name)
            .ok_or_else(|| refuse(&format!("`{}` is not numeric", c.name)))?
            .to_vec();
        let fit = t.f64_column(&format!("fit_{phase}")).map(|v| v.to_vec());
        out.push(Curve {
            phase: phase.to_string(),
            pdf,
            fit,
        });
    }
    if out.is_empty() {
        return Err(refuse("no `pdf_<phase>` column"));
    }
    if x.len() < 2
        || x.windows(2)
            .any(|w| w[1].partial_cmp(&w[0]) != Some(std::cmp::Ordering::Greater))
    {
        return Err(refuse("`x` needs at least two increasing bin centres"));
    }
    Ok((x, out))
}

/// Colour of a phase: the paper's sample phases get fixed colours (large, small, matrix), so
/// plots of different runs compare at a glance; others take the next of a qualitative set.
fn colour(phase: &str, k: usize) -> RGBColor {
    const OTHERS: [RGBColor; 5] = [
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(127, 127, 127),
        RGBColor(188, 189, 34),
    ];
    match phase {
        "large" => RGBColor(31, 119, 180),
        "small" => RGBColor(255, 127, 14),
        "matrix" => RGBColor(44, 160, 44),
        _ => OTHERS[k % OTHERS.len()],
    }
}

/// Renders the plot into an RGB buffer of `width` x `height`.
pub fn render(t: &Table, width: u32, height: u32) -> Result<Vec<u8>, String> {
    let (x, curves) = curves(t)?;
    let half = 0.5 * (x[1] - x[0]);
    let (x0, x1) = (x[0] - half, x[x.len() - 1] + half);
    let positive = curves
        .iter()
        .flat_map(|c| c.pdf.iter().chain(c.fit.iter().flatten()))
        .copied()
        .filter(|v| v.is_finite() && *v > 0.0);
    let (lo, hi) = positive.fold((f64::INFINITY, 0f64), |(l, h), v| (l.min(v), h.max(v)));
    if hi <= 0.0 {
        return Err("the stress PDF table has no positive value to draw on a log axis".into());
    }
    // Whole decades around the data, so the log axis gets labelled powers of ten.
    let (y0, y1) = (
        10f64.powf(lo.log10().floor()),
        10f64.powf((hi.log10() + 1e-9).ceil()),
    );
    let text = font_available();
    let mut buf = vec![0u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (width, height)).into_drawing_area();
        let e = |e: DrawingAreaErrorKind<_>| e.to_string();
        root.fill(&WHITE).map_err(e)?;
        let mut builder = ChartBuilder::on(&root);
        builder.margin(20);
        if text {
            builder
                .caption("stress PDF per phase", (grainpipe_charts::style::FONT, 22))
                .x_label_area_size(45)
                .y_label_area_size(70);
        } else {
            builder.x_label_area_size(10).y_label_area_size(10);
        }
        let mut chart = builder
            .build_cartesian_2d(x0..x1, (y0..y1).log_scale())
            .map_err(e)?;
        let mut mesh = chart.configure_mesh();
        mesh.light_line_style(WHITE.mix(0.0));
        if text {
            mesh.x_desc("σ / ⟨σ⟩ (phase mean)")
                .y_desc("PDF")
                .y_label_formatter(&|v| grainpipe_charts::style::log_tick(*v))
                .label_style((grainpipe_charts::style::FONT, 15))
                .axis_desc_style((grainpipe_charts::style::FONT, 17));
        } else {
            mesh.x_labels(0).y_labels(0);
        }
        mesh.draw().map_err(e)?;
        for (k, c) in curves.iter().enumerate() {
            let col = colour(&c.phase, k);
            let pts: Vec<(f64, f64)> = x
                .iter()
                .zip(&c.pdf)
                .filter(|(_, p)| p.is_finite() && **p > 0.0)
                .map(|(&x, &p)| (x, p))
                .collect();
            let label = match c.exponent(&x) {
                Some(s) => format!("{} (s = {s:.2})", c.phase),
                None => c.phase.clone(),
            };
            chart
                .draw_series(LineSeries::new(pts.clone(), col.mix(0.5).stroke_width(1)))
                .map_err(e)?;
            chart
                .draw_series(pts.iter().map(|&p| Circle::new(p, 3, col.filled())))
                .map_err(e)?
                .label(label)
                .legend(move |(x, y)| Circle::new((x + 10, y), 4, col.filled()));
            let fit: Vec<(f64, f64)> = c
                .fit
                .iter()
                .flat_map(|f| x.iter().zip(f))
                .filter(|(_, f)| f.is_finite() && **f > 0.0)
                .map(|(&x, &f)| (x, f))
                .collect();
            if fit.len() >= 2 {
                // Extended by half a bin either way: the line covers the fitted bins.
                let (a, b) = (fit[0], fit[fit.len() - 1]);
                let slope = (b.1.ln() - a.1.ln()) / (b.0 - a.0);
                let ends = [
                    (a.0 - half, (a.1.ln() - slope * half).exp()),
                    (b.0 + half, (b.1.ln() + slope * half).exp()),
                ];
                chart
                    .draw_series(DashedLineSeries::new(ends, 10, 6, col.stroke_width(2)))
                    .map_err(e)?;
            }
        }
        if text {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.9))
                .border_style(BLACK)
                .label_font((grainpipe_charts::style::FONT, 16))
                .draw()
                .map_err(e)?;
        }
        root.present().map_err(e)?;
    }
    Ok(buf)
}

fn edge(options: &ExportOptions, name: &str) -> Result<u32, (String, String)> {
    let bad = || {
        (
            name.to_string(),
            format!(
                "image {name} in pixels: an integer from {} to {}",
                EDGE.start(),
                EDGE.end()
            ),
        )
    };
    let v = options.get(name).and_then(|v| v.as_u64()).ok_or_else(bad)?;
    u32::try_from(v)
        .ok()
        .filter(|v| EDGE.contains(v))
        .ok_or_else(bad)
}

impl Exporter for PdfPng {
    fn name(&self) -> &'static str {
        "pdf-png"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["png"]
    }
    fn accepts(&self, kind: ArtifactKind) -> bool {
        kind == ArtifactKind::Table
    }
    fn doc(&self) -> &'static str {
        "plot of the per-phase stress PDFs of analysis.stress_stats (its `pdf` table: x, \
         pdf_<phase>, fit_<phase>) as in Heinze et al. 2020, Fig. 14d / 15: log y axis, \
         markers per bin, the exponential-tail fit as a dashed line with s in the legend; \
         RGB PNG, `width` x `height` pixels (default 900 x 600)"
    }
    fn options(&self) -> Vec<ExportOption> {
        vec![
            ExportOption {
                name: "width",
                doc: "image width in pixels (200 to 8000)",
                default: serde_json::json!(WIDTH),
            },
            ExportOption {
                name: "height",
                doc: "image height in pixels (200 to 8000)",
                default: serde_json::json!(HEIGHT),
            },
        ]
    }
    fn check_options(&self, options: &ExportOptions) -> Result<(), (String, String)> {
        edge(options, "width")?;
        edge(options, "height").map(|_| ())
    }
    fn write(
        &self,
        artifact: &Artifact,
        path: &Path,
        provenance: &Provenance,
        options: &ExportOptions,
    ) -> Result<(), String> {
        let t = artifact
            .as_table()
            .ok_or_else(|| format!("pdf-png exports a Table, got a {}", artifact.kind()))?;
        let (w, h) = (
            edge(options, "width").map_err(|e| e.1)?,
            edge(options, "height").map_err(|e| e.1)?,
        );
        let buf = render(t, w, h)?;
        atomic_write(path, |tmp| -> Result<(), String> {
            let file = std::fs::File::create(tmp).map_err(|e| e.to_string())?;
            let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
            enc.set_depth(png::BitDepth::Eight);
            enc.set_color(png::ColorType::Rgb);
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
