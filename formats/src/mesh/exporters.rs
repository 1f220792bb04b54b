//! The mesh exporters: `vtu`, `vtk`, `xdmf`, `abaqus` (.inp), `gmsh` (.msh). They build a
//! [`Mesh`] or [`VoxelHexMesh`] over the artifact (no copy of the voxels) and stream it to
//! an atomic temporary file.

use super::legacy_vtk::write_legacy_vtk;
use super::surface::{self, InterfaceMesh, EXTERIOR};
use super::vtu::{write_vtu, VtuEncoding};
use super::{abaqus, emit, gmsh, xdmf, CellKind, Column, Dtype, Mesh, VoxelHexMesh};
use crate::h5util::{self, provenance_attrs, H5Result};
use crate::vtk_xml::graph_lines;
use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::registry::{ExportOption, ExportOptions, WrittenPath};
use grainpipe_core::serde_json::{json, Value};
use grainpipe_core::{
    Artifact, ArtifactKind, ArtifactMeta, BodyShape, Exporter, FieldData, Phase, PhaseImage,
    Provenance,
};
use std::path::{Path, PathBuf};

/// Working memory of a streaming writer besides the mesh tables: chunk and block buffers,
/// the 1 MiB file buffer, HDF5's chunk cache [bytes].
const STREAM_BUFFERS: u64 = 16 << 20;

/// The phases an export meshes: `all` or a list of phase names and/or labels.
#[derive(Clone, Debug, PartialEq)]
pub enum PhaseSelection {
    All,
    Listed(Vec<Value>),
}

impl PhaseSelection {
    pub fn parse(v: &Value) -> Result<Self, String> {
        match v {
            Value::String(s) if s == "all" => Ok(Self::All),
            Value::Array(items) if !items.is_empty() => {
                for it in items {
                    let ok = it.is_string() || it.as_u64().is_some_and(|k| k <= 255);
                    if !ok {
                        return Err(format!(
                            "{it} is not a phase: give phase names (e.g. [grain, binder]) or \
                             labels 0..=255"
                        ));
                    }
                }
                Ok(Self::Listed(items.clone()))
            }
            other => Err(format!(
                "{other}: give `all` or a list of phase names or labels, e.g. [grain, binder]"
            )),
        }
    }

    /// The selected (label, name) pairs in order. `present`: the labels that occur (for
    /// `all`, labels outside the table are meshed too, named `phase<k>`).
    pub fn resolve(
        &self,
        table: &[Phase],
        present: Option<&[bool; 256]>,
    ) -> Result<Vec<(u8, String)>, String> {
        let listing = || {
            table
                .iter()
                .map(|p| format!("{} ({})", p.name, p.id))
                .collect::<Vec<_>>()
                .join(", ")
        };
        match self {
            PhaseSelection::All => {
                let mut out: Vec<(u8, String)> =
                    table.iter().map(|p| (p.id, p.name.clone())).collect();
                if let Some(present) = present {
                    for k in 0..=255u8 {
                        if present[k as usize] && !table.iter().any(|p| p.id == k) {
                            out.push((k, format!("phase{k}")));
                        }
                    }
                }
                out.sort_by_key(|p| p.0);
                Ok(out)
            }
            PhaseSelection::Listed(items) => {
                let mut out: Vec<(u8, String)> = Vec::new();
                for it in items {
                    let found = match it {
                        Value::String(name) => table
                            .iter()
                            .find(|p| &p.name == name)
                            .map(|p| (p.id, p.name.clone()))
                            .ok_or_else(|| {
                                let names = || table.iter().map(|p| p.name.as_str());
                                let hint = match grainpipe_core::phases::renamed_in(name, names()) {
                                    Some(r) => format!(" ({})", r.message()),
                                    None => grainpipe_core::registry::closest(name, names())
                                        .map(|s| format!(" (did you mean `{s}`?)"))
                                        .unwrap_or_default(),
                                };
                                format!(
                                    "unknown phase `{name}`{hint}; the image has: {}",
                                    listing()
                                )
                            })?,
                        _ => {
                            let k = it.as_u64().expect("checked by parse") as u8;
                            let name = table
                                .iter()
                                .find(|p| p.id == k)
                                .map(|p| p.name.clone())
                                .unwrap_or_else(|| format!("phase{k}"));
                            (k, name)
                        }
                    };
                    if out.iter().any(|p| p.0 == found.0) {
                        return Err(format!("phase `{}` is listed twice", found.1));
                    }
                    out.push(found);
                }
                Ok(out)
            }
        }
    }
}

fn phases_option() -> ExportOption {
    ExportOption {
        name: "phases",
        doc: "phase images: the phases meshed, `all` or a list of phase names and/or labels \
              (e.g. [grain, binder]); one hexahedron per voxel of a selected phase (`mesh: \
              surface`: every interface with a selected phase on one side)",
        default: json!("all"),
    }
}

fn opt<'o>(o: &'o ExportOptions, k: &str) -> &'o Value {
    o.get(k).unwrap_or(&Value::Null)
}

