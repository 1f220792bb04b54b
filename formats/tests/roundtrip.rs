//! Round trips for every writer/reader pair, readers of files written by others (VTK
//! variants, CF NetCDF, raw), atomic writes, and the import stages.
//!
//! Values are compared exactly: every format stores doubles in binary or as shortest
//! round-trip text, so any difference is a bug, not roundoff.

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::*;
use grainpipe_formats::import::*;
use grainpipe_formats::*;
use std::path::Path;

fn prov() -> Provenance {
    let mut p = Provenance::default();
    p.entries.insert("seed".into(), "7".into());
    p.entries
        .insert("pipeline".into(), "name: t\nstages: []\n".into());
    p
}

fn grid(dims: [usize; 3]) -> Grid {
    Grid {
        dims,
        spacing: [1.5e-6, 2.5e-6, 4e-6],
        origin: [-1e-4, 3e-5, 7.25e-3],
        periodic: [false, true, true],
    }
}

/// Labels x + 2y + 3z mod 4 (every axis matters) with phases 0..3.
fn image(dims: [usize; 3]) -> PhaseImage {
    let g = grid(dims);
    let mut labels = vec![0; g.voxel_count()];
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                labels[g.index(x, y, z)] = ((x + 2 * y + 3 * z) % 4) as u8;
            }
        }
    }
    PhaseImage {
        grid: g,
        labels,
        phases: ["pore", "grain A", "grain B", "binder & glue <x>"]
            .iter()
            .enumerate()
            .map(|(i, n)| Phase {
                id: i as u8,
                name: n.to_string(),
            })
            .collect(),
    }
}

fn field(dims: [usize; 3], components: usize, f32: bool) -> Field {
    let g = grid(dims);
    let n = g.voxel_count() * components;
    let v: Vec<f64> = (0..n).map(|i| i as f64 * 0.125 - 3.0).collect();
    Field {
        grid: g,
        name: "temperature".into(),
        unit: "K".into(),
        components,
        // Three components are a vector, so every format must carry the convention through.
        convention: if components == 3 {
            ComponentConvention::Vector
        } else {
            ComponentConvention::Plain
        },
        data: if f32 {
            FieldData::F32(v.iter().map(|&x| x as f32).collect())
        } else {
            FieldData::F64(v)
        },
    }
}

