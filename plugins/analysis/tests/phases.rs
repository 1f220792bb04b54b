//! `analysis.phases` through pipelines: an RSA packing voxelized and analysed (fractions,
//! surfaces and components against the packing's analytic values), a three-layer image
//! imported from a raw file (every number known by construction), a periodic image, the
//! `labels` parameter and its preflight check.

use grainpipe_analysis::phases::analyse;
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::testing::run_yaml;
use grainpipe_core::*;
use std::f64::consts::PI;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_geometry::register(&mut r);
    grainpipe_analysis::register(&mut r);
    r
}

#[test]
fn stages_describe_themselves_consistently() {
    registry().check_consistency().unwrap();
}

/// Row of `label` in the `phases` table.
fn row(t: &Table, label: i64) -> usize {
    match &t.column("label").unwrap().data {
        ColumnData::I64(v) => v.iter().position(|&l| l == label).unwrap(),
        _ => panic!("label column is not integer"),
    }
}

fn f(t: &Table, col: &str, label: i64) -> f64 {
    let r = row(t, label);
    match &t.column(col).unwrap_or_else(|| panic!("no {col}")).data {
        ColumnData::F64(v) => v[r],
        ColumnData::I64(v) => v[r] as f64,
        ColumnData::Str(_) => panic!("{col} is text"),
    }
}

#[test]
fn rsa_packing_voxelized_and_analysed_matches_the_packing() {
    // ~36 spheres of R = 20 um (10 voxels) at 15 % in a periodic 200 um box, 2 um voxels.
    let yaml = "name: t\nseed: 5\nstages:\n\
        - id: pack\n  use: packing.rsa\n  with: { size: [200 um, 200 um, 200 um], radius: { kind: fixed, value: 20 um }, volume_fraction: 0.15 }\n\
        - id: vox\n  use: voxelize.packing\n  in: { packing: pack.packing }\n  with: { voxel_size: 2 um }\n\
        - id: ph\n  use: analysis.phases\n  in: { image: vox.image }\n";
    let res = run_yaml(&registry(), yaml).unwrap_or_else(|e| panic!("{e}"));
    let packing = res.artifact("pack.packing").as_packing().unwrap();
    let t = res.table("ph.phases");
    assert_eq!(t.rows(), 2);
    let n = packing.bodies.len();
    // Volume fraction: the voxel count, identical to voxelize's own report, and within
    // 1 % of the analytic fraction at 20 voxels per diameter.
    let phi = f(t, "volume_fraction", 1);
    assert_eq!(phi, res.value("vox.report", "image_fraction"));
    assert!((phi / packing.volume_fraction() - 1.0).abs() < 0.01);
    assert!((phi + f(t, "volume_fraction", 0) - 1.0).abs() < 1e-15);
    // Specific surface: the spheres do not overlap, so the interface is sum 4 pi r^2 / V
    // (less the few voxel faces where nearly touching spheres merge). R = 10 voxels:
    // measured 0.14 % (Crofton) and 0.25 % (faces / 1.5) off; 1.5 % allows for the
    // digitisation error of small spheres, which grows like 1/R.
    let exact: f64 = 4.0 * PI * 20e-6f64.powi(2) * n as f64 / 200e-6f64.powi(3);
    let s = f(t, "specific_surface", 1);
    assert!((s / exact - 1.0).abs() < 0.015, "{s} vs {exact}");
    assert_eq!(s, f(t, "specific_surface", 0));
    let faces = f(t, "specific_surface_faces", 1);
    assert!(
        (faces / (1.5 * exact) - 1.0).abs() < 0.015,
        "{faces} vs 1.5 x {exact}"
    );
    // Components: one per sphere, except spheres closer than a voxel diagonal may merge in
    // the image. Bounds from the packing: clusters of spheres with gaps < sqrt(3) h .. n.
    let spheres = packing.world_spheres();
    let mut parent: Vec<usize> = (0..n).collect();
    fn root(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            i = p[i];
        }
        i
    }
    for i in 0..n {
        for j in 0..i {
            let d: f64 = (0..3)
                .map(|a| {
                    let x = (spheres[i].center[a] - spheres[j].center[a]).abs();
                    x.min(200e-6 - x).powi(2)
                })
                .sum::<f64>()
                .sqrt();
            if d - 40e-6 < 3f64.sqrt() * 2e-6 {
                let (a, b) = (root(&mut parent, i), root(&mut parent, j));
                parent[a] = b;
            }
        }
    }
    let clusters = (0..n).filter(|&i| root(&mut parent, i) == i).count();
    let c = f(t, "components", 1) as usize;
    assert!(clusters <= c && c <= n, "{c} components, {clusters}..{n}");
    for a in ["x", "y", "z"] {
        assert_eq!(f(t, &format!("percolates_{a}"), 1), 0.0);
        assert_eq!(f(t, &format!("percolates_{a}"), 0), 1.0);
    }
    // The pore space is one piece that winds around the periodic box.
    assert_eq!(f(t, "components", 0), 1.0);
    assert_eq!(f(t, "largest_component_fraction", 0), 1.0);
    assert_eq!(f(t, "percolating_fraction", 0), 1.0);
    assert_eq!(f(t, "percolating_fraction", 1), 0.0);
}

