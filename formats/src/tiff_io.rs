//! TIFF stacks, as CT reconstruction software writes them: a multi-page TIFF (page k is
//! slice z = k) or a directory of single-page TIFFs taken in file-name order. Grayscale
//! only; row r of a page is voxel row y = r (no flip).
//!
//! The voxel size is read from the first page when it is stated in a way that cannot be a
//! program's default: grainpipe's own description keys, an ImageJ calibration (`unit=` in
//! the description), or resolution tags in centimetres. Inch resolutions (72 dpi is what
//! most programs write without knowing anything) are ignored. The pipeline's `spacing`
//! overrides all of them.

use crate::volume::{Probe, Volume, VolumeData, VolumeRef};
use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::FieldData;
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use tiff::decoder::{Decoder, DecodingResult};
use tiff::encoder::{Rational, TiffEncoder};
use tiff::tags::ResolutionUnit;
use tiff::ColorType;

/// The files of a stack: the file itself, or the `.tif`/`.tiff` files of a directory in
/// natural name order (runs of digits compared as numbers: `s2` before `s10`, as CT software
/// numbers slices without padding).
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
    files.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));
    if files.is_empty() {
        return Err(format!(
            "{}: no .tif or .tiff files in this directory",
            path.display()
        ));
    }
    Ok(files)
}

