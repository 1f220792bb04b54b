//! CSV and JSON for tables, tensors and contact graphs, with readers for round trips.
//!
//! CSV: one header row, then data rows, nothing else (a plain `pandas.read_csv` reads it).
//! Headers are `name [unit]` for numeric columns ("[1]" when dimensionless), the bare name
//! for text. A table has one column per table column; a tensor has its matrix rows under
//! column labels (`xx [Pa]` .. `xy [Pa]` for a 6x6 Voigt/Mandel tensor, `x`..`z` for 3
//! columns); a contact graph has `i [1],j [1],gap [m],bonded [1]` and the bond attributes
//! (contacts, then bonds that are not contacts with an empty gap). Provenance, the table or
//! tensor name, exact units and the tensor convention and shape are in the sidecar
//! `x.csv.json` ([`csv_sidecar`]).
//! JSON: one object with `kind`, the data and `provenance`. JSON has no NaN: non-finite
//! numbers are written as `null` and read back as NaN.

use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::*;
use serde_json::{json, Map, Value};
use std::collections::{HashMap, HashSet};
use std::path::Path;

// ---------------------------------------------------------------------------------------
// CSV

/// The one header convention of every CSV: `name [unit]` for numbers ("1" when
/// dimensionless, so a bare name never hides a unit), the bare name for text.
fn header(name: &str, unit: &str, numeric: bool) -> String {
    if !numeric {
        name.to_string()
    } else if unit.is_empty() {
        format!("{name} [1]")
    } else {
        format!("{name} [{unit}]")
    }
}

/// Splits `name [unit]` back into its parts.
fn split_header(h: &str) -> (String, String) {
    let h = h.trim();
    if let (Some(open), true) = (h.rfind(" ["), h.ends_with(']')) {
        (h[..open].to_string(), h[open + 2..h.len() - 1].to_string())
    } else {
        (h.to_string(), String::new())
    }
}

/// Shortest round-trip text, in exponent form for very small or large magnitudes.
fn fmt_f64(x: f64) -> String {
    if x != 0.0 && (x.abs() < 1e-3 || x.abs() >= 1e15) {
        format!("{x:e}")
    } else {
        x.to_string()
    }
}

fn csv_err(e: csv::Error) -> String {
    e.to_string()
}

/// Where the provenance and exact column metadata of `x.csv` go: `x.csv.json` beside it.
/// The CSV itself is the header row and the data rows and nothing else, so a plain
/// `pandas.read_csv(path)`, `numpy.genfromtxt(path, delimiter=",", names=True)` or a
/// spreadsheet reads it right with no options.
pub fn csv_sidecar(path: &Path) -> std::path::PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".json");
    path.with_file_name(name)
}

/// Writes the sidecar, then the CSV (each atomically): a CSV on disk always has the sidecar
/// of the same write or a newer one beside it.
fn write_csv_records(
    path: &Path,
    meta: Value,
    prov: &Provenance,
    rows: impl Iterator<Item = Vec<String>>,
) -> Result<(), String> {
    let mut meta = meta;
    meta["csv"] = Value::String(
        path.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
    );
    meta["provenance"] = prov_json(prov);
    let text = serde_json::to_string_pretty(&meta).map_err(|e| e.to_string())?;
    atomic_write(&csv_sidecar(path), |tmp| std::fs::write(tmp, text))?;
    atomic_write(path, |tmp| -> Result<(), String> {
        let file = std::fs::File::create(tmp).map_err(|e| e.to_string())?;
        let mut w = csv::WriterBuilder::new().flexible(true).from_writer(file);
        for r in rows {
            w.write_record(&r).map_err(csv_err)?;
        }
        w.flush().map_err(|e| e.to_string())
    })
}

/// Column labels of a tensor's matrix rows: the symmetric-tensor order for 6 columns of a
/// Voigt/Mandel tensor, x y z for 3, else c0, c1, ...
fn tensor_labels(t: &Tensor, cols: usize) -> Vec<String> {
    match (t.convention, cols) {
        (TensorConvention::Voigt | TensorConvention::Mandel, 6) => {
            ["xx", "yy", "zz", "yz", "xz", "xy"]
                .map(String::from)
                .to_vec()
        }
        (_, 3) => ["x", "y", "z"].map(String::from).to_vec(),
        _ => (0..cols).map(|k| format!("c{k}")).collect(),
    }
}

