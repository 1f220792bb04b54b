//! The frame of an image slice: axes in micrometres, a scale bar and, for fields, a colour
//! bar with the unit — as a transparent inline SVG laid over the slice's picture, so the
//! picture stays a plain `<img>` (sharp voxels, decoded by the browser).

use crate::figure::{InlineSvg, PlotArea};
use crate::style;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

/// A colour bar: the colour map from `lo` (dark) to `hi` (bright).
#[derive(Clone, Debug)]
pub struct ColorBar {
    pub lo: f64,
    pub hi: f64,
    /// Description with the unit, e.g. "velocity magnitude [m/s]".
    pub label: String,
    /// Values above `hi` saturate (the bar's top label reads `≥ hi`).
    pub saturated: bool,
}

/// A slice to frame.
#[derive(Clone, Debug)]
pub struct Slice {
    /// Displayed size of the picture in CSS pixels.
    pub width: u32,
    pub height: u32,
    /// Physical extent along the horizontal and the vertical axis [µm].
    pub extent: (f64, f64),
    /// Names of the horizontal and vertical axes ("x", "z").
    pub axes: (String, String),
    pub colorbar: Option<ColorBar>,
}

/// Margins around the picture in the frame.
const LEFT: u32 = 62;
const TOP: u32 = 8;
const RIGHT: u32 = 14;
const BOTTOM: u32 = 42;
const BAR: u32 = 104;

