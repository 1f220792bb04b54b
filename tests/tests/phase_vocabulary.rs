//! The phase vocabulary (docs/ARCHITECTURE.md, "Phase names"): every image-making stage's
//! default phase table uses it (label 0 `pore`; `grain`, `binder`; the cemented sample's
//! `large`, `small`, `matrix`), announced at preflight as it is produced; and a pipeline that
//! still names a former default (`sand`, `void`, `solid`) is refused at preflight with the
//! file, line and key and the name it has now.

use grainpipe_core::engine::{plan, PlanOptions};
use grainpipe_core::pipeline::{PipelineDoc, PipelineError};
use grainpipe_core::testing::run_yaml;
use grainpipe_core::Phase;
use std::path::Path;

fn names(phases: &[Phase]) -> Vec<(u8, &str)> {
    let mut v: Vec<(u8, &str)> = phases.iter().map(|p| (p.id, p.name.as_str())).collect();
    v.sort();
    v
}

fn plan_err(yaml: &str) -> PipelineError {
    let d = PipelineDoc::parse(Path::new("p.yaml"), yaml.to_string()).unwrap();
    match plan(
        &d,
        &grainpipe_cli::builtin_registry(),
        &PlanOptions::default(),
    ) {
        Ok(_) => panic!("planned although it names a former phase:\n{yaml}"),
        Err(e) => e,
    }
}

