//! Plain HDF5 (`.h5`, `.hdf5`) for every artifact kind, and its readers.
//!
//! Layout (all lengths in metres, arrays row-major with the last index fastest). Every
//! dataset with a physical meaning has a `units` attribute (udunits: "m", "m^3", "1" for
//! dimensionless and for indices); datasets of more than 4 KiB are chunked and deflated
//! (level 4 unless the export's `compression` says otherwise):
//! - root attributes: `grainpipe_kind` (artifact kind: what the file holds, since `.h5` says
//!   nothing by itself) and one attribute per provenance entry (`seed` and `stage_seed` as
//!   u64, the rest as strings);
//! - PhaseImage: dataset `phase` (nz, ny, nx) u8 with attributes `spacing`, `origin` (x, y, z
//!   order), `periodic`, `phase_ids`, `phase_names`, `axis_order` = "z y x";
//! - Field: dataset named after the field, (nz, ny, nx) or (nz, ny, nx, components), with
//!   `units`, `spacing`, `origin`, `periodic`, `components`; root attribute `dataset` names it;
//! - Packing: `positions` (N,3), `radius` (N; the clump's bounding radius for clump bodies),
//!   `clump_index` (N; -1 for spheres), `orientation` (N,4) (w,x,y,z), `layer`, `frozen`,
//!   group `domain` (attributes `min`, `max`, `units`, `periodic`; dataset
//!   `excluded_spheres` (M,4) = centre, radius), group `library` when present, group
//!   `attributes` (one dataset per body attribute with `units` and `name`, int64 when
//!   dimensionless and integer-valued, else float64; order in the group's `order` attribute);
//! - ClumpLibrary (group `library`): `sphere_offset` (S,3), `sphere_radius` (S),
//!   `first_sphere` (C+1), `volume`, `bounding_radius`, `principal_inertia` (C,3; per unit
//!   density, m^5), `principal_axes` (C,3,3), `clump_source` (C) and attribute `source`;
//! - ContactGraph: `pairs` (M,2), `gaps` (M), `bonds` (B,2), `positions` (N,3), `radius` (N,
//!   only when the bodies are spheres of known radius), group
//!   `bond_attributes` (one dataset per name, B values, like a packing's `attributes`), group
//!   `faces` with datasets `xmin` .. `zmax`;
//! - Table: group `table` (attribute `name`, `column_order`), one dataset per column with
//!   attributes `units` (numeric columns) and `name`;
//! - Tensor: dataset `tensor` of the tensor's shape with `name`, `units`, `convention`;
//! - Collection: group `items` with one group per item (`0000`, ...) with attribute `name`,
//!   holding that item's layout
//! - Series: group `frames` with one group per frame (`0000`, ...) holding that frame's layout
//!   and a `time` attribute [s].
//!
//! The readers take `unit` where `units` is missing (files written before `units`).

pub use crate::h5util::DEFAULT_DEFLATE;
use crate::h5util::*;
use crate::volume::{Probe, StatedGrid, Volume, VolumeData, VolumeRef};
use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::*;
use hdf5_metno::types::{FloatSize, IntSize, TypeDescriptor};
use hdf5_metno::{File, Group};
use indexmap::IndexMap;
use std::path::Path;

fn err(msg: impl Into<String>) -> hdf5_metno::Error {
    hdf5_metno::Error::from(msg.into())
}

fn kind_name(k: ArtifactKind) -> String {
    k.to_string()
}

/// Writes any artifact as plain HDF5, datasets deflated at [`DEFAULT_DEFLATE`].
pub fn write_h5(a: &Artifact, path: &Path, prov: &Provenance) -> Result<(), String> {
    write_h5_with(a, path, prov, DEFAULT_DEFLATE)
}

/// Writes any artifact as plain HDF5 with datasets deflated at `deflate` (0 = contiguous,
/// uncompressed; 1-9 chunked and deflated).
pub fn write_h5_with(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    deflate: u8,
) -> Result<(), String> {
    atomic_write(path, |tmp| -> H5Result<()> {
        let f = File::create(tmp)?;
        provenance_attrs(&f, prov)?;
        write_into(&f, a, deflate)
    })
}

/// A dataset with its `units` attribute (a udunits string, "1" for dimensionless).
fn quantity<T: hdf5_metno::H5Type>(
    g: &Group,
    name: &str,
    shape: &[usize],
    data: &[T],
    units: &str,
    z: u8,
) -> H5Result<hdf5_metno::Dataset> {
    let d = dataset(g, name, shape, data, z)?;
    attr_str(&d, "units", units_or_one(units))?;
    Ok(d)
}

