//! One declaration per parameter. A stage's parameters are a struct marked
//! [`params`](crate::params_attr) whose fields carry doc comments and `#[param(...)]`
//! attributes; from it come the serde struct, its defaults, the words and units `pipe describe`
//! prints, the JSON Schema, the unknown-key check (with a suggestion) and the cache's list of
//! files to hash. Parameter groups shared by several stages flatten into them without losing
//! the unknown-key check, which is done here against the declaration rather than by serde.

use crate::units::{Dim, Q};
use indexmap::IndexMap;
use serde::Serialize;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::path::PathBuf;

/// A declared parameter, shown by `pipe describe` and `pipe describe --json`.
#[derive(Clone, Debug, Serialize)]
pub struct ParamSpec {
    pub name: &'static str,
    /// What the YAML value looks like, in words: "length", "integer", "one of: a, b", ...
    #[serde(rename = "type")]
    pub ty: String,
    /// SI unit of the value ("" for dimensionless or non-numeric values).
    pub unit: String,
    pub doc: &'static str,
    /// The value names an input file or directory: the cache key hashes its content.
    pub reads_file: bool,
    /// JSON Schema of the value.
    pub schema: Value,
    /// Default value as JSON (SI numbers).
    pub default: Value,
}

/// A parameter struct: implemented by `#[params]`.
pub trait Params:
    Serialize + serde::de::DeserializeOwned + Default + Clone + Send + Sync + 'static
{
    /// Every parameter in declaration order (groups flattened in place).
    fn specs() -> Vec<ParamSpec>;
    /// Deserializes the value of parameter `key` alone, into its declared type: `None` when
    /// no field (of this struct or a flattened group) is called `key`, else the error as
    /// (key path, message). Locates errors that serde reports without a path (inside a
    /// flattened group).
    fn check_value(key: &str, value: &Value) -> Option<Result<(), (String, String)>>;
}

/// Deserializes one parameter value into `T` (used by `#[params]`); the error names the
/// path inside the value, e.g. `radius.value`.
pub fn check_field<T: serde::de::DeserializeOwned>(
    key: &str,
    value: &Value,
) -> Result<(), (String, String)> {
    serde_path_to_error::deserialize::<_, T>(value)
        .map(|_| ())
        .map_err(|e| {
            let path = e.path().to_string();
            let path = if path == "." || path.is_empty() {
                key.to_string()
            } else {
                format!("{key}.{path}")
            };
            (path, e.into_inner().to_string())
        })
}

/// A type a parameter can have: how `pipe describe` and the JSON Schema name it.
pub trait ParamType {
    fn type_name() -> String;
    /// SI unit of the value ("" when dimensionless or not a number).
    fn unit() -> &'static str {
        ""
    }
    fn schema() -> Value;
}

/// Fills each spec's `default` from the serialized default struct (used by `#[params]`).
pub fn fill_defaults<P: Serialize>(specs: &mut [ParamSpec], defaults: &P) {
    let v = serde_json::to_value(defaults).expect("parameter defaults serialize to JSON");
    for s in specs {
        if let Some(d) = v.get(s.name) {
            s.default = d.clone();
        }
    }
}

/// The serde spelling of a unit enum variant (used by `ParamChoice`).
pub fn serde_word<T: Serialize>(v: &T) -> String {
    match serde_json::to_value(v) {
        Ok(Value::String(s)) => s,
        other => panic!("a ParamChoice variant must serialize to a string, got {other:?}"),
    }
}

