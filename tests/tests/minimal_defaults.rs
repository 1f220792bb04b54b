//! Every registered stage runs from the smallest pipeline that can feed it, with all of its
//! parameters at their defaults: a user's first `use: STAGE` must not be refused by the
//! stage's own preflight. Required inputs are fed by a small upstream stage producing that
//! port kind (table `producer`); parameters with no usable default (file paths, the size of
//! a raw file) get a value from `required_values`. Stages whose defaults are legitimately
//! heavy are preflighted only (`PREFLIGHT_ONLY`, with the reason).

use grainpipe_core::engine::{plan, PlanOptions};
use grainpipe_core::pipeline::PipelineDoc;
use grainpipe_core::testing::run_yaml;
use grainpipe_core::ArtifactKind;
use std::path::Path;
use std::time::Instant;

/// Stages of other crates whose defaults currently fail from a minimal pipeline, with the
/// error seen. Empty this list as they are fixed: the test then covers them.
const KNOWN_FAILING_DEFAULTS_OF_OTHER_CRATES: &[(&str, &str)] = &[];

/// Stages whose defaults are valid but too heavy for this test's ~2 minute budget on
/// 2 cores: planned and preflighted only.
const PREFLIGHT_ONLY: &[(&str, &str)] = &[
    (
        "elasticity.fft",
        "six load cases on binder.levelset's default image: ~5 min on 2 cores",
    ),
    (
        "conductivity.fft",
        "three gradients on binder.levelset's default image: ~12 s on 2 cores",
    ),
    (
        "packing.poisson_disk",
        "the paper's full 53 mm sample with gap calibration: ~20 s",
    ),
    (
        "dem.compact",
        "quasi-static DEM to the default pressure tolerance: ~25 s",
    ),
];

const RSA: &str = "  - id: up_pack
    use: packing.rsa
    with: { size: [40 um, 40 um, 40 um], radius: { kind: fixed, value: 8 um }, volume_fraction: 0.3 }
";
const VOXELS: &str = "  - id: up_image
    use: voxelize.packing
    in: { packing: up_pack.packing }
";
const BRICKS: &str = "  - id: up_bricks
    use: bricks.method1
";
const GRAINS: &str = "  - id: up_grains
    use: grains.from_harmonics
    with: { files: [MA107-6-fine-anm-00002.dat] }
";
const CLUMPS: &str = "  - id: up_lib
    use: clumps.garcia
    in: { grains: up_grains.grains }
";
// Cemented samples: a small bidisperse disk packing (per-body `class`, walls) and its
// bridges image (phases void, large, small, matrix).
const DISKS: &str = "  - id: up_disks
    use: packing.poisson_disk
    with: { size: 16 mm, large_radius: 1 mm, theta_tolerance: 0.05 }
";
const BRIDGES: &str = "  - id: up_bridges
    use: binder.bridges
    in: { packing: up_disks.packing }
    with: { resolution: 96 }
";
const PERIDYNAMICS: &str = "  - id: up_peri
    use: peridynamics.bond_based
    in: { image: up_bridges.image }
";
// A grain/binder image (the phases the FFT solvers' default materials name).
const LEVELSET: &str = "  - id: up_binder
    use: binder.levelset
    in: { packing: up_pack.packing }
";

