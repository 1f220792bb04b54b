//! DEM inputs (LAMMPS data and molecule files, Yade text) parsed back by small independent
//! parsers, and raw + MetaImage volumes read back through `import.raw`.

use grainpipe_core::registry::ExportOptions;
use grainpipe_core::testing::run_yaml;
use grainpipe_core::*;
use grainpipe_formats::dem::{
    molecule_paths, LammpsDataExporter, LammpsMoleculeExporter, YadeExporter,
};
use grainpipe_formats::raw::RawExporter;
use std::collections::HashMap;
use std::f64::consts::PI;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    r
}

/// Two spheres of radius r, centres d apart: union volume = 2 sphere volumes - the lens
/// (pi (4r + d)(2r - d)^2 / 12).
fn dimer() -> Clump {
    let (r, d) = (1e-5, 1e-5);
    let volume =
        2.0 * 4.0 / 3.0 * PI * r * r * r - PI * (4.0 * r + d) * (2.0 * r - d).powi(2) / 12.0;
    Clump {
        spheres: vec![
            ClumpSphere {
                offset: [-d / 2.0, 0.0, 0.0],
                radius: r,
            },
            ClumpSphere {
                offset: [d / 2.0, 0.0, 0.0],
                radius: r,
            },
        ],
        volume,
        bounding_radius: r + d / 2.0,
        principal_inertia: [1.0; 3],
        principal_axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        source: "dimer".into(),
    }
}

fn sphere_packing() -> Packing {
    let mut p = Packing::new(Domain::boxed(
        [-1e-4, 0.0, 2e-5],
        [3e-4, 2.5e-4, 4.1e-4],
        [false; 3],
    ));
    for k in 0..7 {
        let k = k as f64;
        p.bodies.push(Body::sphere(
            [-9e-5 + 4.7e-5 * k, 1.1e-5 * k + 3e-5, 3.3e-4 - 1.9e-5 * k],
            1.0e-5 + 1.3e-6 * k,
        ));
    }
    p
}

fn clump_packing() -> Packing {
    let mut p = Packing::new(Domain::boxed([0.0; 3], [2e-4; 3], [false; 3]));
    p.library = Some(ClumpLibrary {
        clumps: vec![dimer()],
        source: "test".into(),
    });
    for k in 0..3 {
        let h = 0.3 * k as f64;
        p.bodies.push(Body {
            shape: BodyShape::Clump { index: 0 },
            position: [5e-5 + 4e-5 * k as f64, 1e-4, 1e-4],
            orientation: [h.cos(), 0.0, 0.0, h.sin()],
            layer: 0,
            frozen: false,
        });
    }
    p
}

/// Minimal LAMMPS data reader: box bounds and the Atoms lines.
fn parse_lammps_data(text: &str) -> ([[f64; 2]; 3], Vec<Vec<f64>>, String) {
    let mut bounds = [[f64::NAN; 2]; 3];
    let mut atoms = Vec::new();
    let mut style = String::new();
    let mut in_atoms = false;
    for line in text.lines().skip(1) {
        let t = line.split('#').next().unwrap().trim();
        if line.starts_with("Atoms") {
            in_atoms = true;
            style = line.split('#').nth(1).unwrap().trim().to_string();
            continue;
        }
        if t.is_empty() {
            continue;
        }
        let w: Vec<&str> = t.split_whitespace().collect();
        if w.len() == 4 && w[2].ends_with("lo") {
            let a = ["xlo", "ylo", "zlo"]
                .iter()
                .position(|x| *x == w[2])
                .unwrap();
            bounds[a] = [w[0].parse().unwrap(), w[1].parse().unwrap()];
        } else if in_atoms {
            atoms.push(w.iter().map(|x| x.parse().unwrap()).collect());
        }
    }
    (bounds, atoms, style)
}