/// Compares names with runs of ASCII digits taken as numbers (`s2` < `s10`); equal numbers
/// with different zero padding, and everything else, compare as text.
pub fn natural_cmp(a: &str, b: &str) -> std::cmp::Ordering {
    use std::cmp::Ordering;
    let (mut x, mut y) = (a.as_bytes(), b.as_bytes());
    while let (Some(&c), Some(&d)) = (x.first(), y.first()) {
        if c.is_ascii_digit() && d.is_ascii_digit() {
            let run = |s: &[u8]| s.iter().take_while(|b| b.is_ascii_digit()).count();
            let (n, m) = (run(x), run(y));
            let trim = |s: &[u8]| {
                let z = s.iter().take_while(|&&b| b == b'0').count();
                s[z..].to_vec()
            };
            let (p, q) = (trim(&x[..n]), trim(&y[..m]));
            let o = p.len().cmp(&q.len()).then_with(|| p.cmp(&q));
            if o != Ordering::Equal {
                return o;
            }
            x = &x[n..];
            y = &y[m..];
        } else {
            if c != d {
                return c.cmp(&d);
            }
            x = &x[1..];
            y = &y[1..];
        }
    }
    x.len().cmp(&y.len()).then_with(|| a.cmp(b))
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
) -> Result<(Probe, Calibration), String> {
    let mut probe: Option<Probe> = None;
    let mut cal = Calibration::default();
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
                    cal = calibration(&mut d);
                    probe = Some(Probe {
                        dims: [w as usize, h as usize, 0],
                        components: 1,
                        dtype: dtype.to_string(),
                        elem_bytes: bytes,
                        spacing: cal.spacing,
                        origin: cal.origin,
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
    Ok((p, cal))
}

/// Size, type, calibration and periodic axes of a stack without decoding pixel data.
pub fn tiff_header(path: &Path) -> Result<crate::headers::Header, String> {
    for_each_page(path, |_, _| Ok(())).map(|(probe, cal)| crate::headers::Header {
        probe,
        periodic: cal.periodic,
    })
}

/// Reads a whole stack (x fastest, then y, then z). The size the page headers declare is
/// checked against the memory available before any page is decoded.
pub fn read_tiff(path: &Path) -> Result<Volume, String> {
    let head = tiff_header(path)?.probe;
    let bytes = grainpipe_core::checked_product(&head.dims)
        .and_then(|n| n.checked_mul(head.elem_bytes + 8))
        .map(|b| b as u64);
    crate::volume::check_declared(&format!("{}: the stack", path.display()), bytes)?;
    let mut slices: Vec<DecodingResult> = Vec::new();
    let (probe, cal) = for_each_page(path, |file, d| {
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
        unit: cal.unit,
        dims: probe.dims,
        components: 1,
        convention: grainpipe_core::ComponentConvention::Plain,
        spacing: cal.spacing,
        origin: cal.origin,
        periodic: cal.periodic,
        data,
        phases: cal.phases,
    })
}

// ---------------------------------------------------------------------------------------
// Calibration: the description keys and resolution tags that carry the voxel size.

/// What a page's tags say about the geometry: the exact SI values grainpipe writes, else
/// ImageJ's calibration (`unit=` with `spacing=` and the resolution tags), else resolution
/// tags in centimetres. Inch resolutions are ignored: 72 dpi is the default of programs that
/// know nothing of the voxel size.
#[derive(Clone, Debug, Default, PartialEq)]
struct Calibration {
    spacing: Option<[f64; 3]>,
    origin: Option<[f64; 3]>,
    phases: Vec<grainpipe_core::Phase>,
    unit: String,
    /// Periodic axes, from grainpipe's own key (other programs do not state them).
    periodic: [bool; 3],
}

/// Metres per ImageJ length unit, `None` for units that are not lengths ("pixel").
fn imagej_unit(u: &str) -> Option<f64> {
    match u.trim() {
        "m" | "meter" | "metre" => Some(1.0),
        "cm" => Some(1e-2),
        "mm" => Some(1e-3),
        "micron" | "microns" | "um" | "\u{b5}m" | "\u{3bc}m" => Some(1e-6),
        "nm" => Some(1e-9),
        _ => None,
    }
}

fn three(s: &str) -> Option<[f64; 3]> {
    let v: Vec<f64> = s
        .split_whitespace()
        .map(|x| x.parse().ok())
        .collect::<Option<_>>()?;
    <[f64; 3]>::try_from(v).ok()
}

fn rational(v: Option<tiff::decoder::ifd::Value>) -> Option<f64> {
    match v? {
        tiff::decoder::ifd::Value::Rational(n, d) if d != 0 => Some(n as f64 / d as f64),
        other => other.into_f64().ok(),
    }
}

fn calibration<R: std::io::Read + std::io::Seek>(d: &mut Decoder<R>) -> Calibration {
    use tiff::tags::Tag;
    let mut c = Calibration::default();
    let desc = d
        .find_tag(Tag::ImageDescription)
        .ok()
        .flatten()
        .and_then(|v| v.into_string().ok())
        .unwrap_or_default();
    // grainpipe writes its description ASCII-escaped (see `ascii_escape`).
    let desc = if desc.contains("grainpipe_spacing_m=") {
        ascii_unescape(&desc)
    } else {
        desc
    };
    let key = |k: &str| {
        desc.lines()
            .find_map(|l| l.strip_prefix(k).and_then(|r| r.strip_prefix('=')))
            .map(str::trim)
    };
    let xres = rational(d.find_tag(Tag::XResolution).ok().flatten());
    let yres = rational(d.find_tag(Tag::YResolution).ok().flatten()).or(xres);
    if let Some(s) = key("grainpipe_spacing_m").and_then(three) {
        c.spacing = Some(s);
    } else if let (Some(m), Some(xr), Some(yr)) = (key("unit").and_then(imagej_unit), xres, yres) {
        // ImageJ: resolutions in pixels per `unit`; the z step in `spacing=`, else the x size.
        let dx = m / xr;
        let dz = key("spacing")
            .and_then(|s| s.parse::<f64>().ok())
            .map_or(dx, |s| s * m);
        c.spacing = Some([dx, m / yr, dz]);
    } else if d
        .find_tag_unsigned::<u16>(Tag::ResolutionUnit)
        .ok()
        .flatten()
        == Some(3)
    {
        if let (Some(xr), Some(yr)) = (xres, yres) {
            let (dx, dy) = (1e-2 / xr, 1e-2 / yr);
            c.spacing = Some([dx, dy, dx]);
        }
    }
    c.origin = key("grainpipe_origin_m").and_then(three);
    c.phases = key("grainpipe_phases")
        .and_then(|s| serde_json::from_str::<Vec<(u8, String)>>(s).ok())
        .map(|v| {
            v.into_iter()
                .map(|(id, name)| grainpipe_core::Phase { id, name })
                .collect()
        })
        .unwrap_or_default();
    c.unit = key("grainpipe_unit").unwrap_or_default().to_string();
    c.periodic = key("grainpipe_periodic")
        .and_then(|s| {
            let v: Vec<bool> = s
                .split_whitespace()
                .map(|x| x.parse().ok())
                .collect::<Option<_>>()?;
            <[bool; 3]>::try_from(v).ok()
        })
        .unwrap_or_default();
    c
}

// ---------------------------------------------------------------------------------------
// Writer

/// How a TIFF export lays out its slices.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StackLayout {
    /// One multi-page file, page k = slice z = k.
    File,
    /// A directory of single-page files `<name>_0000.tif`, ...
    Directory,
}

impl StackLayout {
    fn parse(v: &serde_json::Value) -> Result<Self, String> {
        match v.as_str() {
            Some("file") => Ok(StackLayout::File),
            Some("directory") => Ok(StackLayout::Directory),
            _ => Err(format!(
                "{v} is not a stack layout; write `file` (one multi-page TIFF) or `directory` \
                 (one TIFF per z slice)"
            )),
        }
    }
}

/// The pixels of one volume as TIFF pages take them.
enum Pages<'a> {
    Gray8(&'a [u8]),
    Float(Vec<f32>),
}

/// ImageJ hyperstack description (read by Fiji, tifffile, Dragonfly and Avizo's ImageJ
/// reader) followed by grainpipe's own keys, which hold the geometry exactly in metres.
fn description(v: VolumeRef, pages: usize, prov: &grainpipe_core::Provenance) -> String {
    let g = v.grid();
    let um = |x: f64| x * 1e6;
    let mut s = format!(
        "ImageJ=1.11a\nimages={pages}\nslices={pages}\nunit=micron\nspacing={:e}\nloop=false\n",
        um(g.spacing[2])
    );
    let f3 = |a: [f64; 3]| format!("{:e} {:e} {:e}", a[0], a[1], a[2]);
    s.push_str(&format!("grainpipe_spacing_m={}\n", f3(g.spacing)));
    s.push_str(&format!("grainpipe_origin_m={}\n", f3(g.origin)));
    let [px, py, pz] = g.periodic;
    s.push_str(&format!("grainpipe_periodic={px} {py} {pz}\n"));
    match v {
        VolumeRef::Phase(p) => {
            let phases: Vec<(u8, &str)> = p
                .phases
                .iter()
                .map(|ph| (ph.id, ph.name.as_str()))
                .collect();
            s.push_str(&format!(
                "grainpipe_phases={}\n",
                serde_json::to_string(&phases).expect("plain data")
            ));
        }
        VolumeRef::Field(f) => {
            s.push_str(&format!("grainpipe_name={}\n", one_line(&f.name)));
            s.push_str(&format!("grainpipe_unit={}\n", one_line(&f.unit)));
        }
    }
    for (k, val) in &prov.entries {
        s.push_str(&format!("grainpipe_{}={}\n", one_line(k), one_line(val)));
    }
    ascii_escape(&s)
}

fn one_line(s: &str) -> String {
    s.replace(['\n', '\r', '='], " ")
}

/// TIFF ASCII tags hold 7-bit text (the encoder refuses anything else, and a pipeline's YAML
/// in the provenance may hold "µm"): every character outside printable ASCII and newline
/// becomes `\u{hex}`, a backslash `\\`. [`ascii_unescape`] reverses it.
pub fn ascii_escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '\\' => out.push_str("\\\\"),
            '\n' | ' '..='~' => out.push(c),
            c => out.push_str(&format!("\\u{{{:x}}}", c as u32)),
        }
    }
    out
}