fn columns_json(cols: &[(String, String, String)]) -> Value {
    Value::Array(
        cols.iter()
            .map(|(n, u, h)| json!({"name": n, "unit": u, "header": h}))
            .collect(),
    )
}

/// Writes a table, tensor or contact graph as CSV: one header row (`name [unit]`, see
/// [`header`]) and the data rows; provenance and exact names/units in the
/// [`csv_sidecar`] `x.csv.json`.
pub fn write_csv(a: &Artifact, path: &Path, prov: &Provenance) -> Result<(), String> {
    match a {
        Artifact::Table(t) => {
            t.validate()?;
            let cols: Vec<(String, String, String)> = t
                .columns
                .iter()
                .map(|c| {
                    let numeric = !matches!(c.data, ColumnData::Str(_));
                    (
                        c.name.clone(),
                        c.unit.clone(),
                        header(&c.name, &c.unit, numeric),
                    )
                })
                .collect();
            let head: Vec<String> = cols.iter().map(|c| c.2.clone()).collect();
            let rows = (0..t.rows()).map(|r| {
                t.columns
                    .iter()
                    .map(|c| match &c.data {
                        ColumnData::F64(v) => fmt_f64(v[r]),
                        ColumnData::I64(v) => v[r].to_string(),
                        ColumnData::Str(v) => v[r].clone(),
                    })
                    .collect()
            });
            let meta = json!({"kind": "Table", "name": t.name, "columns": columns_json(&cols)});
            write_csv_records(path, meta, prov, std::iter::once(head).chain(rows))
        }
        Artifact::Tensor(t) => {
            check_tensor(t)?;
            let cols = (*t.shape.last().unwrap_or(&1)).max(1);
            let labels = tensor_labels(t, cols);
            let head: Vec<String> = labels.iter().map(|l| header(l, &t.unit, true)).collect();
            let rows = t
                .values
                .chunks(cols)
                .map(|r| r.iter().map(|&x| fmt_f64(x)).collect());
            let meta = json!({
                "kind": "Tensor", "name": t.name, "unit": t.unit,
                "convention": format!("{:?}", t.convention), "shape": t.shape,
                "columns": labels,
            });
            write_csv_records(path, meta, prov, std::iter::once(head).chain(rows))
        }
        Artifact::ContactGraph(g) => {
            g.validate()?;
            let mut cols: Vec<(String, String, String)> =
                [("i", ""), ("j", ""), ("gap", "m"), ("bonded", "")]
                    .iter()
                    .map(|(n, u)| (n.to_string(), u.to_string(), header(n, u, true)))
                    .collect();
            for (name, a) in &g.bond_attributes {
                cols.push((name.clone(), a.unit.clone(), header(name, &a.unit, true)));
            }
            let head: Vec<String> = cols.iter().map(|c| c.2.clone()).collect();
            let bonds: HashMap<(usize, usize), usize> = g
                .bonds
                .iter()
                .enumerate()
                .map(|(k, b)| ((b[0].min(b[1]), b[0].max(b[1])), k))
                .collect();
            let contacts: HashSet<(usize, usize)> = g
                .contacts
                .iter()
                .map(|c| (c.i.min(c.j), c.i.max(c.j)))
                .collect();
            // One row per contact (bond attributes empty when unbonded), then the bonds that
            // are not contacts.
            let row = |i: usize, j: usize, gap: Option<f64>, bond: Option<usize>| {
                let mut r = vec![
                    i.to_string(),
                    j.to_string(),
                    gap.map(fmt_f64).unwrap_or_default(),
                    (bond.is_some() as u8).to_string(),
                ];
                for a in g.bond_attributes.values() {
                    r.push(bond.map(|k| fmt_f64(a.values[k])).unwrap_or_default());
                }
                r
            };
            let rows = g
                .contacts
                .iter()
                .map(|c| {
                    let bond = bonds.get(&(c.i.min(c.j), c.i.max(c.j))).copied();
                    row(c.i, c.j, Some(c.gap), bond)
                })
                .chain(
                    g.bonds
                        .iter()
                        .enumerate()
                        .filter(|(_, b)| !contacts.contains(&(b[0].min(b[1]), b[0].max(b[1]))))
                        .map(|(k, b)| row(b[0], b[1], None, Some(k))),
                );
            let meta = json!({"kind": "ContactGraph", "columns": columns_json(&cols)});
            write_csv_records(path, meta, prov, std::iter::once(head).chain(rows))
        }
        other => Err(format!(
            "csv takes a Table, a Tensor or a ContactGraph, not a {}",
            other.kind()
        )),
    }
}

