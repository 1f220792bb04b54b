//! The HTML of a run report and of a single artifact (the `html` export format), from the
//! run record and the extracted report data.

use crate::data::{Body, Col, Item, Picture, Sizes};
use crate::html::{self, esc, kv, num, pct, table};
use crate::numbers;
use crate::record::RunRecord;
use std::collections::HashMap;
use std::fmt::Write;

/// Pictures by file name.
pub type Pics = HashMap<String, Vec<u8>>;

/// Every item with its nesting depth, collection members and the last frame of series
/// included, in order.
fn flatten<'a>(items: &'a [Item], depth: usize, out: &mut Vec<(&'a Item, usize)>) {
    for it in items {
        match &it.body {
            Body::Collection { members, .. } => flatten(members, depth + 1, out),
            Body::Series { last: Some(l), .. } => {
                out.push((it, depth));
                flatten(std::slice::from_ref(l), depth + 1, out)
            }
            _ => out.push((it, depth)),
        }
    }
}

fn step_of(source: &str) -> &str {
    source.split('.').next().unwrap_or(source)
}

fn figure(p: &Picture, pics: &Pics, css_width: usize) -> String {
    match pics.get(&p.file) {
        Some(png) => format!(
            "<figure>{}<figcaption>{}</figcaption></figure>",
            html::img(png, &p.caption, p.width, p.height, css_width),
            esc(&p.caption)
        ),
        None => format!(
            "<p class=\"bad\">picture {} is missing from report-data/</p>",
            esc(&p.file)
        ),
    }
}

/// The horizontal and vertical axes of a picture, from its file name (`stem.xz.png`, a
/// rendering `stem.side.png`).
fn picture_axes(p: &Picture) -> Option<(usize, usize)> {
    match p.file.rsplit('.').nth(1)? {
        "xy" | "top" => Some((0, 1)),
        "xz" | "side" => Some((0, 2)),
        "yz" => Some((1, 2)),
        _ => None,
    }
}

/// A slice or rendering with axes in µm and a scale bar (and a colour bar for fields):
/// `size` is the physical size of the grid or domain [m].
fn framed_figure(
    p: &Picture,
    pics: &Pics,
    css_width: usize,
    size: [f64; 3],
    colorbar: Option<grainpipe_charts::slice::ColorBar>,
) -> String {
    match (pics.get(&p.file), picture_axes(p)) {
        (Some(png), Some((h, v))) => crate::plots::framed(
            p,
            png,
            css_width,
            (size[h] * 1e6, size[v] * 1e6),
            (crate::raster::AXIS[h], crate::raster::AXIS[v]),
            colorbar,
        ),
        _ => figure(p, pics, css_width),
    }
}

fn css_width(p: &Picture) -> usize {
    // Upscale small slices so voxels are visible; keep large ones at most 360 px wide.
    let target = 300.0f64.max(p.width as f64).min(360.0);
    target.round() as usize
}

/// Phase image: legend with fractions and the three mid-plane slices.
pub fn phase_image_html(it: &Item, pics: &Pics) -> String {
    let Body::PhaseImage {
        dims,
        spacing,
        phases,
        slices,
    } = &it.body
    else {
        return String::new();
    };
    let mut s = format!(
        "<div class=\"phase-image\" data-source=\"{}\"><h3>{}</h3><p>{} × {} × {} voxels of {} \
         ({} × {} × {}).</p><p class=\"legend\">",
        esc(&it.source),
        esc(&it.source),
        dims[0],
        dims[1],
        dims[2],
        html::length(spacing[0]),
        html::length(dims[0] as f64 * spacing[0]),
        html::length(dims[1] as f64 * spacing[1]),
        html::length(dims[2] as f64 * spacing[2]),
    );
    for p in phases {
        let [r, g, b] = p.color;
        let _ = write!(
            s,
            "<span class=\"sw\" style=\"background:rgb({r},{g},{b})\"></span>{} (label {}): {}",
            esc(&p.name),
            p.label,
            pct(p.fraction)
        );
    }
    s.push_str("</p>");
    let size = [0, 1, 2].map(|a| dims[a] as f64 * spacing[a]);
    for p in slices {
        s.push_str(&framed_figure(p, pics, css_width(p), size, None));
    }
    s.push_str("</div>");
    s
}

/// Field: the scalar shown, its range with a colour bar, the three slices.
pub fn field_html(it: &Item, pics: &Pics) -> String {
    let Body::Field {
        unit,
        components,
        convention,
        quantity,
        dims,
        spacing,
        min,
        max,
        scale_max,
        mean,
        slices,
        ..
    } = &it.body
    else {
        return String::new();
    };
    let u = if unit.is_empty() { "1" } else { unit };
    let mut s = format!(
        "<div class=\"field\" data-source=\"{}\"><h3>{} — {}</h3><p>{} component(s) ({}) on \
         {} × {} × {} voxels. Shown: {}, from {} to {} {} (mean {} {}).</p>\
         <p>Colour scale: {} {u} to {}{} {u}.</p>",
        esc(&it.source),
        esc(&it.source),
        esc(quantity),
        components,
        esc(convention),
        dims[0],
        dims[1],
        dims[2],
        esc(quantity),
        num(*min),
        num(*max),
        esc(u),
        num(*mean),
        esc(u),
        num(*min),
        if scale_max.is_some_and(|t| t < *max) {
            "≥ "
        } else {
            ""
        },
        num(scale_max.unwrap_or(*max)),
    );
    let size = [0, 1, 2].map(|a| dims[a] as f64 * spacing[a]);
    let top = scale_max.unwrap_or(*max);
    for p in slices {
        let cb = grainpipe_charts::slice::ColorBar {
            lo: *min,
            hi: top,
            label: grainpipe_charts::style::axis_label(quantity, u),
            saturated: top < *max,
        };
        s.push_str(&framed_figure(p, pics, css_width(p), size, Some(cb)));
    }
    s.push_str("</div>");
    s
}

