//! One chart model ([`Figure`]) drawn by plotters on any backend: inline SVG for the HTML
//! pages ([`Figure::svg`]), PNG and SVG files for sweeps and stages ([`Figure::save`]).

use crate::style::{self, Rgb};
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters_backend::{BackendColor, BackendCoord, BackendTextStyle, DrawingErrorKind};
use std::ops::Range;
use std::path::Path;

/// A series of points, with optional vertical error bars (low, high), a connecting line and
/// markers.
#[derive(Clone, Debug, Default)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    /// Per point (low, high); drawn as a whisker with caps, centred on the point's x.
    pub err: Vec<(f64, f64)>,
    pub line: bool,
    pub markers: bool,
    /// Default: the palette colour of the series' index.
    pub color: Option<Rgb>,
    /// Marker radius in pixels (0: 4).
    pub marker_size: u32,
    /// Markers filled white with a coloured edge.
    pub hollow: bool,
}

/// A horizontal reference line across the plot (a tolerance, a target).
#[derive(Clone, Debug)]
pub struct HLine {
    pub y: f64,
    pub label: String,
}

/// Series on a second y axis at the right (e.g. a cumulative share over a histogram).
#[derive(Clone, Debug, Default)]
pub struct Secondary {
    pub label: String,
    pub range: (f64, f64),
    pub series: Vec<Series>,
}

/// One chart.
#[derive(Clone, Debug, Default)]
pub struct Figure {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    /// Filled polygons (violins), with a palette index.
    pub polygons: Vec<(Vec<(f64, f64)>, usize)>,
    /// Category names at x = 0, 1, 2, ... (violin plots).
    pub categories: Vec<String>,
    /// Histogram bars: (x from, x to, height), filled from the bottom of the plot.
    pub bars: Vec<(f64, f64, f64)>,
    pub hlines: Vec<HLine>,
    pub x_log: bool,
    pub y_log: bool,
    /// Fixed axis ranges (else from the data, padded).
    pub x_range: Option<(f64, f64)>,
    pub y_range: Option<(f64, f64)>,
    pub secondary: Option<Secondary>,
    /// Pixels (default 960 x 640 for files, 560 x 300 inline).
    pub size: Option<(u32, u32)>,
}

/// The pixel rectangle of a chart's plotting area: (x range, y range).
pub type PlotArea = (Range<i32>, Range<i32>);

fn color(c: Rgb) -> RGBColor {
    RGBColor(c.0, c.1, c.2)
}

/// The data range of one axis, padded: `pad` of the span on a linear axis, a factor on a log
/// axis (non-positive values left out there).
fn range_of(v: &[f64], log: bool, pad: f64) -> (f64, f64) {
    let v: Vec<f64> = v
        .iter()
        .copied()
        .filter(|x| x.is_finite() && (!log || *x > 0.0))
        .collect();
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !lo.is_finite() {
        return if log { (0.1, 1.0) } else { (0.0, 1.0) };
    }
    if log {
        let (lo, hi) = if hi > lo {
            (lo, hi)
        } else {
            (lo / 2.0, hi * 2.0)
        };
        let f = (hi / lo).powf(pad);
        return (lo / f, hi * f);
    }
    let p = if hi > lo {
        pad * (hi - lo)
    } else {
        0.5 * lo.abs().max(1e-12)
    };
    (lo - p, hi + p)
}

impl Figure {
    /// The axis ranges the chart is drawn with.
    pub fn bounds(&self) -> ((f64, f64), (f64, f64)) {
        let mut xs: Vec<f64> = Vec::new();
        let mut ys: Vec<f64> = Vec::new();
        for s in &self.series {
            xs.extend(s.points.iter().map(|p| p.0));
            ys.extend(s.points.iter().map(|p| p.1));
            ys.extend(s.err.iter().flat_map(|e| [e.0, e.1]));
        }
        for (p, _) in &self.polygons {
            xs.extend(p.iter().map(|q| q.0));
            ys.extend(p.iter().map(|q| q.1));
        }
        for b in &self.bars {
            xs.extend([b.0, b.1]);
            ys.push(b.2);
            if !self.y_log {
                ys.push(0.0);
            }
        }
        ys.extend(self.hlines.iter().map(|h| h.y));
        let mut x = range_of(
            &xs,
            self.x_log,
            if self.bars.is_empty() { 0.06 } else { 0.0 },
        );
        if !self.categories.is_empty() {
            x = (-0.6, self.categories.len() as f64 - 0.4);
        }
        let mut y = range_of(&ys, self.y_log, 0.06);
        if !self.bars.is_empty() && !self.y_log {
            y.0 = 0.0;
        }
        (self.x_range.unwrap_or(x), self.y_range.unwrap_or(y))
    }