/// Three layers along z of a 10 x 10 x 12 raw image: z < 4 label 0, 4..8 label 1, 8..12
/// label 2; 1.5 um voxels, non-periodic.
fn layers_pipeline(dir: &std::path::Path, with: &str) -> String {
    let p = dir.join("layers.raw");
    let labels: Vec<u8> = (0..1200).map(|i| (i / 100 / 4) as u8).collect();
    std::fs::write(&p, labels).unwrap();
    format!(
        "name: t\nstages:\n  - id: img\n    use: import.raw\n    with: {{ path: {}, dims: [10, 10, 12], spacing: 1.5 um }}\n  - id: ph\n    use: analysis.phases\n    in: {{ image: img.image }}\n    with: {with}\n",
        serde_json::to_string(&p.display().to_string()).unwrap()
    )
}

#[test]
fn layered_image_numbers_are_known_by_construction() {
    let d = tempfile::tempdir().unwrap();
    let res = run_yaml(&registry(), &layers_pipeline(d.path(), "{}")).unwrap();
    let t = res.table("ph.phases");
    let h = 1.5e-6;
    let names = match &t.column("phase").unwrap().data {
        ColumnData::Str(v) => v.clone(),
        _ => panic!(),
    };
    assert_eq!(names, ["pore", "phase1", "phase2"]);
    for l in 0..3 {
        assert_eq!(f(t, "volume_fraction", l), 1.0 / 3.0);
        assert_eq!(f(t, "voxels", l), 400.0);
        assert_eq!(f(t, "components", l), 1.0);
        assert_eq!(f(t, "largest_component_fraction", l), 1.0);
        // Every layer spans x and y (touches both faces), none spans z.
        assert_eq!(f(t, "percolates_x", l), 1.0);
        assert_eq!(f(t, "percolates_y", l), 1.0);
        assert_eq!(f(t, "percolates_z", l), 0.0);
    }
    // Interfaces are planes of 10 x 10 faces: the middle layer has two, the outer ones one
    // (the image border is not an interface). Face count exact: A / V = 1 / (12 h).
    let unit = 1.0 / (12.0 * h);
    for (l, planes) in [(0, 1.0), (1, 2.0), (2, 1.0)] {
        let faces = f(t, "specific_surface_faces", l);
        assert!(
            (faces / (planes * unit) - 1.0).abs() < 1e-12,
            "{l}: {faces}"
        );
    }
    // `labels` picks rows in the given order; an absent label gives an empty row.
    let res = run_yaml(
        &registry(),
        &layers_pipeline(d.path(), "{ labels: [2, 7] }"),
    )
    .unwrap();
    let t = res.table("ph.phases");
    assert_eq!(t.rows(), 2);
    assert_eq!(row(t, 2), 0);
    assert_eq!(f(t, "voxels", 7), 0.0);
    assert_eq!(f(t, "components", 7), 0.0);
    assert_eq!(f(t, "specific_surface", 7), 0.0);
}