/// A text option with a fixed set of values: the value of the one given (`absent` when the
/// option is left out), or the error naming the choices.
fn choice<T: Copy>(
    o: &ExportOptions,
    key: &str,
    choices: &[(&str, T)],
    absent: Option<T>,
) -> Result<T, (String, String)> {
    let v = opt(o, key);
    if v.is_null() {
        if let Some(t) = absent {
            return Ok(t);
        }
    }
    v.as_str()
        .and_then(|s| choices.iter().find(|(name, _)| *name == s))
        .map(|(_, t)| *t)
        .ok_or_else(|| {
            let names: Vec<&str> = choices.iter().map(|(n, _)| *n).collect();
            (
                key.into(),
                format!("{v} is not one of: {}", names.join(", ")),
            )
        })
}

fn selection(o: &ExportOptions) -> Result<PhaseSelection, (String, String)> {
    match o.get("phases") {
        None => Ok(PhaseSelection::All),
        Some(v) => PhaseSelection::parse(v).map_err(|m| ("phases".into(), m)),
    }
}

/// Preflight shared by the mesh formats: `phases` only on phase images, checked against the
/// announced phase table; memory of the mesh tables and buffers.
fn mesh_preflight(
    meta: &ArtifactMeta,
    o: &ExportOptions,
    extra_per_corner: u64,
) -> Result<u64, (String, String)> {
    let sel = selection(o)?;
    if meta.kind != ArtifactKind::PhaseImage && sel != PhaseSelection::All {
        return Err((
            "phases".into(),
            format!(
                "a {} has no phases; `phases` applies to phase images",
                meta.kind
            ),
        ));
    }
    if let Some(table) = &meta.phases {
        sel.resolve(table, None)
            .map_err(|m| ("phases".to_string(), m))?;
    }
    Ok(STREAM_BUFFERS
        + match (&meta.grid, meta.kind) {
            (Some(g), ArtifactKind::PhaseImage | ArtifactKind::Field) => {
                VoxelHexMesh::memory_bytes(g.dims)
                    + extra_per_corner
                        * ((g.dims[0] + 1) * (g.dims[1] + 1) * (g.dims[2] + 1)) as u64
            }
            // Packings and graphs are written from per-sphere / per-line tables.
            _ => 160 * meta.count_estimate,
        })
}

fn provenance_text(prov: &Provenance) -> String {
    let entries: grainpipe_core::serde_json::Map<String, Value> = prov
        .entries
        .iter()
        .map(|(k, v)| (k.clone(), Value::String(v.clone())))
        .collect();
    format!("grainpipe provenance: {}", Value::Object(entries))
}

fn labels_present(labels: &[u8]) -> [bool; 256] {
    let mut p = [false; 256];
    for &l in labels {
        p[l as usize] = true;
    }
    p
}

/// Selected phases as (label, name), in output order, and the mask of selected labels.
type Selected = (Vec<(u8, String)>, [bool; 256]);

/// The selected phases of an image and the label mask.
fn image_phases(img: &PhaseImage, o: &ExportOptions) -> Result<Selected, String> {
    crate::volume::VolumeRef::Phase(img).validate()?;
    let sel = selection(o).map_err(|(k, m)| format!("option `{k}`: {m}"))?;
    let present = labels_present(&img.labels);
    let phases = sel
        .resolve(&img.phases, Some(&present))
        .map_err(|m| format!("option `phases`: {m}"))?;
    let mut mask = [false; 256];
    for (id, _) in &phases {
        mask[*id as usize] = true;
    }
    Ok((phases, mask))
}