fn check_tensor(t: &Tensor) -> Result<(), String> {
    if t.shape.iter().product::<usize>() != t.values.len() {
        return Err(format!(
            "tensor `{}` has {} values for shape {:?}",
            t.name,
            t.values.len(),
            t.shape
        ));
    }
    Ok(())
}

/// Reads a table written by [`write_csv`] (or any CSV with one header row; `#` comment lines,
/// as files written before the sidecar had, are skipped): a column whose cells all parse as
/// integers is I64, else as numbers F64, else text. Names and units come from the sidecar
/// `x.csv.json` when it describes these columns, else from the `name [unit]` headers.
pub fn read_table_csv(path: &Path) -> Result<Table, String> {
    let at = |e: String| format!("{}: {e}", path.display());
    let mut r = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .from_path(path)
        .map_err(|e| at(csv_err(e)))?;
    let mut heads: Vec<(String, String)> = r
        .headers()
        .map_err(|e| at(csv_err(e)))?
        .iter()
        .map(split_header)
        .collect();
    let mut cells: Vec<Vec<String>> = vec![Vec::new(); heads.len()];
    for (k, rec) in r.records().enumerate() {
        let rec = rec.map_err(|e| at(csv_err(e)))?;
        if rec.len() != heads.len() {
            return Err(at(format!(
                "row {} has {} cells, header has {}",
                k + 2,
                rec.len(),
                heads.len()
            )));
        }
        for (c, v) in rec.iter().enumerate() {
            cells[c].push(v.to_string());
        }
    }
    let mut t = Table::new(
        path.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default(),
    );
    // Our own sidecar holds the exact names and units (a dimensionless unit written "1" in
    // the header may have been "" in the table) and the table's name.
    if let Some(meta) = std::fs::read_to_string(csv_sidecar(path))
        .ok()
        .and_then(|text| serde_json::from_str::<Value>(&text).ok())
        .filter(|m| m["kind"] == "Table")
    {
        let cols = meta["columns"].as_array().cloned().unwrap_or_default();
        if cols.len() == heads.len()
            && cols
                .iter()
                .zip(&heads)
                .all(|(c, (n, _))| c["name"].as_str() == Some(n.as_str()))
        {
            heads = cols
                .iter()
                .map(|c| (s(&c["name"]), s(&c["unit"])))
                .collect();
            t.name = s(&meta["name"]);
        }
    }
    for ((name, unit), col) in heads.into_iter().zip(cells) {
        let data = if let Ok(v) = col.iter().map(|s| s.parse::<i64>()).collect() {
            ColumnData::I64(v)
        } else if let Ok(v) = col.iter().map(|s| s.parse::<f64>()).collect() {
            ColumnData::F64(v)
        } else {
            ColumnData::Str(col)
        };
        t.columns.push(Column { name, unit, data });
    }
    Ok(t)
}

// ---------------------------------------------------------------------------------------
// JSON

fn num(x: f64) -> Value {
    serde_json::Number::from_f64(x)
        .map(Value::Number)
        .unwrap_or(Value::Null)
}