#[test]
fn lammps_data_of_spheres_reads_back_exactly() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("bed.data");
    let p = sphere_packing();
    LammpsDataExporter
        .write_defaults(&Artifact::Packing(p.clone()), &f, &Provenance::default())
        .unwrap();
    let (bounds, atoms, style) = parse_lammps_data(&std::fs::read_to_string(&f).unwrap());
    assert_eq!(style, "sphere");
    for (a, bound) in bounds.iter().enumerate() {
        assert_eq!(*bound, [p.domain.min[a], p.domain.max[a]]);
    }
    assert_eq!(atoms.len(), p.bodies.len());
    for (row, b) in atoms.iter().zip(&p.bodies) {
        // id type diameter density x y z
        let BodyShape::Sphere { radius } = b.shape else {
            unreachable!()
        };
        assert_eq!(row[2], 2.0 * radius);
        assert_eq!(row[3], 2650.0);
        assert_eq!(&row[4..7], &b.position);
    }
}

#[test]
fn lammps_data_of_clumps_keeps_bodies_as_molecules_and_mass() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("clumps.data");
    let p = clump_packing();
    let mut o = ExportOptions::new();
    o.insert("density".into(), serde_json::json!(1000.0));
    LammpsDataExporter
        .write(
            &Artifact::Packing(p.clone()),
            &f,
            &Provenance::default(),
            &o,
        )
        .unwrap();
    let (_, atoms, style) = parse_lammps_data(&std::fs::read_to_string(&f).unwrap());
    assert_eq!(style, "hybrid");
    let world = p.world_spheres();
    assert_eq!(atoms.len(), world.len());
    let mut mass: HashMap<i64, f64> = HashMap::new();
    for (row, s) in atoms.iter().zip(&world) {
        // id type x y z diameter density molecule
        assert_eq!(&row[2..5], &s.center);
        assert_eq!(row[5], 2.0 * s.radius);
        assert_eq!(row[7] as usize, s.body + 1);
        *mass.entry(row[7] as i64).or_default() += row[6] * PI / 6.0 * row[5].powi(3);
    }
    // Each body's mass is density x clump volume, not x the overlapping spheres' volume.
    let want = 1000.0 * dimer().volume;
    assert_eq!(mass.len(), 3);
    for m in mass.values() {
        assert!((m / want - 1.0).abs() < 1e-12, "{m} vs {want}");
    }
}

#[test]
fn lammps_molecule_files_hold_body_frame_spheres_and_clump_mass() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("grains.in");
    let lib = ClumpLibrary {
        clumps: vec![dimer(), dimer().scaled(2.0)],
        source: "t".into(),
    };
    LammpsMoleculeExporter
        .write_defaults(
            &Artifact::ClumpLibrary(lib.clone()),
            &f,
            &Provenance::default(),
        )
        .unwrap();
    let script = std::fs::read_to_string(&f).unwrap();
    assert!(
        script.contains("molecule grains grains_0000.mol grains_0001.mol"),
        "{script}"
    );
    for (c, path) in lib.clumps.iter().zip(molecule_paths(&f, 2)) {
        let text = std::fs::read_to_string(path).unwrap();
        let mut section = "";
        let mut coords = Vec::new();
        let mut diam = Vec::new();
        let mut masses = Vec::new();
        for line in text.lines().skip(1) {
            let t = line.trim();
            if t.is_empty() || t.starts_with('#') {
                continue;
            }
            if ["Coords", "Types", "Diameters", "Masses"].contains(&t) {
                section = ["Coords", "Types", "Diameters", "Masses"]
                    .into_iter()
                    .find(|s| *s == t)
                    .unwrap();
                continue;
            }
            let w: Vec<f64> = t
                .split_whitespace()
                .filter(|x| *x != "atoms")
                .map(|x| x.parse().unwrap())
                .collect();
            match section {
                "Coords" => coords.push([w[1], w[2], w[3]]),
                "Diameters" => diam.push(w[1]),
                "Masses" => masses.push(w[1]),
                _ => {}
            }
        }
        assert_eq!(
            coords,
            c.spheres.iter().map(|s| s.offset).collect::<Vec<_>>()
        );
        assert_eq!(
            diam,
            c.spheres.iter().map(|s| 2.0 * s.radius).collect::<Vec<_>>()
        );
        let m: f64 = masses.iter().sum();
        assert!((m / (2650.0 * c.volume) - 1.0).abs() < 1e-12);
    }
}