/// Builds the unstructured mesh of an artifact and hands it to `f`: a phase image or field
/// as hexahedral voxel cells (labels or field values as cell data), a packing as one vertex
/// per sphere (clumps expanded; radius, body_id, layer, frozen, clump_index, body
/// attributes as point data), a contact graph as lines (gap, bonded, bond attributes as cell
/// data; body_id, coordination, radius as point data).
pub fn with_mesh<R>(
    a: &Artifact,
    o: &ExportOptions,
    f: impl FnOnce(&Mesh) -> Result<R, String>,
) -> Result<R, String> {
    match a {
        Artifact::PhaseImage(img) => {
            let (phases, mask) = image_phases(img, o)?;
            let g = &img.grid;
            let vm = VoxelHexMesh::new(g.dims, g.origin, g.spacing, Some(&img.labels), mask)?;
            let mut mesh = Mesh::of_voxels(&vm);
            let labels = &img.labels;
            let vmr = &vm;
            mesh.cell_data.push(Column::generated::<u8>(
                "phase",
                1,
                vm.cell_count(),
                move |sink| emit(sink, vmr.voxels().map(|v| labels[v])),
            ));
            mesh.field_data.push(Column::owned(
                "periodic",
                3,
                g.periodic.map(u8::from).to_vec(),
            ));
            for (id, name) in &phases {
                mesh.field_data
                    .push(Column::owned(&format!("phase.{name}"), 1, vec![*id]));
            }
            f(&mesh)
        }
        Artifact::Field(fl) => {
            crate::volume::VolumeRef::Field(fl).validate()?;
            if selection(o).map_err(|(_, m)| m)? != PhaseSelection::All {
                return Err("option `phases`: a field has no phases".into());
            }
            let g = &fl.grid;
            let vm = VoxelHexMesh::new(g.dims, g.origin, g.spacing, None, [true; 256])?;
            let mut mesh = Mesh::of_voxels(&vm);
            let c = fl.components;
            let col = match &fl.data {
                FieldData::F32(d) => Column::borrowed(&fl.name, c, d),
                FieldData::F64(d) => Column::borrowed(&fl.name, c, d),
            };
            mesh.cell_data.push(if c > 1 {
                col.with_component_names(fl.component_names())
            } else {
                col
            });
            mesh.field_data.push(Column::owned(
                "periodic",
                3,
                g.periodic.map(u8::from).to_vec(),
            ));
            f(&mesh)
        }
        Artifact::Packing(p) => {
            a.validate()?;
            let spheres = p.world_spheres();
            let n = spheres.len();
            let points: Vec<f64> = spheres.iter().flat_map(|s| s.center).collect();
            let mut mesh = Mesh::explicit(CellKind::Vertex, points, (0..n as i64).collect());
            let pd = &mut mesh.point_data;
            pd.push(Column::owned(
                "radius",
                1,
                spheres.iter().map(|s| s.radius).collect(),
            ));
            pd.push(Column::owned(
                "body_id",
                1,
                spheres.iter().map(|s| s.body as i64).collect(),
            ));
            pd.push(Column::owned(
                "layer",
                1,
                spheres
                    .iter()
                    .map(|s| i64::from(p.bodies[s.body].layer))
                    .collect(),
            ));
            pd.push(Column::owned(
                "frozen",
                1,
                spheres
                    .iter()
                    .map(|s| u8::from(p.bodies[s.body].frozen))
                    .collect(),
            ));
            if p.library.is_some() {
                pd.push(Column::owned(
                    "clump_index",
                    1,
                    spheres
                        .iter()
                        .map(|s| match p.bodies[s.body].shape {
                            BodyShape::Clump { index } => index as i64,
                            BodyShape::Sphere { .. } => -1,
                        })
                        .collect(),
                ));
            }
            for (name, attr) in &p.attributes {
                pd.push(Column::owned(
                    name,
                    1,
                    spheres.iter().map(|s| attr.values[s.body]).collect(),
                ));
            }
            mesh.field_data
                .push(Column::owned("domain_min", 3, p.domain.min.to_vec()));
            mesh.field_data
                .push(Column::owned("domain_max", 3, p.domain.max.to_vec()));
            mesh.field_data.push(Column::owned(
                "periodic",
                3,
                p.domain.periodic.map(u8::from).to_vec(),
            ));
            f(&mesh)
        }
        Artifact::ContactGraph(g) => {
            g.validate()?;
            let gl = graph_lines(g);
            let points: Vec<f64> = g.positions.iter().flatten().copied().collect();
            let mut mesh = Mesh::explicit(CellKind::Line, points, gl.lines);
            mesh.cell_data.push(Column::owned("gap", 1, gl.gap));
            mesh.cell_data.push(Column::owned("bonded", 1, gl.bonded));
            for (name, attr) in &g.bond_attributes {
                let v: Vec<f64> = gl
                    .line_bond
                    .iter()
                    .map(|b| b.map(|k| attr.values[k]).unwrap_or(f64::NAN))
                    .collect();
                mesh.cell_data.push(Column::owned(name, 1, v));
            }
            let n = g.positions.len();
            let mut coordination = vec![0i32; n];
            for c in &g.contacts {
                coordination[c.i] += 1;
                coordination[c.j] += 1;
            }
            mesh.point_data
                .push(Column::owned("body_id", 1, (0..n as i64).collect()));
            mesh.point_data
                .push(Column::owned("coordination", 1, coordination));
            if !g.radii.is_empty() {
                mesh.point_data
                    .push(Column::owned("radius", 1, g.radii.clone()));
            }
            f(&mesh)
        }
        other => Err(format!("a mesh cannot hold a {}", other.kind())),
    }
}

// ---------------------------------------------------------------------------------------
// interface surfaces (`mesh: surface`)

/// The `mesh` option of `vtu` and `gmsh`: voxel hexahedra (or a packing's vertices, a
/// graph's lines) or the interface surfaces of a phase image.
fn surface_mode(o: &ExportOptions) -> Result<bool, (String, String)> {
    choice(
        o,
        "mesh",
        &[("hexahedra", false), ("surface", true)],
        Some(false),
    )
}

fn mesh_option(what: &'static str) -> ExportOption {
    ExportOption {
        name: "mesh",
        doc: what,
        default: json!("hexahedra"),
    }
}

fn smooth_option() -> ExportOption {
    ExportOption {
        name: "smooth",
        doc: "`mesh: surface`: Taubin lambda|mu smoothing iterations (Taubin 1995; lambda = \
              0.6307, mu = -0.6732), 0 = none; junction lines and the image box stay fixed",
        default: json!(0),
    }
}

fn decimate_option() -> ExportOption {
    ExportOption {
        name: "decimate",
        doc: "`mesh: surface`: fraction of each interface's triangles to keep, 0 < f <= 1 (1 = \
              none), by meshoptimizer's edge collapses (the `meshopt` crate) moving the \
              surface by at most half a voxel; junction lines stay",
        default: json!(1.0),
    }
}

