//! `import.packing`: CSV (units from the parameter and from headers), LIGGGHTS/LAMMPS dumps
//! written by hand, grainpipe .h5 round trips, and every bad input refused in preflight with
//! the file, line and YAML key.
//!
//! References are the numbers typed into the hand-written files (converted by hand to SI),
//! never the reader's own output. Unit conversions multiply by a power of ten, so positions
//! are compared to 1e-15 relative (a few ulps); everything else is exact.

use grainpipe_core::testing::run_yaml;
use grainpipe_core::*;
use grainpipe_formats::write_h5;
use std::path::{Path, PathBuf};

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    r
}

#[test]
fn import_packing_describes_itself_consistently() {
    registry().check_consistency().unwrap();
}

/// A one-step pipeline: `with` lines (YAML, already indented by the caller's keys) under
/// `path: <file>`, which is on line 6.
fn yaml(path: &Path, with: &[&str]) -> String {
    let mut y = format!(
        "name: t\nstages:\n  - id: imp\n    use: import.packing\n    with:\n      path: {}\n",
        serde_json::to_string(&path.display().to_string()).unwrap()
    );
    for w in with {
        y += &format!("      {w}\n");
    }
    y
}

fn import(path: &Path, with: &[&str]) -> Packing {
    let res = run_yaml(&registry(), &yaml(path, with))
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    res.artifact("imp.packing").as_packing().unwrap().clone()
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-15 * a.abs().max(b.abs())
}

fn assert_close3(got: [f64; 3], want: [f64; 3], what: &str) {
    assert!(
        (0..3).all(|k| close(got[k], want[k])),
        "{what}: got {got:?}, want {want:?}"
    );
}

fn radius(b: &Body) -> f64 {
    match b.shape {
        BodyShape::Sphere { radius } => radius,
        _ => panic!("not a sphere"),
    }
}

/// The spheres (centre, radius) in SI, compared to 1e-15 relative.
fn assert_spheres(p: &Packing, want: &[([f64; 3], f64)]) {
    assert_eq!(p.bodies.len(), want.len());
    for (k, (b, (c, r))) in p.bodies.iter().zip(want).enumerate() {
        assert_close3(b.position, *c, &format!("body {k} centre"));
        assert!(close(radius(b), *r), "body {k} radius {} vs {r}", radius(b));
    }
}

#[test]
fn csv_in_micrometres_and_in_metres_give_the_same_packing() {
    let d = tempfile::tempdir().unwrap();
    let um = write(
        d.path(),
        "um.csv",
        // As a spreadsheet writes it: byte order mark and CRLF line ends.
        "\u{feff}x,y,z,r,layer\r\n10,20,30,5,0\r\n# a comment\r\n\r\n40,50,60,7.5,1\r\n",
    );
    let m = write(
        d.path(),
        "m.csv",
        "x, y, z, radius, layer\n1e-5, 2e-5, 3e-5, 5e-6, 0\n4e-5, 5e-5, 6e-5, 7.5e-6, 1\n",
    );
    let a = import(&um, &["unit: um", "box: [100 um, 100 um, 100 um]"]);
    let b = import(&m, &["box: 100 um"]);
    let want = [([1e-5, 2e-5, 3e-5], 5e-6), ([4e-5, 5e-5, 6e-5], 7.5e-6)];
    assert_spheres(&a, &want);
    assert_spheres(&b, &want);
    for p in [&a, &b] {
        assert_eq!(p.bodies[1].layer, 1);
        assert_eq!(p.domain.min, [0.0; 3]);
        assert_close3(p.domain.max, [1e-4; 3], "box");
        assert_eq!(p.domain.periodic, [false; 3]);
    }
}

#[test]
fn csv_header_units_set_their_column_and_the_rest_take_the_parameter() {
    let d = tempfile::tempdir().unwrap();
    // x in micrometres, y in millimetres, z from `unit` (cm), diameter in micrometres;
    // `body` ids kept; semicolons as delimiter.
    let p = write(
        d.path(),
        "h.csv",
        "body;x [um];y (mm);z;diameter [um]\n7;100;0.2;0.03;20\n3;150;0.25;0.04;30\n",
    );
    let got = import(
        &p,
        &[
            "unit: cm",
            "box: [1 mm, 1 mm, 1 mm]",
            "origin: [0, 0, 0]",
            "periodic: [true, false, false]",
        ],
    );
    assert_spheres(
        &got,
        &[([1e-4, 2e-4, 3e-4], 1e-5), ([1.5e-4, 2.5e-4, 4e-4], 1.5e-5)],
    );
    assert_eq!(got.attributes["body"].values, vec![7.0, 3.0]);
    assert_eq!(got.domain.periodic, [true, false, false]);
    // White-space delimited, with `x [um]` split over two tokens.
    let q = write(
        d.path(),
        "w.csv",
        "x [um]  y [um] z [um] r [um]\n1 2 3 0.5\n",
    );
    let got = import(&q, &["box: 10 um"]);
    assert_spheres(&got, &[([1e-6, 2e-6, 3e-6], 5e-7)]);
}

