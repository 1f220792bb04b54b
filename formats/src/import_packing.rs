//! `import.packing`: a sphere packing made elsewhere (a DEM run, another packer, a paper's
//! supplementary data) or written by grainpipe itself, as a [`Packing`].
//!
//! Three formats:
//! - CSV with a header row naming the columns `x, y, z` and `r` (or `radius`, or `diameter`/`d`),
//!   optionally `body` (an id kept as the body attribute `body`) and `layer`; a header may carry
//!   its column's unit (`x [um]`, `r (mm)`), other columns take the `unit` parameter. The
//!   delimiter is `,`, `;`, a tab or white space (whichever the header uses); blank lines and
//!   lines starting with `#` are skipped. A CSV has no box: `box` is required.
//! - our plain HDF5 packings (`.h5`, `.hdf5`, see [`crate::hdf5_plain`]): spheres, clumps with
//!   their library, layers, orientations and body attributes, exactly as written.
//! - LIGGGHTS/LAMMPS text dumps (`dump ... custom`): `ITEM: TIMESTEP`, `ITEM: NUMBER OF
//!   ATOMS`, `ITEM: BOX BOUNDS` with its boundary flags (`pp` = periodic), `ITEM: ATOMS` with
//!   columns located by name (`x y z` or unwrapped `xu yu zu` or scaled `xs ys zs`; `radius` or
//!   `diameter`; `id` and `type` kept as body attributes). The last frame, or frame `frame`.
//!   Atoms are ordered by `id` (LAMMPS writes them in processor order, which changes with the
//!   number of processes).
//!
//! The whole file is parsed in preflight, so every error (missing column, non-numeric value,
//! radius <= 0, NaN, a centre outside a non-periodic box, an unknown unit, an empty file, a
//! frame out of range) stops the pipeline before anything runs, with the file and line; the
//! parsed packing is the plan `run` hands on. Preflight announces the exact box, periodic
//! axes, body count and mean diameter, so downstream stages know their grid at validate time.

use crate::import::Lengths3;
use grainpipe_core::units::{parse_unit, Dim, Length};
use grainpipe_core::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The format of a packing file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum PackingFormat {
    /// From the extension (.csv; .h5, .hdf5; .dump, .lammpstrj, .liggghts or a name
    /// starting with `dump`), else from the content (HDF5 signature, `ITEM:` first line).
    Auto,
    /// Comma (or semicolon, tab, space) separated values with a header row.
    Csv,
    /// A packing written by grainpipe's `h5` exporter.
    H5,
    /// A LIGGGHTS/LAMMPS text dump (`dump custom`).
    Dump,
}

#[params]
pub struct ImportPackingParams {
    /// packing file: .csv, .h5 written by grainpipe, or a LIGGGHTS/LAMMPS text dump
    /// (relative to the working directory)
    #[param(file, ty = "path")]
    pub path: String,
    /// file format: auto (from the extension, then the content), csv, h5 or dump
    #[param(default = PackingFormat::Auto)]
    pub format: PackingFormat,
    /// length unit of the numbers of a CSV or dump (e.g. um); a CSV header like `x [um]`
    /// sets its own column's unit. An .h5 is always in metres.
    #[param(default = "m".into(), ty = "unit string")]
    pub unit: String,
    /// domain size [lx, ly, lz] (one length for a cube); required for CSV, overrides the
    /// box of a dump or .h5
    #[serde(rename = "box")]
    #[param(ty = "length or [x, y, z]")]
    pub box_: Option<Lengths3>,
    /// lower domain corner [x, y, z]; overrides the file's (CSV default: 0)
    #[param(ty = "length or [x, y, z]")]
    pub origin: Option<Lengths3>,
    /// periodic axes [x, y, z]; overrides the file's (CSV default: none). Centres on a
    /// periodic axis are wrapped into the box.
    pub periodic: Option<[bool; 3]>,
    /// dump frame to read: 0 = first, -1 = last, negative counts from the end
    #[param(default = -1)]
    pub frame: i64,
}

pub struct ImportPacking;

