//! XDMF 3 (`.xdmf`) with the heavy data in a sibling HDF5 file.
//!
//! Two layouts (XDMF model and format, xdmf.org "XDMF Model and Format"):
//! - an unstructured `Uniform` grid: `Topology TopologyType="Hexahedron"` (or `Polyvertex`,
//!   `Polyline` with `NodesPerElement`) over an HDF5 `(cells, nodes)` Int64 dataset,
//!   `Geometry GeometryType="XYZ"` over `(points, 3)` Float64, `Attribute`s with
//!   `Center="Cell"` or `"Node"`. meshio, ParaView/VTK and dolfinx read this layout.
//! - an image: `Topology TopologyType="3DCoRectMesh" Dimensions="nz+1 ny+1 nx+1"` (point
//!   counts, slowest axis first) with `Geometry GeometryType="ORIGIN_DXDYDZ"` whose origin and
//!   spacing are likewise given z, y, x (the order VTK's XDMF reader applies them in), and cell
//!   attributes of dimensions `nz ny nx`. ParaView/VTK read it; meshio 5 reads only XYZ
//!   geometry and refuses it.
//!
//! meshio's reader refuses an `Information` element without text, so the phase table and
//! provenance are HDF5 attributes and an XML comment.

use super::vtu::xml_comment;
use super::{Chunk, Column, Dtype, Elem, Mesh};
use crate::h5util::{empty_dataset, H5Result};
use hdf5_metno::{Dataset, Group, H5Type};

fn esc(s: &str) -> String {
    quick_xml::escape::escape(s).into_owned()
}

/// XDMF `NumberType` and `Precision` of a column type. Bytes are `UChar` (VTK's XDMF reader
/// widens `UInt` of precision 1 to 32 bits); meshio takes the type of HDF5 data from the
/// dataset itself.
fn number_type(d: Dtype) -> (&'static str, usize) {
    match d {
        Dtype::U8 => ("UChar", 1),
        Dtype::I32 => ("Int", 4),
        Dtype::I64 => ("Int", 8),
        Dtype::F32 => ("Float", 4),
        Dtype::F64 => ("Float", 8),
    }
}

fn attribute_type(components: usize) -> &'static str {
    match components {
        1 => "Scalar",
        3 => "Vector",
        6 => "Tensor6",
        9 => "Tensor",
        _ => "Matrix",
    }
}

/// A `<DataItem>` referring to `h5:/path` with the given dimensions.
pub(crate) fn data_item(dims: &[usize], d: Dtype, h5_name: &str, path: &str) -> String {
    let (nt, p) = number_type(d);
    let dims: Vec<String> = dims.iter().map(|x| x.to_string()).collect();
    format!(
        "<DataItem Dimensions=\"{}\" NumberType=\"{nt}\" Precision=\"{p}\" Format=\"HDF\">{}:{}</DataItem>\n",
        dims.join(" "),
        esc(h5_name),
        esc(path)
    )
}

/// Dataset name for a column (HDF5 names cannot hold `/`).
fn dataset_name(name: &str) -> String {
    let n = name.replace('/', "_");
    if n.is_empty() || n == "." {
        "_".into()
    } else {
        n
    }
}

/// Streams `c` into a new dataset of shape (tuples) or (tuples, components), whole rows
/// per write.
fn stream_typed<T: Elem + H5Type>(
    g: &Group,
    name: &str,
    c: &Column,
    row_len: usize,
    deflate: u8,
) -> H5Result<Dataset> {
    let comps = row_len.max(1);
    let rows = c.values() / comps;
    let shape: Vec<usize> = if comps == 1 {
        vec![rows]
    } else {
        vec![rows, comps]
    };
    let ds = empty_dataset::<T>(g, name, &shape, deflate)?;
    let mut pending: Vec<T> = Vec::new();
    let mut row = 0usize;
    let mut failure: Option<hdf5_metno::Error> = None;
    let mut flush = |pending: &mut Vec<T>, all: bool| -> H5Result<()> {
        let rows = pending.len() / comps;
        if rows == 0 || (!all && rows < 4096) {
            return Ok(());
        }
        let vals = &pending[..rows * comps];
        if comps == 1 {
            ds.write_slice(
                ndarray::ArrayView1::from(vals),
                ndarray::s![row..row + rows],
            )?;
        } else {
            let v = ndarray::ArrayView2::from_shape((rows, comps), vals)
                .map_err(|e| hdf5_metno::Error::from(e.to_string()))?;
            ds.write_slice(v, ndarray::s![row..row + rows, ..])?;
        }
        row += rows;
        pending.drain(..rows * comps);
        Ok(())
    };
    let r = c.produce(&mut |ch: Chunk<'_>| {
        let vals = T::of_chunk(&ch).ok_or_else(|| std::io::Error::other("column type"))?;
        pending.extend_from_slice(vals);
        flush(&mut pending, false).map_err(|e| {
            let m = e.to_string();
            failure = Some(e);
            std::io::Error::other(m)
        })
    });
    if let Some(e) = failure {
        return Err(e);
    }
    r.map_err(|e| hdf5_metno::Error::from(e.to_string()))?;
    flush(&mut pending, true)?;
    Ok(ds)
}

