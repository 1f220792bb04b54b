//! Writes one file of every format with known contents into the directory given as argv[1],
//! plus `manifest.json` with the numbers a reader must find (used by tests/interop/).
//!
//! cargo run --release -p grainpipe-formats --example write_samples -- /tmp/samples

use grainpipe_core::*;
use grainpipe_formats::*;
use serde_json::json;
use std::path::Path;

/// Grid shared by the image and the field: anisotropic spacing and a non-zero origin so that a
/// swapped axis or a centre/corner confusion shows up.
fn grid() -> Grid {
    Grid {
        dims: [12, 10, 8],
        spacing: [10e-6, 20e-6, 30e-6],
        origin: [1e-3, -2e-3, 0.5e-3],
        periodic: [true, false, false],
    }
}

/// Label 2 for the slab z index < 2 (exactly 1/4 of the voxels), label 1 for voxels whose
/// centre lies within 2.5 voxels of index point (7, 5, 5) (off-centre along x), 0 elsewhere.
fn phase_image() -> PhaseImage {
    let g = grid();
    let [nx, ny, nz] = g.dims;
    let mut labels = vec![0u8; nx * ny * nz];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let d2 = [
                    x as f64 + 0.5 - 7.0,
                    y as f64 + 0.5 - 5.0,
                    z as f64 + 0.5 - 5.0,
                ]
                .iter()
                .map(|d| d * d)
                .sum::<f64>();
                labels[g.index(x, y, z)] = if z < 2 {
                    2
                } else if d2 <= 2.5 * 2.5 {
                    1
                } else {
                    0
                };
            }
        }
    }
    PhaseImage {
        grid: g,
        labels,
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 1,
                name: "grain".into(),
            },
            Phase {
                id: 2,
                name: "base plate".into(),
            },
        ],
    }
}

/// value(x, y, z, k) = x + 100 y + 10000 z + 0.25 k: every index is recoverable from a value.
fn field_value(x: usize, y: usize, z: usize, k: usize) -> f64 {
    x as f64 + 100.0 * y as f64 + 10000.0 * z as f64 + 0.25 * k as f64
}

fn field() -> Field {
    let g = grid();
    let [nx, ny, nz] = g.dims;
    let mut data = Vec::with_capacity(3 * nx * ny * nz);
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                for k in 0..3 {
                    data.push(field_value(x, y, z, k));
                }
            }
        }
    }
    Field {
        grid: g,
        name: "velocity".into(),
        unit: "m/s".into(),
        components: 3,
        convention: ComponentConvention::Vector,
        data: FieldData::F64(data),
    }
}

fn packing(shift: f64) -> Packing {
    let mut p = Packing::new(Domain::boxed([0.0; 3], [1e-3; 3], [true, true, false]));
    p.bodies
        .push(Body::sphere([2e-4 + shift, 2e-4, 2e-4], 1e-4));
    p.bodies
        .push(Body::sphere([6e-4 + shift, 2e-4, 2e-4], 1.5e-4));
    let mut b = Body::sphere([5e-4 + shift, 6e-4, 5e-4], 0.0);
    b.shape = BodyShape::Clump { index: 0 };
    // 90 degrees about z: the clump's +x offset points along +y in the world
    let h = std::f64::consts::FRAC_1_SQRT_2;
    b.orientation = [h, 0.0, 0.0, h];
    b.layer = 1;
    b.frozen = true;
    p.bodies.push(b);
    p.library = Some(ClumpLibrary {
        clumps: vec![Clump {
            spheres: vec![
                ClumpSphere {
                    offset: [-5e-5, 0.0, 0.0],
                    radius: 8e-5,
                },
                ClumpSphere {
                    offset: [5e-5, 0.0, 0.0],
                    radius: 8e-5,
                },
            ],
            volume: 3.6e-12,
            bounding_radius: 1.3e-4,
            principal_inertia: [1.0e-20, 2.0e-20, 2.0e-20],
            principal_axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            source: "two-sphere dumbbell".into(),
        }],
        source: "write_samples".into(),
    });
    p.attributes.insert(
        "peak_temperature".into(),
        BodyAttribute {
            unit: "K".into(),
            values: vec![300.0, 450.5, 1200.25],
        },
    );
    p
}

fn graph() -> ContactGraph {
    ContactGraph {
        contacts: vec![
            Contact {
                i: 0,
                j: 1,
                gap: -1e-7,
            },
            Contact {
                i: 1,
                j: 2,
                gap: 2e-7,
            },
        ],
        faces: [vec![0], vec![3], vec![], vec![], vec![0, 1], vec![]],
        bonds: vec![[0, 1], [2, 3]],
        bond_attributes: Default::default(),
        positions: vec![
            [0.0, 0.0, 0.0],
            [1e-4, 0.0, 0.0],
            [1e-4, 1e-4, 0.0],
            [2e-4, 1e-4, 5e-5],
        ],
        radii: vec![5e-5, 5e-5, 4e-5, 6e-5],
    }
}

fn table() -> Table {
    Table::new("sinter history")
        .with_f64("time", "s", vec![0.0, 0.5, 1.25])
        .with_i64("step", "", vec![0, 10, 25])
        .with_f64("neck radius", "m", vec![0.0, 1.5e-6, 3.25e-6])
        .with_str(
            "note",
            vec!["start".into(), "a, b".into(), "end \"x\"".into()],
        )
}

