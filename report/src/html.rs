//! HTML building blocks: escaping, number and unit formatting, the page frame with its
//! style sheet, embedded PNGs, tables and inline SVG charts. Everything is inline so a page
//! opens from disk, offline, in any browser.

use base64::Engine;
use std::fmt::Write;

/// Escapes text for HTML content and attribute values.
pub fn esc(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&#39;"),
            _ => o.push(c),
        }
    }
    o
}

/// A number with four significant digits, plain between 1e-3 and 1e5, else with an
/// exponent; "–" for NaN (a value that was not computed).
pub fn num(v: f64) -> String {
    if v.is_nan() {
        return "–".into();
    }
    if v == 0.0 {
        return "0".into();
    }
    if !v.is_finite() {
        return if v > 0.0 {
            "∞".into()
        } else {
            "−∞".into()
        };
    }
    let a = v.abs();
    if (1e-3..1e5).contains(&a) {
        let digits = (3 - a.log10().floor() as i32).max(0) as usize;
        let s = format!("{v:.digits$}");
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        }
    } else {
        let s = format!("{v:.3e}");
        let (m, e) = s.split_once('e').unwrap_or((&s, "0"));
        let m = if m.contains('.') {
            m.trim_end_matches('0').trim_end_matches('.')
        } else {
            m
        };
        format!("{m}×10<sup>{e}</sup>")
    }
}

/// A length in micrometres (the scale of grains and voxels).
pub fn length(m: f64) -> String {
    format!("{} µm", num(m * 1e6))
}

/// A percentage with two decimals.
pub fn pct(v: f64) -> String {
    if v.is_finite() {
        format!("{:.2} %", 100.0 * v)
    } else {
        "–".into()
    }
}

pub fn bytes(b: u64) -> String {
    grainpipe_core::engine::human_bytes(b)
}

/// A PNG as an `<img>` with a data URI. `pixelated` keeps voxels sharp when scaled up.
pub fn img(png: &[u8], alt: &str, width: usize, height: usize, css_width: usize) -> String {
    let b64 = base64::engine::general_purpose::STANDARD.encode(png);
    let css_height = (css_width as f64 * height as f64 / width.max(1) as f64).round();
    format!(
        "<img src=\"data:image/png;base64,{b64}\" alt=\"{}\" width=\"{css_width}\" \
         height=\"{css_height}\" class=\"pic\">",
        esc(alt)
    )
}

/// The page frame: title, style sheet, body, and a script that marks the document with
/// `data-images-ok` once every image has decoded (what the browser test reads back).
pub fn page(title: &str, body: &str) -> String {
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n\
         <meta name=\"generator\" content=\"grainpipe {}\">\n<title>{}</title>\n<style>{STYLE}</style>\n\
         </head>\n<body>\n{body}\n<script>{SCRIPT}</script>\n</body>\n</html>\n",
        grainpipe_core::VERSION,
        esc(title)
    )
}