fn nested(values: &[f64], shape: &[usize]) -> Value {
    match shape {
        [] | [_] => Value::Array(values.iter().map(|&x| num(x)).collect()),
        [_, rest @ ..] => {
            let step: usize = rest.iter().product();
            Value::Array(
                values
                    .chunks(step.max(1))
                    .map(|c| nested(c, rest))
                    .collect(),
            )
        }
    }
}

fn prov_json(p: &Provenance) -> Value {
    Value::Object(
        p.entries
            .iter()
            .map(|(k, v)| (k.clone(), Value::String(v.clone())))
            .collect::<Map<_, _>>(),
    )
}

pub fn write_json(a: &Artifact, path: &Path, prov: &Provenance) -> Result<(), String> {
    let v = match a {
        Artifact::Table(t) => {
            t.validate()?;
            let cols: Vec<Value> = t
                .columns
                .iter()
                .map(|c| {
                    let values = match &c.data {
                        ColumnData::F64(v) => Value::Array(v.iter().map(|&x| num(x)).collect()),
                        ColumnData::I64(v) => json!(v),
                        ColumnData::Str(v) => json!(v),
                    };
                    json!({"name": c.name, "unit": c.unit, "values": values})
                })
                .collect();
            json!({"kind": "Table", "name": t.name, "columns": cols})
        }
        Artifact::Tensor(t) => {
            check_tensor(t)?;
            json!({
                "kind": "Tensor", "name": t.name, "unit": t.unit,
                "convention": format!("{:?}", t.convention),
                "shape": t.shape, "values": nested(&t.values, &t.shape),
            })
        }
        Artifact::ContactGraph(g) => {
            let faces: Map<String, Value> = FACE_NAMES
                .iter()
                .zip(&g.faces)
                .map(|(n, f)| (n.to_string(), json!(f)))
                .collect();
            let mut v = json!({
                "kind": "ContactGraph",
                "contacts": g.contacts.iter().map(|c| json!([c.i, c.j, num(c.gap)])).collect::<Vec<_>>(),
                "bonds": g.bonds,
                "bond_attributes": g.bond_attributes.iter().map(|(n, a)| (n.clone(), json!({
                    "unit": a.unit, "values": a.values.iter().map(|&x| num(x)).collect::<Vec<_>>()
                }))).collect::<Map<String, Value>>(),
                "faces": faces,
                "positions": g.positions.iter().map(|p| p.iter().map(|&x| num(x)).collect::<Vec<_>>()).collect::<Vec<_>>(),
            });
            if !g.radii.is_empty() {
                v["radius"] = json!(g.radii.iter().map(|&x| num(x)).collect::<Vec<_>>());
            }
            v
        }
        other => {
            return Err(format!(
                "json takes a Table, a Tensor or a ContactGraph, not a {}",
                other.kind()
            ))
        }
    };
    let mut v = v;
    v["provenance"] = prov_json(prov);
    let text = serde_json::to_string_pretty(&v).map_err(|e| e.to_string())?;
    atomic_write(path, |tmp| std::fs::write(tmp, text))
}

fn load(path: &Path, kind: &str) -> Result<Value, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let v: Value = serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
    if v["kind"] != kind {
        return Err(format!(
            "{}: holds kind {}, expected {kind}",
            path.display(),
            v["kind"]
        ));
    }
    Ok(v)
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}
fn idx(v: &Value, what: &str) -> Result<usize, String> {
    v.as_u64()
        .map(|x| x as usize)
        .ok_or_else(|| format!("`{what}`: {v} is not an index"))
}
fn s(v: &Value) -> String {
    v.as_str().unwrap_or_default().to_string()
}

pub fn read_table_json(path: &Path) -> Result<Table, String> {
    let v = load(path, "Table")?;
    let mut t = Table::new(s(&v["name"]));
    for c in v["columns"].as_array().into_iter().flatten() {
        let vals = c["values"].as_array().cloned().unwrap_or_default();
        let data = if vals.iter().all(|x| x.is_i64()) && !vals.is_empty() {
            ColumnData::I64(vals.iter().map(|x| x.as_i64().unwrap_or(0)).collect())
        } else if vals.iter().all(|x| x.is_number() || x.is_null()) {
            ColumnData::F64(vals.iter().map(f).collect())
        } else {
            ColumnData::Str(vals.iter().map(s).collect())
        };
        t.columns.push(Column {
            name: s(&c["name"]),
            unit: s(&c["unit"]),
            data,
        });
    }
    Ok(t)
}