/// Streams a column into `g/name` of shape (values / row_len, row_len), or (values) when
/// `row_len` is 1.
pub(crate) fn stream_column(
    g: &Group,
    name: &str,
    c: &Column,
    row_len: usize,
    deflate: u8,
) -> H5Result<Dataset> {
    match c.dtype {
        Dtype::U8 => stream_typed::<u8>(g, name, c, row_len, deflate),
        Dtype::I32 => stream_typed::<i32>(g, name, c, row_len, deflate),
        Dtype::I64 => stream_typed::<i64>(g, name, c, row_len, deflate),
        Dtype::F32 => stream_typed::<f32>(g, name, c, row_len, deflate),
        Dtype::F64 => stream_typed::<f64>(g, name, c, row_len, deflate),
    }
}

/// Writes the heavy data of an unstructured mesh into the HDF5 file `f`: `/geometry`,
/// `/topology`, `/cell_data/<name>`, `/point_data/<name>`; returns the XDMF text that
/// refers to them as `h5_name:/...`.
pub fn write_mesh_heavy(
    f: &hdf5_metno::File,
    mesh: &Mesh,
    h5_name: &str,
    deflate: u8,
    comment: &str,
) -> H5Result<String> {
    stream_column(f, "geometry", &mesh.points, 3, deflate)?;
    stream_column(
        f,
        "topology",
        &mesh.connectivity,
        mesh.kind.nodes(),
        deflate,
    )?;
    let mut attrs = String::new();
    for (group, center, cols) in [
        ("cell_data", "Cell", &mesh.cell_data),
        ("point_data", "Node", &mesh.point_data),
    ] {
        if cols.is_empty() {
            continue;
        }
        let g = f.create_group(group)?;
        for c in cols {
            let name = dataset_name(&c.name);
            stream_column(&g, &name, c, c.components, deflate)?;
            let mut dims = vec![c.tuples];
            if c.components > 1 {
                dims.push(c.components);
            }
            attrs.push_str(&format!(
                "<Attribute Name=\"{}\" AttributeType=\"{}\" Center=\"{center}\">\n{}</Attribute>\n",
                esc(&c.name),
                attribute_type(c.components),
                data_item(&dims, c.dtype, h5_name, &format!("/{group}/{name}"))
            ));
        }
    }
    let nodes = mesh.kind.nodes();
    let per_element = if matches!(mesh.kind, super::CellKind::Vertex | super::CellKind::Line) {
        format!(" NodesPerElement=\"{nodes}\"")
    } else {
        String::new()
    };
    let mut s = String::from("<?xml version=\"1.0\"?>\n");
    s.push_str(&xml_comment(comment));
    s.push_str(
        "<Xdmf Version=\"3.0\">\n<Domain>\n<Grid Name=\"grainpipe\" GridType=\"Uniform\">\n",
    );
    s.push_str(&format!(
        "<Topology TopologyType=\"{}\" NumberOfElements=\"{}\"{per_element}>\n{}</Topology>\n",
        mesh.kind.xdmf_name(),
        mesh.cell_count,
        data_item(&[mesh.cell_count, nodes], Dtype::I64, h5_name, "/topology")
    ));
    s.push_str(&format!(
        "<Geometry GeometryType=\"XYZ\">\n{}</Geometry>\n",
        data_item(&[mesh.point_count, 3], Dtype::F64, h5_name, "/geometry")
    ));
    s.push_str(&attrs);
    s.push_str("</Grid>\n</Domain>\n</Xdmf>\n");
    Ok(s)
}

/// The XDMF text of an image on a 3DCoRectMesh: `dims` (x, y, z voxel counts), lower corner
/// `origin`, voxel `spacing`, and one cell attribute (name, components, type, HDF5 path).
pub fn image_xdmf(
    dims: [usize; 3],
    origin: [f64; 3],
    spacing: [f64; 3],
    attribute: (&str, usize, Dtype, &str),
    h5_name: &str,
    comment: &str,
) -> String {
    let [nx, ny, nz] = dims;
    let num = |v: [f64; 3]| format!("{:e} {:e} {:e}", v[2], v[1], v[0]);
    let (name, comps, dtype, path) = attribute;
    let mut adims = vec![nz, ny, nx];
    if comps > 1 {
        adims.push(comps);
    }
    let mut s = String::from("<?xml version=\"1.0\"?>\n");
    s.push_str(&xml_comment(comment));
    s.push_str(
        "<Xdmf Version=\"3.0\">\n<Domain>\n<Grid Name=\"grainpipe\" GridType=\"Uniform\">\n",
    );
    s.push_str(&format!(
        "<Topology TopologyType=\"3DCoRectMesh\" Dimensions=\"{} {} {}\"/>\n",
        nz + 1,
        ny + 1,
        nx + 1
    ));
    s.push_str(&format!(
        "<Geometry GeometryType=\"ORIGIN_DXDYDZ\">\n\
         <DataItem Dimensions=\"3\" NumberType=\"Float\" Precision=\"8\" Format=\"XML\">{}</DataItem>\n\
         <DataItem Dimensions=\"3\" NumberType=\"Float\" Precision=\"8\" Format=\"XML\">{}</DataItem>\n\
         </Geometry>\n",
        num(origin),
        num(spacing)
    ));
    s.push_str(&format!(
        "<Attribute Name=\"{}\" AttributeType=\"{}\" Center=\"Cell\">\n{}</Attribute>\n",
        esc(name),
        attribute_type(comps),
        data_item(&adims, dtype, h5_name, path)
    ));
    s.push_str("</Grid>\n</Domain>\n</Xdmf>\n");
    s
}