    /// The chart as an inline `<svg>` element (no XML prolog), `class` set on it. Text is
    /// laid out by the browser, so no font is needed.
    pub fn svg(&self, class: &str) -> Result<String, String> {
        let size = self.size.unwrap_or((560, 300));
        let mut out = String::new();
        {
            let root = InlineSvg(SVGBackend::with_string(&mut out, size)).into_drawing_area();
            self.draw(&root, true, true)?;
        }
        Ok(tag_svg(&out, class))
    }

    /// Writes `<stem>.png` and `<stem>.svg` (each atomically). The PNG has text when a
    /// system font is available ([`style::font_available`]), else none.
    pub fn save(&self, stem: &Path) -> Result<(), String> {
        let text = style::font_available();
        let size = self.size.unwrap_or((960, 640));
        let png = stem.with_extension("png");
        let dir = png.parent().map(Path::to_path_buf).unwrap_or_default();
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        }
        // The bitmap backend picks the encoder by extension: the temporary file ends in .png.
        let name = png
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let tmp = png.with_file_name(format!(".{name}.{}.tmp.png", std::process::id()));
        let r = {
            let root = BitMapBackend::new(&tmp, size).into_drawing_area();
            self.draw(&root, text, true)
        };
        match r {
            Ok(_) => std::fs::rename(&tmp, &png).map_err(|e| format!("{}: {e}", png.display()))?,
            Err(e) => {
                let _ = std::fs::remove_file(&tmp);
                return Err(format!("{}: {e}", png.display()));
            }
        }
        let svg_path = stem.with_extension("svg");
        let mut svg = String::new();
        {
            let root = InlineSvg(SVGBackend::with_string(&mut svg, size)).into_drawing_area();
            self.draw(&root, true, true)
                .map_err(|e| format!("{}: {e}", svg_path.display()))?;
        }
        write_atomic(&svg_path, svg.as_bytes())
    }

    /// Draws the chart on `root` (filled white when `fill`); returns the plotting area.
    pub fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        text: bool,
        fill: bool,
    ) -> Result<PlotArea, String>
    where
        DB::ErrorType: 'static,
    {
        if fill {
            root.fill(&WHITE).map_err(|e| e.to_string())?;
        }
        let ((x0, x1), (y0, y1)) = self.bounds();
        match (self.x_log, self.y_log) {
            (false, false) => self.draw_in(root, text, x0..x1, y0..y1),
            (false, true) => self.draw_in(root, text, x0..x1, (y0..y1).log_scale()),
            (true, false) => self.draw_in(root, text, (x0..x1).log_scale(), y0..y1),
            (true, true) => self.draw_in(root, text, (x0..x1).log_scale(), (y0..y1).log_scale()),
        }
    }

    fn draw_in<DB, X, Y>(
        &self,
        root: &DrawingArea<DB, Shift>,
        text: bool,
        xr: X,
        yr: Y,
    ) -> Result<PlotArea, String>
    where
        DB: DrawingBackend,
        DB::ErrorType: 'static,
        X: AsRangedCoord<Value = f64>,
        Y: AsRangedCoord<Value = f64>,
        X::CoordDescType: ValueFormatter<f64>,
        Y::CoordDescType: ValueFormatter<f64>,
    {
        let e = |x: DrawingAreaErrorKind<DB::ErrorType>| x.to_string();
        let mut b = ChartBuilder::on(root);
        b.margin(10)
            .margin_right(if self.secondary.is_some() { 4 } else { 16 });
        if text {
            if !self.title.is_empty() {
                b.caption(&self.title, (style::FONT, style::TITLE_SIZE));
            }
            b.x_label_area_size(if self.x_label.is_empty() { 24 } else { 42 })
                .y_label_area_size(if self.y_label.is_empty() { 52 } else { 70 });
            if self.secondary.is_some() {
                b.right_y_label_area_size(56);
            }
        }
        let mut chart = b.build_cartesian_2d(xr, yr).map_err(e)?;
        let ink = color(style::INK);
        let area = chart.plotting_area().get_pixel_range();
        match &self.secondary {
            None => {
                self.body(&mut chart, text)?;
                if text {
                    self.legend(root, &area, false)?;
                }
            }
            Some(sec) => {
                let ((x0, x1), _) = self.bounds();
                let (s0, s1) = sec.range;
                let mut dual = chart.set_secondary_coord(x0..x1, s0..s1);
                self.body(std::ops::DerefMut::deref_mut(&mut dual), text)?;
                if text {
                    dual.configure_secondary_axes()
                        .y_desc(&sec.label)
                        .y_label_formatter(&|y: &f64| style::tick(*y))
                        .label_style((style::FONT, style::TICK_SIZE).into_font().color(&ink))
                        .axis_desc_style((style::FONT, style::LABEL_SIZE).into_font().color(&ink))
                        .axis_style(ink)
                        .draw()
                        .map_err(e)?;
                }
                for (k, s) in sec.series.iter().enumerate() {
                    let col = color(s.color.unwrap_or(style::pick(k)));
                    let pts: Vec<(f64, f64)> = s
                        .points
                        .iter()
                        .copied()
                        .filter(|p| p.0.is_finite() && p.1.is_finite())
                        .collect();
                    dual.draw_secondary_series(LineSeries::new(pts, col.stroke_width(2)))
                        .map_err(e)?;
                }
                if text {
                    self.legend(root, &area, true)?;
                }
            }
        }
        root.present().map_err(e)?;
        Ok(area)
    }

    /// The legend's entries: (text, colour, drawn as a line rather than a dot).
    fn legend_entries(&self) -> Vec<(String, Rgb, bool)> {
        let mut out: Vec<(String, Rgb, bool)> = self
            .hlines
            .iter()
            .filter(|h| !h.label.is_empty())
            .map(|h| (h.label.clone(), style::ACCENT, true))
            .collect();
        for (k, s) in self.series.iter().enumerate() {
            if !s.name.is_empty() {
                out.push((s.name.clone(), s.color.unwrap_or(style::pick(k)), s.line));
            }
        }
        for (k, s) in self.secondary.iter().flat_map(|x| &x.series).enumerate() {
            if !s.name.is_empty() {
                out.push((s.name.clone(), s.color.unwrap_or(style::pick(k)), true));
            }
        }
        out
    }

    /// The legend in a corner of the plotting area (upper right, or upper left), its text
    /// sized by the backend (no font needed for inline SVG).
    fn legend<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        area: &PlotArea,
        left: bool,
    ) -> Result<(), String>
    where
        DB::ErrorType: 'static,
    {
        let entries = self.legend_entries();
        if entries.is_empty() {
            return Ok(());
        }
        let e = |x: DrawingAreaErrorKind<DB::ErrorType>| x.to_string();
        let font = (style::FONT, style::TICK_SIZE)
            .into_font()
            .color(&color(style::INK));
        let mut w = 0u32;
        let mut line_h = 0u32;
        for (t, _, _) in &entries {
            let (tw, th) = root.estimate_text_size(t, &font).map_err(e)?;
            w = w.max(tw);
            line_h = line_h.max(th);
        }
        let line_h = line_h as i32 + 6;
        let (pad, mark) = (6, 22);
        let bw = w as i32 + mark + 2 * pad;
        let bh = entries.len() as i32 * line_h + 2 * pad - 6;
        let x0 = if left {
            area.0.start + 8
        } else {
            area.0.end - 8 - bw
        };
        let y0 = area.1.start + 8;
        root.draw(&Rectangle::new(
            [(x0, y0), (x0 + bw, y0 + bh)],
            WHITE.mix(0.85).filled(),
        ))
        .map_err(e)?;
        root.draw(&Rectangle::new(
            [(x0, y0), (x0 + bw, y0 + bh)],
            color(style::INK).stroke_width(1),
        ))
        .map_err(e)?;
        for (k, (t, c, line)) in entries.iter().enumerate() {
            let y = y0 + pad + k as i32 * line_h + (line_h - 6) / 2;
            let c = color(*c);
            if *line {
                root.draw(&PathElement::new(
                    vec![(x0 + pad, y), (x0 + pad + 16, y)],
                    c.stroke_width(2),
                ))
                .map_err(e)?;
            } else {
                root.draw(&Circle::new((x0 + pad + 8, y), 4, c.filled()))
                    .map_err(e)?;
            }
            root.draw(&Text::new(
                t.clone(),
                (x0 + pad + mark, y),
                font.pos(plotters::style::text_anchor::Pos::new(
                    plotters::style::text_anchor::HPos::Left,
                    plotters::style::text_anchor::VPos::Center,
                )),
            ))
            .map_err(e)?;
        }
        Ok(())
    }

    /// Mesh, bars, violins, reference lines and series on the primary axes.
    fn body<DB, X, Y>(
        &self,
        chart: &mut ChartContext<'_, DB, Cartesian2d<X, Y>>,
        text: bool,
    ) -> Result<(), String>
    where
        DB: DrawingBackend,
        DB::ErrorType: 'static,
        X: plotters::coord::ranged1d::Ranged<ValueType = f64> + ValueFormatter<f64>,
        Y: plotters::coord::ranged1d::Ranged<ValueType = f64> + ValueFormatter<f64>,
    {
        let e = |x: DrawingAreaErrorKind<DB::ErrorType>| x.to_string();
        let ((_, _), (y0, _)) = self.bounds();
        let (x_log, y_log) = (self.x_log, self.y_log);
        let cats = self.categories.clone();
        let fmt_x = move |x: &f64| {
            if !cats.is_empty() {
                let k = x.round();
                if (x - k).abs() < 1e-6 && k >= 0.0 && (k as usize) < cats.len() {
                    cats[k as usize].clone()
                } else {
                    String::new()
                }
            } else if x_log {
                style::log_tick(*x)
            } else {
                style::tick(*x)
            }
        };
        let fmt_y = move |y: &f64| {
            if y_log {
                style::log_tick(*y)
            } else {
                style::tick(*y)
            }
        };
        let ink = color(style::INK);
        {
            let mut mesh = chart.configure_mesh();
            if text {
                mesh.x_desc(&self.x_label)
                    .y_desc(&self.y_label)
                    .x_label_formatter(&fmt_x)
                    .y_label_formatter(&fmt_y)
                    .label_style((style::FONT, style::TICK_SIZE).into_font().color(&ink))
                    .axis_desc_style((style::FONT, style::LABEL_SIZE).into_font().color(&ink));
                if !self.categories.is_empty() {
                    mesh.x_labels(self.categories.len() * 2 + 1)
                        .disable_x_mesh();
                }
            } else {
                mesh.x_labels(0).y_labels(0);
            }
            mesh.light_line_style(WHITE.mix(0.0))
                .bold_line_style(color(style::GRID))
                .axis_style(ink)
                .draw()
                .map_err(e)?;
        }
        // Bars from the bottom of the plot.
        let base = if y_log { y0 } else { y0.max(0.0) };
        let bar = color(style::PALETTE[1]);
        chart
            .draw_series(
                self.bars
                    .iter()
                    .map(|&(a, b, h)| Rectangle::new([(a, base), (b, h)], bar.mix(0.85).filled())),
            )
            .map_err(e)?;
        chart
            .draw_series(self.bars.iter().map(|&(a, b, h)| {
                Rectangle::new([(a, base), (b, h)], RGBColor(138, 106, 58).stroke_width(1))
            }))
            .map_err(e)?;
        for (poly, c) in &self.polygons {
            let col = color(style::pick(*c));
            chart
                .draw_series(std::iter::once(Polygon::new(
                    poly.clone(),
                    col.mix(0.35).filled(),
                )))
                .map_err(e)?;
            chart
                .draw_series(std::iter::once(PathElement::new(
                    poly.clone(),
                    col.stroke_width(1),
                )))
                .map_err(e)?;
        }
        let ((x0, x1), _) = self.bounds();
        let accent = color(style::ACCENT);
        for h in &self.hlines {
            chart
                .draw_series(LineSeries::new(
                    vec![(x0, h.y), (x1, h.y)],
                    accent.stroke_width(1),
                ))
                .map_err(e)?;
        }
        draw_series(chart, &self.series)?;
        Ok(())
    }
}

