//! What users see in the files: compression of HDF5/VTKHDF/NetCDF (sizes against the same
//! file written uncompressed, values read back exactly), `units` on every HDF5 dataset,
//! seeds and integer attributes stored as integers, and the `compression` option as the
//! engine passes it.

use grainpipe_core::registry::ExportOptions;
use grainpipe_core::*;
use grainpipe_formats::hdf5_plain::write_h5_with;
use grainpipe_formats::netcdf_io::write_nc_with;
use grainpipe_formats::vtkhdf::write_vtkhdf_with;
use grainpipe_formats::*;
use std::path::Path;

fn prov() -> Provenance {
    let mut p = Provenance::default();
    // Above 2^53: a float64 or a JSON number in JavaScript would round it.
    p.entries
        .insert("seed".into(), "18446744073709551557".into());
    p.entries.insert("stage_seed".into(), "7".into());
    p.entries.insert("step".into(), "pack.packing".into());
    p
}

/// A 96^3 image of one ball of radius 30 voxels: two phases in large runs, the kind of
/// image deflate shrinks by an order of magnitude.
fn ball_image() -> PhaseImage {
    let n = 96;
    let grid = Grid {
        dims: [n; 3],
        spacing: [2e-6; 3],
        origin: [0.0; 3],
        periodic: [true; 3],
    };
    let c = n as f64 / 2.0;
    let mut labels = Vec::with_capacity(n * n * n);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let d2 = [x, y, z]
                    .map(|i| (i as f64 + 0.5 - c).powi(2))
                    .iter()
                    .sum::<f64>();
                labels.push((d2 < 900.0) as u8);
            }
        }
    }
    PhaseImage {
        grid,
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
    }
}

fn size(p: &Path) -> u64 {
    std::fs::metadata(p).unwrap().len()
}

#[test]
fn compressed_volumes_are_at_least_ten_times_smaller_and_read_back_exactly() {
    let d = tempfile::tempdir().unwrap();
    let img = ball_image();
    let a = Artifact::PhaseImage(img.clone());
    let raw_bytes = img.labels.len() as u64;
    for ext in ["h5", "vtkhdf", "nc"] {
        let off = d.path().join(format!("off.{ext}"));
        let on = d.path().join(format!("on.{ext}"));
        let write = |p: &Path, level: u8| match ext {
            "h5" => write_h5_with(&a, p, &prov(), level),
            "vtkhdf" => write_vtkhdf_with(&a, p, &prov(), level),
            _ => write_nc_with(&a, p, &prov(), level),
        };
        write(&off, 0).unwrap();
        write(&on, 4).unwrap();
        // Uncompressed holds every label byte; compressed must shrink at least tenfold.
        assert!(
            size(&off) >= raw_bytes,
            "{ext}: {} < {raw_bytes}",
            size(&off)
        );
        assert!(
            size(&on) * 10 <= size(&off),
            "{ext}: {} vs {} uncompressed",
            size(&on),
            size(&off)
        );
        let back = match ext {
            "h5" => read_h5(&on).unwrap(),
            "vtkhdf" => {
                Artifact::PhaseImage(read_vtkhdf(&on, None).unwrap().into_phase_image().unwrap())
            }
            _ => Artifact::PhaseImage(
                read_netcdf_variable(&on, "phase")
                    .unwrap()
                    .into_phase_image()
                    .unwrap(),
            ),
        };
        let Artifact::PhaseImage(back) = back else {
            panic!("{ext}: not an image")
        };
        assert_eq!(back.labels, img.labels, "{ext}");
        assert_eq!(back.grid.dims, img.grid.dims, "{ext}");
    }
}

#[test]
fn compressed_dataset_is_chunked_by_whole_slices_with_deflate() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("x.h5");
    write_h5_with(&Artifact::PhaseImage(ball_image()), &p, &prov(), 4).unwrap();
    let f = hdf5_metno::File::open(&p).unwrap();
    let ds = f.dataset("phase").unwrap();
    // 96*96 bytes per slice: 113 slices would fill 1 MiB, clamped to the 96 there are.
    assert_eq!(ds.chunk(), Some(vec![96, 96, 96]));
    let filters = ds.filters();
    assert_eq!(filters, vec![hdf5_metno::filters::Filter::deflate(4)]);
    write_h5_with(&Artifact::PhaseImage(ball_image()), &p, &prov(), 0).unwrap();
    let f = hdf5_metno::File::open(&p).unwrap();
    assert_eq!(f.dataset("phase").unwrap().chunk(), None);
}