const STYLE: &str = "
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0 auto;max-width:1150px;padding:1em 2em;color:#1d1d1f;line-height:1.45}
h1{font-size:1.7em;margin-bottom:.2em}h2{margin-top:1.8em;border-bottom:2px solid #ddd;padding-bottom:.2em}
h3{margin-top:1.3em}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .55em;text-align:right;vertical-align:top}
th{background:#f3f3f3}td.l,th.l{text-align:left}
table.headline td,table.headline th,table.table7 td,table.table7 th{text-align:left}
caption{caption-side:bottom;text-align:left;font-size:.85em;color:#555;padding-top:.3em}
figure{display:inline-block;margin:.4em 1em .8em 0;vertical-align:top}
figcaption{font-size:.85em;color:#444;max-width:360px}
img.pic{image-rendering:pixelated;border:1px solid #bbb;background:#fff}
.legend span.sw{display:inline-block;width:1em;height:1em;border:1px solid #888;vertical-align:middle;margin:0 .3em 0 1em}
.cbar{display:inline-block;width:220px;height:12px;border:1px solid #888;vertical-align:middle;margin:0 .5em}
.note{color:#555;font-size:.9em}
.bad{color:#b00020;font-weight:bold}.ok{color:#1b7f3a;font-weight:bold}.warn{color:#9a5b00;font-weight:bold}\
.warnings{border-left:4px solid #9a5b00;background:#fff8e6;padding:.3em 1em}
pre{background:#f7f7f7;border:1px solid #ddd;padding:.6em;overflow:auto;font-size:.85em;max-height:30em}
details{margin:.4em 0}summary{cursor:pointer;font-weight:600}
nav a{margin-right:1em}
.kv th{text-align:left}
svg text{font-family:inherit}
";

/// Sets `data-images-ok` on <html> to "true" when every <img> has decoded with a non-zero
/// size, "false" if any failed, and the count in `data-images`.
const SCRIPT: &str = "
(function(){var imgs=Array.prototype.slice.call(document.images);
function check(){var ok=imgs.every(function(i){return i.complete&&i.naturalWidth>0;});
var done=imgs.every(function(i){return i.complete;});
document.documentElement.setAttribute('data-images',String(imgs.length));
document.documentElement.setAttribute('data-images-ok',done?String(ok):'pending');}
imgs.forEach(function(i){i.addEventListener('load',check);i.addEventListener('error',check);});
check();window.addEventListener('load',check);})();
";

/// A table of strings: `head` cells, then rows; the first column left-aligned.
pub fn table(class: &str, head: &[String], rows: &[Vec<String>], caption: &str) -> String {
    let mut s = format!("<table class=\"{}\">", esc(class));
    if !caption.is_empty() {
        let _ = write!(s, "<caption>{caption}</caption>");
    }
    s.push_str("<thead><tr>");
    for (k, h) in head.iter().enumerate() {
        let _ = write!(
            s,
            "<th{}>{h}</th>",
            if k == 0 { " class=\"l\"" } else { "" }
        );
    }
    s.push_str("</tr></thead><tbody>");
    for r in rows {
        s.push_str("<tr>");
        for (k, c) in r.iter().enumerate() {
            let _ = write!(
                s,
                "<td{}>{c}</td>",
                if k == 0 { " class=\"l\"" } else { "" }
            );
        }
        s.push_str("</tr>");
    }
    s.push_str("</tbody></table>");
    s
}

/// Key/value table.
pub fn kv(rows: &[(&str, String)]) -> String {
    let mut s = String::from("<table class=\"kv\"><tbody>");
    for (k, v) in rows {
        let _ = write!(s, "<tr><th>{}</th><td class=\"l\">{v}</td></tr>", esc(k));
    }
    s.push_str("</tbody></table>");
    s
}

/// A histogram as inline SVG: bars of `counts` over `edges` (in display units), with an
/// optional cumulative curve in percent on the right axis.
pub fn histogram_svg(
    edges: &[f64],
    counts: &[f64],
    cumulative: Option<&[f64]>,
    xlabel: &str,
    ylabel: &str,
) -> String {
    let (w, h, l, r, t, b) = (560.0, 260.0, 60.0, 50.0, 12.0, 42.0);
    let pw = w - l - r;
    let ph = h - t - b;
    let (x0, x1) = (edges[0], edges[edges.len() - 1]);
    let xs = |x: f64| l + (x - x0) / (x1 - x0).max(f64::MIN_POSITIVE) * pw;
    let ymax = counts
        .iter()
        .copied()
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    let ys = |y: f64| t + ph - y / ymax * ph;
    let mut s = format!(
        "<svg class=\"chart\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" \
         xmlns=\"http://www.w3.org/2000/svg\" role=\"img\">"
    );
    for (k, c) in counts.iter().enumerate() {
        let (a, bb) = (xs(edges[k]), xs(edges[k + 1]));
        let _ = write!(
            s,
            "<rect x=\"{a:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"#d6a65c\" \
             stroke=\"#8a6a3a\" stroke-width=\"0.5\"/>",
            ys(*c),
            (bb - a).max(0.5),
            t + ph - ys(*c)
        );
    }
    if let Some(cum) = cumulative {
        let pts: Vec<String> = cum
            .iter()
            .enumerate()
            .map(|(k, c)| format!("{:.1},{:.1}", xs(edges[k + 1]), t + ph - c / 100.0 * ph))
            .collect();
        let _ = write!(
            s,
            "<polyline points=\"{:.1},{:.1} {}\" fill=\"none\" stroke=\"#2e68b4\" stroke-width=\"2\"/>",
            xs(edges[0]),
            t + ph,
            pts.join(" ")
        );
        for k in 0..=4 {
            let y = t + ph - k as f64 / 4.0 * ph;
            let _ = write!(
                s,
                "<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"11\" fill=\"#2e68b4\">{}</text>",
                l + pw + 4.0,
                y + 4.0,
                k * 25
            );
        }
        let _ = write!(
            s,
            "<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"11\" fill=\"#2e68b4\" transform=\"rotate(90 {:.1} {:.1})\">cumulative volume [%]</text>",
            w - 8.0,
            t + 20.0,
            w - 8.0,
            t + 20.0
        );
    }
    axes(&mut s, l, t, pw, ph, (x0, x1), (0.0, ymax), xlabel, ylabel);
    s.push_str("</svg>");
    s
}

/// Axes with ticks for a chart whose plot area is (l, t, pw, ph).
#[allow(clippy::too_many_arguments)]
fn axes(
    s: &mut String,
    l: f64,
    t: f64,
    pw: f64,
    ph: f64,
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
    xlabel: &str,
    ylabel: &str,
) {
    let _ = write!(
        s,
        "<path d=\"M{l},{t} V{} H{}\" fill=\"none\" stroke=\"#333\"/>",
        t + ph,
        l + pw
    );
    for k in 0..=4 {
        let f = k as f64 / 4.0;
        let x = l + f * pw;
        let _ = write!(
            s,
            "<text x=\"{x:.1}\" y=\"{:.1}\" font-size=\"11\" text-anchor=\"middle\">{}</text>",
            t + ph + 15.0,
            plain(x0 + f * (x1 - x0))
        );
        let y = t + ph - f * ph;
        let _ = write!(
            s,
            "<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"11\" text-anchor=\"end\">{}</text>",
            l - 4.0,
            y + 4.0,
            plain(y0 + f * (y1 - y0))
        );
    }
    let _ = write!(
        s,
        "<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"12\" text-anchor=\"middle\">{}</text>",
        l + pw / 2.0,
        t + ph + 34.0,
        esc(xlabel)
    );
    let _ = write!(
        s,
        "<text x=\"14\" y=\"{:.1}\" font-size=\"12\" text-anchor=\"middle\" transform=\"rotate(-90 14 {:.1})\">{}</text>",
        t + ph / 2.0,
        t + ph / 2.0,
        esc(ylabel)
    );
}

/// A number for SVG text (no markup).
pub fn plain(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if (1e-2..1e5).contains(&a) {
        let digits = (2 - a.log10().floor() as i32).max(0) as usize;
        format!("{v:.digits$}")
    } else {
        format!("{v:.2e}")
    }
}

/// A violin plot of one sample as inline SVG: the mirrored kernel density, the individual
/// values as dots, the mean as a bar and its 90 % confidence interval as a whisker.
pub fn violin_svg(values: &[f64], label: &str) -> String {
    use crate::numbers::{kde, summary};
    let (w, h, l, t, b) = (240.0, 300.0, 70.0, 12.0, 34.0);
    let ph = h - t - b;
    let s = summary(values);
    let (lo, hi) = if s.max > s.min {
        let pad = 0.15 * (s.max - s.min);
        (s.min - pad, s.max + pad)
    } else {
        let pad = if s.mean != 0.0 {
            0.05 * s.mean.abs()
        } else {
            1.0
        };
        (s.mean - pad, s.mean + pad)
    };
    let ys = |v: f64| t + ph - (v - lo) / (hi - lo) * ph;
    let cx = l + (w - l) / 2.0 - 5.0;
    let half = (w - l) / 2.0 - 20.0;
    let mut o = format!(
        "<svg class=\"violin\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" \
         xmlns=\"http://www.w3.org/2000/svg\" role=\"img\">"
    );
    let grid: Vec<f64> = (0..=80).map(|k| lo + (hi - lo) * k as f64 / 80.0).collect();
    if let Some(d) = kde(values, &grid) {
        let dmax = d.iter().copied().fold(0.0, f64::max).max(f64::MIN_POSITIVE);
        let mut path = String::new();
        for (k, (&v, &dv)) in grid.iter().zip(&d).enumerate() {
            let _ = write!(
                path,
                "{}{:.1},{:.1} ",
                if k == 0 { "M" } else { "L" },
                cx + dv / dmax * half,
                ys(v)
            );
        }
        for (&v, &dv) in grid.iter().zip(&d).rev() {
            let _ = write!(path, "L{:.1},{:.1} ", cx - dv / dmax * half, ys(v));
        }
        let _ = write!(
            o,
            "<path d=\"{path}Z\" fill=\"#c9daf0\" stroke=\"#2e68b4\" stroke-width=\"1\"/>"
        );
    }
    for v in values.iter().filter(|v| v.is_finite()) {
        let _ = write!(
            o,
            "<circle cx=\"{cx:.1}\" cy=\"{:.1}\" r=\"2.2\" fill=\"#333\" fill-opacity=\"0.6\"/>",
            ys(*v)
        );
    }
    if s.ci90.is_finite() {
        let _ = write!(
            o,
            "<path d=\"M{:.1},{:.1} V{:.1} M{:.1},{:.1} H{:.1} M{:.1},{:.1} H{:.1}\" stroke=\"#b00020\" stroke-width=\"2\"/>",
            cx + half * 0.6,
            ys(s.mean - s.ci90),
            ys(s.mean + s.ci90),
            cx + half * 0.6 - 5.0,
            ys(s.mean - s.ci90),
            cx + half * 0.6 + 5.0,
            cx + half * 0.6 - 5.0,
            ys(s.mean + s.ci90),
            cx + half * 0.6 + 5.0
        );
    }
    let _ = write!(
        o,
        "<path d=\"M{:.1},{:.1} H{:.1}\" stroke=\"#b00020\" stroke-width=\"2.5\"/>",
        cx - half * 0.4,
        ys(s.mean),
        cx + half * 0.4
    );
    axes(
        &mut o,
        l,
        t,
        w - l - 10.0,
        ph,
        (f64::NAN, f64::NAN),
        (lo, hi),
        label,
        "",
    );
    o.push_str("</svg>");
    // The x ticks of a violin are meaningless: drop the NaN labels `axes` wrote.
    o.replace(">NaN</text>", "></text>")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats() {
        assert_eq!(num(4.81e9), "4.81×10<sup>9</sup>");
        assert_eq!(num(0.1613), "0.1613");
        assert_eq!(num(140.0), "140");
        assert_eq!(num(f64::NAN), "–");
        assert_eq!(length(1.4e-4), "140 µm");
        assert_eq!(pct(0.0948), "9.48 %");
        assert_eq!(esc("<a href=\"x\">&"), "&lt;a href=&quot;x&quot;&gt;&amp;");
    }
}