/// Two frames; periodic in x and y, walls in z; the second frame lists atoms out of id
/// order (as several processors write them), has an atom beyond the periodic x bound and
/// uses other column orders and an extra section (UNITS) that is skipped.
const DUMP: &str = "\
ITEM: TIMESTEP
0
ITEM: NUMBER OF ATOMS
2
ITEM: BOX BOUNDS pp pp ff
0 0.001
-0.0005 0.0005
0 0.002
ITEM: ATOMS id type x y z radius vx
1 1 0.0001 0 0.0001 5e-05 0
2 2 0.0002 0 0.0002 6e-05 0
ITEM: TIMESTEP
1000
ITEM: UNITS
si
ITEM: NUMBER OF ATOMS
3
ITEM: BOX BOUNDS pp pp ff
0 0.001
-0.0005 0.0005
0 0.002
ITEM: ATOMS radius z y x type id
7e-05 0.0015 0.0001 0.0003 1 3
5e-05 0.0001 -0.0004 0.0011 1 1
6e-05 0.0019 0.0002 0.0002 2 2
";

#[test]
fn liggghts_dump_written_by_hand_round_trips() {
    let d = tempfile::tempdir().unwrap();
    let p = write(d.path(), "post.dump", DUMP);
    // Default: the last frame, atoms in id order, x = 1.1 mm wrapped to 0.1 mm.
    let last = import(&p, &[]);
    assert_eq!(last.domain.min, [0.0, -0.0005, 0.0]);
    assert_eq!(last.domain.max, [0.001, 0.0005, 0.002]);
    assert_eq!(last.domain.periodic, [true, true, false]);
    assert_spheres(
        &last,
        &[
            ([0.0001, -0.0004, 0.0001], 5e-5),
            ([0.0002, 0.0002, 0.0019], 6e-5),
            ([0.0003, 0.0001, 0.0015], 7e-5),
        ],
    );
    assert_eq!(last.attributes["id"].values, vec![1.0, 2.0, 3.0]);
    assert_eq!(last.attributes["type"].values, vec![1.0, 2.0, 1.0]);
    // frame 0 and frame -2 are the first frame.
    for f in ["frame: 0", "frame: -2"] {
        let first = import(&p, &[f]);
        assert_spheres(
            &first,
            &[([0.0001, 0.0, 0.0001], 5e-5), ([0.0002, 0.0, 0.0002], 6e-5)],
        );
    }
    // Parameters override the file: micrometre numbers, a box and no periodicity.
    let um = write(
        d.path(),
        "dump.micro",
        "ITEM: TIMESTEP\n5\nITEM: NUMBER OF ATOMS\n1\nITEM: BOX BOUNDS ff ff ff\n\
         0 100\n0 100\n0 100\nITEM: ATOMS id xs ys zs diameter\n1 0.25 0.5 0.75 20\n",
    );
    let got = import(&um, &["unit: um"]);
    assert_spheres(&got, &[([2.5e-5, 5e-5, 7.5e-5], 1e-5)]);
    assert_eq!(got.domain.periodic, [false; 3]);
    let got = import(
        &um,
        &["unit: um", "periodic: [true, true, true]", "box: 200 um"],
    );
    assert_eq!(got.domain.periodic, [true; 3]);
    assert_close3(got.domain.max, [2e-4; 3], "box override");
}

