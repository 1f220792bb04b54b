//! Time of the mesh exporters on a 140^3 phase image (a ball of label 1 in label 0, all
//! phases meshed: 2.74 M hexahedra, 2.86 M points), and the file sizes; the interface
//! surfaces (`mesh: surface`) of the same image.
//!
//! `cargo run --release -p grainpipe-formats --example mesh_bench [-- N]`

use grainpipe_core::serde_json::json;
use grainpipe_core::*;
use grainpipe_formats::mesh::{
    AbaqusExporter, GmshExporter, LegacyVtkExporter, VtuExporter, XdmfExporter,
};
use std::time::Instant;

fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(140);
    let c = n as f64 / 2.0;
    let mut labels = Vec::with_capacity(n * n * n);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let d2: f64 = [x, y, z]
                    .iter()
                    .map(|&i| (i as f64 + 0.5 - c).powi(2))
                    .sum();
                labels.push(u8::from(d2 < (0.4 * n as f64).powi(2)));
            }
        }
    }
    let img = Artifact::PhaseImage(PhaseImage {
        grid: Grid {
            dims: [n; 3],
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [true; 3],
        },
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
        ],
    });
    let dir = std::env::temp_dir().join(format!("grainpipe_mesh_bench_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let prov = Provenance::default();
    let cases: Vec<(&str, Box<dyn Exporter>, serde_json::Value)> = vec![
        ("appended.vtu", Box::new(VtuExporter), json!({})),
        (
            "appended_z1.vtu",
            Box::new(VtuExporter),
            json!({"compression": 1}),
        ),
        (
            "binary.vtu",
            Box::new(VtuExporter),
            json!({"encoding": "binary"}),
        ),
        (
            "grain.vtu",
            Box::new(VtuExporter),
            json!({"phases": ["grain"]}),
        ),
        ("binary.vtk", Box::new(LegacyVtkExporter), json!({})),
        ("hex.xdmf", Box::new(XdmfExporter), json!({})),
        ("m.inp", Box::new(AbaqusExporter), json!({})),
        ("m.msh", Box::new(GmshExporter), json!({})),
        (
            "surface.vtu",
            Box::new(VtuExporter),
            json!({"mesh": "surface"}),
        ),
        (
            "surface_z1.vtu",
            Box::new(VtuExporter),
            json!({"mesh": "surface", "compression": 1}),
        ),
        (
            "surface_s10.vtu",
            Box::new(VtuExporter),
            json!({"mesh": "surface", "smooth": 10}),
        ),
        (
            "surface_s10_d25.vtu",
            Box::new(VtuExporter),
            json!({"mesh": "surface", "smooth": 10, "decimate": 0.25}),
        ),
        (
            "surface.msh",
            Box::new(GmshExporter),
            json!({"mesh": "surface"}),
        ),
    ];
    println!("{n}^3 image, all phases unless named");
    for (name, e, opts) in cases {
        let mut o = e.default_options();
        for (k, v) in opts.as_object().unwrap() {
            o.insert(k.clone(), v.clone());
        }
        let path = dir.join(name);
        let t = Instant::now();
        e.write(&img, &path, &prov, &o).unwrap();
        let secs = t.elapsed().as_secs_f64();
        let mut bytes = std::fs::metadata(&path).unwrap().len();
        if name.ends_with(".xdmf") {
            bytes += std::fs::metadata(path.with_extension("h5")).unwrap().len();
        }
        println!("{name:>16}: {secs:6.2} s  {:8.1} MB", bytes as f64 / 1e6);
    }
    let (m, names) =
        grainpipe_formats::mesh::image_surface(&img, &VtuExporter.default_options()).unwrap();
    println!(
        "surface: {} triangles ({:.3} per voxel), {} points, interfaces {names:?}",
        m.triangles.len(),
        m.triangles.len() as f64 / (n * n * n) as f64,
        m.points.len()
    );
    // Triangles per voxel of denser images (what preflight's estimate must cover): balls of
    // radius 6 voxels on a 14-voxel lattice, each with a binder shell of 2 voxels, and the
    // worst case, independent random labels 0..=2.
    let dense = |f: &dyn Fn(usize, usize, usize) -> u8, n: usize| {
        let mut l = Vec::with_capacity(n * n * n);
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    l.push(f(x, y, z));
                }
            }
        }
        let m = grainpipe_formats::mesh::surface::interfaces(
            [n; 3],
            [0.0; 3],
            [1e-6; 3],
            &l,
            |_, _| true,
        )
        .unwrap();
        m.triangles.len() as f64 / (n * n * n) as f64
    };
    let shells = |x: usize, y: usize, z: usize| {
        let d2: f64 = [x, y, z]
            .iter()
            .map(|&i| ((i % 14) as f64 + 0.5 - 7.0).powi(2))
            .sum();
        if d2 < 36.0 {
            1
        } else if d2 < 64.0 {
            2
        } else {
            0
        }
    };
    let random = |x: usize, y: usize, z: usize| {
        let h = ((x * 73856093) ^ (y * 19349663) ^ (z * 83492791)) as u64;
        (h.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 61) as u8 % 3
    };
    println!(
        "triangles per voxel: balls with binder shells {:.3}, random three-phase labels {:.3}",
        dense(&shells, n),
        dense(&random, 60)
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