/// The text [`ascii_escape`] was given.
pub fn ascii_unescape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    let mut rest = s;
    while let Some(i) = rest.find('\\') {
        out.push_str(&rest[..i]);
        let tail = &rest[i + 1..];
        if let Some(t) = tail.strip_prefix('\\') {
            out.push('\\');
            rest = t;
            continue;
        }
        let decoded = tail
            .strip_prefix("u{")
            .and_then(|t| t.split_once('}'))
            .and_then(|(hex, after)| {
                let c = u32::from_str_radix(hex, 16).ok().and_then(char::from_u32)?;
                Some((c, after))
            });
        match decoded {
            Some((c, after)) => {
                out.push(c);
                rest = after;
            }
            None => {
                out.push('\\');
                rest = tail;
            }
        }
    }
    out.push_str(rest);
    out
}

/// Pixels per micrometre as a TIFF rational n/d, with the largest power-of-ten d that keeps
/// n within 32 bits (the description holds the exact value).
fn per_micron(spacing: f64) -> Rational {
    let v = 1e-6 / spacing;
    for k in (0..=9).rev() {
        let d = 10u64.pow(k);
        let n = (v * d as f64).round();
        if n >= 1.0 && n <= u32::MAX as f64 {
            return Rational {
                n: n as u32,
                d: d as u32,
            };
        }
    }
    Rational { n: 1, d: 1 }
}