fn packing() -> Packing {
    let mut p = Packing::new(Domain {
        min: [0.0; 3],
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
        "peak temperature / K".into(),
        BodyAttribute {
            unit: "K".into(),
            values: vec![300.0, 1700.5],
        },
    );
    p
}

fn graph() -> ContactGraph {
    ContactGraph {
        contacts: vec![
            Contact {
                i: 0,
                j: 1,
                gap: -2.5e-8,
            },
            Contact {
                i: 2,
                j: 1,
                gap: 1e-9,
            },
        ],
        faces: [vec![0], vec![], vec![1, 2], vec![], vec![], vec![2]],
        bonds: vec![[0, 1], [0, 2]],
        bond_attributes: [
            (
                "neck/radius".to_string(),
                BodyAttribute {
                    unit: "m".into(),
                    values: vec![1e-6, 2e-6],
                },
            ),
            (
                "damage".to_string(),
                BodyAttribute {
                    unit: String::new(),
                    values: vec![0.0, 1.0],
                },
            ),
        ]
        .into_iter()
        .collect(),
        positions: vec![[0.0, 0.0, 0.0], [1e-4, 0.0, 0.0], [0.0, 1e-4, 2e-4]],
        radii: vec![5e-5, 4e-5, 3e-5],
    }
}

fn table() -> Table {
    Table::new("stats")
        .with_f64("d50", "m", vec![1.25e-5, 3e-5, 0.0])
        .with_i64("count", "", vec![3, -4, 1000])
        .with_str("label", vec!["a".into(), "b, \"c\"".into(), "".into()])
        .with_f64("a/b", "1", vec![0.5, 1.0, 1e300])
}

fn tensor() -> Tensor {
    Tensor {
        name: "permeability".into(),
        unit: "m^2".into(),
        shape: vec![3, 3],
        values: (0..9).map(|i| 1e-12 * (i as f64 + 1.0)).collect(),
        convention: TensorConvention::Voigt,
    }
}

/// `a` with every table unit "1" written as "": how dimensionless columns read back from
/// HDF5 (table() has one of each spelling).
fn dimensionless_as_empty(a: &Artifact) -> Artifact {
    match a {
        Artifact::Table(t) => {
            let mut t = t.clone();
            for c in &mut t.columns {
                if c.unit == "1" {
                    c.unit.clear();
                }
            }
            Artifact::Table(t)
        }
        Artifact::Series(s) => Artifact::Series(Series {
            frames: s
                .frames
                .iter()
                .map(|(t, f)| (*t, dimensionless_as_empty(f)))
                .collect(),
        }),
        Artifact::Collection(c) => Artifact::Collection(Collection {
            items: c
                .items
                .iter()
                .map(|(n, i)| (n.clone(), dimensionless_as_empty(i)))
                .collect(),
        }),
        other => other.clone(),
    }
}

fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

// ------------------------------------------------------------------------- volumes

#[test]
fn vti_round_trip_phase_image_and_fields() {
    let d = tmp();
    let img = image([5, 4, 3]);
    let p = d.path().join("a.vti");
    write_vti(&Artifact::PhaseImage(img.clone()), &p, &prov()).unwrap();
    let back = read_vti(&p, None).unwrap();
    assert_eq!(back.into_phase_image().unwrap(), img);
    for f32 in [false, true] {
        let f = field([3, 2, 4], 3, f32);
        write_vti(&Artifact::Field(f.clone()), &p, &prov()).unwrap();
        assert_eq!(read_vti(&p, None).unwrap().into_field().unwrap(), f);
    }
}

#[test]
fn vti_of_a_large_image_spans_several_zlib_blocks() {
    // 40^3 bytes = 64000 > two 32 KiB blocks, with a partial last block
    let d = tmp();
    let img = image([40, 40, 40]);
    let p = d.path().join("big.vti");
    write_vti(&Artifact::PhaseImage(img.clone()), &p, &prov()).unwrap();
    assert_eq!(
        read_vti(&p, Some("phase"))
            .unwrap()
            .into_phase_image()
            .unwrap(),
        img
    );
}

/// A 2x2x1 image as VTK writes it in its other encodings; all must read to the same values.
#[test]
fn vti_reader_takes_ascii_uncompressed_and_appended_files() {
    use base64::Engine;
    let b64 = base64::engine::general_purpose::STANDARD;
    let values: [f32; 4] = [1.0, 2.5, -3.0, 4.0];
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let head = |extra: &str| {
        format!(
            "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"0.1\" \
             byte_order=\"LittleEndian\" header_type=\"UInt32\"{extra}>\n\
             <ImageData WholeExtent=\"0 2 0 2 0 1\" Origin=\"0.5 0 0\" Spacing=\"0.1 0.2 0.3\">\n\
             <Piece Extent=\"0 2 0 2 0 1\"><CellData Scalars=\"s\">\n"
        )
    };
    let tail = "</CellData></Piece>\n</ImageData>\n";
    let ascii = format!(
        "{}<DataArray type=\"Float32\" Name=\"s\" format=\"ascii\">1 2.5 -3 4</DataArray>\n{tail}</VTKFile>\n",
        head("")
    );
    let mut joint = (bytes.len() as u32).to_le_bytes().to_vec();
    joint.extend_from_slice(&bytes);
    let binary = format!(
        "{}<DataArray type=\"Float32\" Name=\"s\" format=\"binary\">\n  {}\n</DataArray>\n{tail}</VTKFile>\n",
        head(""),
        b64.encode(&joint)
    );
    let mut appended = format!(
        "{}<DataArray type=\"Float32\" Name=\"s\" format=\"appended\" offset=\"0\"/>\n{tail}\
         <AppendedData encoding=\"raw\">\n   _",
        head("")
    )
    .into_bytes();
    appended.extend_from_slice(&joint);
    appended.extend_from_slice(b"\n</AppendedData>\n</VTKFile>\n");
    let d = tmp();
    for (name, content) in [
        ("ascii.vti", ascii.into_bytes()),
        ("binary.vti", binary.into_bytes()),
        ("appended.vti", appended),
    ] {
        let p = d.path().join(name);
        std::fs::write(&p, content).unwrap();
        let v = read_vti(&p, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(v.dims, [2, 2, 1], "{name}");
        assert_eq!(v.data, VolumeData::F32(values.to_vec()), "{name}");
        assert_eq!(v.spacing, Some([0.1, 0.2, 0.3]), "{name}");
        assert_eq!(v.origin, Some([0.5, 0.0, 0.0]), "{name}");
    }
}

#[test]
fn vti_point_data_is_read_as_voxel_centres() {
    // 3x2x1 points -> 3x2x1 voxels centred on the points: corner = point origin - spacing/2
    let d = tmp();
    let p = d.path().join("points.vti");
    std::fs::write(
        &p,
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"1.0\">\n\
         <ImageData WholeExtent=\"0 2 0 1 0 0\" Origin=\"1 2 3\" Spacing=\"0.5 0.25 1\">\n\
         <Piece Extent=\"0 2 0 1 0 0\"><PointData Scalars=\"l\">\n\
         <DataArray type=\"UInt8\" Name=\"l\" format=\"ascii\">0 1 2 3 4 5</DataArray>\n\
         </PointData><CellData></CellData></Piece></ImageData></VTKFile>\n",
    )
    .unwrap();
    let v = read_vti(&p, None).unwrap();
    assert_eq!(v.dims, [3, 2, 1]);
    assert_eq!(v.origin, Some([0.75, 1.875, 2.5]));
    assert_eq!(v.data, VolumeData::U8(vec![0, 1, 2, 3, 4, 5]));
}

#[test]
fn vtkhdf_round_trip() {
    let d = tmp();
    let p = d.path().join("a.vtkhdf");
    let img = image([4, 3, 2]);
    write_vtkhdf(&Artifact::PhaseImage(img.clone()), &p, &prov()).unwrap();
    assert_eq!(
        read_vtkhdf(&p, None).unwrap().into_phase_image().unwrap(),
        img
    );
    let f = field([2, 3, 4], 2, true);
    write_vtkhdf(&Artifact::Field(f.clone()), &p, &prov()).unwrap();
    assert_eq!(read_vtkhdf(&p, None).unwrap().into_field().unwrap(), f);
}

#[test]
fn hdf5_round_trip_volumes_and_dataset_reader() {
    let d = tmp();
    let p = d.path().join("a.h5");
    let img = image([6, 5, 4]);
    write_h5(&Artifact::PhaseImage(img.clone()), &p, &prov()).unwrap();
    assert_eq!(read_h5(&p).unwrap(), Artifact::PhaseImage(img.clone()));
    let v = read_hdf5_dataset(&p, "phase").unwrap();
    assert_eq!(v.dims, [6, 5, 4]);
    assert_eq!(v.phases, img.phases);
    let f = field([3, 4, 2], 3, false);
    write_h5(&Artifact::Field(f.clone()), &p, &prov()).unwrap();
    assert_eq!(read_h5(&p).unwrap(), Artifact::Field(f.clone()));
    let v = read_hdf5_dataset(&p, "temperature").unwrap();
    assert_eq!((v.dims, v.components, v.unit.as_str()), ([3, 4, 2], 3, "K"));
}

#[test]
fn netcdf_round_trip() {
    let d = tmp();
    let p = d.path().join("a.nc");
    let img = image([5, 3, 2]);
    write_nc(&Artifact::PhaseImage(img.clone()), &p, &prov()).unwrap();
    assert_eq!(
        read_netcdf_variable(&p, "phase")
            .unwrap()
            .into_phase_image()
            .unwrap(),
        img
    );
    for comps in [1, 3] {
        let f = field([4, 3, 2], comps, comps == 1);
        write_nc(&Artifact::Field(f.clone()), &p, &prov()).unwrap();
        assert_eq!(
            read_netcdf_variable(&p, "temperature")
                .unwrap()
                .into_field()
                .unwrap(),
            f
        );
    }
}

/// A CF file from elsewhere: no grainpipe attributes, coordinates in micrometres.
#[test]
fn netcdf_grid_from_cf_coordinates_in_other_units() {
    let d = tmp();
    let p = d.path().join("cf.nc");
    {
        let mut f = netcdf::create(&p).unwrap();
        for (n, l) in [("z", 2), ("y", 3), ("x", 4)] {
            f.add_dimension(n, l).unwrap();
        }
        for (n, l, s, o) in [("x", 4, 2.0, 10.0), ("y", 3, 3.0, 0.0), ("z", 2, 5.0, -5.0)] {
            let mut v = f.add_variable::<f64>(n, &[n]).unwrap();
            v.put_attribute("units", "um").unwrap();
            let c: Vec<f64> = (0..l).map(|i| o + s * i as f64).collect();
            v.put_values(&c, ..).unwrap();
        }
        let mut v = f.add_variable::<i16>("labels", &["z", "y", "x"]).unwrap();
        v.put_values(&(0..24).map(|i| (i % 3) as i16).collect::<Vec<_>>(), ..)
            .unwrap();
    }
    let v = read_netcdf_variable(&p, "labels").unwrap();
    let s = v.spacing.unwrap();
    let o = v.origin.unwrap();
    // centres o + i s in um -> corner (o - s/2) um; 1e-12 relative covers the um->m factor
    for (a, (ws, wo)) in [(2.0, 9.0), (3.0, -1.5), (5.0, -7.5)].iter().enumerate() {
        assert!((s[a] - ws * 1e-6).abs() < 1e-18, "spacing {s:?}");
        assert!((o[a] - wo * 1e-6).abs() < 1e-18, "origin {o:?}");
    }
    let img = v.into_phase_image().unwrap();
    assert_eq!(img.labels.iter().filter(|&&l| l == 2).count(), 8);
}

#[test]
fn raw_reader_handles_types_byte_order_and_header() {
    let d = tmp();
    let p = d.path().join("v.raw");
    let values: Vec<u16> = (0..24).map(|i| 1000 + 7 * i).collect();
    let mut bytes = vec![0xAB; 16];
    bytes.extend(values.iter().flat_map(|v| v.to_be_bytes()));
    std::fs::write(&p, &bytes).unwrap();
    let layout = RawLayout {
        dims: [4, 3, 2],
        dtype: RawDtype::U16,
        endian: Endian::Big,
        header_bytes: 16,
    };
    let v = read_raw(&p, &layout, [1e-6; 3], [0.0; 3]).unwrap();
    assert_eq!(v.data, VolumeData::U16(values));
    // a wrong layout is refused with the file name and both sizes
    let bad = RawLayout {
        header_bytes: 0,
        ..layout
    };
    let e = read_raw(&p, &bad, [1e-6; 3], [0.0; 3]).unwrap_err();
    assert!(
        e.contains("v.raw") && e.contains("64 bytes") && e.contains("48"),
        "{e}"
    );
}

// ------------------------------------------------------------------------- other kinds

#[test]
fn hdf5_round_trip_every_other_kind() {
    let d = tmp();
    let p = d.path().join("x.h5");
    let series = Series {
        frames: vec![
            (0.0, Artifact::Table(table())),
            (
                2.5,
                Artifact::Table(table().with_f64("extra", "s", vec![1.0; 3])),
            ),
        ],
    };
    let lib = packing().library.unwrap();
    // Item names need not sort like their order: the order is kept, not re-sorted by name.
    let collection = Collection {
        items: vec![
            ("zeta".into(), Artifact::Packing(packing())),
            ("alpha".into(), Artifact::ContactGraph(graph())),
        ],
    };
    for a in [
        Artifact::Packing(packing()),
        Artifact::ContactGraph(graph()),
        Artifact::Table(table()),
        Artifact::Tensor(tensor()),
        Artifact::ClumpLibrary(lib),
        Artifact::Series(series),
        Artifact::Collection(collection),
    ] {
        write_h5(&a, &p, &prov()).unwrap();
        // HDF5 spells dimensionless "1"; it reads back as the model's "".
        assert_eq!(
            read_h5(&p).unwrap(),
            dimensionless_as_empty(&a),
            "{}",
            a.kind()
        );
    }
    assert!(read_h5_packing(&p).unwrap_err().contains("Collection"));
}

#[test]
fn pvd_of_a_collection_names_its_parts_and_refuses_mixed_kinds() {
    let d = tmp();
    let p = d.path().join("grains.pvd");
    let two = Collection {
        items: vec![
            ("a".into(), Artifact::Packing(packing())),
            ("b".into(), Artifact::Packing(packing())),
        ],
    };
    write_pvd(&Artifact::Collection(two), &p, &prov()).unwrap();
    let text = std::fs::read_to_string(&p).unwrap();
    // frames live in a fresh folder `grains_frames_<tag>/` (a series is replaced as a set)
    let folder = text
        .split("file=\"")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .unwrap()
        .to_string();
    assert!(folder.starts_with("grains_frames_"), "{text}");
    assert!(
        text.contains(&format!(
            "part=\"0\" name=\"a\" file=\"{folder}/grains_0000.vtp\""
        )),
        "{text}"
    );
    assert!(
        text.contains(&format!(
            "part=\"1\" name=\"b\" file=\"{folder}/grains_0001.vtp\""
        )),
        "{text}"
    );
    assert!(d.path().join(&folder).join("grains_0001.vtp").is_file());
    let mixed = Collection {
        items: vec![
            ("a".into(), Artifact::Packing(packing())),
            ("b".into(), Artifact::Table(table())),
        ],
    };
    let e = write_pvd(
        &Artifact::Collection(mixed),
        &d.path().join("m.pvd"),
        &prov(),
    )
    .unwrap_err();
    assert!(e.contains("mixes Packing and Table"), "{e}");
}

#[test]
fn csv_and_json_round_trips() {
    let d = tmp();
    let p = d.path().join("t.csv");
    write_csv(&Artifact::Table(table()), &p, &prov()).unwrap();
    let mut back = read_table_csv(&p).unwrap();
    back.name = "stats".into();
    assert_eq!(back, table());
    let p = d.path().join("t.json");
    write_json(&Artifact::Table(table()), &p, &prov()).unwrap();
    assert_eq!(read_table_json(&p).unwrap(), table());
    write_json(&Artifact::Tensor(tensor()), &p, &prov()).unwrap();
    assert_eq!(read_tensor_json(&p).unwrap(), tensor());
    write_json(&Artifact::ContactGraph(graph()), &p, &prov()).unwrap();
    assert_eq!(read_contact_graph_json(&p).unwrap(), graph());
    let text = std::fs::read_to_string(&p).unwrap();
    assert!(text.contains("\"seed\": \"7\""), "provenance missing");
}

#[test]
fn tensor_and_graph_csv_layout() {
    let d = tmp();
    let p = d.path().join("k.csv");
    write_csv(&Artifact::Tensor(tensor()), &p, &prov()).unwrap();
    let text = std::fs::read_to_string(&p).unwrap();
    // One header row, then the matrix rows: nothing a plain CSV reader would misparse.
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 4);
    assert_eq!(lines[0], "x [m^2],y [m^2],z [m^2]");
    let row1: Vec<f64> = lines[2].split(',').map(|x| x.parse().unwrap()).collect();
    assert_eq!(row1, tensor().values[3..6]);
    // Name, convention, shape and provenance in the sidecar.
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.path().join("k.csv.json")).unwrap())
            .unwrap();
    assert_eq!(side["kind"], "Tensor");
    assert_eq!(side["name"], "permeability");
    assert_eq!(side["convention"], "Voigt");
    assert_eq!(side["shape"], serde_json::json!([3, 3]));
    assert_eq!(side["csv"], "k.csv");
    assert_eq!(side["provenance"]["seed"], "7");
    assert_eq!(side["provenance"]["pipeline"], "name: t\nstages: []\n");
    write_csv(&Artifact::ContactGraph(graph()), &p, &prov()).unwrap();
    assert_eq!(
        std::fs::read_to_string(&p).unwrap(),
        // Bond attributes follow, empty on the unbonded contact (2, 1).
        "i [1],j [1],gap [m],bonded [1],neck/radius [m],damage [1]\n0,1,-2.5e-8,1,1e-6,0\n\
         2,1,1e-9,0,,\n0,2,,1,2e-6,1\n"
    );
}

