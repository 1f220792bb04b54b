//! STL surfaces: enclosed volume (divergence theorem) against the sphere volume or the
//! phase's volume, watertightness, and the file read back.

use grainpipe_core::*;
use grainpipe_formats::stl::{enclosed_volume, icosphere, phase_surface, read_stl, StlExporter};
use std::collections::HashMap;
use std::f64::consts::PI;

/// Every edge of the surface in exactly two triangles, traversed once in each direction
/// (closed, consistently oriented).
fn assert_watertight(tris: &[[[f64; 3]; 3]]) {
    let key = |p: [f64; 3]| p.map(|x| x.to_bits());
    let mut edges: HashMap<([u64; 3], [u64; 3]), i32> = HashMap::new();
    for t in tris {
        for k in 0..3 {
            *edges.entry((key(t[k]), key(t[(k + 1) % 3]))).or_default() += 1;
        }
    }
    for (&(a, b), &n) in &edges {
        assert_eq!(n, 1, "edge used {n} times in one direction");
        assert_eq!(edges.get(&(b, a)), Some(&1), "edge without its twin");
    }
}

#[test]
fn icosphere_volume_converges_to_the_sphere_at_second_order() {
    let exact = 4.0 / 3.0 * PI;
    let err: Vec<f64> = (0..5)
        .map(|s| 1.0 - enclosed_volume(&icosphere(s)) / exact)
        .collect();
    // Inscribed: always below the sphere; error / 4 per level once h is small (h halves,
    // error ~ h^2; the icosahedron to level 1 step is 3.1).
    assert!(err[0] > 0.0);
    for s in 2..5 {
        assert!(err[s] > 0.0);
        let ratio = err[s - 1] / err[s];
        assert!((ratio - 4.0).abs() < 0.6, "level {s}: ratio {ratio}");
    }
    // Subdivisions 2 (the default, 320 triangles): 3.4 % low; 4: 0.22 % low.
    assert!(err[2] < 0.035, "{err:?}");
    assert!(err[4] < 0.0025, "{err:?}");
    assert_watertight(&icosphere(2));
}

#[test]
fn packing_stl_encloses_the_sphere_volumes() {
    let d = tempfile::tempdir().unwrap();
    let mut p = Packing::new(Domain::boxed([0.0; 3], [1e-3; 3], [false; 3]));
    p.bodies.push(Body::sphere([2e-4, 3e-4, 4e-4], 1e-4));
    p.bodies.push(Body::sphere([7e-4, 6e-4, 5e-4], 5e-5));
    let f = d.path().join("bed.stl");
    StlExporter
        .write_defaults(&Artifact::Packing(p.clone()), &f, &Provenance::default())
        .unwrap();
    let tris = read_stl(&std::fs::read(&f).unwrap()).unwrap();
    assert_eq!(tris.len(), 2 * 320);
    // File in mm; the two spheres are disjoint, so the volumes add.
    let v = enclosed_volume(&tris) * 1e-9;
    let want = p.solid_volume() * enclosed_volume(&icosphere(2)) / (4.0 / 3.0 * PI);
    assert!((v / want - 1.0).abs() < 1e-5, "{v} vs {want}");
}

/// A voxelized ball: the marching-tetrahedra surface is watertight and encloses the
/// voxel count's volume within 2 % (the midpoint surface cuts corners of the staircase
/// and adds nothing outside it).
#[test]
fn image_surface_is_watertight_and_encloses_the_phase_volume() {
    let n = 24usize;
    let h = 2e-6;
    let grid = Grid {
        dims: [n, n, n],
        spacing: [h; 3],
        origin: [1e-3, -2e-4, 0.0],
        periodic: [false; 3],
    };
    let c = (n as f64) / 2.0;
    let r = 9.5;
    let labels: Vec<u8> = (0..n * n * n)
        .map(|i| {
            let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
            let d2 = [x, y, z]
                .map(|a| (a as f64 + 0.5 - c).powi(2))
                .iter()
                .sum::<f64>();
            // phase 2 inside, and a separate 1-voxel speck touching the image face.
            if d2 <= r * r || (x == 0 && y == 0 && z == 0) {
                2
            } else {
                0
            }
        })
        .collect();
    let count = labels.iter().filter(|&&l| l == 2).count() as f64;
    let img = PhaseImage {
        grid,
        labels,
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 2,
                name: "grain".into(),
            },
        ],
    };
    let tris = phase_surface(&img, 2);
    assert_watertight(&tris);
    let v = enclosed_volume(&tris);
    let voxels = count * h * h * h;
    assert!(v < voxels && v / voxels > 0.98, "{v} vs {voxels}");
    // Written with `phase: 2` in um and read back: same volume to f32 precision.
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("grain.stl");
    let mut o = grainpipe_core::registry::ExportOptions::new();
    o.insert("subdivisions".into(), serde_json::json!(2));
    o.insert("phase".into(), serde_json::json!(2));
    o.insert("length_unit".into(), serde_json::json!("um"));
    StlExporter
        .write(
            &Artifact::PhaseImage(img.clone()),
            &f,
            &Provenance::default(),
            &o,
        )
        .unwrap();
    let back = read_stl(&std::fs::read(&f).unwrap()).unwrap();
    assert_eq!(back.len(), tris.len());
    assert!((enclosed_volume(&back) * 1e-18 / v - 1.0).abs() < 1e-4);
    // A phase that is not in the image is an error naming the phases present.
    o.insert("phase".into(), serde_json::json!(7));
    let e = StlExporter
        .write(&Artifact::PhaseImage(img), &f, &Provenance::default(), &o)
        .unwrap_err();
    assert!(e.contains("0 (pore), 2 (grain)"), "{e}");
}

/// Issue 35: an image's STL is written layer by layer (never the whole surface in memory),
/// byte for byte what the collected surface gives; the export's memory estimate is one
/// layer, not the surface.
#[test]
fn image_stl_streams_the_same_bytes_and_estimates_one_layer() {
    let n = 16usize;
    let grid = Grid {
        dims: [n, n, n],
        spacing: [1e-6; 3],
        origin: [0.0; 3],
        periodic: [false; 3],
    };
    let labels: Vec<u8> = (0..n * n * n)
        .map(|i| u8::from((i * 7919) % 5 < 2))
        .collect();
    let img = PhaseImage {
        grid: grid.clone(),
        labels,
        phases: vec![],
    };
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("a.stl");
    let a = Artifact::PhaseImage(img.clone());
    StlExporter
        .write_defaults(&a, &p, &Provenance::default())
        .unwrap();
    let want =
        grainpipe_formats::stl::stl_bytes(&phase_surface(&img, 1), 1e3, "grainpipe  STL").unwrap();
    assert_eq!(std::fs::read(&p).unwrap(), want);
    let meta = ArtifactMeta::on_grid(ArtifactKind::PhaseImage, grid);
    let est = StlExporter.memory_bytes(&meta, &StlExporter.default_options());
    assert!(est < 16 << 20, "{est}");
    // A 333^3 image: one layer of triangles (about 1 GB in memory for the whole surface
    // before), still a few MiB.
    let big = ArtifactMeta::on_grid(
        ArtifactKind::PhaseImage,
        Grid {
            dims: [333; 3],
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
    );
    assert!(StlExporter.memory_bytes(&big, &StlExporter.default_options()) < 128 << 20);
}
