//! HTML building blocks: escaping, number and unit formatting, the page frame with its
//! style sheet, embedded PNGs and tables (charts: [`crate::plots`]). Everything is inline so a page
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

/// A PNG as an `<img>` placed at (left, top) with the given CSS size inside a positioned
/// frame (a slice under its axes).
pub fn img_at(png: &[u8], alt: &str, left: i32, top: i32, width: i32, height: i32) -> String {
    let b64 = base64::engine::general_purpose::STANDARD.encode(png);
    format!(
        "<img src=\"data:image/png;base64,{b64}\" alt=\"{}\" width=\"{width}\" \
         height=\"{height}\" class=\"pic\" style=\"left:{left}px;top:{top}px\">",
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
.frame{position:relative}.frame img.pic{position:absolute;border:0}.frame svg{position:absolute;left:0;top:0}
figure.slice figcaption{max-width:460px}
#pictures img.pic{image-rendering:auto}
svg.violin,svg.chart{display:block;margin:.4em 0}
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
