//! Header-only readers for the import stages: the shape, element type and grid (dims,
//! spacing, origin, periodic axes) a volume file states, read without its voxel values, so
//! that an import's preflight can announce the exact grid of its output.
//!
//! Each reader derives the grid exactly as the matching full reader does (same attributes,
//! same fallbacks, same arithmetic), so the announced grid equals the imported one bit for
//! bit; the tests below hold every reader to its full counterpart on the file variants the
//! full readers accept.

use crate::volume::{from_bytes, Le, Probe, Volume};
use crate::vtk_xml::{Node, VtkFile};
use base64::Engine;
use grainpipe_core::units::{parse_unit, Dimension};
use netcdf::AttributeValue;
use std::io::{BufReader, Read};
use std::path::Path;

/// What a volume file says about its array before the array is read: the probe of its
/// shape, element type and stated spacing/origin, and its periodic axes.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    pub probe: Probe,
    pub periodic: [bool; 3],
}

impl From<Probe> for Header {
    fn from(probe: Probe) -> Self {
        Header {
            probe,
            periodic: [false; 3],
        }
    }
}

/// Dims, components, spacing, origin and periodic axes: what a header and a full read of the
/// same file must agree on.
pub type Geometry = (
    [usize; 3],
    usize,
    Option<[f64; 3]>,
    Option<[f64; 3]>,
    [bool; 3],
);

impl Header {
    pub fn geometry(&self) -> Geometry {
        let p = &self.probe;
        (p.dims, p.components, p.spacing, p.origin, self.periodic)
    }
}

/// The same quantities of a volume read in full.
pub fn volume_geometry(v: &Volume) -> Geometry {
    (v.dims, v.components, v.spacing, v.origin, v.periodic)
}

// ---------------------------------------------------------------------------------------
// HDF5

/// Header of an HDF5 dataset as [`crate::read_hdf5_dataset`] interprets it: `spacing`, else
/// ImageJ's `element_size_um` (z, y, x in micrometres), `origin`, `periodic`.
pub fn hdf5_header(path: &Path, dataset: &str) -> Result<Header, String> {
    let probe = crate::hdf5_plain::probe_hdf5_dataset(path, dataset)?;
    let f = hdf5_metno::File::open(path)
        .map_err(|e| format!("{}: cannot open as HDF5: {e}", path.display()))?;
    let ds = f
        .dataset(dataset)
        .map_err(|e| format!("{}: no dataset `{dataset}` ({e})", path.display()))?;
    let three =
        |k: &str| crate::h5util::read_attr_f64s(&ds, k).and_then(|v| <[f64; 3]>::try_from(v).ok());
    let spacing = probe
        .spacing
        .or_else(|| three("element_size_um").map(|[z, y, x]| [x * 1e-6, y * 1e-6, z * 1e-6]));
    let periodic = three("periodic")
        .map(|p| p.map(|x| x != 0.0))
        .unwrap_or_default();
    Ok(Header {
        probe: Probe { spacing, ..probe },
        periodic,
    })
}

// ---------------------------------------------------------------------------------------
// NetCDF

