//! NetCDF-4 (`.nc`) for phase images and fields, CF style: dimensions (z, y, x) (+ `component`
//! when a field has more than one), coordinate variables x, y, z at voxel centres [m], `units`
//! and `long_name` on every variable, phase tables as CF `flag_values`/`flag_meanings`, and
//! provenance as global attributes. Global `spacing`/`origin` (x, y, z order) keep the grid
//! exact for readers that do not want to difference coordinates.

use crate::volume::{Probe, StatedGrid, Volume, VolumeData, VolumeRef};
use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::units::{parse_unit, Dimension};
use grainpipe_core::{Artifact, ComponentConvention, FieldData, Phase, Provenance};
use netcdf::types::{FloatType, IntType, NcVariableType};
use netcdf::AttributeValue;
use std::path::Path;

type NcResult<T> = Result<T, String>;

/// netCDF-C probes optional HDF5 attributes (quantization settings) and libhdf5 would print
/// an error stack for each missing one; errors are still returned as values.
fn quiet_hdf5() {
    hdf5_metno::silence_errors(true);
}

fn nc(e: netcdf::Error) -> String {
    e.to_string()
}

/// netCDF names: letters, digits, `_.@+-`, not starting with a digit or punctuation.
fn nc_name(k: &str) -> String {
    let mut s: String = k
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "_.@+-".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect();
    if !s.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') {
        s.insert(0, '_');
    }
    s
}

/// Writes a NetCDF-4 file, the data variable deflated at
/// [`crate::hdf5_plain::DEFAULT_DEFLATE`].
pub fn write_nc(a: &Artifact, path: &Path, prov: &Provenance) -> Result<(), String> {
    write_nc_with(a, path, prov, crate::hdf5_plain::DEFAULT_DEFLATE)
}

/// Writes a NetCDF-4 file with the data variable chunked (whole xy slices, about 1 MiB per
/// chunk) and deflated at `deflate` (0 = contiguous, uncompressed), with the shuffle filter
/// for multi-byte values.
pub fn write_nc_with(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    deflate: u8,
) -> Result<(), String> {
    let v = VolumeRef::from_artifact(a, "nc")?;
    v.validate()?;
    atomic_write(path, |tmp| write_inner(v, tmp, prov, deflate))
}

/// Chunks and deflates a data variable of `shape` and `elem` bytes per value (no-op for
/// `deflate` 0 or a variable too small to gain).
fn compress(
    var: &mut netcdf::VariableMut,
    shape: &[usize],
    elem: usize,
    deflate: u8,
) -> NcResult<()> {
    if deflate == 0 || shape.iter().product::<usize>() * elem < 4096 {
        return Ok(());
    }
    var.set_chunking(&crate::h5util::chunk_shape(shape, elem))
        .map_err(nc)?;
    var.set_compression(i32::from(deflate.min(9)), elem > 1)
        .map_err(nc)
}