/// Writes the pixels of every page first, back to back, then one directory per page
/// pointing into them. Readers of ImageJ stacks (Fiji, tifffile) read the pages as one
/// contiguous block after the first page's offset, so interleaving data and directories
/// (what the encoder's per-image API does) would be misread by them.
fn write_pages<W: std::io::Write + std::io::Seek, K: tiff::encoder::TiffKind>(
    enc: &mut TiffEncoder<W, K>,
    v: VolumeRef,
    pages: &Pages,
    zs: std::ops::Range<usize>,
    desc: &str,
) -> Result<(), String> {
    use tiff::tags::{CompressionMethod, PhotometricInterpretation, SampleFormat, Tag};
    let g = v.grid();
    let (w, h) = (g.dims[0] as u32, g.dims[1] as u32);
    let n = g.dims[0] * g.dims[1];
    let e = |e: tiff::TiffError| e.to_string();
    let (bits, format, page_bytes) = match pages {
        Pages::Gray8(_) => (8u16, SampleFormat::Uint, n as u64),
        Pages::Float(_) => (32u16, SampleFormat::IEEEFP, 4 * n as u64),
    };
    let zs: Vec<usize> = zs.collect();
    let tags = |dir: &mut tiff::encoder::DirectoryEncoder<'_, W, K>,
                first: bool,
                off: u64|
     -> tiff::TiffResult<()> {
        dir.write_tag(Tag::NewSubfileType, 0u32)?;
        dir.write_tag(Tag::ImageWidth, w)?;
        dir.write_tag(Tag::ImageLength, h)?;
        dir.write_tag(Tag::BitsPerSample, bits)?;
        dir.write_tag(Tag::Compression, CompressionMethod::None)?;
        dir.write_tag(
            Tag::PhotometricInterpretation,
            PhotometricInterpretation::BlackIsZero,
        )?;
        // ImageJ reads the description of the first page only.
        if first {
            dir.write_tag(Tag::ImageDescription, desc)?;
        }
        dir.write_tag(Tag::StripOffsets, K::convert_offset(off)?)?;
        dir.write_tag(Tag::SamplesPerPixel, 1u16)?;
        dir.write_tag(Tag::RowsPerStrip, h)?;
        dir.write_tag(Tag::StripByteCounts, K::convert_offset(page_bytes)?)?;
        dir.write_tag(Tag::XResolution, per_micron(g.spacing[0]))?;
        dir.write_tag(Tag::YResolution, per_micron(g.spacing[1]))?;
        dir.write_tag(Tag::ResolutionUnit, ResolutionUnit::None)?;
        dir.write_tag(Tag::SampleFormat, &[format][..])
    };
    let mut offsets = Vec::with_capacity(zs.len());
    let mut dir = enc.image_directory().map_err(e)?;
    for &z in &zs {
        let off = match pages {
            Pages::Gray8(d) => dir.write_data(&d[z * n..(z + 1) * n]),
            Pages::Float(d) => dir.write_data(&d[z * n..(z + 1) * n]),
        }
        .map_err(e)?;
        offsets.push(off);
    }
    if let Some(&off) = offsets.first() {
        tags(&mut dir, true, off).map_err(e)?;
    }
    dir.finish().map_err(e)?;
    for &off in offsets.iter().skip(1) {
        let mut dir = enc.image_directory().map_err(e)?;
        tags(&mut dir, false, off).map_err(e)?;
        dir.finish().map_err(e)?;
    }
    Ok(())
}

/// Writes pages `zs` of `v` to `path` (BigTIFF past what 32-bit offsets address).
fn write_file(
    path: &Path,
    v: VolumeRef,
    pages: &Pages,
    zs: std::ops::Range<usize>,
    desc: &str,
) -> Result<(), String> {
    let g = v.grid();
    let bytes = (g.dims[0] * g.dims[1] * zs.len()) as u64
        * match pages {
            Pages::Gray8(_) => 1,
            Pages::Float(_) => 4,
        };
    let mut f = std::io::BufWriter::new(
        File::create(path).map_err(|e| format!("{}: {e}", path.display()))?,
    );
    // Margin under 4 GiB for the directories and the description.
    if bytes < (1 << 32) - (1 << 24) {
        let mut enc = TiffEncoder::new(&mut f).map_err(|e| e.to_string())?;
        write_pages(&mut enc, v, pages, zs, desc)?;
    } else {
        let mut enc = TiffEncoder::new_big(&mut f).map_err(|e| e.to_string())?;
        write_pages(&mut enc, v, pages, zs, desc)?;
    }
    std::io::Write::flush(&mut f).map_err(|e| format!("{}: {e}", path.display()))
}

