//! Unstructured meshes for finite-element and mesh tools (meshio, ParaView/VTK, dolfinx,
//! Abaqus, Gmsh): a phase image or field as hexahedral voxel cells, a packing as vertex
//! cells, a contact graph as line cells.
//!
//! The kernels here know no framework type: [`VoxelHexMesh`] numbers the corner points of
//! the selected voxels of a label array, [`Mesh`] describes a single-cell-type mesh whose
//! arrays ([`Column`]) are produced chunk by chunk, so writers stream them to disk and never
//! hold a copy of the whole mesh. [`surface`] builds the conforming interface surfaces
//! of a phase image (`mesh: surface`). The writers are `vtu`, `legacy_vtk`, `xdmf`, `abaqus` and
//! `gmsh`; `exporters` binds them to artifacts and export options.

pub mod abaqus;
mod exporters;
pub mod gmsh;
pub mod legacy_vtk;
pub mod surface;
pub mod vtu;
pub mod xdmf;

pub use exporters::{
    image_surface, surface_memory, with_mesh, AbaqusExporter, GmshExporter, LegacyVtkExporter,
    PhaseSelection, VtuExporter, XdmfExporter, SURFACE_TRIANGLES_PER_VOXEL,
};

use std::io;

/// Tuples per chunk handed to a writer (a few MiB at most).
pub const CHUNK_TUPLES: usize = 1 << 16;

/// Corners of a voxel in the node order of VTK_HEXAHEDRON, which is also Gmsh's 8-node
/// hexahedron (type 5), Abaqus' C3D8 and XDMF's Hexahedron: the lower face counter-clockwise
/// seen from above, then the upper face (VTK file formats, "Linear cell types", fig. 2).
pub const HEX_CORNERS: [[usize; 3]; 8] = [
    [0, 0, 0],
    [1, 0, 0],
    [1, 1, 0],
    [0, 1, 0],
    [0, 0, 1],
    [1, 0, 1],
    [1, 1, 1],
    [0, 1, 1],
];

const NO_POINT: u32 = u32::MAX;

/// The hexahedral mesh of the selected voxels of a grid: one cell per selected voxel, one
/// point per voxel corner that a selected voxel touches (corners shared between voxels are
/// one point). Points are numbered in corner order (x fastest), cells in voxel order.
pub struct VoxelHexMesh<'a> {
    pub dims: [usize; 3],
    pub origin: [f64; 3],
    pub spacing: [f64; 3],
    labels: Option<&'a [u8]>,
    selected: [bool; 256],
    /// Point index of every grid corner, [`NO_POINT`] for corners no selected voxel touches.
    corner_point: Vec<u32>,
    point_count: usize,
    cell_count: usize,
}

impl<'a> VoxelHexMesh<'a> {
    /// Bytes the mesh holds for a grid of `dims` (the corner table).
    pub fn memory_bytes(dims: [usize; 3]) -> u64 {
        4 * ((dims[0] + 1) * (dims[1] + 1) * (dims[2] + 1)) as u64
    }