#[test]
fn csv_headers_follow_one_convention_and_the_sidecar_restores_exact_units() {
    let d = tmp();
    let p = d.path().join("t.csv");
    write_csv(&Artifact::Table(table()), &p, &prov()).unwrap();
    let text = std::fs::read_to_string(&p).unwrap();
    // `count` has unit "" and `a/b` unit "1": both dimensionless, both `[1]`; text bare.
    assert_eq!(
        text.lines().next().unwrap(),
        "d50 [m],count [1],label,a/b [1]"
    );
    assert!(!text.contains('#'), "no comment lines: {text}");
    // Without the sidecar the header is all there is: both dimensionless spellings read "1".
    std::fs::remove_file(d.path().join("t.csv.json")).unwrap();
    let back = read_table_csv(&p).unwrap();
    let units: Vec<&str> = back.columns.iter().map(|c| c.unit.as_str()).collect();
    assert_eq!(units, ["m", "1", "", "1"]);
    assert_eq!(back.name, "t");
}

// ------------------------------------------------------------------------- atomicity

#[test]
fn failed_write_leaves_no_file() {
    let d = tmp();
    // The name check happens inside the HDF5 writer, after the temporary file exists.
    let mut f = field([2, 2, 2], 1, false);
    f.name = "bad/name".into();
    for name in ["f.h5", "f.vtkhdf"] {
        let p = d.path().join(name);
        let e = write_via_registry(&Artifact::Field(f.clone()), &p).unwrap_err();
        assert!(e.contains("bad/name"), "{e}");
        assert!(!p.exists());
    }
    // A packing whose attribute is too short fails half-way through the HDF5 file.
    let mut pk = packing();
    pk.attributes.get_index_mut(0).unwrap().1.values.pop();
    let e = write_via_registry(&Artifact::Packing(pk), &d.path().join("p.h5")).unwrap_err();
    assert!(e.contains("1 values for 2 bodies"), "{e}");
    // An existing good file survives a failed overwrite.
    let good = d.path().join("g.h5");
    write_via_registry(&Artifact::Table(table()), &good).unwrap();
    let before = std::fs::read(&good).unwrap();
    assert!(write_via_registry(&Artifact::Field(f), &good).is_err());
    assert_eq!(std::fs::read(&good).unwrap(), before);
    let left: Vec<_> = std::fs::read_dir(d.path()).unwrap().collect();
    assert_eq!(left.len(), 1, "temporary files left behind: {left:?}");
}