fn draw_series<DB, X, Y>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<X, Y>>,
    series: &[Series],
) -> Result<(), String>
where
    DB: DrawingBackend,
    DB::ErrorType: 'static,
    X: plotters::coord::ranged1d::Ranged<ValueType = f64>,
    Y: plotters::coord::ranged1d::Ranged<ValueType = f64>,
{
    let e = |x: DrawingAreaErrorKind<DB::ErrorType>| x.to_string();
    for (k, s) in series.iter().enumerate() {
        let col = color(s.color.unwrap_or(style::pick(k)));
        let pts: Vec<(f64, f64)> = s
            .points
            .iter()
            .copied()
            .filter(|p| p.0.is_finite() && p.1.is_finite())
            .collect();
        if s.line && pts.len() > 1 {
            chart
                .draw_series(LineSeries::new(pts.clone(), col.stroke_width(2)))
                .map_err(e)?;
        }
        for (p, er) in s.points.iter().zip(&s.err) {
            if p.0.is_finite() && er.0.is_finite() && er.1.is_finite() {
                let st = col.stroke_width(2);
                chart
                    .draw_series(std::iter::once(PathElement::new(
                        vec![(p.0, er.0), (p.0, er.1)],
                        st,
                    )))
                    .map_err(e)?;
                // Caps, 10 px wide, centred on the whisker.
                for y in [er.0, er.1] {
                    chart
                        .draw_series(std::iter::once(
                            EmptyElement::at((p.0, y))
                                + PathElement::new(vec![(-5, 0), (5, 0)], st),
                        ))
                        .map_err(e)?;
                }
            }
        }
        if s.markers {
            let r = if s.marker_size == 0 { 4 } else { s.marker_size };
            let hollow = s.hollow;
            chart
                .draw_series(pts.iter().map(|&p| {
                    EmptyElement::at(p)
                        + Circle::new(
                            (0, 0),
                            r,
                            if hollow { WHITE.filled() } else { col.filled() },
                        )
                        + Circle::new((0, 0), r, col.stroke_width(1))
                }))
                .map_err(e)?;
        }
    }
    Ok(())
}