    /// The voxels whose label is selected (`labels` = None: every voxel, as for a field).
    pub fn new(
        dims: [usize; 3],
        origin: [f64; 3],
        spacing: [f64; 3],
        labels: Option<&'a [u8]>,
        selected: [bool; 256],
    ) -> Result<Self, String> {
        let [nx, ny, nz] = dims;
        let corners = (nx + 1)
            .checked_mul(ny + 1)
            .and_then(|c| c.checked_mul(nz + 1))
            .filter(|&c| c < NO_POINT as usize)
            .ok_or_else(|| {
                format!("{nx}x{ny}x{nz} voxels have more corners than 32-bit point ids number")
            })?;
        if let Some(l) = labels {
            if l.len() != nx * ny * nz {
                return Err(format!("{} labels for {nx}x{ny}x{nz} voxels", l.len()));
            }
        }
        let mut mesh = VoxelHexMesh {
            dims,
            origin,
            spacing,
            labels,
            selected,
            corner_point: vec![NO_POINT; corners],
            point_count: 0,
            cell_count: 0,
        };
        let mut cells = 0;
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    if !mesh.is_selected(x + nx * (y + ny * z)) {
                        continue;
                    }
                    cells += 1;
                    for c in HEX_CORNERS {
                        let k = mesh.corner_index([x + c[0], y + c[1], z + c[2]]);
                        mesh.corner_point[k] = 0;
                    }
                }
            }
        }
        let mut n = 0u32;
        for p in mesh.corner_point.iter_mut() {
            if *p != NO_POINT {
                *p = n;
                n += 1;
            }
        }
        mesh.point_count = n as usize;
        mesh.cell_count = cells;
        Ok(mesh)
    }

    pub fn point_count(&self) -> usize {
        self.point_count
    }

    pub fn cell_count(&self) -> usize {
        self.cell_count
    }

    pub fn is_selected(&self, voxel: usize) -> bool {
        self.labels.is_none_or(|l| self.selected[l[voxel] as usize])
    }

    /// The label of a voxel (0 when the mesh has no labels).
    pub fn label(&self, voxel: usize) -> u8 {
        self.labels.map_or(0, |l| l[voxel])
    }

    pub fn corner_index(&self, c: [usize; 3]) -> usize {
        let [nx, ny, _] = self.dims;
        c[0] + (nx + 1) * (c[1] + (ny + 1) * c[2])
    }

    /// The point at a grid corner, if a selected voxel touches it.
    pub fn point_at(&self, c: [usize; 3]) -> Option<u32> {
        let p = self.corner_point[self.corner_index(c)];
        (p != NO_POINT).then_some(p)
    }

    /// Grid corners of the points, in point order.
    pub fn point_corners(&self) -> impl Iterator<Item = [usize; 3]> + '_ {
        let [nx, ny, _] = self.dims;
        self.corner_point
            .iter()
            .enumerate()
            .filter(|(_, &p)| p != NO_POINT)
            .map(move |(k, _)| {
                [
                    k % (nx + 1),
                    (k / (nx + 1)) % (ny + 1),
                    k / ((nx + 1) * (ny + 1)),
                ]
            })
    }

    /// Position of a grid corner [m]: origin + index * spacing.
    pub fn position(&self, c: [usize; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| self.origin[a] + c[a] as f64 * self.spacing[a])
    }

    /// The selected voxels (linear index, x fastest), in cell order.
    pub fn voxels(&self) -> impl Iterator<Item = usize> + '_ {
        let [nx, ny, nz] = self.dims;
        (0..nx * ny * nz).filter(|&v| self.is_selected(v))
    }

    /// The selected voxels (linear index, x fastest) with their eight points in
    /// [`HEX_CORNERS`] order.
    pub fn cells(&self) -> impl Iterator<Item = (usize, [u32; 8])> + '_ {
        let [nx, ny, nz] = self.dims;
        (0..nx * ny * nz)
            .filter(|&v| self.is_selected(v))
            .map(move |v| {
                let (x, y, z) = (v % nx, (v / nx) % ny, v / (nx * ny));
                let nodes = HEX_CORNERS
                    .map(|c| self.corner_point[self.corner_index([x + c[0], y + c[1], z + c[2]])]);
                (v, nodes)
            })
    }
}

/// The cell types the writers know.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CellKind {
    Vertex,
    Line,
    Triangle,
    Hexahedron,
}

impl CellKind {
    pub fn nodes(self) -> usize {
        match self {
            CellKind::Vertex => 1,
            CellKind::Line => 2,
            CellKind::Triangle => 3,
            CellKind::Hexahedron => 8,
        }
    }

    /// VTK cell type id (vtkCellType.h: VTK_VERTEX 1, VTK_LINE 3, VTK_TRIANGLE 5,
    /// VTK_HEXAHEDRON 12).
    pub fn vtk_type(self) -> u8 {
        match self {
            CellKind::Vertex => 1,
            CellKind::Line => 3,
            CellKind::Triangle => 5,
            CellKind::Hexahedron => 12,
        }
    }

    /// XDMF topology type (XDMF model: "Topology", linear cell types).
    pub fn xdmf_name(self) -> &'static str {
        match self {
            CellKind::Vertex => "Polyvertex",
            CellKind::Line => "Polyline",
            CellKind::Triangle => "Triangle",
            CellKind::Hexahedron => "Hexahedron",
        }
    }
}

/// Element type of a [`Column`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    U8,
    I32,
    I64,
    F32,
    F64,
}

impl Dtype {
    pub fn size(self) -> usize {
        match self {
            Dtype::U8 => 1,
            Dtype::I32 | Dtype::F32 => 4,
            Dtype::I64 | Dtype::F64 => 8,
        }
    }
}

