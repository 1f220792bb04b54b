//! The look every grainpipe chart shares: colours, the colour map, fonts, tick and axis text.

use std::sync::OnceLock;

/// An 8-bit RGB colour.
pub type Rgb = (u8, u8, u8);

/// Ink of axes and text.
pub const INK: Rgb = (51, 51, 51);
/// Light grid lines.
pub const GRID: Rgb = (235, 235, 235);
/// The accent of means, confidence intervals and tolerances.
pub const ACCENT: Rgb = (176, 0, 32);
/// Series colours, in order: blue, tan, green, purple, orange, teal, red, grey.
pub const PALETTE: [Rgb; 8] = [
    (46, 104, 180),
    (214, 166, 92),
    (80, 160, 90),
    (140, 90, 170),
    (230, 140, 40),
    (60, 170, 180),
    (200, 70, 60),
    (120, 120, 120),
];

/// The `k`-th series colour (cycling).
pub fn pick(k: usize) -> Rgb {
    PALETTE[k % PALETTE.len()]
}

/// The font family charts ask for (an SVG shown in a browser uses the browser's sans-serif).
pub const FONT: &str = "sans-serif";
/// Tick label size (plotters' units: pixel height of the glyph box).
pub const TICK_SIZE: f64 = 13.0;
/// Axis description size.
pub const LABEL_SIZE: f64 = 14.0;
/// Title size.
pub const TITLE_SIZE: f64 = 17.0;

const FONT_CANDIDATES: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation/LiberationSans-Regular.ttf",
];

/// Registers a system TrueType font for the bitmap (PNG) charts once; false when none is
/// available (DejaVu Sans, Debian package fonts-dejavu-core, or Liberation Sans). SVG charts
/// do not need one: their text is laid out by the browser, sized here by an estimate.
pub fn font_available() -> bool {
    static OK: OnceLock<bool> = OnceLock::new();
    *OK.get_or_init(|| {
        for p in FONT_CANDIDATES {
            if let Ok(bytes) = std::fs::read(p) {
                // plotters keeps fonts for the life of the process.
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font(FONT, plotters::style::FontStyle::Normal, bytes)
                    .is_ok()
                {
                    return true;
                }
            }
        }
        false
    })
}

