//! VTKHDF ImageData (`.vtkhdf`): the HDF5 layout VTK's `vtkHDFReader` (and so `pyvista.read`
//! and ParaView >= 5.12) opens directly.
//!
//! Group `/VTKHDF` with attributes `Version` = (2, 0), `Type` = "ImageData" (fixed-length
//! ASCII, as VTK writes it), `WholeExtent`, `Origin` (lower grid corner), `Spacing`,
//! `Direction`; cell arrays in `/VTKHDF/CellData/<name>` with shape (nz, ny, nx) or
//! (nz, ny, nx, components). VTK 9.7 writes Version (2, 8) and reads every 2.x file; the
//! ImageData layout has not changed since 1.0, so 2.0 is the lowest version that VTK >= 9.3
//! accepts without a warning.
//!
//! Cell arrays are chunked (whole xy slices, about 1 MiB per chunk) and deflated, level 4 by
//! default: libhdf5 inflates them for VTK, and a two-phase image shrinks tenfold or more.

use crate::h5util::*;
use crate::volume::{Volume, VolumeRef};
use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::{Artifact, FieldData, Provenance};
use hdf5_metno::types::FixedAscii;
use hdf5_metno::File;
use std::path::Path;

pub const VTKHDF_VERSION: [i64; 2] = [2, 0];

/// Writes a VTKHDF ImageData, cell arrays deflated at [`crate::hdf5_plain::DEFAULT_DEFLATE`].
pub fn write_vtkhdf(a: &Artifact, path: &Path, prov: &Provenance) -> Result<(), String> {
    write_vtkhdf_with(a, path, prov, DEFAULT_DEFLATE)
}

/// Writes a VTKHDF ImageData with the cell array deflated at `deflate` (0 = contiguous,
/// uncompressed). VTK reads chunked, deflated datasets through libhdf5 like contiguous ones.
pub fn write_vtkhdf_with(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    deflate: u8,
) -> Result<(), String> {
    let z = deflate;
    let v = VolumeRef::from_artifact(a, "vtkhdf")?;
    v.validate()?;
    atomic_write(path, |tmp| -> H5Result<()> {
        let f = File::create(tmp)?;
        provenance_attrs(&f, prov)?;
        let g = f.create_group("VTKHDF")?;
        let grid = v.grid();
        let [nx, ny, nz] = grid.dims;
        attr_array(&g, "Version", &VTKHDF_VERSION)?;
        let ty = FixedAscii::<9>::from_ascii(b"ImageData").expect("ascii");
        attr_scalar(&g, "Type", ty)?;
        attr_array(
            &g,
            "WholeExtent",
            &[0, nx as i32, 0, ny as i32, 0, nz as i32],
        )?;
        attr_array(&g, "Origin", &grid.origin)?;
        attr_array(&g, "Spacing", &grid.spacing)?;
        attr_array(
            &g,
            "Direction",
            &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        )?;
        g.create_group("PointData")?;
        let cells = g.create_group("CellData")?;
        let fd = g.create_group("FieldData")?;
        let mut shape = vec![nz, ny, nx];
        if v.components() > 1 {
            shape.push(v.components());
        }
        let name = v.name();
        if name.contains('/') || name.is_empty() {
            return Err(format!("array name `{name}` cannot name an HDF5 dataset").into());
        }
        let ds = match v {
            VolumeRef::Phase(p) => {
                let d = dataset(&cells, name, &shape, &p.labels, z)?;
                let ids: Vec<u8> = p.phases.iter().map(|ph| ph.id).collect();
                dataset(&fd, "phase_ids", &[ids.len()], &ids, 0)?;
                let names: Vec<&str> = p.phases.iter().map(|ph| ph.name.as_str()).collect();
                attr_array(&d, "phase_ids", &ids)?;
                attr_strs(&d, "phase_names", &names)?;
                d
            }
            VolumeRef::Field(fl) => match &fl.data {
                FieldData::F32(x) => dataset(&cells, name, &shape, x, z)?,
                FieldData::F64(x) => dataset(&cells, name, &shape, x, z)?,
            },
        };
        attr_str(
            &ds,
            "units",
            if v.unit().is_empty() { "1" } else { v.unit() },
        )?;
        let periodic = grid.periodic.map(|b| b as u8);
        dataset(&fd, "periodic", &[3], &periodic, 0)?;
        Ok(())
    })
}

/// Reads the first (or the named) cell array of a VTKHDF ImageData file.
pub fn read_vtkhdf(path: &Path, array: Option<&str>) -> Result<Volume, String> {
    let at = |e: hdf5_metno::Error| format!("{}: {e}", path.display());
    let f = File::open(path).map_err(at)?;
    let g = f.group("VTKHDF").map_err(at)?;
    let ty = read_attr_str(&g, "Type").unwrap_or_default();
    if ty != "ImageData" {
        return Err(format!(
            "{}: VTKHDF type `{ty}` is not ImageData",
            path.display()
        ));
    }
    let three = |k: &str| read_attr_f64s(&g, k).and_then(|v| <[f64; 3]>::try_from(v).ok());
    let cells = g.group("CellData").map_err(at)?;
    let name = match array {
        Some(a) => a.to_string(),
        None => cells
            .member_names()
            .map_err(at)?
            .into_iter()
            .next()
            .ok_or_else(|| format!("{}: no cell arrays", path.display()))?,
    };
    let mut v = crate::hdf5_plain::read_hdf5_dataset(path, &format!("VTKHDF/CellData/{name}"))?;
    v.spacing = three("Spacing");
    v.origin = three("Origin");
    if let Some(p) = g
        .dataset("FieldData/periodic")
        .ok()
        .and_then(|d| d.read_raw::<u8>().ok())
    {
        if p.len() == 3 {
            v.periodic = [p[0] != 0, p[1] != 0, p[2] != 0];
        }
    }
    Ok(v)
}

crate::vtk_xml::exporter!(
    VtkHdfExporter,
    "vtkhdf",
    &["vtkhdf"],
    [PhaseImage, Field],
    "VTKHDF ImageData (HDF5) that pyvista.read and ParaView >= 5.12 open directly; cell arrays \
     (nz, ny, nx[, components]) with `units`, origin = lower grid corner; chunked and deflated \
     (option `compression`)",
    options: vec![compression_option()],
    check: check_compression,
    write: write_vtkhdf_options
);

fn write_vtkhdf_options(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<(), String> {
    write_vtkhdf_with(a, path, prov, deflate_option(options))
}