/// A chunk of an array's values.
pub enum Chunk<'c> {
    U8(&'c [u8]),
    I32(&'c [i32]),
    I64(&'c [i64]),
    F32(&'c [f32]),
    F64(&'c [f64]),
}

impl Chunk<'_> {
    pub fn len(&self) -> usize {
        match self {
            Chunk::U8(v) => v.len(),
            Chunk::I32(v) => v.len(),
            Chunk::I64(v) => v.len(),
            Chunk::F32(v) => v.len(),
            Chunk::F64(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The values as bytes, little- or big-endian, appended to `out`.
    pub fn put_bytes(&self, little: bool, out: &mut Vec<u8>) {
        macro_rules! put {
            ($v:expr) => {
                for x in $v.iter() {
                    out.extend_from_slice(&if little {
                        x.to_le_bytes()
                    } else {
                        x.to_be_bytes()
                    });
                }
            };
        }
        match self {
            Chunk::U8(v) => out.extend_from_slice(v),
            Chunk::I32(v) => put!(v),
            Chunk::I64(v) => put!(v),
            Chunk::F32(v) => put!(v),
            Chunk::F64(v) => put!(v),
        }
    }

    /// The values as text: integers exactly, floats as the shortest text that reads back to
    /// the same number; each value followed by `sep`.
    pub fn put_text(&self, out: &mut String, sep: char) {
        use std::fmt::Write;
        macro_rules! put {
            ($v:expr, $fmt:literal) => {
                for x in $v.iter() {
                    let _ = write!(out, $fmt, x);
                    out.push(sep);
                }
            };
        }
        match self {
            Chunk::U8(v) => put!(v, "{}"),
            Chunk::I32(v) => put!(v, "{}"),
            Chunk::I64(v) => put!(v, "{}"),
            Chunk::F32(v) => put!(v, "{:e}"),
            Chunk::F64(v) => put!(v, "{:e}"),
        }
    }
}

/// A writer's receiver of chunks.
pub type Sink<'s> = dyn FnMut(Chunk<'_>) -> io::Result<()> + 's;

type Producer<'a> = Box<dyn Fn(&mut Sink<'_>) -> io::Result<()> + 'a>;

/// Element types of columns.
pub trait Elem: Copy {
    const DTYPE: Dtype;
    fn chunk(v: &[Self]) -> Chunk<'_>;
    /// The values of a chunk of this type, None for another type.
    fn of_chunk<'c>(c: &Chunk<'c>) -> Option<&'c [Self]>;
}
macro_rules! elem {
    ($($t:ty => $d:ident),*) => {$(
        impl Elem for $t {
            const DTYPE: Dtype = Dtype::$d;
            fn chunk(v: &[Self]) -> Chunk<'_> { Chunk::$d(v) }
            fn of_chunk<'c>(c: &Chunk<'c>) -> Option<&'c [Self]> {
                match c { Chunk::$d(v) => Some(v), _ => None }
            }
        }
    )*};
}
elem!(u8 => U8, i32 => I32, i64 => I64, f32 => F32, f64 => F64);

/// Hands the values of `items` to `sink` in chunks of [`CHUNK_TUPLES`] values.
pub fn emit<T: Elem>(sink: &mut Sink<'_>, items: impl Iterator<Item = T>) -> io::Result<()> {
    let mut buf = Vec::with_capacity(CHUNK_TUPLES);
    for v in items {
        buf.push(v);
        if buf.len() == CHUNK_TUPLES {
            sink(T::chunk(&buf))?;
            buf.clear();
        }
    }
    if !buf.is_empty() {
        sink(T::chunk(&buf))?;
    }
    Ok(())
}

/// One named array of a mesh (points, connectivity, point, cell or field data), whose values
/// are produced on demand, chunk by chunk, as often as a writer asks.
pub struct Column<'a> {
    pub name: String,
    pub dtype: Dtype,
    pub components: usize,
    pub tuples: usize,
    /// Names of the components (ParaView shows them), empty for none.
    pub component_names: Vec<String>,
    produce: Producer<'a>,
}

impl<'a> Column<'a> {
    /// A column whose values `produce` hands to its sink (`tuples * components` values).
    pub fn generated<T: Elem>(
        name: &str,
        components: usize,
        tuples: usize,
        produce: impl Fn(&mut Sink<'_>) -> io::Result<()> + 'a,
    ) -> Self {
        Column {
            name: name.to_string(),
            dtype: T::DTYPE,
            components,
            tuples,
            component_names: Vec::new(),
            produce: Box::new(produce),
        }
    }

    /// A column over values held elsewhere.
    pub fn borrowed<T: Elem>(name: &str, components: usize, values: &'a [T]) -> Self {
        Self::generated::<T>(
            name,
            components,
            values.len() / components.max(1),
            move |sink| {
                for c in values.chunks(CHUNK_TUPLES) {
                    sink(T::chunk(c))?;
                }
                Ok(())
            },
        )
    }

    /// A column owning its (small) values.
    pub fn owned<T: Elem + 'a>(name: &str, components: usize, values: Vec<T>) -> Self {
        Self::generated::<T>(
            name,
            components,
            values.len() / components.max(1),
            move |sink| {
                for c in values.chunks(CHUNK_TUPLES) {
                    sink(T::chunk(c))?;
                }
                Ok(())
            },
        )
    }