fn write_via_registry(a: &Artifact, p: &Path) -> Result<(), String> {
    let mut r = Registry::new();
    register(&mut r);
    r.exporter_for(None, p, a.kind())
        .expect("exporter")
        .write_defaults(a, p, &prov())
}

#[test]
fn registry_has_every_exporter_and_consistent_stages() {
    let mut r = Registry::new();
    register(&mut r);
    r.check_consistency().unwrap();
    for (ext, kind) in [
        ("vti", ArtifactKind::PhaseImage),
        ("vtp", ArtifactKind::Packing),
        ("pvd", ArtifactKind::Series),
        ("vtkhdf", ArtifactKind::Field),
        ("hdf5", ArtifactKind::ClumpLibrary),
        ("nc", ArtifactKind::Field),
        ("csv", ArtifactKind::Tensor),
        ("json", ArtifactKind::ContactGraph),
    ] {
        let e = r
            .exporter_for(None, Path::new(&format!("x.{ext}")), kind)
            .unwrap_or_else(|| panic!("no exporter for .{ext}"));
        assert!(e.accepts(kind), "{ext} should take {kind}");
    }
    for id in ["import.raw", "import.hdf5", "import.netcdf", "import.vti"] {
        assert!(r.stage(id).is_some(), "{id}");
    }
}

