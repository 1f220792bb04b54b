//! Single values of a run's results by name (`step.port.column[k]`, `step.port[k]`): what
//! `pipe sweep --collect` puts in its table and what a pipeline's `reference:` block compares.

use crate::{Artifact, ColumnData, Outputs};
use indexmap::IndexMap;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// A value of a run's results, named as `pipe sweep --collect` and `reference:` name it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Value {
    pub name: String,
    pub unit: String,
    /// JSON has no NaN: a non-finite value is stored as null.
    pub value: Option<f64>,
    /// The name of a tensor component (`kappa_xx`, `C_11`) or of a table row (the row's
    /// first text cell, e.g. `apparent`) when the value is one of several, for reports.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub component: Option<String>,
}

/// The name of component `k` of a tensor: `kappa_xy` for a 3 x 3 permeability (`k_xy` for a
/// conductivity, `<name>_xy` else), `C_12` for a 6 x 6 Voigt or Mandel matrix, `<name>_k`
/// otherwise.
pub fn component_name(t: &crate::Tensor, k: usize) -> String {
    const XYZ: [&str; 3] = ["x", "y", "z"];
    let sym = match t.name.as_str() {
        "permeability" => "kappa",
        "conductivity" => "k",
        "stiffness" => "C",
        n => n,
    };
    match t.shape.as_slice() {
        [3, 3] => format!("{sym}_{}{}", XYZ[k / 3], XYZ[k % 3]),
        [6, 6] => format!("{sym}_{}{}", k / 6 + 1, k % 6 + 1),
        [3] => format!("{sym}_{}", XYZ[k % 3]),
        _ => format!("{sym}_{k}"),
    }
}