    pub fn with_component_names(mut self, names: Vec<String>) -> Self {
        self.component_names = names;
        self
    }

    pub fn values(&self) -> usize {
        self.tuples * self.components
    }

    pub fn bytes(&self) -> u64 {
        (self.values() * self.dtype.size()) as u64
    }

    /// Hands every value to `sink`, in order.
    pub fn produce(&self, sink: &mut Sink<'_>) -> io::Result<()> {
        (self.produce)(sink)
    }
}

/// A mesh of one cell type.
pub struct Mesh<'a> {
    pub kind: CellKind,
    pub point_count: usize,
    pub cell_count: usize,
    /// Float64, 3 components.
    pub points: Column<'a>,
    /// Int64 point indices, [`CellKind::nodes`] per cell, as one component (VTK reads
    /// connectivity only as a one-component array).
    pub connectivity: Column<'a>,
    pub point_data: Vec<Column<'a>>,
    pub cell_data: Vec<Column<'a>>,
    /// Small arrays about the whole mesh (phase ids, periodic axes).
    pub field_data: Vec<Column<'a>>,
}

impl<'a> Mesh<'a> {
    /// The hexahedral voxel mesh's points and connectivity; data columns to be added.
    pub fn of_voxels(v: &'a VoxelHexMesh<'a>) -> Mesh<'a> {
        let points = Column::generated::<f64>("Points", 3, v.point_count(), move |sink| {
            emit(sink, v.point_corners().flat_map(|c| v.position(c)))
        });
        let connectivity =
            Column::generated::<i64>("connectivity", 1, 8 * v.cell_count(), move |sink| {
                emit(sink, v.cells().flat_map(|(_, n)| n.map(i64::from)))
            });
        Mesh {
            kind: CellKind::Hexahedron,
            point_count: v.point_count(),
            cell_count: v.cell_count(),
            points,
            connectivity,
            point_data: Vec::new(),
            cell_data: Vec::new(),
            field_data: Vec::new(),
        }
    }

    /// Points with one cell of `kind` per `kind.nodes()` consecutive indices of `cells`.
    pub fn explicit(kind: CellKind, points: Vec<f64>, cells: Vec<i64>) -> Mesh<'a> {
        let point_count = points.len() / 3;
        let cell_count = cells.len() / kind.nodes();
        Mesh {
            kind,
            point_count,
            cell_count,
            points: Column::owned("Points", 3, points),
            connectivity: Column::owned("connectivity", 1, cells),
            point_data: Vec::new(),
            cell_data: Vec::new(),
            field_data: Vec::new(),
        }
    }

    /// Bytes of all arrays as written uncompressed (what a writer may need to buffer at most
    /// when it must know compressed sizes before writing).
    pub fn bytes(&self) -> u64 {
        let data: u64 = self
            .point_data
            .iter()
            .chain(&self.cell_data)
            .map(Column::bytes)
            .sum();
        self.points.bytes() + self.connectivity.bytes() + data + 9 * self.cell_count as u64
    }
}

/// A name as one whitespace-free token (legacy VTK data names, Abaqus labels, ...).
pub fn token(name: &str) -> String {
    let t: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' || c == '-' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if t.is_empty() {
        "_".into()
    } else {
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shared_corners_are_one_point_and_cells_follow_vtk_order() {
        // 2x1x1 voxels, both selected: 3x2x2 = 12 corners, all used.
        let labels = [1u8, 1];
        let mut sel = [false; 256];
        sel[1] = true;
        let m = VoxelHexMesh::new([2, 1, 1], [0.0; 3], [1.0; 3], Some(&labels), sel).unwrap();
        assert_eq!((m.point_count(), m.cell_count()), (12, 2));
        let cells: Vec<_> = m.cells().collect();
        // Corner (1,0,0) is point 1; (1,1,0) is point 4; shared by both voxels.
        assert_eq!(cells[0].1, [0, 1, 4, 3, 6, 7, 10, 9]);
        assert_eq!(cells[1].1, [1, 2, 5, 4, 7, 8, 11, 10]);
        // Only voxel 1 selected: 8 points, renumbered densely in corner order.
        let labels = [0u8, 1];
        let m = VoxelHexMesh::new([2, 1, 1], [0.0; 3], [1.0; 3], Some(&labels), sel).unwrap();
        assert_eq!((m.point_count(), m.cell_count()), (8, 1));
        let corners: Vec<_> = m.point_corners().collect();
        assert_eq!(corners[0], [1, 0, 0]);
        assert_eq!(m.position([2, 1, 1]), [2.0, 1.0, 1.0]);
        assert_eq!(m.cells().next().unwrap().1, [0, 1, 3, 2, 4, 5, 7, 6]);
    }
}