// ------------------------------------------------------------------------- import stages

fn ctx() -> RunContext<'static> {
    RunContext::new(1, &SilentReporter)
}

#[test]
fn import_raw_preflight_checks_size_and_run_gives_labels() {
    let d = tmp();
    let p = d.path().join("labels.raw");
    let img = image([4, 3, 2]);
    std::fs::write(&p, &img.labels).unwrap();
    let mut params = RawParams {
        path: p.display().to_string(),
        dims: [4, 3, 2],
        spacing: Some(Lengths3::Three(grid([1; 3]).spacing.map(units::Q::new))),
        options: ImportOptions {
            origin: Some(Lengths3::Three(grid([1; 3]).origin.map(units::Q::new))),
            ..ImportOptions::default()
        },
        ..RawParams::default()
    };
    let pf = ImportRaw.preflight(&params, &InputMetas::new()).unwrap();
    // the bytes as stored, the values as read and the labels (issue 35: the values read
    // were not counted)
    assert_eq!(pf.memory_bytes, 3 * 24);
    assert_eq!(pf.outputs["image"].grid.as_ref().unwrap().dims, [4, 3, 2]);
    let out = ImportRaw
        .run(&params, &pf.plan, &Inputs::new(), &ctx())
        .unwrap();
    let got = out["image"].as_phase_image().unwrap();
    assert_eq!(got.labels, img.labels);
    assert_eq!(got.grid.spacing, img.grid.spacing);
    // truncated file: refused in preflight, naming the file
    params.dims = [4, 3, 3];
    match ImportRaw.preflight(&params, &InputMetas::new()) {
        Err(StageError::InvalidParam { key, message }) => {
            assert_eq!(key, "dims");
            assert!(
                message.contains("labels.raw") && message.contains("truncated"),
                "{message}"
            );
        }
        other => panic!("expected a dims error, got {other:?}"),
    }
    // missing file
    params.path = d.path().join("nope.raw").display().to_string();
    let e = ImportRaw
        .preflight(&params, &InputMetas::new())
        .unwrap_err();
    assert!(e.to_string().contains("nope.raw"), "{e}");
}

