//! Headerless raw volumes (`.raw`, `.bin`, ...): the layout is given by the user, so the only
//! check possible before reading is the file size.

use crate::volume::{from_bytes, Probe, Volume, VolumeData};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Element type of a raw volume.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RawDtype {
    #[default]
    U8,
    U16,
    I32,
    F32,
    F64,
}

impl RawDtype {
    pub fn size(self) -> usize {
        match self {
            RawDtype::U8 => 1,
            RawDtype::U16 => 2,
            RawDtype::I32 | RawDtype::F32 => 4,
            RawDtype::F64 => 8,
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Endian {
    #[default]
    Little,
    Big,
}

/// How a raw file is laid out: x fastest, then y, then z, after `header_bytes` skipped bytes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RawLayout {
    /// [nx, ny, nz].
    pub dims: [usize; 3],
    pub dtype: RawDtype,
    pub endian: Endian,
    pub header_bytes: u64,
}

impl RawLayout {
    /// Bytes the layout needs, `None` when the dims overflow (dims come from the user and
    /// a wrapped product would match a small file).
    pub fn expected_size(&self) -> Option<u64> {
        let [x, y, z] = self.dims;
        grainpipe_core::checked_product(&[x, y, z, self.dtype.size()])
            .and_then(|n| u64::try_from(n).ok())
            .and_then(|n| n.checked_add(self.header_bytes))
    }
}

/// Checks that the file exists and has exactly the size the layout implies.
pub fn probe_raw(path: &Path, l: &RawLayout) -> Result<Probe, String> {
    let meta = std::fs::metadata(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let want = l.expected_size().ok_or_else(|| {
        format!(
            "{}: dims {:?} of {:?} describe more bytes than any file can hold",
            path.display(),
            l.dims,
            l.dtype
        )
    })?;
    if meta.len() != want {
        return Err(format!(
            "{}: is {} bytes, but dims {:?} of {:?}{} need {want} bytes ({})",
            path.display(),
            meta.len(),
            l.dims,
            l.dtype,
            if l.header_bytes > 0 {
                format!(" after a {}-byte header", l.header_bytes)
            } else {
                String::new()
            },
            if meta.len() < want {
                "truncated file or wrong dims/dtype"
            } else {
                "wrong dims/dtype, or a header to skip with `header_bytes`"
            }
        ));
    }
    Ok(Probe {
        dims: l.dims,
        components: 1,
        dtype: format!("{:?}", l.dtype).to_lowercase(),
        elem_bytes: l.dtype.size(),
        spacing: None,
        origin: None,
    })
}

/// Reads a raw volume; spacing and origin [m] come from the caller.
pub fn read_raw(
    path: &Path,
    layout: &RawLayout,
    spacing: [f64; 3],
    origin: [f64; 3],
) -> Result<Volume, String> {
    probe_raw(path, layout)?;
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let b = &bytes[layout.header_bytes as usize..];
    let little = layout.endian == Endian::Little;
    let data = match layout.dtype {
        RawDtype::U8 => VolumeData::U8(b.to_vec()),
        RawDtype::U16 => VolumeData::U16(from_bytes(b, little)),
        RawDtype::I32 => VolumeData::I32(from_bytes(b, little)),
        RawDtype::F32 => VolumeData::F32(from_bytes(b, little)),
        RawDtype::F64 => VolumeData::F64(from_bytes(b, little)),
    };
    Ok(Volume {
        name: path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "raw".into()),
        unit: String::new(),
        dims: layout.dims,
        components: 1,
        convention: grainpipe_core::ComponentConvention::Plain,
        spacing: Some(spacing),
        origin: Some(origin),
        periodic: [false; 3],
        data,
        phases: Vec::new(),
    })
}