/// The empty unit of the data model is written "1", as CF and udunits spell dimensionless.
fn units_or_one(u: &str) -> &str {
    if u.is_empty() {
        "1"
    } else {
        u
    }
}

fn write_into(g: &Group, a: &Artifact, z: u8) -> H5Result<()> {
    attr_str(g, "grainpipe_kind", &kind_name(a.kind()))?;
    match a {
        Artifact::PhaseImage(_) | Artifact::Field(_) => {
            write_volume(g, VolumeRef::from_artifact(a, "h5").map_err(err)?, z)
        }
        Artifact::Packing(p) => write_packing(g, p, z),
        Artifact::ClumpLibrary(l) => write_library(&g.create_group("library")?, l, z),
        Artifact::ContactGraph(c) => write_graph(g, c, z),
        Artifact::Table(t) => write_table(g, t, z),
        Artifact::Tensor(t) => write_tensor(g, t, z),
        Artifact::Series(s) => {
            let frames = g.create_group("frames")?;
            for (k, (t, frame)) in s.frames.iter().enumerate() {
                let fg = frames.create_group(&format!("{k:04}"))?;
                attr_scalar(&fg, "time", *t)?;
                write_into(&fg, frame, z)?;
            }
            Ok(())
        }
        Artifact::Collection(c) => {
            let items = g.create_group("items")?;
            for (k, (name, item)) in c.items.iter().enumerate() {
                let ig = items.create_group(&format!("{k:04}"))?;
                attr_str(&ig, "name", name)?;
                write_into(&ig, item, z)?;
            }
            Ok(())
        }
    }
}

fn write_volume(g: &Group, v: VolumeRef, z: u8) -> H5Result<()> {
    v.validate().map_err(err)?;
    let grid = v.grid();
    let [nx, ny, nz] = grid.dims;
    let mut shape = vec![nz, ny, nx];
    if v.components() > 1 {
        shape.push(v.components());
    }
    let name = v.name();
    if name.is_empty() || name.contains('/') || name == "." {
        return Err(err(format!(
            "field name `{name}` cannot name an HDF5 dataset (empty, `.` or containing `/`)"
        )));
    }
    // Data are stored x fastest, which is C order for shape (z, y, x[, c]): no reordering.
    let ds = match v {
        VolumeRef::Phase(p) => {
            let d = dataset(g, name, &shape, &p.labels, z)?;
            let ids: Vec<u8> = p.phases.iter().map(|ph| ph.id).collect();
            attr_array(&d, "phase_ids", &ids)?;
            let names: Vec<&str> = p.phases.iter().map(|ph| ph.name.as_str()).collect();
            attr_strs(&d, "phase_names", &names)?;
            d
        }
        VolumeRef::Field(f) => match &f.data {
            FieldData::F32(x) => dataset(g, name, &shape, x, z)?,
            FieldData::F64(x) => dataset(g, name, &shape, x, z)?,
        },
    };
    attr_array(&ds, "spacing", &grid.spacing)?;
    attr_array(&ds, "origin", &grid.origin)?;
    attr_array(&ds, "periodic", &grid.periodic.map(|b| b as u8))?;
    attr_str(&ds, "units", units_or_one(v.unit()))?;
    attr_str(&ds, "spacing_units", "m")?;
    attr_str(&ds, "axis_order", "z y x")?;
    attr_scalar(&ds, "components", v.components() as u64)?;
    if let VolumeRef::Field(f) = v {
        attr_str(&ds, "component_convention", f.convention.name())?;
        let names = f.component_names();
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        attr_strs(&ds, "component_names", &names)?;
    }
    attr_str(g, "dataset", name)?;
    Ok(())
}