/// Periodicity is stated, never guessed: a raw file (which cannot state it) is not periodic
/// unless the YAML says so; a file that records it keeps it; `periodic:` overrides the file.
#[test]
fn import_periodicity_comes_from_the_file_or_the_yaml() {
    let d = tmp();
    let img = image([4, 3, 2]);
    let raw = d.path().join("labels.raw");
    std::fs::write(&raw, &img.labels).unwrap();
    let mut rp = RawParams {
        path: raw.display().to_string(),
        dims: [4, 3, 2],
        spacing: Some(Lengths3::One(units::Q::new(1e-6))),
        ..RawParams::default()
    };
    let periodic_of =
        |pf: &Preflight<ImportPlan>| pf.outputs["image"].grid.as_ref().unwrap().periodic;
    let pf = ImportRaw.preflight(&rp, &InputMetas::new()).unwrap();
    assert_eq!(periodic_of(&pf), [false; 3]);
    rp.options.periodic = Some([true, false, true]);
    let pf = ImportRaw.preflight(&rp, &InputMetas::new()).unwrap();
    assert_eq!(periodic_of(&pf), [true, false, true]);
    let out = ImportRaw
        .run(&rp, &pf.plan, &Inputs::new(), &ctx())
        .unwrap();
    assert_eq!(
        out["image"].as_phase_image().unwrap().grid.periodic,
        [true, false, true]
    );

    // The .h5 records [false, true, true]; kept by default, replaced when the YAML says so.
    let h5 = d.path().join("i.h5");
    write_h5(&Artifact::PhaseImage(img.clone()), &h5, &prov()).unwrap();
    let mut hp = Hdf5Params {
        path: h5.display().to_string(),
        dataset: "phase".into(),
        ..Default::default()
    };
    let pf = ImportHdf5.preflight(&hp, &InputMetas::new()).unwrap();
    assert_eq!(periodic_of(&pf), [false, true, true]);
    hp.options.periodic = Some([false; 3]);
    let pf = ImportHdf5.preflight(&hp, &InputMetas::new()).unwrap();
    assert_eq!(periodic_of(&pf), [false; 3]);
    let out = ImportHdf5
        .run(&hp, &pf.plan, &Inputs::new(), &ctx())
        .unwrap();
    assert_eq!(
        out["image"].as_phase_image().unwrap().grid.periodic,
        [false; 3]
    );
}