/// Header of a NetCDF variable as [`crate::read_netcdf_variable`] interprets it: global
/// `spacing`/`origin`, else uniform CF coordinate variables (values only, converted through
/// their `units`), and global `periodic`.
pub fn netcdf_header(path: &Path, var: &str) -> Result<Header, String> {
    let probe = crate::netcdf_io::probe_netcdf_variable(path, var)?;
    let at = |e: String| format!("{}: {e}", path.display());
    let f = netcdf::open(path).map_err(|e| at(format!("cannot open as NetCDF: {e}")))?;
    let v = f
        .variable(var)
        .ok_or_else(|| at(format!("no variable `{var}`")))?;
    let dnames: Vec<String> = v.dimensions().iter().map(|d| d.name()).collect();
    let ndims = v.dimensions().len();
    let mut h = Header::from(probe);
    if h.probe.spacing.is_none() {
        // CF coordinates: dimension order is (z, y, x) or (y, x); axis a of [x, y, z].
        let axis_names: Vec<&String> = dnames
            .iter()
            .take(if ndims == 2 { 2 } else { 3 })
            .rev()
            .collect();
        let mut s = [1.0; 3];
        let mut o = [0.0; 3];
        let mut ok = axis_names.len() >= 2;
        for (a, dn) in axis_names.iter().enumerate() {
            match nc_coordinate(&f, dn) {
                Some(Ok((sa, oa))) => {
                    s[a] = sa;
                    o[a] = oa;
                }
                Some(Err(e)) => return Err(at(e)),
                None => ok = false,
            }
        }
        if ok {
            if ndims == 2 {
                s[2] = s[0];
            }
            h.probe.spacing = Some(s);
            h.probe.origin = Some(o);
        }
    }
    h.periodic = nc_f64s(f.attribute("periodic").map(|a| a.value()))
        .and_then(|v| <[f64; 3]>::try_from(v).ok())
        .map(|p| p.map(|x| x != 0.0))
        .unwrap_or_default();
    Ok(h)
}

