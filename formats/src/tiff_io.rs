//! TIFF stacks, as CT reconstruction software writes them: a multi-page TIFF (page k is
//! slice z = k) or a directory of single-page TIFFs taken in file-name order. Grayscale
//! only; row r of a page is voxel row y = r (no flip). TIFF resolution tags are unreliable
//! for CT data, so the voxel size comes from the pipeline.

use crate::volume::{Probe, Volume, VolumeData};
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use tiff::decoder::{Decoder, DecodingResult};
use tiff::ColorType;

/// The files of a stack: the file itself, or the `.tif`/`.tiff` files of a directory sorted
/// by name.
pub fn stack_files(path: &Path) -> Result<Vec<PathBuf>, String> {
    if !path.is_dir() {
        return Ok(vec![path.to_path_buf()]);
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(path)
        .map_err(|e| format!("{}: {e}", path.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|x| x.to_str())
                .is_some_and(|x| x.eq_ignore_ascii_case("tif") || x.eq_ignore_ascii_case("tiff"))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(format!(
            "{}: no .tif or .tiff files in this directory",
            path.display()
        ));
    }
    Ok(files)
}

fn open(file: &Path) -> Result<Decoder<BufReader<File>>, String> {
    let f = File::open(file).map_err(|e| format!("{}: {e}", file.display()))?;
    Decoder::new(BufReader::new(f))
        .map_err(|e| format!("{}: not a readable TIFF: {e}", file.display()))
}

/// (dtype name, bytes per element) of a grayscale page.
fn gray(file: &Path, c: ColorType) -> Result<(&'static str, usize), String> {
    match c {
        ColorType::Gray(8) => Ok(("u8", 1)),
        ColorType::Gray(16) => Ok(("u16", 2)),
        ColorType::Gray(32) => Ok(("32-bit", 4)),
        ColorType::Gray(64) => Ok(("64-bit", 8)),
        other => Err(format!(
            "{}: {other:?} pages are not supported; a label or grey-value stack must be single-channel",
            file.display()
        )),
    }
}

/// Visits every page of every file, checking that all pages share size and type.
fn for_each_page(
    path: &Path,
    mut visit: impl FnMut(&Path, &mut Decoder<BufReader<File>>) -> Result<(), String>,
) -> Result<Probe, String> {
    let mut probe: Option<Probe> = None;
    let mut pages = 0usize;
    for file in stack_files(path)? {
        let mut d = open(&file)?;
        loop {
            let (w, h) = d
                .dimensions()
                .map_err(|e| format!("{}: {e}", file.display()))?;
            let ct = d
                .colortype()
                .map_err(|e| format!("{}: {e}", file.display()))?;
            let (dtype, bytes) = gray(&file, ct)?;
            match &probe {
                None => {
                    probe = Some(Probe {
                        dims: [w as usize, h as usize, 0],
                        components: 1,
                        dtype: dtype.to_string(),
                        elem_bytes: bytes,
                        spacing: None,
                        origin: None,
                    })
                }
                Some(p)
                    if p.dims[0] != w as usize || p.dims[1] != h as usize || p.dtype != dtype =>
                {
                    return Err(format!(
                        "{} page {}: {w} x {h} {dtype} differs from the first page ({} x {} {})",
                        file.display(),
                        pages,
                        p.dims[0],
                        p.dims[1],
                        p.dtype
                    ))
                }
                Some(_) => {}
            }
            visit(&file, &mut d)?;
            pages += 1;
            if !d.more_images() {
                break;
            }
            d.next_image()
                .map_err(|e| format!("{}: {e}", file.display()))?;
        }
    }
    let mut p = probe.ok_or_else(|| format!("{}: no pages", path.display()))?;
    p.dims[2] = pages;
    Ok(p)
}

/// Size and type of a stack without decoding pixel data.
pub fn probe_tiff(path: &Path) -> Result<Probe, String> {
    for_each_page(path, |_, _| Ok(()))
}

/// Reads a whole stack (x fastest, then y, then z).
pub fn read_tiff(path: &Path) -> Result<Volume, String> {
    let mut slices: Vec<DecodingResult> = Vec::new();
    let probe = for_each_page(path, |file, d| {
        slices.push(
            d.read_image()
                .map_err(|e| format!("{}: {e}", file.display()))?,
        );
        Ok(())
    })?;
    macro_rules! concat {
        ($variant:ident, $conv:expr) => {{
            // no capacity from the header's dims: they are checked against the data below
            let mut out = Vec::new();
            for s in slices {
                match s {
                    DecodingResult::$variant(v) => out.extend(v.into_iter().map($conv)),
                    _ => return Err(format!("{}: pages of mixed sample formats", path.display())),
                }
            }
            out
        }};
    }
    let data = match slices.first() {
        Some(DecodingResult::U8(_)) => VolumeData::U8(concat!(U8, |x| x)),
        Some(DecodingResult::U16(_)) => VolumeData::U16(concat!(U16, |x| x)),
        Some(DecodingResult::I8(_)) => VolumeData::I32(concat!(I8, i32::from)),
        Some(DecodingResult::I16(_)) => VolumeData::I32(concat!(I16, i32::from)),
        Some(DecodingResult::I32(_)) => VolumeData::I32(concat!(I32, |x| x)),
        Some(DecodingResult::U32(_)) => VolumeData::F64(concat!(U32, f64::from)),
        Some(DecodingResult::F32(_)) => VolumeData::F32(concat!(F32, |x| x)),
        Some(DecodingResult::F64(_)) => VolumeData::F64(concat!(F64, |x| x)),
        _ => {
            return Err(format!(
                "{}: unsupported TIFF sample format",
                path.display()
            ))
        }
    };
    if Some(data.len()) != grainpipe_core::checked_product(&probe.dims) {
        return Err(format!(
            "{}: decoded {} samples, expected {:?}",
            path.display(),
            data.len(),
            probe.dims
        ));
    }
    Ok(Volume {
        name: path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default(),
        unit: String::new(),
        dims: probe.dims,
        components: 1,
        convention: grainpipe_core::ComponentConvention::Plain,
        spacing: None,
        origin: None,
        periodic: [false; 3],
        data,
        phases: Vec::new(),
    })
}