fn sizes_html(sz: &Sizes, what: &str) -> String {
    let um: Vec<f64> = sz.edges.iter().map(|e| e * 1e6).collect();
    let counts: Vec<f64> = sz
        .counts
        .iter()
        .map(|&c| 100.0 * c as f64 / sz.count.max(1) as f64)
        .collect();
    let cum: Vec<f64> = sz.cumulative_volume.iter().map(|c| 100.0 * c).collect();
    format!(
        "<div class=\"sizes\"><h4>Size distribution of the {what}</h4>{}<p>{} {what}; \
         equivalent diameter (of the sphere of the same volume): mean {}; by number D10 {}, \
         D50 {}, D90 {}; by volume D10 {}, D50 {}, D90 {}.</p></div>",
        crate::plots::histogram(
            &um,
            &counts,
            Some(&cum),
            "equivalent diameter [µm]",
            "share by number [%]"
        ),
        sz.count,
        html::length(sz.mean),
        html::length(sz.d_number[0]),
        html::length(sz.d_number[1]),
        html::length(sz.d_number[2]),
        html::length(sz.d_volume[0]),
        html::length(sz.d_volume[1]),
        html::length(sz.d_volume[2]),
    )
}

/// Packing: renderings, counts, size distribution.
pub fn packing_html(it: &Item, pics: &Pics) -> String {
    match &it.body {
        Body::Packing {
            bodies,
            spheres,
            clumps,
            layers,
            volume_fraction,
            domain,
            periodic,
            renders,
            sizes,
        } => {
            let per: Vec<&str> = (0..3)
                .filter(|&a| periodic[a])
                .map(|a| crate::raster::AXIS[a])
                .collect();
            let mut s =
                format!(
                "<div class=\"packing\" data-source=\"{}\"><h3>{}</h3><p>{} {} ({} spheres) in \
                 {} × {} × {}, {} layer(s), solid volume fraction {}, \
                 periodic along {}.</p>",
                esc(&it.source),
                esc(&it.source),
                bodies,
                if *clumps { "grains (clumps)" } else { "spheres" },
                spheres,
                html::length(domain[0]),
                html::length(domain[1]),
                html::length(domain[2]),
                layers,
                pct(*volume_fraction),
                if per.is_empty() {
                    "no axis".to_string()
                } else {
                    per.join(", ")
                }
            );
            for p in renders {
                s.push_str(&framed_figure(p, pics, p.width.min(360), *domain, None));
            }
            if let Some(sz) = sizes {
                s.push_str(&sizes_html(sz, if *clumps { "grains" } else { "spheres" }));
            }
            s.push_str("</div>");
            s
        }
        Body::ClumpLibrary {
            clumps,
            spheres,
            sizes,
        } => {
            let mut s = format!(
                "<div class=\"clump-library\" data-source=\"{}\"><h3>{}</h3><p>{} clumps, {} \
                 spheres ({} per clump on average).</p>",
                esc(&it.source),
                esc(&it.source),
                clumps,
                spheres,
                num(*spheres as f64 / (*clumps).max(1) as f64)
            );
            if let Some(sz) = sizes {
                s.push_str(&sizes_html(sz, "clumps"));
            }
            s.push_str("</div>");
            s
        }
        _ => String::new(),
    }
}

/// A matrix as a table; `scale` divides the values (e.g. 1e9 for GPa).
fn matrix_html(values: &[f64], rows: usize, cols: usize, labels: &[&str], scale: f64) -> String {
    let head: Vec<String> = std::iter::once(String::new())
        .chain((0..cols).map(|j| labels.get(j).map(|l| l.to_string()).unwrap_or_default()))
        .collect();
    let body: Vec<Vec<String>> = (0..rows)
        .map(|i| {
            std::iter::once(labels.get(i).map(|l| l.to_string()).unwrap_or_default())
                .chain((0..cols).map(|j| num(values[i * cols + j] / scale)))
                .collect()
        })
        .collect();
    table("matrix", &head, &body, "")
}

const VOIGT: [&str; 6] = ["11", "22", "33", "23", "13", "12"];
const XYZ: [&str; 3] = ["x", "y", "z"];