fn decimate_fraction(o: &ExportOptions) -> Result<f64, (String, String)> {
    match o.get("decimate") {
        None => Ok(1.0),
        Some(v) => v.as_f64().filter(|&f| f > 0.0 && f <= 1.0).ok_or_else(|| {
            (
                "decimate".into(),
                format!("{v}: give the fraction of triangles to keep, 0 < f <= 1 (e.g. 0.25)"),
            )
        }),
    }
}

/// Most smoothing iterations accepted.
const MAX_SMOOTH: u64 = 1000;

fn smooth_iterations(o: &ExportOptions) -> Result<u32, (String, String)> {
    match o.get("smooth") {
        None => Ok(0),
        Some(v) => v
            .as_u64()
            .filter(|&n| n <= MAX_SMOOTH)
            .map(|n| n as u32)
            .ok_or_else(|| {
                (
                    "smooth".into(),
                    format!("{v}: give a number of iterations 0..={MAX_SMOOTH} (10 is typical)"),
                )
            }),
    }
}

/// Checks the surface options; `smooth` only with `mesh: surface`.
fn check_surface_options(o: &ExportOptions) -> Result<bool, (String, String)> {
    let surface = surface_mode(o)?;
    let smooth = smooth_iterations(o)?;
    if !surface && smooth > 0 {
        return Err((
            "smooth".into(),
            "smoothing applies to `mesh: surface`; voxel hexahedra are not smoothed".into(),
        ));
    }
    if !surface && decimate_fraction(o)? < 1.0 {
        return Err((
            "decimate".into(),
            "decimation applies to `mesh: surface`; voxel hexahedra are not decimated".into(),
        ));
    }
    Ok(surface)
}

/// Triangles preflight assumes per voxel of an image (measured by `mesh_bench`: 0.47 for a
/// ball filling half of a 140^3 box, 3.4 for balls of radius 6 voxels with 2-voxel binder
/// shells; independent random labels, no microstructure, reach 26.5 and exceed it).
pub const SURFACE_TRIANGLES_PER_VOXEL: f64 = 4.0;

/// Memory of a surface export of a `dims` image [bytes].
pub fn surface_memory(dims: [usize; 3], smooth: bool, decimate: bool) -> u64 {
    let voxels = (dims[0] * dims[1] * dims[2]) as f64;
    let tris = SURFACE_TRIANGLES_PER_VOXEL * voxels;
    // A closed triangulation has about half as many points as triangles.
    let points = 0.5 * tris;
    let per_point = surface::BYTES_PER_POINT
        + if smooth {
            surface::SMOOTH_BYTES_PER_POINT
        } else {
            0
        }
        + if decimate {
            surface::DECIMATE_BYTES_PER_POINT
        } else {
            0
        };
    // The grouping pass holds the triangles twice.
    (tris * (2 * surface::BYTES_PER_TRIANGLE) as f64 + points * per_point as f64) as u64
}

fn surface_preflight(meta: &ArtifactMeta, o: &ExportOptions) -> Result<u64, (String, String)> {
    if meta.kind != ArtifactKind::PhaseImage {
        return Err((
            "mesh".into(),
            format!(
                "`surface` meshes the interfaces of phase images, not a {}",
                meta.kind
            ),
        ));
    }
    mesh_preflight(meta, o, 0)?;
    let smooth = smooth_iterations(o)? > 0;
    let decimate = decimate_fraction(o)? < 1.0;
    Ok(STREAM_BUFFERS
        + meta
            .grid
            .as_ref()
            .map_or(0, |g| surface_memory(g.dims, smooth, decimate)))
}

/// The name of a label in interface names: the phase's, `exterior` for the outside.
fn label_name(img: &PhaseImage, l: i32) -> String {
    if l == EXTERIOR {
        return "exterior".into();
    }
    img.phases
        .iter()
        .find(|p| p.id as i32 == l)
        .map(|p| p.name.clone())
        .unwrap_or_else(|| format!("phase{l}"))
}

/// The interface surfaces of the selected phases of an image (every interface with a
/// selected phase on either side), smoothed as asked, and the interface names `a|b`.
pub fn image_surface(
    a: &Artifact,
    o: &ExportOptions,
) -> Result<(InterfaceMesh, Vec<String>), String> {
    let Artifact::PhaseImage(img) = a else {
        return Err(format!(
            "option `mesh`: `surface` meshes the interfaces of phase images, not a {}",
            a.kind()
        ));
    };
    let (_, mask) = image_phases(img, o)?;
    let g = &img.grid;
    let mut m = surface::interfaces(g.dims, g.origin, g.spacing, &img.labels, |lo, hi| {
        (lo >= 0 && mask[lo as usize]) || mask[hi as usize]
    })?;
    let iterations = smooth_iterations(o).map_err(|(k, e)| format!("option `{k}`: {e}"))?;
    surface::taubin_smooth(&mut m, iterations);
    let fraction = decimate_fraction(o).map_err(|(k, e)| format!("option `{k}`: {e}"))?;
    surface::decimate(&mut m, fraction, g.spacing);
    let names = m
        .pairs
        .iter()
        .map(|[lo, hi]| format!("{}|{}", label_name(img, *lo), label_name(img, *hi)))
        .collect();
    Ok((m, names))
}