#[test]
fn float_fields_get_the_shuffle_filter_before_deflate() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("f.h5");
    let grid = Grid {
        dims: [40, 30, 20],
        spacing: [1e-6; 3],
        origin: [0.0; 3],
        periodic: [false; 3],
    };
    let values: Vec<f64> = (0..grid.voxel_count())
        .map(|i| (i % 97) as f64 * 0.5)
        .collect();
    let field = Field {
        name: "temperature".into(),
        unit: "K".into(),
        grid,
        components: 1,
        convention: ComponentConvention::Plain,
        data: FieldData::F64(values.clone()),
    };
    write_h5_with(&Artifact::Field(field), &p, &prov(), 6).unwrap();
    let f = hdf5_metno::File::open(&p).unwrap();
    let ds = f.dataset("temperature").unwrap();
    assert_eq!(
        ds.filters(),
        vec![
            hdf5_metno::filters::Filter::shuffle(),
            hdf5_metno::filters::Filter::deflate(6)
        ]
    );
    assert_eq!(ds.read_raw::<f64>().unwrap(), values);
}

fn str_attr(loc: &hdf5_metno::Location, name: &str) -> String {
    loc.attr(name)
        .unwrap()
        .read_scalar::<hdf5_metno::types::VarLenUnicode>()
        .unwrap()
        .to_string()
}

fn packing() -> Packing {
    let mut p = Packing::new(Domain::boxed([0.0; 3], [1e-3; 3], [true; 3]));
    p.domain.excluded.push(ExcludedSolid::Sphere {
        center: [5e-4; 3],
        radius: 1e-4,
    });
    for k in 0..300 {
        let mut b = Body::sphere([k as f64 * 3e-6, 1e-4, 2e-4], 2e-5 + k as f64 * 1e-8);
        b.layer = (k / 100) as u32;
        p.bodies.push(b);
    }
    let attr = |unit: &str, values: Vec<f64>| BodyAttribute {
        unit: unit.into(),
        values,
    };
    p.attributes.insert(
        "brick".into(),
        attr("", (0..300).map(|k| (k % 7) as f64).collect()),
    );
    p.attributes.insert(
        "temperature".into(),
        attr("K", (0..300).map(|k| 300.0 + k as f64).collect()),
    );
    // Dimensionless but not integer: stays float.
    p.attributes.insert(
        "damage".into(),
        attr("1", (0..300).map(|k| k as f64 / 300.0).collect()),
    );
    p
}

