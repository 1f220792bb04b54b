//! Small helpers over hdf5-metno shared by the plain HDF5 and the VTKHDF writers/readers.

use hdf5_metno::types::{TypeDescriptor, VarLenUnicode};
use hdf5_metno::{Dataset, Group, H5Type, Location};

pub(crate) type H5Result<T> = hdf5_metno::Result<T>;

fn vlu(s: &str) -> H5Result<VarLenUnicode> {
    s.replace('\0', " ")
        .parse::<VarLenUnicode>()
        .map_err(|e| hdf5_metno::Error::from(e.to_string()))
}

/// Creates a dataset of `shape` holding `data` (row-major, last index fastest).
pub(crate) fn dataset<T: H5Type>(
    g: &Group,
    name: &str,
    shape: &[usize],
    data: &[T],
) -> H5Result<Dataset> {
    debug_assert_eq!(shape.iter().product::<usize>(), data.len());
    let d = g.new_dataset::<T>().shape(shape).create(name)?;
    if !data.is_empty() {
        d.write_raw(data)?;
    }
    Ok(d)
}

pub(crate) fn string_dataset(g: &Group, name: &str, values: &[String]) -> H5Result<Dataset> {
    let v = values
        .iter()
        .map(|s| vlu(s))
        .collect::<H5Result<Vec<_>>>()?;
    dataset(g, name, &[v.len()], &v)
}

pub(crate) fn attr_array<T: H5Type>(loc: &Location, name: &str, values: &[T]) -> H5Result<()> {
    loc.new_attr::<T>()
        .shape(values.len())
        .create(name)?
        .write_raw(values)
}

pub(crate) fn attr_scalar<T: H5Type>(loc: &Location, name: &str, value: T) -> H5Result<()> {
    loc.new_attr::<T>().create(name)?.write_scalar(&value)
}

pub(crate) fn attr_str(loc: &Location, name: &str, value: &str) -> H5Result<()> {
    attr_scalar(loc, name, vlu(value)?)
}

pub(crate) fn attr_strs(loc: &Location, name: &str, values: &[&str]) -> H5Result<()> {
    let v = values
        .iter()
        .map(|s| vlu(s))
        .collect::<H5Result<Vec<_>>>()?;
    attr_array(loc, name, &v)
}

/// Opens an attribute if it exists (probing a missing one makes HDF5 print an error stack).
fn attr(loc: &Location, name: &str) -> Option<hdf5_metno::Attribute> {
    if !loc.attr_names().ok()?.iter().any(|n| n == name) {
        return None;
    }
    loc.attr(name).ok()
}

/// A string attribute, whether stored as variable- or fixed-length text.
pub(crate) fn read_attr_str(loc: &Location, name: &str) -> Option<String> {
    let a = attr(loc, name)?;
    match a.dtype().ok()?.to_descriptor().ok()? {
        TypeDescriptor::VarLenUnicode => {
            a.read_scalar::<VarLenUnicode>().ok().map(|s| s.to_string())
        }
        TypeDescriptor::VarLenAscii => a
            .read_scalar::<hdf5_metno::types::VarLenAscii>()
            .ok()
            .map(|s| s.to_string()),
        TypeDescriptor::FixedAscii(_) => a
            .read_scalar::<hdf5_metno::types::FixedAscii<1024>>()
            .ok()
            .map(|s| s.as_str().trim_end_matches('\0').to_string()),
        TypeDescriptor::FixedUnicode(_) => a
            .read_scalar::<hdf5_metno::types::FixedUnicode<1024>>()
            .ok()
            .map(|s| s.as_str().trim_end_matches('\0').to_string()),
        _ => None,
    }
}

pub(crate) fn read_attr_strs(loc: &Location, name: &str) -> Option<Vec<String>> {
    let a = attr(loc, name)?;
    let v = a.read_raw::<VarLenUnicode>().ok()?;
    Some(v.iter().map(|s| s.to_string()).collect())
}

pub(crate) fn read_attr_f64s(loc: &Location, name: &str) -> Option<Vec<f64>> {
    attr(loc, name)?.read_raw::<f64>().ok()
}

pub(crate) fn read_strings(g: &Group, name: &str) -> H5Result<Vec<String>> {
    Ok(g.dataset(name)?
        .read_raw::<VarLenUnicode>()?
        .iter()
        .map(|s| s.to_string())
        .collect())
}

/// Provenance entries as string attributes of `loc`.
pub(crate) fn provenance_attrs(loc: &Location, prov: &grainpipe_core::Provenance) -> H5Result<()> {
    for (k, v) in &prov.entries {
        attr_str(loc, k, v)?;
    }
    Ok(())
}