/// The interface surfaces as a triangle [`Mesh`]: cell data `interface` (id = index in the
/// table + 1), `phase_a`, `phase_b` (Int32 labels, a < b, -1 = exterior); field data
/// `interface.<a>|<b>` = [id, a, b] and `phase.<name>` = label.
fn surface_mesh<'m>(m: &'m InterfaceMesh, names: &[String], img: &PhaseImage) -> Mesh<'m> {
    let np = m.points.len();
    let nt = m.triangles.len();
    let mut mesh = Mesh {
        kind: CellKind::Triangle,
        point_count: np,
        cell_count: nt,
        points: Column::generated::<f64>("Points", 3, np, move |sink| {
            emit(sink, m.points.iter().flatten().copied())
        }),
        connectivity: Column::generated::<i64>("connectivity", 1, 3 * nt, move |sink| {
            emit(sink, m.triangles.iter().flatten().map(|&v| i64::from(v)))
        }),
        point_data: Vec::new(),
        cell_data: vec![Column::generated::<i32>("interface", 1, nt, move |sink| {
            emit(sink, m.interface.iter().map(|&k| i32::from(k) + 1))
        })],
        field_data: Vec::new(),
    };
    for (side, name) in [(0, "phase_a"), (1, "phase_b")] {
        mesh.cell_data
            .push(Column::generated::<i32>(name, 1, nt, move |sink| {
                emit(sink, m.interface.iter().map(|&k| m.pairs[k as usize][side]))
            }));
    }
    for (k, (pair, name)) in m.pairs.iter().zip(names).enumerate() {
        mesh.field_data.push(Column::owned(
            &format!("interface.{name}"),
            3,
            vec![k as i32 + 1, pair[0], pair[1]],
        ));
    }
    for p in &img.phases {
        mesh.field_data
            .push(Column::owned(&format!("phase.{}", p.name), 1, vec![p.id]));
    }
    mesh
}

// ---------------------------------------------------------------------------------------
// vtu

fn vtu_encoding(o: &ExportOptions) -> Result<VtuEncoding, (String, String)> {
    let v = opt(o, "encoding");
    v.as_str().and_then(VtuEncoding::from_name).ok_or_else(|| {
        (
            "encoding".into(),
            format!("{v} is not one of: {}", VtuEncoding::NAMES.join(", ")),
        )
    })
}

fn zlib_level(o: &ExportOptions) -> Result<u32, (String, String)> {
    let v = opt(o, "compression");
    v.as_u64()
        .filter(|&l| l <= 9)
        .map(|l| l as u32)
        .ok_or_else(|| {
            (
                "compression".into(),
                format!("{v}: give a zlib level 0..=9 (0 = uncompressed)"),
            )
        })
}

/// The preflight of the exports with `mesh: surface` (vtu, gmsh): the surface's, or the voxel
/// mesh's ([`mesh_preflight`], `extra_per_corner` as there).
fn voxel_or_surface_preflight(
    meta: &ArtifactMeta,
    o: &ExportOptions,
    extra_per_corner: u64,
) -> Result<u64, (String, String)> {
    if check_surface_options(o)? {
        return surface_preflight(meta, o);
    }
    mesh_preflight(meta, o, extra_per_corner)
}

fn keyed(r: Result<(), (String, String)>) -> Result<(), String> {
    r.map_err(|(k, m)| format!("option `{k}`: {m}"))
}

/// `vtu`: VTK XML UnstructuredGrid.
pub struct VtuExporter;