fn write_packing(g: &Group, p: &Packing, z: u8) -> H5Result<()> {
    let n = p.bodies.len();
    let positions: Vec<f64> = p.bodies.iter().flat_map(|b| b.position).collect();
    let orientation: Vec<f64> = p.bodies.iter().flat_map(|b| b.orientation).collect();
    let mut radius = Vec::with_capacity(n);
    let mut clump = Vec::with_capacity(n);
    for b in &p.bodies {
        match b.shape {
            BodyShape::Sphere { radius: r } => {
                radius.push(r);
                clump.push(-1i64);
            }
            BodyShape::Clump { index } => {
                let c = p
                    .library
                    .as_ref()
                    .and_then(|l| l.clumps.get(index))
                    .ok_or_else(|| err(format!("clump index {index} is not in the library")))?;
                radius.push(c.bounding_radius);
                clump.push(index as i64);
            }
        }
    }
    quantity(g, "positions", &[n, 3], &positions, "m", z)?;
    quantity(g, "radius", &[n], &radius, "m", z)?;
    quantity(g, "clump_index", &[n], &clump, "1", z)?;
    quantity(g, "orientation", &[n, 4], &orientation, "1", z)?;
    let layer: Vec<u32> = p.bodies.iter().map(|b| b.layer).collect();
    quantity(g, "layer", &[n], &layer, "1", z)?;
    let frozen: Vec<u8> = p.bodies.iter().map(|b| b.frozen as u8).collect();
    quantity(g, "frozen", &[n], &frozen, "1", z)?;
    let d = g.create_group("domain")?;
    attr_array(&d, "min", &p.domain.min)?;
    attr_array(&d, "max", &p.domain.max)?;
    attr_str(&d, "units", "m")?;
    attr_array(&d, "periodic", &p.domain.periodic.map(|b| b as u8))?;
    let ex: Vec<f64> = p
        .domain
        .excluded
        .iter()
        .flat_map(|e| match e {
            ExcludedSolid::Sphere { center, radius } => [center[0], center[1], center[2], *radius],
        })
        .collect();
    quantity(&d, "excluded_spheres", &[ex.len() / 4, 4], &ex, "m", z)?;
    if let Some(l) = &p.library {
        write_library(&g.create_group("library")?, l, z)?;
    }
    write_named_values(g, "attributes", &p.attributes, n, "bodies", z)
}

/// Named per-item values (body or bond attributes) as group `group`: one dataset per name
/// with attributes `units` and `name`, and the order in the group's `order` attribute.
/// Dimensionless values that are all integers (brick or class labels, bond counts) are
/// stored as int64, the rest as float64; both read back as the same f64 values.
fn write_named_values(
    g: &Group,
    group: &str,
    values: &IndexMap<String, BodyAttribute>,
    n: usize,
    items: &str,
    z: u8,
) -> H5Result<()> {
    let ag = g.create_group(group)?;
    let mut order = Vec::new();
    for (name, a) in values_checked(values, n, items)? {
        let key = dataset_key(name);
        let ds = match integer_values(a) {
            Some(v) => quantity(&ag, &key, &[n], &v, &a.unit, z)?,
            None => quantity(&ag, &key, &[n], &a.values, &a.unit, z)?,
        };
        attr_str(&ds, "name", name)?;
        order.push(key);
    }
    let order: Vec<&str> = order.iter().map(|s| s.as_str()).collect();
    attr_strs(&ag, "order", &order)
}

fn values_checked<'a>(
    values: &'a IndexMap<String, BodyAttribute>,
    n: usize,
    items: &str,
) -> H5Result<&'a IndexMap<String, BodyAttribute>> {
    for (name, a) in values {
        if a.values.len() != n {
            return Err(err(format!(
                "attribute `{name}` has {} values for {n} {items}",
                a.values.len()
            )));
        }
    }
    Ok(values)
}

/// The values as integers when the attribute is dimensionless and every value is an
/// integer that f64 holds exactly (|v| <= 2^53), so int64 and back is lossless.
pub(crate) fn integer_values(a: &BodyAttribute) -> Option<Vec<i64>> {
    const EXACT: f64 = 9_007_199_254_740_992.0; // 2^53
    if !(a.unit.is_empty() || a.unit == "1") || a.values.is_empty() {
        return None;
    }
    a.values
        .iter()
        .map(|&v| (v.fract() == 0.0 && v.abs() <= EXACT).then_some(v as i64))
        .collect()
}

/// Reads what [`write_named_values`] wrote.
fn read_named_values(ag: &Group) -> H5Result<IndexMap<String, BodyAttribute>> {
    let mut out = IndexMap::new();
    for key in read_attr_strs(ag, "order").unwrap_or_default() {
        let ds = ag.dataset(&key)?;
        let name = read_attr_str(&ds, "name").unwrap_or(key.clone());
        out.insert(
            name,
            BodyAttribute {
                unit: read_units(&ds),
                values: ds.read_raw::<f64>()?,
            },
        );
    }
    Ok(out)
}

/// The unit of a dataset: `units` (as CF and h5py users expect), else `unit` (files written
/// before `units`), else none. Dimensionless, written "1", reads back as the data model's
/// empty unit: the model spells it both ways and every writer treats them alike.
pub(crate) fn read_units(ds: &hdf5_metno::Dataset) -> String {
    let u = read_attr_str(ds, "units")
        .or_else(|| read_attr_str(ds, "unit"))
        .unwrap_or_default();
    if u == "1" {
        String::new()
    } else {
        u
    }
}

/// HDF5 link names cannot contain `/` or be `.`; the true name is kept in a `name` attribute.
fn dataset_key(name: &str) -> String {
    let k = name.replace('/', "_");
    if k.is_empty() || k == "." {
        format!("_{k}")
    } else {
        k
    }
}