impl TypedStage for ImportPacking {
    type Params = ImportPackingParams;
    /// The packing parsed and checked by preflight.
    type Plan = Packing;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "import.packing",
            "1.0.0",
            "Reads a packing made elsewhere: CSV with a header row (x, y, z, r or radius; \
             optional body, layer; units from `unit` or headers like `x [um]`; `box` \
             required), a grainpipe .h5 packing (spheres and clumps, round trip), or a \
             LIGGGHTS/LAMMPS text dump (box and periodic flags from ITEM: BOX BOUNDS, \
             columns located by name, the last frame or `frame`). The file is parsed and \
             checked in preflight: a bad value stops the pipeline with file:line before \
             anything runs. Centres on periodic axes are wrapped into the box; a centre \
             outside a non-periodic box is refused.",
        )
        .outputs(vec![PortSpec::new(
            "packing",
            ArtifactKind::Packing,
            "spheres (CSV, dump) or the bodies of the .h5",
        )])
    }

    fn preflight(
        &self,
        p: &ImportPackingParams,
        _: &InputMetas,
    ) -> Result<Preflight<Packing>, StageError> {
        let packing = read_packing(p)?;
        let n = packing.bodies.len() as u64;
        let d = &packing.domain;
        let meta = ArtifactMeta::packing(d.min, d.max, d.periodic)
            .with_count(n, Some([n, n]))
            .with_mean_diameter(packing.mean_diameter());
        // The packing itself is held from preflight to run and then copied out.
        let bytes = 2 * (n * std::mem::size_of::<Body>() as u64 + 64 * n);
        Ok(Preflight::from_info(&self.info(), bytes)
            .announce("packing", meta)
            .with_plan(packing))
    }

    fn run(
        &self,
        _: &ImportPackingParams,
        plan: &Packing,
        _: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        let mut out = Outputs::new();
        out.insert("packing".into(), Artifact::Packing(plan.clone()));
        Ok(out)
    }
}

fn bad(msg: impl Into<String>) -> StageError {
    StageError::param("path", msg)
}

/// Reads, checks and places the packing `p` names (everything preflight does).
pub fn read_packing(p: &ImportPackingParams) -> Result<Packing, StageError> {
    let scale = length_unit(&p.unit).map_err(|e| StageError::param("unit", e))?;
    if let Some(b) = p.box_ {
        let s = b.si();
        if s.iter().any(|x| !(x.is_finite() && *x > 0.0)) {
            return Err(StageError::param(
                "box",
                format!("{s:?} m: give three positive lengths"),
            ));
        }
    }
    if let Some(o) = p.origin {
        if o.si().iter().any(|x| !x.is_finite()) {
            return Err(StageError::param("origin", "give three finite lengths"));
        }
    }
    if p.path.is_empty() {
        return Err(bad("no input file given"));
    }
    let path = Path::new(&p.path);
    let file = p.path.as_str();
    let bytes = std::fs::read(path).map_err(|e| {
        bad(format!(
            "{file}: {e} (relative paths start at {})",
            std::env::current_dir()
                .map(|d| d.display().to_string())
                .unwrap_or_default()
        ))
    })?;
    let format = match p.format {
        PackingFormat::Auto => detect(path, &bytes).ok_or_else(|| {
            StageError::param(
                "format",
                format!(
                    "cannot tell the format of {file} from its name or content: set \
                     `format: csv`, `h5` or `dump`"
                ),
            )
        })?,
        f => f,
    };
    if format != PackingFormat::Dump && p.frame != -1 {
        return Err(StageError::param(
            "frame",
            format!("{file} is not a dump: `frame` applies to dumps only"),
        ));
    }
    if format == PackingFormat::H5 {
        if scale != 1.0 {
            return Err(StageError::param(
                "unit",
                format!(
                    "`{}`: a grainpipe .h5 packing is stored in metres; `unit` applies to \
                     CSV and dumps only",
                    p.unit
                ),
            ));
        }
        return read_h5(p, file);
    }
    let text = String::from_utf8(bytes)
        .map_err(|e| bad(format!("{file}: not a text file ({e}); is it an .h5?")))?;
    // Spreadsheets start UTF-8 CSV files with a byte order mark.
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    if text.trim().is_empty() {
        return Err(bad(format!("{file}: the file is empty")));
    }
    let parsed = if format == PackingFormat::Csv {
        if p.box_.is_none() {
            return Err(StageError::param(
                "box",
                format!(
                    "{file} is a CSV file, which carries no domain box: give `box: [lx, ly, \
                     lz]` (and `origin`, default 0, and `periodic`, default none)"
                ),
            ));
        }
        parse_csv(text, file, scale)?
    } else {
        parse_dump(text, file, scale, p.frame)?
    };
    assemble(parsed, p, file)
}