/// The phase table step `step` announces for its `image` at preflight.
fn announced(yaml: &str, step: &str) -> Vec<Phase> {
    let d = PipelineDoc::parse(Path::new("p.yaml"), yaml.to_string()).unwrap();
    let p = plan(
        &d,
        &grainpipe_cli::builtin_registry(),
        &PlanOptions::default(),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let s = p
        .steps
        .iter()
        .flatten()
        .find(|s| s.id == step)
        .unwrap_or_else(|| panic!("no step {step}"));
    s.preflight.outputs["image"]
        .phases
        .clone()
        .unwrap_or_else(|| panic!("{step} announces no phase table"))
}

/// Plans and runs `yaml`; the announced and the produced phase table of `step.image` agree
/// and are returned.
fn produced(yaml: &str, step: &str) -> Vec<(u8, String)> {
    let before = announced(yaml, step);
    let res = run_yaml(&grainpipe_cli::builtin_registry(), yaml).unwrap_or_else(|e| panic!("{e}"));
    let img = res
        .artifact(&format!("{step}.image"))
        .as_phase_image()
        .unwrap();
    assert_eq!(
        names(&before),
        names(&img.phases),
        "{step}: announced vs produced"
    );
    names(&img.phases)
        .into_iter()
        .map(|(l, n)| (l, n.to_string()))
        .collect()
}

fn owned(v: &[(u8, &str)]) -> Vec<(u8, String)> {
    v.iter().map(|(l, n)| (*l, n.to_string())).collect()
}

const SPHERES: &str = "\
name: t
seed: 1
stages:
  - id: pack
    use: packing.rsa
    with: { size: [200 um, 200 um, 200 um], radius: { kind: fixed, value: 30 um }, volume_fraction: 0.3 }
";

#[test]
fn binder_and_voxelize_images_use_the_vocabulary() {
    use grainpipe_core::phases::{BINDER, GRAIN, PORE};
    let three = owned(&[(0, PORE), (1, GRAIN), (2, BINDER)]);
    for stage in ["binder.levelset", "binder.closing"] {
        let yaml = format!(
            "{SPHERES}  - id: img\n    use: {stage}\n    in: {{ packing: pack.packing }}\n    \
             with: {{ voxel_size: 10 um }}\n"
        );
        assert_eq!(produced(&yaml, "img"), three, "{stage}");
    }
    let yaml = format!(
        "{SPHERES}  - id: img\n    use: voxelize.packing\n    in: {{ packing: pack.packing }}\n    \
         with: {{ voxel_size: 10 um }}\n"
    );
    assert_eq!(produced(&yaml, "img"), owned(&[(0, PORE), (1, GRAIN)]));
}

#[test]
fn segmentation_classes_use_the_vocabulary() {
    use grainpipe_core::phases::{BINDER, GRAIN, PORE};
    let dir = tempfile::tempdir().unwrap();
    // Three grey levels along x of an 12 x 4 x 4 f32 volume.
    let values: Vec<u8> = (0..12 * 4 * 4)
        .flat_map(|i| [10.0f32, 50.0, 90.0][(i % 12) / 4].to_le_bytes())
        .collect();
    let path = dir.path().join("grey.raw");
    std::fs::write(&path, values).unwrap();
    for (classes, want) in [
        (2, owned(&[(0, PORE), (1, GRAIN)])),
        (3, owned(&[(0, PORE), (1, BINDER), (2, GRAIN)])),
    ] {
        let yaml = format!(
            "name: t\nstages:\n  - id: scan\n    use: import.raw\n    with: {{ path: {}, dims: [12, 4, 4], \
             spacing: 1 um, dtype: f32, as: field }}\n  - id: seg\n    use: segment.threshold\n    \
             in: {{ field: scan.field }}\n    with: {{ method: multi_otsu, classes: {classes} }}\n  \
             - id: clean\n    use: segment.clean\n    in: {{ image: seg.image }}\n",
            serde_json::to_string(&path.display().to_string()).unwrap()
        );
        assert_eq!(produced(&yaml, "seg"), want, "{classes} classes");
        // segment.clean hands the table on, announced too.
        assert_eq!(produced(&yaml, "clean"), want, "{classes} classes, cleaned");
    }
}

#[test]
fn cemented_images_use_the_vocabulary() {
    use grainpipe_core::phases::{LARGE, MATRIX, PORE, SMALL};
    let yaml = "\
name: t
seed: 1
stages:
  - id: pack
    use: packing.poisson_disk
    with: { size: 16 mm, large_radius: 1 mm, theta_tolerance: 0.05 }
  - id: bridges
    use: binder.bridges
    in: { packing: pack.packing }
    with: { resolution: 64 }
";
    assert_eq!(
        produced(yaml, "bridges"),
        owned(&[(0, PORE), (1, LARGE), (2, SMALL), (3, MATRIX)])
    );
}

/// The binder image piped into a solver whose map still names `sand`: refused at preflight,
/// located at the key in the file, naming `materials.sand` and the new name.
#[test]
fn a_former_default_phase_name_is_refused_with_file_line_and_key() {
    let yaml = format!(
        "{SPHERES}  - id: binder\n    use: binder.levelset\n    in: {{ packing: pack.packing }}\n    \
         with: {{ voxel_size: 10 um }}\n  - id: stiffness\n    use: elasticity.fft\n    \
         in: {{ image: binder.image }}\n    with:\n      materials:\n        \
         sand: {{ E: 66.9 GPa, nu: 0.25 }}\n        binder: {{ E: 43 GPa, nu: 0.17 }}\n"
    );
    let e = plan_err(&yaml);
    let line = yaml.lines().position(|l| l.trim() == "materials:").unwrap() as u64 + 1;
    assert_eq!(e.file, Path::new("p.yaml"), "{e}");
    assert_eq!(e.loc.map(|l| l.line), Some(line), "{e}");
    let text = e.to_string();
    assert!(
        text.starts_with(&format!("p.yaml:{line}:")),
        "file and line first: {text}"
    );
    assert!(
        text.contains(
            "parameter `materials.sand`: `sand` is the binder stages' former name for phase 1; \
             it is now `grain` (or set `sand_phase: sand` on the binder step)"
        ),
        "{text}"
    );
    // Keeping the old name on the binder step is the other way out.
    let kept = yaml.replace(
        "with: { voxel_size: 10 um }",
        "with: { voxel_size: 10 um, sand_phase: sand }",
    );
    let d = PipelineDoc::parse(Path::new("p.yaml"), kept).unwrap();
    plan(
        &d,
        &grainpipe_cli::builtin_registry(),
        &PlanOptions::default(),
    )
    .unwrap();
}

/// The cemented image's label 0 was `void`: a conductivity or peridynamics map, or the
/// stress statistics' `exclude`, that still says so is refused before anything runs (label 0
/// would otherwise quietly take the default instead of the value given).
#[test]
fn void_is_refused_for_the_cemented_pore() {
    let head = "\
name: t
seed: 1
stages:
  - id: pack
    use: packing.poisson_disk
    with: { size: 16 mm, large_radius: 1 mm, theta_tolerance: 0.05 }
  - id: bridges
    use: binder.bridges
    in: { packing: pack.packing }
    with: { resolution: 64 }
";
    let k = "conductivities: { void: 0.5 W/(m K), large: 7 W/(m K), small: 7 W/(m K), matrix: 1 W/(m K) }";
    let yaml =
        format!("{head}  - id: k\n    use: conductivity.fft\n    in: {{ image: bridges.image }}\n    with: {{ {k} }}\n");
    let text = plan_err(&yaml).to_string();
    assert!(
        text.contains("parameter `conductivities.void`")
            && text.contains(
                "`void` is the cemented stages' former name for label 0; it is now `pore`"
            ),
        "{text}"
    );

    let yaml = format!(
        "{head}  - id: pd\n    use: peridynamics.bond_based\n    in: {{ image: bridges.image }}\n    \
         with:\n      materials:\n        void: {{ role: void }}\n        \
         large: {{ role: particle, E: 4 GPa, toughness: 30 J/m^2 }}\n        \
         small: {{ role: particle, E: 4 GPa, toughness: 30 J/m^2 }}\n        \
         matrix: {{ role: matrix, E: 1 GPa, toughness: 10 J/m^2 }}\n"
    );
    let e = plan_err(&yaml);
    let line = yaml.lines().position(|l| l.trim() == "materials:").unwrap() as u64 + 1;
    assert_eq!(e.loc.map(|l| l.line), Some(line), "{e}");
    assert!(e.to_string().contains("parameter `materials.void`"), "{e}");

    let yaml = format!(
        "{head}  - id: pd\n    use: peridynamics.bond_based\n    in: {{ image: bridges.image }}\n  \
         - id: stats\n    use: analysis.stress_stats\n    in: {{ stress: pd.stress, image: bridges.image }}\n    \
         with: {{ exclude: [void] }}\n"
    );
    let text = plan_err(&yaml).to_string();
    assert!(
        text.contains("parameter `exclude`") && text.contains("it is now `pore`"),
        "{text}"
    );
}