#[test]
fn grainpipe_h5_packing_with_clumps_round_trips() {
    let mut p = Packing::new(Domain {
        min: [-1e-4, 0.0, 0.0],
        max: [1e-3, 2e-3, 3e-3],
        periodic: [true, false, true],
        excluded: vec![ExcludedSolid::Sphere {
            center: [5e-4, 5e-4, 0.0],
            radius: 2e-4,
        }],
    });
    p.bodies.push(Body::sphere([1e-4, 2e-4, 3e-4], 5e-5));
    let mut b = Body::sphere([4e-4, 4e-4, 4e-4], 0.0);
    b.shape = BodyShape::Clump { index: 1 };
    b.orientation = [0.5, 0.5, 0.5, 0.5];
    b.layer = 3;
    b.frozen = true;
    p.bodies.push(b);
    p.library = Some(ClumpLibrary {
        clumps: (0..2)
            .map(|k| Clump {
                spheres: (0..=k)
                    .map(|s| ClumpSphere {
                        offset: [s as f64 * 1e-5, -2e-5, 3e-5],
                        radius: 4e-5 + s as f64 * 1e-6,
                    })
                    .collect(),
                volume: 1e-13 * (k + 1) as f64,
                bounding_radius: 6e-5,
                principal_inertia: [1e-22, 2e-22, 3e-22],
                principal_axes: [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]],
                source: format!("grain {k}"),
            })
            .collect(),
        source: "test library".into(),
    });
    p.attributes.insert(
        "peak temperature".into(),
        BodyAttribute {
            unit: "K".into(),
            values: vec![300.0, 1700.5],
        },
    );
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("p.h5");
    write_h5(&Artifact::Packing(p.clone()), &f, &Provenance::default()).unwrap();
    assert_eq!(import(&f, &[]), p);
    // Also found by content under another name.
    let g = d.path().join("packing.bin");
    std::fs::copy(&f, &g).unwrap();
    assert_eq!(import(&g, &[]), p);
}

/// The preflight error of `with` (checked directly, so it is known to come from preflight)
/// and the pipeline error (exit code 2, at the YAML key `key`, message containing `text`).
fn refused(path: &Path, with: &[&str], key: &str, text: &str) {
    let reg = registry();
    let stage = reg.stage("import.packing").unwrap().stage.clone();
    let mut params = serde_json::json!({ "path": path });
    for w in with {
        let (k, v) = w.split_once(": ").unwrap();
        let v: serde_json::Value = serde_json::from_str(v).unwrap_or(v.into());
        params[k] = v;
    }
    let params = stage.normalize_params(&params).unwrap();
    match stage.preflight(&params, &InputMetas::new()) {
        Err(StageError::InvalidParam { key: k, message }) => {
            assert_eq!(k, key, "{message}");
            assert!(message.contains(text), "`{message}` lacks `{text}`");
        }
        Err(e) => panic!("{}: expected a `{key}` error, got {e}", path.display()),
        Ok(_) => panic!("{}: accepted {with:?}", path.display()),
    }
    let Err(e) = run_yaml(&reg, &yaml(path, with)) else {
        panic!("{}: the pipeline ran", path.display())
    };
    assert_eq!(e.exit_code(), 2, "{e}");
    assert!(e.message.contains(text), "{e}");
    // A missing key is reported at the step's `use:` line (4).
    let line = match with.iter().position(|w| w.starts_with(key)) {
        _ if key == "path" => 6,
        Some(k) => 7 + k as u64,
        None => 4,
    };
    assert_eq!(e.loc.map(|l| l.line), Some(line), "{e}");
}

