//! The `tiff` exporter: stacks written by us read back through `import.tiff` voxel for voxel
//! with the same geometry, and the calibration read independently from the raw tags.

use grainpipe_core::registry::ExportOptions;
use grainpipe_core::testing::run_yaml;
use grainpipe_core::*;
use grainpipe_formats::tiff_io::{slice_directory, write_tiff, StackLayout, TiffExporter};
use std::path::Path;
use tiff::decoder::{ifd::Value, Decoder};
use tiff::tags::Tag;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    r
}

/// An anisotropic grid with an offset origin: a swapped axis or a lost origin shows.
fn grid(dims: [usize; 3]) -> Grid {
    Grid {
        dims,
        spacing: [1.5e-6, 2.5e-6, 4e-6],
        origin: [-1e-4, 3e-5, 7.25e-3],
        // Mixed, so the round trips check each axis's flag.
        periodic: [true, false, true],
    }
}

fn image(dims: [usize; 3]) -> PhaseImage {
    let g = grid(dims);
    PhaseImage {
        // Distinct along every axis, and label 200 so 8-bit storage is exercised fully.
        labels: (0..g.voxel_count())
            .map(|i| [0u8, 1, 200][(i + i / dims[0] + i / (dims[0] * dims[1])) % 3])
            .collect(),
        grid: g,
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 1,
                name: "sand = quartz".into(),
            },
            Phase {
                id: 200,
                name: "binder".into(),
            },
        ],
    }
}

/// Runs `import.tiff` on `path` through the engine (which holds the output to what preflight
/// announced).
fn import(path: &Path, extra: &str, port: &str) -> Artifact {
    let yaml = format!(
        "name: t\nstages:\n  - id: tif\n    use: import.tiff\n    with: {{path: {:?}{extra}}}\n",
        path.to_str().unwrap()
    );
    run_yaml(&registry(), &yaml)
        .unwrap_or_else(|e| panic!("{e}"))
        .artifact(&format!("tif.{port}"))
        .clone()
}

#[test]
fn multipage_file_round_trips_labels_spacing_origin_periodic_axes_and_phases() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("bed.tif");
    let img = image([5, 4, 3]);
    TiffExporter
        .write_defaults(
            &Artifact::PhaseImage(img.clone()),
            &p,
            &Provenance::default(),
        )
        .unwrap();
    // No `spacing` given: the stack's own calibration is used, exactly.
    let back = import(&p, "", "image");
    assert_eq!(back.as_phase_image().unwrap(), &img);
}

#[test]
fn directory_stack_round_trips_and_is_replaced_as_a_whole() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("ct.tiff");
    let img = image([3, 2, 5]);
    let art = Artifact::PhaseImage(img.clone());
    write_tiff(&art, &p, &Provenance::default(), StackLayout::Directory).unwrap();
    let (dir, stem) = slice_directory(&p);
    assert_eq!(dir, d.path().join("ct"));
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        (0..5)
            .map(|z| format!("{stem}_{z:04}.tif"))
            .collect::<Vec<_>>()
    );
    assert_eq!(import(&dir, "", "image").as_phase_image().unwrap(), &img);

    // Rewritten with fewer slices: no slice of the old stack survives.
    let small = image([3, 2, 2]);
    write_tiff(
        &Artifact::PhaseImage(small.clone()),
        &p,
        &Provenance::default(),
        StackLayout::Directory,
    )
    .unwrap();
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 2);
    assert_eq!(import(&dir, "", "image").as_phase_image().unwrap(), &small);
    // Nothing else is left beside it (temporary directories are renamed or removed).
    assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);

    // A directory holding someone else's file is never replaced.
    std::fs::write(dir.join("notes.txt"), "mine").unwrap();
    let e = write_tiff(&art, &p, &Provenance::default(), StackLayout::Directory).unwrap_err();
    assert!(e.contains("notes.txt"), "{e}");
    assert_eq!(std::fs::read(dir.join("notes.txt")).unwrap(), b"mine");
    assert_eq!(import(&dir, "", "image").as_phase_image().unwrap(), &small);
}

#[test]
fn float_field_round_trips_bit_for_bit_and_multi_component_fields_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("t.tif");
    let g = grid([4, 3, 2]);
    let values: Vec<f32> = (0..g.voxel_count())
        .map(|i| (i as f32 - 7.3) * 1.0e-3)
        .collect();
    let f = Field {
        grid: g.clone(),
        name: "temperature".into(),
        unit: "K".into(),
        components: 1,
        convention: ComponentConvention::Plain,
        data: FieldData::F32(values.clone()),
    };
    TiffExporter
        .write_defaults(&Artifact::Field(f), &p, &Provenance::default())
        .unwrap();
    let back = import(&p, ", as: field", "field");
    let back = back.as_field().unwrap();
    assert_eq!(back.grid, g);
    assert_eq!(back.unit, "K");
    match &back.data {
        FieldData::F32(v) => assert_eq!(v, &values),
        other => panic!("read back as {other:?}"),
    }
    let vec3 = Field {
        grid: g.clone(),
        name: "u".into(),
        unit: "m".into(),
        components: 3,
        convention: ComponentConvention::Vector,
        data: FieldData::F64(vec![0.0; 3 * g.voxel_count()]),
    };
    let q = d.path().join("u.tif");
    let e = TiffExporter
        .write_defaults(&Artifact::Field(vec3), &q, &Provenance::default())
        .unwrap_err();
    assert!(e.contains("3 components") && e.contains(".vti"), "{e}");
    assert!(!q.exists());
}

