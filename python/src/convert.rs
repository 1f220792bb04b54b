//! Artifacts -> plain Python objects (dicts, lists, numpy arrays). The pure-Python layer
//! (`grainpipe/_results.py`) wraps these dicts in classes with `.to_xarray()` and friends.
//!
//! Arrays move into numpy without a copy: an owned `Vec` becomes an `ndarray::Array` of the
//! same memory (`from_shape_vec` does not copy) and numpy takes ownership of it. Voxel data
//! are stored x fastest, which is C order for the shape (z, y, x[, component]).

use grainpipe_core::model::{
    Artifact, BodyAttribute, BodyShape, ClumpLibrary, ColumnData, ExcludedSolid, FieldData, Grid,
    Packing, TensorConvention,
};
use indexmap::IndexMap;
use numpy::ndarray::{Array, IxDyn};
use numpy::{Element, IntoPyArray};
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

/// A numpy array of `shape` that takes over `v` (no copy).
fn array<'py, T: Element>(
    py: Python<'py>,
    v: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    let a = Array::from_shape_vec(IxDyn(shape), v)
        .map_err(|e| PyRuntimeError::new_err(format!("array of shape {shape:?}: {e}")))?;
    Ok(a.into_pyarray(py).into_any())
}

fn grid_into(py: Python<'_>, d: &Bound<'_, PyDict>, g: &Grid) -> PyResult<()> {
    d.set_item("dims", g.dims.to_vec())?;
    d.set_item("spacing", g.spacing.to_vec())?;
    d.set_item("origin", g.origin.to_vec())?;
    d.set_item("periodic", g.periodic.to_vec())?;
    let _ = py;
    Ok(())
}

/// Shape of a voxel array in numpy's C order: (z, y, x), plus the component axis when a
/// field has more than one value per voxel.
fn voxel_shape(g: &Grid, components: usize) -> Vec<usize> {
    let mut s = vec![g.dims[2], g.dims[1], g.dims[0]];
    if components > 1 {
        s.push(components);
    }
    s
}

fn attributes<'py>(
    py: Python<'py>,
    attrs: IndexMap<String, BodyAttribute>,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    for (name, a) in attrs {
        let e = PyDict::new(py);
        e.set_item("unit", a.unit)?;
        let n = a.values.len();
        e.set_item("values", array(py, a.values, &[n])?)?;
        d.set_item(name, e)?;
    }
    Ok(d)
}

fn library<'py>(py: Python<'py>, l: ClumpLibrary) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("source", l.source)?;
    let clumps = PyList::empty(py);
    for c in l.clumps {
        let e = PyDict::new(py);
        let k = c.spheres.len();
        let spheres: Vec<f64> = c
            .spheres
            .iter()
            .flat_map(|s| [s.offset[0], s.offset[1], s.offset[2], s.radius])
            .collect();
        e.set_item("spheres", array(py, spheres, &[k, 4])?)?;
        e.set_item("volume", c.volume)?;
        e.set_item("bounding_radius", c.bounding_radius)?;
        e.set_item("principal_inertia", c.principal_inertia.to_vec())?;
        let axes: Vec<f64> = c.principal_axes.iter().flatten().copied().collect();
        e.set_item("principal_axes", array(py, axes, &[3, 3])?)?;
        e.set_item("source", c.source)?;
        clumps.append(e)?;
    }
    d.set_item("clumps", clumps)?;
    Ok(d)
}

/// A packing as the HDF5 writer lays it out (positions, radius, clump_index, orientation,
/// layer, frozen), plus body ids and the world spheres (one row per sphere of every clump).
fn packing<'py>(py: Python<'py>, d: &Bound<'py, PyDict>, p: Packing) -> PyResult<()> {
    let n = p.bodies.len();
    let spheres = p.world_spheres();
    let m = spheres.len();
    let mut radius = Vec::with_capacity(n);
    let mut clump = Vec::with_capacity(n);
    for b in &p.bodies {
        match b.shape {
            BodyShape::Sphere { radius: r } => {
                radius.push(r);
                clump.push(-1i64);
            }
            BodyShape::Clump { index } => {
                let r = p
                    .library
                    .as_ref()
                    .and_then(|l| l.clumps.get(index))
                    .map(|c| c.bounding_radius)
                    .ok_or_else(|| {
                        PyRuntimeError::new_err(format!(
                            "clump index {index} is not in the library"
                        ))
                    })?;
                radius.push(r);
                clump.push(index as i64);
            }
        }
    }
    let positions: Vec<f64> = p.bodies.iter().flat_map(|b| b.position).collect();
    let orientation: Vec<f64> = p.bodies.iter().flat_map(|b| b.orientation).collect();
    let layer: Vec<u32> = p.bodies.iter().map(|b| b.layer).collect();
    let frozen: Vec<bool> = p.bodies.iter().map(|b| b.frozen).collect();
    d.set_item("positions", array(py, positions, &[n, 3])?)?;
    d.set_item("radii", array(py, radius, &[n])?)?;
    d.set_item("body_ids", array(py, (0..n as i64).collect(), &[n])?)?;
    d.set_item("clump_index", array(py, clump, &[n])?)?;
    d.set_item("quaternions", array(py, orientation, &[n, 4])?)?;
    d.set_item("layer", array(py, layer, &[n])?)?;
    d.set_item("frozen", array(py, frozen, &[n])?)?;
    let centers: Vec<f64> = spheres.iter().flat_map(|s| s.center).collect();
    let sr: Vec<f64> = spheres.iter().map(|s| s.radius).collect();
    let sb: Vec<i64> = spheres.iter().map(|s| s.body as i64).collect();
    d.set_item("sphere_centers", array(py, centers, &[m, 3])?)?;
    d.set_item("sphere_radii", array(py, sr, &[m])?)?;
    d.set_item("sphere_body", array(py, sb, &[m])?)?;
    let dom = PyDict::new(py);
    dom.set_item("min", p.domain.min.to_vec())?;
    dom.set_item("max", p.domain.max.to_vec())?;
    dom.set_item("periodic", p.domain.periodic.to_vec())?;
    let ex: Vec<f64> = p
        .domain
        .excluded
        .iter()
        .flat_map(|e| match e {
            ExcludedSolid::Sphere { center, radius } => [center[0], center[1], center[2], *radius],
        })
        .collect();
    let k = ex.len() / 4;
    dom.set_item("excluded_spheres", array(py, ex, &[k, 4])?)?;
    d.set_item("domain", dom)?;
    d.set_item("attributes", attributes(py, p.attributes)?)?;
    match p.library {
        Some(l) => d.set_item("library", library(py, l)?)?,
        None => d.set_item("library", py.None())?,
    }
    Ok(())
}