pub fn read_tensor_json(path: &Path) -> Result<Tensor, String> {
    let v = load(path, "Tensor")?;
    fn flatten(v: &Value, out: &mut Vec<f64>) {
        match v {
            Value::Array(a) => a.iter().for_each(|x| flatten(x, out)),
            x => out.push(f(x)),
        }
    }
    let mut values = Vec::new();
    flatten(&v["values"], &mut values);
    let shape: Vec<usize> = v["shape"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|x| idx(x, "shape"))
        .collect::<Result<_, _>>()?;
    let convention = match v["convention"].as_str() {
        Some("Voigt") => TensorConvention::Voigt,
        Some("Mandel") => TensorConvention::Mandel,
        _ => TensorConvention::Plain,
    };
    let t = Tensor {
        name: s(&v["name"]),
        unit: s(&v["unit"]),
        shape,
        values,
        convention,
    };
    check_tensor(&t).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(t)
}

pub fn read_contact_graph_json(path: &Path) -> Result<ContactGraph, String> {
    let v = load(path, "ContactGraph")?;
    let at = |e: String| format!("{}: {e}", path.display());
    let mut g = ContactGraph::default();
    for c in v["contacts"].as_array().into_iter().flatten() {
        g.contacts.push(Contact {
            i: idx(&c[0], "contacts").map_err(at)?,
            j: idx(&c[1], "contacts").map_err(at)?,
            gap: f(&c[2]),
        });
    }
    for b in v["bonds"].as_array().into_iter().flatten() {
        g.bonds.push([
            idx(&b[0], "bonds").map_err(at)?,
            idx(&b[1], "bonds").map_err(at)?,
        ]);
    }
    for (name, a) in v["bond_attributes"].as_object().into_iter().flatten() {
        g.bond_attributes.insert(
            name.clone(),
            BodyAttribute {
                unit: a["unit"].as_str().unwrap_or("").to_string(),
                values: a["values"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .map(f)
                    .collect(),
            },
        );
    }
    for (k, name) in FACE_NAMES.iter().enumerate() {
        for x in v["faces"][name].as_array().into_iter().flatten() {
            g.faces[k].push(idx(x, name).map_err(at)?);
        }
    }
    for p in v["positions"].as_array().into_iter().flatten() {
        g.positions.push([f(&p[0]), f(&p[1]), f(&p[2])]);
    }
    g.radii = v["radius"]
        .as_array()
        .into_iter()
        .flatten()
        .map(f)
        .collect();
    g.validate().map_err(at)?;
    Ok(g)
}

crate::vtk_xml::exporter!(
    CsvExporter,
    "csv",
    &["csv"],
    [Table, Tensor, ContactGraph],
    "CSV that a plain pandas.read_csv reads: one header row (`name [unit]`, `[1]` when \
     dimensionless) and the data rows; tables, tensors (matrix rows under `xx [Pa]` .. \
     labels), contact graphs (i, j, gap, bonded, bond attributes). Provenance, names, units, \
     tensor convention and shape go to the sidecar `<file>.csv.json`",
    write_csv,
    paths: csv_written_paths
);

/// A CSV export writes the file and its sidecar.
fn csv_written_paths(
    path: &Path,
    _: &grainpipe_core::registry::ExportOptions,
) -> Vec<grainpipe_core::registry::WrittenPath> {
    use grainpipe_core::registry::WrittenPath;
    vec![
        WrittenPath::file(path),
        WrittenPath::file(csv_sidecar(path)),
    ]
}
crate::vtk_xml::exporter!(
    JsonExporter,
    "json",
    &["json"],
    [Table, Tensor, ContactGraph],
    "JSON: tables (columns with units), tensors (nested rows, shape, convention), contact \
     graphs (contacts, bonds, faces, positions); provenance included",
    write_json
);