/// The values `step.port[.column]` names in a run's outputs: every row of the column (or of
/// every numeric column when none is named) of a table, one row with `column[k]` or
/// `column[label]`, or every component of a tensor (one with an index or a component name as
/// the column). Names are `step.port.column`, with `[k]` appended when there are several rows,
/// and `step.port[k]` for a tensor; a value asked for by row or component name is named as
/// asked. `what` is how errors name the request
/// (`--collect`, `reference`).
pub fn values_of(
    outputs: &IndexMap<String, Arc<Outputs>>,
    step: &str,
    port: &str,
    column: Option<&str>,
    what: &str,
) -> Result<Vec<Value>, String> {
    let full = format!("{step}.{port}");
    let a = outputs
        .get(step)
        .and_then(|o| o.get(port))
        .ok_or_else(|| format!("{what} `{full}`: the step gave no such output"))?;
    let v = |name: String, unit: &str, x: f64| Value {
        name,
        unit: unit.to_string(),
        value: x.is_finite().then_some(x),
        component: None,
    };
    match a {
        Artifact::Table(t) => {
            // `column[row]`: one row, by index or by its label (the first text cell).
            let (column, row) =
                match column.and_then(|c| c.strip_suffix(']').and_then(|c| c.split_once('['))) {
                    Some((c, r)) => (Some(c), Some(r)),
                    None => (column, None),
                };
            let cols: Vec<&crate::Column> = match column {
                Some(c) => vec![t.column(c).ok_or_else(|| {
                    let names: Vec<&str> = t.columns.iter().map(|c| c.name.as_str()).collect();
                    format!(
                        "{what} `{full}.{c}`: no column `{c}`{}; it has: {}",
                        crate::registry::closest(c, names.iter().copied())
                            .map(|s| format!(" (did you mean `{s}`?)"))
                            .unwrap_or_default(),
                        names.join(", ")
                    )
                })?],
                None => t
                    .columns
                    .iter()
                    .filter(|c| !matches!(c.data, ColumnData::Str(_)))
                    .collect(),
            };
            let mut out = Vec::new();
            for c in cols {
                let xs: Vec<f64> = match &c.data {
                    ColumnData::F64(x) => x.clone(),
                    ColumnData::I64(x) => x.iter().map(|&i| i as f64).collect(),
                    ColumnData::Str(_) => {
                        return Err(format!("{what} `{full}.{}`: the column holds text", c.name))
                    }
                };
                let name = format!("{full}.{}", c.name);
                // Rows are named by the table's first text column (an approximation, a
                // direction), when it has one.
                let rows: Option<&Vec<String>> = t.columns.iter().find_map(|c| match &c.data {
                    ColumnData::Str(s) => Some(s),
                    _ => None,
                });
                if xs.len() == 1 {
                    out.push(v(name, &c.unit, xs[0]));
                } else {
                    for (k, x) in xs.iter().enumerate() {
                        let mut val = v(format!("{name}[{k}]"), &c.unit, *x);
                        val.component = rows
                            .and_then(|r| r.get(k))
                            .map(|r| format!("{} ({r})", c.name));
                        out.push(val);
                    }
                }
            }
            let Some(r) = row else {
                return Ok(out);
            };
            let asked = format!("{full}.{}[{r}]", column.unwrap_or_default());
            let labels: Vec<String> = out
                .iter()
                .filter_map(|v| v.component.as_deref())
                .filter_map(|c| {
                    c.split_once(" (")
                        .map(|x| x.1.trim_end_matches(')').to_string())
                })
                .collect();
            let k = match r.parse::<usize>() {
                Ok(k) if k < out.len() => Some(k),
                _ => labels.iter().position(|l| l == r),
            };
            match k {
                Some(k) => {
                    let mut one = out.swap_remove(k);
                    one.name = asked;
                    Ok(vec![one])
                }
                None => Err(format!(
                    "{what} `{asked}`: no row `{r}`; rows are 0..{}{}",
                    out.len().saturating_sub(1),
                    if labels.is_empty() {
                        String::new()
                    } else {
                        format!(" or by name: {}", labels.join(", "))
                    }
                )),
            }
        }
        Artifact::Tensor(t) => {
            // A component by index (`flow.permeability.8`, named `flow.permeability[8]`) or
            // by name (`flow.permeability.kappa_zz`, named as asked).
            let names: Vec<String> = (0..t.values.len()).map(|k| component_name(t, k)).collect();
            let (idx, by_name) = match column {
                Some(c) => match c.parse::<usize>() {
                    Ok(i) if i < t.values.len() => (Some(i), false),
                    _ => match names.iter().position(|n| n == c) {
                        Some(i) => (Some(i), true),
                        None => {
                            return Err(format!(
                                "{what} `{full}.{c}`: a tensor's values are chosen by index \
                                 (0..{}) or by name ({}){}",
                                t.values.len() - 1,
                                names.join(", "),
                                crate::registry::closest(c, names.iter().map(String::as_str))
                                    .map(|s| format!("; did you mean `{s}`?"))
                                    .unwrap_or_default()
                            ))
                        }
                    },
                },
                None => (None, false),
            };
            Ok(t.values
                .iter()
                .enumerate()
                .filter(|(k, _)| idx.is_none_or(|i| i == *k))
                .map(|(k, x)| {
                    let name = if by_name {
                        format!("{full}.{}", names[k])
                    } else {
                        format!("{full}[{k}]")
                    };
                    Value {
                        component: Some(names[k].clone()),
                        ..v(name, &t.unit, *x)
                    }
                })
                .collect())
        }
        other => Err(format!(
            "{what} `{full}`: a {} has no values to collect (collect a table or a tensor)",
            other.kind()
        )),
    }
}

/// How a collected value is shown in tables and charts: its component name (`kappa_xx`,
/// `E_z (apparent)`) when it has one, after the artifact it belongs to
/// (`flow.permeability kappa_xx`, `x.constants E_z (apparent)`), else its name.
pub fn display_name(name: &str, component: Option<&str>) -> String {
    match component {
        Some(comp) => {
            // `flow.permeability[0]` -> `flow.permeability`; `x.constants.E_z[0]` -> `x.constants`.
            let base = name.split('[').next().unwrap_or(name);
            let base = match comp.split(' ').next() {
                Some(first) => base
                    .strip_suffix(first)
                    .map(|b| b.trim_end_matches('.'))
                    .unwrap_or(base),
                None => base,
            };
            format!("{base} {comp}")
        }
        None => name.to_string(),
    }
}