pub fn choice_type_name(choices: &[(String, &'static str)]) -> String {
    format!(
        "one of: {}",
        choices
            .iter()
            .map(|(c, _)| c.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    )
}

pub fn choice_schema(choices: &[(String, &'static str)]) -> Value {
    json!({ "enum": choices.iter().map(|(c, _)| c.clone()).collect::<Vec<_>>() })
}

/// A parameter key that the stage does not declare.
#[derive(Clone, Debug, PartialEq)]
pub struct UnknownKey {
    pub key: String,
    pub suggestion: Option<String>,
}

/// Finds the keys of `given` (a YAML `with:` mapping as JSON) that no spec declares, each with
/// the closest declared name.
pub fn unknown_keys(given: &Value, specs: &[ParamSpec]) -> Vec<UnknownKey> {
    let Some(map) = given.as_object() else {
        return Vec::new();
    };
    map.keys()
        .filter(|k| !specs.iter().any(|s| s.name == k.as_str()))
        .map(|k| UnknownKey {
            key: k.clone(),
            suggestion: crate::suggest::closest(k, specs.iter().map(|s| s.name)),
        })
        .collect()
}

/// JSON Schema of a stage's `with:` mapping.
pub fn object_schema(specs: &[ParamSpec]) -> Value {
    let props: serde_json::Map<String, Value> = specs
        .iter()
        .map(|s| {
            let mut p = s.schema.clone();
            if let Value::Object(m) = &mut p {
                m.insert("description".into(), Value::String(s.doc.to_string()));
                m.insert("default".into(), s.default.clone());
                if !s.unit.is_empty() {
                    m.insert("x-unit".into(), Value::String(s.unit.clone()));
                }
            }
            (s.name.to_string(), p)
        })
        .collect();
    json!({ "type": "object", "properties": props, "additionalProperties": false })
}

macro_rules! plain_types {
    ($($t:ty => $name:expr, $schema:expr;)*) => {$(
        impl ParamType for $t {
            fn type_name() -> String {
                $name.to_string()
            }
            fn schema() -> Value {
                $schema
            }
        }
    )*};
}

plain_types! {
    f64 => "number", json!({"type": "number"});
    f32 => "number", json!({"type": "number"});
    u8 => "integer", json!({"type": "integer", "minimum": 0, "maximum": 255});
    u32 => "integer", json!({"type": "integer", "minimum": 0});
    u64 => "integer", json!({"type": "integer", "minimum": 0});
    usize => "integer", json!({"type": "integer", "minimum": 0});
    i32 => "integer", json!({"type": "integer"});
    i64 => "integer", json!({"type": "integer"});
    bool => "true or false", json!({"type": "boolean"});
    String => "text", json!({"type": "string"});
    PathBuf => "path", json!({"type": "string"});
    Value => "any value", json!({});
}

/// A number, or a string with a unit such as "140 um".
fn quantity_schema(unit: &str) -> Value {
    json!({"anyOf": [
        {"type": "number"},
        {"type": "string", "pattern": "^\\s*[-+0-9.eE]+\\s*\\S.*$", "description": format!("a number with a unit of the dimension of {unit}")},
    ]})
}

impl<D: Dim> ParamType for Q<D> {
    fn type_name() -> String {
        D::NAME.to_string()
    }
    fn unit() -> &'static str {
        if D::SI_UNIT == "1" {
            ""
        } else {
            D::SI_UNIT
        }
    }
    fn schema() -> Value {
        quantity_schema(D::SI_UNIT)
    }
}

impl<T: ParamType, const N: usize> ParamType for [T; N] {
    fn type_name() -> String {
        let t = T::type_name();
        // "[length, length, length]" shows the YAML shape; longer words read better once.
        if N <= 3 && !t.contains(' ') {
            format!("[{}]", vec![t; N].join(", "))
        } else {
            format!("list of {N}: {t}")
        }
    }
    fn unit() -> &'static str {
        T::unit()
    }
    fn schema() -> Value {
        json!({"type": "array", "items": T::schema(), "minItems": N, "maxItems": N})
    }
}

impl<T: ParamType> ParamType for Vec<T> {
    fn type_name() -> String {
        format!("list of {}", T::type_name())
    }
    fn unit() -> &'static str {
        T::unit()
    }
    fn schema() -> Value {
        json!({"type": "array", "items": T::schema()})
    }
}

impl<T: ParamType> ParamType for Option<T> {
    fn type_name() -> String {
        format!("{} (optional)", T::type_name())
    }
    fn unit() -> &'static str {
        T::unit()
    }
    fn schema() -> Value {
        json!({"anyOf": [T::schema(), {"type": "null"}]})
    }
}

impl<T: ParamType> ParamType for IndexMap<String, T> {
    fn type_name() -> String {
        format!("map of name to {}", T::type_name())
    }
    fn unit() -> &'static str {
        T::unit()
    }
    fn schema() -> Value {
        json!({"type": "object", "additionalProperties": T::schema()})
    }
}

impl<T: ParamType> ParamType for BTreeMap<String, T> {
    fn type_name() -> String {
        IndexMap::<String, T>::type_name()
    }
    fn unit() -> &'static str {
        T::unit()
    }
    fn schema() -> Value {
        IndexMap::<String, T>::schema()
    }
}

/// Words that betray a Rust type rather than describing a value; the registry's consistency
/// check refuses them in `pipe describe`.
pub const RUST_TYPE_WORDS: &[&str] = &[
    "f64", "f32", "usize", "u64", "u32", "u8", "i64", "i32", "Q<", "Vec<", "Option<", "String",
    "PathBuf", "; 2]", "; 3]",
];