fn write_library(g: &Group, l: &ClumpLibrary, z: u8) -> H5Result<()> {
    attr_str(g, "source", &l.source)?;
    let c = l.clumps.len();
    let mut first = vec![0i64];
    let mut off = Vec::new();
    let mut rad = Vec::new();
    for cl in &l.clumps {
        for s in &cl.spheres {
            off.extend(s.offset);
            rad.push(s.radius);
        }
        first.push(rad.len() as i64);
    }
    quantity(g, "sphere_offset", &[rad.len(), 3], &off, "m", z)?;
    quantity(g, "sphere_radius", &[rad.len()], &rad, "m", z)?;
    quantity(g, "first_sphere", &[c + 1], &first, "1", z)?;
    let vol: Vec<f64> = l.clumps.iter().map(|c| c.volume).collect();
    quantity(g, "volume", &[c], &vol, "m^3", z)?;
    let br: Vec<f64> = l.clumps.iter().map(|c| c.bounding_radius).collect();
    quantity(g, "bounding_radius", &[c], &br, "m", z)?;
    // Moments per unit density: kg m^2 / (kg m^-3).
    let pi: Vec<f64> = l.clumps.iter().flat_map(|c| c.principal_inertia).collect();
    quantity(g, "principal_inertia", &[c, 3], &pi, "m^5", z)?;
    let pa: Vec<f64> = l
        .clumps
        .iter()
        .flat_map(|c| c.principal_axes.into_iter().flatten())
        .collect();
    quantity(g, "principal_axes", &[c, 3, 3], &pa, "1", z)?;
    let src: Vec<String> = l.clumps.iter().map(|c| c.source.clone()).collect();
    string_dataset(g, "clump_source", &src)?;
    Ok(())
}

fn write_graph(g: &Group, c: &ContactGraph, z: u8) -> H5Result<()> {
    c.validate().map_err(err)?;
    let m = c.contacts.len();
    let pairs: Vec<i64> = c
        .contacts
        .iter()
        .flat_map(|k| [k.i as i64, k.j as i64])
        .collect();
    let gaps: Vec<f64> = c.contacts.iter().map(|k| k.gap).collect();
    quantity(g, "pairs", &[m, 2], &pairs, "1", z)?;
    quantity(g, "gaps", &[m], &gaps, "m", z)?;
    let bonds: Vec<i64> = c.bonds.iter().flatten().map(|&i| i as i64).collect();
    quantity(g, "bonds", &[c.bonds.len(), 2], &bonds, "1", z)?;
    let pos: Vec<f64> = c.positions.iter().flatten().copied().collect();
    quantity(g, "positions", &[c.positions.len(), 3], &pos, "m", z)?;
    if !c.radii.is_empty() {
        quantity(g, "radius", &[c.radii.len()], &c.radii, "m", z)?;
    }
    let faces = g.create_group("faces")?;
    for (f, name) in c.faces.iter().zip(FACE_NAMES) {
        let v: Vec<i64> = f.iter().map(|&i| i as i64).collect();
        quantity(&faces, name, &[v.len()], &v, "1", z)?;
    }
    write_named_values(
        g,
        "bond_attributes",
        &c.bond_attributes,
        c.bonds.len(),
        "bonds",
        z,
    )
}

fn write_table(g: &Group, t: &Table, z: u8) -> H5Result<()> {
    t.validate().map_err(err)?;
    let tg = g.create_group("table")?;
    attr_str(&tg, "name", &t.name)?;
    let mut order = Vec::new();
    for (k, c) in t.columns.iter().enumerate() {
        let mut key = dataset_key(&c.name);
        if order.contains(&key) {
            key = format!("{key}_{k}");
        }
        let n = c.data.len();
        let ds = match &c.data {
            ColumnData::F64(v) => quantity(&tg, &key, &[n], v, &c.unit, z)?,
            ColumnData::I64(v) => quantity(&tg, &key, &[n], v, &c.unit, z)?,
            // Text has no unit.
            ColumnData::Str(v) => string_dataset(&tg, &key, v)?,
        };
        attr_str(&ds, "name", &c.name)?;
        order.push(key);
    }
    let order: Vec<&str> = order.iter().map(|s| s.as_str()).collect();
    attr_strs(&tg, "column_order", &order)
}

fn write_tensor(g: &Group, t: &Tensor, z: u8) -> H5Result<()> {
    if t.shape.iter().product::<usize>() != t.values.len() {
        return Err(err(format!(
            "tensor `{}` has {} values for shape {:?}",
            t.name,
            t.values.len(),
            t.shape
        )));
    }
    let ds = quantity(g, "tensor", &t.shape, &t.values, &t.unit, z)?;
    attr_str(&ds, "name", &t.name)?;
    attr_str(&ds, "convention", &format!("{:?}", t.convention))?;
    let shape: Vec<u64> = t.shape.iter().map(|&s| s as u64).collect();
    attr_array(&ds, "shape", &shape)
}