// ---------------------------------------------------------------------------------------
// `reference:`: published or independent values a run's results are compared with

/// How far a result may lie from its reference value.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Tolerance {
    /// A fraction of the reference value (`10 %` is 0.1).
    Relative(f64),
    /// In the quantity's SI unit.
    Absolute(f64),
    /// A published range (lowest and highest of the reference's realizations), in SI.
    Range(f64, f64),
}

/// One value of a pipeline's `reference:` block.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReferenceValue {
    /// `step.port.column`, `step.port.column[k]`, `step.port[k]` or `step.port.<component>`
    /// (`flow.permeability.kappa_zz`).
    pub quantity: String,
    /// The reference value in SI.
    pub value: f64,
    /// Its dimension (SI base exponents), to check against the result's unit.
    pub dimension: [i8; 7],
    /// As written in the file (`4.97 GPa`).
    pub written: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<Tolerance>,
    /// The tolerance as written (`10 %`, `0.3 GPa`).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub tolerance_written: String,
}

/// A pipeline's `reference:` block: where the numbers come from and the numbers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Reference {
    /// The publication, table or independent computation the values come from.
    pub source: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
    pub values: Vec<ReferenceValue>,
}

/// The step and port a reference quantity reads (`stiffness.constants.E_x` ->
/// (`stiffness`, `constants`, `E_x`)); `None` when it is not of the form step.port[...].
pub fn split_quantity(q: &str) -> Option<(&str, &str, &str)> {
    let (step, rest) = q.split_once('.')?;
    let end = rest.find(['.', '[']).unwrap_or(rest.len());
    let (port, tail) = rest.split_at(end);
    let tail = tail.strip_prefix('.').unwrap_or(tail);
    (!step.is_empty() && !port.is_empty()).then_some((step, port, tail))
}

/// How one result compares with its reference.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    Within,
    Outside,
    /// No tolerance was given: the difference is shown, not judged.
    Compared,
    /// The run did not compute the quantity (a failed run, a `--target` run, NaN).
    Missing,
}

/// One row of the comparison `run.json` records and the report shows.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Comparison {
    pub quantity: String,
    /// The result's component name when it has one (`kappa_zz`, `E_x (apparent)`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub component: Option<String>,
    pub reference: f64,
    pub reference_written: String,
    /// The result in its unit (`unit`); `None` when missing.
    pub result: Option<f64>,
    pub unit: String,
    /// (result - reference) / |reference|.
    pub relative_difference: Option<f64>,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub tolerance: String,
    pub verdict: Verdict,
    /// Why a result is missing.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub why: String,
}

impl Comparison {
    /// The unit the reference was written in and the factor from SI to it (`5.07 GPa` ->
    /// (1e9, "GPa")); a bare number is in SI.
    pub fn written_unit(&self) -> (f64, &str) {
        let w = self.reference_written.trim();
        let (number, unit) = match w.split_once(char::is_whitespace) {
            Some((n, u)) => (n.parse::<f64>().ok(), u.trim()),
            None => (w.parse::<f64>().ok(), ""),
        };
        match number.filter(|n| *n != 0.0) {
            Some(n) => (self.reference / n, unit),
            None => (1.0, ""),
        }
    }

    /// The result minus the reference, in SI.
    pub fn difference(&self) -> Option<f64> {
        self.result.map(|x| x - self.reference)
    }
}

/// The dimension of a result's unit string (`Pa`, `m^2`, `1`, empty for a number).
fn unit_dimension(unit: &str) -> Option<[i8; 7]> {
    match unit.trim() {
        "" | "1" => Some([0; 7]),
        u => crate::units::parse_unit(u).ok().map(|(_, d)| d.0),
    }
}