/// Upstream steps and the `in:` map feeding `stage`'s required inputs. The default producer
/// of each kind is the smallest stage giving it; a few stages need content of that kind that
/// only one upstream gives (named phases, a per-body class), said in the match arm.
fn producer(stage: &str, port: &str, kind: ArtifactKind, files: &Path) -> (String, String) {
    let f = files.display();
    match (stage, port) {
        // Per-body `class` attribute and walls: packing.poisson_disk.
        ("analysis.pores" | "binder.bridges" | "dem.compact", "packing") => {
            (DISKS.into(), "up_disks.packing".into())
        }
        ("analysis.pores", "image") => (format!("{DISKS}{BRIDGES}"), "up_bridges.image".into()),
        // Phases pore/large/small/matrix: binder.bridges.
        ("peridynamics.bond_based" | "analysis.stress_stats", "image") => {
            (format!("{DISKS}{BRIDGES}"), "up_bridges.image".into())
        }
        ("analysis.stress_stats", "stress") => (
            format!("{DISKS}{BRIDGES}{PERIDYNAMICS}"),
            "up_peri.stress".into(),
        ),
        // Phases grain/binder: binder.levelset.
        ("elasticity.fft" | "conductivity.fft", "image") => {
            (format!("{RSA}{LEVELSET}"), "up_binder.image".into())
        }
        // Grain ids: a label volume with two balls, read by import.raw.
        ("grains.from_labels", "labels") => (
            format!(
                "  - id: up_labels\n    use: import.raw\n    with: {{ path: {f}/labels.raw, \
                 dims: [24, 24, 24], spacing: 4 um }}\n"
            ),
            "up_labels.image".into(),
        ),
        // Downsampling needs dims its factor (default 2) divides: the 24^3 label volume.
        ("segment.downsample", "image") => (
            format!(
                "  - id: up_labels\n    use: import.raw\n    with: {{ path: {f}/labels.raw, \
                 dims: [24, 24, 24], spacing: 4 um }}\n"
            ),
            "up_labels.image".into(),
        ),
        // A grey-value volume: the label volume read as a field (a scan before segmentation).
        (_, "field") if kind == ArtifactKind::Field => (
            format!(
                "  - id: up_scan\n    use: import.raw\n    with: {{ path: {f}/labels.raw, \
                 dims: [24, 24, 24], spacing: 4 um, as: field }}\n"
            ),
            "up_scan.field".into(),
        ),
        // The contacts must be those of the packing it heats: both from one brick.
        ("sintering.laser", "packing") => (BRICKS.into(), "up_bricks.packing".into()),
        // Analyses the report table of a small packing.
        ("analysis.ensemble", "table") => (RSA.into(), "up_pack.report".into()),
        _ => match kind {
            ArtifactKind::Packing => (RSA.into(), "up_pack.packing".into()),
            ArtifactKind::PhaseImage => (format!("{RSA}{VOXELS}"), "up_image.image".into()),
            ArtifactKind::ContactGraph => (BRICKS.into(), "up_bricks.contacts".into()),
            ArtifactKind::Collection => (GRAINS.into(), "up_grains.grains".into()),
            ArtifactKind::ClumpLibrary => (format!("{GRAINS}{CLUMPS}"), "up_lib.library".into()),
            ArtifactKind::Table => (RSA.into(), "up_pack.report".into()),
            other => panic!("{stage}.{port}: no producer of {other:?}: add one to `producer`"),
        },
    }
}

/// Inputs a stage needs although they are declared optional (one of several must be
/// connected, or the stage has nothing to work on without it).
fn needed_optional_inputs(stage: &str) -> &'static [&'static str] {
    match stage {
        "grains.from_labels" => &["labels"],
        "analysis.ensemble" => &["table"],
        // One of image / field; the image is the common case.
        "segment.crop" | "segment.downsample" => &["image"],
        _ => &[],
    }
}

/// Values for parameters whose default cannot work (a file to read, what a raw file holds).
fn required_values(stage: &str, files: &Path) -> Option<String> {
    let f = files.display();
    Some(match stage {
        "grains.from_meshes" => format!("{{ files: [{f}/octahedron.stl] }}"),
        "import.hdf5" => format!("{{ path: {f}/image.h5, dataset: phase }}"),
        "import.netcdf" => format!("{{ path: {f}/image.nc, variable: phase }}"),
        "import.vti" => format!("{{ path: {f}/image.vti }}"),
        "import.tiff" => format!("{{ path: {f}/stack.tif, spacing: 4 um }}"),
        "import.raw" => format!("{{ path: {f}/labels.raw, dims: [24, 24, 24], spacing: 4 um }}"),
        "import.packing" => format!("{{ path: {f}/packing.csv, box: 40 um, unit: um }}"),
        _ => return None,
    })
}