fn write_inner(v: VolumeRef, tmp: &Path, prov: &Provenance, deflate: u8) -> NcResult<()> {
    let g = v.grid();
    let [nx, ny, nz] = g.dims;
    quiet_hdf5();
    let mut f = netcdf::create(tmp).map_err(nc)?;
    f.add_attribute("Conventions", "CF-1.8").map_err(nc)?;
    f.add_attribute("title", format!("grainpipe {}", v.name()))
        .map_err(nc)?;
    f.add_attribute("spacing", g.spacing.to_vec()).map_err(nc)?;
    f.add_attribute("origin", g.origin.to_vec()).map_err(nc)?;
    f.add_attribute("periodic", g.periodic.map(|b| b as u8).to_vec())
        .map_err(nc)?;
    for (k, val) in &prov.entries {
        match prov.integer(k) {
            // NC_UINT64, so `ds.seed` is a number in netCDF4-python and 64-bit seeds stay exact.
            Some(n) => f.add_attribute(&nc_name(k), n).map_err(nc)?,
            None => f.add_attribute(&nc_name(k), val.as_str()).map_err(nc)?,
        };
    }
    for (name, n) in [("z", nz), ("y", ny), ("x", nx)] {
        f.add_dimension(name, n).map_err(nc)?;
    }
    for (a, name) in ["x", "y", "z"].iter().enumerate() {
        let centres: Vec<f64> = (0..g.dims[a])
            .map(|i| g.origin[a] + (i as f64 + 0.5) * g.spacing[a])
            .collect();
        let mut c = f.add_variable::<f64>(name, &[name]).map_err(nc)?;
        c.put_attribute("units", "m").map_err(nc)?;
        c.put_attribute("long_name", format!("{name} coordinate of voxel centres"))
            .map_err(nc)?;
        c.put_attribute("axis", name.to_uppercase()).map_err(nc)?;
        c.put_values(&centres, ..).map_err(nc)?;
    }
    let mut dims = vec!["z", "y", "x"];
    if v.components() > 1 {
        f.add_dimension("component", v.components()).map_err(nc)?;
        dims.push("component");
    }
    let name = nc_name(v.name());
    let mut shape = vec![nz, ny, nx];
    if v.components() > 1 {
        shape.push(v.components());
    }
    match v {
        VolumeRef::Phase(p) => {
            let mut var = f.add_variable::<u8>(&name, &dims).map_err(nc)?;
            compress(&mut var, &shape, 1, deflate)?;
            var.put_attribute("long_name", "phase label").map_err(nc)?;
            var.put_attribute("units", "1").map_err(nc)?;
            let ids: Vec<u8> = p.phases.iter().map(|ph| ph.id).collect();
            let meanings: Vec<String> = p.phases.iter().map(|ph| nc_name(&ph.name)).collect();
            let names: Vec<String> = p.phases.iter().map(|ph| ph.name.clone()).collect();
            if !ids.is_empty() {
                var.put_attribute("flag_values", ids).map_err(nc)?;
                var.put_attribute("flag_meanings", meanings.join(" "))
                    .map_err(nc)?;
                var.put_attribute("phase_names", names).map_err(nc)?;
            }
            var.put_values(&p.labels, ..).map_err(nc)?;
        }
        VolumeRef::Field(fl) => {
            let unit = if fl.unit.is_empty() { "1" } else { &fl.unit };
            macro_rules! put {
                ($t:ty, $d:expr) => {{
                    let mut var = f.add_variable::<$t>(&name, &dims).map_err(nc)?;
                    compress(&mut var, &shape, std::mem::size_of::<$t>(), deflate)?;
                    var.put_attribute("long_name", fl.name.as_str())
                        .map_err(nc)?;
                    var.put_attribute("units", unit).map_err(nc)?;
                    var.put_attribute("component_convention", fl.convention.name())
                        .map_err(nc)?;
                    if fl.components > 1 {
                        var.put_attribute("component_names", fl.component_names().join(" "))
                            .map_err(nc)?;
                    }
                    var.put_values($d, ..).map_err(nc)?;
                }};
            }
            match &fl.data {
                FieldData::F32(d) => put!(f32, d),
                FieldData::F64(d) => put!(f64, d),
            }
        }
    }
    f.close().map_err(nc)
}

fn attr_f64s(v: Option<netcdf::Result<AttributeValue>>) -> Option<Vec<f64>> {
    Some(match v?.ok()? {
        AttributeValue::Doubles(d) => d,
        AttributeValue::Floats(d) => d.into_iter().map(f64::from).collect(),
        AttributeValue::Double(d) => vec![d],
        AttributeValue::Uchars(d) => d.into_iter().map(f64::from).collect(),
        AttributeValue::Schars(d) => d.into_iter().map(f64::from).collect(),
        AttributeValue::Shorts(d) => d.into_iter().map(f64::from).collect(),
        AttributeValue::Ints(d) => d.into_iter().map(f64::from).collect(),
        AttributeValue::Uchar(d) => vec![d.into()],
        AttributeValue::Int(d) => vec![d.into()],
        _ => return None,
    })
}

fn attr_str(v: Option<netcdf::Result<AttributeValue>>) -> Option<String> {
    match v?.ok()? {
        AttributeValue::Str(s) => Some(s),
        _ => None,
    }
}

/// Shape ([nx, ny, nz], components) of variable `var`, without reading it.
pub fn probe_netcdf_variable(path: &Path, var: &str) -> Result<Probe, String> {
    let at = |e: String| format!("{}: {e}", path.display());
    quiet_hdf5();
    let f = netcdf::open(path).map_err(|e| crate::h5util::cannot_open(path, "NetCDF", &e))?;
    let v = f.variable(var).ok_or_else(|| at(missing(&f, var)))?;
    let lens: Vec<usize> = v.dimensions().iter().map(|d| d.len()).collect();
    let (dims, components) = shape(&lens).map_err(at)?;
    Ok(Probe {
        dims,
        components,
        dtype: format!("{:?}", v.vartype()),
        elem_bytes: v.vartype().size(),
        spacing: global3(&f, "spacing"),
        origin: global3(&f, "origin"),
    })
}

fn missing(f: &netcdf::File, var: &str) -> String {
    let names: Vec<String> = f.variables().map(|v| v.name()).collect();
    format!("no variable `{var}` (variables: {})", names.join(", "))
}

fn shape(lens: &[usize]) -> NcResult<([usize; 3], usize)> {
    Ok(match *lens {
        [ny, nx] => ([nx, ny, 1], 1),
        [nz, ny, nx] => ([nx, ny, nz], 1),
        [nz, ny, nx, c] => ([nx, ny, nz], c),
        _ => {
            return Err(format!(
                "variable shape {lens:?} is not (y, x), (z, y, x) or (z, y, x, component)"
            ))
        }
    })
}

