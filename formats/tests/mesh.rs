//! FE meshes of a phase image read back by small parsers written here from the format
//! specifications: the Abaqus deck (nodes, C3D8 elements per phase, element sets, materials
//! and sections, face node sets, periodic pairs) and the Gmsh MSH 4.1 file (physical
//! groups, entities, node and element blocks). meshio, pyvista and gmsh read the same files
//! in tests/interop/test_mesh.py.

use grainpipe_core::registry::ExportOptions;
use grainpipe_core::serde_json::json;
use grainpipe_core::*;
use grainpipe_formats::mesh::{AbaqusExporter, GmshExporter};
use std::collections::{BTreeMap, BTreeSet, HashMap};

const DIMS: [usize; 3] = [6, 5, 4];
const ORIGIN: [f64; 3] = [1e-3, -2e-4, 5e-5];
const SPACING: [f64; 3] = [2e-6, 3e-6, 5e-6];

/// Labels 0 (pore), 1 (grain), 2 (binder) in a pattern with every phase touching every face.
fn image() -> PhaseImage {
    let [nx, ny, nz] = DIMS;
    let mut labels = Vec::new();
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                labels.push(((x + 2 * y + 3 * z) % 3) as u8);
            }
        }
    }
    PhaseImage {
        grid: Grid {
            dims: DIMS,
            spacing: SPACING,
            origin: ORIGIN,
            periodic: [true, false, true],
        },
        labels,
        phases: ["pore", "grain", "binder"]
            .iter()
            .enumerate()
            .map(|(i, n)| Phase {
                id: i as u8,
                name: n.to_string(),
            })
            .collect(),
    }
}

fn prov() -> Provenance {
    let mut p = Provenance::default();
    p.entries.insert("pipeline".into(), "mesh-test".into());
    p
}

fn options(e: &dyn Exporter, phases: serde_json::Value) -> ExportOptions {
    let mut o = e.default_options();
    o.insert("phases".into(), phases);
    o
}

/// The grid corner of a position (exact: coordinates are origin + i * spacing).
fn corner(p: [f64; 3]) -> [usize; 3] {
    std::array::from_fn(|a| {
        let i = ((p[a] - ORIGIN[a]) / SPACING[a]).round();
        assert!(
            (ORIGIN[a] + i * SPACING[a] - p[a]).abs() <= 1e-12 * SPACING[a].max(p[a].abs()),
            "{p:?} is not on the grid"
        );
        i as usize
    })
}

struct Deck {
    nodes: HashMap<u64, [f64; 3]>,
    /// ELSET -> elements (label, nodes).
    elsets: BTreeMap<String, Vec<(u64, [u64; 8])>>,
    nsets: BTreeMap<String, Vec<u64>>,
    materials: BTreeSet<String>,
    /// ELSET -> MATERIAL of each *SOLID SECTION.
    sections: BTreeMap<String, String>,
}

fn param(line: &str, key: &str) -> Option<String> {
    line.split(',')
        .skip(1)
        .filter_map(|kv| kv.split_once('='))
        .find(|(k, _)| k.trim().eq_ignore_ascii_case(key))
        .map(|(_, v)| v.trim().to_string())
}

fn parse_inp(text: &str) -> Deck {
    let mut d = Deck {
        nodes: HashMap::new(),
        elsets: BTreeMap::new(),
        nsets: BTreeMap::new(),
        materials: BTreeSet::new(),
        sections: BTreeMap::new(),
    };
    let mut mode = String::new();
    let mut set = String::new();
    for line in text.lines() {
        if line.starts_with("**") || line.trim().is_empty() {
            continue;
        }
        if let Some(kw) = line.strip_prefix('*') {
            let name = kw.split(',').next().unwrap().trim().to_ascii_uppercase();
            mode = name.clone();
            match name.as_str() {
                "ELEMENT" => {
                    assert_eq!(param(line, "TYPE").as_deref(), Some("C3D8"));
                    set = param(line, "ELSET").expect("ELSET");
                    d.elsets.entry(set.clone()).or_default();
                }
                "NSET" => {
                    set = param(line, "NSET").unwrap();
                    d.nsets.entry(set.clone()).or_default();
                }
                "MATERIAL" => {
                    d.materials.insert(param(line, "NAME").unwrap());
                }
                "SOLID SECTION" => {
                    d.sections.insert(
                        param(line, "ELSET").unwrap(),
                        param(line, "MATERIAL").unwrap(),
                    );
                }
                _ => {}
            }
            continue;
        }
        let nums: Vec<&str> = line.split(',').map(str::trim).collect();
        match mode.as_str() {
            "NODE" => {
                let l: u64 = nums[0].parse().unwrap();
                let p = [1, 2, 3].map(|k| nums[k].parse::<f64>().unwrap());
                assert!(d.nodes.insert(l, p).is_none(), "node {l} twice");
            }
            "ELEMENT" => {
                let v: Vec<u64> = nums.iter().map(|s| s.parse().unwrap()).collect();
                assert_eq!(v.len(), 9, "C3D8 data line: label + 8 nodes");
                d.elsets
                    .get_mut(&set)
                    .unwrap()
                    .push((v[0], v[1..].try_into().unwrap()));
            }
            "NSET" => {
                assert!(nums.len() <= 16, "at most 16 labels per data line");
                d.nsets
                    .get_mut(&set)
                    .unwrap()
                    .extend(nums.iter().map(|s| s.parse::<u64>().unwrap()));
            }
            _ => {}
        }
    }
    d
}