/// A little-endian 8-bit greyscale multi-page TIFF (baseline, uncompressed, one strip per
/// page), `pages[z]` of `w * h` bytes.
fn write_tiff(path: &Path, w: u32, h: u32, pages: &[Vec<u8>]) {
    let mut out: Vec<u8> = b"II*\0".to_vec();
    out.extend_from_slice(&8u32.to_le_bytes());
    let mut next_ifd_at = 4usize;
    for page in pages {
        let data_at = out.len() as u32;
        out.extend_from_slice(page);
        if out.len() % 2 == 1 {
            out.push(0);
        }
        let ifd_at = out.len() as u32;
        out[next_ifd_at..next_ifd_at + 4].copy_from_slice(&ifd_at.to_le_bytes());
        // (tag, type: 3 = SHORT, 4 = LONG, value)
        let entries: [(u16, u16, u32); 9] = [
            (256, 4, w),
            (257, 4, h),
            (258, 3, 8),
            (259, 3, 1),
            (262, 3, 1),
            (273, 4, data_at),
            (277, 3, 1),
            (278, 4, h),
            (279, 4, w * h),
        ];
        out.extend_from_slice(&(entries.len() as u16).to_le_bytes());
        for (tag, ty, v) in entries {
            out.extend_from_slice(&tag.to_le_bytes());
            out.extend_from_slice(&ty.to_le_bytes());
            out.extend_from_slice(&1u32.to_le_bytes());
            if ty == 3 {
                out.extend_from_slice(&(v as u16).to_le_bytes());
                out.extend_from_slice(&[0, 0]);
            } else {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        next_ifd_at = out.len();
        out.extend_from_slice(&0u32.to_le_bytes());
    }
    std::fs::write(path, out).unwrap();
}

/// The input files of the import stages: a label volume (two balls, ids 1 and 2), the same
/// as a TIFF stack, an octahedron STL, a packing CSV, and an image exported by a small
/// pipeline as .h5, .nc and .vti.
fn write_inputs(dir: &Path) {
    let n = 24usize;
    let mut labels = vec![0u8; n * n * n];
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let d = |cx: f64, r: f64| {
                    let (dx, dy, dz) = (x as f64 - cx, y as f64 - 12.0, z as f64 - 12.0);
                    dx * dx + dy * dy + dz * dz < r * r
                };
                labels[x + n * (y + n * z)] = if d(8.0, 5.0) {
                    1
                } else if d(17.0, 4.0) {
                    2
                } else {
                    0
                };
            }
        }
    }
    std::fs::write(dir.join("labels.raw"), &labels).unwrap();
    let pages: Vec<Vec<u8>> = labels.chunks(n * n).map(|c| c.to_vec()).collect();
    write_tiff(&dir.join("stack.tif"), n as u32, n as u32, &pages);
    // Octahedron |x| + |y| + |z| <= 0.05 mm: 25 voxels across at 4 um.
    let a = 0.05;
    let mut stl = String::from("solid octahedron\n");
    for sx in [-1.0, 1.0] {
        for sy in [-1.0, 1.0] {
            for sz in [-1.0f64, 1.0] {
                let (p, q, r) = ([sx * a, 0.0, 0.0], [0.0, sy * a, 0.0], [0.0, 0.0, sz * a]);
                // Outward orientation: the normal (sx, sy, sz) needs a positive triple product.
                let (q, r) = if sx * sy * sz > 0.0 { (q, r) } else { (r, q) };
                stl.push_str(&format!(
                    "facet normal {sx} {sy} {sz}\nouter loop\nvertex {} {} {}\nvertex {} {} {}\n\
                     vertex {} {} {}\nendloop\nendfacet\n",
                    p[0], p[1], p[2], q[0], q[1], q[2], r[0], r[1], r[2]
                ));
            }
        }
    }
    stl.push_str("endsolid octahedron\n");
    std::fs::write(dir.join("octahedron.stl"), stl).unwrap();
    std::fs::write(dir.join("packing.csv"), "x,y,z,r\n10,10,10,5\n30,30,30,6\n").unwrap();
    let d = dir.display();
    let setup = format!(
        "name: setup\nstages:\n{RSA}{VOXELS}export:\n  - {{ from: up_image.image, to: {d}/image.h5 }}\n  \
         - {{ from: up_image.image, to: {d}/image.nc }}\n  - {{ from: up_image.image, to: {d}/image.vti }}\n"
    );
    run_yaml(&grainpipe_cli::builtin_registry(), &setup).unwrap();
}