// ---------------------------------------------------------------------------------------
// Readers

fn open(path: &Path) -> Result<File, String> {
    File::open(path).map_err(|e| crate::h5util::cannot_open(path, "HDF5", &e))
}

fn at(path: &Path) -> impl Fn(hdf5_metno::Error) -> String + '_ {
    move |e| format!("{}: {e}", path.display())
}

/// Reads any artifact written by [`write_h5`].
pub fn read_h5(path: &Path) -> Result<Artifact, String> {
    let f = open(path)?;
    read_from(&f).map_err(at(path))
}

macro_rules! typed_reader {
    ($($fn_name:ident -> $variant:ident),*) => {$(
        #[doc = concat!("Reads a ", stringify!($variant), " written by [`write_h5`].")]
        pub fn $fn_name(path: &Path) -> Result<$variant, String> {
            match read_h5(path)? {
                Artifact::$variant(x) => Ok(x),
                other => Err(format!(
                    "{}: holds a {}, not a {}",
                    path.display(),
                    other.kind(),
                    stringify!($variant)
                )),
            }
        }
    )*};
}
typed_reader!(
    read_h5_packing -> Packing,
    read_h5_table -> Table,
    read_h5_contact_graph -> ContactGraph,
    read_h5_clump_library -> ClumpLibrary,
    read_h5_tensor -> Tensor,
    read_h5_series -> Series,
    read_h5_collection -> Collection
);

fn read_from(g: &Group) -> H5Result<Artifact> {
    let kind = read_attr_str(g, "grainpipe_kind")
        .ok_or_else(|| err("no `grainpipe_kind` attribute: not written by grainpipe"))?;
    Ok(match kind.as_str() {
        "PhaseImage" | "Field" => {
            let name = read_attr_str(g, "dataset").ok_or_else(|| err("no `dataset` attribute"))?;
            let v = volume_from(g, &name)?;
            if kind == "PhaseImage" {
                Artifact::PhaseImage(v.into_phase_image().map_err(err)?)
            } else {
                Artifact::Field(v.into_field().map_err(err)?)
            }
        }
        "Packing" => Artifact::Packing(read_packing(g)?),
        "ClumpLibrary" => Artifact::ClumpLibrary(read_library(&g.group("library")?)?),
        "ContactGraph" => Artifact::ContactGraph(read_graph(g)?),
        "Table" => Artifact::Table(read_table(&g.group("table")?)?),
        "Tensor" => Artifact::Tensor(read_tensor(g)?),
        "Series" => {
            let frames = g.group("frames")?;
            let mut names = frames.member_names()?;
            names.sort();
            let mut out = Vec::new();
            for n in names {
                let fg = frames.group(&n)?;
                let t = fg.attr("time")?.read_scalar::<f64>()?;
                out.push((t, read_from(&fg)?));
            }
            Artifact::Series(Series { frames: out })
        }
        "Collection" => {
            let items = g.group("items")?;
            let mut names = items.member_names()?;
            names.sort();
            let mut out = Vec::new();
            for n in names {
                let ig = items.group(&n)?;
                let name = read_attr_str(&ig, "name").unwrap_or(n);
                out.push((name, read_from(&ig)?));
            }
            Artifact::Collection(Collection { items: out })
        }
        k => return Err(err(format!("unknown artifact kind `{k}`"))),
    })
}

/// Reads a whole dataset as `T` after checking the size it declares against the memory
/// available: an HDF5 file of a few KB can declare a chunked dataset of terabytes.
fn read_checked<T: hdf5_metno::H5Type>(ds: &hdf5_metno::Dataset) -> H5Result<Vec<T>> {
    let bytes = ds
        .shape()
        .iter()
        .try_fold(std::mem::size_of::<T>() as u64, |a, &d| {
            a.checked_mul(d as u64)
        });
    crate::volume::check_declared(&format!("dataset `{}`", ds.name()), bytes).map_err(err)?;
    ds.read_raw::<T>()
}

fn f64s(g: &Group, name: &str) -> H5Result<Vec<f64>> {
    read_checked::<f64>(&g.dataset(name)?)
}
fn i64s(g: &Group, name: &str) -> H5Result<Vec<i64>> {
    read_checked::<i64>(&g.dataset(name)?)
}
fn to_usize(v: &[i64], what: &str) -> H5Result<Vec<usize>> {
    v.iter()
        .map(|&i| usize::try_from(i).map_err(|_| err(format!("negative index {i} in `{what}`"))))
        .collect()
}
fn arr3(v: Option<Vec<f64>>, what: &str) -> H5Result<[f64; 3]> {
    v.and_then(|v| v.try_into().ok())
        .ok_or_else(|| err(format!("`{what}` must hold 3 numbers")))
}