#[test]
fn abaqus_deck_has_one_brick_per_selected_voxel_sets_sections_and_faces() {
    let img = image();
    let dir = tempfile::tempdir().unwrap();
    for (sel, names) in [
        (json!("all"), vec!["pore", "grain", "binder"]),
        (json!(["grain", 2]), vec!["grain", "binder"]),
    ] {
        let path = dir.path().join("m.inp");
        AbaqusExporter
            .write(
                &Artifact::PhaseImage(img.clone()),
                &path,
                &prov(),
                &options(&AbaqusExporter, sel),
            )
            .unwrap();
        let d = parse_inp(&std::fs::read_to_string(&path).unwrap());
        assert_eq!(
            d.elsets.keys().cloned().collect::<BTreeSet<_>>(),
            names.iter().map(|s| s.to_string()).collect()
        );
        let mut labels = BTreeSet::new();
        let mut used = BTreeSet::new();
        for name in &names {
            let id = img.phases.iter().find(|p| p.name == *name).unwrap().id;
            let elems = &d.elsets[*name];
            // Count: the voxels of the phase.
            assert_eq!(elems.len(), img.labels.iter().filter(|&&l| l == id).count());
            // Section and material per phase.
            assert_eq!(d.sections.get(*name).map(String::as_str), Some(*name));
            assert!(d.materials.contains(*name));
            for (label, nodes) in elems {
                assert!(labels.insert(*label), "element {label} twice");
                // The eight nodes are the corners of a voxel of this phase, in C3D8 order.
                let cs: Vec<[usize; 3]> = nodes.iter().map(|n| corner(d.nodes[n])).collect();
                let lo = cs[0];
                let order = [
                    [0, 0, 0],
                    [1, 0, 0],
                    [1, 1, 0],
                    [0, 1, 0],
                    [0, 0, 1],
                    [1, 0, 1],
                    [1, 1, 1],
                    [0, 1, 1],
                ];
                for (c, o) in cs.iter().zip(order) {
                    assert_eq!(*c, [lo[0] + o[0], lo[1] + o[1], lo[2] + o[2]]);
                }
                assert_eq!(img.labels[img.grid.index(lo[0], lo[1], lo[2])], id);
                used.extend(nodes.iter().copied());
            }
        }
        // Every node is used, and shared corners are one node.
        assert_eq!(used.len(), d.nodes.len());
        let distinct: BTreeSet<[usize; 3]> = d.nodes.values().map(|p| corner(*p)).collect();
        assert_eq!(distinct.len(), d.nodes.len());
        // Face sets: exactly the nodes on each face plane of the box.
        for (f, set) in ["XMIN", "XMAX", "YMIN", "YMAX", "ZMIN", "ZMAX"]
            .iter()
            .enumerate()
        {
            let (axis, at) = (f / 2, if f % 2 == 0 { 0 } else { DIMS[f / 2] });
            let want: BTreeSet<u64> = d
                .nodes
                .iter()
                .filter(|(_, p)| corner(**p)[axis] == at)
                .map(|(l, _)| *l)
                .collect();
            let got: BTreeSet<u64> = d.nsets[*set].iter().copied().collect();
            assert!(!want.is_empty());
            assert_eq!(got, want, "{set}");
        }
        // Periodic pairs on x and z (the periodic axes), none on y.
        assert!(!d.nsets.contains_key("PERIODIC_Y_LO"));
        for (axis, a) in [(0, "X"), (2, "Z")] {
            let lo = &d.nsets[&format!("PERIODIC_{a}_LO")];
            let hi = &d.nsets[&format!("PERIODIC_{a}_HI")];
            assert_eq!(lo.len(), hi.len());
            let by_corner: HashMap<[usize; 3], u64> =
                d.nodes.iter().map(|(l, p)| (corner(*p), *l)).collect();
            let expected = d
                .nodes
                .values()
                .map(|p| corner(*p))
                .filter(|c| c[axis] == 0)
                .filter(|c| {
                    let mut u = *c;
                    u[axis] = DIMS[axis];
                    by_corner.contains_key(&u)
                })
                .count();
            assert_eq!(lo.len(), expected);
            // Abaqus sorts node sets by label: both sets are sorted, so pairs stay paired.
            assert!(lo.windows(2).all(|w| w[0] < w[1]) && hi.windows(2).all(|w| w[0] < w[1]));
            for (l, h) in lo.iter().zip(hi) {
                let (cl, ch) = (corner(d.nodes[l]), corner(d.nodes[h]));
                let mut moved = cl;
                moved[axis] = DIMS[axis];
                assert_eq!(ch, moved);
            }
        }
    }
}