#[test]
fn import_refuses_labels_above_255() {
    let d = tmp();
    let p = d.path().join("big.raw");
    let v: Vec<u8> = [3u16, 300, 7, 0]
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    std::fs::write(&p, v).unwrap();
    let params = RawParams {
        path: p.display().to_string(),
        dims: [2, 2, 1],
        dtype: RawDtype::U16,
        spacing: Some(Lengths3::One(units::Q::new(1e-6))),
        ..RawParams::default()
    };
    // A small file is read once at preflight, so the range error comes before any run.
    let Err(e) = ImportRaw.preflight(&params, &InputMetas::new()) else {
        panic!("labels above 255 must be refused at preflight");
    };
    let e = e.to_string();
    assert!(
        e.contains("300") && e.contains("0..=255") && e.contains("big.raw"),
        "{e}"
    );
    // the same data is fine as a field
    let params = RawParams {
        options: ImportOptions {
            as_: ImportAs::Field,
            unit: "Pa".into(),
            ..params.options.clone()
        },
        ..params
    };
    let pf = ImportRaw.preflight(&params, &InputMetas::new()).unwrap();
    let out = ImportRaw
        .run(&params, &pf.plan, &Inputs::new(), &ctx())
        .unwrap();
    let f = out["field"].as_field().unwrap();
    assert_eq!(f.data, FieldData::F64(vec![3.0, 300.0, 7.0, 0.0]));
    assert_eq!(f.unit, "Pa");
}

#[test]
fn import_hdf5_netcdf_vti_round_trip_through_the_stages() {
    let d = tmp();
    let img = image([5, 4, 3]);
    let f = field([5, 4, 3], 3, true);
    let h5 = d.path().join("i.h5");
    let nc = d.path().join("i.nc");
    let vti = d.path().join("f.vti");
    write_h5(&Artifact::PhaseImage(img.clone()), &h5, &prov()).unwrap();
    write_nc(&Artifact::PhaseImage(img.clone()), &nc, &prov()).unwrap();
    write_vti(&Artifact::Field(f.clone()), &vti, &prov()).unwrap();

    let hp = Hdf5Params {
        path: h5.display().to_string(),
        dataset: "phase".into(),
        ..Default::default()
    };
    let pf = ImportHdf5.preflight(&hp, &InputMetas::new()).unwrap();
    // The file's periodic flags are announced (the run gives them too).
    assert_eq!(pf.outputs["image"].grid.as_ref().unwrap(), &img.grid);
    let out = ImportHdf5
        .run(&hp, &pf.plan, &Inputs::new(), &ctx())
        .unwrap();
    assert_eq!(out["image"].as_phase_image().unwrap(), &img);
    let missing = Hdf5Params {
        dataset: "nope".into(),
        ..hp
    };
    let e = ImportHdf5
        .preflight(&missing, &InputMetas::new())
        .unwrap_err()
        .to_string();
    assert!(e.contains("i.h5") && e.contains("nope"), "{e}");

    let np = NetcdfParams {
        path: nc.display().to_string(),
        variable: "phase".into(),
        ..Default::default()
    };
    let pf = ImportNetcdf.preflight(&np, &InputMetas::new()).unwrap();
    let out = ImportNetcdf
        .run(&np, &pf.plan, &Inputs::new(), &ctx())
        .unwrap();
    assert_eq!(out["image"].as_phase_image().unwrap(), &img);

    let vp = VtiParams {
        path: vti.display().to_string(),
        options: ImportOptions {
            as_: ImportAs::Field,
            ..Default::default()
        },
        ..Default::default()
    };
    let pf = ImportVti.preflight(&vp, &InputMetas::new()).unwrap();
    // stored, read and output values, and the file parsed in memory (bytes, XML text,
    // appended block)
    let file = std::fs::metadata(&vti).unwrap().len();
    assert_eq!(
        pf.memory_bytes,
        (5 * 4 * 3 * 3 * (4 + 4 + 4)) as u64 + 3 * file
    );
    let out = ImportVti
        .run(&vp, &pf.plan, &Inputs::new(), &ctx())
        .unwrap();
    assert_eq!(out["field"].as_field().unwrap(), &f);
    // three components cannot be labels
    let as_img = VtiParams {
        options: ImportOptions {
            as_: ImportAs::PhaseImage,
            ..vp.options.clone()
        },
        ..vp.clone()
    };
    let e = ImportVti
        .preflight(&as_img, &InputMetas::new())
        .unwrap_err()
        .to_string();
    assert!(e.contains("3 components"), "{e}");
    // a truncated file is a clear error naming it
    let text = std::fs::read(&vti).unwrap();
    let cut = d.path().join("cut.vti");
    std::fs::write(&cut, &text[..text.len() * 2 / 3]).unwrap();
    let cp = VtiParams {
        path: cut.display().to_string(),
        ..vp
    };
    let e = match ImportVti.preflight(&cp, &InputMetas::new()) {
        Err(e) => e.to_string(),
        Ok(pf) => ImportVti
            .run(&cp, &pf.plan, &Inputs::new(), &ctx())
            .unwrap_err()
            .to_string(),
    };
    assert!(e.contains("cut.vti"), "{e}");
}