#[test]
fn repeated_labels_are_refused_before_running() {
    let d = tempfile::tempdir().unwrap();
    let Err(e) = run_yaml(
        &registry(),
        &layers_pipeline(d.path(), "{ labels: [1, 2, 1] }"),
    ) else {
        panic!("ran")
    };
    assert_eq!(e.exit_code(), 2, "{e}");
    assert!(e.message.contains("label 1 is listed twice"), "{e}");
    assert_eq!(e.loc.map(|l| l.line), Some(9), "{e}");
}

#[test]
fn periodic_and_non_periodic_grids_of_the_same_image() {
    // 12 x 10 x 8 voxels; label 1: a slab z in [2, 5) (spans x and y); label 2: a bar along
    // y at x in [3, 6), z in [5, 7) (spans y only); label 3: a 2 x 2 x 2 cube through the
    // corner of the box (x in {11, 0}, y in {9, 0}, z in {7, 0}); the rest label 0.
    let d = [12usize, 10, 8];
    let mut labels = vec![0u8; d.iter().product()];
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                let i = x + d[0] * (y + d[1] * z);
                labels[i] = if (2..5).contains(&z) {
                    1
                } else if (3..6).contains(&x) && (5..7).contains(&z) {
                    2
                } else if [11, 0].contains(&x) && [9, 0].contains(&y) && [7, 0].contains(&z) {
                    3
                } else {
                    0
                };
            }
        }
    }
    let image = |periodic: [bool; 3]| PhaseImage {
        grid: Grid {
            dims: d,
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic,
        },
        labels: labels.clone(),
        phases: vec![],
    };
    let ctx = RunContext::new(0, &SilentReporter);
    let per = analyse(&image([true; 3]), &[], &ctx).unwrap();
    let open = analyse(&image([false; 3]), &[], &ctx).unwrap();
    // Label 3: one cube through the corner when periodic, 8 single voxels otherwise.
    assert_eq!(f(&per, "components", 3), 1.0);
    assert_eq!(f(&open, "components", 3), 8.0);
    assert_eq!(f(&open, "largest_component_fraction", 3), 1.0 / 8.0);
    // Percolation flags (x, y, z) per label.
    let flags = |t: &Table, l| ["x", "y", "z"].map(|a| f(t, &format!("percolates_{a}"), l));
    assert_eq!(flags(&per, 1), [1.0, 1.0, 0.0]);
    assert_eq!(flags(&open, 1), [1.0, 1.0, 0.0]);
    assert_eq!(flags(&per, 2), [0.0, 1.0, 0.0]);
    assert_eq!(flags(&open, 2), [0.0, 1.0, 0.0]);
    assert_eq!(flags(&per, 3), [0.0; 3]);
    // Label 0: periodic it is one piece (z < 2 joins z >= 5 through the z face), a layer
    // that winds along x and y but is stopped by the slab along z; open it is two pieces
    // (below and above the slab), each spanning x and y, not z.
    assert_eq!(f(&per, "components", 0), 1.0);
    assert_eq!(flags(&per, 0), [1.0, 1.0, 0.0]);
    assert_eq!(f(&open, "components", 0), 2.0);
    assert_eq!(flags(&open, 0), [1.0, 1.0, 0.0]);
    // Volume fractions by count: 360, 60 and 8 voxels of 960.
    for (l, v) in [(1, 360.0), (2, 60.0), (3, 8.0)] {
        assert_eq!(f(&per, "volume_fraction", l), v / 960.0);
    }
    // The slab's faces: two planes of 12 x 10 (against label 0 below, labels 0 and 2
    // above), none along x and y where it wraps: 240 um^2 over 960 um^3.
    let faces = f(&per, "specific_surface_faces", 1);
    assert!((faces / (240.0 / 960e-6) - 1.0).abs() < 1e-12, "{faces}");
}