#[test]
fn unknown_phase_is_refused_naming_the_option() {
    let e = AbaqusExporter
        .write(
            &Artifact::PhaseImage(image()),
            &tempfile::tempdir().unwrap().path().join("x.inp"),
            &prov(),
            &options(&AbaqusExporter, json!(["grain", "cement"])),
        )
        .unwrap_err();
    assert!(
        e.contains("phases") && e.contains("cement") && e.contains("binder (2)"),
        "{e}"
    );
}

#[test]
fn gmsh_file_has_a_named_physical_group_and_entity_per_phase() {
    let img = image();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.msh");
    GmshExporter
        .write(
            &Artifact::PhaseImage(img.clone()),
            &path,
            &prov(),
            &options(&GmshExporter, json!(["binder", "grain"])),
        )
        .unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let section = |name: &str| -> Vec<&str> {
        let start = text.find(&format!("${name}\n")).unwrap() + name.len() + 2;
        let end = text.find(&format!("$End{name}\n")).unwrap();
        text[start..end].lines().collect()
    };
    assert_eq!(section("MeshFormat"), vec!["4.1 0 8"]);
    // Physical tag = label + 1.
    assert_eq!(
        section("PhysicalNames"),
        vec!["2", "3 3 \"binder\"", "3 2 \"grain\""]
    );
    let ent = section("Entities");
    assert_eq!(ent[0], "0 0 0 2");
    for (line, tag) in ent[1..].iter().zip([3, 2]) {
        let t: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(t[0], tag.to_string());
        assert_eq!(&t[7..], &["1", &tag.to_string(), "0"]);
    }
    // Nodes: every tag once, coordinates on the grid.
    let nodes = section("Nodes");
    let head: Vec<usize> = nodes[0]
        .split_whitespace()
        .map(|s| s.parse().unwrap())
        .collect();
    let mut coords: HashMap<usize, [f64; 3]> = HashMap::new();
    let mut i = 1;
    for _ in 0..head[0] {
        let b: Vec<usize> = nodes[i]
            .split_whitespace()
            .map(|s| s.parse().unwrap())
            .collect();
        let n = b[3];
        for k in 0..n {
            let tag: usize = nodes[i + 1 + k].parse().unwrap();
            let p: Vec<f64> = nodes[i + 1 + n + k]
                .split_whitespace()
                .map(|s| s.parse().unwrap())
                .collect();
            assert!(coords.insert(tag, [p[0], p[1], p[2]]).is_none());
        }
        i += 1 + 2 * n;
    }
    assert_eq!(coords.len(), head[1]);
    // Elements: per block, one hexahedron (type 5) per voxel of the phase, nodes at its corners.
    let els = section("Elements");
    let mut i = 1;
    let mut total = 0;
    for (tag, id) in [(3usize, 2u8), (2, 1)] {
        let b: Vec<usize> = els[i]
            .split_whitespace()
            .map(|s| s.parse().unwrap())
            .collect();
        assert_eq!(&b[..3], &[3, tag, 5]);
        assert_eq!(b[3], img.labels.iter().filter(|&&l| l == id).count());
        for line in &els[i + 1..i + 1 + b[3]] {
            let v: Vec<usize> = line
                .split_whitespace()
                .map(|s| s.parse().unwrap())
                .collect();
            let lo = corner(coords[&v[1]]);
            assert_eq!(corner(coords[&v[7]]), [lo[0] + 1, lo[1] + 1, lo[2] + 1]);
            assert_eq!(img.labels[img.grid.index(lo[0], lo[1], lo[2])], id);
        }
        total += b[3];
        i += 1 + b[3];
    }
    assert_eq!(total, img.labels.iter().filter(|&&l| l > 0).count());
}