/// The SI factor of a length unit, or why it is not one.
fn length_unit(unit: &str) -> Result<f64, String> {
    let (f, dim) = parse_unit(unit.trim()).map_err(|e| format!("`{unit}`: {e}"))?;
    if dim != Length::DIM {
        return Err(format!("`{unit}` is not a length unit (dimension {dim})"));
    }
    Ok(f)
}

fn detect(path: &Path, bytes: &[u8]) -> Option<PackingFormat> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    let name = path
        .file_name()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "csv" => return Some(PackingFormat::Csv),
        "h5" | "hdf5" => return Some(PackingFormat::H5),
        "dump" | "lammpstrj" | "liggghts" => return Some(PackingFormat::Dump),
        _ if name.starts_with("dump") => return Some(PackingFormat::Dump),
        _ => {}
    }
    // No telling extension: the HDF5 signature, or a dump's first line.
    if bytes.starts_with(b"\x89HDF\r\n\x1a\n") {
        return Some(PackingFormat::H5);
    }
    let head = String::from_utf8_lossy(&bytes[..bytes.len().min(256)]);
    if head.trim_start().starts_with("ITEM:") {
        return Some(PackingFormat::Dump);
    }
    None
}

/// Spheres read from a text file, in SI, before placing them in the domain.
struct Parsed {
    rows: Vec<Row>,
    /// Per-row numbers kept as body attributes (name, values), unitless.
    attributes: Vec<(String, Vec<f64>)>,
    /// The file's box (min, max) and periodic axes, for dumps.
    file_box: Option<([f64; 3], [f64; 3])>,
    file_periodic: Option<[bool; 3]>,
}

struct Row {
    /// 1-based line in the file.
    line: usize,
    pos: [f64; 3],
    radius: f64,
    layer: u32,
}

// ------------------------------------------------------------------------------- CSV

/// A header cell split into its lower-case name and optional unit (`x [um]`, `x (um)`).
fn header_cell(cell: &str) -> (String, Option<String>) {
    let c = cell.trim().trim_matches('"').trim();
    for (open, close) in [('[', ']'), ('(', ')')] {
        if let Some(i) = c.find(open) {
            if c.ends_with(close) {
                let unit = c[i + 1..c.len() - 1].trim().to_string();
                return (c[..i].trim().to_lowercase(), Some(unit));
            }
        }
    }
    (c.to_lowercase(), None)
}

#[derive(Clone, Copy, PartialEq)]
enum Delim {
    Char(char),
    Space,
}

fn split(line: &str, d: Delim) -> Vec<&str> {
    match d {
        Delim::Char(c) => line.split(c).map(|s| s.trim().trim_matches('"')).collect(),
        Delim::Space => line.split_whitespace().collect(),
    }
}

/// Header cells; with white-space delimiters a `[um]` or `(um)` token belongs to the name
/// before it.
fn header_cells(line: &str, d: Delim) -> Vec<String> {
    let mut cells: Vec<String> = Vec::new();
    for tok in split(line, d) {
        match cells.last_mut() {
            Some(last) if d == Delim::Space && (tok.starts_with('[') || tok.starts_with('(')) => {
                last.push(' ');
                last.push_str(tok);
            }
            _ => cells.push(tok.to_string()),
        }
    }
    cells
}

fn number(file: &str, line: usize, col: &str, cell: &str) -> Result<f64, StageError> {
    let v: f64 = cell.trim().parse().map_err(|_| {
        bad(format!(
            "{file}:{line}: column `{col}`: `{cell}` is not a number"
        ))
    })?;
    if !v.is_finite() {
        return Err(bad(format!(
            "{file}:{line}: column `{col}`: {cell} is not a finite number"
        )));
    }
    Ok(v)
}

fn layer_value(file: &str, line: usize, cell: &str) -> Result<u32, StageError> {
    let v = number(file, line, "layer", cell)?;
    if v < 0.0 || v.fract() != 0.0 || v > u32::MAX as f64 {
        return Err(bad(format!(
            "{file}:{line}: column `layer`: `{cell}` is not a non-negative integer"
        )));
    }
    Ok(v as u32)
}