#[test]
fn import_params_accept_unit_strings() {
    let s = Typed::new(ImportRaw);
    let v = s
        .normalize_params(&serde_json::json!({"path": "x.raw", "dims": [2, 2, 2],
            "spacing": "10 um", "origin": ["1 mm", 0, "-2 um"], "as": "field", "dtype": "f32"}))
        .unwrap();
    // unit conversion multiplies by 1e-6 in floating point: equal to 1 ulp
    let close = |a: &serde_json::Value, b: f64| (a.as_f64().unwrap() - b).abs() <= 1e-15 * b.abs();
    assert!(close(&v["spacing"], 1e-5), "{v}");
    for (k, want) in [1e-3, 0.0, -2e-6].iter().enumerate() {
        assert!(close(&v["origin"][k], *want), "{v}");
    }
    let e = s
        .normalize_params(&serde_json::json!({"path": "x.raw", "dim": [2, 2, 2]}))
        .unwrap_err();
    assert!(e.to_string().contains("dim"), "{e}");
}

use grainpipe_core::stage::{Stage, Typed};

/// Verbatim output of VTK 9.7's vtkXMLImageDataWriter (pyvista `save`): zlib, UInt32 header.
#[test]
fn vti_reader_takes_vtk_compressed_output() {
    let d = tmp();
    let p = d.path().join("vtk.vti");
    std::fs::write(
        &p,
        r#"<?xml version="1.0"?>
<VTKFile type="ImageData" version="0.1" byte_order="LittleEndian" header_type="UInt32" compressor="vtkZLibDataCompressor">
  <ImageData WholeExtent="0 3 0 2 0 1" Origin="1 2 3" Spacing="0.1 0.2 0.3" Direction="1 0 0 0 1 0 0 0 1">
  <Piece Extent="0 3 0 2 0 1">
    <PointData>
    </PointData>
    <CellData Scalars="a">
      <DataArray type="UInt8" Name="a" format="binary" RangeMin="0" RangeMax="5">
        AQAAAACAAAAGAAAADgAAAA==eF5jYGRiZmEFAAApABA=
      </DataArray>
    </CellData>
  </Piece>
  </ImageData>
</VTKFile>
"#,
    )
    .unwrap();
    let v = read_vti(&p, None).unwrap();
    assert_eq!(v.dims, [3, 2, 1]);
    assert_eq!(v.data, VolumeData::U8(vec![0, 1, 2, 3, 4, 5]));
    assert_eq!(
        (v.spacing, v.origin),
        (Some([0.1, 0.2, 0.3]), Some([1.0, 2.0, 3.0]))
    );
    let img = v.into_phase_image().unwrap();
    // no phase table in the file: one default entry per label present
    assert_eq!(img.phases.len(), 6);
    assert_eq!(img.phases[0].name, "pore");
}

#[test]
fn import_of_corrupt_hdf5_and_netcdf_names_the_file() {
    let d = tmp();
    let img = image([6, 5, 4]);
    for (name, var) in [("c.h5", "phase"), ("c.nc", "phase")] {
        let p = d.path().join(name);
        let a = Artifact::PhaseImage(img.clone());
        if name.ends_with("h5") {
            write_h5(&a, &p, &prov()).unwrap();
        } else {
            write_nc(&a, &p, &prov()).unwrap();
        }
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() / 3]).unwrap();
        let path = p.display().to_string();
        let e = if name.ends_with("h5") {
            let hp = Hdf5Params {
                path,
                dataset: var.into(),
                ..Default::default()
            };
            ImportHdf5
                .preflight(&hp, &InputMetas::new())
                .and_then(|pf| {
                    ImportHdf5
                        .run(&hp, &pf.plan, &Inputs::new(), &ctx())
                        .map(|_| unreachable!())
                })
        } else {
            let np = NetcdfParams {
                path,
                variable: var.into(),
                ..Default::default()
            };
            ImportNetcdf
                .preflight(&np, &InputMetas::new())
                .and_then(|pf| {
                    ImportNetcdf
                        .run(&np, &pf.plan, &Inputs::new(), &ctx())
                        .map(|_| unreachable!())
                })
        }
        .unwrap_err()
        .to_string();
        assert!(e.contains(name), "{e}");
    }
}