/// Perceptually ordered colour map from dark blue through green to yellow (anchors after
/// matplotlib's viridis, interpolated linearly); NaN maps to the low end.
pub fn viridis(t: f64) -> [u8; 3] {
    const A: [[f64; 3]; 9] = [
        [68.0, 1.0, 84.0],
        [71.0, 44.0, 122.0],
        [59.0, 81.0, 139.0],
        [44.0, 113.0, 142.0],
        [33.0, 144.0, 141.0],
        [39.0, 173.0, 129.0],
        [92.0, 200.0, 99.0],
        [170.0, 220.0, 50.0],
        [253.0, 231.0, 37.0],
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * (A.len() - 1) as f64;
    let i = (x.floor() as usize).min(A.len() - 2);
    let f = x - i as f64;
    [0, 1, 2].map(|c| (A[i][c] + f * (A[i + 1][c] - A[i][c])).round() as u8)
}

/// Compact tick text: plain between 1e-2 and 1e4 with at most three decimals, else
/// `1.5e-11`. No markup (SVG text and PNG alike).
pub fn tick(x: f64) -> String {
    if x == 0.0 || (x.abs() < 1e-300) {
        return "0".into();
    }
    if !x.is_finite() {
        return String::new();
    }
    let a = x.abs();
    if (1e-2..1e4).contains(&a) {
        let s = format!("{x:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        let s = format!("{x:.2e}");
        let (m, e) = s.split_once('e').unwrap_or((&s, "0"));
        let m = if m.contains('.') {
            m.trim_end_matches('0').trim_end_matches('.')
        } else {
            m
        };
        format!("{m}e{e}")
    }
}

/// Tick text of a log axis: `1e-6`, `1e2`, or the plain value between 0.01 and 1000.
pub fn log_tick(x: f64) -> String {
    if !(x.is_finite() && x > 0.0) {
        return String::new();
    }
    let e = x.log10().round();
    if (x / 10f64.powf(e) - 1.0).abs() < 1e-6 {
        if (-2.0..=3.0).contains(&e) {
            tick(x)
        } else {
            format!("1e{}", e as i32)
        }
    } else {
        tick(x)
    }
}

/// An axis description with its unit: `name [unit]`, or `name` when the unit is empty or
/// dimensionless ("1"). Units are written as on the page (`um` becomes `µm`, `^2` `²`).
pub fn axis_label(name: &str, unit: &str) -> String {
    let u = pretty_unit(unit);
    if u.is_empty() || u == "1" {
        name.to_string()
    } else {
        format!("{name} [{u}]")
    }
}

/// `m^2` -> `m²`, `um` -> `µm`, `W/(m K)` unchanged.
pub fn pretty_unit(unit: &str) -> String {
    let u = if unit == "um" { "µm" } else { unit };
    u.replace("^-1", "⁻¹")
        .replace("^2", "²")
        .replace("^3", "³")
        .replace("^-2", "⁻²")
}

/// The "nice" step (1, 2 or 5 times a power of ten) that cuts `span` into about `n` parts.
pub fn nice_step(span: f64, n: usize) -> f64 {
    if !(span.is_finite() && span > 0.0) {
        return 1.0;
    }
    let raw = span / n.max(1) as f64;
    let p = 10f64.powf(raw.log10().floor());
    let m = raw / p;
    let k = if m < 1.5 {
        1.0
    } else if m < 3.5 {
        2.0
    } else if m < 7.5 {
        5.0
    } else {
        10.0
    };
    k * p
}

/// Tick positions: the multiples of [`nice_step`] inside [lo, hi].
pub fn ticks(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
        return vec![lo];
    }
    let s = nice_step(hi - lo, n);
    let first = (lo / s).ceil() as i64;
    let last = (hi / s).floor() as i64;
    (first..=last)
        .map(|k| {
            let v = k as f64 * s;
            // Kill the rounding noise of k * s (0.30000000000000004).
            let digits = (-s.log10().floor()).max(0.0) as i32 + 1;
            let q = 10f64.powi(digits);
            if digits < 15 {
                (v * q).round() / q
            } else {
                v
            }
        })
        .collect()
}

/// [lo, hi] widened to the enclosing multiples of the nice step for about `n` ticks, with a
/// little room: the range one y axis shares across several plots.
pub fn nice_range(lo: f64, hi: f64, n: usize) -> (f64, f64) {
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    let (lo, hi) = if hi > lo {
        (lo, hi)
    } else {
        let pad = if lo != 0.0 { 0.05 * lo.abs() } else { 1.0 };
        (lo - pad, hi + pad)
    };
    let s = nice_step(hi - lo, n);
    ((lo / s).floor() * s, (hi / s).ceil() * s)
}

/// The length of a scale bar for a picture `extent` wide: the nice length (1, 2 or 5 times a
/// power of ten) closest below a fifth of the width.
pub fn scale_bar(extent: f64) -> f64 {
    if !(extent.is_finite() && extent > 0.0) {
        return 0.0;
    }
    let target = extent / 5.0;
    let p = 10f64.powf(target.log10().floor());
    let m = target / p;
    let k = if m >= 5.0 {
        5.0
    } else if m >= 2.0 {
        2.0
    } else {
        1.0
    };
    k * p
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nice_ticks() {
        assert_eq!(ticks(0.0, 1.0, 5), vec![0.0, 0.2, 0.4, 0.6, 0.8, 1.0]);
        assert_eq!(ticks(0.03, 0.31, 3), vec![0.1, 0.2, 0.3]);
        assert_eq!(ticks(-7.0, 23.0, 3), vec![0.0, 10.0, 20.0]);
        assert_eq!(nice_step(192.0, 4), 50.0);
        assert_eq!(nice_range(4.1e9, 5.3e9, 5), (4.0e9, 5.4e9));
        let (lo, hi) = nice_range(3.0, 3.0, 5);
        assert!(lo < 3.0 && hi > 3.0);
    }

    #[test]
    fn scale_bars_are_nice_and_short() {
        assert_eq!(scale_bar(192.0), 20.0);
        assert_eq!(scale_bar(1000.0), 200.0);
        assert_eq!(scale_bar(30.0), 5.0);
        assert_eq!(scale_bar(0.0), 0.0);
    }

    #[test]
    fn tick_text() {
        assert_eq!(tick(0.25), "0.25");
        assert_eq!(tick(4.5e9), "4.5e9");
        assert_eq!(tick(3.5e-11), "3.5e-11");
        assert_eq!(tick(140.0), "140");
        assert_eq!(log_tick(1e-6), "1e-6");
        assert_eq!(log_tick(0.1), "0.1");
        assert_eq!(axis_label("kappa", "m^2"), "kappa [m²]");
        assert_eq!(axis_label("x", "um"), "x [µm]");
        assert_eq!(axis_label("porosity", "1"), "porosity");
    }

    #[test]
    fn colour_map_ends() {
        assert_eq!(viridis(0.0), [68, 1, 84]);
        assert_eq!(viridis(1.0), [253, 231, 37]);
        assert_eq!(viridis(f64::NAN), [68, 1, 84]);
    }
}
