//! Physical quantities in SI units, with parsing of unit strings such as `"140 um"`,
//! `"66.9 GPa"` or `"0.5 J/(g K)"`.
//!
//! Everything inside grainpipe is SI. YAML values may be plain numbers (taken as SI) or
//! strings with a unit; [`Q`] checks the dimension when it deserializes, so `radius: 3 W`
//! is refused with a message naming the expected unit.

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::fmt;
use std::marker::PhantomData;

/// Exponents of the SI base units (m, kg, s, K, A, mol, cd).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Dimension(pub [i8; 7]);

impl Dimension {
    pub const NONE: Dimension = Dimension([0; 7]);
    pub const LENGTH: Dimension = Dimension([1, 0, 0, 0, 0, 0, 0]);
    pub const MASS: Dimension = Dimension([0, 1, 0, 0, 0, 0, 0]);
    pub const TIME: Dimension = Dimension([0, 0, 1, 0, 0, 0, 0]);
    pub const TEMPERATURE: Dimension = Dimension([0, 0, 0, 1, 0, 0, 0]);

    fn mul(self, other: Dimension, power: i8) -> Dimension {
        let mut e = self.0;
        for (a, b) in e.iter_mut().zip(other.0) {
            *a += b * power;
        }
        Dimension(e)
    }
}

impl fmt::Display for Dimension {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        const NAMES: [&str; 7] = ["m", "kg", "s", "K", "A", "mol", "cd"];
        if *self == Dimension::NONE {
            return write!(f, "1 (dimensionless)");
        }
        let mut first = true;
        for (name, e) in NAMES.iter().zip(self.0) {
            if e == 0 {
                continue;
            }
            if !first {
                write!(f, " ")?;
            }
            first = false;
            if e == 1 {
                write!(f, "{name}")?;
            } else {
                write!(f, "{name}^{e}")?;
            }
        }
        Ok(())
    }
}

/// A parsed quantity: SI value and its dimension.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Quantity {
    pub value: f64,
    pub dim: Dimension,
}

/// Named units: symbol, factor to SI, dimension.
const UNITS: &[(&str, f64, [i8; 7])] = &[
    ("m", 1.0, [1, 0, 0, 0, 0, 0, 0]),
    ("g", 1e-3, [0, 1, 0, 0, 0, 0, 0]),
    ("s", 1.0, [0, 0, 1, 0, 0, 0, 0]),
    ("min", 60.0, [0, 0, 1, 0, 0, 0, 0]),
    ("h", 3600.0, [0, 0, 1, 0, 0, 0, 0]),
    ("K", 1.0, [0, 0, 0, 1, 0, 0, 0]),
    ("A", 1.0, [0, 0, 0, 0, 1, 0, 0]),
    ("mol", 1.0, [0, 0, 0, 0, 0, 1, 0]),
    ("N", 1.0, [1, 1, -2, 0, 0, 0, 0]),
    ("Pa", 1.0, [-1, 1, -2, 0, 0, 0, 0]),
    ("J", 1.0, [2, 1, -2, 0, 0, 0, 0]),
    ("W", 1.0, [2, 1, -3, 0, 0, 0, 0]),
    ("Hz", 1.0, [0, 0, -1, 0, 0, 0, 0]),
    ("L", 1e-3, [3, 0, 0, 0, 0, 0, 0]),
    ("D", 9.869_233e-13, [2, 0, 0, 0, 0, 0, 0]), // darcy, for permeability
    ("%", 0.01, [0, 0, 0, 0, 0, 0, 0]),
    // What people write for micrometres.
    ("micron", 1e-6, [1, 0, 0, 0, 0, 0, 0]),
    ("microns", 1e-6, [1, 0, 0, 0, 0, 0, 0]),
];

/// For a unit that parsed to the wrong dimension: the symbols read as a prefix on a unit
/// where the prefix is itself a unit (`mK` is millikelvin, not metre kelvin), with the
/// spelling that separates them.
pub fn prefix_reading_hint(text: &str) -> Option<String> {
    let unit = text.trim_start_matches(|c: char| {
        c.is_ascii_digit() || matches!(c, '.' | '-' | '+' | 'e' | 'E' | ' ')
    });
    let tokens = tokenize(unit).ok()?;
    for t in &tokens {
        if UNITS.iter().any(|(s, _, _)| s == t) {
            continue;
        }
        for (p, _) in PREFIXES {
            if let Some(rest) = t.strip_prefix(p) {
                let prefix_is_unit = UNITS.iter().any(|(s, _, _)| s == p);
                if prefix_is_unit && UNITS.iter().any(|(s, _, _)| *s == rest) {
                    return Some(format!(
                        "`{t}` reads as {p}-prefixed `{rest}`; for `{p}` times `{rest}` write \
                         `{p} {rest}` (e.g. `W/(m K)`)"
                    ));
                }
            }
        }
    }
    None
}