/// What Fiji reads: ImageJ description with `unit=micron`, `spacing=` the z step in µm,
/// resolution tags in pixels per µm. Read here from the raw tags, not through our reader.
#[test]
fn imagej_calibration_is_in_the_tags() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("bed.tif");
    let img = image([5, 4, 3]);
    TiffExporter
        .write_defaults(&Artifact::PhaseImage(img), &p, &Provenance::default())
        .unwrap();
    let mut dec = Decoder::new(std::fs::File::open(&p).unwrap()).unwrap();
    let desc = dec.get_tag_ascii_string(Tag::ImageDescription).unwrap();
    let lines: Vec<&str> = desc.lines().collect();
    assert_eq!(lines[0], "ImageJ=1.11a");
    for want in ["images=3", "slices=3", "unit=micron", "spacing=4e0"] {
        assert!(lines.contains(&want), "{want} missing in {desc}");
    }
    let mut per_um = |t| match dec.get_tag(t).unwrap() {
        Value::Rational(n, d) => n as f64 / d as f64,
        other => panic!("{other:?}"),
    };
    // 1 / 1.5 um and 1 / 2.5 um, to the 1e-9 the rational's denominator allows.
    assert!((per_um(Tag::XResolution) - 1.0 / 1.5).abs() < 1e-9);
    assert!((per_um(Tag::YResolution) - 0.4).abs() < 1e-9);
}

/// A stack calibrated by Fiji (no grainpipe keys) gets its voxel size from the ImageJ
/// description; `spacing` in the pipeline overrides it.
#[test]
fn fiji_calibration_is_read_and_pipeline_spacing_wins() {
    use tiff::encoder::{colortype, Rational, TiffEncoder};
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("fiji.tif");
    let mut enc = TiffEncoder::new(std::fs::File::create(&p).unwrap()).unwrap();
    for z in 0..2u8 {
        let mut im = enc.new_image::<colortype::Gray8>(3, 2).unwrap();
        if z == 0 {
            im.encoder()
                .write_tag(
                    Tag::ImageDescription,
                    "ImageJ=1.54f\nimages=2\nslices=2\nunit=mm\nspacing=0.02\nloop=false\n",
                )
                .unwrap();
        }
        // 50 pixels per mm = 20 um in x, 25 per mm = 40 um in y.
        im.x_resolution(Rational { n: 50, d: 1 });
        im.y_resolution(Rational { n: 25, d: 1 });
        im.write_data(&[z; 6]).unwrap();
    }
    drop(enc);
    let a = import(&p, "", "image");
    let sp = a.as_phase_image().unwrap().grid.spacing;
    let want = [2e-5, 4e-5, 2e-5];
    for k in 0..3 {
        assert!((sp[k] - want[k]).abs() < 1e-18, "{sp:?}");
    }
    let a = import(&p, ", spacing: 1 um", "image");
    assert_eq!(a.as_phase_image().unwrap().grid.spacing, [1e-6; 3]);
}

/// `with: {stack: ...}` reaches the writer through a pipeline, and a wrong value is refused
/// before anything runs, naming the option.
#[test]
fn stack_option_through_a_pipeline() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("l.raw");
    std::fs::write(&raw, [0u8, 1, 2, 3, 4, 5, 6, 7]).unwrap();
    let out = d.path().join("out/slices.tif");
    let yaml = |stack: &str| {
        format!(
            "name: t\nstages:\n  - id: r\n    use: import.raw\n    with: {{path: {:?}, dims: [2, 2, 2], spacing: 3 um}}\n\
             export:\n  - {{ from: r.image, to: {:?}, with: {{ stack: {stack} }} }}\n",
            raw.to_str().unwrap(),
            out.to_str().unwrap()
        )
    };
    run_yaml(&registry(), &yaml("directory")).unwrap();
    let back = import(&d.path().join("out/slices"), "", "image");
    assert_eq!(
        back.as_phase_image().unwrap().labels,
        [0, 1, 2, 3, 4, 5, 6, 7]
    );
    assert_eq!(back.as_phase_image().unwrap().grid.spacing, [3e-6; 3]);
    let e = match run_yaml(&registry(), &yaml("folder")) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("`stack: folder` accepted"),
    };
    assert!(e.contains("stack") && e.contains("directory"), "{e}");
    let mut o = ExportOptions::new();
    o.insert("stack".into(), serde_json::json!("file"));
    assert!(TiffExporter.check_options(&o).is_ok());
}