#[test]
fn csv_packing_imported_voxelized_and_analysed_with_the_grid_known_at_preflight() {
    // Two spheres of R = 20 um, 0.5 R apart (centres 90 um apart), from a CSV in um; and
    // the same pair overlapping by 10 um (centres 30 um apart) in a second file.
    let d = tempfile::tempdir().unwrap();
    let yaml = |name: &str, text: &str| {
        let p = d.path().join(name);
        std::fs::write(&p, text).unwrap();
        format!(
            "name: t\nstages:\n  - id: imp\n    use: import.packing\n    with: {{ path: {}, unit: um, box: [200 um, 100 um, 100 um], periodic: [false, true, true] }}\n  - id: vox\n    use: voxelize.packing\n    in: {{ packing: imp.packing }}\n    with: {{ voxels_per_diameter: 20 }}\n  - id: ph\n    use: analysis.phases\n    in: {{ image: vox.image }}\n",
            serde_json::to_string(&p.display().to_string()).unwrap()
        )
    };
    let apart = yaml(
        "apart.csv",
        "x [um],y [um],z [um],r [um]\n55,50,50,20\n145,50,50,20\n",
    );
    // Equal spheres fix the mean diameter: the voxelized grid (2 um voxels) is known before
    // anything runs, as the binder stages need.
    let doc =
        grainpipe_core::pipeline::PipelineDoc::parse(std::path::Path::new("t.yaml"), apart.clone())
            .unwrap();
    let plan = grainpipe_core::engine::plan(&doc, &registry(), &Default::default()).unwrap();
    let (i, _) = doc.step("vox").unwrap();
    let grid = plan.steps[i].as_ref().unwrap().preflight.outputs["image"]
        .grid
        .clone()
        .expect("grid announced");
    assert_eq!(grid.dims, [100, 50, 50]);
    assert_eq!(grid.periodic, [false, true, true]);
    let res = run_yaml(&registry(), &apart).unwrap();
    let t = res.table("ph.phases");
    assert_eq!(f(t, "components", 1), 2.0);
    // Volume: the voxel count, the same as voxelize's report, and within 1 % of
    // 2 x 4/3 pi R^3 over the box at 20 voxels per diameter (voxelize's stated accuracy is
    // 0.5 % on random packings; these centres sit on symmetric lattice positions).
    let phi = f(t, "volume_fraction", 1);
    assert_eq!(phi, res.value("vox.report", "image_fraction"));
    let analytic = 2.0 * 4.0 / 3.0 * PI * 20e-6f64.powi(3) / (200e-6 * 100e-6 * 100e-6);
    assert!((phi / analytic - 1.0).abs() < 0.01, "{phi} vs {analytic}");
    let joined = yaml(
        "joined.csv",
        "x [um],y [um],z [um],r [um]\n85,50,50,20\n115,50,50,20\n",
    );
    let res = run_yaml(&registry(), &joined).unwrap();
    assert_eq!(f(res.table("ph.phases"), "components", 1), 1.0);
}

#[test]
fn a_two_dimensional_image_percolates_in_plane_only_where_it_spans() {
    // 6 x 4 x 1: label 1 is the column x = 2 (spans y), label 2 the single voxel (4, 1).
    let d = [6usize, 4, 1];
    let labels: Vec<u8> = (0..24)
        .map(|i| match (i % 6, i / 6) {
            (2, _) => 1,
            (4, 1) => 2,
            _ => 0,
        })
        .collect();
    let image = PhaseImage {
        grid: Grid {
            dims: d,
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
        labels,
        phases: vec![],
    };
    let t = analyse(&image, &[], &RunContext::new(0, &SilentReporter)).unwrap();
    // Every component spans the one-voxel z axis, which percolating_fraction ignores.
    assert_eq!(f(&t, "percolates_z", 2), 1.0);
    assert_eq!(f(&t, "percolating_fraction", 2), 0.0);
    assert_eq!(f(&t, "percolates_y", 1), 1.0);
    assert_eq!(f(&t, "percolating_fraction", 1), 1.0);
    // Perimeter per area of the column: its two long sides, 2 x 4 um over 24 um^2
    // (the image border is not an interface).
    let faces = f(&t, "specific_surface_faces", 1);
    assert!((faces / (8e-6 / 24e-12) - 1.0).abs() < 1e-12, "{faces}");
}