/// Engineering constants in the layout of Table 7 of Donval et al. (2025): isotropy (E),
/// transverse isotropy about z (E_L = E_z, E_T = E_x), orthotropy (E_x, E_y, E_z), each
/// with its relative distance to the apparent stiffness.
pub fn table7_html(rows: &[(String, [f64; 12], f64)]) -> String {
    let find = |n: &str| rows.iter().find(|r| r.0 == n);
    let gpa = |v: f64| num(v / 1e9);
    let mut body = vec![];
    if let Some(r) = find("isotropic") {
        body.push(vec![
            "Isotropy".into(),
            format!("E = {} GPa, ν = {}", gpa(r.1[0]), num(r.1[6])),
            pct(r.2),
        ]);
    }
    if let Some(r) = find("transversely_isotropic_z") {
        body.push(vec![
            "Transverse isotropy (z)".into(),
            format!("E_L = {} GPa, E_T = {} GPa", gpa(r.1[2]), gpa(r.1[0])),
            pct(r.2),
        ]);
    }
    if let Some(r) = find("orthotropic") {
        body.push(vec![
            "Orthotropy".into(),
            format!(
                "E_x = {} GPa, E_y = {} GPa, E_z = {} GPa",
                gpa(r.1[0]),
                gpa(r.1[1]),
                gpa(r.1[2])
            ),
            pct(r.2),
        ]);
    }
    let mut s = table(
        "table7",
        &["approximation".into(), "moduli".into(), "error".into()],
        &body,
        "The closest isotropic, transversely isotropic (axis z, E_L along z) and orthotropic \
         stiffness and its relative distance (Mandel norm) to the apparent stiffness (the layout \
         of Table 7 of Donval et al. 2025).",
    );
    let mut head: Vec<String> = vec!["approximation".into()];
    for (k, n) in numbers::ENGINEERING_NAMES.iter().enumerate() {
        head.push(if k < 6 {
            format!("{n} [GPa]")
        } else {
            n.to_string()
        });
    }
    head.push("relative error".into());
    let all: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            std::iter::once(esc(&r.0))
                .chain(
                    r.1.iter()
                        .enumerate()
                        .map(|(k, v)| if k < 6 { gpa(*v) } else { num(*v) }),
                )
                .chain(std::iter::once(pct(r.2)))
                .collect()
        })
        .collect();
    s.push_str(&table(
        "constants",
        &head,
        &all,
        "Engineering constants of each approximation (ν_ij: contraction along j under \
         uniaxial stress along i).",
    ));
    s
}

/// The rows of a `constants` table (approximation, 12 constants, relative error).
fn constants_rows(it: &Item) -> Option<Vec<(String, [f64; 12], f64)>> {
    let Body::Table { columns, rows, .. } = &it.body else {
        return None;
    };
    let col = |n: &str| columns.iter().find(|c| c.name == n);
    let names = col("approximation")?;
    let err = col("relative_error")?;
    let mut out = vec![];
    for i in 0..*rows.min(&names.values.len()) {
        let f = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
        let mut k = [f64::NAN; 12];
        for (j, n) in numbers::ENGINEERING_NAMES.iter().enumerate() {
            k[j] = f(&col(n)?.values[i]);
        }
        out.push((
            names.values[i].as_str().unwrap_or("").to_string(),
            k,
            f(&err.values[i]),
        ));
    }
    Some(out)
}

/// A 6x6 stiffness: matrix in GPa, symmetry error, constants (from the run's `constants`
/// table when given, else apparent and isotropic computed here).
pub fn stiffness_html(it: &Item, constants: Option<&Item>) -> String {
    let Body::Tensor {
        unit,
        values,
        convention,
        ..
    } = &it.body
    else {
        return String::new();
    };
    let mut s = format!(
        "<div class=\"stiffness\" data-source=\"{}\"><h3>{}</h3>",
        esc(&it.source),
        esc(&it.source)
    );
    let gpa = unit == "Pa";
    s.push_str(&matrix_html(
        values,
        6,
        6,
        &VOIGT,
        if gpa { 1e9 } else { 1.0 },
    ));
    let sym = numbers::symmetry_error(values, 6, convention == "voigt");
    let _ = write!(
        s,
        "<p>{} notation, {}; symmetry error |C − Cᵀ| / |C| (Mandel norm) = \
         <span class=\"symmetry-error\">{}</span>.</p>",
        esc(convention),
        if gpa { "GPa".to_string() } else { esc(unit) },
        num(sym)
    );
    let rows = constants.and_then(constants_rows);
    match (rows, numbers::m6(values)) {
        (Some(rows), _) => {
            let _ = write!(
                s,
                "<h4>Engineering constants and symmetry classes (from {})</h4>",
                esc(&constants.map(|c| c.source.clone()).unwrap_or_default())
            );
            s.push_str(&table7_html(&rows));
            if let Some(a) = rows.iter().find(|r| r.0 == "apparent") {
                let _ = write!(
                    s,
                    "<p>Anisotropy: E_x / E_z = {}, E_y / E_z = {}.</p>",
                    num(a.1[0] / a.1[2]),
                    num(a.1[1] / a.1[2])
                );
            }
        }
        (None, Some(c)) if convention == "voigt" => {
            let iso = numbers::isotropic(&c);
            let mut rows = vec![];
            if let Some(k) = numbers::engineering(&c) {
                rows.push(("apparent".to_string(), k, 0.0));
            }
            let g = iso.shear;
            rows.push((
                "isotropic".to_string(),
                [
                    iso.young,
                    iso.young,
                    iso.young,
                    g,
                    g,
                    g,
                    iso.poisson,
                    iso.poisson,
                    iso.poisson,
                    iso.poisson,
                    iso.poisson,
                    iso.poisson,
                ],
                iso.relative_error,
            ));
            s.push_str("<h4>Engineering constants</h4>");
            s.push_str(&table7_html(&rows));
        }
        _ => {}
    }
    s.push_str("</div>");
    s
}