/// One artifact as a dict with a `kind` key (the [`ArtifactKind`] name) and its data.
///
/// [`ArtifactKind`]: grainpipe_core::model::ArtifactKind
pub fn artifact<'py>(py: Python<'py>, a: Artifact) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("kind", a.kind().to_string())?;
    match a {
        Artifact::PhaseImage(x) => {
            grid_into(py, &d, &x.grid)?;
            let shape = voxel_shape(&x.grid, 1);
            d.set_item("array", array(py, x.labels, &shape)?)?;
            let phases = PyDict::new(py);
            for p in x.phases {
                phases.set_item(p.id, p.name)?;
            }
            d.set_item("phases", phases)?;
        }
        Artifact::Field(x) => {
            grid_into(py, &d, &x.grid)?;
            d.set_item("name", &x.name)?;
            d.set_item("unit", &x.unit)?;
            d.set_item("components", x.components)?;
            d.set_item("convention", x.convention.name())?;
            d.set_item("component_names", x.component_names())?;
            let shape = voxel_shape(&x.grid, x.components);
            match x.data {
                FieldData::F32(v) => d.set_item("array", array(py, v, &shape)?)?,
                FieldData::F64(v) => d.set_item("array", array(py, v, &shape)?)?,
            }
        }
        Artifact::ClumpLibrary(l) => {
            d.set_item("library", library(py, l)?)?;
        }
        Artifact::Packing(p) => packing(py, &d, p)?,
        Artifact::ContactGraph(g) => {
            let n = g.contacts.len();
            let pairs: Vec<i64> = g
                .contacts
                .iter()
                .flat_map(|c| [c.i as i64, c.j as i64])
                .collect();
            let gaps: Vec<f64> = g.contacts.iter().map(|c| c.gap).collect();
            d.set_item("contacts", array(py, pairs, &[n, 2])?)?;
            d.set_item("gaps", array(py, gaps, &[n])?)?;
            let faces = PyDict::new(py);
            for (name, f) in grainpipe_core::model::FACE_NAMES.iter().zip(g.faces) {
                let k = f.len();
                let f: Vec<i64> = f.into_iter().map(|i| i as i64).collect();
                faces.set_item(*name, array(py, f, &[k])?)?;
            }
            d.set_item("faces", faces)?;
            let nb = g.bonds.len();
            let bonds: Vec<i64> = g.bonds.iter().flatten().map(|&i| i as i64).collect();
            d.set_item("bonds", array(py, bonds, &[nb, 2])?)?;
            d.set_item("bond_attributes", attributes(py, g.bond_attributes)?)?;
            let np = g.positions.len();
            let pos: Vec<f64> = g.positions.into_iter().flatten().collect();
            d.set_item("positions", array(py, pos, &[np, 3])?)?;
            if !g.radii.is_empty() {
                let nr = g.radii.len();
                d.set_item("radius", array(py, g.radii, &[nr])?)?;
            }
        }
        Artifact::Table(t) => {
            d.set_item("name", t.name)?;
            let cols = PyList::empty(py);
            for c in t.columns {
                let n = c.data.len();
                let values = match c.data {
                    ColumnData::F64(v) => array(py, v, &[n])?,
                    ColumnData::I64(v) => array(py, v, &[n])?,
                    ColumnData::Str(v) => PyList::new(py, v)?.into_any(),
                };
                cols.append((c.name, c.unit, values))?;
            }
            d.set_item("columns", cols)?;
        }
        Artifact::Tensor(t) => {
            d.set_item("name", t.name)?;
            d.set_item("unit", t.unit)?;
            d.set_item(
                "convention",
                match t.convention {
                    TensorConvention::Plain => "plain",
                    TensorConvention::Voigt => "voigt",
                    TensorConvention::Mandel => "mandel",
                },
            )?;
            d.set_item("array", array(py, t.values, &t.shape)?)?;
        }
        Artifact::Series(s) => {
            let frames = PyList::empty(py);
            for (t, a) in s.frames {
                frames.append((t, artifact(py, a)?))?;
            }
            d.set_item("frames", frames)?;
        }
        Artifact::Collection(c) => {
            let items = PyList::empty(py);
            for (name, a) in c.items {
                items.append((name, artifact(py, a)?))?;
            }
            d.set_item("items", items)?;
        }
    }
    Ok(d)
}