fn check_radius(file: &str, line: usize, r: f64) -> Result<(), StageError> {
    if r < 0.0 {
        return Err(bad(format!("{file}:{line}: radius {r:e} is negative")));
    }
    if r == 0.0 {
        return Err(bad(format!("{file}:{line}: radius is zero")));
    }
    Ok(())
}

fn parse_csv(text: &str, file: &str, default_scale: f64) -> Result<Parsed, StageError> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
    let (hline, header) = lines
        .next()
        .ok_or_else(|| bad(format!("{file}: the file is empty")))?;
    let delim = [',', ';', '\t']
        .into_iter()
        .find(|c| header.contains(*c))
        .map(Delim::Char)
        .unwrap_or(Delim::Space);
    let cells = header_cells(header, delim);
    let mut names: Vec<String> = Vec::new();
    let mut scales: Vec<f64> = Vec::new();
    for cell in &cells {
        let (name, unit) = header_cell(cell);
        if names.contains(&name) {
            return Err(bad(format!(
                "{file}:{hline}: column `{name}` appears twice in the header"
            )));
        }
        let scale = match unit {
            Some(u) => {
                length_unit(&u).map_err(|e| bad(format!("{file}:{hline}: column `{cell}`: {e}")))?
            }
            None => default_scale,
        };
        names.push(name);
        scales.push(scale);
    }
    let find = |alts: &[&str]| alts.iter().find_map(|a| names.iter().position(|n| n == a));
    let has = names.join(", ");
    let need = |alts: &[&str]| {
        find(alts).ok_or_else(|| {
            bad(format!(
                "{file}:{hline}: no column `{}`{} in the header ({has})",
                alts[0],
                if alts.len() > 1 {
                    format!(" (or `{}`)", alts[1..].join("`, `"))
                } else {
                    String::new()
                }
            ))
        })
    };
    let xyz = [need(&["x"])?, need(&["y"])?, need(&["z"])?];
    let (rcol, rfactor) = match find(&["r", "radius"]) {
        Some(c) => (c, 1.0),
        None => (need(&["r", "radius", "diameter", "d"])?, 0.5),
    };
    let body = find(&["body"]);
    let layer = find(&["layer"]);
    let mut rows = Vec::new();
    let mut ids = Vec::new();
    for (line, l) in lines {
        let v = split(l, delim);
        if v.len() != names.len() {
            return Err(bad(format!(
                "{file}:{line}: {} values, but the header names {} columns ({has})",
                v.len(),
                names.len()
            )));
        }
        let mut pos = [0.0; 3];
        for a in 0..3 {
            pos[a] = number(file, line, &names[xyz[a]], v[xyz[a]])? * scales[xyz[a]];
        }
        let radius = number(file, line, &names[rcol], v[rcol])? * scales[rcol] * rfactor;
        check_radius(file, line, radius)?;
        if let Some(b) = body {
            ids.push(number(file, line, "body", v[b])?);
        }
        rows.push(Row {
            line,
            pos,
            radius,
            layer: layer
                .map(|c| layer_value(file, line, v[c]))
                .transpose()?
                .unwrap_or(0),
        });
    }
    if rows.is_empty() {
        return Err(bad(format!(
            "{file}:{hline}: a header but no spheres after it"
        )));
    }
    let mut attributes = Vec::new();
    if body.is_some() {
        check_unique(file, &rows, &ids, "body")?;
        attributes.push(("body".to_string(), ids));
    }
    Ok(Parsed {
        rows,
        attributes,
        file_box: None,
        file_periodic: None,
    })
}

/// Ids must name one sphere each (several spheres per body would be a clump, which these
/// text formats do not describe).
fn check_unique(file: &str, rows: &[Row], ids: &[f64], what: &str) -> Result<(), StageError> {
    let mut order: Vec<usize> = (0..ids.len()).collect();
    order.sort_by(|&a, &b| ids[a].total_cmp(&ids[b]).then(a.cmp(&b)));
    for w in order.windows(2) {
        if ids[w[0]] == ids[w[1]] {
            return Err(bad(format!(
                "{file}:{}: {what} {} already appears on line {}; one sphere per {what} \
                 (import clumps from an .h5)",
                rows[w[1]].line, ids[w[1]], rows[w[0]].line
            )));
        }
    }
    Ok(())
}