/// A second-order tensor (permeability, conductivity, orientation): matrix, diagonal ratios
/// and symmetry error.
pub fn tensor_html(it: &Item) -> String {
    let Body::Tensor {
        name,
        unit,
        shape,
        values,
        convention,
    } = &it.body
    else {
        return String::new();
    };
    let class = if unit == "m^2" {
        "permeability"
    } else {
        "tensor"
    };
    let mut s = format!(
        "<div class=\"{class}\" data-source=\"{}\"><h3>{} <span class=\"note\">({}{})</span></h3>",
        esc(&it.source),
        esc(&it.source),
        esc(name),
        if unit.is_empty() {
            String::new()
        } else {
            format!(", {}", esc(unit))
        }
    );
    if shape.len() == 2 && shape[0] * shape[1] == values.len() {
        let (r, c) = (shape[0], shape[1]);
        let labels: &[&str] = if r == 6 { &VOIGT } else { &XYZ };
        s.push_str(&matrix_html(values, r, c, labels, 1.0));
        if r == c {
            let sym = numbers::symmetry_error(values, r, convention == "voigt");
            let _ = write!(
                s,
                "<p>Symmetry error |K − Kᵀ| / |K| (Frobenius) = <span class=\"symmetry-error\">{}</span>",
                num(sym)
            );
            if r == 3 {
                let d = [values[0], values[4], values[8]];
                let _ = write!(
                    s,
                    "; diagonal {} {}, {} {}, {} {}; z / x = {}, z / y = {}",
                    num(d[0]),
                    esc(unit),
                    num(d[1]),
                    esc(unit),
                    num(d[2]),
                    esc(unit),
                    num(d[2] / d[0]),
                    num(d[2] / d[1])
                );
                if unit == "m^2" {
                    let _ = write!(
                        s,
                        " (1 darcy = 9.869×10<sup>−13</sup> m²: κ_zz = {} D)",
                        num(d[2] / 9.869233e-13)
                    );
                }
            }
            s.push_str(".</p>");
        }
    } else {
        let _ = write!(
            s,
            "<p>shape {:?}: {}</p>",
            shape,
            values
                .iter()
                .map(|v| num(*v))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    s.push_str("</div>");
    s
}

/// A table, cut to its first and last rows when long.
pub fn table_html(it: &Item) -> String {
    let Body::Table {
        name,
        rows,
        columns,
        ..
    } = &it.body
    else {
        return String::new();
    };
    let head: Vec<String> = columns
        .iter()
        .map(|c| {
            if c.unit.is_empty() {
                esc(&c.name)
            } else {
                format!("{} [{}]", esc(&c.name), esc(&c.unit))
            }
        })
        .collect();
    let shown = columns.first().map(|c| c.values.len()).unwrap_or(0);
    let body: Vec<Vec<String>> = (0..shown)
        .map(|i| {
            columns
                .iter()
                .map(|c| match &c.values[i] {
                    serde_json::Value::Number(n) => num(n.as_f64().unwrap_or(f64::NAN)),
                    serde_json::Value::String(t) => esc(t),
                    serde_json::Value::Null => "–".into(),
                    v => esc(&v.to_string()),
                })
                .collect()
        })
        .collect();
    let caption = if shown < *rows {
        format!(
            "{} rows; the first and last {} shown (the exported file has all of them).",
            rows,
            shown / 2
        )
    } else {
        format!("{rows} row(s).")
    };
    format!(
        "<div class=\"table\" data-source=\"{}\"><h3>{} <span class=\"note\">({})</span></h3>{}{}</div>",
        esc(&it.source),
        esc(&it.source),
        esc(name),
        distribution_chart(name, columns, *rows).unwrap_or_default(),
        table("data", &head, &body, &caption)
    )
}

/// The chart of a distribution table a stage writes (analysis.local_thickness: volume share
/// per diameter bin and the cumulative share), when the item holds all of its rows.
fn distribution_chart(name: &str, columns: &[Col], rows: usize) -> Option<String> {
    if name != "local_thickness" {
        return None;
    }
    let col = |n: &str| -> Option<Vec<f64>> {
        let c = columns.iter().find(|c| c.name == n)?;
        Some(
            c.values
                .iter()
                .map(|v| v.as_f64().unwrap_or(f64::NAN))
                .collect(),
        )
    };
    let (lower, upper) = (col("diameter_lower")?, col("diameter_upper")?);
    let (share, cumulative) = (col("volume_fraction")?, col("cumulative")?);
    if lower.is_empty() || lower.len() != rows {
        return None;
    }
    let mut edges: Vec<f64> = lower.iter().map(|d| d * 1e6).collect();
    edges.push(upper[upper.len() - 1] * 1e6);
    Some(crate::plots::histogram(
        &edges,
        &share.iter().map(|v| 100.0 * v).collect::<Vec<_>>(),
        Some(&cumulative.iter().map(|v| 100.0 * v).collect::<Vec<_>>()),
        "local thickness (diameter of the largest ball) [µm]",
        "share of the phase's volume [%]",
    ))
}

/// Any item as HTML (collections member by member).
pub fn item_html(it: &Item, pics: &Pics) -> String {
    match &it.body {
        Body::PhaseImage { .. } => phase_image_html(it, pics),
        Body::Field { .. } => field_html(it, pics),
        Body::Packing { .. } | Body::ClumpLibrary { .. } => packing_html(it, pics),
        Body::Table { .. } => table_html(it),
        Body::Tensor { shape, .. } if shape == &[6, 6] => stiffness_html(it, None),
        Body::Tensor { .. } => tensor_html(it),
        Body::ContactGraph {
            contacts,
            bonds,
            bodies,
        } => format!(
            "<div class=\"contacts\"><h3>{}</h3><p>{contacts} contacts and {bonds} bonds between \
             {bodies} bodies.</p></div>",
            esc(&it.source)
        ),
        Body::Series {
            frames,
            times,
            last,
        } => {
            let mut s = format!(
                "<div class=\"series\"><h3>{}</h3><p>{frames} frames from t = {} s to {} s; the \
                 last frame:</p>",
                esc(&it.source),
                num(times[0]),
                num(times[1])
            );
            if let Some(l) = last {
                s.push_str(&item_html(l, pics));
            }
            s.push_str("</div>");
            s
        }
        Body::Collection { members, total } => {
            let mut s = format!(
                "<div class=\"collection\"><h3>{}</h3><p>{} member(s); shown: {}</p>",
                esc(&it.source),
                total.max(&members.len()),
                members
                    .iter()
                    .map(|m| esc(m.source.rsplit('.').next().unwrap_or("")))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
            for m in members {
                s.push_str(&item_html(m, pics));
            }
            s.push_str("</div>");
            s
        }
    }
}

/// The pipeline's `reference:` values beside this run's: each result in the unit its
/// reference was written in, the relative difference, and whether it lies within the stated
/// tolerance (a comparison without tolerance is shown, not judged).
pub fn reference_html(r: &crate::record::ReferenceRecord) -> String {
    use grainpipe_core::values::Verdict;
    let rows: Vec<Vec<String>> = r
        .rows
        .iter()
        .map(|c| {
            let (factor, unit) = c.written_unit();
            let result = match c.result {
                Some(x) => format!("{} {}", num(x / factor), esc(unit)),
                None => format!("<span class=\"warn\">not computed</span> {}", esc(&c.why)),
            };
            let verdict = match c.verdict {
                Verdict::Within => "<span class=\"ok\">within</span>",
                Verdict::Outside => "<span class=\"bad\">outside</span>",
                Verdict::Compared => "no tolerance given",
                Verdict::Missing => "<span class=\"warn\">missing</span>",
            };
            vec![
                format!(
                    "<code>{}</code>{}",
                    esc(&c.quantity),
                    c.component
                        .as_ref()
                        .map(|k| format!(" ({})", esc(k)))
                        .unwrap_or_default()
                ),
                result,
                esc(&c.reference_written),
                match (c.difference(), c.relative_difference) {
                    (Some(d), Some(r)) => format!(
                        "{}{} {} ({})",
                        if d < 0.0 { "−" } else { "+" },
                        num(d.abs() / factor),
                        esc(unit),
                        signed_pct(r)
                    ),
                    _ => "–".into(),
                },
                if c.tolerance.is_empty() {
                    "–".into()
                } else {
                    format!("± {}", esc(&c.tolerance))
                },
                verdict.into(),
            ]
        })
        .collect();
    let within = r
        .rows
        .iter()
        .filter(|c| c.verdict == Verdict::Within)
        .count();
    let judged = r
        .rows
        .iter()
        .filter(|c| matches!(c.verdict, Verdict::Within | Verdict::Outside))
        .count();
    let mut out = format!(
        "<p>Reference: {}.{}</p>",
        esc(&r.source),
        if r.note.is_empty() {
            String::new()
        } else {
            format!(" {}", esc(&r.note))
        }
    );
    if judged > 0 {
        let _ = write!(
            out,
            "<p id=\"reference-verdict\" class=\"{}\">{within} of {judged} within their tolerance</p>",
            if within == judged { "ok" } else { "bad" }
        );
    }
    out.push_str(&table(
        "reference",
        &[
            "quantity".into(),
            "this run".into(),
            "reference".into(),
            "difference".into(),
            "tolerance".into(),
            "".into(),
        ],
        &rows,
        "",
    ));
    out
}

/// A relative difference with its sign (`+3.2 %`, `−12.0 %`).
fn signed_pct(v: f64) -> String {
    if v < 0.0 {
        format!("−{}", pct(-v))
    } else {
        format!("+{}", pct(v))
    }
}

/// "2026-11-24 23:05:12 UTC" from Unix seconds (civil-from-days, proleptic Gregorian).
pub fn utc(secs: f64) -> String {
    let s = secs.max(0.0) as i64;
    let (days, rem) = (s.div_euclid(86400), s.rem_euclid(86400));
    let z = days + 719468;
    let era = z.div_euclid(146097);
    let doe = z - era * 146097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02} UTC",
        rem / 3600,
        rem / 60 % 60,
        rem % 60
    )
}

fn section(id: &str, title: &str, content: &str) -> String {
    format!("<section id=\"{id}\"><h2>{title}</h2>{content}</section>\n")
}

/// The run report.
pub fn run_page(rec: &RunRecord, data: &crate::data::ReportData, pics: &Pics) -> String {
    let mut nested = vec![];
    flatten(&data.items, 0, &mut nested);
    // Top-level results first, members of collections (grains, load cases) after them.
    nested.sort_by_key(|x| x.1);
    let all: Vec<&Item> = nested.iter().map(|x| x.0).collect();
    let top: Vec<&Item> = nested.iter().filter(|x| x.1 == 0).map(|x| x.0).collect();
    let of = |f: &dyn Fn(&Body) -> bool| -> Vec<&Item> {
        all.iter().copied().filter(|i| f(&i.body)).collect()
    };
    let images = of(&|b| matches!(b, Body::PhaseImage { .. }));
    let packings = of(&|b| matches!(b, Body::Packing { .. } | Body::ClumpLibrary { .. }));
    let fields = of(&|b| matches!(b, Body::Field { .. }));
    let stiff = of(&|b| matches!(b, Body::Tensor { shape, .. } if shape == &[6, 6]));
    let perm =
        of(&|b| matches!(b, Body::Tensor { unit, shape, .. } if unit == "m^2" && shape == &[3, 3]));
    let other_tensors = of(
        &|b| matches!(b, Body::Tensor { unit, shape, .. } if shape != &[6, 6] && !(unit == "m^2" && shape == &[3, 3])),
    );
    let tables = of(&|b| matches!(b, Body::Table { .. }));
    let others = of(&|b| matches!(b, Body::ContactGraph { .. } | Body::Series { .. }));
    // What the run computed over iterations or time: the charts of its history tables, each
    // solver's residual against the tolerance of its step.
    let histories: Vec<String> = tables
        .iter()
        .filter(|i| matches!(&i.body, Body::Table { name, .. } if name.contains("history")))
        .flat_map(|it| {
            let step = step_of(&it.source);
            let tol = rec
                .provenance
                .iter()
                .find(|p| p.step == step)
                .and_then(|p| crate::plots::tolerance(&p.params));
            crate::plots::history_charts(it, tol)
        })
        .collect();
    let exported = exported_pngs(rec, pics);

    let mut body = String::new();
    let ok = rec.status == "ok";
    let warned = !rec.warnings.is_empty();
    // A run that warned did not simply "complete": the status says so in amber.
    let (class, status) = match (ok, warned) {
        (false, _) => ("bad", "FAILED".to_string()),
        (true, true) => (
            "warn",
            format!(
                "completed with {} warning{}",
                rec.warnings.len(),
                if rec.warnings.len() == 1 { "" } else { "s" }
            ),
        ),
        (true, false) => ("ok", "completed".to_string()),
    };
    let _ = write!(
        body,
        "<header id=\"top\"><h1>{} <span class=\"{class}\" id=\"status\">{status}</span></h1><p>{}</p>\
         <nav>",
        esc(&rec.pipeline_name),
        esc(&rec.description)
    );
    for (id, t, n) in [
        ("summary", "Summary", 1),
        (
            "reference",
            "Reference",
            usize::from(rec.reference.is_some()),
        ),
        ("microstructure", "Microstructure", images.len()),
        ("packing", "Packing", packings.len()),
        ("fields", "Fields", fields.len()),
        ("convergence", "Convergence", histories.len()),
        ("pictures", "Exported pictures", exported.len()),
        ("stiffness", "Stiffness", stiff.len()),
        ("permeability", "Permeability", perm.len()),
        ("tensors", "Other tensors", other_tensors.len()),
        ("tables", "Tables", tables.len()),
        ("steps", "Steps", 1),
        ("exports", "Exports", 1),
        ("provenance", "Provenance", 1),
    ] {
        if n > 0 {
            let _ = write!(body, "<a href=\"#{id}\">{t}</a>");
        }
    }
    body.push_str("</nav></header>\n");
    if warned {
        body.push_str(&warnings_block(&rec.warnings));
    }

    // Summary: the run and the headline numbers.
    let peak = rec.steps.iter().filter_map(|s| s.peak_heap_bytes).max();
    let mut rows: Vec<(&str, String)> = vec![
        ("pipeline file", esc(&rec.pipeline_file)),
        ("seed", rec.seed.to_string()),
        ("started", utc(rec.started_unix_s)),
        ("wall time", format!("{} s", num(rec.wall_s))),
        (
            "peak heap",
            peak.map(html::bytes)
                .unwrap_or_else(|| "not measured".into()),
        ),
        (
            "host",
            format!("{} ({} threads)", esc(&rec.host), rec.threads),
        ),
        ("grainpipe", esc(&rec.grainpipe_version)),
    ];
    if !rec.overrides.is_empty() {
        rows.push(("overrides", esc(&rec.overrides.join(" "))));
    }
    let cut: Vec<String> = data
        .items
        .iter()
        .filter_map(|it| match &it.body {
            Body::Collection { members, total } if *total > members.len() => Some(format!(
                "{}: the first {} of {} members are shown",
                esc(&it.source),
                members.len(),
                total
            )),
            _ => None,
        })
        .collect();
    if !cut.is_empty() {
        rows.push(("collections", cut.join("; ")));
    }
    let mut summary = kv(&rows);
    if let Some(e) = &rec.error {
        let _ = write!(
            summary,
            "<p class=\"bad\" id=\"error\">The run failed: {}</p>",
            esc(e)
        );
    }
    let mut headline = vec![];
    let is_top = |it: &&&Item| top.iter().any(|t| std::ptr::eq(*t, **it));
    for it in images.iter().filter(is_top) {
        if let Body::PhaseImage { phases, .. } = &it.body {
            let f: Vec<String> = phases
                .iter()
                .map(|p| format!("{} {}", esc(&p.name), pct(p.fraction)))
                .collect();
            headline.push(vec![format!("phases ({})", esc(&it.source)), f.join(", ")]);
        }
    }
    for it in stiff.iter().filter(is_top) {
        if let Body::Tensor { values, .. } = &it.body {
            if let Some(k) = numbers::m6(values).and_then(|c| numbers::engineering(&c)) {
                headline.push(vec![
                    format!("Young's moduli ({})", esc(&it.source)),
                    format!(
                        "E_x {} GPa, E_y {} GPa, E_z {} GPa",
                        num(k[0] / 1e9),
                        num(k[1] / 1e9),
                        num(k[2] / 1e9)
                    ),
                ]);
            }
        }
    }
    for it in perm.iter().filter(is_top) {
        if let Body::Tensor { values, .. } = &it.body {
            headline.push(vec![
                format!("permeability ({})", esc(&it.source)),
                format!(
                    "κ_xx {} m², κ_yy {} m², κ_zz {} m²",
                    num(values[0]),
                    num(values[4]),
                    num(values[8])
                ),
            ]);
        }
    }
    if !headline.is_empty() {
        summary.push_str(&table(
            "headline",
            &["result".into(), "value".into()],
            &headline,
            "",
        ));
    }
    body.push_str(&section("summary", "Summary", &summary));
    if let Some(r) = &rec.reference {
        body.push_str(&section(
            "reference",
            "Comparison with the pipeline's reference",
            &reference_html(r),
        ));
    }

    let join = |v: &[&Item], f: &dyn Fn(&Item) -> String| -> String {
        v.iter().map(|i| f(i)).collect::<Vec<_>>().join("\n")
    };
    if !images.is_empty() {
        body.push_str(&section(
            "microstructure",
            "Microstructure: phase images",
            &format!(
                "<p class=\"note\">Mid-plane slices, one pixel per voxel.</p>{}",
                join(&images, &|i| phase_image_html(i, pics))
            ),
        ));
    }
    if !packings.is_empty() {
        body.push_str(&section(
            "packing",
            "Packing and size distributions",
            &format!(
                "<p class=\"note\">Orthographic renderings, depth-shaded, one colour per body, \
                 clipped to the domain box.</p>{}",
                join(&packings, &|i| packing_html(i, pics))
            ),
        ));
    }
    if !fields.is_empty() {
        body.push_str(&section(
            "fields",
            "Fields",
            &format!(
                "<p class=\"note\">Mid-plane slices of the magnitude (vectors), the von Mises \
                 equivalent (stresses) or the value (scalars), on a linear colour scale from the \
                 field's minimum to its 99th percentile (brighter values saturate).</p>{}",
                join(&fields, &|i| field_html(i, pics))
            ),
        ));
    }
    if !histories.is_empty() {
        body.push_str(&section(
            "convergence",
            "Convergence and histories",
            &format!(
                "<p class=\"note\">From the steps' history tables: solver residuals against the \
                 iteration on a log scale, with the step's tolerance as a line (one line per load \
                 case or direction); energies; temperatures and bonds against time.</p>{}",
                histories.join("\n")
            ),
        ));
    }
    if !exported.is_empty() {
        let mut t =
            String::from("<p class=\"note\">The PNG files the run exported, as written.</p>");
        for (e, png) in &exported {
            let (w, h) = png_size(png).unwrap_or((560, 400));
            let _ = write!(
                t,
                "<figure>{}<figcaption>{} (from {})</figcaption></figure>",
                html::img(png, &e.path, w, h, w.min(560)),
                esc(&e.path),
                esc(&e.from)
            );
        }
        body.push_str(&section("pictures", "Exported pictures", &t));
    }
    if !stiff.is_empty() {
        body.push_str(&section(
            "stiffness",
            "Apparent stiffness",
            &join(&stiff, &|i| {
                let step = step_of(&i.source);
                let constants = all
                    .iter()
                    .copied()
                    .find(|c| step_of(&c.source) == step && constants_rows(c).is_some());
                stiffness_html(i, constants)
            }),
        ));
    }
    if !perm.is_empty() {
        body.push_str(&section(
            "permeability",
            "Permeability",
            &join(&perm, &|i| tensor_html(i)),
        ));
    }
    if !other_tensors.is_empty() {
        body.push_str(&section(
            "tensors",
            "Other tensors",
            &join(&other_tensors, &|i| tensor_html(i)),
        ));
    }
    if !tables.is_empty() || !others.is_empty() {
        let mut t = String::new();
        for it in tables.iter().chain(&others) {
            let _ = write!(
                t,
                "<details><summary>{}</summary>{}</details>",
                esc(&it.source),
                item_html(it, pics)
            );
        }
        body.push_str(&section("tables", "Tables", &t));
    }

    // Steps: wall time and memory, with bars proportional to the wall time.
    let total: f64 = rec.steps.iter().map(|s| s.wall_s).sum();
    let tmax = rec.steps.iter().map(|s| s.wall_s).fold(0.0, f64::max);
    let mut rows: Vec<Vec<String>> = rec
        .steps
        .iter()
        .map(|s| {
            vec![
                esc(&s.step),
                esc(&s.stage),
                format!("{:.3}", s.wall_s),
                format!(
                    "<span style=\"display:inline-block;background:#2e68b4;height:.8em;width:{:.0}px\"></span>",
                    200.0 * s.wall_s / tmax.max(f64::MIN_POSITIVE)
                ),
                {
                    let how = if s.from_cache { "cache" } else { "computed" };
                    let n = rec.warnings.iter().filter(|w| w.step == s.step).count();
                    match n {
                        0 => how.to_string(),
                        _ => format!(
                            "{how}, <a class=\"warn\" href=\"#warnings\">{n} warning{}</a>",
                            if n == 1 { "" } else { "s" }
                        ),
                    }
                },
                s.peak_bytes.map(html::bytes).unwrap_or_else(|| "–".into()),
                s.peak_heap_bytes
                    .map(html::bytes)
                    .unwrap_or_else(|| "–".into()),
            ]
        })
        .collect();
    rows.push(vec![
        "<b>total</b>".into(),
        String::new(),
        format!("<b>{total:.3}</b>"),
        String::new(),
        String::new(),
        String::new(),
        peak.map(html::bytes).unwrap_or_else(|| "–".into()),
    ]);
    body.push_str(&section(
        "steps",
        "Steps: wall time and memory",
        &table(
            "steps",
            &[
                "step".into(),
                "stage".into(),
                "wall [s]".into(),
                String::new(),
                "result".into(),
                "peak memory (step)".into(),
                "peak heap (process)".into(),
            ],
            &rows,
            "Peak memory: the largest growth of the heap during the step over what was live when \
             it started; peak heap: the largest live heap of the whole process during the step. \
             Steps read from the cache take no compute time.",
        ),
    ));

    let ex: Vec<Vec<String>> = rec
        .exports
        .iter()
        .map(|e| {
            vec![
                esc(&e.from),
                esc(&e.path),
                esc(&e.format),
                if e.written { "written" } else { "not written" }.into(),
            ]
        })
        .collect();
    body.push_str(&section(
        "exports",
        "Exports",
        &table(
            "exports",
            &["from".into(), "file".into(), "format".into(), "".into()],
            &ex,
            "",
        ),
    ));

    let mut prov = String::new();
    for p in &rec.provenance {
        let inputs: Vec<String> = p
            .inputs
            .iter()
            .map(|(k, v)| format!("{} ← {}", esc(k), esc(v)))
            .collect();
        let files: Vec<String> = p
            .input_files
            .iter()
            .map(|(k, v)| format!("{} (BLAKE3 {})", esc(k), esc(v)))
            .collect();
        let _ = write!(
            prov,
            "<details class=\"provenance\"><summary>{} — {} {}</summary>{}<pre>{}</pre></details>",
            esc(&p.step),
            esc(&p.stage),
            esc(&p.stage_version),
            kv(&[
                ("origin", esc(&p.origin)),
                ("step seed", p.seed.to_string()),
                ("cache key", esc(&p.cache_key)),
                ("inputs", inputs.join(", ")),
                ("input files", files.join(", ")),
            ]),
            esc(&serde_json::to_string_pretty(&p.params).unwrap_or_default())
        );
    }
    let _ = write!(
        prov,
        "<details><summary>pipeline as run (overrides applied)</summary><pre>{}</pre></details>\
         <details><summary>pipeline file {}</summary><pre>{}</pre></details>",
        esc(&rec.effective_yaml),
        esc(&rec.pipeline_file),
        esc(&rec.source_yaml)
    );
    body.push_str(&section("provenance", "Provenance", &prov));
    let _ = write!(
        body,
        "<footer><p class=\"note\">Written by grainpipe {} (<code>pipe report</code>) from \
         run.json and report-data/.</p></footer>",
        esc(&rec.grainpipe_version)
    );
    html::page(&format!("{} — grainpipe report", rec.pipeline_name), &body)
}

/// The key under which [`crate::render_dir`] puts an exported file's bytes into the pictures.
pub fn export_key(path: &str) -> String {
    format!("export:{path}")
}

/// Exported PNG files bigger than this are not embedded.
const MAX_EMBEDDED_PNG: usize = 8 << 20;

/// The PNG exports of a run that were written, with their bytes (from `pics`, else read from
/// the recorded path).
fn exported_pngs<'a>(
    rec: &'a RunRecord,
    pics: &Pics,
) -> Vec<(&'a crate::record::ExportRecord, Vec<u8>)> {
    rec.exports
        .iter()
        .filter(|e| e.written && e.path.to_ascii_lowercase().ends_with(".png"))
        .filter_map(|e| {
            let bytes = pics
                .get(&export_key(&e.path))
                .cloned()
                .or_else(|| std::fs::read(&e.path).ok())?;
            (bytes.starts_with(b"\x89PNG") && bytes.len() <= MAX_EMBEDDED_PNG).then_some((e, bytes))
        })
        .collect()
}

