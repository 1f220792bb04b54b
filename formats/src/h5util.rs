//! Small helpers over hdf5-metno shared by the plain HDF5 and the VTKHDF writers/readers.

use hdf5_metno::types::{TypeDescriptor, VarLenUnicode};
use hdf5_metno::{Dataset, Group, H5Type, Location};

pub(crate) type H5Result<T> = hdf5_metno::Result<T>;

fn vlu(s: &str) -> H5Result<VarLenUnicode> {
    s.replace('\0', " ")
        .parse::<VarLenUnicode>()
        .map_err(|e| hdf5_metno::Error::from(e.to_string()))
}

/// "`path`: cannot open as `format`: `err`", with the likely cause when it is HDF5's file
/// lock: a file another process holds open for writing (or a process forked while it was
/// open, which inherits the lock) cannot be opened, and NetCDF-4 reports that only as "HDF
/// error".
pub(crate) fn cannot_open(
    path: &std::path::Path,
    format: &str,
    err: &dyn std::fmt::Display,
) -> String {
    let err = err.to_string();
    let mut head = [0u8; 8];
    let hdf5_signature = std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .is_ok()
        && &head == b"\x89HDF\r\n\x1a\n";
    let locked = err.contains("lock") || (err.contains("HDF error") && hdf5_signature);
    let hint = if locked {
        "; if another program has the file open for writing, HDF5's file lock refuses to read \
         it: close it there, or set HDF5_USE_FILE_LOCKING=FALSE"
    } else {
        ""
    };
    format!("{}: cannot open as {format}: {err}{hint}", path.display())
}

/// Deflate level the HDF5, VTKHDF and NetCDF writers use unless told otherwise: level 4
/// gives nearly all of level 9's size on voxel images at a fraction of its time.
pub const DEFAULT_DEFLATE: u8 = 4;

/// Uncompressed bytes per chunk the chunk shapes aim at: HDF5's default chunk cache is
/// 1 MiB, so a chunk is decompressed once per read of a z-slab, and small datasets are not
/// split into chunks whose index outweighs them.
const CHUNK_BYTES: usize = 1 << 20;

/// Datasets smaller than this stay contiguous: deflate cannot win back its chunk index.
const MIN_COMPRESSED_BYTES: usize = 4096;

/// A chunk shape of about [`CHUNK_BYTES`] for a row-major dataset of `shape`: whole trailing
/// axes (whole xy slices of a (z, y, x) volume, whole rows of an (N, 3) table), as many
/// leading indices as fit.
pub(crate) fn chunk_shape(shape: &[usize], elem_bytes: usize) -> Vec<usize> {
    let mut chunk = shape.to_vec();
    for a in 0..shape.len() {
        let trailing: usize = shape[a + 1..].iter().product::<usize>() * elem_bytes.max(1);
        if trailing <= CHUNK_BYTES {
            chunk[a] = (CHUNK_BYTES / trailing).clamp(1, shape[a].max(1));
            return chunk;
        }
        chunk[a] = 1;
    }
    chunk
}

/// Creates a dataset of `shape` holding `data` (row-major, last index fastest), chunked and
/// deflated at `deflate` (1-9; 0 = contiguous, uncompressed), with the byte shuffle filter
/// for multi-byte elements (it groups the similar high bytes of neighbouring numbers, which
/// is what lets deflate shrink floats).
pub(crate) fn dataset<T: H5Type>(
    g: &Group,
    name: &str,
    shape: &[usize],
    data: &[T],
    deflate: u8,
) -> H5Result<Dataset> {
    debug_assert_eq!(shape.iter().product::<usize>(), data.len());
    let d = empty_dataset::<T>(g, name, shape, deflate)?;
    if !data.is_empty() {
        d.write_raw(data)?;
    }
    Ok(d)
}

/// A dataset of `shape`, chunked and deflated as [`dataset`] does, to be filled by slabs.
pub(crate) fn empty_dataset<T: H5Type>(
    g: &Group,
    name: &str,
    shape: &[usize],
    deflate: u8,
) -> H5Result<Dataset> {
    let elem = std::mem::size_of::<T>();
    let mut b = g.new_dataset::<T>().shape(shape);
    if deflate > 0 && shape.iter().product::<usize>() * elem >= MIN_COMPRESSED_BYTES {
        let mut filters = Vec::new();
        if elem > 1 {
            filters.push(hdf5_metno::filters::Filter::shuffle());
        }
        filters.push(hdf5_metno::filters::Filter::deflate(deflate.min(9)));
        b = b.chunk(chunk_shape(shape, elem)).set_filters(&filters);
    }
    b.create(name)
}

pub(crate) fn string_dataset(g: &Group, name: &str, values: &[String]) -> H5Result<Dataset> {
    let v = values
        .iter()
        .map(|s| vlu(s))
        .collect::<H5Result<Vec<_>>>()?;
    // Variable-length strings live in the global heap: deflating their references gains
    // nothing.
    dataset(g, name, &[v.len()], &v, 0)
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

/// Provenance entries as attributes of `loc`: the seeds as u64 (so `f.attrs["seed"]` is a
/// number in h5py and 64-bit seeds survive exactly), the rest as strings.
pub(crate) fn provenance_attrs(loc: &Location, prov: &grainpipe_core::Provenance) -> H5Result<()> {
    for (k, v) in &prov.entries {
        match prov.integer(k) {
            Some(n) => attr_scalar(loc, k, n)?,
            None => attr_str(loc, k, v)?,
        }
    }
    Ok(())
}

/// The deflate level of an exporter's options (`compression`, 0-9; the default when absent).
pub(crate) fn deflate_option(options: &grainpipe_core::registry::ExportOptions) -> u8 {
    options
        .get("compression")
        .and_then(|v| v.as_u64())
        .map(|l| l.min(9) as u8)
        .unwrap_or(DEFAULT_DEFLATE)
}

/// The `compression` option the HDF5, VTKHDF and NetCDF exporters declare.
pub(crate) fn compression_option() -> grainpipe_core::registry::ExportOption {
    grainpipe_core::registry::ExportOption {
        name: "compression",
        doc: "deflate level of the datasets, 0-9: 0 writes them contiguous and uncompressed \
              (fastest to write, largest), 1-9 chunked (about 1 MiB per chunk, whole xy \
              slices) and deflated, with the byte shuffle filter for multi-byte numbers",
        default: serde_json::json!(DEFAULT_DEFLATE),
    }
}

/// Checks a `compression` value: an integer 0-9.
pub(crate) fn check_compression(
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<(), (String, String)> {
    match options.get("compression") {
        None => Ok(()),
        Some(v) if v.as_u64().is_some_and(|l| l <= 9) => Ok(()),
        Some(v) => Err((
            "compression".into(),
            format!("{v} is not a deflate level; write an integer 0 (off) to 9 (smallest)"),
        )),
    }
}