// ------------------------------------------------------------------------------- dump

fn parse_dump(text: &str, file: &str, scale: f64, frame: i64) -> Result<Parsed, StageError> {
    let lines: Vec<&str> = text.lines().collect();
    let starts: Vec<usize> = (0..lines.len())
        .filter(|&i| lines[i].trim_start().starts_with("ITEM: TIMESTEP"))
        .collect();
    if starts.is_empty() {
        let first = (0..lines.len())
            .find(|&i| !lines[i].trim().is_empty())
            .unwrap_or(0);
        return Err(bad(format!(
            "{file}:{}: not a LAMMPS/LIGGGHTS dump: no `ITEM: TIMESTEP` line",
            first + 1
        )));
    }
    let n = starts.len() as i64;
    let k = if frame < 0 { n + frame } else { frame };
    if !(0..n).contains(&k) {
        return Err(StageError::param(
            "frame",
            format!(
                "{file} holds {n} frame{}: frame {frame} is out of range (use 0..{} or -1..-{n})",
                if n == 1 { "" } else { "s" },
                n - 1
            ),
        ));
    }
    let k = k as usize;
    let end = starts.get(k + 1).copied().unwrap_or(lines.len());
    parse_frame(&lines, starts[k], end, file, scale, k)
}

/// Parses lines `start..end` (0-based) of a dump: one frame.
fn parse_frame(
    lines: &[&str],
    start: usize,
    end: usize,
    file: &str,
    scale: f64,
    k: usize,
) -> Result<Parsed, StageError> {
    let at = |i: usize| i + 1;
    // The line after an ITEM line, or an error naming the item.
    let next = |i: usize, item: &str| -> Result<&str, StageError> {
        if i + 1 < end {
            Ok(lines[i + 1].trim())
        } else {
            Err(bad(format!(
                "{file}:{}: `ITEM: {item}` is the last line of frame {k}",
                at(i)
            )))
        }
    };
    let mut n_atoms: Option<usize> = None;
    let mut bounds: Option<([f64; 3], [f64; 3])> = None;
    let mut periodic: Option<[bool; 3]> = None;
    let mut atoms: Option<Parsed> = None;
    let mut i = start;
    while i < end {
        let l = lines[i].trim();
        let Some(item) = l.strip_prefix("ITEM:").map(str::trim) else {
            if !l.is_empty() {
                return Err(bad(format!(
                    "{file}:{}: `{l}` where an `ITEM:` line was expected",
                    at(i)
                )));
            }
            i += 1;
            continue;
        };
        if item == "TIMESTEP" {
            let v = next(i, item)?;
            v.parse::<u64>().map_err(|_| {
                bad(format!(
                    "{file}:{}: timestep `{v}` is not an integer",
                    at(i + 1)
                ))
            })?;
            i += 2;
        } else if item == "NUMBER OF ATOMS" {
            let v = next(i, item)?;
            n_atoms = Some(v.parse::<usize>().map_err(|_| {
                bad(format!(
                    "{file}:{}: number of atoms `{v}` is not a non-negative integer",
                    at(i + 1)
                ))
            })?);
            i += 2;
        } else if let Some(flags) = item.strip_prefix("BOX BOUNDS") {
            let flags: Vec<&str> = flags.split_whitespace().collect();
            if flags.iter().any(|f| matches!(*f, "xy" | "xz" | "yz")) {
                return Err(bad(format!(
                    "{file}:{}: a triclinic box ({}): only orthogonal boxes are read",
                    at(i),
                    l
                )));
            }
            periodic = match flags.len() {
                // Old dumps give no flags: the `periodic` parameter or none.
                0 => None,
                3 if flags.iter().all(|f| f.len() == 2) => {
                    Some([0, 1, 2].map(|a| flags[a] == "pp"))
                }
                _ => {
                    return Err(bad(format!(
                        "{file}:{}: boundary flags `{}`: expected three like `pp pp ff`",
                        at(i),
                        flags.join(" ")
                    )))
                }
            };
            let mut lo = [0.0; 3];
            let mut hi = [0.0; 3];
            for a in 0..3 {
                let j = i + 1 + a;
                if j >= end {
                    return Err(bad(format!(
                        "{file}:{}: `ITEM: BOX BOUNDS` needs three lines `lo hi`",
                        at(i)
                    )));
                }
                let v: Vec<&str> = lines[j].split_whitespace().collect();
                if v.len() != 2 {
                    return Err(bad(format!(
                        "{file}:{}: `{}`: expected `lo hi` ({} values; 3 would be a triclinic box)",
                        at(j),
                        lines[j].trim(),
                        v.len()
                    )));
                }
                lo[a] = number(file, at(j), "box lo", v[0])? * scale;
                hi[a] = number(file, at(j), "box hi", v[1])? * scale;
                if hi[a] <= lo[a] {
                    return Err(bad(format!(
                        "{file}:{}: box bounds {} {}: hi must exceed lo",
                        at(j),
                        v[0],
                        v[1]
                    )));
                }
            }
            bounds = Some((lo, hi));
            i += 4;
        } else if let Some(cols) = item.strip_prefix("ATOMS") {
            let n = n_atoms.ok_or_else(|| {
                bad(format!(
                    "{file}:{}: `ITEM: ATOMS` before `ITEM: NUMBER OF ATOMS`",
                    at(i)
                ))
            })?;
            atoms = Some(parse_atoms(lines, i, end, cols, n, bounds, file, scale, k)?);
            i += 1 + n;
        } else {
            // Other items (UNITS, TIME, ...) are skipped up to the next item.
            i += 1;
            while i < end && !lines[i].trim_start().starts_with("ITEM:") {
                i += 1;
            }
        }
    }
    let mut parsed = atoms.ok_or_else(|| {
        bad(format!(
            "{file}:{}: frame {k} has no `ITEM: ATOMS` section",
            at(start)
        ))
    })?;
    parsed.file_box = Some(bounds.ok_or_else(|| {
        bad(format!(
            "{file}:{}: frame {k} has no `ITEM: BOX BOUNDS` section",
            at(start)
        ))
    })?);
    parsed.file_periodic = periodic;
    Ok(parsed)
}