fn read_packing(g: &Group) -> H5Result<Packing> {
    let pos = f64s(g, "positions")?;
    let radius = f64s(g, "radius")?;
    let clump = i64s(g, "clump_index")?;
    let ori = f64s(g, "orientation")?;
    let layer = g.dataset("layer")?.read_raw::<u32>()?;
    let frozen = g.dataset("frozen")?.read_raw::<u8>()?;
    let n = radius.len();
    if pos.len() != 3 * n || ori.len() != 4 * n || clump.len() != n || layer.len() != n {
        return Err(err("packing datasets disagree on the number of bodies"));
    }
    let d = g.group("domain")?;
    let periodic = arr3(read_attr_f64s(&d, "periodic"), "domain/periodic")?.map(|x| x != 0.0);
    let mut domain = Domain::boxed(
        arr3(read_attr_f64s(&d, "min"), "domain/min")?,
        arr3(read_attr_f64s(&d, "max"), "domain/max")?,
        periodic,
    );
    for e in f64s(&d, "excluded_spheres")?.chunks_exact(4) {
        domain.excluded.push(ExcludedSolid::Sphere {
            center: [e[0], e[1], e[2]],
            radius: e[3],
        });
    }
    let mut p = Packing::new(domain);
    if g.link_exists("library") {
        p.library = Some(read_library(&g.group("library")?)?);
    }
    for k in 0..n {
        p.bodies.push(Body {
            shape: if clump[k] >= 0 {
                BodyShape::Clump {
                    index: clump[k] as usize,
                }
            } else {
                BodyShape::Sphere { radius: radius[k] }
            },
            position: [pos[3 * k], pos[3 * k + 1], pos[3 * k + 2]],
            orientation: [ori[4 * k], ori[4 * k + 1], ori[4 * k + 2], ori[4 * k + 3]],
            layer: layer[k],
            frozen: frozen[k] != 0,
        });
    }
    p.attributes = read_named_values(&g.group("attributes")?)?;
    Ok(p)
}

fn read_library(g: &Group) -> H5Result<ClumpLibrary> {
    let first = to_usize(&i64s(g, "first_sphere")?, "first_sphere")?;
    let off = f64s(g, "sphere_offset")?;
    let rad = f64s(g, "sphere_radius")?;
    let vol = f64s(g, "volume")?;
    let br = f64s(g, "bounding_radius")?;
    let pi = f64s(g, "principal_inertia")?;
    let pa = f64s(g, "principal_axes")?;
    let src = read_strings(g, "clump_source")?;
    let c = vol.len();
    if first.len() != c + 1 || first.last() != Some(&rad.len()) || pa.len() != 9 * c {
        return Err(err("clump library datasets disagree"));
    }
    let clumps = (0..c)
        .map(|k| Clump {
            spheres: (first[k]..first[k + 1])
                .map(|s| ClumpSphere {
                    offset: [off[3 * s], off[3 * s + 1], off[3 * s + 2]],
                    radius: rad[s],
                })
                .collect(),
            volume: vol[k],
            bounding_radius: br[k],
            principal_inertia: [pi[3 * k], pi[3 * k + 1], pi[3 * k + 2]],
            principal_axes: [0, 1, 2].map(|r| [0, 1, 2].map(|col| pa[9 * k + 3 * r + col])),
            source: src.get(k).cloned().unwrap_or_default(),
        })
        .collect();
    Ok(ClumpLibrary {
        clumps,
        source: read_attr_str(g, "source").unwrap_or_default(),
    })
}

fn read_graph(g: &Group) -> H5Result<ContactGraph> {
    let pairs = to_usize(&i64s(g, "pairs")?, "pairs")?;
    let gaps = f64s(g, "gaps")?;
    if pairs.len() != 2 * gaps.len() {
        return Err(err("`pairs` and `gaps` disagree"));
    }
    let bonds = to_usize(&i64s(g, "bonds")?, "bonds")?;
    let pos = f64s(g, "positions")?;
    let fg = g.group("faces")?;
    let mut faces: [Vec<usize>; 6] = Default::default();
    for (f, name) in faces.iter_mut().zip(FACE_NAMES) {
        *f = to_usize(&i64s(&fg, name)?, name)?;
    }
    Ok(ContactGraph {
        contacts: gaps
            .iter()
            .enumerate()
            .map(|(k, &gap)| Contact {
                i: pairs[2 * k],
                j: pairs[2 * k + 1],
                gap,
            })
            .collect(),
        faces,
        bonds: bonds.chunks_exact(2).map(|b| [b[0], b[1]]).collect(),
        // Files written before bonds carried attributes have no group.
        bond_attributes: if g.link_exists("bond_attributes") {
            read_named_values(&g.group("bond_attributes")?)?
        } else {
            IndexMap::new()
        },
        positions: pos.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect(),
        // Graphs of non-spherical bodies (and files written before radii) have none.
        radii: if g.link_exists("radius") {
            f64s(g, "radius")?
        } else {
            Vec::new()
        },
    })
}

