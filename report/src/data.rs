//! What a report shows of each artifact, extracted from the in-memory artifacts into a small
//! serializable form (`report-data/data.json` plus PNG pictures), so a report can be
//! re-rendered later without the multi-gigabyte fields it was drawn from.

use crate::raster::{phase_slice, render_packing, scalar_slice, Plane, View};
use grainpipe_core::model::{
    Artifact, BodyShape, ColumnData, ComponentConvention, Field, Packing, TensorConvention,
};
use serde::{Deserialize, Serialize};

/// Tables longer than this are cut in the report (the full table is in the exported file).
pub const MAX_TABLE_ROWS: usize = 40;
/// Members of a collection the report shows (30 grains would drown the page).
pub const MAX_MEMBERS: usize = 4;
/// Rows of a history table kept for its plot.
pub const MAX_CURVE_ROWS: usize = 2000;
/// Pixels along the longer side of a packing rendering.
const RENDER_SIZE: usize = 360;

/// Everything `report-data/data.json` holds.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ReportData {
    pub items: Vec<Item>,
}

/// One artifact: `source` is `step.port` (or a collection member's path).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Item {
    pub source: String,
    pub body: Body,
}

/// A picture stored beside the data (`file`) with its caption and pixel size.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Picture {
    pub file: String,
    pub caption: String,
    pub width: usize,
    pub height: usize,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PhaseInfo {
    pub label: u8,
    pub name: String,
    pub fraction: f64,
    pub color: [u8; 3],
}