#[allow(clippy::too_many_arguments)]
fn parse_atoms(
    lines: &[&str],
    i: usize,
    end: usize,
    cols: &str,
    n: usize,
    bounds: Option<([f64; 3], [f64; 3])>,
    file: &str,
    scale: f64,
    k: usize,
) -> Result<Parsed, StageError> {
    let names: Vec<&str> = cols.split_whitespace().collect();
    let hline = i + 1;
    let find = |alts: &[&str]| alts.iter().find_map(|a| names.iter().position(|n| n == a));
    let need = |alts: &[&str]| {
        find(alts).ok_or_else(|| {
            bad(format!(
                "{file}:{hline}: no column `{}` in `ITEM: ATOMS {}`",
                alts.join("` or `"),
                names.join(" ")
            ))
        })
    };
    // Per axis: the column and whether it holds scaled (0..1 of the box) coordinates.
    let mut xyz = [(0, false); 3];
    for (a, ax) in ["x", "y", "z"].iter().enumerate() {
        let plain = [ax.to_string(), format!("{ax}u")];
        let scaled = [format!("{ax}s"), format!("{ax}su")];
        xyz[a] = match find(&[plain[0].as_str(), plain[1].as_str()]) {
            Some(c) => (c, false),
            None => (
                need(&[
                    plain[0].as_str(),
                    plain[1].as_str(),
                    scaled[0].as_str(),
                    scaled[1].as_str(),
                ])?,
                true,
            ),
        };
    }
    if xyz.iter().any(|c| c.1) && bounds.is_none() {
        return Err(bad(format!(
            "{file}:{hline}: scaled coordinates need `ITEM: BOX BOUNDS` before `ITEM: ATOMS`"
        )));
    }
    let (rcol, rfactor) = match find(&["radius"]) {
        Some(c) => (c, 1.0),
        None => (need(&["radius", "diameter"])?, 0.5),
    };
    let id = find(&["id"]);
    let ty = find(&["type"]);
    if n == 0 {
        return Err(bad(format!("{file}:{hline}: frame {k} has no atoms")));
    }
    // The count is the file's word: nothing is allocated for atoms the frame cannot list
    // (a 300-byte dump may claim 10^12 atoms).
    let lines_left = end.saturating_sub(i + 1);
    if n > lines_left {
        let listed = lines[i + 1..end]
            .iter()
            .take_while(|l| !l.trim().starts_with("ITEM:"))
            .count();
        return Err(bad(format!(
            "{file}:{}: frame {k} announces {n} atoms but lists {listed}",
            i + 1 + listed + 1
        )));
    }
    let mut rows = Vec::with_capacity(n);
    let mut ids = Vec::new();
    let mut types = Vec::new();
    for listed in 0..n {
        let j = i + 1 + listed;
        let line = j + 1;
        let l = match lines[..end].get(j).map(|l| l.trim()) {
            Some(l) if !l.starts_with("ITEM:") => l,
            _ => {
                return Err(bad(format!(
                    "{file}:{line}: frame {k} announces {n} atoms but lists {listed}"
                )))
            }
        };
        let v: Vec<&str> = l.split_whitespace().collect();
        if v.len() != names.len() {
            return Err(bad(format!(
                "{file}:{line}: {} values, but `ITEM: ATOMS` names {} columns",
                v.len(),
                names.len()
            )));
        }
        let mut pos = [0.0; 3];
        for a in 0..3 {
            let (c, scaled) = xyz[a];
            let x = number(file, line, names[c], v[c])?;
            pos[a] = match (scaled, bounds) {
                (true, Some((lo, hi))) => lo[a] + x * (hi[a] - lo[a]),
                _ => x * scale,
            };
        }
        let radius = number(file, line, names[rcol], v[rcol])? * scale * rfactor;
        check_radius(file, line, radius)?;
        if let Some(c) = id {
            ids.push(number(file, line, "id", v[c])?);
        }
        if let Some(c) = ty {
            types.push(number(file, line, "type", v[c])?);
        }
        rows.push(Row {
            line,
            pos,
            radius,
            layer: 0,
        });
    }
    let mut attributes = Vec::new();
    if id.is_some() {
        check_unique(file, &rows, &ids, "id")?;
        // Processor order is not meaningful; id order is.
        let mut order: Vec<usize> = (0..rows.len()).collect();
        order.sort_by(|&a, &b| ids[a].total_cmp(&ids[b]));
        let mut slots: Vec<Option<Row>> = rows.into_iter().map(Some).collect();
        rows = order.iter().map(|&o| slots[o].take().unwrap()).collect();
        types = if ty.is_some() {
            order.iter().map(|&o| types[o]).collect()
        } else {
            types
        };
        ids = order.iter().map(|&o| ids[o]).collect();
        attributes.push(("id".to_string(), ids));
    }
    if ty.is_some() {
        attributes.push(("type".to_string(), types));
    }
    Ok(Parsed {
        rows,
        attributes,
        file_box: None,
        file_periodic: None,
    })
}