/// `class` (and the namespace) on the `<svg>` plotters wrote, the XML prolog dropped.
fn tag_svg(svg: &str, class: &str) -> String {
    let s = svg
        .trim_start()
        .strip_prefix("<?xml version=\"1.0\" encoding=\"UTF-8\"?>")
        .unwrap_or(svg)
        .trim_start();
    match s.strip_prefix("<svg") {
        Some(rest) if !class.is_empty() => format!("<svg class=\"{class}\" role=\"img\"{rest}"),
        _ => s.to_string(),
    }
}

pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), String> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
    std::fs::write(&tmp, bytes).map_err(|e| format!("{}: {e}", tmp.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        format!("{}: {e}", path.display())
    })
}

/// plotters' SVG backend with text sized by an estimate instead of a font's metrics: the
/// browser lays the text out with its own font, and a page renders where no TrueType font is
/// installed.
pub struct InlineSvg<'a>(pub SVGBackend<'a>);

/// Width of a character in ems (a sans-serif average; narrow and wide glyphs apart).
fn em_width(c: char) -> f64 {
    match c {
        'i' | 'l' | 'j' | '.' | ',' | ':' | ';' | '\'' | '|' | '!' | ' ' => 0.3,
        'f' | 't' | 'r' | '(' | ')' | '[' | ']' | '-' => 0.4,
        'm' | 'w' | 'M' | 'W' => 0.85,
        c if c.is_ascii_uppercase() => 0.68,
        c if c.is_ascii_digit() => 0.56,
        _ => 0.55,
    }
}

