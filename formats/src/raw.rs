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

/// Feeds the values of a raw volume to `scan` block by block (no copy of the volume).
pub fn scan_raw(
    path: &Path,
    layout: &RawLayout,
    scan: &mut crate::volume::LabelScan,
) -> Result<(), String> {
    use std::io::{Read, Seek, SeekFrom};
    probe_raw(path, layout)?;
    let at = |e: std::io::Error| format!("{}: {e}", path.display());
    let mut f = std::fs::File::open(path).map_err(at)?;
    f.seek(SeekFrom::Start(layout.header_bytes)).map_err(at)?;
    let size = layout.dtype.size();
    let little = layout.endian == Endian::Little;
    let mut buf = vec![0u8; crate::import::SCAN_BLOCK_BYTES / size * size];
    loop {
        let mut filled = 0;
        while filled < buf.len() {
            match f.read(&mut buf[filled..]).map_err(at)? {
                0 => break,
                k => filled += k,
            }
        }
        let b = &buf[..filled - filled % size];
        match layout.dtype {
            RawDtype::U8 => scan.feed(b.iter().map(|&x| x as f64)),
            RawDtype::U16 => scan.feed(from_bytes::<u16>(b, little).into_iter().map(f64::from)),
            RawDtype::I32 => scan.feed(from_bytes::<i32>(b, little).into_iter().map(f64::from)),
            RawDtype::F32 => scan.feed(from_bytes::<f32>(b, little).into_iter().map(f64::from)),
            RawDtype::F64 => scan.feed(from_bytes::<f64>(b, little).into_iter()),
        }
        if filled < buf.len() {
            return Ok(());
        }
    }
}

// ---------------------------------------------------------------------------------------
// Writer: raw data plus a MetaImage header

use crate::volume::{to_le_bytes, VolumeRef};
use grainpipe_core::fsutil::{atomic_write, atomic_write_bytes};
use grainpipe_core::FieldData;

/// The `.raw` and `.mhd` paths of an export to `path` (either extension names the pair).
pub fn mhd_pair(path: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    (path.with_extension("raw"), path.with_extension("mhd"))
}

/// Metres per unit of the lengths written in the `.mhd` header.
fn length_unit(v: &serde_json::Value) -> Result<f64, String> {
    match v.as_str() {
        Some("m") => Ok(1.0),
        Some("mm") => Ok(1e-3),
        Some("um") => Ok(1e-6),
        _ => Err(format!(
            "{v} is not a length unit of the header; write `mm` (what ITK and 3D Slicer \
             assume), `um` or `m`"
        )),
    }
}

/// Writes the voxels headerless (x fastest, little-endian; components interleaved) and a
/// MetaImage header beside them. `unit`: metres per header length unit.
///
/// The pair is replaced so that a reader never finds a header beside a payload of another
/// write, whenever the process is killed (a header names its payload file, so the order is):
/// 1. the voxels go to a fresh file `<stem>.grainpipe-<tag>.raw` (atomically);
/// 2. the `.mhd` is replaced by a header naming that fresh file;
/// 3. `<stem>.raw` is replaced by a hard link to the fresh file (a copy where the file
///    system has no hard links);
/// 4. the `.mhd` is replaced by the final header naming `<stem>.raw`;
/// 5. the fresh name, and fresh names a killed export left, are removed.
///
/// Killed before 2, the old pair is intact (the fresh file goes with the next export); after
/// 2, the header names the new payload, under one name or the other.
pub fn write_raw_mhd(
    artifact: &grainpipe_core::Artifact,
    path: &Path,
    prov: &grainpipe_core::Provenance,
    unit: f64,
) -> Result<(), String> {
    let v = VolumeRef::from_artifact(artifact, "raw")?;
    v.validate()?;
    let (raw, mhd) = mhd_pair(path);
    let met = match v {
        VolumeRef::Phase(_) => "MET_UCHAR",
        VolumeRef::Field(f) => match &f.data {
            FieldData::F32(_) => "MET_FLOAT",
            FieldData::F64(_) => "MET_DOUBLE",
        },
    };
    let g = v.grid();
    let l = |a: [f64; 3]| format!("{:e} {:e} {:e}", a[0] / unit, a[1] / unit, a[2] / unit);
    // MetaImage's Offset is the centre of the first voxel, not the grid's lower corner.
    let centre = [0, 1, 2].map(|a| g.origin[a] + 0.5 * g.spacing[a]);
    let mut h = String::new();
    for (k, val) in &prov.entries {
        // Comment lines are not MetaImage; provenance goes into keys ITK ignores.
        let key: String = k
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
            .collect();
        h.push_str(&format!(
            "grainpipe_{key} = {}\n",
            val.replace(['\n', '\r'], " ")
        ));
    }
    let mut head = format!(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n\
         CompressedData = False\nTransformMatrix = 1 0 0 0 1 0 0 0 1\nOffset = {}\n\
         CenterOfRotation = 0 0 0\nAnatomicalOrientation = RAI\nElementSpacing = {}\n\
         DimSize = {} {} {}\n",
        l(centre),
        l(g.spacing),
        g.dims[0],
        g.dims[1],
        g.dims[2]
    );
    if v.components() > 1 {
        head.push_str(&format!("ElementNumberOfChannels = {}\n", v.components()));
    }
    head.push_str(&h);
    let header_naming = |data: &Path| {
        let name = data
            .file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        format!("{head}ElementType = {met}\nElementDataFile = {name}\n")
    };
    let fresh = fresh_payload(&raw);
    // 1. the voxels, streamed in blocks (no copy of the volume in memory)
    atomic_write(&fresh, |tmp| write_voxels(tmp, v))?;
    let result = (|| {
        // 2. a header naming the fresh payload
        atomic_write_bytes(&mhd, header_naming(&fresh).as_bytes())?;
        // 3. the payload under its final name
        atomic_write(&raw, |tmp| {
            std::fs::hard_link(&fresh, tmp)
                .or_else(|_| std::fs::copy(&fresh, tmp).map(|_| ()))
                .map_err(|e| format!("{}: {e}", fresh.display()))
        })?;
        // 4. the final header
        atomic_write_bytes(&mhd, header_naming(&raw).as_bytes())
    })();
    if result.is_ok() {
        // 5. no header names the fresh file any more
        let _ = std::fs::remove_file(&fresh);
        remove_stale_payloads(&raw);
    }
    result
}

