//! TIFF stacks: a multi-page file and a directory of slices read back voxel for voxel, and
//! broken stacks refused before running.

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{Inputs, RunContext, StageError, TypedStage};
use grainpipe_formats::import::{ImportAs, ImportOptions, ImportTiff, Lengths3, TiffParams};
use grainpipe_formats::tiff_io::{read_tiff, tiff_header};
use std::path::Path;
use tiff::encoder::{colortype, TiffEncoder};

/// Label of voxel (x, y, z): distinct per voxel within 8 bits for the small stack below.
fn label(x: usize, y: usize, z: usize) -> u8 {
    (x + 5 * y + 20 * z) as u8
}

fn write_multipage(path: &Path, dims: [usize; 3]) {
    let mut enc = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
    for z in 0..dims[2] {
        let page: Vec<u8> = (0..dims[1])
            .flat_map(|y| (0..dims[0]).map(move |x| label(x, y, z)))
            .collect();
        enc.write_image::<colortype::Gray8>(dims[0] as u32, dims[1] as u32, &page)
            .unwrap();
    }
}

#[test]
fn multipage_tiff_reads_back_every_voxel() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("stack.tif");
    write_multipage(&f, [5, 4, 3]);
    let probe = tiff_header(&f).unwrap().probe;
    assert_eq!(probe.dims, [5, 4, 3]);
    let params = TiffParams {
        path: f.to_str().unwrap().into(),
        spacing: Some(Lengths3::One(grainpipe_core::units::Q::new(4e-6))),
        ..Default::default()
    };
    let plan = ImportTiff
        .preflight(&params, &Default::default())
        .unwrap()
        .plan;
    let out = ImportTiff
        .run(
            &params,
            &plan,
            &Inputs::new(),
            &RunContext::new(0, &SilentReporter),
        )
        .unwrap();
    let img = out["image"].as_phase_image().unwrap();
    assert_eq!(img.grid.dims, [5, 4, 3]);
    assert_eq!(img.grid.spacing, [4e-6; 3]);
    for z in 0..3 {
        for y in 0..4 {
            for x in 0..5 {
                assert_eq!(img.labels[img.grid.index(x, y, z)], label(x, y, z));
            }
        }
    }
}

#[test]
fn directory_of_16_bit_slices_in_name_order() {
    let dir = tempfile::tempdir().unwrap();
    // Written out of order: the file names, not creation order, give z.
    for z in [2usize, 0, 1] {
        let page: Vec<u16> = (0..6).map(|i| (1000 * z + i) as u16).collect();
        let mut enc = TiffEncoder::new(
            std::fs::File::create(dir.path().join(format!("slice_{z:03}.tiff"))).unwrap(),
        )
        .unwrap();
        enc.write_image::<colortype::Gray16>(3, 2, &page).unwrap();
    }
    let v = read_tiff(dir.path()).unwrap();
    assert_eq!(v.dims, [3, 2, 3]);
    for z in 0..3 {
        for i in 0..6 {
            assert_eq!(v.data.get(z * 6 + i), (1000 * z + i) as f64);
        }
    }
    // Values above 255 cannot be labels: `as: phase_image` fails, `as: field` works.
    let mut p = TiffParams {
        path: dir.path().to_str().unwrap().into(),
        spacing: Some(Lengths3::One(grainpipe_core::units::Q::new(1e-6))),
        options: ImportOptions {
            as_: ImportAs::Field,
            ..Default::default()
        },
    };
    let ctx = RunContext::new(0, &SilentReporter);
    let plan = ImportTiff.preflight(&p, &Default::default()).unwrap().plan;
    let out = ImportTiff.run(&p, &plan, &Inputs::new(), &ctx).unwrap();
    assert_eq!(out["field"].as_field().unwrap().data.get(17), 2005.0);
    p.options.as_ = ImportAs::PhaseImage;
    let plan = ImportTiff.preflight(&p, &Default::default()).unwrap().plan;
    assert!(matches!(
        ImportTiff.run(&p, &plan, &Inputs::new(), &ctx),
        Err(StageError::Failed(_))
    ));
}