#[test]
fn bad_csv_is_refused_in_preflight_with_file_and_line() {
    let d = tempfile::tempdir().unwrap();
    let bx = ["box: \"1 mm\""];
    let case = |name: &str, text: &str, want: &str| {
        let p = write(d.path(), name, text);
        refused(&p, &bx, "path", &format!("{}{want}", p.display()));
    };
    case(
        "nor.csv",
        "x,y,z,rad\n1e-4,1e-4,1e-4,1e-5\n",
        ":1: no column `r` (or `radius`, `diameter`, `d`) in the header (x, y, z, rad)",
    );
    case(
        "text.csv",
        "x,y,z,r\n1e-4,1e-4,1e-4,1e-5\n1e-4,abc,1e-4,1e-5\n",
        ":3: column `y`: `abc` is not a number",
    );
    case(
        "neg.csv",
        "x,y,z,r\n1e-4,1e-4,1e-4,1e-5\n\n\n1e-4,1e-4,1e-4,1e-5\n# c\n2e-4,2e-4,2e-4,-1e-6\n",
        ":7: radius -1e-6 is negative",
    );
    case(
        "zero.csv",
        "x,y,z,r\n1e-4,1e-4,1e-4,0\n",
        ":2: radius is zero",
    );
    case(
        "nan.csv",
        "x,y,z,r\n1e-4,NaN,1e-4,1e-5\n",
        ":2: column `y`: NaN is not a finite number",
    );
    case(
        "out.csv",
        "x,y,z,r\n1e-4,1e-4,1e-4,1e-5\n1e-4,1e-4,1.5e-3,1e-5\n",
        ":3: centre z = 1.5e-3 m is outside the non-periodic box 0e0..1e-3 m",
    );
    // Issue 35: a sphere wider than the box (an analytic solid fraction of 524 before).
    case(
        "huge.csv",
        "x,y,z,r\n1e-4,1e-4,1e-4,1e-5\n5e-4,5e-4,5e-4,5e-4\n5e-4,5e-4,5e-4,6e-4\n",
        ":4: a sphere of diameter 1.2 mm is wider than the box along x (1 mm)",
    );
    case(
        "short.csv",
        "x,y,z,r\n1e-4,1e-4,1e-4\n",
        ":2: 3 values, but the header names 4 columns",
    );
    case(
        "hdr.csv",
        "x,y,z,r\n",
        ":1: a header but no spheres after it",
    );
    case("empty.csv", "\n  \n", ": the file is empty");
    case(
        "unit.csv",
        "x [furlong],y,z,r\n1,1,1,1\n",
        ":1: column `x [furlong]`: `furlong`",
    );
    case(
        "sec.csv",
        "x [s],y,z,r\n1,1,1,1\n",
        ":1: column `x [s]`: `s` is not a length unit",
    );
    case(
        "dup.csv",
        "body,x,y,z,r\n4,1e-4,1e-4,1e-4,1e-5\n4,2e-4,2e-4,2e-4,1e-5\n",
        ":3: body 4 already appears on line 2",
    );
    // The same atom is accepted once the axis is periodic (and wrapped into the box).
    let p = d.path().join("out.csv");
    let got = import(&p, &["box: \"1 mm\"", "periodic: [false, false, true]"]);
    assert_close3(got.bodies[1].position, [1e-4, 1e-4, 5e-4], "wrapped centre");
    // Parameter errors name their key.
    refused(&p, &["unit: \"furlong\""], "unit", "`furlong`");
    refused(&p, &["unit: \"kg\""], "unit", "`kg` is not a length unit");
    refused(&p, &[], "box", "carries no domain box");
    refused(
        &p,
        &["box: \"1 mm\"", "frame: 0"],
        "frame",
        "applies to dumps only",
    );
    refused(&p, &["box: [1, 1, 0]"], "box", "three positive lengths");
    let q = write(d.path(), "mystery.dat", "x,y,z,r\n1,1,1,1\n");
    refused(&q, &bx, "format", "cannot tell the format");
    refused(
        &d.path().join("missing.csv"),
        &bx,
        "path",
        "missing.csv: No such file",
    );
}

#[test]
fn bad_dumps_are_refused_in_preflight_with_file_and_line() {
    let d = tempfile::tempdir().unwrap();
    let good = write(d.path(), "ok.dump", DUMP);
    refused(
        &good,
        &["frame: 2"],
        "frame",
        "holds 2 frames: frame 2 is out of range (use 0..1 or -1..-2)",
    );
    refused(&good, &["frame: -3"], "frame", "frame -3 is out of range");
    let case = |name: &str, text: String, want: &str| {
        let p = write(d.path(), name, &text);
        refused(&p, &[], "path", &format!("{}{want}", p.display()));
    };
    case(
        "norad.dump",
        DUMP.replace("radius z y x", "rad z y x"),
        ":22: no column `radius` or `diameter` in `ITEM: ATOMS rad z y x type id`",
    );
    case(
        "text.dump",
        DUMP.replace("0.0019 0.0002", "0.0019 zz"),
        ":25: column `y`: `zz` is not a number",
    );
    case(
        "neg.dump",
        DUMP.replace("7e-05 0.0015", "-7e-05 0.0015"),
        ":23: radius -7e-5 is negative",
    );
    // z has walls (ff): 2.5 mm is above the 2 mm box.
    case(
        "out.dump",
        DUMP.replace("0.0015 0.0001 0.0003", "0.0025 0.0001 0.0003"),
        ":23: centre z = 2.5e-3 m is outside the non-periodic box 0e0..2e-3 m",
    );
    case(
        "few.dump",
        DUMP.replace("ATOMS\n3\n", "ATOMS\n4\n"),
        ":26: frame 1 announces 4 atoms but lists 3",
    );
    case(
        "tri.dump",
        DUMP.replace("BOX BOUNDS pp pp ff\n0 0.001\n-0.0005 0.0005\n0 0.002\nITEM: ATOMS radius",
                     "BOX BOUNDS xy xz yz pp pp ff\n0 0.001 0\n-0.0005 0.0005 0\n0 0.002 0\nITEM: ATOMS radius"),
        ":18: a triclinic box",
    );
    case("empty.dump", String::new(), ": the file is empty");
    case(
        "notdump.dump",
        "\nhello\n".into(),
        ":2: not a LAMMPS/LIGGGHTS dump",
    );
}