#[test]
fn h5_packing_has_units_integer_seeds_and_integer_attributes() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("p.h5");
    let pk = packing();
    write_h5_with(&Artifact::Packing(pk.clone()), &path, &prov(), 4).unwrap();
    let f = hdf5_metno::File::open(&path).unwrap();
    assert_eq!(str_attr(&f, "grainpipe_kind"), "Packing");
    // Seeds are u64 attributes holding the exact 64-bit value.
    let seed = f.attr("seed").unwrap();
    assert_eq!(
        seed.dtype().unwrap().to_descriptor().unwrap(),
        hdf5_metno::types::TypeDescriptor::Unsigned(hdf5_metno::types::IntSize::U8)
    );
    assert_eq!(seed.read_scalar::<u64>().unwrap(), 18446744073709551557);
    assert_eq!(
        f.attr("stage_seed").unwrap().read_scalar::<u64>().unwrap(),
        7
    );
    assert_eq!(str_attr(&f, "step"), "pack.packing");
    let want = [
        ("positions", "m"),
        ("radius", "m"),
        ("clump_index", "1"),
        ("orientation", "1"),
        ("layer", "1"),
        ("frozen", "1"),
        ("domain/excluded_spheres", "m"),
        ("attributes/brick", "1"),
        ("attributes/temperature", "K"),
        ("attributes/damage", "1"),
    ];
    for (name, unit) in want {
        assert_eq!(str_attr(&f.dataset(name).unwrap(), "units"), unit, "{name}");
    }
    assert_eq!(str_attr(&f.group("domain").unwrap(), "units"), "m");
    let dtype = |name: &str| {
        f.dataset(name)
            .unwrap()
            .dtype()
            .unwrap()
            .to_descriptor()
            .unwrap()
    };
    use hdf5_metno::types::{FloatSize, IntSize, TypeDescriptor};
    assert_eq!(
        dtype("attributes/brick"),
        TypeDescriptor::Integer(IntSize::U8)
    );
    assert_eq!(
        dtype("attributes/temperature"),
        TypeDescriptor::Float(FloatSize::U8)
    );
    assert_eq!(
        dtype("attributes/damage"),
        TypeDescriptor::Float(FloatSize::U8)
    );
    let brick = f
        .dataset("attributes/brick")
        .unwrap()
        .read_raw::<i64>()
        .unwrap();
    assert_eq!(brick, (0..300).map(|k| k % 7).collect::<Vec<i64>>());
    // And the reader gives back the same packing (dimensionless "1" reads as "").
    let mut expect = pk;
    expect.attributes["damage"].unit.clear();
    assert_eq!(read_h5_packing(&path).unwrap(), expect);
}

#[test]
fn netcdf_seeds_are_uint64_attributes() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("x.nc");
    write_nc_with(&Artifact::PhaseImage(ball_image()), &p, &prov(), 1).unwrap();
    let f = netcdf::open(&p).unwrap();
    match f.attribute("seed").unwrap().value().unwrap() {
        netcdf::AttributeValue::Ulonglong(s) => assert_eq!(s, 18446744073709551557),
        other => panic!("seed stored as {other:?}"),
    }
}

#[test]
fn exporters_declare_and_check_their_options() {
    let mut r = Registry::new();
    register(&mut r);
    let opts = |pairs: &[(&str, serde_json::Value)]| -> ExportOptions {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.clone()))
            .collect()
    };
    for name in ["h5", "vtkhdf", "nc"] {
        let e = r
            .exporter_for(Some(name), Path::new("x"), ArtifactKind::PhaseImage)
            .unwrap_or_else(|| panic!("{name}"));
        let declared = e.options();
        assert_eq!(declared.len(), 1, "{name}");
        assert_eq!(declared[0].name, "compression");
        assert_eq!(declared[0].default, serde_json::json!(4));
        assert!(e
            .check_options(&opts(&[("compression", serde_json::json!(0))]))
            .is_ok());
        for bad in [
            serde_json::json!(10),
            serde_json::json!("fast"),
            serde_json::json!(-1),
        ] {
            let (key, msg) = e
                .check_options(&opts(&[("compression", bad.clone())]))
                .unwrap_err();
            assert_eq!(key, "compression");
            assert!(msg.contains("0 (off) to 9"), "{msg}");
        }
    }
    let vtp = r
        .exporter_for(Some("vtp"), Path::new("x"), ArtifactKind::Packing)
        .unwrap();
    assert_eq!(vtp.options()[0].default, serde_json::json!("as_is"));
    let (key, msg) = vtp
        .check_options(&opts(&[("periodic", serde_json::json!("fold"))]))
        .unwrap_err();
    assert_eq!(key, "periodic");
    assert!(msg.contains("as_is, wrap, clip"), "{msg}");
    // The engine's path: write_with with `compression: 0` gives the uncompressed size.
    let d = tempfile::tempdir().unwrap();
    let a = Artifact::PhaseImage(ball_image());
    let h5 = r
        .exporter_for(Some("h5"), Path::new("x"), a.kind())
        .unwrap();
    let (p0, p4) = (d.path().join("0.h5"), d.path().join("4.h5"));
    h5.write(
        &a,
        &p0,
        &prov(),
        &opts(&[("compression", serde_json::json!(0))]),
    )
    .unwrap();
    h5.write_defaults(&a, &p4, &prov()).unwrap();
    assert!(size(&p0) >= 96 * 96 * 96 && size(&p4) * 10 <= size(&p0));
}