#[test]
fn preflight_checks_phases_against_the_announced_table_and_counts_memory() {
    use grainpipe_formats::mesh::{VtuExporter, XdmfExporter};
    let img = image();
    let meta = ArtifactMeta::on_grid(ArtifactKind::PhaseImage, img.grid.clone())
        .with_phases(img.phases.clone());
    let ok = VtuExporter
        .preflight(&meta, &options(&VtuExporter, json!(["grain"])))
        .unwrap();
    // The corner table (4 bytes per grid corner) is counted.
    assert!(ok >= 4 * 7 * 6 * 5, "{ok}");
    let (key, msg) = VtuExporter
        .preflight(&meta, &options(&VtuExporter, json!(["grain", "cemnt"])))
        .unwrap_err();
    assert_eq!(key, "phases");
    assert!(
        msg.contains("unknown phase `cemnt`") && msg.contains("binder (2)"),
        "{msg}"
    );
    // A former default name says what it is called now.
    let (key, msg) = VtuExporter
        .preflight(&meta, &options(&VtuExporter, json!(["sand"])))
        .unwrap_err();
    assert_eq!(key, "phases");
    assert!(
        msg.contains("`sand` is the binder stages' former name for phase 1; it is now `grain`"),
        "{msg}"
    );
    // `phases` on a field, `mesh: image` of a packing: refused naming the option.
    let field = ArtifactMeta::on_grid(ArtifactKind::Field, img.grid.clone());
    let (key, _) = VtuExporter
        .preflight(&field, &options(&VtuExporter, json!([1])))
        .unwrap_err();
    assert_eq!(key, "phases");
    let mut o = XdmfExporter.default_options();
    o.insert("mesh".into(), json!("image"));
    let (key, _) = XdmfExporter
        .preflight(&ArtifactMeta::of(ArtifactKind::Packing), &o)
        .unwrap_err();
    assert_eq!(key, "mesh");
    // The .xdmf writes its .h5 too: the engine's duplicate check sees both.
    let paths = XdmfExporter.written_paths(
        std::path::Path::new("out/a.xdmf"),
        &XdmfExporter.default_options(),
    );
    assert_eq!(paths[1].path, std::path::Path::new("out/a.h5"));
}

#[test]
fn contact_graph_and_packing_meshes_hold_lines_and_vertices() {
    use grainpipe_formats::mesh::{with_mesh, CellKind, Chunk};
    let mut g = ContactGraph {
        contacts: vec![
            Contact {
                i: 0,
                j: 1,
                gap: -1e-7,
            },
            Contact {
                i: 1,
                j: 2,
                gap: 2e-7,
            },
        ],
        faces: Default::default(),
        bonds: vec![[0, 1], [0, 2]],
        bond_attributes: Default::default(),
        positions: vec![[0.0; 3], [1e-5, 0.0, 0.0], [0.0, 1e-5, 0.0]],
        radii: vec![5e-6; 3],
    };
    g.bond_attributes.insert(
        "neck".into(),
        BodyAttribute {
            unit: "m".into(),
            values: vec![1e-6, 2e-6],
        },
    );
    let a = Artifact::ContactGraph(g);
    with_mesh(&a, &VtuExporterOptions::get(), |m| {
        assert_eq!(m.kind, CellKind::Line);
        assert_eq!((m.point_count, m.cell_count), (3, 3));
        let mut conn = Vec::new();
        m.connectivity
            .produce(&mut |c| {
                if let Chunk::I64(v) = c {
                    conn.extend_from_slice(v);
                }
                Ok(())
            })
            .unwrap();
        // Contacts, then the bond that is not a contact.
        assert_eq!(conn, vec![0, 1, 1, 2, 0, 2]);
        let mut neck = Vec::new();
        let col = m.cell_data.iter().find(|c| c.name == "neck").unwrap();
        col.produce(&mut |c| {
            if let Chunk::F64(v) = c {
                neck.extend_from_slice(v);
            }
            Ok(())
        })
        .unwrap();
        assert_eq!(neck[0], 1e-6);
        assert!(neck[1].is_nan());
        assert_eq!(neck[2], 2e-6);
        Ok(())
    })
    .unwrap();
}

struct VtuExporterOptions;
impl VtuExporterOptions {
    fn get() -> ExportOptions {
        grainpipe_formats::mesh::VtuExporter.default_options()
    }
}