/// Histogram of equivalent diameters [m] by number and by volume.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Sizes {
    pub count: usize,
    pub edges: Vec<f64>,
    pub counts: Vec<u64>,
    /// Cumulative volume fraction at each upper bin edge.
    pub cumulative_volume: Vec<f64>,
    pub mean: f64,
    /// D10, D50, D90 by number.
    pub d_number: [f64; 3],
    /// D10, D50, D90 by volume.
    pub d_volume: [f64; 3],
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Col {
    pub name: String,
    pub unit: String,
    pub values: Vec<serde_json::Value>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Body {
    PhaseImage {
        dims: [usize; 3],
        spacing: [f64; 3],
        phases: Vec<PhaseInfo>,
        slices: Vec<Picture>,
    },
    Field {
        name: String,
        unit: String,
        components: usize,
        convention: String,
        /// What the slices show ("velocity magnitude |u|", "von Mises stress", ...).
        quantity: String,
        dims: [usize; 3],
        spacing: [f64; 3],
        min: f64,
        max: f64,
        /// Upper end of the colour scale (the 99th percentile); values above it saturate.
        #[serde(default)]
        scale_max: Option<f64>,
        mean: f64,
        slices: Vec<Picture>,
    },
    Packing {
        bodies: usize,
        spheres: usize,
        clumps: bool,
        layers: usize,
        volume_fraction: f64,
        domain: [f64; 3],
        periodic: [bool; 3],
        renders: Vec<Picture>,
        sizes: Option<Sizes>,
    },
    ClumpLibrary {
        clumps: usize,
        spheres: usize,
        sizes: Option<Sizes>,
    },
    ContactGraph {
        contacts: usize,
        bonds: usize,
        bodies: usize,
    },
    Table {
        name: String,
        rows: usize,
        columns: Vec<Col>,
        /// A history table (convergence, time steps) whole, or every k-th row of it and its
        /// last (at most [`MAX_CURVE_ROWS`]): what the page plots.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        curve: Option<Vec<Col>>,
    },
    Tensor {
        name: String,
        unit: String,
        convention: String,
        shape: Vec<usize>,
        /// NaN (a component not computed: a direction not solved, the off-diagonal of a
        /// permeameter) is written as null and read back as NaN.
        #[serde(with = "nan_as_null")]
        values: Vec<f64>,
    },
    Series {
        frames: usize,
        times: [f64; 2],
        last: Option<Box<Item>>,
    },
    Collection {
        /// The first [`MAX_MEMBERS`] members.
        members: Vec<Item>,
        /// How many members the collection has.
        #[serde(default)]
        total: usize,
    },
}

/// JSON has no NaN: serde_json writes a NaN f64 as null, which does not read back as an
/// f64. Values that may be NaN go through this: null on the way out, NaN on the way in.
mod nan_as_null {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(v: &[f64], s: S) -> Result<S::Ok, S::Error> {
        let o: Vec<Option<f64>> = v.iter().map(|x| x.is_finite().then_some(*x)).collect();
        o.serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
        let o = Vec::<Option<f64>>::deserialize(d)?;
        Ok(o.into_iter().map(|x| x.unwrap_or(f64::NAN)).collect())
    }
}

/// Pictures made while extracting: (file name, PNG bytes).
pub type Pictures = Vec<(String, Vec<u8>)>;

fn file_stem(source: &str) -> String {
    source
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '.' || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Extracts what the report shows of `a`, adding its pictures to `pics`.
pub fn item(source: &str, a: &Artifact, pics: &mut Pictures) -> Item {
    let stem = file_stem(source);
    let mut picture = |suffix: &str, caption: String, rgb: crate::raster::Rgb| {
        let file = format!("{stem}.{suffix}.png");
        let p = Picture {
            file: file.clone(),
            caption,
            width: rgb.width,
            height: rgb.height,
        };
        pics.push((file, rgb.png()));
        p
    };
    let body = match a {
        Artifact::PhaseImage(img) => {
            let mut labels: Vec<u8> = img.phases.iter().map(|p| p.id).collect();
            let mut counts = [0usize; 256];
            for &l in &img.labels {
                counts[l as usize] += 1;
            }
            for (l, c) in counts.iter().enumerate() {
                if *c > 0 && !labels.contains(&(l as u8)) {
                    labels.push(l as u8);
                }
            }
            labels.sort_unstable();
            let n = img.labels.len().max(1) as f64;
            let phases = labels
                .iter()
                .map(|&l| {
                    let name = img
                        .phases
                        .iter()
                        .find(|p| p.id == l)
                        .map(|p| p.name.clone())
                        .unwrap_or_else(|| format!("label {l}"));
                    PhaseInfo {
                        label: l,
                        color: crate::raster::phase_color(l, &name),
                        name,
                        fraction: counts[l as usize] as f64 / n,
                    }
                })
                .collect();
            let slices = if img.labels.is_empty() {
                vec![]
            } else {
                Plane::ALL
                    .iter()
                    .map(|&pl| picture(pl.name(), pl.caption(&img.grid), phase_slice(img, pl)))
                    .collect()
            };
            Body::PhaseImage {
                dims: img.grid.dims,
                spacing: img.grid.spacing,
                phases,
                slices,
            }
        }
        Artifact::Field(f) => {
            let (quantity, value) = magnitude(f);
            let n = f.grid.voxel_count();
            let (mut lo, mut hi, mut sum, mut count) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0);
            for i in 0..n {
                let v = value(i);
                if v.is_finite() {
                    lo = lo.min(v);
                    hi = hi.max(v);
                    sum += v;
                    count += 1;
                }
            }
            // The colour scale ends at the 99th percentile: stress and velocity fields have
            // a few hot voxels that would otherwise leave the rest of the slice dark.
            let top = if count == 0 {
                hi
            } else {
                let stride = (n / 200_000).max(1);
                let mut sample: Vec<f64> = (0..n)
                    .step_by(stride)
                    .map(&value)
                    .filter(|v| v.is_finite())
                    .collect();
                sample.sort_by(f64::total_cmp);
                let p = crate::numbers::percentile(&sample, 0.99);
                if p > lo {
                    p
                } else {
                    hi
                }
            };
            let slices = if count == 0 {
                vec![]
            } else {
                Plane::ALL
                    .iter()
                    .map(|&pl| {
                        picture(
                            pl.name(),
                            pl.caption(&f.grid),
                            scalar_slice(&f.grid, &value, pl, lo, top),
                        )
                    })
                    .collect()
            };
            Body::Field {
                name: f.name.clone(),
                unit: f.unit.clone(),
                components: f.components,
                convention: f.convention.name().into(),
                quantity,
                dims: f.grid.dims,
                spacing: f.grid.spacing,
                min: if count > 0 { lo } else { f64::NAN },
                max: if count > 0 { hi } else { f64::NAN },
                scale_max: (count > 0).then_some(top),
                mean: sum / count.max(1) as f64,
                slices,
            }
        }
        Artifact::Packing(p) => {
            let renders = if p.bodies.is_empty() {
                vec![]
            } else {
                vec![
                    picture(
                        "top",
                        "top view (looking down z; x rightwards, y upwards)".into(),
                        render_packing(p, View::Top, RENDER_SIZE),
                    ),
                    picture(
                        "side",
                        "side view (looking along y; x rightwards, z upwards)".into(),
                        render_packing(p, View::Side, RENDER_SIZE),
                    ),
                ]
            };
            let diameters: Vec<f64> = p.bodies.iter().map(|b| equivalent_diameter(p, b)).collect();
            let mut layers: Vec<u32> = p.bodies.iter().map(|b| b.layer).collect();
            layers.sort_unstable();
            layers.dedup();
            Body::Packing {
                bodies: p.bodies.len(),
                spheres: p.world_spheres().len(),
                clumps: p
                    .bodies
                    .iter()
                    .any(|b| matches!(b.shape, BodyShape::Clump { .. })),
                layers: layers.len(),
                volume_fraction: p.volume_fraction(),
                domain: p.domain.size(),
                periodic: p.domain.periodic,
                renders,
                sizes: sizes(&diameters),
            }
        }
        Artifact::ClumpLibrary(l) => {
            let d: Vec<f64> = l
                .clumps
                .iter()
                .map(|c| (6.0 * c.volume / std::f64::consts::PI).cbrt())
                .collect();
            Body::ClumpLibrary {
                clumps: l.clumps.len(),
                spheres: l.clumps.iter().map(|c| c.spheres.len()).sum(),
                sizes: sizes(&d),
            }
        }
        Artifact::ContactGraph(g) => Body::ContactGraph {
            contacts: g.contacts.len(),
            bonds: g.bonds.len(),
            bodies: g.positions.len(),
        },
        Artifact::Table(t) => {
            let rows = t.rows();
            // Long tables (convergence histories) keep their first and last rows.
            let keep: Vec<usize> = if rows <= MAX_TABLE_ROWS {
                (0..rows).collect()
            } else {
                let h = MAX_TABLE_ROWS / 2;
                (0..h).chain(rows - h..rows).collect()
            };
            let cols = |keep: &[usize]| -> Vec<Col> {
                t.columns
                    .iter()
                    .map(|c| Col {
                        name: c.name.clone(),
                        unit: c.unit.clone(),
                        values: keep
                            .iter()
                            .map(|&i| match &c.data {
                                ColumnData::F64(v) => serde_json::Number::from_f64(v[i])
                                    .map(serde_json::Value::Number)
                                    .unwrap_or(serde_json::Value::Null),
                                ColumnData::I64(v) => v[i].into(),
                                ColumnData::Str(v) => v[i].clone().into(),
                            })
                            .collect(),
                    })
                    .collect()
            };
            // Histories longer than the shown rows keep a thinned copy for their plot.
            let curve = (t.name.contains("history") && rows > keep.len()).then(|| {
                let stride = rows.div_ceil(MAX_CURVE_ROWS).max(1);
                let mut rows_kept: Vec<usize> = (0..rows).step_by(stride).collect();
                if rows_kept.last() != Some(&(rows - 1)) {
                    rows_kept.push(rows - 1);
                }
                cols(&rows_kept)
            });
            Body::Table {
                name: t.name.clone(),
                rows,
                columns: cols(&keep),
                curve,
            }
        }
        Artifact::Tensor(t) => Body::Tensor {
            name: t.name.clone(),
            unit: t.unit.clone(),
            convention: match t.convention {
                TensorConvention::Plain => "plain",
                TensorConvention::Voigt => "voigt",
                TensorConvention::Mandel => "mandel",
            }
            .into(),
            shape: t.shape.clone(),
            values: t.values.clone(),
        },
        Artifact::Series(s) => Body::Series {
            frames: s.frames.len(),
            times: [
                s.frames.first().map(|f| f.0).unwrap_or(f64::NAN),
                s.frames.last().map(|f| f.0).unwrap_or(f64::NAN),
            ],
            last: s
                .frames
                .last()
                .map(|(_, a)| Box::new(item(&format!("{source}.last"), a, pics))),
        },
        Artifact::Collection(c) => Body::Collection {
            members: c
                .items
                .iter()
                .take(MAX_MEMBERS)
                .map(|(name, a)| item(&format!("{source}.{name}"), a, pics))
                .collect(),
            total: c.items.len(),
        },
    };
    Item {
        source: source.to_string(),
        body,
    }
}

/// The scalar a field's slices show, and its name: the magnitude of a vector, the von Mises
/// equivalent of a stress (Voigt or Mandel in Pa), the Frobenius norm of other symmetric
/// tensors, the value itself for one component.
pub fn magnitude(f: &Field) -> (String, Box<dyn Fn(usize) -> f64 + '_>) {
    let n = f.components.max(1);
    let get = move |i: usize, k: usize| f.data.get(i * n + k);
    let name = f.name.as_str();
    match (f.convention, n) {
        (_, 1) => (name.to_string(), Box::new(move |i| get(i, 0))),
        (ComponentConvention::Vector, _) => (
            format!("{name} magnitude"),
            Box::new(move |i| (0..n).map(|k| get(i, k).powi(2)).sum::<f64>().sqrt()),
        ),
        (ComponentConvention::Voigt | ComponentConvention::Mandel, 6) => {
            // Mandel stores shear components times sqrt 2.
            let sh = if f.convention == ComponentConvention::Mandel {
                0.5
            } else {
                1.0
            };
            if f.unit == "Pa" {
                (
                    format!("von Mises equivalent of {name}"),
                    Box::new(move |i| {
                        let [a, b, c] = [get(i, 0), get(i, 1), get(i, 2)];
                        let s2 = sh * (get(i, 3).powi(2) + get(i, 4).powi(2) + get(i, 5).powi(2));
                        (0.5 * ((a - b).powi(2) + (b - c).powi(2) + (c - a).powi(2)) + 3.0 * s2)
                            .sqrt()
                    }),
                )
            } else {
                (
                    format!("norm of {name}"),
                    Box::new(move |i| {
                        let d = get(i, 0).powi(2) + get(i, 1).powi(2) + get(i, 2).powi(2);
                        let s2 =
                            2.0 * sh * (get(i, 3).powi(2) + get(i, 4).powi(2) + get(i, 5).powi(2));
                        (d + s2).sqrt()
                    }),
                )
            }
        }
        _ => (
            format!("norm of {name}"),
            Box::new(move |i| (0..n).map(|k| get(i, k).powi(2)).sum::<f64>().sqrt()),
        ),
    }
}

/// Diameter of the sphere of the body's volume.
fn equivalent_diameter(p: &Packing, b: &grainpipe_core::model::Body) -> f64 {
    match b.shape {
        BodyShape::Sphere { radius } => 2.0 * radius,
        BodyShape::Clump { .. } => (6.0 * p.body_volume(b) / std::f64::consts::PI).cbrt(),
    }
}

/// Histogram (up to 24 bins) and characteristic diameters of a sample of diameters.
pub fn sizes(d: &[f64]) -> Option<Sizes> {
    let mut v: Vec<f64> = d
        .iter()
        .copied()
        .filter(|x| x.is_finite() && *x > 0.0)
        .collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let (lo, hi) = (v[0], v[v.len() - 1]);
    let bins = ((v.len() as f64).sqrt().ceil() as usize).clamp(1, 24);
    let (lo, hi) = if hi > lo {
        (lo, hi)
    } else {
        (0.95 * lo, 1.05 * hi)
    };
    let edges: Vec<f64> = (0..=bins)
        .map(|k| lo + (hi - lo) * k as f64 / bins as f64)
        .collect();
    let mut counts = vec![0u64; bins];
    let mut vol = vec![0.0; bins];
    for &x in &v {
        let k = (((x - lo) / (hi - lo) * bins as f64) as usize).min(bins - 1);
        counts[k] += 1;
        vol[k] += x.powi(3);
    }
    let total: f64 = vol.iter().sum();
    let mut acc = 0.0;
    let cumulative_volume = vol
        .iter()
        .map(|x| {
            acc += x;
            acc / total
        })
        .collect();
    let by_volume = |q: f64| {
        // Smallest diameter below which a fraction q of the volume lies.
        let mut acc = 0.0;
        for &x in &v {
            acc += x.powi(3);
            if acc >= q * total {
                return x;
            }
        }
        v[v.len() - 1]
    };
    let pq = |q: f64| crate::numbers::percentile(&v, q);
    Some(Sizes {
        count: v.len(),
        edges,
        counts,
        cumulative_volume,
        mean: v.iter().sum::<f64>() / v.len() as f64,
        d_number: [pq(0.1), pq(0.5), pq(0.9)],
        d_volume: [by_volume(0.1), by_volume(0.5), by_volume(0.9)],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use grainpipe_core::model::{FieldData, Grid};

    /// A tensor with components not computed (NaN) survives the report data's JSON: the
    /// report of a permeameter or of a subset of load directions is written.
    #[test]
    fn nan_components_of_a_tensor_round_trip_through_json() {
        let body = Body::Tensor {
            name: "permeability".into(),
            unit: "m^2".into(),
            convention: "plain".into(),
            shape: vec![3],
            values: vec![1.5e-11, f64::NAN, 0.0],
        };
        let text = serde_json::to_string(&body).unwrap();
        assert!(text.contains("null"), "{text}");
        let Body::Tensor { values, .. } = serde_json::from_str(&text).unwrap() else {
            panic!("not a tensor")
        };
        assert_eq!(values[0], 1.5e-11);
        assert!(values[1].is_nan());
        assert_eq!(values[2], 0.0);
    }

    #[test]
    fn von_mises_of_uniaxial_and_shear_stress() {
        let grid = Grid {
            dims: [2, 1, 1],
            spacing: [1.0; 3],
            origin: [0.0; 3],
            periodic: [true; 3],
        };
        // Voxel 0: uniaxial 10 Pa -> 10; voxel 1: pure shear tau = 3 -> sqrt(3) * 3.
        let data = vec![10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0];
        let f = Field {
            grid,
            name: "stress".into(),
            unit: "Pa".into(),
            components: 6,
            convention: ComponentConvention::Voigt,
            data: FieldData::F64(data),
        };
        let (q, v) = magnitude(&f);
        assert!(q.contains("von Mises"));
        assert!((v(0) - 10.0).abs() < 1e-12);
        assert!((v(1) - 3.0 * 3f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn characteristic_diameters() {
        // 1 to 100: by number the median is 50.5; by volume (x^3 weights) D50 is where
        // sum_{k<=d} k^3 = (d(d+1)/2)^2 reaches half of (5050)^2: 84*85/2 = 3570 < 3570.9 <=
        // 85*86/2, so d = 85.
        let d: Vec<f64> = (1..=100).map(|k| k as f64).collect();
        let s = sizes(&d).unwrap();
        assert_eq!(s.d_number[1], 50.5);
        assert_eq!(s.d_volume[1], 85.0);
        assert_eq!(s.counts.iter().sum::<u64>(), 100);
        assert!((s.cumulative_volume.last().unwrap() - 1.0).abs() < 1e-12);
    }
}