/// The directory a `stack: directory` export writes and the name its slices start with:
/// `out/ct.tif` gives `out/ct/ct_0000.tif`, `out/ct_0001.tif`, ...
pub fn slice_directory(path: &Path) -> (PathBuf, String) {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "slice".into());
    let is_tif = path
        .extension()
        .and_then(|x| x.to_str())
        .is_some_and(|x| x.eq_ignore_ascii_case("tif") || x.eq_ignore_ascii_case("tiff"));
    let dir = if is_tif {
        path.with_extension("")
    } else {
        path.to_path_buf()
    };
    (dir, stem)
}

/// Whether `name` is a slice file `<stem>_<digits>.tif` of a directory stack.
fn is_slice_name(name: &str, stem: &str) -> bool {
    name.strip_prefix(stem)
        .and_then(|r| r.strip_prefix('_'))
        .and_then(|r| r.strip_suffix(".tif"))
        .is_some_and(|d| !d.is_empty() && d.bytes().all(|b| b.is_ascii_digit()))
}

/// Writes a directory of slices into a fresh temporary directory beside the target, then
/// swaps it in, so readers see the old stack or the new one, never a mix. An existing target
/// holding anything but slices of this name is left alone and the export fails.
fn write_directory(path: &Path, v: VolumeRef, pages: &Pages, desc: &str) -> Result<(), String> {
    let (dir, stem) = slice_directory(path);
    if let Ok(meta) = std::fs::symlink_metadata(&dir) {
        if !meta.is_dir() {
            return Err(format!(
                "{} exists and is not a directory; remove it or export to another name",
                dir.display()
            ));
        }
        for e in std::fs::read_dir(&dir).map_err(|e| format!("{}: {e}", dir.display()))? {
            let name = e
                .map_err(|e| format!("{}: {e}", dir.display()))?
                .file_name()
                .to_string_lossy()
                .into_owned();
            if !is_slice_name(&name, &stem) {
                return Err(format!(
                    "{} holds `{name}`, which is not a slice of this stack; refusing to \
                     replace the directory (move that file, or export to another name)",
                    dir.display()
                ));
            }
        }
    }
    if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .map_err(|e| format!("cannot create directory {}: {e}", parent.display()))?;
    }
    // Temporary directories a killed export left (slices of a whole stack) go first.
    grainpipe_core::fsutil::clean_stale_temps_of(&dir);
    let tmp = grainpipe_core::fsutil::temp_path_for(&dir);
    std::fs::create_dir(&tmp).map_err(|e| format!("{}: {e}", tmp.display()))?;
    grainpipe_core::fsutil::temp_started(&tmp);
    let result = fill_and_swap(&dir, &tmp, &stem, v, pages, desc);
    grainpipe_core::fsutil::temp_done(&tmp);
    result
}

/// The slices into `tmp`, then `tmp` swapped in for `dir` (see [`write_directory`]).
fn fill_and_swap(
    dir: &Path,
    tmp: &Path,
    stem: &str,
    v: VolumeRef,
    pages: &Pages,
    desc: &str,
) -> Result<(), String> {
    let nz = v.grid().dims[2];
    let width = nz.saturating_sub(1).to_string().len().max(4);
    let written = (0..nz).try_for_each(|z| {
        grainpipe_core::fsutil::check_interrupt()?;
        let f = tmp.join(format!("{stem}_{z:0width$}.tif"));
        write_file(&f, v, pages, z..z + 1, desc)?;
        File::open(&f)
            .and_then(|f| f.sync_all())
            .map_err(|e| format!("{}: {e}", f.display()))
    });
    let swapped = written.and_then(|()| {
        let old = grainpipe_core::fsutil::temp_path_for(dir);
        let had_old = dir.exists();
        if had_old {
            std::fs::rename(dir, &old)
                .map_err(|e| format!("cannot move {} aside: {e}", dir.display()))?;
        }
        std::fs::rename(tmp, dir).map_err(|e| {
            if had_old {
                let _ = std::fs::rename(&old, dir);
            }
            format!("cannot move {} to {}: {e}", tmp.display(), dir.display())
        })?;
        if had_old {
            let _ = std::fs::remove_dir_all(&old);
        }
        Ok(())
    });
    if swapped.is_err() {
        let _ = std::fs::remove_dir_all(tmp);
    }
    swapped.map_err(|e| format!("writing {}: {e}", dir.display()))
}

