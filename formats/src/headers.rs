//! Header-only readers for the import stages: the shape, element type and grid (dims,
//! spacing, origin, periodic axes) a volume file states, read without its voxel values, so
//! that an import's preflight can announce the exact grid of its output.
//!
//! Each reader derives the grid exactly as the matching full reader does (same attributes,
//! same fallbacks, same arithmetic), so the announced grid equals the imported one bit for
//! bit; the tests below hold every reader to its full counterpart on the file variants the
//! full readers accept.

use crate::volume::{Probe, Volume};
use crate::vtk_xml::{
    array_components, choose_array, no_array_error, vtk_type_size, Encoding, ImageGrid, Node,
    VtkFile,
};
use std::io::BufReader;
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
    let f =
        hdf5_metno::File::open(path).map_err(|e| crate::h5util::cannot_open(path, "HDF5", &e))?;
    let ds = f
        .dataset(dataset)
        .map_err(|e| format!("{}: no dataset `{dataset}` ({e})", path.display()))?;
    let (spacing, origin, periodic) = crate::hdf5_plain::dataset_grid(&ds);
    Ok(Header {
        probe: Probe {
            spacing,
            origin,
            ..probe
        },
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
    let f = netcdf::open(path).map_err(|e| crate::h5util::cannot_open(path, "NetCDF", &e))?;
    let v = f
        .variable(var)
        .ok_or_else(|| at(format!("no variable `{var}`")))?;
    let (spacing, origin, periodic) = crate::netcdf_io::grid(&f, &v).map_err(at)?;
    Ok(Header {
        probe: Probe {
            spacing,
            origin,
            ..probe
        },
        periodic,
    })
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
    let grid = ImageGrid::of(img).map_err(at)?;
    if !s.piece_seen {
        return Err(at("no <Piece>".into()));
    }
    let (node, is_cell) = s.choice().ok_or_else(|| {
        let names = s.arrays.iter().filter_map(|(a, _)| a.attr("Name"));
        at(no_array_error(array, names))
    })?;
    let (dims, spacing, origin) = grid.voxels(is_cell);
    let components = array_components(node);
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
        use quick_xml::events::Event;
        let file = std::fs::File::open(path).map_err(|e| e.to_string())?;
        let mut reader = quick_xml::Reader::from_reader(BufReader::new(file));
        let mut buf = Vec::new();
        let mut s = VtiScan {
            want: array.map(str::to_string),
            ..Default::default()
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
            let node = Node::open(e)?;
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
        let of = |cell: bool| {
            self.arrays
                .iter()
                .filter(move |a| a.1 == cell)
                .map(|a| &a.0)
        };
        choose_array(of(true), of(false), want.as_deref())
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
        let values = if p.attr("format") == Some("appended") {
            let f = VtkFile::open(path)?;
            match f.field_array("periodic") {
                Some(n) => f.array_values(n)?,
                None => return Ok(None),
            }
        } else {
            let enc = Encoding::of(self.vtk.as_ref().expect("checked by run"))?;
            enc.inline_payload(p)?.values(p, enc.little)?
        };
        Ok(Some((0..values.len()).map(|i| values.get(i)).collect()))
    }
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
