//! grainpipe-formats: file formats for every artifact kind, their readers and the import
//! stages.
//!
//! | format | extension | artifact kinds |
//! |---|---|---|
//! | `vti` | .vti | PhaseImage, Field |
//! | `vtp` | .vtp | Packing, ContactGraph |
//! | `pvd` | .pvd | Series or Collection (of images/fields or packings/graphs) |
//! | `vtkhdf` | .vtkhdf | PhaseImage, Field |
//! | `h5` | .h5, .hdf5 | every kind |
//! | `nc` | .nc | PhaseImage, Field |
//! | `csv` | .csv | Table, Tensor, ContactGraph |
//! | `json` | .json | Table, Tensor, ContactGraph |
//! | `tiff` | .tif, .tiff | PhaseImage, Field (one component) |
//! | `raw` | .mhd, .raw | PhaseImage, Field (raw voxels + MetaImage header) |
//! | `lammps-data` | .data, .lmp | Packing |
//! | `lammps-molecule` | (by name) | ClumpLibrary, Packing with clumps |
//! | `yade` | (by name) | Packing |
//! | `stl` | .stl | Packing, ClumpLibrary (icospheres), PhaseImage (one phase's surface) |
//! | `vtu` | .vtu | PhaseImage, Field (hexahedra), Packing (vertices), ContactGraph (lines) |
//! | `vtk` | .vtk | as `vtu`, legacy format |
//! | `xdmf` | .xdmf, .xmf | as `vtu` (+ `<stem>.h5`), or images as a 3DCoRectMesh |
//! | `abaqus` | .inp | PhaseImage (C3D8 voxel mesh) |
//! | `gmsh` | .msh | PhaseImage (hexahedra, physical group per phase) |
//!
//! Every writer goes through `grainpipe_core::fsutil::atomic_write`: a failed write leaves
//! no file behind. See docs/stages/formats.md for the layouts and how to open them.

pub mod dem;
mod h5util;
pub mod hdf5_plain;
pub mod headers;
pub mod import;
pub mod import_packing;
pub mod mesh;
pub mod netcdf_io;
pub mod raw;
pub mod stl;
pub mod tables;
pub mod tiff_io;
pub mod volume;
pub mod vtk_xml;
pub mod vtkhdf;

pub use hdf5_plain::{
    read_h5, read_h5_clump_library, read_h5_contact_graph, read_h5_packing, read_h5_series,
    read_h5_table, read_h5_tensor, read_hdf5_dataset, write_h5,
};
pub use netcdf_io::{read_netcdf_variable, write_nc};
pub use raw::{read_raw, Endian, RawDtype, RawLayout};
pub use tables::{
    read_contact_graph_json, read_table_csv, read_table_json, read_tensor_json, write_csv,
    write_json,
};
pub use volume::{Probe, Volume, VolumeData};
pub use vtk_xml::{read_vti, write_pvd, write_vti, write_vtp};
pub use vtkhdf::{read_vtkhdf, write_vtkhdf};

use grainpipe_core::Registry;

/// Adds every exporter and the import stages.
pub fn register(r: &mut Registry) {
    r.add_exporter(vtk_xml::VtiExporter);
    r.add_exporter(vtk_xml::VtpExporter);
    r.add_exporter(vtk_xml::PvdExporter);
    r.add_exporter(vtkhdf::VtkHdfExporter);
    r.add_exporter(hdf5_plain::H5Exporter);
    r.add_exporter(netcdf_io::NcExporter);
    r.add_exporter(tables::CsvExporter);
    r.add_exporter(tables::JsonExporter);
    r.add_exporter(tiff_io::TiffExporter);
    r.add_exporter(raw::RawExporter);
    r.add_exporter(dem::LammpsDataExporter);
    r.add_exporter(dem::LammpsMoleculeExporter);
    r.add_exporter(dem::YadeExporter);
    r.add_exporter(stl::StlExporter);
    r.add_exporter(mesh::VtuExporter);
    r.add_exporter(mesh::LegacyVtkExporter);
    r.add_exporter(mesh::XdmfExporter);
    r.add_exporter(mesh::AbaqusExporter);
    r.add_exporter(mesh::GmshExporter);
    r.add_stage(import::ImportRaw);
    r.add_stage(import::ImportHdf5);
    r.add_stage(import::ImportNetcdf);
    r.add_stage(import::ImportVti);
    r.add_stage(import::ImportTiff);
    r.add_stage(import_packing::ImportPacking);
}