/// Compares a run's outputs with every value of its `reference:` block (outputs of steps that
/// did not run give rows with [`Verdict::Missing`]).
pub fn compare(reference: &Reference, outputs: &IndexMap<String, Arc<Outputs>>) -> Vec<Comparison> {
    reference
        .values
        .iter()
        .map(|rv| {
            let row = |result: Option<f64>, unit: String, component, why: String| {
                let rel = result.map(|x| (x - rv.value) / rv.value.abs());
                let verdict = match (result, rv.tolerance) {
                    (None, _) => Verdict::Missing,
                    (Some(_), None) => Verdict::Compared,
                    (Some(x), Some(Tolerance::Relative(t))) => {
                        if (x - rv.value).abs() <= t * rv.value.abs() {
                            Verdict::Within
                        } else {
                            Verdict::Outside
                        }
                    }
                    (Some(x), Some(Tolerance::Absolute(t))) => {
                        if (x - rv.value).abs() <= t {
                            Verdict::Within
                        } else {
                            Verdict::Outside
                        }
                    }
                    (Some(x), Some(Tolerance::Range(lo, hi))) => {
                        if (lo..=hi).contains(&x) {
                            Verdict::Within
                        } else {
                            Verdict::Outside
                        }
                    }
                };
                Comparison {
                    quantity: rv.quantity.clone(),
                    component,
                    reference: rv.value,
                    reference_written: rv.written.clone(),
                    result,
                    unit,
                    relative_difference: rel.filter(|r| r.is_finite()),
                    tolerance: rv.tolerance_written.clone(),
                    verdict,
                    why,
                }
            };
            let Some((step, port, tail)) = split_quantity(&rv.quantity) else {
                return row(
                    None,
                    String::new(),
                    None,
                    "not of the form step.port".into(),
                );
            };
            let values = match values_of(outputs, step, port, None, "reference") {
                Ok(v) => v,
                Err(_) if !outputs.contains_key(step) => {
                    return row(
                        None,
                        String::new(),
                        None,
                        format!("step `{step}` did not run"),
                    )
                }
                Err(e) => return row(None, String::new(), None, e),
            };
            // A row named by its label: `E_x[orthotropic]` is the component `E_x (orthotropic)`.
            let by_label = tail
                .strip_suffix(']')
                .and_then(|t| t.split_once('['))
                .map(|(col, row)| format!("{col} ({row})"));
            let found = values.iter().find(|v| {
                v.name == rv.quantity
                    || v.component.as_deref() == Some(tail)
                    || (by_label.is_some() && v.component == by_label)
            });
            let Some(v) = found else {
                // As they would be written: `step.port.column[row]`, `step.port.kappa_zz`.
                let mut names: Vec<String> = values
                    .iter()
                    .map(|v| match &v.component {
                        Some(c) => match c.split_once(" (") {
                            Some((col, row)) => {
                                format!("{step}.{port}.{col}[{}]", row.trim_end_matches(')'))
                            }
                            None => format!("{step}.{port}.{c}"),
                        },
                        None => v.name.clone(),
                    })
                    .collect();
                names.truncate(12);
                return row(
                    None,
                    String::new(),
                    None,
                    format!("no value `{}`; it has: {}", rv.quantity, names.join(", ")),
                );
            };
            if unit_dimension(&v.unit) != Some(rv.dimension) {
                return row(
                    None,
                    v.unit.clone(),
                    v.component.clone(),
                    format!(
                        "the result is in {} but the reference `{}` is not",
                        if v.unit.is_empty() { "1" } else { &v.unit },
                        rv.written
                    ),
                );
            }
            match v.value {
                Some(x) => row(Some(x), v.unit.clone(), v.component.clone(), String::new()),
                None => row(
                    None,
                    v.unit.clone(),
                    v.component.clone(),
                    "not finite (NaN)".into(),
                ),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Tensor, TensorConvention};

    fn tensor(name: &str, shape: Vec<usize>) -> Tensor {
        let n = shape.iter().product();
        Tensor {
            name: name.into(),
            unit: String::new(),
            shape,
            values: vec![0.0; n],
            convention: TensorConvention::Plain,
        }
    }

    /// Issue 36: sweep reports name tensor components (`kappa_xx`, not `[0]`).
    #[test]
    fn tensor_components_are_named() {
        let k = tensor("permeability", vec![3, 3]);
        assert_eq!(component_name(&k, 0), "kappa_xx");
        assert_eq!(component_name(&k, 5), "kappa_yz");
        assert_eq!(component_name(&k, 8), "kappa_zz");
        assert_eq!(
            component_name(&tensor("conductivity", vec![3, 3]), 4),
            "k_yy"
        );
        assert_eq!(component_name(&tensor("stiffness", vec![6, 6]), 7), "C_22");
        assert_eq!(component_name(&tensor("fabric", vec![3]), 2), "fabric_z");
        // Stored only when known: result.json of values without a name read back.
        let v: Value = serde_json::from_str(r#"{"name":"a","unit":"","value":1.0}"#).unwrap();
        assert_eq!(v.component, None);
        let t = serde_json::to_string(&Value {
            component: Some("kappa_xx".into()),
            ..v
        })
        .unwrap();
        assert!(t.contains("\"component\":\"kappa_xx\""));
    }

    #[test]
    fn values_are_shown_by_their_component_names() {
        assert_eq!(
            display_name("flow.permeability[8]", Some("kappa_zz")),
            "flow.permeability kappa_zz"
        );
        assert_eq!(
            display_name("x.constants.E_z[0]", Some("E_z (apparent)")),
            "x.constants E_z (apparent)"
        );
        assert_eq!(display_name("s.report.volume", None), "s.report.volume");
    }

    /// `--collect`, `--metric` and `auto_quantities` name a tensor component by index or by
    /// name; a wrong name lists the names.
    #[test]
    fn tensor_components_are_chosen_by_index_or_name() {
        let mut k = tensor("permeability", vec![3, 3]);
        k.values = (0..9).map(f64::from).collect();
        let mut o = Outputs::new();
        o.insert("permeability".into(), Artifact::Tensor(k));
        let mut outputs = IndexMap::new();
        outputs.insert("flow".to_string(), Arc::new(o));
        let by_index = values_of(&outputs, "flow", "permeability", Some("8"), "--collect").unwrap();
        assert_eq!(
            (by_index[0].name.as_str(), by_index[0].value),
            ("flow.permeability[8]", Some(8.0))
        );
        let by_name = values_of(
            &outputs,
            "flow",
            "permeability",
            Some("kappa_yz"),
            "--collect",
        )
        .unwrap();
        assert_eq!(
            (by_name[0].name.as_str(), by_name[0].value),
            ("flow.permeability.kappa_yz", Some(5.0))
        );
        let e = values_of(
            &outputs,
            "flow",
            "permeability",
            Some("kapa_zz"),
            "--collect",
        )
        .unwrap_err();
        assert!(
            e.contains("did you mean `kappa_zz`?") && e.contains("0..8"),
            "{e}"
        );
    }

    /// A table row by index or by its label: `constants.E_x[orthotropic]`.
    #[test]
    fn table_rows_are_chosen_by_index_or_label() {
        let t = crate::Table::new("c")
            .with_str(
                "approximation",
                vec!["apparent".into(), "orthotropic".into()],
            )
            .with_f64("E_x", "Pa", vec![1.0, 2.0]);
        let mut o = Outputs::new();
        o.insert("constants".into(), Artifact::Table(t));
        let mut outputs = IndexMap::new();
        outputs.insert("s".to_string(), Arc::new(o));
        let get = |c: &str| values_of(&outputs, "s", "constants", Some(c), "--collect");
        let by_label = get("E_x[orthotropic]").unwrap();
        assert_eq!(by_label.len(), 1);
        assert_eq!(by_label[0].name, "s.constants.E_x[orthotropic]");
        assert_eq!(by_label[0].value, Some(2.0));
        assert_eq!(get("E_x[0]").unwrap()[0].value, Some(1.0));
        assert_eq!(get("E_x").unwrap().len(), 2);
        let e = get("E_x[isotropic]").unwrap_err();
        assert!(
            e.contains("no row `isotropic`") && e.contains("apparent, orthotropic"),
            "{e}"
        );
    }

    /// Results are shown in the unit their reference was written in.
    #[test]
    fn a_comparison_knows_its_written_unit() {
        let c = |w: &str, r: f64| Comparison {
            quantity: "s.t.x".into(),
            component: None,
            reference: r,
            reference_written: w.into(),
            result: Some(0.5 * r),
            unit: String::new(),
            relative_difference: Some(-0.5),
            tolerance: String::new(),
            verdict: Verdict::Compared,
            why: String::new(),
        };
        let gpa = c("5.07 GPa", 5.07e9);
        let (f, u) = gpa.written_unit();
        assert!((f / 1e9 - 1.0).abs() < 1e-12 && u == "GPa", "{f} {u}");
        let m2 = c("2.19e-11 m^2", 2.19e-11);
        let (f, u) = m2.written_unit();
        assert!((f - 1.0).abs() < 1e-12 && u == "m^2", "{f} {u}");
        assert_eq!(c("-0.09", -0.09).written_unit(), (1.0, ""));
        assert_eq!(c("-0.09", -0.09).difference(), Some(0.045));
    }

    #[test]
    fn quantities_split_into_step_port_and_the_rest() {
        assert_eq!(
            split_quantity("s.constants.E_x"),
            Some(("s", "constants", "E_x"))
        );
        assert_eq!(
            split_quantity("flow.permeability[8]"),
            Some(("flow", "permeability", "[8]"))
        );
        assert_eq!(
            split_quantity("flow.permeability"),
            Some(("flow", "permeability", ""))
        );
        assert_eq!(split_quantity("flow"), None);
        assert_eq!(split_quantity(".x"), None);
    }

    /// A tensor component by name and by index, a relative and an absolute tolerance, and a
    /// NaN component (a direction not solved), against values worked out by hand.
    #[test]
    fn tensor_components_compare_by_name_and_index() {
        let mut k = tensor("permeability", vec![3, 3]);
        k.unit = "m^2".into();
        k.values = vec![2e-11, 0.0, 0.0, 0.0, 2e-11, 0.0, 0.0, 0.0, f64::NAN];
        let mut o = Outputs::new();
        o.insert("permeability".into(), Artifact::Tensor(k));
        let mut outputs = IndexMap::new();
        outputs.insert("flow".to_string(), Arc::new(o));
        let rv = |q: &str, v: f64, t: Option<Tolerance>| ReferenceValue {
            quantity: q.into(),
            value: v,
            dimension: [2, 0, 0, 0, 0, 0, 0],
            written: format!("{v} m^2"),
            tolerance: t,
            tolerance_written: String::new(),
        };
        let r = Reference {
            source: "hand".into(),
            note: String::new(),
            values: vec![
                rv(
                    "flow.permeability.kappa_xx",
                    2.5e-11,
                    Some(Tolerance::Relative(0.1)),
                ),
                rv(
                    "flow.permeability[4]",
                    2.5e-11,
                    Some(Tolerance::Absolute(0.6e-11)),
                ),
                rv("flow.permeability.kappa_zz", 2.5e-11, None),
                rv("solid.constants.E_x", 2.5e-11, None),
            ],
        };
        let c = compare(&r, &outputs);
        // (2 - 2.5) / 2.5 = -0.2: outside 10 %, within 0.6e-11 absolute.
        assert!((c[0].relative_difference.unwrap() + 0.2).abs() < 1e-12);
        assert_eq!(c[0].verdict, Verdict::Outside);
        assert_eq!(c[0].component.as_deref(), Some("kappa_xx"));
        assert_eq!(c[1].verdict, Verdict::Within);
        assert_eq!(c[2].verdict, Verdict::Missing);
        assert!(c[2].why.contains("NaN"));
        assert_eq!(c[3].verdict, Verdict::Missing);
        assert!(c[3].why.contains("did not run"));
    }
}