fn read_table(g: &Group) -> H5Result<Table> {
    let mut t = Table::new(read_attr_str(g, "name").unwrap_or_default());
    for key in read_attr_strs(g, "column_order").unwrap_or_default() {
        let ds = g.dataset(&key)?;
        let data = match ds.dtype()?.to_descriptor()? {
            TypeDescriptor::Float(_) => ColumnData::F64(ds.read_raw::<f64>()?),
            TypeDescriptor::Integer(_) | TypeDescriptor::Unsigned(_) => {
                ColumnData::I64(ds.read_raw::<i64>()?)
            }
            _ => ColumnData::Str(read_strings(g, &key)?),
        };
        t.columns.push(Column {
            name: read_attr_str(&ds, "name").unwrap_or(key.clone()),
            unit: read_units(&ds),
            data,
        });
    }
    Ok(t)
}

fn read_tensor(g: &Group) -> H5Result<Tensor> {
    let ds = g.dataset("tensor")?;
    let convention = match read_attr_str(&ds, "convention").as_deref() {
        Some("Voigt") => TensorConvention::Voigt,
        Some("Mandel") => TensorConvention::Mandel,
        _ => TensorConvention::Plain,
    };
    Ok(Tensor {
        name: read_attr_str(&ds, "name").unwrap_or_default(),
        unit: read_units(&ds),
        shape: ds.shape(),
        values: ds.read_raw::<f64>()?,
        convention,
    })
}

/// Reads any 2-D (y, x), 3-D (z, y, x) or 4-D (z, y, x, components) numeric dataset (a path
/// such as `group/data` is fine) with `spacing`/`origin` (x, y, z order, metres),
/// `element_size_um` (z, y, x order, micrometres, as ImageJ/ilastik write it), `unit` and
/// phase-table attributes when present.
pub fn read_hdf5_dataset(path: &Path, name: &str) -> Result<Volume, String> {
    let f = open(path)?;
    volume_from(&f, name).map_err(at(path))
}

/// Feeds the values of a dataset to `scan` in slabs along its first axis (z, or y of a 2-D
/// dataset) of about [`crate::import::SCAN_BLOCK_BYTES`], so checking the labels of a large
/// dataset never holds it in memory.
pub fn scan_hdf5_dataset(
    path: &Path,
    name: &str,
    scan: &mut crate::volume::LabelScan,
) -> Result<(), String> {
    let f = open(path)?;
    let r = (|| -> H5Result<()> {
        let ds = f
            .dataset(name)
            .map_err(|e| err(format!("no dataset `{name}` ({e})")))?;
        let shape = ds.shape();
        dims_of(&shape)?;
        let row: usize = shape[1..].iter().product::<usize>().max(1);
        let step = (crate::import::SCAN_BLOCK_BYTES / 8 / row).max(1);
        let mut a = 0;
        while a < shape[0] {
            let b = (a + step).min(shape[0]);
            let block: Vec<f64> = match shape.len() {
                2 => ds.read_slice::<f64, _, ndarray::IxDyn>((a..b, ..))?,
                3 => ds.read_slice::<f64, _, ndarray::IxDyn>((a..b, .., ..))?,
                _ => ds.read_slice::<f64, _, ndarray::IxDyn>((a..b, .., .., ..))?,
            }
            .into_raw_vec_and_offset()
            .0;
            scan.feed(block.into_iter());
            a = b;
        }
        Ok(())
    })();
    r.map_err(at(path))
}

/// Shape ([nx, ny, nz], components) and element type of a dataset, without reading it.
pub fn probe_hdf5_dataset(path: &Path, name: &str) -> Result<Probe, String> {
    let f = open(path)?;
    let r = (|| -> H5Result<_> {
        let ds = f
            .dataset(name)
            .map_err(|e| err(format!("no dataset `{name}` ({e})")))?;
        let (dims, components) = dims_of(&ds.shape())?;
        let dt = ds.dtype()?;
        let three = |k: &str| read_attr_f64s(&ds, k).and_then(|v| <[f64; 3]>::try_from(v).ok());
        Ok(Probe {
            dims,
            components,
            dtype: format!("{:?}", dt.to_descriptor()?),
            elem_bytes: dt.size(),
            spacing: three("spacing"),
            origin: three("origin"),
        })
    })();
    r.map_err(at(path))
}