const PREFIXES: &[(&str, f64)] = &[
    ("p", 1e-12),
    ("n", 1e-9),
    ("u", 1e-6),
    ("µ", 1e-6),
    ("μ", 1e-6),
    ("m", 1e-3),
    ("c", 1e-2),
    ("k", 1e3),
    ("M", 1e6),
    ("G", 1e9),
    ("T", 1e12),
];

fn lookup_unit(symbol: &str) -> Option<(f64, Dimension)> {
    // Exact names win over prefix decomposition ("min" is minutes, not milli-inch; "m" is metre).
    if let Some((_, f, d)) = UNITS.iter().find(|(s, _, _)| *s == symbol) {
        return Some((*f, Dimension(*d)));
    }
    for (p, pf) in PREFIXES {
        if let Some(rest) = symbol.strip_prefix(p) {
            if let Some((_, f, d)) = UNITS.iter().find(|(s, _, _)| *s == rest && *s != "%") {
                return Some((pf * f, Dimension(*d)));
            }
        }
    }
    None
}

/// Parses a unit expression: products separated by spaces or `*`, one `/` level, parentheses
/// for a grouped denominator, and integer exponents with `^` (e.g. `g/um^3`, `J/(g K)`, `W/m^2`).
pub fn parse_unit(expr: &str) -> Result<(f64, Dimension), String> {
    let tokens = tokenize(expr)?;
    let mut pos = 0;
    let (f, d) = parse_product(&tokens, &mut pos, expr)?;
    if pos != tokens.len() {
        return Err(format!("unexpected `{}` in unit `{expr}`", tokens[pos]));
    }
    Ok((f, d))
}

fn tokenize(expr: &str) -> Result<Vec<String>, String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    for c in expr.chars() {
        match c {
            ' ' | '*' | '·' | '.' => {
                if !cur.is_empty() {
                    out.push(std::mem::take(&mut cur));
                }
            }
            '/' | '(' | ')' | '^' => {
                if !cur.is_empty() {
                    out.push(std::mem::take(&mut cur));
                }
                out.push(c.to_string());
            }
            _ => cur.push(c),
        }
    }
    if !cur.is_empty() {
        out.push(cur);
    }
    if out.is_empty() {
        return Err("empty unit".into());
    }
    Ok(out)
}

fn parse_product(t: &[String], pos: &mut usize, expr: &str) -> Result<(f64, Dimension), String> {
    let mut factor = 1.0;
    let mut dim = Dimension::NONE;
    let mut sign: i8 = 1;
    while *pos < t.len() && t[*pos] != ")" {
        if t[*pos] == "/" {
            if sign == -1 {
                return Err(format!(
                    "ambiguous unit `{expr}`: use parentheses after `/`"
                ));
            }
            sign = -1;
            *pos += 1;
            continue;
        }
        let (f, d) = if t[*pos] == "(" {
            *pos += 1;
            let inner = parse_product(t, pos, expr)?;
            if *pos >= t.len() || t[*pos] != ")" {
                return Err(format!("unbalanced parenthesis in unit `{expr}`"));
            }
            *pos += 1;
            inner
        } else {
            let sym = &t[*pos];
            *pos += 1;
            lookup_unit(sym).ok_or_else(|| format!("unknown unit `{sym}` in `{expr}`"))?
        };
        let mut exp: i8 = 1;
        if *pos < t.len() && t[*pos] == "^" {
            let e = t
                .get(*pos + 1)
                .ok_or_else(|| format!("missing exponent in unit `{expr}`"))?;
            exp = e
                .parse()
                .map_err(|_| format!("exponent `{e}` in unit `{expr}` is not an integer"))?;
            *pos += 2;
        }
        let p = exp * sign;
        factor *= f.powi(p as i32);
        dim = dim.mul(d, p);
    }
    Ok((factor, dim))
}

/// A length for messages, in the unit that keeps it between 1 and 1000 (`400 um`, `1 mm`),
/// with 4 significant digits; the text parses back with [`parse_quantity`].
pub fn format_length(metres: f64) -> String {
    if !metres.is_finite() || metres == 0.0 {
        return format!("{metres} m");
    }
    let (scale, unit) = match metres.abs() {
        x if x >= 1.0 => (1.0, "m"),
        x if x >= 1e-3 => (1e-3, "mm"),
        x if x >= 1e-6 => (1e-6, "um"),
        _ => (1e-9, "nm"),
    };
    let v = metres / scale;
    let digits = (3 - v.abs().log10().floor() as i32).clamp(0, 3) as usize;
    let text = format!("{v:.digits$}");
    let text = if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        text
    };
    format!("{text} {unit}")
}