/// `<stem>.grainpipe-<tag>.raw` beside `raw`: a name no earlier write used.
fn fresh_payload(raw: &Path) -> std::path::PathBuf {
    let stem = raw
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tag = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    raw.with_file_name(format!(
        "{stem}{FRESH_MARK}{tag:x}{:x}.raw",
        std::process::id()
    ))
}

const FRESH_MARK: &str = ".grainpipe-";

/// Removes the fresh payloads (`<stem>.grainpipe-<hex>.raw`) of earlier writes of `raw`
/// that were killed: once the final header names `<stem>.raw`, none of them is named.
fn remove_stale_payloads(raw: &Path) {
    let stem = raw
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let prefix = format!("{stem}{FRESH_MARK}");
    let dir = raw
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let ours = name
            .strip_prefix(&prefix)
            .and_then(|r| r.strip_suffix(".raw"))
            .is_some_and(|t| !t.is_empty() && t.bytes().all(|b| b.is_ascii_hexdigit()));
        if ours && e.path().is_file() {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// The voxels of `v`, little-endian, written in blocks (polling the interrupt flag).
fn write_voxels(path: &Path, v: VolumeRef) -> Result<(), String> {
    use std::io::Write;
    const BLOCK: usize = 1 << 20;
    let at = |e: std::io::Error| format!("{}: {e}", path.display());
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).map_err(at)?);
    match v {
        VolumeRef::Phase(p) => {
            for c in p.labels.chunks(BLOCK) {
                grainpipe_core::fsutil::check_interrupt()?;
                f.write_all(c).map_err(at)?;
            }
        }
        VolumeRef::Field(fl) => {
            macro_rules! values {
                ($d:expr) => {
                    for c in $d.chunks(BLOCK) {
                        grainpipe_core::fsutil::check_interrupt()?;
                        f.write_all(&to_le_bytes(c)).map_err(at)?;
                    }
                };
            }
            match &fl.data {
                FieldData::F32(d) => values!(d),
                FieldData::F64(d) => values!(d),
            }
        }
    }
    f.flush().map_err(at)
}

/// The `.mhd` and the `.raw` of an export (the target first).
fn raw_written_paths(
    path: &Path,
    _: &grainpipe_core::registry::ExportOptions,
) -> Vec<grainpipe_core::registry::WrittenPath> {
    use grainpipe_core::registry::WrittenPath;
    let (raw, mhd) = mhd_pair(path);
    if path == raw {
        vec![WrittenPath::file(raw), WrittenPath::file(mhd)]
    } else {
        vec![WrittenPath::file(mhd), WrittenPath::file(raw)]
    }
}

crate::vtk_xml::exporter!(
    RawExporter,
    "raw",
    &["mhd", "raw"],
    [PhaseImage, Field],
    "Headerless raw voxels (x fastest, little-endian; u8 labels, f32/f64 values, \
     components interleaved) as <name>.raw plus a MetaImage header <name>.mhd (DimSize, \
     ElementType, ElementSpacing, Offset = first voxel centre, byte order), which ITK, \
     3D Slicer, Avizo, Dragonfly and Fiji open; `to:` may name either file. import.raw \
     reads the .raw back.",
    options: vec![grainpipe_core::registry::ExportOption {
        name: "length_unit",
        doc: "unit of ElementSpacing and Offset in the .mhd: `mm` (ITK/3D Slicer \
              convention), `um` or `m`",
        default: serde_json::json!("mm"),
    }],
    check: check_raw_options,
    write: write_raw_options,
    paths: raw_written_paths
);

/// Metres per `length_unit` (millimetres when the option is absent).
fn unit_of(options: &grainpipe_core::registry::ExportOptions) -> Result<f64, String> {
    Ok(options
        .get("length_unit")
        .map(length_unit)
        .transpose()?
        .unwrap_or(1e-3))
}

fn check_raw_options(
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<(), (String, String)> {
    unit_of(options)
        .map(|_| ())
        .map_err(|m| ("length_unit".to_string(), m))
}

fn write_raw_options(
    artifact: &grainpipe_core::Artifact,
    path: &Path,
    provenance: &grainpipe_core::Provenance,
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<(), String> {
    write_raw_mhd(artifact, path, provenance, unit_of(options)?)
}