/// Reads a variable of shape (y, x), (z, y, x) or (z, y, x, component). The grid comes from
/// the global `spacing`/`origin` attributes when present (grainpipe files), otherwise from
/// uniformly spaced CF coordinate variables named like the dimensions, converted to metres
/// through their `units`.
pub fn read_netcdf_variable(path: &Path, var: &str) -> Result<Volume, String> {
    let at = |e: String| format!("{}: {e}", path.display());
    quiet_hdf5();
    let f = netcdf::open(path).map_err(|e| crate::h5util::cannot_open(path, "NetCDF", &e))?;
    let v = f.variable(var).ok_or_else(|| at(missing(&f, var)))?;
    let lens: Vec<usize> = v.dimensions().iter().map(|d| d.len()).collect();
    let (dims, components) = shape(&lens).map_err(at)?;
    let bytes = lens
        .iter()
        .try_fold(v.vartype().size() as u64, |a, &d| a.checked_mul(d as u64));
    crate::volume::check_declared(&format!("variable `{var}`"), bytes).map_err(at)?;
    let data = match v.vartype() {
        NcVariableType::Int(IntType::U8) => {
            VolumeData::U8(v.get_values(..).map_err(|e| at(nc(e)))?)
        }
        NcVariableType::Int(IntType::U16) => {
            VolumeData::U16(v.get_values(..).map_err(|e| at(nc(e)))?)
        }
        NcVariableType::Int(IntType::I8 | IntType::I16 | IntType::I32) => {
            VolumeData::I32(v.get_values(..).map_err(|e| at(nc(e)))?)
        }
        NcVariableType::Int(_) => VolumeData::F64(v.get_values(..).map_err(|e| at(nc(e)))?),
        NcVariableType::Float(FloatType::F32) => {
            VolumeData::F32(v.get_values(..).map_err(|e| at(nc(e)))?)
        }
        NcVariableType::Float(FloatType::F64) => {
            VolumeData::F64(v.get_values(..).map_err(|e| at(nc(e)))?)
        }
        t => return Err(at(format!("variable `{var}` holds {t:?}, not numbers"))),
    };
    let (spacing, origin, periodic) = grid(&f, &v).map_err(at)?;
    let mut phases = Vec::new();
    let names = match v.attribute_value("phase_names").and_then(|r| r.ok()) {
        Some(AttributeValue::Strs(s)) => Some(s),
        Some(AttributeValue::Str(s)) => Some(vec![s]),
        _ => attr_str(v.attribute_value("flag_meanings"))
            .map(|m| m.split_whitespace().map(str::to_string).collect()),
    };
    if let (Some(ids), Some(names)) = (attr_f64s(v.attribute_value("flag_values")), names) {
        if ids.len() == names.len() {
            phases = ids
                .iter()
                .zip(names)
                .map(|(&id, name)| Phase { id: id as u8, name })
                .collect();
        }
    }
    let unit = attr_str(v.attribute_value("units"))
        .filter(|u| u != "1")
        .unwrap_or_default();
    let convention = attr_str(v.attribute_value("component_convention"))
        .and_then(|c| ComponentConvention::from_name(&c))
        .unwrap_or_default();
    Ok(Volume {
        name: var.to_string(),
        unit,
        dims,
        components,
        convention,
        spacing,
        origin,
        periodic,
        data,
        phases,
    })
}

/// Feeds the values of variable `var` to `scan` in slabs along its first dimension of about
/// [`crate::import::SCAN_BLOCK_BYTES`], read in the variable's own type, so checking the labels
/// of a large variable never holds it in memory.
pub fn scan_netcdf_variable(
    path: &Path,
    var: &str,
    scan: &mut crate::volume::LabelScan,
) -> Result<(), String> {
    let at = |e: String| format!("{}: {e}", path.display());
    quiet_hdf5();
    let f = netcdf::open(path).map_err(|e| crate::h5util::cannot_open(path, "NetCDF", &e))?;
    let v = f.variable(var).ok_or_else(|| at(missing(&f, var)))?;
    let lens: Vec<usize> = v.dimensions().iter().map(|d| d.len()).collect();
    shape(&lens).map_err(at)?;
    let row: usize = lens[1..].iter().product::<usize>().max(1);
    let step = (crate::import::SCAN_BLOCK_BYTES / 8 / row).max(1);
    let mut a = 0;
    while a < lens[0] {
        let b = (a + step).min(lens[0]);
        let ext: Vec<std::ops::Range<usize>> = std::iter::once(a..b)
            .chain(lens[1..].iter().map(|&l| 0..l))
            .collect();
        macro_rules! feed {
            ($t:ty) => {{
                let block: Vec<$t> = v.get_values(ext).map_err(|e| at(nc(e)))?;
                scan.feed(block.into_iter().map(|x| x as f64));
            }};
        }
        match v.vartype() {
            NcVariableType::Int(IntType::U8) => feed!(u8),
            NcVariableType::Int(IntType::I8) => feed!(i8),
            NcVariableType::Int(IntType::U16) => feed!(u16),
            NcVariableType::Int(IntType::I16) => feed!(i16),
            NcVariableType::Int(IntType::U32) => feed!(u32),
            NcVariableType::Int(IntType::I32) => feed!(i32),
            NcVariableType::Int(IntType::U64) => feed!(u64),
            NcVariableType::Int(IntType::I64) => feed!(i64),
            NcVariableType::Float(FloatType::F32) => feed!(f32),
            NcVariableType::Float(FloatType::F64) => feed!(f64),
            t => return Err(at(format!("variable `{var}` holds {t:?}, not numbers"))),
        }
        a = b;
    }
    Ok(())
}