#[test]
fn every_stage_runs_with_its_defaults_from_a_minimal_pipeline() {
    let registry = grainpipe_cli::builtin_registry();
    let dir = tempfile::tempdir().unwrap();
    write_inputs(dir.path());
    let mut failures = Vec::new();
    let mut ran = 0;
    let mut preflighted = 0;
    for entry in registry.stages() {
        let info = entry.stage.info();
        let id = info.id;
        if KNOWN_FAILING_DEFAULTS_OF_OTHER_CRATES
            .iter()
            .any(|(s, _)| *s == id)
        {
            continue;
        }
        let mut upstream = String::new();
        let mut wiring = Vec::new();
        for port in &info.inputs {
            if port.optional && !needed_optional_inputs(id).contains(&port.name) {
                continue;
            }
            let (steps, from) = producer(id, port.name, port.kind, dir.path());
            // Upstream snippets share steps; keep each step once.
            for step in steps.split("  - id: ").filter(|x| !x.trim().is_empty()) {
                let step = format!("  - id: {step}");
                if !upstream.contains(&step) {
                    upstream.push_str(&step);
                }
            }
            wiring.push(format!("{}: {from}", port.name));
        }
        let mut yaml = format!("name: minimal\nstages:\n{upstream}  - id: s\n    use: {id}\n");
        if !wiring.is_empty() {
            yaml.push_str(&format!("    in: {{ {} }}\n", wiring.join(", ")));
        }
        if let Some(w) = required_values(id, dir.path()) {
            yaml.push_str(&format!("    with: {w}\n"));
        }
        let t = Instant::now();
        let heavy = PREFLIGHT_ONLY.iter().find(|(s, _)| *s == id);
        let outcome = if heavy.is_some() {
            preflighted += 1;
            PipelineDoc::parse(Path::new("minimal.yaml"), yaml.clone())
                .and_then(|doc| plan(&doc, &registry, &PlanOptions::default()).map(|_| ()))
        } else {
            ran += 1;
            run_yaml(&registry, &yaml).map(|r| {
                // Every output the step gave has the kind its port declares.
                let out = &r.outputs["s"];
                assert!(!out.is_empty(), "{id}: no output");
                for (name, a) in out.iter() {
                    let port = info.outputs.iter().find(|p| p.name == *name).unwrap();
                    assert_eq!(a.kind(), port.kind, "{id}.{name}");
                }
            })
        };
        println!(
            "{id:<26} {:<10} {:6.2} s",
            if heavy.is_some() { "preflight" } else { "run" },
            t.elapsed().as_secs_f64()
        );
        if let Err(e) = outcome {
            failures.push(format!("{id}: {e}\n--- pipeline:\n{yaml}"));
        }
    }
    assert!(
        failures.is_empty(),
        "{} stage(s) fail with their defaults:\n{}",
        failures.len(),
        failures.join("\n")
    );
    // The lists above name registered stages only (a renamed stage must not hide here).
    for (s, _) in KNOWN_FAILING_DEFAULTS_OF_OTHER_CRATES
        .iter()
        .chain(PREFLIGHT_ONLY)
    {
        assert!(
            registry.stages().iter().any(|e| e.stage.info().id == *s),
            "{s} is not registered"
        );
    }
    let total = registry.stages().len();
    assert_eq!(
        ran + preflighted + KNOWN_FAILING_DEFAULTS_OF_OTHER_CRATES.len(),
        total
    );
}