fn dims_of(shape: &[usize]) -> H5Result<([usize; 3], usize)> {
    Ok(match *shape {
        [ny, nx] => ([nx, ny, 1], 1),
        [nz, ny, nx] => ([nx, ny, nz], 1),
        [nz, ny, nx, c] => ([nx, ny, nz], c),
        _ => {
            return Err(err(format!(
                "dataset shape {shape:?} is not (y, x), (z, y, x) or (z, y, x, components)"
            )))
        }
    })
}

fn volume_from(g: &Group, name: &str) -> H5Result<Volume> {
    let ds = g
        .dataset(name)
        .map_err(|e| err(format!("no dataset `{name}` ({e})")))?;
    let (dims, components) = dims_of(&ds.shape())?;
    let data = match ds.dtype()?.to_descriptor()? {
        TypeDescriptor::Unsigned(IntSize::U1) => VolumeData::U8(read_checked(&ds)?),
        TypeDescriptor::Unsigned(IntSize::U2) => VolumeData::U16(read_checked(&ds)?),
        TypeDescriptor::Integer(IntSize::U1 | IntSize::U2 | IntSize::U4) => {
            VolumeData::I32(read_checked(&ds)?)
        }
        TypeDescriptor::Boolean => VolumeData::U8(read_checked(&ds)?),
        TypeDescriptor::Unsigned(_) | TypeDescriptor::Integer(_) => {
            VolumeData::F64(read_checked(&ds)?)
        }
        TypeDescriptor::Float(FloatSize::U4) => VolumeData::F32(read_checked(&ds)?),
        TypeDescriptor::Float(_) => VolumeData::F64(read_checked(&ds)?),
        t => return Err(err(format!("dataset `{name}` holds {t:?}, not numbers"))),
    };
    let (spacing, origin, periodic) = dataset_grid(&ds);
    let mut phases = Vec::new();
    if let (Some(ids), Some(names)) = (
        read_attr_f64s(&ds, "phase_ids"),
        read_attr_strs(&ds, "phase_names"),
    ) {
        if ids.len() == names.len() {
            phases = ids
                .iter()
                .zip(names)
                .map(|(&id, name)| Phase { id: id as u8, name })
                .collect();
        }
    }
    Ok(Volume {
        name: name.rsplit('/').next().unwrap_or(name).to_string(),
        unit: read_units(&ds),
        dims,
        components,
        convention: read_attr_str(&ds, "component_convention")
            .and_then(|c| ComponentConvention::from_name(&c))
            .unwrap_or_default(),
        spacing,
        origin,
        periodic,
        data,
        phases,
    })
}

/// The grid of a dataset as the readers take it: `spacing`, else ImageJ's `element_size_um`
/// (z, y, x in micrometres), `origin`, `periodic`.
pub(crate) fn dataset_grid(ds: &hdf5_metno::Dataset) -> StatedGrid {
    let three = |k: &str| read_attr_f64s(ds, k).and_then(|v| <[f64; 3]>::try_from(v).ok());
    let spacing = three("spacing")
        .or_else(|| three("element_size_um").map(|[z, y, x]| [x * 1e-6, y * 1e-6, z * 1e-6]));
    let periodic = three("periodic")
        .map(|p| p.map(|x| x != 0.0))
        .unwrap_or_default();
    (spacing, three("origin"), periodic)
}

crate::vtk_xml::exporter!(
    H5Exporter,
    "h5",
    &["h5", "hdf5"],
    [
        PhaseImage,
        Field,
        ClumpLibrary,
        Packing,
        ContactGraph,
        Table,
        Tensor,
        Series,
        Collection
    ],
    "plain HDF5: images/fields as (z, y, x) datasets with spacing/origin attributes, packings, \
     clump libraries, contact graphs, tables (one dataset per column with its unit), tensors, \
     series (one group per frame), collections (one named group per item); `units` on every \
     dataset, root attribute `grainpipe_kind`, provenance as root attributes (seeds as u64); \
     datasets chunked and deflated (option `compression`). pyvista.read does not know this \
     layout: export `.vtkhdf` (images) or `.vtp` (packings) for pyvista",
    options: vec![compression_option()],
    check: check_compression,
    write: write_h5_options
);

fn write_h5_options(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    options: &registry::ExportOptions,
) -> Result<(), String> {
    write_h5_with(a, path, prov, deflate_option(options))
}