#[test]
fn yade_text_reads_back_exactly_with_clump_ids() {
    let d = tempfile::tempdir().unwrap();
    for p in [sphere_packing(), clump_packing()] {
        let f = d.path().join("bed.txt");
        YadeExporter
            .write_defaults(&Artifact::Packing(p.clone()), &f, &Provenance::default())
            .unwrap();
        let rows: Vec<Vec<f64>> = std::fs::read_to_string(&f)
            .unwrap()
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| l.split_whitespace().map(|x| x.parse().unwrap()).collect())
            .collect();
        let world = p.world_spheres();
        assert_eq!(rows.len(), world.len());
        for (r, s) in rows.iter().zip(&world) {
            assert_eq!(&r[..3], &s.center);
            assert_eq!(r[3], s.radius);
            assert_eq!(r[4] as usize, s.body);
        }
    }
}

/// Minimal MetaImage reader: `key = value` lines.
fn parse_mhd(text: &str) -> HashMap<String, String> {
    text.lines()
        .filter_map(|l| l.split_once(" = "))
        .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
        .collect()
}

fn nums(s: &str) -> Vec<f64> {
    s.split_whitespace().map(|x| x.parse().unwrap()).collect()
}

#[test]
fn raw_with_mhd_round_trips_through_import_raw() {
    let d = tempfile::tempdir().unwrap();
    let g = Grid {
        dims: [5, 4, 3],
        spacing: [1.5e-6, 2.5e-6, 4e-6],
        origin: [-1e-4, 3e-5, 7.25e-3],
        periodic: [false; 3],
    };
    let labels: Vec<u8> = (0..60).map(|i| (i * 7 % 256) as u8).collect();
    let img = PhaseImage {
        grid: g.clone(),
        labels: labels.clone(),
        phases: vec![],
    };
    let f = d.path().join("img.mhd");
    RawExporter
        .write_defaults(&Artifact::PhaseImage(img), &f, &Provenance::default())
        .unwrap();
    let h = parse_mhd(&std::fs::read_to_string(&f).unwrap());
    assert_eq!(h["DimSize"], "5 4 3");
    assert_eq!(h["ElementType"], "MET_UCHAR");
    assert_eq!(h["BinaryDataByteOrderMSB"], "False");
    assert_eq!(h["ElementDataFile"], "img.raw");
    // Millimetres by default; Offset is the first voxel's centre.
    let sp = nums(&h["ElementSpacing"]);
    let off = nums(&h["Offset"]);
    for a in 0..3 {
        assert!((sp[a] * 1e-3 / g.spacing[a] - 1.0).abs() < 1e-12);
        let want = g.origin[a] + 0.5 * g.spacing[a];
        assert!((off[a] * 1e-3 - want).abs() < 1e-12 * want.abs().max(1e-9));
    }
    let yaml = format!(
        "name: t\nstages:\n  - id: r\n    use: import.raw\n    with: {{path: {:?}, dims: [5, 4, 3], spacing: [1.5 um, 2.5 um, 4 um]}}\n",
        d.path().join("img.raw").to_str().unwrap()
    );
    let res = run_yaml(&registry(), &yaml).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        res.artifact("r.image").as_phase_image().unwrap().labels,
        labels
    );

    // A two-component f64 field: interleaved little-endian doubles, channels in the header.
    let values: Vec<f64> = (0..120).map(|i| i as f64 * -0.25 + 1e-7).collect();
    let field = Field {
        grid: g,
        name: "u".into(),
        unit: "m".into(),
        components: 2,
        convention: ComponentConvention::Plain,
        data: FieldData::F64(values.clone()),
    };
    let q = d.path().join("u.raw");
    let mut o = ExportOptions::new();
    o.insert("length_unit".into(), serde_json::json!("um"));
    RawExporter
        .write(&Artifact::Field(field), &q, &Provenance::default(), &o)
        .unwrap();
    let h = parse_mhd(&std::fs::read_to_string(d.path().join("u.mhd")).unwrap());
    assert_eq!(h["ElementType"], "MET_DOUBLE");
    assert_eq!(h["ElementNumberOfChannels"], "2");
    assert!((nums(&h["ElementSpacing"])[0] - 1.5).abs() < 1e-12);
    let back: Vec<f64> = std::fs::read(&q)
        .unwrap()
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert_eq!(back, values);
}