impl Exporter for VtuExporter {
    fn name(&self) -> &'static str {
        "vtu"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["vtu"]
    }
    fn accepts(&self, kind: ArtifactKind) -> bool {
        matches!(
            kind,
            ArtifactKind::PhaseImage
                | ArtifactKind::Field
                | ArtifactKind::Packing
                | ArtifactKind::ContactGraph
        )
    }
    fn doc(&self) -> &'static str {
        "VTK XML UnstructuredGrid, read by meshio, ParaView and pyvista. A phase image: one \
         hexahedron per voxel of the selected phases, points at the voxel corners (origin + \
         index * spacing, shared corners once), cell data `phase` (UInt8 labels), field data \
         `phase.<name>` = label and `periodic`; a field: every voxel, cell data = the field's \
         components; a packing: one vertex per sphere with point data radius, body_id, layer, \
         frozen, clump_index, body attributes; a contact graph: lines with gap, bonded and bond \
         attributes. `mesh: surface` (phase images): the interfaces between phases and with the \
         outside of the image as welded triangles (marching tetrahedra over the voxel centres, \
         as `stl`, extended to many phases), cell data `interface` (id), `phase_a` < \
         `phase_b` (the labels it separates, -1 = exterior; the normal points out of b into \
         a), field data `interface.<a>|<b>` = [id, a, b]; `smooth: N` Taubin-smooths it, `decimate: f` keeps \
         about a fraction f of its triangles (meshoptimizer). \
         Provenance in an XML comment (meshio reads no string arrays)."
    }
    fn options(&self) -> Vec<ExportOption> {
        vec![
            phases_option(),
            mesh_option(
                "`hexahedra`: one hexahedron per voxel of the selected phases (a packing's \
                 vertices, a graph's lines); `surface`: the triangles of every interface with \
                 a selected phase on one side (phase images)",
            ),
            smooth_option(),
            decimate_option(),
            ExportOption {
                name: "encoding",
                doc: "`appended` (raw binary after the XML, smallest and fastest), `binary` \
                      (base64 inside each array) or `ascii` (text)",
                default: json!("appended"),
            },
            ExportOption {
                name: "compression",
                doc: "zlib level 0..=9 of binary arrays (0 = uncompressed); VTK, ParaView and \
                      meshio inflate them",
                default: json!(0),
            },
        ]
    }
    fn check_options(&self, o: &ExportOptions) -> Result<(), (String, String)> {
        selection(o)?;
        check_surface_options(o)?;
        vtu_encoding(o)?;
        zlib_level(o)?;
        Ok(())
    }
    fn preflight(&self, meta: &ArtifactMeta, o: &ExportOptions) -> Result<u64, (String, String)> {
        voxel_or_surface_preflight(meta, o, 0)
    }
    fn write(
        &self,
        a: &Artifact,
        path: &Path,
        prov: &Provenance,
        o: &ExportOptions,
    ) -> Result<(), String> {
        keyed(self.check_options(o))?;
        let enc = vtu_encoding(o).expect("checked");
        let level = zlib_level(o).expect("checked");
        let comment = provenance_text(prov);
        if surface_mode(o).expect("checked") {
            let (m, names) = image_surface(a, o)?;
            let Artifact::PhaseImage(img) = a else {
                unreachable!("image_surface holds images only")
            };
            let mesh = surface_mesh(&m, &names, img);
            return atomic_write(path, |tmp| write_vtu(tmp, &mesh, enc, level, &comment));
        }
        with_mesh(a, o, |mesh| {
            atomic_write(path, |tmp| write_vtu(tmp, mesh, enc, level, &comment))
        })
    }
}

// ---------------------------------------------------------------------------------------
// legacy vtk

fn legacy_binary(o: &ExportOptions) -> Result<bool, (String, String)> {
    choice(o, "encoding", &[("binary", true), ("ascii", false)], None)
}

/// `vtk`: legacy VTK UNSTRUCTURED_GRID.
pub struct LegacyVtkExporter;

impl Exporter for LegacyVtkExporter {
    fn name(&self) -> &'static str {
        "vtk"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["vtk"]
    }
    fn accepts(&self, kind: ArtifactKind) -> bool {
        VtuExporter.accepts(kind)
    }
    fn doc(&self) -> &'static str {
        "Legacy VTK UNSTRUCTURED_GRID (file version 5.1, what VTK 9 writes), read by meshio, \
         ParaView and pyvista: the same cells and arrays as `vtu` (array names with spaces \
         get `_`); binary (big-endian) or ascii"
    }
    fn options(&self) -> Vec<ExportOption> {
        vec![
            phases_option(),
            ExportOption {
                name: "encoding",
                doc: "`binary` (big-endian, as the legacy format defines) or `ascii`",
                default: json!("binary"),
            },
        ]
    }
    fn check_options(&self, o: &ExportOptions) -> Result<(), (String, String)> {
        selection(o)?;
        legacy_binary(o)?;
        Ok(())
    }
    fn preflight(&self, meta: &ArtifactMeta, o: &ExportOptions) -> Result<u64, (String, String)> {
        mesh_preflight(meta, o, 0)
    }
    fn write(
        &self,
        a: &Artifact,
        path: &Path,
        prov: &Provenance,
        o: &ExportOptions,
    ) -> Result<(), String> {
        keyed(self.check_options(o))?;
        let binary = legacy_binary(o).expect("checked");
        let title = format!(
            "grainpipe {} {}",
            prov.entries
                .get("pipeline")
                .map(String::as_str)
                .unwrap_or(""),
            prov.entries.get("step").map(String::as_str).unwrap_or("")
        );
        with_mesh(a, o, |mesh| {
            atomic_write(path, |tmp| write_legacy_vtk(tmp, mesh, binary, &title))
        })
    }
}

// ---------------------------------------------------------------------------------------
// xdmf

/// The heavy-data file of an `.xdmf`: `<stem>.h5` beside it.
pub fn xdmf_heavy_path(path: &Path) -> PathBuf {
    path.with_extension("h5")
}

fn xdmf_image(o: &ExportOptions) -> Result<bool, (String, String)> {
    choice(o, "mesh", &[("hexahedra", false), ("image", true)], None)
}

/// `xdmf`: XDMF 3 + HDF5.
pub struct XdmfExporter;