/// Width and height from a PNG's header.
fn png_size(png: &[u8]) -> Option<(usize, usize)> {
    let w = u32::from_be_bytes(png.get(16..20)?.try_into().ok()?);
    let h = u32::from_be_bytes(png.get(20..24)?.try_into().ok()?);
    Some((w as usize, h as usize))
}

/// The warnings of a run, at the top of its page: one line per warning, with its step.
fn warnings_block(warnings: &[crate::record::WarningRecord]) -> String {
    let mut out = String::from("<section id=\"warnings\" class=\"warnings\"><h2>Warnings</h2><ul>");
    for w in warnings {
        let _ = write!(
            out,
            "<li><span class=\"step\">{}</span>: {}</li>",
            esc(&w.step),
            esc(&w.text)
        );
    }
    out.push_str("</ul></section>\n");
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn utc_dates() {
        assert_eq!(super::utc(0.0), "1970-01-01 00:00:00 UTC");
        // 2000-02-29 12:34:56 UTC = 951827696.
        assert_eq!(super::utc(951827696.0), "2000-02-29 12:34:56 UTC");
    }

    /// A local-thickness distribution gets its histogram (one bar per bin, the cumulative
    /// curve), other tables none.
    #[test]
    fn local_thickness_table_gets_a_histogram() {
        use crate::data::Col;
        let col = |name: &str, v: &[f64]| Col {
            name: name.into(),
            unit: "m".into(),
            values: v.iter().map(|&x| serde_json::json!(x)).collect(),
        };
        let columns = vec![
            col("diameter_lower", &[0.0, 1e-5, 2e-5]),
            col("diameter_upper", &[1e-5, 2e-5, 3e-5]),
            col("volume_fraction", &[0.2, 0.5, 0.3]),
            col("cumulative", &[0.2, 0.7, 1.0]),
        ];
        let svg = super::distribution_chart("local_thickness", &columns, 3).unwrap();
        assert!(
            svg.starts_with("<svg class=\"chart histogram\" data-bars=\"3\""),
            "{svg}"
        );
        assert!(svg.contains("polyline") && svg.contains("µm"));
        assert!(svg.contains("cumulative volume [%]"));
        assert!(super::distribution_chart("phases", &columns, 3).is_none());
        // a table cut to its first and last rows is not drawn
        assert!(super::distribution_chart("local_thickness", &columns, 90).is_none());
    }
}