/// Writes a phase image (8-bit labels) or a one-component field (32-bit float) as a TIFF
/// stack, one page per z slice.
pub fn write_tiff(
    artifact: &grainpipe_core::Artifact,
    path: &Path,
    prov: &grainpipe_core::Provenance,
    layout: StackLayout,
) -> Result<(), String> {
    let v = VolumeRef::from_artifact(artifact, "tiff")?;
    v.validate()?;
    let g = v.grid();
    if g.dims[0] > u32::MAX as usize || g.dims[1] > u32::MAX as usize {
        return Err(format!("{:?}: a TIFF page is at most 2^32-1 wide", g.dims));
    }
    let pages = match v {
        VolumeRef::Phase(p) => Pages::Gray8(&p.labels),
        VolumeRef::Field(f) if f.components != 1 => {
            return Err(format!(
                "field `{}` has {} components; TIFF pages hold one value per pixel \
                 (export it as .vti, .h5 or .nc)",
                f.name, f.components
            ))
        }
        VolumeRef::Field(f) => Pages::Float(match &f.data {
            FieldData::F32(d) => d.clone(),
            FieldData::F64(d) => d.iter().map(|&x| x as f32).collect(),
        }),
    };
    match layout {
        StackLayout::File => {
            let desc = description(v, g.dims[2], prov);
            atomic_write(path, |tmp| write_file(tmp, v, &pages, 0..g.dims[2], &desc))
        }
        StackLayout::Directory => write_directory(path, v, &pages, &description(v, 1, prov)),
    }
}

crate::vtk_xml::exporter!(
    TiffExporter,
    "tiff",
    &["tif", "tiff"],
    [PhaseImage, Field],
    "TIFF stack, one page per z slice (row r of a page = y = r): a phase image as 8-bit \
     labels, a one-component field as 32-bit float. The voxel size is in the resolution \
     tags and an ImageJ description (unit=micron, spacing = z step), which Fiji, \
     Dragonfly, Avizo and tifffile read; exact spacing, origin, phase names and field \
     unit in grainpipe_* description keys, which import.tiff reads back.",
    options: vec![grainpipe_core::registry::ExportOption {
        name: "stack",
        doc: "`file`: one multi-page TIFF; `directory`: one single-page TIFF per z slice, \
              `out/ct.tif` giving out/ct/ct_0000.tif, ct_0001.tif, ... (replaced as a \
              whole)",
        default: serde_json::json!("file"),
    }],
    check: check_tiff_options,
    write: write_tiff_options,
    paths: tiff_written_paths
);

/// A `stack: file` export writes its file; a `stack: directory` export replaces the
/// directory named like the file (`out/ct.tif` -> `out/ct/`) as a whole.
fn tiff_written_paths(
    path: &Path,
    options: &grainpipe_core::registry::ExportOptions,
) -> Vec<grainpipe_core::registry::WrittenPath> {
    use grainpipe_core::registry::WrittenPath;
    match stack_layout(options) {
        Ok(StackLayout::Directory) => vec![WrittenPath::directory(slice_directory(path).0)],
        _ => vec![WrittenPath::file(path)],
    }
}

fn stack_layout(options: &grainpipe_core::registry::ExportOptions) -> Result<StackLayout, String> {
    Ok(options
        .get("stack")
        .map(StackLayout::parse)
        .transpose()?
        .unwrap_or(StackLayout::File))
}

fn check_tiff_options(
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<(), (String, String)> {
    stack_layout(options)
        .map(|_| ())
        .map_err(|m| ("stack".to_string(), m))
}

fn write_tiff_options(
    artifact: &grainpipe_core::Artifact,
    path: &Path,
    provenance: &grainpipe_core::Provenance,
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<(), String> {
    write_tiff(artifact, path, provenance, stack_layout(options)?)
}