#[test]
fn broken_stacks_are_refused_in_preflight() {
    let dir = tempfile::tempdir().unwrap();
    let spacing = Some(Lengths3::One(grainpipe_core::units::Q::new(1e-6)));
    // Slices of different sizes.
    write_multipage(&dir.path().join("a.tif"), [4, 4, 1]);
    write_multipage(&dir.path().join("b.tif"), [5, 4, 1]);
    let p = TiffParams {
        path: dir.path().to_str().unwrap().into(),
        spacing,
        ..Default::default()
    };
    match ImportTiff.preflight(&p, &Default::default()) {
        Err(StageError::InvalidParam { key, message }) => {
            assert_eq!(key, "path");
            assert!(message.contains("differs from the first page"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    // Not a TIFF at all.
    let junk = dir.path().join("junk.tif");
    std::fs::write(&junk, b"not a tiff").unwrap();
    let p = TiffParams {
        path: junk.to_str().unwrap().into(),
        spacing,
        ..Default::default()
    };
    assert!(matches!(
        ImportTiff.preflight(&p, &Default::default()),
        Err(StageError::InvalidParam { .. })
    ));
    // No voxel size: a stack without calibration and no `spacing`.
    let bare = dir.path().join("bare.tif");
    write_multipage(&bare, [4, 4, 2]);
    let p = TiffParams {
        path: bare.to_str().unwrap().into(),
        ..Default::default()
    };
    assert!(
        matches!(ImportTiff.preflight(&p, &Default::default()), Err(StageError::InvalidParam { key, .. }) if key == "spacing")
    );
}

/// Preflight knows the grid: a stack imported through the engine (which holds every output
/// to its announcement) lands on exactly the grid its preflight announced, for a multi-page
/// file and for a directory of slices.
#[test]
fn tiff_import_announces_its_grid() {
    use grainpipe_core::testing::run_yaml;
    use grainpipe_core::{InputMetas, Registry};
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("stack.tif");
    write_multipage(&file, [5, 4, 3]);
    let slices = dir.path().join("slices");
    std::fs::create_dir(&slices).unwrap();
    for z in 0..2 {
        write_multipage(&slices.join(format!("s{z}.tif")), [3, 2, 1]);
    }
    let mut reg = Registry::new();
    grainpipe_formats::register(&mut reg);
    for (path, dims) in [(&file, [5, 4, 3]), (&slices, [3, 2, 2])] {
        let with = serde_json::json!({"path": path, "spacing": ["4 um", "4 um", "10 um"], "origin": [0, "1 mm", 0]});
        let st = reg.stage("import.tiff").unwrap().stage.clone();
        let (pf, _) = st
            .preflight(&st.normalize_params(&with).unwrap(), &InputMetas::new())
            .unwrap();
        let announced = pf.outputs["image"].grid.clone().unwrap();
        assert_eq!(announced.dims, dims);
        let yaml =
            format!("name: t\nstages:\n  - id: tif\n    use: import.tiff\n    with: {with}\n");
        let res = run_yaml(&reg, &yaml).unwrap();
        let img = res.artifact("tif.image").as_phase_image().unwrap();
        assert_eq!(img.grid, announced);
        assert_eq!(img.grid.origin, [0.0, 1e-3, 0.0]);
    }
}

/// Issue 35: slices numbered without padding (s1, s2, s10) are read in natural order, not
/// plain name order (which put s10 before s2).
#[test]
fn directory_slices_numbered_without_padding_are_read_in_natural_order() {
    let dir = tempfile::tempdir().unwrap();
    for z in [10usize, 2, 1, 0, 9] {
        let page = vec![z as u8; 4];
        let mut enc =
            TiffEncoder::new(std::fs::File::create(dir.path().join(format!("s{z}.tif"))).unwrap())
                .unwrap();
        enc.write_image::<colortype::Gray8>(2, 2, &page).unwrap();
    }
    let v = read_tiff(dir.path()).unwrap();
    let order: Vec<f64> = (0..5).map(|z| v.data.get(4 * z)).collect();
    assert_eq!(order, [0.0, 1.0, 2.0, 9.0, 10.0]);
    use grainpipe_formats::tiff_io::natural_cmp;
    assert!(natural_cmp("ct_2.tif", "ct_10.tif").is_lt());
    assert!(natural_cmp("a10b2", "a10b10").is_lt());
    assert!(natural_cmp("ct_0002.tif", "ct_10.tif").is_lt());
}

/// Issue 35: the description of a TIFF export holds the pipeline's YAML, which may hold
/// "µm"; TIFF ASCII tags hold 7-bit text, so it is escaped, and read back exactly.
#[test]
fn non_ascii_provenance_is_escaped_in_the_description_and_read_back() {
    use grainpipe_formats::tiff_io::{ascii_escape, ascii_unescape};
    for s in ["5 µm", "a\\u{b5}b", "tab\there", "∅ — 😀", "plain\nlines\\"] {
        let e = ascii_escape(s);
        assert!(
            e.bytes().all(|b| b == b'\n' || (b' '..=b'~').contains(&b)),
            "{e}"
        );
        assert_eq!(ascii_unescape(&e), s);
    }
    let dir = tempfile::tempdir().unwrap();
    let img = grainpipe_core::Artifact::PhaseImage(grainpipe_core::PhaseImage {
        grid: grainpipe_core::Grid {
            dims: [3, 2, 2],
            spacing: [2e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
        labels: vec![0, 1, 1, 0, 1, 1, 0, 0, 1, 1, 1, 0],
        phases: vec![
            grainpipe_core::Phase {
                id: 0,
                name: "pore".into(),
            },
            grainpipe_core::Phase {
                id: 1,
                name: "grain µ".into(),
            },
        ],
    });
    let mut prov = grainpipe_core::Provenance::default();
    prov.entries
        .insert("pipeline_yaml".into(), "# 5 µm voxels\nname: t\n".into());
    let p = dir.path().join("a.tif");
    for layout in [
        grainpipe_formats::tiff_io::StackLayout::File,
        grainpipe_formats::tiff_io::StackLayout::Directory,
    ] {
        grainpipe_formats::tiff_io::write_tiff(&img, &p, &prov, layout).unwrap();
    }
    let v = read_tiff(&p).unwrap();
    assert_eq!(v.spacing, Some([2e-6; 3]));
    assert_eq!(v.phases[1].name, "grain µ");
}