/// Parses `"<number> <unit>"` (or a bare number, which is dimensionless).
pub fn parse_quantity(text: &str) -> Result<Quantity, String> {
    let s = text.trim();
    let split = s
        .char_indices()
        .find(|(i, c)| {
            !(c.is_ascii_digit()
                || *c == '.'
                || *c == '-'
                || *c == '+'
                || ((*c == 'e' || *c == 'E')
                    && s[i + 1..]
                        .starts_with(|n: char| n.is_ascii_digit() || n == '-' || n == '+')))
        })
        .map(|(i, _)| i)
        .unwrap_or(s.len());
    let (num, unit) = s.split_at(split);
    let value: f64 = num
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` does not start with a number"))?;
    let unit = unit.trim();
    if unit.is_empty() {
        return Ok(Quantity {
            value,
            dim: Dimension::NONE,
        });
    }
    let (f, dim) = parse_unit(unit)?;
    Ok(Quantity {
        value: value * f,
        dim,
    })
}

/// Marker for the dimension a [`Q`] must have.
pub trait Dim {
    const DIM: Dimension;
    /// Unit shown in `pipe describe` and error messages.
    const SI_UNIT: &'static str;
    /// What the quantity is, in words, as `pipe describe` names its type.
    const NAME: &'static str;
}

macro_rules! dims {
    ($($name:ident = $exp:expr, $unit:expr, $word:expr;)*) => {$(
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
        pub struct $name;
        impl Dim for $name {
            const DIM: Dimension = Dimension($exp);
            const SI_UNIT: &'static str = $unit;
            const NAME: &'static str = $word;
        }
    )*};
}

dims! {
    Dimensionless = [0, 0, 0, 0, 0, 0, 0], "1", "number";
    Length = [1, 0, 0, 0, 0, 0, 0], "m", "length";
    Area = [2, 0, 0, 0, 0, 0, 0], "m^2", "area";
    Volume = [3, 0, 0, 0, 0, 0, 0], "m^3", "volume";
    Mass = [0, 1, 0, 0, 0, 0, 0], "kg", "mass";
    Time = [0, 0, 1, 0, 0, 0, 0], "s", "time";
    Temperature = [0, 0, 0, 1, 0, 0, 0], "K", "temperature";
    Velocity = [1, 0, -1, 0, 0, 0, 0], "m/s", "speed";
    Pressure = [-1, 1, -2, 0, 0, 0, 0], "Pa", "pressure or stress";
    Power = [2, 1, -3, 0, 0, 0, 0], "W", "power";
    Energy = [2, 1, -2, 0, 0, 0, 0], "J", "energy";
    Density = [-3, 1, 0, 0, 0, 0, 0], "kg/m^3", "density";
    SpecificHeat = [2, 0, -2, -1, 0, 0, 0], "J/(kg K)", "specific heat";
    SpecificEnergy = [2, 0, -2, 0, 0, 0, 0], "J/kg", "specific energy";
    Conductance = [2, 1, -3, -1, 0, 0, 0], "W/K", "thermal conductance";
    Viscosity = [-1, 1, -1, 0, 0, 0, 0], "Pa s", "dynamic viscosity";
    ThermalConductivity = [1, 1, -3, -1, 0, 0, 0], "W/(m K)", "thermal conductivity";
}

/// A value of dimension `D`, stored in SI. Deserializes from a number (SI) or a unit string.
#[derive(Clone, Copy, PartialEq, PartialOrd)]
pub struct Q<D: Dim>(pub f64, PhantomData<D>);

impl<D: Dim> Q<D> {
    pub const fn new(si: f64) -> Self {
        Q(si, PhantomData)
    }
    pub fn si(self) -> f64 {
        self.0
    }
}

impl<D: Dim> Default for Q<D> {
    fn default() -> Self {
        Q::new(0.0)
    }
}

impl<D: Dim> fmt::Debug for Q<D> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}", self.0, D::SI_UNIT)
    }
}

impl<D: Dim> Serialize for Q<D> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_f64(self.0)
    }
}

impl<'de, D: Dim> Deserialize<'de> for Q<D> {
    fn deserialize<De: Deserializer<'de>>(d: De) -> Result<Self, De::Error> {
        struct V<D>(PhantomData<D>);
        impl<D: Dim> serde::de::Visitor<'_> for V<D> {
            type Value = Q<D>;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                write!(f, "a number in {} or a string with a unit", D::SI_UNIT)
            }
            fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<Q<D>, E> {
                Ok(Q::new(v))
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<Q<D>, E> {
                Ok(Q::new(v as f64))
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<Q<D>, E> {
                Ok(Q::new(v as f64))
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<Q<D>, E> {
                let q = parse_quantity(v).map_err(E::custom)?;
                if q.dim != D::DIM {
                    let hint = prefix_reading_hint(v)
                        .map(|h| format!(": {h}"))
                        .unwrap_or_default();
                    return Err(E::custom(format!(
                        "`{v}` has dimension {} but this parameter takes {}{hint}",
                        q.dim,
                        D::SI_UNIT
                    )));
                }
                Ok(Q::new(q.value))
            }
        }
        d.deserialize_any(V(PhantomData))
    }
}

pub type LengthQ = Q<Length>;

/// Largest elastic modulus the solvers accept: 1e15 Pa, about 1000 times diamond's Young's
/// modulus. Above it the value is a unit slip (`GPa` for `Pa` twice over), and energies of
/// order E^2 head for the f64 overflow.
pub const MAX_MODULUS: f64 = 1e15;

/// Smallest elastic modulus the solvers accept: 1e-20 Pa. Nothing solid is that soft, but
/// scale-free studies use moduli of order 1 Pa, so the floor sits where the arithmetic
/// fails: near the subnormals (E = 5e-324) the derived Lame constants underflow to zero and
/// the solid is taken for pore, and single-precision stresses lose their digits below
/// about 1e-30.
pub const MIN_MODULUS: f64 = 1e-20;

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        ((a - b) / b).abs() < 1e-12
    }

    #[test]
    fn parses_prefixed_and_compound_units() {
        let q = parse_quantity("140 um").unwrap();
        assert!(close(q.value, 140e-6) && q.dim == Dimension::LENGTH);
        let q = parse_quantity("66.9 GPa").unwrap();
        assert!(close(q.value, 66.9e9));
        // The paper's heat capacity 0.5 J/(g K) is 500 J/(kg K).
        let q = parse_quantity("0.5 J/(g K)").unwrap();
        assert!(close(q.value, 500.0));
        assert_eq!(q.dim, SpecificHeat::DIM);
        // The paper's density 8e-12 g/um^3 is 8000 kg/m^3.
        let q = parse_quantity("8e-12 g/um^3").unwrap();
        assert!(close(q.value, 8000.0));
        assert_eq!(q.dim, Density::DIM);
        let q = parse_quantity("2.9090e-5 W/K").unwrap();
        assert!(close(q.value, 2.909e-5));
        let q = parse_quantity("1.5 mm/s").unwrap();
        assert!(close(q.value, 1.5e-3));
        let q = parse_quantity("3 min").unwrap();
        assert!(close(q.value, 180.0));
        // Silica sand conducts about 1.4 W/(m K); 0.0014 W/(mm K) is the same.
        let q = parse_quantity("0.0014 W/(mm K)").unwrap();
        assert!(close(q.value, 1.4));
        assert_eq!(q.dim, ThermalConductivity::DIM);
        let q = parse_quantity("2 um^2").unwrap();
        assert!(close(q.value, 2e-12));
        assert_eq!(q.dim, Area::DIM);
    }

    #[test]
    fn rejects_wrong_dimension_and_unknown_units() {
        let e = serde_json::from_str::<Q<Length>>("\"3 W\"").unwrap_err();
        assert!(e.to_string().contains("takes m"), "{e}");
        assert!(parse_quantity("3 furlongs").is_err());
        assert!(parse_quantity("um").is_err());
        // Issue 36: `micron(s)` are accepted, and `W/mK` (watts per millikelvin) is explained.
        assert!(close(parse_quantity("140 microns").unwrap().value, 140e-6));
        assert!(close(parse_quantity("1 micron").unwrap().value, 1e-6));
        let hint = prefix_reading_hint("0.5 W/mK").unwrap();
        assert!(
            hint.contains("`mK` reads as m-prefixed `K`") && hint.contains("W/(m K)"),
            "{hint}"
        );
        assert_eq!(prefix_reading_hint("0.5 W/(m K)"), None);
        let e = serde_json::from_value::<Q<ThermalConductivity>>(serde_json::json!("0.5 W/mK"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("takes W/(m K)") && e.contains("reads as m-prefixed"),
            "{e}"
        );
        assert_eq!(format_length(4e-4), "400 um");
        assert_eq!(format_length(1e-3), "1 mm");
        assert_eq!(format_length(2.5e-5), "25 um");
        assert_eq!(format_length(1.234567e-5), "12.35 um");
        assert_eq!(format_length(3.0), "3 m");
        for x in [4e-4, 1.234567e-5, 7.5e-8, 0.02] {
            let back = parse_quantity(&format_length(x)).unwrap().value;
            assert!((back - x).abs() <= 1e-3 * x, "{x} -> {back}");
        }
        let q: Q<Length> = serde_json::from_str("2.5e-6").unwrap();
        assert_eq!(q.si(), 2.5e-6);
    }
}