impl Exporter for XdmfExporter {
    fn name(&self) -> &'static str {
        "xdmf"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["xdmf", "xmf"]
    }
    fn accepts(&self, kind: ArtifactKind) -> bool {
        VtuExporter.accepts(kind)
    }
    fn doc(&self) -> &'static str {
        "XDMF 3 with the heavy data in `<stem>.h5` beside it (chunked, deflated). `mesh: \
         hexahedra`: an unstructured grid (hexahedra per voxel of the selected phases, or a \
         packing's vertices, a contact graph's lines) that meshio, ParaView and dolfinx read; \
         `mesh: image`: a 3DCoRectMesh with the voxels as one cell array (ParaView/VTK; \
         meshio 5 reads only XYZ geometry)"
    }
    fn options(&self) -> Vec<ExportOption> {
        vec![
            phases_option(),
            ExportOption {
                name: "mesh",
                doc: "`hexahedra` (unstructured, for meshio, dolfinx and ParaView) or `image` \
                      (3DCoRectMesh of a phase image or field, all voxels, for ParaView/VTK)",
                default: json!("hexahedra"),
            },
            h5util::compression_option(),
        ]
    }
    fn check_options(&self, o: &ExportOptions) -> Result<(), (String, String)> {
        selection(o)?;
        xdmf_image(o)?;
        h5util::check_compression(o)?;
        Ok(())
    }
    fn written_paths(&self, path: &Path, _: &ExportOptions) -> Vec<WrittenPath> {
        vec![
            WrittenPath::file(path),
            WrittenPath::file(xdmf_heavy_path(path)),
        ]
    }
    fn preflight(&self, meta: &ArtifactMeta, o: &ExportOptions) -> Result<u64, (String, String)> {
        if xdmf_image(o)? {
            if !matches!(meta.kind, ArtifactKind::PhaseImage | ArtifactKind::Field) {
                return Err((
                    "mesh".into(),
                    format!("`image` holds phase images and fields, not a {}", meta.kind),
                ));
            }
            if selection(o)? != PhaseSelection::All {
                return Err((
                    "phases".into(),
                    "`mesh: image` writes every voxel; select phases with `mesh: hexahedra`".into(),
                ));
            }
            return Ok(STREAM_BUFFERS);
        }
        mesh_preflight(meta, o, 0)
    }
    fn write(
        &self,
        a: &Artifact,
        path: &Path,
        prov: &Provenance,
        o: &ExportOptions,
    ) -> Result<(), String> {
        keyed(self.check_options(o))?;
        let image = xdmf_image(o).expect("checked");
        let deflate = h5util::deflate_option(o);
        let heavy = xdmf_heavy_path(path);
        if path.extension().and_then(|e| e.to_str()) == Some("h5") {
            return Err(
                "an .xdmf export needs another extension than .h5 (its heavy data \
                        goes to <stem>.h5)"
                    .into(),
            );
        }
        let h5_name = heavy
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let comment = provenance_text(prov);
        let mut xml = String::new();
        let write_heavy = |tmp: &Path, xml: &mut String| -> H5Result<()> {
            let f = hdf5_metno::File::create(tmp)?;
            provenance_attrs(&f, prov)?;
            if image {
                let v = crate::volume::VolumeRef::from_artifact(a, "xdmf")
                    .map_err(hdf5_metno::Error::from)?;
                v.validate().map_err(hdf5_metno::Error::from)?;
                let g = v.grid();
                let [nx, ny, nz] = g.dims;
                let mut shape = vec![nz, ny, nx];
                if v.components() > 1 {
                    shape.push(v.components());
                }
                let name = v.name().replace('/', "_");
                let (ds, dtype) = match a {
                    Artifact::PhaseImage(p) => {
                        let d = h5util::dataset(&f, &name, &shape, &p.labels, deflate)?;
                        let ids: Vec<u8> = p.phases.iter().map(|ph| ph.id).collect();
                        let names: Vec<&str> = p.phases.iter().map(|ph| ph.name.as_str()).collect();
                        h5util::attr_array(&d, "phase_ids", &ids)?;
                        h5util::attr_strs(&d, "phase_names", &names)?;
                        (d, Dtype::U8)
                    }
                    Artifact::Field(fl) => match &fl.data {
                        FieldData::F32(x) => {
                            (h5util::dataset(&f, &name, &shape, x, deflate)?, Dtype::F32)
                        }
                        FieldData::F64(x) => {
                            (h5util::dataset(&f, &name, &shape, x, deflate)?, Dtype::F64)
                        }
                    },
                    _ => unreachable!("VolumeRef accepted it"),
                };
                h5util::attr_str(
                    &ds,
                    "units",
                    if v.unit().is_empty() { "1" } else { v.unit() },
                )?;
                h5util::attr_array(&f, "periodic", &g.periodic.map(u8::from))?;
                *xml = xdmf::image_xdmf(
                    g.dims,
                    g.origin,
                    g.spacing,
                    (v.name(), v.components(), dtype, &format!("/{name}")),
                    &h5_name,
                    &comment,
                );
                Ok(())
            } else {
                let r = with_mesh(a, o, |mesh| {
                    xdmf::write_mesh_heavy(&f, mesh, &h5_name, deflate, &comment)
                        .map_err(|e| e.to_string())
                });
                let text = r.map_err(hdf5_metno::Error::from)?;
                if let Artifact::PhaseImage(p) = a {
                    let ids: Vec<u8> = p.phases.iter().map(|ph| ph.id).collect();
                    let names: Vec<&str> = p.phases.iter().map(|ph| ph.name.as_str()).collect();
                    h5util::attr_array(&f, "phase_ids", &ids)?;
                    h5util::attr_strs(&f, "phase_names", &names)?;
                }
                *xml = text;
                Ok(())
            }
        };
        atomic_write(&heavy, |tmp| write_heavy(tmp, &mut xml))?;
        atomic_write(path, |tmp| std::fs::write(tmp, xml.as_bytes()))
    }
}