/// Numbers of a NetCDF attribute (as the NetCDF reader takes them).
fn nc_f64s(v: Option<netcdf::Result<AttributeValue>>) -> Option<Vec<f64>> {
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

/// (spacing, lower corner) in metres of a uniformly spaced CF coordinate variable, as the
/// NetCDF reader computes them.
fn nc_coordinate(f: &netcdf::File, name: &str) -> Option<Result<(f64, f64), String>> {
    let c = f.variable(name)?;
    let vals: Vec<f64> = c.get_values(..).ok()?;
    if vals.len() < 2 {
        return None;
    }
    let units = match c.attribute_value("units").and_then(|r| r.ok()) {
        Some(AttributeValue::Str(s)) => Some(s),
        _ => None,
    };
    let scale = match units {
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

// ---------------------------------------------------------------------------------------
// VTK XML ImageData

/// Header of one `.vti` array as [`crate::read_vti`] chooses and interprets it (`array` by
/// name, else the active cell scalars, the first cell array or the first point array; point
/// data as voxel centres; a piece extent above 0 shifts the origin; field-data `periodic`).
/// Streams the XML tags and stops at the chosen array's tag: inline array values are skipped
/// as text and never decoded, appended data is not read. Only a `periodic` field array
/// stored in the appended block makes it read the file in full.
pub fn vti_header(path: &Path, array: Option<&str>) -> Result<Header, String> {
    let at = |e: String| format!("{}: {e}", path.display());
    let s = VtiScan::run(path, array).map_err(at)?;
    let img = s
        .image
        .as_ref()
        .ok_or_else(|| at("no <ImageData>: not a .vti image".into()))?;
    let ext: [f64; 6] = nums(img.attr("WholeExtent"), "WholeExtent")
        .map_err(at)?
        .ok_or_else(|| at("no WholeExtent".into()))?;
    let ext = ext.map(|e| e as i64);
    let spacing = nums::<3>(img.attr("Spacing"), "Spacing").map_err(at)?;
    let mut origin = nums::<3>(img.attr("Origin"), "Origin").map_err(at)?;
    if let Some(d) = nums::<9>(img.attr("Direction"), "Direction").map_err(at)? {
        let id = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        if d.iter().zip(id).any(|(a, b)| (a - b).abs() > 1e-12) {
            return Err(at(
                "rotated images (Direction not identity) are not supported".into(),
            ));
        }
    }
    if !s.piece_seen {
        return Err(at("no <Piece>".into()));
    }
    let (node, is_cell) = s.choice().ok_or_else(|| {
        let names: Vec<&str> = s
            .arrays
            .iter()
            .filter_map(|(a, _)| a.attr("Name"))
            .collect();
        at(format!(
            "no array {} (arrays: {names:?})",
            array.map(|a| format!("`{a}`")).unwrap_or_default()
        ))
    })?;
    let span = |a: usize| (ext[2 * a + 1] - ext[2 * a]).max(0) as usize;
    let mut dims = [span(0), span(1), span(2)];
    if is_cell {
        dims = dims.map(|d| d.max(1));
    } else {
        dims = dims.map(|d| d + 1);
        if let (Some(o), Some(s)) = (origin.as_mut(), spacing) {
            for a in 0..3 {
                o[a] -= 0.5 * s[a];
            }
        }
    }
    if let Some(o) = origin.as_mut() {
        for a in 0..3 {
            o[a] += ext[2 * a] as f64 * spacing.map(|s| s[a]).unwrap_or(0.0);
        }
    }
    let components: usize = node
        .attr("NumberOfComponents")
        .and_then(|c| c.parse().ok())
        .unwrap_or(1);
    let dtype = node.attr("type").unwrap_or("Float32").to_string();
    let elem_bytes = vtk_type_size(&dtype).ok_or_else(|| {
        at(format!(
            "array `{}`: type {dtype} is not numeric",
            node.attr("Name").unwrap_or("?")
        ))
    })?;
    let periodic = match s.periodic_values(path).map_err(at)? {
        Some(p) if p.len() == 3 => [0, 1, 2].map(|a| p[a] != 0.0),
        _ => [false; 3],
    };
    Ok(Header {
        probe: Probe {
            dims,
            components,
            dtype,
            elem_bytes,
            spacing,
            origin,
        },
        periodic,
    })
}

fn vtk_type_size(t: &str) -> Option<usize> {
    Some(match t {
        "Int8" | "UInt8" => 1,
        "Int16" | "UInt16" => 2,
        "Int32" | "UInt32" | "Float32" => 4,
        "Int64" | "UInt64" | "Float64" => 8,
        _ => return None,
    })
}

fn nums<const N: usize>(s: Option<&str>, what: &str) -> Result<Option<[f64; N]>, String> {
    let Some(s) = s else { return Ok(None) };
    let v: Vec<f64> = s
        .split_whitespace()
        .map(|t| t.parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{what} `{s}`: {e}"))?;
    v.try_into()
        .map(Some)
        .map_err(|_| format!("{what} `{s}` needs {N} numbers"))
}

/// What the tag stream of a `.vti` says, up to the chosen array.
#[derive(Default)]
struct VtiScan {
    vtk: Option<Node>,
    image: Option<Node>,
    piece_seen: bool,
    /// The first CellData of the piece was seen, with its active scalars.
    cell_active: Option<Option<String>>,
    /// Data arrays of the piece (attributes only), with "is cell data".
    arrays: Vec<(Node, bool)>,
    want: Option<String>,
    /// The `periodic` array of the first FieldData (attributes and inline text).
    periodic: Option<Node>,
}

/// Where in the document the scanner is.
#[derive(Clone, Copy, PartialEq)]
enum Place {
    Other,
    /// The first ImageData element.
    Image,
    /// Its first Piece.
    Piece,
    /// The piece's first CellData (true) or PointData (false).
    Section(bool),
    /// The first FieldData.
    FieldData,
    /// The `periodic` array of that FieldData (its text is kept).
    Periodic,
}

impl VtiScan {
    fn run(path: &Path, array: Option<&str>) -> Result<VtiScan, String> {
        use quick_xml::events::{BytesStart, Event};
        let file = std::fs::File::open(path).map_err(|e| e.to_string())?;
        let mut reader = quick_xml::Reader::from_reader(BufReader::new(file));
        let mut buf = Vec::new();
        let mut s = VtiScan {
            want: array.map(str::to_string),
            ..Default::default()
        };
        let open = |e: &BytesStart| -> Result<Node, String> {
            let mut n = Node {
                name: e.name().as_ref().to_string(),
                ..Node::default()
            };
            for a in e.attributes() {
                let a = a.map_err(|e| e.to_string())?;
                let v = a
                    .normalized_value(quick_xml::XmlVersion::Implicit1_0)
                    .map_err(|e| e.to_string())?;
                n.attrs.push((a.key.as_ref().to_string(), v.into_owned()));
            }
            Ok(n)
        };
        let mut stack: Vec<Place> = Vec::new();
        let mut seen_sections = [false; 2];
        let mut field_seen = false;
        loop {
            let ev = reader
                .read_event_into(&mut buf)
                .map_err(|e| format!("malformed XML: {e}"))?;
            let (e, empty) = match &ev {
                Event::Start(e) => (e, false),
                Event::Empty(e) => (e, true),
                Event::Text(t) => {
                    if stack.last() == Some(&Place::Periodic) {
                        if let Some(p) = s.periodic.as_mut() {
                            p.text.push_str(&t.xml10_content());
                        }
                    }
                    buf.clear();
                    continue;
                }
                Event::End(_) => {
                    if stack.pop() == Some(Place::Piece) {
                        break;
                    }
                    buf.clear();
                    continue;
                }
                Event::Eof => break,
                _ => {
                    buf.clear();
                    continue;
                }
            };
            let node = open(e)?;
            let parent = stack.last().copied().unwrap_or(Place::Other);
            let place = match node.name.as_str() {
                "VTKFile" if s.vtk.is_none() => {
                    s.vtk = Some(node);
                    Place::Other
                }
                "ImageData" if s.image.is_none() => {
                    s.image = Some(node);
                    Place::Image
                }
                "FieldData" if !field_seen => {
                    field_seen = true;
                    Place::FieldData
                }
                "Piece" if parent == Place::Image && !s.piece_seen => {
                    s.piece_seen = true;
                    Place::Piece
                }
                "CellData" | "PointData" if parent == Place::Piece => {
                    let cell = node.name == "CellData";
                    let k = cell as usize;
                    if seen_sections[k] {
                        Place::Other
                    } else {
                        seen_sections[k] = true;
                        if cell {
                            s.cell_active = Some(node.attr("Scalars").map(str::to_string));
                        }
                        Place::Section(cell)
                    }
                }
                "DataArray" if matches!(parent, Place::Section(_)) => {
                    let cell = parent == Place::Section(true);
                    s.arrays.push((node, cell));
                    Place::Other
                }
                "AppendedData" => break,
                _ if parent == Place::FieldData
                    && s.periodic.is_none()
                    && node.attr("Name") == Some("periodic") =>
                {
                    s.periodic = Some(node);
                    Place::Periodic
                }
                _ => Place::Other,
            };
            if s.decided() {
                break;
            }
            if !empty {
                stack.push(place);
            }
            buf.clear();
        }
        if s.vtk.is_none() {
            return Err("no <VTKFile> element: not a VTK XML file".into());
        }
        Ok(s)
    }

    /// The array the full reader would take, as far as the tags seen so far decide it.
    fn choice(&self) -> Option<(&Node, bool)> {
        let active = self.cell_active.clone().flatten();
        let want = self.want.clone().or(active);
        let cells = self.arrays.iter().filter(|(_, c)| *c);
        let points = self.arrays.iter().filter(|(_, c)| !*c);
        match want {
            Some(name) => {
                let named = |(a, _): &&(Node, bool)| a.attr("Name") == Some(name.as_str());
                cells
                    .clone()
                    .find(named)
                    .or_else(|| points.clone().find(named))
            }
            None => cells.clone().next().or_else(|| points.clone().next()),
        }
        .map(|(n, c)| (n, *c))
    }

    /// True once no later tag can change [`VtiScan::choice`]: a cell array is chosen and the
    /// name it was chosen by (given, or the active scalars) is known.
    fn decided(&self) -> bool {
        let known = self.want.is_some() || self.cell_active.is_some();
        known && self.choice().is_some_and(|(_, cell)| cell)
    }

    /// Values of the field-data `periodic` array: decoded from its inline text, or (stored in
    /// the appended block) through the full reader's file parser.
    fn periodic_values(&self, path: &Path) -> Result<Option<Vec<f64>>, String> {
        let Some(p) = &self.periodic else {
            return Ok(None);
        };
        let vtk = self.vtk.as_ref().expect("checked by run");
        let ty = p.attr("type").unwrap_or("Float32");
        let little = vtk.attr("byte_order") != Some("BigEndian");
        let bytes = match p.attr("format").unwrap_or("ascii") {
            "ascii" => {
                return p
                    .text
                    .split_whitespace()
                    .map(|t| {
                        t.parse::<f64>()
                            .map_err(|e| format!("array `periodic`: {e}"))
                    })
                    .collect::<Result<Vec<_>, _>>()
                    .map(Some)
            }
            "binary" => inline_binary(
                &p.text,
                vtk.attr("header_type") == Some("UInt64"),
                little,
                matches!(vtk.attr("compressor"), Some(c) if !c.is_empty()),
            )
            .map_err(|e| format!("array `periodic`: {e}"))?,
            _ => {
                let f = VtkFile::open(path)?;
                return match f.field_array("periodic") {
                    Some(n) => {
                        let v = f.array_values(n)?;
                        Ok(Some((0..v.len()).map(|i| v.get(i)).collect()))
                    }
                    None => Ok(None),
                };
            }
        };
        fn conv<T: Le + Into<f64>>(b: &[u8], little: bool) -> Vec<f64> {
            from_bytes::<T>(b, little)
                .into_iter()
                .map(Into::into)
                .collect()
        }
        Ok(Some(match ty {
            "UInt8" => conv::<u8>(&bytes, little),
            "Int8" => conv::<i8>(&bytes, little),
            "UInt16" => conv::<u16>(&bytes, little),
            "Int16" => conv::<i16>(&bytes, little),
            "UInt32" => conv::<u32>(&bytes, little),
            "Int32" => conv::<i32>(&bytes, little),
            "Int64" => from_bytes::<i64>(&bytes, little)
                .into_iter()
                .map(|x| x as f64)
                .collect(),
            "UInt64" => from_bytes::<u64>(&bytes, little)
                .into_iter()
                .map(|x| x as f64)
                .collect(),
            "Float32" => conv::<f32>(&bytes, little),
            "Float64" => conv::<f64>(&bytes, little),
            t => return Err(format!("array `periodic`: type {t} is not numeric")),
        }))
    }
}

/// The bytes of a small inline `format="binary"` array (base64, with VTK's size header, zlib
/// blocks when the file is compressed).
fn inline_binary(
    text: &str,
    u64_header: bool,
    little: bool,
    zlib: bool,
) -> Result<Vec<u8>, String> {
    let b64 = base64::engine::general_purpose::STANDARD;
    let t: Vec<u8> = text.bytes().filter(|b| !b.is_ascii_whitespace()).collect();
    let hs = if u64_header { 8 } else { 4 };
    let value = |b: &[u8]| {
        if u64_header {
            u64::from_bytes(b, little) as usize
        } else {
            u32::from_bytes(b, little) as usize
        }
    };
    let dec = |t: &[u8]| b64.decode(t).map_err(|e| format!("bad base64: {e}"));
    if !zlib {
        let all = dec(&t)?;
        let n = value(all.get(..hs).ok_or("truncated array")?);
        return all
            .get(hs..hs + n)
            .map(<[u8]>::to_vec)
            .ok_or_else(|| "truncated array".to_string());
    }
    let b64len = |bytes: usize| bytes.div_ceil(3) * 4;
    let first = dec(t.get(..b64len(3 * hs)).ok_or("truncated header")?)?;
    let nblocks = value(&first[..hs]);
    let hlen = b64len((3 + nblocks) * hs);
    let header = dec(t.get(..hlen).ok_or("truncated header")?)?;
    let body = dec(&t[hlen..])?;
    let mut out = Vec::new();
    let mut pos = 0;
    for k in 0..nblocks {
        let c = value(
            header
                .get((3 + k) * hs..(4 + k) * hs)
                .ok_or("truncated header")?,
        );
        let chunk = body.get(pos..pos + c).ok_or("compressed data truncated")?;
        pos += c;
        flate2::read::ZlibDecoder::new(chunk)
            .read_to_end(&mut out)
            .map_err(|e| format!("zlib: {e}"))?;
    }
    Ok(out)
}

/// Small volumes and files in the layouts the readers take, for the tests of this module
/// and of the import stages.
#[cfg(test)]
pub(crate) mod testdata {
    use grainpipe_core::{Field, FieldData, Grid, Phase, PhaseImage};
    use std::path::Path;

    /// A grid with distinct spacings, an origin off zero and periodic y and z axes.
    pub fn grid(dims: [usize; 3]) -> Grid {
        Grid {
            dims,
            spacing: [1.5e-6, 2.5e-6, 4e-6],
            origin: [-1e-4, 3e-5, 7.25e-3],
            periodic: [false, true, true],
        }
    }

    pub fn image(dims: [usize; 3]) -> PhaseImage {
        let g = grid(dims);
        PhaseImage {
            labels: (0..g.voxel_count()).map(|i| (i % 3) as u8).collect(),
            grid: g,
            phases: (0..3)
                .map(|id| Phase {
                    id,
                    name: format!("p{id}"),
                })
                .collect(),
        }
    }

    pub fn field(dims: [usize; 3], components: usize) -> Field {
        let g = grid(dims);
        Field {
            data: FieldData::F32(
                (0..g.voxel_count() * components)
                    .map(|i| i as f32 * 0.5)
                    .collect(),
            ),
            grid: g,
            name: "f".into(),
            unit: "K".into(),
            components,
            convention: grainpipe_core::ComponentConvention::Plain,
        }
    }

    /// An HDF5 file with one f32 dataset of `shape` (values 1), written as other tools do:
    /// no grainpipe attributes, ImageJ's `element_size_um` (z, y, x) when given.
    pub fn write_plain_h5(
        path: &Path,
        name: &str,
        shape: &[usize],
        element_size_um: Option<[f64; 3]>,
    ) {
        let f = hdf5_metno::File::create(path).unwrap();
        let ds = f.new_dataset::<f32>().shape(shape).create(name).unwrap();
        ds.write_raw(&vec![1f32; shape.iter().product()]).unwrap();
        if let Some(e) = element_size_um {
            crate::h5util::attr_array(&ds, "element_size_um", &e).unwrap();
        }
    }

    /// A CF NetCDF file: dimensions `axes` (slowest first: (z,) y, x), each with a coordinate
    /// variable of voxel centres `origin + i * step` in micrometres, and an i16 variable
    /// `labels` (values 1) over them.
    pub fn write_cf_nc(path: &Path, axes: &[(&str, usize, f64, f64)]) {
        let mut f = netcdf::create(path).unwrap();
        for (n, l, _, _) in axes {
            f.add_dimension(n, *l).unwrap();
        }
        for (n, l, step, origin) in axes {
            let mut v = f.add_variable::<f64>(n, &[n]).unwrap();
            v.put_attribute("units", "um").unwrap();
            let c: Vec<f64> = (0..*l).map(|i| origin + step * i as f64).collect();
            v.put_values(&c, ..).unwrap();
        }
        let names: Vec<&str> = axes.iter().map(|a| a.0).collect();
        let mut v = f.add_variable::<i16>("labels", &names).unwrap();
        let n: usize = axes.iter().map(|a| a.1).product();
        v.put_values(&vec![1i16; n], ..).unwrap();
    }
}

#[cfg(test)]
mod tests {
    use super::testdata::*;
    use super::*;
    use crate::{read_hdf5_dataset, read_netcdf_variable, read_vti, write_h5, write_nc, write_vti};
    use grainpipe_core::{Artifact, Provenance};

    /// Every listed file: the header reader states what the full reader then reads.
    fn agree(
        header: impl Fn(&Path) -> Result<Header, String>,
        read: impl Fn(&Path) -> Result<Volume, String>,
        files: &[std::path::PathBuf],
    ) {
        for f in files {
            let h = header(f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            let v = read(f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            assert_eq!(h.geometry(), volume_geometry(&v), "{}", f.display());
        }
    }

    #[test]
    fn hdf5_header_matches_the_reader_for_grainpipe_and_imagej_files() {
        let d = tempfile::tempdir().unwrap();
        let a = d.path().join("a.h5");
        write_h5(
            &Artifact::PhaseImage(image([5, 4, 3])),
            &a,
            &Provenance::default(),
        )
        .unwrap();
        // ImageJ/ilastik style: element_size_um (z, y, x), no spacing, no origin.
        let b = d.path().join("b.h5");
        write_plain_h5(&b, "volume", &[2, 3, 4], Some([2.0, 0.5, 0.25]));
        agree(
            |p| hdf5_header(p, if p == a { "phase" } else { "volume" }),
            |p| read_hdf5_dataset(p, if p == a { "phase" } else { "volume" }),
            &[a.clone(), b.clone()],
        );
        let h = hdf5_header(&b, "volume").unwrap();
        assert_eq!(h.probe.dims, [4, 3, 2]);
        assert_eq!(h.probe.spacing, Some([0.25e-6, 0.5e-6, 2e-6]));
        assert_eq!(
            hdf5_header(&a, "phase").unwrap().periodic,
            [false, true, true]
        );
    }

    #[test]
    fn netcdf_header_matches_the_reader_for_grainpipe_and_cf_files() {
        let d = tempfile::tempdir().unwrap();
        let a = d.path().join("a.nc");
        write_nc(
            &Artifact::Field(field([3, 4, 2], 1)),
            &a,
            &Provenance::default(),
        )
        .unwrap();
        let b = d.path().join("cf.nc");
        write_cf_nc(
            &b,
            &[("z", 2, 5.0, -5.0), ("y", 3, 3.0, 0.0), ("x", 4, 2.0, 10.0)],
        );
        agree(
            |p| netcdf_header(p, if p == a { "f" } else { "labels" }),
            |p| read_netcdf_variable(p, if p == a { "f" } else { "labels" }),
            &[a.clone(), b.clone()],
        );
        assert!(netcdf_header(&b, "labels").unwrap().probe.spacing.is_some());
        assert_eq!(
            netcdf_header(&a, "f").unwrap().periodic,
            [false, true, true]
        );
    }

    #[test]
    fn vti_header_matches_the_reader_for_every_layout() {
        let d = tempfile::tempdir().unwrap();
        let mut files = Vec::new();
        let a = d.path().join("grainpipe_image.vti");
        write_vti(
            &Artifact::PhaseImage(image([5, 4, 3])),
            &a,
            &Provenance::default(),
        )
        .unwrap();
        files.push(a);
        let b = d.path().join("grainpipe_field.vti");
        write_vti(
            &Artifact::Field(field([3, 2, 4], 3)),
            &b,
            &Provenance::default(),
        )
        .unwrap();
        files.push(b);
        let head = "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"0.1\" \
                    byte_order=\"LittleEndian\" header_type=\"UInt32\">\n";
        let texts = [
            // point data: voxel centres, origin moved back by half a voxel
            ("points.vti", "<ImageData WholeExtent=\"0 2 0 1 0 0\" Origin=\"1 2 3\" Spacing=\"0.5 0.25 1\">\n\
              <Piece Extent=\"0 2 0 1 0 0\"><PointData Scalars=\"l\">\n\
              <DataArray type=\"UInt8\" Name=\"l\" format=\"ascii\">0 1 2 3 4 5</DataArray>\n\
              </PointData><CellData></CellData></Piece></ImageData></VTKFile>\n"),
            // a piece extent above 0, ascii periodic flags after the provenance
            ("offset.vti", "<ImageData WholeExtent=\"2 4 1 2 0 1\" Origin=\"0 0 0\" Spacing=\"0.5 0.25 1\">\n\
              <FieldData><Array type=\"UInt8\" Name=\"periodic\" NumberOfTuples=\"3\" format=\"ascii\">1 0 1</Array></FieldData>\n\
              <Piece Extent=\"2 4 1 2 0 1\"><PointData></PointData><CellData Scalars=\"l\">\n\
              <DataArray type=\"Int16\" Name=\"m\" format=\"ascii\">9 9</DataArray>\n\
              <DataArray type=\"Int16\" Name=\"l\" format=\"ascii\">0 1</DataArray>\n\
              </CellData></Piece></ImageData></VTKFile>\n"),
            // a point array and a cell array of the same name: the cell array wins
            ("both.vti", "<ImageData WholeExtent=\"0 1 0 1 0 1\" Origin=\"0 0 0\" Spacing=\"1 1 1\">\n\
              <Piece Extent=\"0 1 0 1 0 1\"><PointData>\n\
              <DataArray type=\"Float64\" Name=\"v\" format=\"ascii\">1 2 3 4 5 6 7 8</DataArray>\n\
              </PointData><CellData>\n\
              <DataArray type=\"Float32\" Name=\"v\" format=\"ascii\">1</DataArray>\n\
              </CellData></Piece></ImageData></VTKFile>\n"),
        ];
        for (name, body) in texts {
            let p = d.path().join(name);
            std::fs::write(&p, format!("{head}{body}")).unwrap();
            files.push(p);
        }
        // Periodic flags in the appended block (read through the full parser).
        let mut appended = format!(
            "{head}<ImageData WholeExtent=\"0 2 0 1 0 1\" Origin=\"0 0 0\" Spacing=\"1 1 1\">\n\
             <FieldData><Array type=\"UInt8\" Name=\"periodic\" format=\"appended\" offset=\"0\"/></FieldData>\n\
             <Piece Extent=\"0 2 0 1 0 1\"><CellData Scalars=\"s\">\n\
             <DataArray type=\"UInt8\" Name=\"s\" format=\"appended\" offset=\"7\"/>\n\
             </CellData></Piece></ImageData>\n<AppendedData encoding=\"raw\">\n_"
        )
        .into_bytes();
        appended.extend_from_slice(&3u32.to_le_bytes());
        appended.extend_from_slice(&[0, 1, 1]);
        appended.extend_from_slice(&2u32.to_le_bytes());
        appended.extend_from_slice(&[4, 5]);
        appended.extend_from_slice(b"\n</AppendedData>\n</VTKFile>\n");
        let p = d.path().join("appended.vti");
        std::fs::write(&p, appended).unwrap();
        files.push(p.clone());
        agree(|p| vti_header(p, None), |p| read_vti(p, None), &files);
        agree(
            |p| vti_header(p, Some("v")),
            |p| read_vti(p, Some("v")),
            &[d.path().join("both.vti")],
        );
        assert_eq!(vti_header(&p, None).unwrap().periodic, [false, true, true]);
        assert_eq!(
            vti_header(&d.path().join("offset.vti"), None)
                .unwrap()
                .periodic,
            [true, false, true]
        );
        // Errors name what is missing.
        let e = vti_header(&d.path().join("both.vti"), Some("nope")).unwrap_err();
        assert!(e.contains("both.vti") && e.contains("nope"), "{e}");
    }
}