/// The frame of `s`: (svg, total size, plotting area where the picture goes). The SVG has
/// class `slice-axes` and the scale bar's length in `data-scale-bar`.
pub fn frame(s: &Slice) -> Result<(String, (u32, u32), PlotArea), String> {
    let total = (
        LEFT + s.width + RIGHT + if s.colorbar.is_some() { BAR } else { 0 },
        TOP + s.height + BOTTOM,
    );
    let (ex, ey) = s.extent;
    let bar_len = style::scale_bar(ex);
    let bar_text = format!("{} µm", style::tick(bar_len));
    let mut out = String::new();
    let area = {
        let root = InlineSvg(SVGBackend::with_string(&mut out, total)).into_drawing_area();
        let e = |x: DrawingAreaErrorKind<std::io::Error>| x.to_string();
        let (left, right) = root.split_horizontally(LEFT + s.width + RIGHT);
        let ink = RGBColor(style::INK.0, style::INK.1, style::INK.2);
        let mut chart = ChartBuilder::on(&left)
            .margin_top(TOP)
            .margin_right(RIGHT)
            .x_label_area_size(BOTTOM)
            .y_label_area_size(LEFT)
            .build_cartesian_2d(
                0.0..ex.max(f64::MIN_POSITIVE),
                0.0..ey.max(f64::MIN_POSITIVE),
            )
            .map_err(e)?;
        chart
            .configure_mesh()
            .disable_mesh()
            // Fewer labels on a narrow or flat picture (a thin bed seen from the side).
            .x_labels((s.width / 60).clamp(2, 5) as usize)
            .y_labels((s.height / 40).clamp(2, 5) as usize)
            .x_desc(format!("{} [µm]", s.axes.0))
            .y_desc(format!("{} [µm]", s.axes.1))
            .x_label_formatter(&|x: &f64| style::tick(*x))
            .y_label_formatter(&|y: &f64| style::tick(*y))
            .label_style((style::FONT, style::TICK_SIZE).into_font().color(&ink))
            .axis_desc_style((style::FONT, style::LABEL_SIZE).into_font().color(&ink))
            .axis_style(ink)
            .draw()
            .map_err(e)?;
        // The scale bar at the bottom right, on a light backdrop.
        if bar_len > 0.0 {
            let lpx = (bar_len / ex * s.width as f64).round() as i32;
            let font = (style::FONT, 12.0)
                .into_font()
                .color(&BLACK)
                .pos(Pos::new(HPos::Center, VPos::Bottom));
            chart
                .draw_series(std::iter::once(
                    EmptyElement::at((ex - 0.04 * ex - bar_len, 0.05 * ey))
                        + Rectangle::new([(-5, -22), (lpx + 5, 4)], WHITE.mix(0.8).filled())
                        + Rectangle::new([(0, -4), (lpx, 0)], BLACK.filled())
                        + Text::new(bar_text.clone(), (lpx / 2, -6), font),
                ))
                .map_err(e)?;
        }
        let area = chart.plotting_area().get_pixel_range();
        if let Some(cb) = &s.colorbar {
            let hi = if cb.hi > cb.lo { cb.hi } else { cb.lo + 1.0 };
            let mut bar = ChartBuilder::on(&right)
                .margin_top(TOP)
                .margin_right(4)
                .x_label_area_size(BOTTOM)
                .right_y_label_area_size(BAR - 4 - 18)
                .build_cartesian_2d(0.0..1.0, cb.lo..hi)
                .map_err(e)?;
            let n = 64;
            bar.draw_series((0..n).map(|k| {
                let (a, b) = (k as f64 / n as f64, (k + 1) as f64 / n as f64);
                let [r, g, bl] = style::viridis((a + b) / 2.0);
                Rectangle::new(
                    [
                        (0.0, cb.lo + a * (hi - cb.lo)),
                        (1.0, cb.lo + b * (hi - cb.lo)),
                    ],
                    RGBColor(r, g, bl).filled(),
                )
            }))
            .map_err(e)?;
            let sat = cb.saturated;
            let top = hi;
            let fmt = move |y: &f64| {
                if sat && (*y - top).abs() <= 1e-9 * top.abs().max(f64::MIN_POSITIVE) {
                    format!("≥{}", style::tick(*y))
                } else {
                    style::tick(*y)
                }
            };
            bar.configure_mesh()
                .disable_mesh()
                .disable_x_axis()
                .x_labels(0)
                .y_labels(5)
                .y_desc(&cb.label)
                .y_label_formatter(&fmt)
                .label_style((style::FONT, style::TICK_SIZE).into_font().color(&ink))
                .axis_desc_style((style::FONT, style::LABEL_SIZE).into_font().color(&ink))
                .axis_style(ink)
                .draw()
                .map_err(e)?;
        }
        root.present().map_err(e)?;
        area
    };
    let svg = out
        .trim_start()
        .strip_prefix("<?xml version=\"1.0\" encoding=\"UTF-8\"?>")
        .unwrap_or(&out)
        .trim_start()
        .replacen(
            "<svg",
            &format!("<svg class=\"slice-axes\" data-scale-bar=\"{bar_text}\""),
            1,
        );
    Ok((svg, total, area))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_has_axes_in_um_a_scale_bar_and_a_colour_bar() {
        let s = Slice {
            width: 300,
            height: 150,
            extent: (192.0, 96.0),
            axes: ("x".into(), "z".into()),
            colorbar: Some(ColorBar {
                lo: 0.0,
                hi: 2.5e-3,
                label: "velocity magnitude [m/s]".into(),
                saturated: true,
            }),
        };
        let (svg, size, (xs, ys)) = frame(&s).unwrap();
        assert!(svg.contains("x [µm]") && svg.contains("z [µm]"), "{svg}");
        assert!(svg.contains("data-scale-bar=\"20 µm\""));
        assert!(svg.contains(">\n20 µm\n<") || svg.contains("20 µm"));
        assert!(svg.contains("velocity magnitude [m/s]"));
        // The picture's place: exactly its displayed size, inside the frame.
        assert_eq!((xs.end - xs.start, ys.end - ys.start), (300, 150));
        assert!(xs.end as u32 <= size.0 && ys.end as u32 <= size.1);
        // No background: the picture under the frame shows through.
        assert!(!svg.contains("fill=\"#FFFFFF\" stroke=\"none\" x=\"0\" y=\"0\""));
    }
}