// ---------------------------------------------------------------------------------------
// Abaqus and Gmsh: voxel meshes of phase images

fn voxel_mesh_write(
    a: &Artifact,
    o: &ExportOptions,
    write: impl FnOnce(&VoxelHexMesh, &[(u8, String)], [bool; 3]) -> Result<(), String>,
) -> Result<(), String> {
    let Artifact::PhaseImage(img) = a else {
        return Err(format!("holds phase images, not a {}", a.kind()));
    };
    let (phases, mask) = image_phases(img, o)?;
    let g = &img.grid;
    let vm = VoxelHexMesh::new(g.dims, g.origin, g.spacing, Some(&img.labels), mask)?;
    write(&vm, &phases, g.periodic)
}

/// `abaqus`: Abaqus input deck.
pub struct AbaqusExporter;

impl Exporter for AbaqusExporter {
    fn name(&self) -> &'static str {
        "abaqus"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["inp"]
    }
    fn accepts(&self, kind: ArtifactKind) -> bool {
        kind == ArtifactKind::PhaseImage
    }
    fn doc(&self) -> &'static str {
        "Abaqus input deck of a phase image: C3D8 bricks, one per voxel of the selected \
         phases (lengths in m); per phase an element set, a placeholder *MATERIAL and a *SOLID \
         SECTION; node sets XMIN..ZMAX on the six faces of the image box; on periodic axes node \
         sets PERIODIC_<X|Y|Z>_LO/_HI whose i-th nodes are periodic pairs (for *EQUATION)"
    }
    fn options(&self) -> Vec<ExportOption> {
        vec![phases_option()]
    }
    fn check_options(&self, o: &ExportOptions) -> Result<(), (String, String)> {
        selection(o).map(|_| ())
    }
    fn preflight(&self, meta: &ArtifactMeta, o: &ExportOptions) -> Result<u64, (String, String)> {
        mesh_preflight(meta, o, 0)
    }
    fn write(
        &self,
        a: &Artifact,
        path: &Path,
        prov: &Provenance,
        o: &ExportOptions,
    ) -> Result<(), String> {
        let comments = vec![provenance_text(prov)];
        voxel_mesh_write(a, o, |vm, phases, periodic| {
            atomic_write(path, |tmp| {
                abaqus::write_inp(tmp, vm, phases, periodic, &comments)
            })
        })
    }
}

/// `gmsh`: Gmsh MSH 4.1 ASCII.
pub struct GmshExporter;

impl Exporter for GmshExporter {
    fn name(&self) -> &'static str {
        "gmsh"
    }
    fn extensions(&self) -> &'static [&'static str] {
        &["msh"]
    }
    fn accepts(&self, kind: ArtifactKind) -> bool {
        kind == ArtifactKind::PhaseImage
    }
    fn doc(&self) -> &'static str {
        "Gmsh MSH 4.1 ASCII of a phase image: 8-node hexahedra, one per voxel of the selected \
         phases (lengths in m), one volume entity and one named physical group per phase \
         (tag = label + 1); read by Gmsh, meshio and the FE codes that import .msh. `mesh: \
         surface`: the interfaces between phases and with the outside of the image as welded \
         3-node triangles, one surface entity and one physical group (dimension 2) per \
         interface named `<a>|<b>` (tag = the `vtu` interface id), element data views \
         `phase_a` and `phase_b`; `smooth: N` Taubin-smooths it, `decimate: f` keeps about a \
         fraction f of its triangles (meshoptimizer)"
    }
    fn options(&self) -> Vec<ExportOption> {
        vec![
            phases_option(),
            mesh_option(
                "`hexahedra`: one hexahedron per voxel of the selected phases; `surface`: the \
                 triangles of every interface with a selected phase on one side",
            ),
            smooth_option(),
            decimate_option(),
        ]
    }
    fn check_options(&self, o: &ExportOptions) -> Result<(), (String, String)> {
        selection(o)?;
        check_surface_options(o).map(|_| ())
    }
    fn preflight(&self, meta: &ArtifactMeta, o: &ExportOptions) -> Result<u64, (String, String)> {
        voxel_or_surface_preflight(meta, o, 1)
    }
    fn write(
        &self,
        a: &Artifact,
        path: &Path,
        prov: &Provenance,
        o: &ExportOptions,
    ) -> Result<(), String> {
        keyed(self.check_options(o))?;
        let comment = provenance_text(prov);
        if surface_mode(o).expect("checked") {
            let (m, names) = image_surface(a, o)?;
            return atomic_write(path, |tmp| {
                gmsh::write_surface_msh(tmp, &m, &names, &comment)
            });
        }
        voxel_mesh_write(a, o, |vm, phases, _| {
            atomic_write(path, |tmp| gmsh::write_msh(tmp, vm, phases, &comment))
        })
    }
}