// ------------------------------------------------------------------------------- placing

/// The domain: `origin`/`box` parameters over the file's box (CSV: origin 0), the
/// `periodic` parameter over the file's flags (default none).
fn domain(
    p: &ImportPackingParams,
    file_box: Option<([f64; 3], [f64; 3])>,
    file_periodic: Option<[bool; 3]>,
    file: &str,
) -> Result<Domain, StageError> {
    if let (None, None, Some((lo, hi))) = (p.origin, p.box_, file_box) {
        // The file's box as stored (min + (max - min) may differ from max in the last bit).
        let periodic = p.periodic.or(file_periodic).unwrap_or([false; 3]);
        return Ok(Domain::boxed(lo, hi, periodic));
    }
    let min = p
        .origin
        .map(|o| o.si())
        .or(file_box.map(|b| b.0))
        .unwrap_or([0.0; 3]);
    let size = match (p.box_, file_box) {
        (Some(b), _) => b.si(),
        (None, Some((lo, hi))) => [0, 1, 2].map(|a| hi[a] - lo[a]),
        (None, None) => {
            return Err(StageError::param(
                "box",
                format!("{file} gives no domain box: set `box: [lx, ly, lz]`"),
            ))
        }
    };
    let periodic = p.periodic.or(file_periodic).unwrap_or([false; 3]);
    Ok(Domain::boxed(
        min,
        [0, 1, 2].map(|a| min[a] + size[a]),
        periodic,
    ))
}