impl DrawingBackend for InlineSvg<'_> {
    type ErrorType = std::io::Error;

    fn get_size(&self) -> (u32, u32) {
        self.0.get_size()
    }
    fn ensure_prepared(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.ensure_prepared()
    }
    fn present(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.present()
    }
    fn draw_pixel(
        &mut self,
        point: BackendCoord,
        color: BackendColor,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_pixel(point, color)
    }
    fn draw_line<S: plotters_backend::BackendStyle>(
        &mut self,
        from: BackendCoord,
        to: BackendCoord,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_line(from, to, style)
    }
    fn draw_rect<S: plotters_backend::BackendStyle>(
        &mut self,
        upper_left: BackendCoord,
        bottom_right: BackendCoord,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_rect(upper_left, bottom_right, style, fill)
    }
    fn draw_path<S: plotters_backend::BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        path: I,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_path(path, style)
    }
    fn draw_circle<S: plotters_backend::BackendStyle>(
        &mut self,
        center: BackendCoord,
        radius: u32,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_circle(center, radius, style, fill)
    }
    fn fill_polygon<S: plotters_backend::BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        vert: I,
        style: &S,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.fill_polygon(vert, style)
    }
    fn draw_text<T: BackendTextStyle>(
        &mut self,
        text: &str,
        style: &T,
        pos: BackendCoord,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_text(text, style, pos)
    }
    fn estimate_text_size<T: BackendTextStyle>(
        &self,
        text: &str,
        style: &T,
    ) -> Result<(u32, u32), DrawingErrorKind<Self::ErrorType>> {
        // plotters' size is the glyph box height; the em is size / 1.24 (as its SVG writes).
        let em = style.size() / 1.24;
        // A little generous: text that overflows its box looks worse than a loose box.
        let w: f64 = 1.08 * text.chars().map(em_width).sum::<f64>() * em;
        let (w, h) = (w.ceil() as u32, em.ceil() as u32);
        Ok(match style.transform() {
            plotters_backend::FontTransform::Rotate90
            | plotters_backend::FontTransform::Rotate270 => (h, w),
            _ => (w, h),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inline_svg_has_a_class_and_no_prolog() {
        let f = Figure {
            x_label: "iteration".into(),
            y_label: "residual".into(),
            y_log: true,
            series: vec![Series {
                name: "xx".into(),
                points: (0..20).map(|i| (i as f64, 0.5f64.powi(i))).collect(),
                line: true,
                ..Default::default()
            }],
            hlines: vec![HLine {
                y: 1e-5,
                label: "tolerance 1e-5".into(),
            }],
            ..Default::default()
        };
        let svg = f.svg("chart convergence").unwrap();
        assert!(svg.starts_with("<svg class=\"chart convergence\""), "{svg}");
        assert!(svg.contains("1e-5") && svg.contains("tolerance"), "{svg}");
        assert!(svg.contains("residual") && svg.contains("iteration"));
    }

    #[test]
    fn log_bounds_leave_out_non_positive_values() {
        let f = Figure {
            y_log: true,
            series: vec![Series {
                points: vec![(0.0, 0.0), (1.0, 1e-3), (2.0, 1.0)],
                ..Default::default()
            }],
            ..Default::default()
        };
        let (_, (lo, hi)) = f.bounds();
        assert!(lo > 0.0 && lo < 1e-3 && hi > 1.0, "{lo} {hi}");
    }

    #[test]
    fn figures_are_written_as_png_and_svg() {
        let d = tempfile::tempdir().unwrap();
        let f = crate::violin::violin_figure(
            "E_x",
            "E_x [Pa]",
            &[
                ("a".into(), vec![1.0, 2.0, 3.0]),
                ("b".into(), vec![2.0, 2.5, 4.0]),
            ],
        );
        f.save(&d.path().join("v")).unwrap();
        let png = std::fs::read(d.path().join("v.png")).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let svg = std::fs::read_to_string(d.path().join("v.svg")).unwrap();
        assert!(svg.contains("<svg") && svg.contains("polygon"));
        // Only the two files: no temporary left behind.
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 2);
    }
}