/// Three numbers of global attribute `k`.
fn global3(f: &netcdf::File, k: &str) -> Option<[f64; 3]> {
    attr_f64s(f.attribute(k).map(|a| a.value())).and_then(|v| <[f64; 3]>::try_from(v).ok())
}

/// The grid of variable `v` of `f` as the readers take it: the global `spacing` and
/// `origin` attributes when present (grainpipe files), otherwise uniformly spaced CF
/// coordinate variables named like the dimensions, converted to metres through their
/// `units`; global `periodic`.
pub(crate) fn grid(f: &netcdf::File, v: &netcdf::Variable) -> NcResult<StatedGrid> {
    let (mut spacing, mut origin) = (global3(f, "spacing"), global3(f, "origin"));
    if spacing.is_none() {
        // CF coordinates: dimension order is (z, y, x) or (y, x); axis a of [x, y, z].
        let dnames: Vec<String> = v.dimensions().iter().map(|d| d.name()).collect();
        let ndims = dnames.len();
        let axis_names: Vec<&String> = dnames
            .iter()
            .take(if ndims == 2 { 2 } else { 3 })
            .rev()
            .collect();
        let mut s = [1.0; 3];
        let mut o = [0.0; 3];
        let mut ok = axis_names.len() >= 2;
        for (a, dn) in axis_names.iter().enumerate() {
            match coordinate(f, dn) {
                Some(Ok((sa, oa))) => {
                    s[a] = sa;
                    o[a] = oa;
                }
                Some(Err(e)) => return Err(e),
                None => ok = false,
            }
        }
        if ok {
            if ndims == 2 {
                s[2] = s[0];
            }
            spacing = Some(s);
            origin = Some(o);
        }
    }
    let periodic = global3(f, "periodic")
        .map(|p| p.map(|x| x != 0.0))
        .unwrap_or_default();
    Ok((spacing, origin, periodic))
}

/// (spacing, lower corner) in metres of a uniformly spaced coordinate variable.
fn coordinate(f: &netcdf::File, name: &str) -> Option<Result<(f64, f64), String>> {
    let c = f.variable(name)?;
    let vals: Vec<f64> = c.get_values(..).ok()?;
    if vals.len() < 2 {
        return None;
    }
    let scale = match attr_str(c.attribute_value("units")) {
        Some(u) => match parse_unit(&u) {
            Ok((k, d)) if d == Dimension::LENGTH => k,
            _ => {
                return Some(Err(format!(
                    "coordinate `{name}` has units `{u}`, not a length"
                )))
            }
        },
        None => 1.0,
    };
    let s = vals[1] - vals[0];
    let n = vals.len() as f64;
    // uniform within float roundoff of the coordinate values
    let tol = 1e-9 * s.abs() * n;
    if s <= 0.0
        || vals
            .iter()
            .enumerate()
            .any(|(i, &x)| (x - (vals[0] + i as f64 * s)).abs() > tol.max(1e-12 * x.abs()))
    {
        return Some(Err(format!(
            "coordinate `{name}` is not increasing uniformly; give `spacing` and `origin` explicitly"
        )));
    }
    Some(Ok((s * scale, (vals[0] - 0.5 * s) * scale)))
}

crate::vtk_xml::exporter!(
    NcExporter,
    "nc",
    &["nc"],
    [PhaseImage, Field],
    "NetCDF-4, CF style: (z, y, x[, component]) variable with units/long_name, coordinate \
     variables x, y, z at voxel centres [m], phase table as flag_values/flag_meanings, \
     provenance as global attributes (seeds as uint64); data variable chunked and deflated \
     (option `compression`)",
    options: vec![crate::h5util::compression_option()],
    check: crate::h5util::check_compression,
    write: write_nc_options
);

fn write_nc_options(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<(), String> {
    write_nc_with(a, path, prov, crate::h5util::deflate_option(options))
}