/// Wraps `pos` into the box along periodic axes; on the others a centre outside the box
/// (beyond a round-off tolerance of 1e-9 of the box edge) is refused with `where_`.
fn place(pos: &mut [f64; 3], d: &Domain, where_: &dyn Fn() -> String) -> Result<(), StageError> {
    const AXES: [&str; 3] = ["x", "y", "z"];
    for a in 0..3 {
        let (lo, hi) = (d.min[a], d.max[a]);
        let len = hi - lo;
        if d.periodic[a] {
            if pos[a] < lo || pos[a] >= hi {
                let mut w = lo + (pos[a] - lo).rem_euclid(len);
                // rem_euclid of a tiny negative offset can round up to the period.
                if w >= hi {
                    w = lo;
                }
                pos[a] = w;
            }
        } else {
            let tol = 1e-9 * len;
            if pos[a] < lo - tol || pos[a] > hi + tol {
                return Err(bad(format!(
                    "{}: centre {} = {:e} m is outside the non-periodic box {lo:e}..{hi:e} m \
                     (make the axis periodic or enlarge `box`)",
                    where_(),
                    AXES[a],
                    pos[a]
                )));
            }
        }
    }
    Ok(())
}

/// Refuses a sphere wider than the box along some axis: on a periodic axis it overlaps its
/// own image, on a closed one the box holds a slice of one grain, and in both its volume
/// fraction exceeds what the box can hold (a 500 um sphere in a 100 um box gave an "analytic"
/// solid fraction of 524).
fn fits_in_box(radius: f64, d: &Domain, where_: &dyn Fn() -> String) -> Result<(), StageError> {
    for (a, axis) in ["x", "y", "z"].iter().enumerate() {
        let len = d.max[a] - d.min[a];
        if 2.0 * radius > len * (1.0 + 1e-9) {
            return Err(bad(format!(
                "{}: a sphere of diameter {} is wider than the box along {} ({}){}; check \
                 `unit` and `box`",
                where_(),
                grainpipe_core::units::format_length(2.0 * radius),
                axis,
                grainpipe_core::units::format_length(len),
                if d.periodic[a] {
                    " and would overlap its own periodic image"
                } else {
                    ""
                }
            )));
        }
    }
    Ok(())
}

fn assemble(parsed: Parsed, p: &ImportPackingParams, file: &str) -> Result<Packing, StageError> {
    let d = domain(p, parsed.file_box, parsed.file_periodic, file)?;
    let mut packing = Packing::new(d);
    for r in parsed.rows {
        let mut pos = r.pos;
        place(&mut pos, &packing.domain, &|| format!("{file}:{}", r.line))?;
        fits_in_box(r.radius, &packing.domain, &|| format!("{file}:{}", r.line))?;
        let mut b = Body::sphere(pos, r.radius);
        b.layer = r.layer;
        packing.bodies.push(b);
    }
    for (name, values) in parsed.attributes {
        packing.attributes.insert(
            name,
            BodyAttribute {
                unit: String::new(),
                values,
            },
        );
    }
    Ok(packing)
}

fn read_h5(p: &ImportPackingParams, file: &str) -> Result<Packing, StageError> {
    let mut packing = crate::hdf5_plain::read_h5_packing(Path::new(file))
        .map_err(|e| bad(format!("{file}: {e}")))?;
    if packing.bodies.is_empty() {
        return Err(bad(format!("{file}: the packing has no bodies")));
    }
    let excluded = std::mem::take(&mut packing.domain.excluded);
    let d = &packing.domain;
    let mut dom = domain(p, Some((d.min, d.max)), Some(d.periodic), file)?;
    dom.excluded = excluded;
    packing.domain = dom;
    let nclumps = packing.library.as_ref().map_or(0, |l| l.clumps.len());
    for (k, b) in packing.bodies.iter_mut().enumerate() {
        match b.shape {
            BodyShape::Sphere { radius } if !(radius.is_finite() && radius > 0.0) => {
                return Err(bad(format!(
                    "{file}: body {k}: radius {radius:e} is not positive"
                )))
            }
            BodyShape::Clump { index } if index >= nclumps => {
                return Err(bad(format!(
                    "{file}: body {k}: clump {index} is not in the file's library of {nclumps}"
                )))
            }
            _ => {}
        }
        if b.position.iter().any(|x| !x.is_finite()) {
            return Err(bad(format!(
                "{file}: body {k}: position {:?} is not finite",
                b.position
            )));
        }
        place(&mut b.position, &packing.domain, &|| {
            format!("{file}: body {k}")
        })?;
    }
    Ok(packing)
}