/// Isotropic stiffness in Mandel notation: C11 = lambda + 2 mu, C12 = lambda, C44 = 2 mu.
fn tensor() -> Tensor {
    let (lambda, mu) = (50e9, 30e9);
    let mut v = vec![0.0; 36];
    for i in 0..3 {
        for j in 0..3 {
            v[6 * i + j] = if i == j { lambda + 2.0 * mu } else { lambda };
        }
        v[6 * (i + 3) + i + 3] = 2.0 * mu;
    }
    Tensor {
        name: "stiffness".into(),
        unit: "Pa".into(),
        shape: vec![6, 6],
        values: v,
        convention: TensorConvention::Mandel,
    }
}

fn main() -> Result<(), String> {
    let dir = std::env::args()
        .nth(1)
        .ok_or("usage: write_samples <output directory>")?;
    let dir = Path::new(&dir);
    std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
    let mut prov = Provenance::default();
    prov.entries
        .insert("grainpipe_version".into(), VERSION.into());
    prov.entries.insert("seed".into(), "42".into());
    prov.entries
        .insert("pipeline".into(), "name: samples\nseed: 42\n".into());

    let mut reg = Registry::new();
    register(&mut reg);
    let write = |a: &Artifact, name: &str| -> Result<(), String> {
        let path = dir.join(name);
        let e = reg
            .exporter_for(None, &path, a.kind())
            .ok_or_else(|| format!("no exporter for {name}"))?;
        if !e.accepts(a.kind()) {
            return Err(format!("{} does not take {}", e.name(), a.kind()));
        }
        e.write_defaults(a, &path, &prov)
    };

    let img = phase_image();
    let fld = field();
    let series = Series {
        frames: (0..3)
            .map(|k| (0.5 * k as f64, Artifact::Packing(packing(1e-4 * k as f64))))
            .collect(),
    };
    let arts = [
        (Artifact::PhaseImage(img.clone()), "phase"),
        (Artifact::Field(fld.clone()), "field"),
    ];
    for (a, stem) in &arts {
        for ext in ["vti", "vtkhdf", "h5", "nc"] {
            write(a, &format!("{stem}.{ext}"))?;
        }
    }
    let pk = packing(0.0);
    write(&Artifact::Packing(pk.clone()), "packing.vtp")?;
    write(&Artifact::Packing(pk.clone()), "packing.h5")?;
    let gr = graph();
    for ext in ["vtp", "h5", "csv", "json"] {
        write(&Artifact::ContactGraph(gr.clone()), &format!("graph.{ext}"))?;
    }
    for ext in ["h5", "csv", "json"] {
        write(&Artifact::Table(table()), &format!("table.{ext}"))?;
        write(&Artifact::Tensor(tensor()), &format!("tensor.{ext}"))?;
    }
    write(&Artifact::Series(series.clone()), "series.pvd")?;
    write(&Artifact::Series(series.clone()), "series.h5")?;

    // Expected numbers, computed here from the artifacts (not from the files).
    let fractions: serde_json::Map<String, serde_json::Value> = img
        .phases
        .iter()
        .map(|p| (p.id.to_string(), json!(img.fraction(p.id))))
        .collect();
    let spheres = pk.world_spheres();
    let t = table();
    let manifest = json!({
        "grid": {"dims": img.grid.dims, "spacing": img.grid.spacing, "origin": img.grid.origin,
                 "periodic": img.grid.periodic},
        "phase": {
            "name": "phase",
            "fractions": fractions,
            "phases": img.phases.iter().map(|p| json!({"id": p.id, "name": p.name})).collect::<Vec<_>>(),
            "slab_fraction_analytic": 0.25,
            "labels_sum": img.labels.iter().map(|&l| l as u64).sum::<u64>(),
        },
        "field": {
            "name": fld.name, "unit": fld.unit, "components": 3,
            "formula": "x + 100 y + 10000 z + 0.25 k",
        },
        "packing": {
            "n_points": spheres.len(),
            "centers": spheres.iter().map(|s| s.center).collect::<Vec<_>>(),
            "radius": spheres.iter().map(|s| s.radius).collect::<Vec<_>>(),
            "body_id": spheres.iter().map(|s| s.body).collect::<Vec<_>>(),
            "layer": spheres.iter().map(|s| pk.bodies[s.body].layer).collect::<Vec<_>>(),
            "peak_temperature": spheres.iter().map(|s| pk.attributes["peak_temperature"].values[s.body]).collect::<Vec<_>>(),
            "n_bodies": pk.bodies.len(),
        },
        "graph": {
            "n_points": gr.positions.len(),
            "lines": [[0, 1], [1, 2], [2, 3]],
            "gap": [-1e-7, 2e-7, null],
            "bonded": [1, 0, 1],
            "faces": {"xmin": [0], "xmax": [3], "zmin": [0, 1]},
        },
        "table": {
            "name": t.name,
            "columns": t.columns.iter().map(|c| json!({"name": c.name, "unit": c.unit})).collect::<Vec<_>>(),
            "time": [0.0, 0.5, 1.25], "step": [0, 10, 25], "neck radius": [0.0, 1.5e-6, 3.25e-6],
            "note": ["start", "a, b", "end \"x\""],
        },
        "tensor": {"name": "stiffness", "unit": "Pa", "convention": "Mandel", "values": tensor().values,
                   "shape": [6, 6]},
        "series": {"times": [0.0, 0.5, 1.0], "n_points": spheres.len(), "x_shift_per_frame": 1e-4},
        "provenance": prov.entries,
    });
    let text = serde_json::to_string_pretty(&manifest).map_err(|e| e.to_string())?;
    fsutil::atomic_write_bytes(&dir.join("manifest.json"), text.as_bytes())?;
    println!("wrote samples to {}", dir.display());
    Ok(())
}
