//! VTK XML files: `.vti` ImageData (phase images, fields), `.vtp` PolyData (packings,
//! contact graphs), `.pvd` collections (series), and a reader for `.vti`.
//!
//! Arrays are written `format="binary"`, zlib-compressed in 32 KiB blocks with a UInt64 header
//! (what VTK/ParaView write by default), so large images stay small. The reader also takes
//! ascii, uncompressed binary and appended (raw or base64) arrays with UInt32/UInt64 headers.

use crate::volume::{from_bytes, to_le_bytes, Le, Volume, VolumeData, VolumeRef};
use base64::Engine;
use grainpipe_core::fsutil::atomic_write;
use grainpipe_core::{
    Artifact, ArtifactKind, ComponentConvention, ContactGraph, FieldData, Packing, Phase,
    Provenance, Series,
};
use std::collections::{HashMap, HashSet};
use std::io::{Read, Write};
use std::path::Path;

const B64: base64::engine::GeneralPurpose = base64::engine::general_purpose::STANDARD;
/// Uncompressed size of one zlib block (VTK's default).
const BLOCK: usize = 1 << 15;

/// VTK type names of the element types we write.
pub(crate) trait VtkType: Le {
    const NAME: &'static str;
}
macro_rules! vtk_type {
    ($($t:ty => $n:expr),*) => {$( impl VtkType for $t { const NAME: &'static str = $n; } )*};
}
vtk_type!(u8 => "UInt8", u32 => "UInt32", i32 => "Int32", i64 => "Int64", f32 => "Float32", f64 => "Float64");

/// One `<DataArray>` ready to encode.
pub(crate) struct Array {
    name: String,
    vtk_type: &'static str,
    ncomp: usize,
    tuples: usize,
    bytes: Vec<u8>,
    /// `ComponentName<k>` attributes (shown by ParaView), empty for none.
    component_names: Vec<String>,
}

impl Array {
    pub fn new<T: VtkType>(name: &str, ncomp: usize, values: &[T]) -> Self {
        Array {
            name: name.to_string(),
            vtk_type: T::NAME,
            ncomp,
            tuples: values.len() / ncomp.max(1),
            bytes: to_le_bytes(values),
            component_names: Vec::new(),
        }
    }

    fn with_component_names(mut self, names: Vec<String>) -> Self {
        self.component_names = names;
        self
    }

    fn xml(&self, tag: &str) -> String {
        let mut head = format!(
            "<{tag} type=\"{}\" Name=\"{}\" NumberOfComponents=\"{}\" NumberOfTuples=\"{}\"",
            self.vtk_type,
            esc(&self.name),
            self.ncomp,
            self.tuples
        );
        for (k, n) in self.component_names.iter().enumerate() {
            head.push_str(&format!(" ComponentName{k}=\"{}\"", esc(n)));
        }
        if self.bytes.is_empty() {
            // An empty compressed array has no blocks, which some VTK versions misread.
            return format!("{head} format=\"ascii\">\n</{tag}>\n");
        }
        format!(
            "{head} format=\"binary\">\n{}\n</{tag}>\n",
            zlib_base64(&self.bytes)
        )
    }
}

/// VTK's compressed binary layout: base64(header) + base64(blocks), header =
/// [#blocks, block size, last partial block size (0 if full), compressed sizes...] as UInt64.
fn zlib_base64(bytes: &[u8]) -> String {
    let blocks: Vec<&[u8]> = bytes.chunks(BLOCK).collect();
    let last = bytes.len() % BLOCK;
    let mut header: Vec<u64> = vec![blocks.len() as u64, BLOCK as u64, last as u64];
    let mut body = Vec::new();
    for b in &blocks {
        let mut enc = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        enc.write_all(b).expect("in-memory write");
        let c = enc.finish().expect("in-memory write");
        header.push(c.len() as u64);
        body.extend_from_slice(&c);
    }
    let mut s = B64.encode(to_le_bytes(&header));
    s.push_str(&B64.encode(body));
    s
}

/// A VTK string array (ascii: character codes, each string ended by 0).
fn string_array(name: &str, values: &[&str]) -> String {
    let mut codes = String::new();
    for v in values {
        for b in v.bytes() {
            codes.push_str(&b.to_string());
            codes.push(' ');
        }
        codes.push_str("0 ");
    }
    format!(
        "<Array type=\"String\" Name=\"{}\" NumberOfTuples=\"{}\" format=\"ascii\">\n{}\n</Array>\n",
        esc(name),
        values.len(),
        codes.trim_end()
    )
}

fn esc(s: &str) -> String {
    quick_xml::escape::escape(s).into_owned()
}

/// Shortest text that parses back to the same f64.
fn num(x: f64) -> String {
    format!("{x:e}")
}

fn nums(v: &[f64]) -> String {
    v.iter().map(|&x| num(x)).collect::<Vec<_>>().join(" ")
}

fn file_head(kind: &str) -> String {
    format!(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"{kind}\" version=\"1.0\" byte_order=\"LittleEndian\" \
         header_type=\"UInt64\" compressor=\"vtkZLibDataCompressor\">\n"
    )
}

/// Names of field-data arrays the writers use themselves; provenance keys that collide get a
/// `provenance.` prefix.
const RESERVED: [&str; 6] = [
    "phase_ids",
    "phase_names",
    "unit",
    "periodic",
    "domain_min",
    "domain_max",
];

/// `<FieldData>` with the provenance (one string array per entry) and the given arrays.
fn field_data(prov: &Provenance, strings: &[(&str, Vec<&str>)], arrays: &[Array]) -> String {
    let mut s = String::from("<FieldData>\n");
    for (k, v) in &prov.entries {
        let name = if RESERVED.contains(&k.as_str()) || k.starts_with("faces_") {
            format!("provenance.{k}")
        } else {
            k.clone()
        };
        s.push_str(&string_array(&name, &[v.as_str()]));
    }
    for (name, values) in strings {
        s.push_str(&string_array(name, values));
    }
    for a in arrays {
        s.push_str(&a.xml("Array"));
    }
    s.push_str("</FieldData>\n");
    s
}

fn write_text(path: &Path, text: &str) -> Result<(), String> {
    atomic_write(path, |tmp| std::fs::write(tmp, text.as_bytes()))
}

// ---------------------------------------------------------------------------------------
// ImageData

fn vti_text(v: VolumeRef, prov: &Provenance) -> Result<String, String> {
    v.validate()?;
    let g = v.grid();
    let [nx, ny, nz] = g.dims;
    let extent = format!("0 {nx} 0 {ny} 0 {nz}");
    let periodic: Vec<u8> = g.periodic.iter().map(|&p| p as u8).collect();
    let mut arrays = vec![Array::new("periodic", 3, &periodic)];
    let mut strings: Vec<(&str, Vec<&str>)> = Vec::new();
    let data = match v {
        VolumeRef::Phase(p) => {
            let ids: Vec<u8> = p.phases.iter().map(|ph| ph.id).collect();
            arrays.push(Array::new("phase_ids", 1, &ids));
            strings.push((
                "phase_names",
                p.phases.iter().map(|ph| ph.name.as_str()).collect(),
            ));
            Array::new("phase", 1, &p.labels)
        }
        VolumeRef::Field(f) => {
            strings.push(("unit", vec![f.unit.as_str()]));
            strings.push(("component_convention", vec![f.convention.name()]));
            let a = match &f.data {
                FieldData::F32(d) => Array::new(&f.name, f.components, d),
                FieldData::F64(d) => Array::new(&f.name, f.components, d),
            };
            if f.components > 1 {
                a.with_component_names(f.component_names())
            } else {
                a
            }
        }
    };
    let role = if v.components() == 3
        && matches!(
            v.convention(),
            ComponentConvention::Vector | ComponentConvention::Plain
        ) {
        "Vectors"
    } else {
        "Scalars"
    };
    let mut s = file_head("ImageData");
    s.push_str(&format!(
        "<ImageData WholeExtent=\"{extent}\" Origin=\"{}\" Spacing=\"{}\" Direction=\"1 0 0 0 1 0 0 0 1\">\n",
        nums(&g.origin),
        nums(&g.spacing)
    ));
    s.push_str(&field_data(prov, &strings, &arrays));
    s.push_str(&format!(
        "<Piece Extent=\"{extent}\">\n<PointData>\n</PointData>\n"
    ));
    s.push_str(&format!("<CellData {role}=\"{}\">\n", esc(v.name())));
    s.push_str(&data.xml("DataArray"));
    s.push_str("</CellData>\n</Piece>\n</ImageData>\n</VTKFile>\n");
    Ok(s)
}

// ---------------------------------------------------------------------------------------
// PolyData

/// Points, vertex or line cells, point and cell data.
struct Poly {
    points: Vec<f64>,
    /// Connectivity and offsets of `Verts` (one per point) or `Lines`.
    verts: bool,
    lines: Vec<i64>,
    point_data: Vec<Array>,
    cell_data: Vec<Array>,
    field: String,
}

impl Poly {
    fn xml(&self) -> String {
        let np = self.points.len() / 3;
        let (nverts, nlines) = if self.verts {
            (np, 0)
        } else {
            (0, self.lines.len() / 2)
        };
        let mut s = file_head("PolyData");
        s.push_str("<PolyData>\n");
        s.push_str(&self.field);
        s.push_str(&format!(
            "<Piece NumberOfPoints=\"{np}\" NumberOfVerts=\"{nverts}\" NumberOfLines=\"{nlines}\" \
             NumberOfStrips=\"0\" NumberOfPolys=\"0\">\n"
        ));
        let scalars = self
            .point_data
            .first()
            .map(|a| format!(" Scalars=\"{}\"", esc(&a.name)))
            .unwrap_or_default();
        s.push_str(&format!("<PointData{scalars}>\n"));
        for a in &self.point_data {
            s.push_str(&a.xml("DataArray"));
        }
        s.push_str("</PointData>\n<CellData>\n");
        for a in &self.cell_data {
            s.push_str(&a.xml("DataArray"));
        }
        s.push_str("</CellData>\n<Points>\n");
        s.push_str(&Array::new("Points", 3, &self.points).xml("DataArray"));
        s.push_str("</Points>\n");
        let (tag, conn, offsets): (&str, Vec<i64>, Vec<i64>) = if self.verts {
            ("Verts", (0..np as i64).collect(), (1..=np as i64).collect())
        } else {
            (
                "Lines",
                self.lines.clone(),
                (1..=nlines as i64).map(|k| 2 * k).collect(),
            )
        };
        s.push_str(&format!("<{tag}>\n"));
        s.push_str(&Array::new("connectivity", 1, &conn).xml("DataArray"));
        s.push_str(&Array::new("offsets", 1, &offsets).xml("DataArray"));
        s.push_str(&format!("</{tag}>\n</Piece>\n</PolyData>\n</VTKFile>\n"));
        s
    }
}

/// What the `.vtp` of a periodic packing does with spheres whose centre lies outside the box
/// (clump spheres of a body near a periodic face): keep them (`as_is`), map the centres
/// into the box along the periodic axes (`wrap`, every sphere appears once, pieces of a clump
/// on both sides), or drop them (`clip`). Non-periodic axes are never changed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PeriodicSpheres {
    AsIs,
    Wrap,
    Clip,
}

impl PeriodicSpheres {
    pub const NAMES: [&'static str; 3] = ["as_is", "wrap", "clip"];

    pub fn from_name(s: &str) -> Option<Self> {
        match s {
            "as_is" => Some(Self::AsIs),
            "wrap" => Some(Self::Wrap),
            "clip" => Some(Self::Clip),
            _ => None,
        }
    }
}

/// `centre` mapped into [min, max) along each periodic axis.
fn wrap_into(centre: [f64; 3], min: [f64; 3], max: [f64; 3], periodic: [bool; 3]) -> [f64; 3] {
    let mut c = centre;
    for a in 0..3 {
        let len = max[a] - min[a];
        if periodic[a] && len > 0.0 {
            let w = min[a] + (c[a] - min[a]).rem_euclid(len);
            // rem_euclid can round up to exactly `len`.
            c[a] = if w >= max[a] { min[a] } else { w };
        }
    }
    c
}

fn packing_poly(
    p: &Packing,
    prov: &Provenance,
    periodic_mode: PeriodicSpheres,
) -> Result<Poly, String> {
    for (name, a) in &p.attributes {
        if a.values.len() != p.bodies.len() {
            return Err(format!(
                "packing attribute `{name}` has {} values for {} bodies",
                a.values.len(),
                p.bodies.len()
            ));
        }
    }
    if p.bodies.iter().any(|b| {
        matches!(b.shape, grainpipe_core::BodyShape::Clump { index }
            if p.library.as_ref().is_none_or(|l| index >= l.clumps.len()))
    }) {
        return Err("a clump body refers to a missing clump library entry".into());
    }
    let (min, max, periodic) = (p.domain.min, p.domain.max, p.domain.periodic);
    let spheres: Vec<_> = p
        .world_spheres()
        .into_iter()
        .filter_map(|mut s| match periodic_mode {
            PeriodicSpheres::AsIs => Some(s),
            PeriodicSpheres::Wrap => {
                s.center = wrap_into(s.center, min, max, periodic);
                Some(s)
            }
            PeriodicSpheres::Clip => (0..3)
                .all(|a| !periodic[a] || (min[a]..max[a]).contains(&s.center[a]))
                .then_some(s),
        })
        .collect();
    let points: Vec<f64> = spheres.iter().flat_map(|s| s.center).collect();
    let radius: Vec<f64> = spheres.iter().map(|s| s.radius).collect();
    let body: Vec<i64> = spheres.iter().map(|s| s.body as i64).collect();
    let layer: Vec<u32> = spheres.iter().map(|s| p.bodies[s.body].layer).collect();
    let frozen: Vec<u8> = spheres
        .iter()
        .map(|s| p.bodies[s.body].frozen as u8)
        .collect();
    let mut point_data = vec![
        Array::new("radius", 1, &radius),
        Array::new("body_id", 1, &body),
        Array::new("layer", 1, &layer),
        Array::new("frozen", 1, &frozen),
    ];
    // Which library clump each sphere's body is (as `clump_index` in the .h5), so clump
    // shapes can be told apart; -1 for plain spheres. Only packings with clumps carry it.
    if p.library.is_some() {
        let clump: Vec<i64> = spheres
            .iter()
            .map(|s| match p.bodies[s.body].shape {
                grainpipe_core::BodyShape::Clump { index } => index as i64,
                grainpipe_core::BodyShape::Sphere { .. } => -1,
            })
            .collect();
        point_data.push(Array::new("clump_index", 1, &clump));
    }
    for (name, a) in &p.attributes {
        let v: Vec<f64> = spheres.iter().map(|s| a.values[s.body]).collect();
        point_data.push(Array::new(name, 1, &v));
    }
    let units: Vec<String> = p
        .attributes
        .iter()
        .map(|(n, a)| format!("{n} [{}]", a.unit))
        .collect();
    let field = field_data(
        prov,
        &[(
            "attribute_units",
            units.iter().map(|s| s.as_str()).collect(),
        )],
        &[
            Array::new("domain_min", 3, &p.domain.min),
            Array::new("domain_max", 3, &p.domain.max),
            Array::new(
                "periodic",
                3,
                &p.domain.periodic.map(|b| b as u8).to_vec()[..],
            ),
        ],
    );
    Ok(Poly {
        points,
        verts: true,
        lines: Vec::new(),
        point_data,
        cell_data: Vec::new(),
        field,
    })
}

/// The lines drawn for a contact graph: every contact, then every bond that is not a
/// contact, with the gap (NaN for bonds without contact), whether the pair is bonded, and
/// the bond each line draws (None for an unbonded contact).
pub(crate) struct GraphLines {
    pub lines: Vec<i64>,
    pub gap: Vec<f64>,
    pub bonded: Vec<u8>,
    pub line_bond: Vec<Option<usize>>,
}

pub(crate) fn graph_lines(g: &ContactGraph) -> GraphLines {
    // Bond index by unordered pair, for the bond attributes of each line.
    let bonds: HashMap<(usize, usize), usize> = g
        .bonds
        .iter()
        .enumerate()
        .map(|(k, b)| ((b[0].min(b[1]), b[0].max(b[1])), k))
        .collect();
    let mut out = GraphLines {
        lines: Vec::new(),
        gap: Vec::new(),
        bonded: Vec::new(),
        line_bond: Vec::new(),
    };
    let mut in_contacts = HashSet::new();
    for c in &g.contacts {
        let key = (c.i.min(c.j), c.i.max(c.j));
        in_contacts.insert(key);
        out.lines.extend([c.i as i64, c.j as i64]);
        out.gap.push(c.gap);
        out.bonded.push(bonds.contains_key(&key) as u8);
        out.line_bond.push(bonds.get(&key).copied());
    }
    for (k, b) in g.bonds.iter().enumerate() {
        if !in_contacts.contains(&(b[0].min(b[1]), b[0].max(b[1]))) {
            out.lines.extend([b[0] as i64, b[1] as i64]);
            out.gap.push(f64::NAN);
            out.bonded.push(1);
            out.line_bond.push(Some(k));
        }
    }
    out
}

/// Contacts as lines (gap, bonded) followed by bonds that are not contacts (gap = NaN: no
/// gap is known for them).
fn graph_poly(g: &ContactGraph, prov: &Provenance) -> Result<Poly, String> {
    g.validate()?;
    let n = g.positions.len();
    let GraphLines {
        lines,
        gap,
        bonded,
        line_bond,
    } = graph_lines(g);
    let mut cell_data = vec![Array::new("gap", 1, &gap), Array::new("bonded", 1, &bonded)];
    for (name, a) in &g.bond_attributes {
        // Unbonded contacts have no value: NaN, which ParaView leaves uncoloured.
        let v: Vec<f64> = line_bond
            .iter()
            .map(|b| b.map(|k| a.values[k]).unwrap_or(f64::NAN))
            .collect();
        cell_data.push(Array::new(name, 1, &v));
    }
    let mut coordination = vec![0i32; n];
    for c in &g.contacts {
        coordination[c.i] += 1;
        coordination[c.j] += 1;
    }
    let ids: Vec<i64> = (0..n as i64).collect();
    let mut point_data = vec![
        Array::new("body_id", 1, &ids),
        Array::new("coordination", 1, &coordination),
    ];
    // Lets ParaView glyph the bodies from the graph alone (Glyph filter, scale by `radius`).
    if !g.radii.is_empty() {
        point_data.push(Array::new("radius", 1, &g.radii));
    }
    let faces: Vec<Array> = g
        .faces
        .iter()
        .zip(grainpipe_core::FACE_NAMES)
        .map(|(f, name)| {
            let v: Vec<i64> = f.iter().map(|&i| i as i64).collect();
            Array::new(&format!("faces_{name}"), 1, &v)
        })
        .collect();
    Ok(Poly {
        points: g.positions.iter().flatten().copied().collect(),
        verts: false,
        lines,
        point_data,
        cell_data,
        field: field_data(prov, &[], &faces),
    })
}

// ---------------------------------------------------------------------------------------
// Exporters

pub fn write_vti(a: &Artifact, path: &Path, prov: &Provenance) -> Result<(), String> {
    let text = vti_text(VolumeRef::from_artifact(a, "vti")?, prov)?;
    write_text(path, &text)
}

pub fn write_vtp(a: &Artifact, path: &Path, prov: &Provenance) -> Result<(), String> {
    write_vtp_with(a, path, prov, PeriodicSpheres::AsIs)
}

/// Writes a `.vtp`; `periodic` applies to packings (a contact graph is written as is).
pub fn write_vtp_with(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    periodic: PeriodicSpheres,
) -> Result<(), String> {
    let poly = match a {
        Artifact::Packing(p) => packing_poly(p, prov, periodic)?,
        Artifact::ContactGraph(g) => graph_poly(g, prov)?,
        other => {
            return Err(format!(
                "vtp takes a Packing or a ContactGraph, not a {}",
                other.kind()
            ))
        }
    };
    write_text(path, &poly.xml())
}

/// Writes every frame (of a Series) or item (of a Collection) into a fresh folder beside the
/// `.pvd` (`<stem>_frames_<tag>/<stem>_0000.vtp|vti`), then the collection file, then removes
/// the frame folders of earlier writes: frames as time steps, items as parts of one time
/// step (ParaView shows them as the blocks of a multiblock data set).
///
/// Why a fresh folder: the series is replaced as a set. Until the `.pvd` is renamed into
/// place it still names the complete old folder; after, the complete new one. A kill at any
/// moment never leaves a `.pvd` that mixes frames of two runs (frames rewritten in place
/// did), and the folders a killed write left are removed by the next write.
pub fn write_pvd(a: &Artifact, path: &Path, prov: &Provenance) -> Result<(), String> {
    // (time step, part, item name, artifact)
    let entries: Vec<(f64, usize, Option<&str>, &Artifact)> = match a {
        Artifact::Series(series) => {
            check_series(series)?;
            series
                .frames
                .iter()
                .map(|(t, f)| (*t, 0, None, f))
                .collect()
        }
        Artifact::Collection(c) => c
            .items
            .iter()
            .enumerate()
            .map(|(k, (name, item))| (0.0, k, Some(name.as_str()), item))
            .collect(),
        _ => {
            return Err(format!(
                "pvd takes a Series or a Collection, not a {}",
                a.kind()
            ))
        }
    };
    let ext = pvd_extension(entries.iter().map(|e| e.3))?;
    let stem = path
        .file_stem()
        .ok_or_else(|| format!("{}: no file name", path.display()))?
        .to_string_lossy()
        .into_owned();
    let dir = path.parent().unwrap_or(Path::new(""));
    let prefix = format!("{stem}_frames_");
    let tag = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let folder = format!("{prefix}{tag:x}{:x}", std::process::id());
    let frames_dir = dir.join(&folder);
    std::fs::create_dir_all(&frames_dir)
        .map_err(|e| format!("cannot create {}: {e}", frames_dir.display()))?;
    let written = write_pvd_set(&entries, ext, &stem, &folder, dir, prov, path);
    if written.is_err() {
        let _ = std::fs::remove_dir_all(&frames_dir);
        return written;
    }
    // The new set is in place: earlier sets (and those a killed write left) go.
    if let Ok(list) = std::fs::read_dir(if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    }) {
        for e in list.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let ours = name.strip_prefix(&prefix).is_some_and(|rest| {
                !rest.is_empty() && rest.chars().all(|c| c.is_ascii_hexdigit())
            });
            if ours && name != folder && e.path().is_dir() {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
    Ok(())
}

/// The frames of a `.pvd` into `dir/folder`, then the `.pvd` itself (last, atomically).
fn write_pvd_set(
    entries: &[(f64, usize, Option<&str>, &Artifact)],
    ext: &str,
    stem: &str,
    folder: &str,
    dir: &Path,
    prov: &Provenance,
    path: &Path,
) -> Result<(), String> {
    let mut coll = String::from(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"1.0\" byte_order=\"LittleEndian\">\n<Collection>\n",
    );
    for (k, (t, part, item_name, item)) in entries.iter().enumerate() {
        let name = format!("{folder}/{stem}_{k:04}.{ext}");
        let mut p = prov.clone();
        match item_name {
            Some(n) => p.entries.insert("item".into(), n.to_string()),
            None => p.entries.insert("time".into(), num(*t)),
        };
        match ext {
            "vti" => write_vti(item, &dir.join(&name), &p)?,
            _ => write_vtp(item, &dir.join(&name), &p)?,
        }
        let label = item_name
            .map(|n| format!(" name=\"{}\"", esc(n)))
            .unwrap_or_default();
        coll.push_str(&format!(
            "<DataSet timestep=\"{}\" group=\"\" part=\"{part}\"{label} file=\"{}\"/>\n",
            num(*t),
            esc(&name)
        ));
    }
    coll.push_str("</Collection>\n</VTKFile>\n");
    write_text(path, &coll)
}

/// Series times must not decrease.
fn check_series(s: &Series) -> Result<(), String> {
    if s.frames.windows(2).any(|w| w[1].0 < w[0].0) {
        return Err("series times must not decrease".into());
    }
    Ok(())
}

/// All frames or items must be of one kind that VTK XML holds; returns their extension.
fn pvd_extension<'a>(
    mut items: impl Iterator<Item = &'a Artifact>,
) -> Result<&'static str, String> {
    let Some(first) = items.next() else {
        return Err("nothing to write: no frames or items".into());
    };
    let kind = first.kind();
    if let Some(other) = items.find(|f| f.kind() != kind) {
        return Err(format!(
            "mixes {kind} and {} entries; a .pvd needs one kind",
            other.kind()
        ));
    }
    match kind {
        ArtifactKind::PhaseImage | ArtifactKind::Field => Ok("vti"),
        ArtifactKind::Packing | ArtifactKind::ContactGraph => Ok("vtp"),
        k => Err(format!(
            "a .pvd holds images, fields, packings or contact graphs, not {k}"
        )),
    }
}

macro_rules! exporter {
    // The methods every format has: name, extensions, the kinds it takes, its description.
    (@identity $name:expr, $ext:expr, [$($kind:ident),*], $doc:expr) => {
        fn name(&self) -> &'static str { $name }
        fn extensions(&self) -> &'static [&'static str] { $ext }
        fn accepts(&self, kind: grainpipe_core::ArtifactKind) -> bool {
            matches!(kind, $(grainpipe_core::ArtifactKind::$kind)|*)
        }
        fn doc(&self) -> &'static str { $doc }
    };
    // A format with options: `$options` lists them, `$check` validates their values at
    // preflight, `$write` writes with the options (every declared one, defaults filled in).
    // Every file an export writes besides its target (`paths:` gives them all, the target
    // first); by default the target alone.
    (@paths) => {};
    (@paths $paths:path) => {
        fn written_paths(
            &self,
            path: &std::path::Path,
            options: &grainpipe_core::registry::ExportOptions,
        ) -> Vec<grainpipe_core::registry::WrittenPath> {
            $paths(path, options)
        }
    };
    ($ty:ident, $name:expr, $ext:expr, [$($kind:ident),*], $doc:expr,
     options: $options:expr, check: $check:path, write: $write:path
     $(, paths: $paths:path)?) => {
        pub struct $ty;
        impl grainpipe_core::Exporter for $ty {
            $crate::vtk_xml::exporter!(@identity $name, $ext, [$($kind),*], $doc);
            $crate::vtk_xml::exporter!(@paths $($paths)?);
            fn options(&self) -> Vec<grainpipe_core::registry::ExportOption> {
                $options
            }
            fn check_options(
                &self,
                options: &grainpipe_core::registry::ExportOptions,
            ) -> Result<(), (String, String)> {
                $check(options)
            }
            fn write(
                &self,
                a: &grainpipe_core::Artifact,
                path: &std::path::Path,
                prov: &grainpipe_core::Provenance,
                options: &grainpipe_core::registry::ExportOptions,
            ) -> Result<(), String> {
                $write(a, path, prov, options)
            }
        }
    };
    ($ty:ident, $name:expr, $ext:expr, [$($kind:ident),*], $doc:expr, $write:path
     $(, paths: $paths:path)?) => {
        pub struct $ty;
        impl grainpipe_core::Exporter for $ty {
            $crate::vtk_xml::exporter!(@identity $name, $ext, [$($kind),*], $doc);
            $crate::vtk_xml::exporter!(@paths $($paths)?);
            fn write(
                &self,
                a: &grainpipe_core::Artifact,
                path: &std::path::Path,
                prov: &grainpipe_core::Provenance,
                _options: &grainpipe_core::registry::ExportOptions,
            ) -> Result<(), String> {
                $write(a, path, prov)
            }
        }
    };
}
pub(crate) use exporter;

exporter!(
    VtiExporter,
    "vti",
    &["vti"],
    [PhaseImage, Field],
    "VTK XML ImageData: cell data `phase` (UInt8, phase table in field data) or the field's \
     components; origin = lower grid corner, spacing = voxel size [m]",
    write_vti
);
exporter!(
    VtpExporter,
    "vtp",
    &["vtp"],
    [Packing, ContactGraph],
    "VTK XML PolyData: a packing as one point per sphere (radius, body_id, layer, frozen, \
     clump_index when the packing has clumps, body attributes) or a contact graph as lines \
     (gap, bonded) between the body centres (body_id, coordination, radius when the bodies are spheres)",
    options: vec![grainpipe_core::registry::ExportOption {
        name: "periodic",
        doc: "packings in a periodic box: `as_is` writes every sphere where its body puts it \
              (clump spheres may stick out of the box), `wrap` maps sphere centres into the \
              box along the periodic axes, `clip` drops spheres whose centre is outside the \
              box along a periodic axis (for pictures of the box)",
        default: grainpipe_core::serde_json::json!("as_is"),
    }],
    check: check_vtp_options,
    write: write_vtp_options
);

fn vtp_periodic(
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<PeriodicSpheres, (String, String)> {
    match options.get("periodic") {
        None => Ok(PeriodicSpheres::AsIs),
        Some(v) => v
            .as_str()
            .and_then(PeriodicSpheres::from_name)
            .ok_or_else(|| {
                (
                    "periodic".into(),
                    format!("{v} is not one of: {}", PeriodicSpheres::NAMES.join(", ")),
                )
            }),
    }
}

fn check_vtp_options(
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<(), (String, String)> {
    vtp_periodic(options).map(|_| ())
}

fn write_vtp_options(
    a: &Artifact,
    path: &Path,
    prov: &Provenance,
    options: &grainpipe_core::registry::ExportOptions,
) -> Result<(), String> {
    let mode = vtp_periodic(options).map_err(|(k, m)| format!("option `{k}`: {m}"))?;
    write_vtp_with(a, path, prov, mode)
}
exporter!(
    PvdExporter,
    "pvd",
    &["pvd"],
    [Series, Collection],
    "ParaView collection: one .vti/.vtp per frame (time steps) or per item (parts) beside the \
     .pvd",
    write_pvd
);

// ---------------------------------------------------------------------------------------
// Reading

/// A minimal element tree.
#[derive(Debug, Default)]
pub(crate) struct Node {
    pub name: String,
    pub attrs: Vec<(String, String)>,
    pub text: String,
    pub children: Vec<Node>,
}

impl Node {
    pub fn attr(&self, k: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(a, _)| a == k)
            .map(|(_, v)| v.as_str())
    }
    pub fn child(&self, name: &str) -> Option<&Node> {
        self.children.iter().find(|c| c.name == name)
    }
    /// Depth-first search for the first element named `name`.
    pub fn find(&self, name: &str) -> Option<&Node> {
        if self.name == name {
            return Some(self);
        }
        self.children.iter().find_map(|c| c.find(name))
    }

    /// An element (name and attributes, no text or children yet) from its start tag.
    pub fn open(e: &quick_xml::events::BytesStart) -> Result<Node, String> {
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
    }
}

fn parse_xml(text: &str) -> Result<Node, String> {
    use quick_xml::events::Event;
    let mut reader = quick_xml::Reader::from_str(text);
    let mut stack: Vec<Node> = vec![Node::default()];
    let open = Node::open;
    loop {
        match reader
            .read_event()
            .map_err(|e| format!("malformed XML at byte {}: {e}", reader.buffer_position()))?
        {
            Event::Start(e) => stack.push(open(&e)?),
            Event::Empty(e) => {
                let n = open(&e)?;
                stack.last_mut().expect("root").children.push(n);
            }
            Event::Text(t) => stack
                .last_mut()
                .expect("root")
                .text
                .push_str(&t.xml10_content()),
            Event::End(_) => {
                let n = stack.pop().expect("balanced");
                stack.last_mut().ok_or("unbalanced XML")?.children.push(n);
            }
            Event::Eof => break,
            _ => {}
        }
    }
    if stack.len() != 1 {
        return Err("XML ends inside an element (truncated file?)".into());
    }
    Ok(stack.pop().expect("root"))
}

/// How a VTK XML file encodes its binary arrays, from the `<VTKFile>` attributes.
#[derive(Clone, Copy)]
pub(crate) struct Encoding {
    header_u64: bool,
    compressed: bool,
    pub little: bool,
}

impl Encoding {
    /// The encoding the `<VTKFile>` element states (only zlib compression is supported).
    pub fn of(vtk: &Node) -> Result<Self, String> {
        let compressed = match vtk.attr("compressor") {
            None | Some("") => false,
            Some("vtkZLibDataCompressor") => true,
            Some(c) => return Err(format!("compressor {c} is not supported (only zlib)")),
        };
        Ok(Encoding {
            header_u64: vtk.attr("header_type") == Some("UInt64"),
            compressed,
            little: vtk.attr("byte_order") != Some("BigEndian"),
        })
    }

    fn hsize(&self) -> usize {
        if self.header_u64 {
            8
        } else {
            4
        }
    }

    /// A size read from the file's header. A UInt64 beyond `usize` saturates, so that every
    /// later bound check refuses it instead of seeing a truncated small number.
    fn header_value(&self, b: &[u8]) -> usize {
        if self.header_u64 {
            usize::try_from(u64::from_bytes(b, self.little)).unwrap_or(usize::MAX)
        } else {
            u32::from_bytes(b, self.little) as usize
        }
    }

    /// The payload of an array stored in its element (`ascii` or `binary`); appended arrays
    /// need the file's appended block ([`VtkFile::array_payload`]).
    pub fn inline_payload(&self, node: &Node) -> Result<Payload, String> {
        self.inline_payload_sized(node, None)
    }

    /// [`Encoding::inline_payload`] of an array that must hold `expect` bytes (when given):
    /// a size header stating another size is refused before anything is allocated.
    pub fn inline_payload_sized(
        &self,
        node: &Node,
        expect: Option<usize>,
    ) -> Result<Payload, String> {
        let name = node.attr("Name").unwrap_or("?");
        let ctx = |e: String| format!("array `{name}`: {e}");
        match node.attr("format").unwrap_or("ascii") {
            "ascii" => Ok(Payload::Ascii(
                node.text.split_whitespace().map(str::to_string).collect(),
            )),
            "binary" => {
                let text: Vec<u8> = node
                    .text
                    .bytes()
                    .filter(|b| !b.is_ascii_whitespace())
                    .collect();
                self.binary_inline(&text, expect)
                    .map(Payload::Bytes)
                    .map_err(ctx)
            }
            f => Err(ctx(format!("unknown format `{f}`"))),
        }
    }

    fn binary_inline(&self, text: &[u8], expect: Option<usize>) -> Result<Vec<u8>, String> {
        let hs = self.hsize();
        let dec = |t: &[u8]| B64.decode(t).map_err(|e| format!("bad base64: {e}"));
        if !self.compressed {
            // Header and data are one base64 stream.
            let all = dec(text)?;
            let n = self.header_value(all.get(..hs).ok_or("truncated array")?);
            check_expected(n, expect)?;
            return hs
                .checked_add(n)
                .and_then(|end| all.get(hs..end))
                .map(|d| d.to_vec())
                .ok_or_else(|| format!("array says {n} bytes but holds {}", all.len() - hs));
        }
        // Header and data are encoded separately; the header's length depends on its first
        // entry (number of blocks).
        let b64len = |bytes: usize| bytes.div_ceil(3) * 4;
        let first = dec(text.get(..b64len(3 * hs)).ok_or("truncated header")?)?;
        let nblocks = self.header_value(first.get(..hs).ok_or("truncated header")?);
        // The header cannot be longer than the text that holds it.
        let hlen = nblocks
            .checked_add(3)
            .and_then(|n| n.checked_mul(hs))
            .filter(|&n| n <= text.len())
            .map(b64len)
            .ok_or_else(|| format!("header claims {nblocks} blocks, more than the array holds"))?;
        let header = dec(text.get(..hlen).ok_or("truncated header")?)?;
        let body = dec(&text[hlen..])?;
        self.inflate(&header, &body, expect)
    }

    /// Inflates zlib blocks. Every size comes from the file, so none is trusted: the header
    /// must hold `3 + nblocks` entries, the compressed sizes must fit in `body`, the total
    /// must not overflow, and no block may inflate past what its header entry says. The
    /// allocation is bounded by what the body can possibly inflate to (zlib's ratio is at
    /// most 1032:1), so a header claiming 2^40 bytes in a small file allocates nothing large.
    fn inflate(
        &self,
        header: &[u8],
        body: &[u8],
        expect: Option<usize>,
    ) -> Result<Vec<u8>, String> {
        const MAX_ZLIB_RATIO: usize = 1032;
        let hs = self.hsize();
        let h: Vec<usize> = header
            .chunks_exact(hs)
            .map(|c| self.header_value(c))
            .collect();
        let [nblocks, bsize, last] = match h.get(..3) {
            Some(&[a, b, c]) => [a, b, c],
            _ => return Err("truncated compression header".into()),
        };
        let sizes = nblocks
            .checked_add(3)
            .and_then(|n| h.get(3..n))
            .ok_or_else(|| format!("compression header lists fewer than its {nblocks} blocks"))?;
        if last > bsize {
            return Err(format!(
                "compression header: last block of {last} bytes exceeds the block size {bsize}"
            ));
        }
        let total = match nblocks {
            0 => Some(0),
            n => (n - 1)
                .checked_mul(bsize)
                .and_then(|t| t.checked_add(if last != 0 { last } else { bsize })),
        }
        .ok_or("compression header: uncompressed size overflows")?;
        check_expected(total, expect)?;
        let possible = body.len().saturating_mul(MAX_ZLIB_RATIO).saturating_add(64);
        if total > possible {
            return Err(format!(
                "compression header claims {total} bytes, but {} compressed bytes cannot \
                 inflate to more than {possible}",
                body.len()
            ));
        }
        let mut out = Vec::with_capacity(total);
        let mut pos = 0usize;
        for (k, &c) in sizes.iter().enumerate() {
            let end = pos.checked_add(c).ok_or("compressed sizes overflow")?;
            let chunk = body.get(pos..end).ok_or("compressed data truncated")?;
            pos = end;
            let before = out.len();
            let expect = if k + 1 == nblocks && last != 0 {
                last
            } else {
                bsize
            };
            // One byte more than expected is enough to tell a lying header.
            flate2::read::ZlibDecoder::new(chunk)
                .take(expect as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| format!("zlib: {e}"))?;
            if out.len() - before != expect {
                return Err(format!(
                    "block {k} inflates to {}{} bytes, header says {expect}",
                    if out.len() - before > expect {
                        "more than "
                    } else {
                        ""
                    },
                    out.len() - before
                ));
            }
        }
        Ok(out)
    }
}

/// A size header against the size the extent implies: checked before the array is
/// allocated, so a header claiming gigabytes in a small file (or a zlib bomb) is refused.
fn check_expected(stated: usize, expect: Option<usize>) -> Result<(), String> {
    match expect {
        Some(e) if e != stated => Err(format!(
            "its size header states {stated} bytes but the extent needs {e}"
        )),
        _ => Ok(()),
    }
}

/// A parsed VTK XML file with its appended-data block, if any.
pub(crate) struct VtkFile {
    pub root: Node,
    appended: Vec<u8>,
    appended_raw: bool,
    enc: Encoding,
}

impl VtkFile {
    pub fn open(path: &Path) -> Result<Self, String> {
        let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
        Self::parse(bytes).map_err(|e| format!("{}: {e}", path.display()))
    }

    fn parse(bytes: Vec<u8>) -> Result<Self, String> {
        // Raw appended data is not text: cut it out before parsing the XML.
        let (xml, appended, appended_raw) = match find(&bytes, b"<AppendedData") {
            Some(start) => {
                let tag_end =
                    start + find(&bytes[start..], b">").ok_or("unterminated <AppendedData> tag")?;
                let tag = String::from_utf8_lossy(&bytes[start..tag_end]).into_owned();
                let raw = tag.contains("\"raw\"");
                let underscore = tag_end
                    + find(&bytes[tag_end..], b"_").ok_or("appended data lacks its `_` marker")?;
                let end = rfind(&bytes, b"</AppendedData>")
                    .ok_or("appended data is not closed (truncated file?)")?;
                if end < underscore {
                    return Err("appended data is not closed (truncated file?)".into());
                }
                let mut xml = bytes[..tag_end + 1].to_vec();
                xml.extend_from_slice(&bytes[end..]);
                let data = bytes[underscore + 1..end].to_vec();
                (xml, data, raw)
            }
            None => (bytes, Vec::new(), false),
        };
        let text = String::from_utf8(xml).map_err(|_| "not a UTF-8 XML file")?;
        let root = parse_xml(&text)?;
        let vtk = root
            .find("VTKFile")
            .ok_or("no <VTKFile> element: not a VTK XML file")?;
        let enc = Encoding::of(vtk)?;
        Ok(VtkFile {
            root,
            appended: appended
                .iter()
                .copied()
                .filter(|b| appended_raw || !b.is_ascii_whitespace())
                .collect(),
            appended_raw,
            enc,
        })
    }

    /// The bytes of a binary or appended array (decompressed, in the file's byte order), or
    /// the whitespace-separated tokens of an ascii array.
    pub fn array_payload(&self, node: &Node) -> Result<Payload, String> {
        self.array_payload_sized(node, None)
    }

    /// [`VtkFile::array_payload`] of an array that must hold `expect` bytes (when given).
    pub fn array_payload_sized(
        &self,
        node: &Node,
        expect: Option<usize>,
    ) -> Result<Payload, String> {
        if node.attr("format") != Some("appended") {
            return self.enc.inline_payload_sized(node, expect);
        }
        let name = node.attr("Name").unwrap_or("?");
        let ctx = |e: String| format!("array `{name}`: {e}");
        let off: usize = node
            .attr("offset")
            .and_then(|o| o.parse().ok())
            .ok_or_else(|| ctx("appended array without offset".into()))?;
        self.appended_at(off, expect)
            .map(Payload::Bytes)
            .map_err(ctx)
    }

    fn appended_at(&self, off: usize, expect: Option<usize>) -> Result<Vec<u8>, String> {
        let enc = &self.enc;
        let hs = enc.hsize();
        if !self.appended_raw {
            // base64 appended data: each array is its own stream(s) starting at `off`.
            let tail = self
                .appended
                .get(off..)
                .ok_or("offset past the appended data")?;
            return enc.binary_inline(tail, expect);
        }
        let a = &self.appended;
        let at = |i: usize, n: usize| {
            i.checked_add(n)
                .and_then(|end| a.get(i..end))
                .ok_or("appended data truncated (or a size in its header is too large)")
        };
        if !enc.compressed {
            let n = enc.header_value(at(off, hs)?);
            check_expected(n, expect)?;
            return Ok(at(off + hs, n)?.to_vec());
        }
        let nblocks = enc.header_value(at(off, hs)?);
        let hlen = nblocks
            .checked_add(3)
            .and_then(|n| n.checked_mul(hs))
            .ok_or("compression header: block count overflows")?;
        let header = at(off, hlen)?;
        let csum = header[3 * hs..]
            .chunks_exact(hs)
            .try_fold(0usize, |acc, c| acc.checked_add(enc.header_value(c)))
            .ok_or("compressed sizes overflow")?;
        let body = at(off + header.len(), csum)?;
        enc.inflate(header, body, expect)
    }

    /// Decodes an array as numbers of its declared type.
    pub fn array_values(&self, node: &Node) -> Result<VolumeData, String> {
        self.array_values_sized(node, None)
    }

    /// [`VtkFile::array_values`] of an array that must hold `expect` bytes (when given).
    pub fn array_values_sized(
        &self,
        node: &Node,
        expect: Option<usize>,
    ) -> Result<VolumeData, String> {
        let payload = self.array_payload_sized(node, expect)?;
        payload.values(node, self.enc.little)
    }

    /// Decodes a `String` array.
    pub fn string_values(&self, node: &Node) -> Result<Vec<String>, String> {
        let bytes: Vec<u8> = match self.array_payload(node)? {
            Payload::Bytes(b) => b,
            Payload::Ascii(t) => t
                .iter()
                .map(|s| s.parse::<u8>())
                .collect::<Result<_, _>>()
                .map_err(|e| format!("string array: {e}"))?,
        };
        let mut v: Vec<String> = bytes
            .split(|&b| b == 0)
            .map(|s| String::from_utf8_lossy(s).into_owned())
            .collect();
        v.pop(); // after the last terminator
        Ok(v)
    }

    /// Field-data arrays by name.
    pub fn field_array(&self, name: &str) -> Option<&Node> {
        self.root
            .find("FieldData")?
            .children
            .iter()
            .find(|c| c.attr("Name") == Some(name))
    }
}

pub(crate) enum Payload {
    Bytes(Vec<u8>),
    Ascii(Vec<String>),
}

impl Payload {
    /// The values of array `node` (its `type` and `Name`), from its payload in byte order
    /// `little`.
    pub fn values(&self, node: &Node, little: bool) -> Result<VolumeData, String> {
        let ty = node.attr("type").unwrap_or("Float32");
        let name = node.attr("Name").unwrap_or("?");
        macro_rules! conv {
            ($t:ty, $variant:ident, $map:expr) => {{
                let v: Vec<$t> = match self {
                    Payload::Bytes(b) => from_bytes::<$t>(b, little),
                    Payload::Ascii(toks) => toks
                        .iter()
                        .map(|s| s.parse::<$t>())
                        .collect::<Result<_, _>>()
                        .map_err(|e| format!("array `{name}`: bad number: {e}"))?,
                };
                #[allow(clippy::redundant_closure_call)]
                VolumeData::$variant(($map)(v))
            }};
        }
        Ok(match ty {
            "UInt8" => conv!(u8, U8, |v| v),
            "Int8" => conv!(i8, I32, |v: Vec<i8>| v.into_iter().map(i32::from).collect()),
            "UInt16" => conv!(u16, U16, |v| v),
            "Int16" => conv!(i16, I32, |v: Vec<i16>| v
                .into_iter()
                .map(i32::from)
                .collect()),
            "Int32" => conv!(i32, I32, |v| v),
            "UInt32" => conv!(u32, F64, |v: Vec<u32>| v
                .into_iter()
                .map(f64::from)
                .collect()),
            "Int64" => conv!(i64, F64, |v: Vec<i64>| v
                .into_iter()
                .map(|x| x as f64)
                .collect()),
            "UInt64" => conv!(u64, F64, |v: Vec<u64>| v
                .into_iter()
                .map(|x| x as f64)
                .collect()),
            "Float32" => conv!(f32, F32, |v| v),
            "Float64" => conv!(f64, F64, |v| v),
            t => return Err(format!("array `{name}`: type {t} is not numeric")),
        })
    }
}

fn find(h: &[u8], n: &[u8]) -> Option<usize> {
    h.windows(n.len()).position(|w| w == n)
}
fn rfind(h: &[u8], n: &[u8]) -> Option<usize> {
    h.windows(n.len()).rposition(|w| w == n)
}

/// `N` whitespace-separated numbers of attribute `what` (value `s`), if it is given.
pub(crate) fn parse_nums<const N: usize>(
    s: Option<&str>,
    what: &str,
) -> Result<Option<[f64; N]>, String> {
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

/// The grid an `<ImageData>` element states: its whole extent, spacing and origin.
pub(crate) struct ImageGrid {
    ext: [i64; 6],
    spacing: Option<[f64; 3]>,
    origin: Option<[f64; 3]>,
}

impl ImageGrid {
    /// Reads `WholeExtent`, `Spacing` and `Origin`; a `Direction` must be the identity.
    pub fn of(img: &Node) -> Result<Self, String> {
        let ext: [f64; 6] =
            parse_nums(img.attr("WholeExtent"), "WholeExtent")?.ok_or("no WholeExtent")?;
        let spacing = parse_nums::<3>(img.attr("Spacing"), "Spacing")?;
        let origin = parse_nums::<3>(img.attr("Origin"), "Origin")?;
        if let Some(d) = parse_nums::<9>(img.attr("Direction"), "Direction")? {
            let id = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
            if d.iter().zip(id).any(|(a, b)| (a - b).abs() > 1e-12) {
                return Err("rotated images (Direction not identity) are not supported".into());
            }
        }
        Ok(ImageGrid {
            ext: ext.map(|e| e as i64),
            spacing,
            origin,
        })
    }

    /// Dims, spacing and origin of the voxels of a cell-data (or point-data) array: point
    /// data are voxel centres (dims = points, origin moved back by half a voxel).
    pub fn voxels(&self, is_cell: bool) -> ([usize; 3], Option<[f64; 3]>, Option<[f64; 3]>) {
        let (ext, spacing, mut origin) = (self.ext, self.spacing, self.origin);
        // saturating: an absurd extent becomes a huge count that size checks refuse
        let span = |a: usize| ext[2 * a + 1].saturating_sub(ext[2 * a]).max(0) as usize;
        let mut dims = [span(0), span(1), span(2)];
        if is_cell {
            // a 2-D image has a zero-thickness extent along z and one cell layer
            dims = dims.map(|d| d.max(1));
        } else {
            dims = dims.map(|d| d.saturating_add(1));
            if let (Some(o), Some(s)) = (origin.as_mut(), spacing) {
                for a in 0..3 {
                    o[a] -= 0.5 * s[a];
                }
            }
        }
        if let Some(o) = origin.as_mut() {
            // a piece extent starting above 0 shifts the first voxel
            for a in 0..3 {
                o[a] += ext[2 * a] as f64 * spacing.map(|s| s[a]).unwrap_or(0.0);
            }
        }
        (dims, spacing, origin)
    }
}

/// The array a `.vti` reader takes from a piece's cell and point arrays: the one named
/// `want` (a cell array before a point array), else the first cell array, else the first
/// point array; with "is cell data".
pub(crate) fn choose_array<'a, C, P>(
    cells: C,
    points: P,
    want: Option<&str>,
) -> Option<(&'a Node, bool)>
where
    C: IntoIterator<Item = &'a Node>,
    P: IntoIterator<Item = &'a Node>,
{
    let named = |a: &&Node| want.is_none() || a.attr("Name") == want;
    let mut cells = cells.into_iter().filter(named);
    let mut points = points.into_iter().filter(named);
    cells
        .next()
        .map(|a| (a, true))
        .or_else(|| points.next().map(|a| (a, false)))
}

/// The error of a `.vti` reader that finds no array to take.
pub(crate) fn no_array_error<'a>(
    array: Option<&str>,
    names: impl Iterator<Item = &'a str>,
) -> String {
    let names: Vec<&str> = names.collect();
    format!(
        "no array {} (arrays: {names:?})",
        array.map(|a| format!("`{a}`")).unwrap_or_default()
    )
}

/// `NumberOfComponents` of a data array (1 when not stated).
pub(crate) fn array_components(node: &Node) -> usize {
    node.attr("NumberOfComponents")
        .and_then(|c| c.parse().ok())
        .unwrap_or(1)
}

/// Bytes per value of a numeric VTK type.
pub(crate) fn vtk_type_size(t: &str) -> Option<usize> {
    Some(match t {
        "Int8" | "UInt8" => 1,
        "Int16" | "UInt16" => 2,
        "Int32" | "UInt32" | "Float32" => 4,
        "Int64" | "UInt64" | "Float64" => 8,
        _ => return None,
    })
}

/// Reads one array of a `.vti` as a [`Volume`]: `array` by name, or else the active cell
/// scalars, the first cell array, or the first point array. Point data is taken as voxel
/// centres (dims = points, origin moved back by half a voxel).
pub fn read_vti(path: &Path, array: Option<&str>) -> Result<Volume, String> {
    let f = VtkFile::open(path)?;
    let at = |e: String| format!("{}: {e}", path.display());
    let img = f
        .root
        .find("ImageData")
        .ok_or_else(|| at("no <ImageData>: not a .vti image".into()))?;
    let grid = ImageGrid::of(img).map_err(at)?;
    let piece = img.child("Piece").ok_or_else(|| at("no <Piece>".into()))?;
    if img.children.iter().filter(|c| c.name == "Piece").count() > 1 {
        return Err(at("multi-piece images are not supported".into()));
    }
    let arrays = |tag: &str| -> Vec<&Node> {
        piece
            .child(tag)
            .map(|n| {
                n.children
                    .iter()
                    .filter(|c| c.name == "DataArray")
                    .collect()
            })
            .unwrap_or_default()
    };
    let (cells, points) = (arrays("CellData"), arrays("PointData"));
    let active = piece
        .child("CellData")
        .and_then(|c| c.attr("Scalars"))
        .map(str::to_string);
    let (node, is_cell) = choose_array(
        cells.iter().copied(),
        points.iter().copied(),
        array.or(active.as_deref()),
    )
    .ok_or_else(|| {
        let names = cells.iter().chain(&points).filter_map(|a| a.attr("Name"));
        at(no_array_error(array, names))
    })?;
    let (dims, spacing, origin) = grid.voxels(is_cell);
    let components = array_components(node);
    let expect = grainpipe_core::checked_product(&[dims[0], dims[1], dims[2], components])
        .ok_or_else(|| {
            at(format!(
                "extent {dims:?} x {components} components overflows"
            ))
        })?;
    // Binary payloads must hold exactly what the extent needs, and no more than the memory
    // available may be allocated for them: checked before decoding (or inflating) anything.
    let elem = vtk_type_size(node.attr("type").unwrap_or("Float32"));
    let expect_bytes = elem.and_then(|b| expect.checked_mul(b));
    if node.attr("format").unwrap_or("ascii") != "ascii" {
        crate::volume::check_declared(
            &format!("array `{}`", node.attr("Name").unwrap_or("?")),
            expect_bytes.map(|b| b as u64),
        )
        .map_err(at)?;
    }
    let data = f.array_values_sized(node, expect_bytes).map_err(at)?;
    if data.len() != expect {
        return Err(at(format!(
            "array `{}` holds {} values; extent {dims:?} x {components} components needs {expect}",
            node.attr("Name").unwrap_or("?"),
            data.len()
        )));
    }
    let name = node.attr("Name").unwrap_or("values").to_string();
    let strings = |n: &str| -> Result<Option<Vec<String>>, String> {
        f.field_array(n)
            .map(|a| f.string_values(a))
            .transpose()
            .map_err(at)
    };
    let mut phases = Vec::new();
    if let (Some(ids), Some(names)) = (f.field_array("phase_ids"), strings("phase_names")?) {
        let ids = f.array_values(ids).map_err(at)?;
        if ids.len() == names.len() {
            phases = (0..ids.len())
                .map(|i| Phase {
                    id: ids.get(i) as u8,
                    name: names[i].clone(),
                })
                .collect();
        }
    }
    let unit = strings("unit")?
        .and_then(|u| u.into_iter().next())
        .unwrap_or_default();
    let mut periodic = [false; 3];
    if let Some(p) = f.field_array("periodic") {
        let p = f.array_values(p).map_err(at)?;
        if p.len() == 3 {
            periodic = [0, 1, 2].map(|a| p.get(a) != 0.0);
        }
    }
    let convention = strings("component_convention")?
        .and_then(|c| c.into_iter().next())
        .and_then(|c| ComponentConvention::from_name(&c))
        .unwrap_or_default();
    Ok(Volume {
        name,
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

#[cfg(test)]
mod tests {
    use super::*;
    use grainpipe_core::{
        Body, BodyAttribute, BodyShape, Clump, ClumpLibrary, ClumpSphere, Contact, Domain,
    };

    fn node_named<'a>(n: &'a Node, tag: &str, name: &str) -> &'a Node {
        fn walk<'a>(n: &'a Node, tag: &str, name: &str) -> Option<&'a Node> {
            if n.name == tag && n.attr("Name") == Some(name) {
                return Some(n);
            }
            n.children.iter().find_map(|c| walk(c, tag, name))
        }
        walk(n, tag, name).unwrap_or_else(|| panic!("no {tag} {name}"))
    }

    fn f64s(f: &VtkFile, tag: &str, name: &str) -> Vec<f64> {
        let d = f.array_values(node_named(&f.root, tag, name)).unwrap();
        (0..d.len()).map(|i| d.get(i)).collect()
    }

    #[test]
    fn vtp_packing_expands_clumps_and_replicates_attributes() {
        let mut p = Packing::new(Domain::boxed([0.0; 3], [1.0; 3], [false; 3]));
        p.bodies.push(Body::sphere([0.1, 0.2, 0.3], 0.05));
        let mut b = Body::sphere([0.5, 0.5, 0.5], 0.0);
        b.shape = BodyShape::Clump { index: 0 };
        // 180 degrees about z: offset (+0.1, 0, 0) lands at x = 0.4
        b.orientation = [0.0, 0.0, 0.0, 1.0];
        b.layer = 2;
        p.bodies.push(b);
        p.library = Some(ClumpLibrary {
            clumps: vec![Clump {
                spheres: vec![
                    ClumpSphere {
                        offset: [0.1, 0.0, 0.0],
                        radius: 0.07,
                    },
                    ClumpSphere {
                        offset: [0.0, 0.0, 0.1],
                        radius: 0.06,
                    },
                ],
                volume: 1.0,
                bounding_radius: 0.2,
                principal_inertia: [1.0; 3],
                principal_axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                source: String::new(),
            }],
            source: String::new(),
        });
        p.attributes.insert(
            "T".into(),
            BodyAttribute {
                unit: "K".into(),
                values: vec![10.0, 20.0],
            },
        );
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.vtp");
        write_vtp(&Artifact::Packing(p), &path, &Provenance::default()).unwrap();
        let f = VtkFile::open(&path).unwrap();
        assert_eq!(f64s(&f, "DataArray", "radius"), [0.05, 0.07, 0.06]);
        assert_eq!(f64s(&f, "DataArray", "body_id"), [0.0, 1.0, 1.0]);
        assert_eq!(f64s(&f, "DataArray", "layer"), [0.0, 2.0, 2.0]);
        assert_eq!(f64s(&f, "DataArray", "T"), [10.0, 20.0, 20.0]);
        let pts = f64s(&f, "DataArray", "Points");
        let want = [0.1, 0.2, 0.3, 0.4, 0.5, 0.5, 0.5, 0.5, 0.6];
        // one rotation of unit vectors: exact to a few ulps
        assert!(
            pts.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-15),
            "{pts:?}"
        );
        assert_eq!(f64s(&f, "DataArray", "offsets"), [1.0, 2.0, 3.0]);
        assert_eq!(f64s(&f, "DataArray", "clump_index"), [-1.0, 0.0, 0.0]);
    }

    /// A clump body at x = 0.95 in a unit box periodic along x only, spheres offset
    /// +-0.1 along x and +0.1 along y (y not periodic, so the y offset is never wrapped).
    fn straddling_packing() -> Packing {
        let mut p = Packing::new(Domain::boxed([0.0; 3], [1.0; 3], [true, false, false]));
        let mut b = Body::sphere([0.95, 0.95, 0.5], 0.0);
        b.shape = BodyShape::Clump { index: 0 };
        p.bodies.push(b);
        p.library = Some(ClumpLibrary {
            clumps: vec![Clump {
                spheres: [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]
                    .map(|offset| ClumpSphere {
                        offset,
                        radius: 0.05,
                    })
                    .to_vec(),
                volume: 1.0,
                bounding_radius: 0.15,
                principal_inertia: [1.0; 3],
                principal_axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                source: String::new(),
            }],
            source: String::new(),
        });
        p
    }

    #[test]
    fn vtp_periodic_modes_keep_wrap_or_clip_spheres_outside_the_box() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.vtp");
        let a = Artifact::Packing(straddling_packing());
        let xs = |mode| {
            write_vtp_with(&a, &path, &Provenance::default(), mode).unwrap();
            let f = VtkFile::open(&path).unwrap();
            let pts = f64s(&f, "DataArray", "Points");
            let x: Vec<f64> = pts.chunks(3).map(|p| p[0]).collect();
            let y: Vec<f64> = pts.chunks(3).map(|p| p[1]).collect();
            (x, y, f64s(&f, "DataArray", "radius"))
        };
        let close = |a: &[f64], b: &[f64]| {
            a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12)
        };
        let (x, y, _) = xs(PeriodicSpheres::AsIs);
        assert!(
            close(&x, &[1.05, 0.85, 0.95]) && close(&y, &[0.95, 0.95, 1.05]),
            "{x:?}"
        );
        // wrap: 1.05 -> 0.05 along periodic x; y = 1.05 stays (y is not periodic).
        let (x, y, r) = xs(PeriodicSpheres::Wrap);
        assert!(
            close(&x, &[0.05, 0.85, 0.95]) && close(&y, &[0.95, 0.95, 1.05]),
            "{x:?}"
        );
        assert_eq!(r, [0.05; 3]);
        // clip: the sphere at x = 1.05 goes; the one at y = 1.05 stays (y not periodic).
        let (x, y, r) = xs(PeriodicSpheres::Clip);
        assert!(
            close(&x, &[0.85, 0.95]) && close(&y, &[0.95, 1.05]),
            "{x:?}"
        );
        assert_eq!(r.len(), 2);
    }

    #[test]
    fn wrap_maps_the_upper_face_to_the_lower() {
        let w = wrap_into([1.0, -0.25, 2.5], [0.0; 3], [1.0; 3], [true; 3]);
        assert_eq!(w, [0.0, 0.75, 0.5]);
        // A tiny negative offset rounds to exactly the box length; it must land inside.
        let w = wrap_into([-1e-300, 0.5, 0.5], [0.0; 3], [1.0; 3], [true; 3]);
        assert!((0.0..1.0).contains(&w[0]), "{w:?}");
    }

    #[test]
    fn vtp_graph_draws_contacts_then_extra_bonds() {
        let g = ContactGraph {
            contacts: vec![Contact {
                i: 0,
                j: 1,
                gap: -1e-6,
            }],
            faces: Default::default(),
            bonds: vec![[1, 0], [1, 2]],
            bond_attributes: [(
                "stretch".to_string(),
                grainpipe_core::BodyAttribute {
                    unit: String::new(),
                    values: vec![0.25, 0.5],
                },
            )]
            .into_iter()
            .collect(),
            positions: vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]],
            radii: vec![0.5, 0.5, 0.25],
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("g.vtp");
        write_vtp(
            &Artifact::ContactGraph(g.clone()),
            &path,
            &Provenance::default(),
        )
        .unwrap();
        let f = VtkFile::open(&path).unwrap();
        assert_eq!(f64s(&f, "DataArray", "connectivity"), [0.0, 1.0, 1.0, 2.0]);
        assert_eq!(f64s(&f, "DataArray", "bonded"), [1.0, 1.0]);
        let gap = f64s(&f, "DataArray", "gap");
        assert_eq!(gap[0], -1e-6);
        assert!(gap[1].is_nan());
        assert_eq!(f64s(&f, "DataArray", "coordination"), [1.0, 1.0, 0.0]);
        assert_eq!(f64s(&f, "DataArray", "radius"), [0.5, 0.5, 0.25]);
        // The bonded contact (0, 1) carries bond 0's value, the extra line bond 1's.
        assert_eq!(f64s(&f, "DataArray", "stretch"), [0.25, 0.5]);
        // an attribute with the wrong length is refused
        let mut short = g.clone();
        short.bond_attributes[0].values.pop();
        let e = write_vtp(
            &Artifact::ContactGraph(short),
            &path,
            &Provenance::default(),
        )
        .unwrap_err();
        assert!(e.contains("`stretch` has 1 values for 2 bonds"), "{e}");
        // radii must match the positions
        let mut few = g.clone();
        few.radii.pop();
        let e = write_vtp(&Artifact::ContactGraph(few), &path, &Provenance::default()).unwrap_err();
        assert!(e.contains("2 radii for 3 positions"), "{e}");
        // a pair past the positions is refused
        let mut bad = g;
        bad.contacts[0].j = 9;
        let e = write_vtp(&Artifact::ContactGraph(bad), &path, &Provenance::default()).unwrap_err();
        assert!(e.contains("(0, 9)"), "{e}");
    }

    #[test]
    fn pvd_writes_frames_then_collection() {
        let img = |v: u8| {
            Artifact::PhaseImage(grainpipe_core::PhaseImage {
                grid: grainpipe_core::Grid {
                    dims: [2, 1, 1],
                    spacing: [1.0; 3],
                    origin: [0.0; 3],
                    periodic: [false; 3],
                },
                labels: vec![v, 0],
                phases: vec![],
            })
        };
        let s = Series {
            frames: vec![(0.0, img(1)), (0.25, img(2)), (1.5, img(3))],
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.pvd");
        write_pvd(&Artifact::Series(s), &path, &Provenance::default()).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let root = parse_xml(&text).unwrap();
        let sets: Vec<&Node> = root.find("Collection").unwrap().children.iter().collect();
        assert_eq!(sets.len(), 3);
        for (k, (t, set)) in [0.0, 0.25, 1.5].iter().zip(sets).enumerate() {
            assert_eq!(set.attr("timestep").unwrap().parse::<f64>().unwrap(), *t);
            let rel = set.attr("file").unwrap();
            assert!(
                rel.starts_with("run_frames_") && rel.ends_with(&format!("/run_{k:04}.vti")),
                "{rel}"
            );
            let file = dir.path().join(rel);
            let v = read_vti(&file, None).unwrap();
            assert_eq!(v.data, VolumeData::U8(vec![k as u8 + 1, 0]));
        }
        // mixed kinds are refused before anything is written
        let mixed = Series {
            frames: vec![(0.0, img(1)), (1.0, Artifact::Table(Default::default()))],
        };
        let p2 = dir.path().join("mixed.pvd");
        assert!(write_pvd(&Artifact::Series(mixed), &p2, &Provenance::default()).is_err());
        assert!(!p2.exists() && !dir.path().join("mixed_0000.vti").exists());
    }

    /// Issue 17: a series is replaced as a set. A rewrite that fails after some frames
    /// (standing in for a kill) leaves the old `.pvd` naming only old, complete frames; a
    /// successful rewrite leaves one frame folder.
    #[test]
    fn pvd_series_is_replaced_as_a_set() {
        let img = |v: u8, n: usize| {
            Artifact::PhaseImage(grainpipe_core::PhaseImage {
                grid: grainpipe_core::Grid {
                    dims: [2, 1, 1],
                    spacing: [1.0; 3],
                    origin: [0.0; 3],
                    periodic: [false; 3],
                },
                labels: vec![v; n],
                phases: vec![],
            })
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.pvd");
        let frames = |v: u8| Series {
            frames: (0..3).map(|k| (k as f64, img(v, 2))).collect(),
        };
        write_pvd(&Artifact::Series(frames(1)), &path, &Provenance::default()).unwrap();
        // The third frame is malformed: the write stops after two frames.
        let mut broken = frames(2);
        broken.frames[2].1 = img(2, 5);
        assert!(write_pvd(&Artifact::Series(broken), &path, &Provenance::default()).is_err());
        let read_all = || -> Vec<VolumeData> {
            let text = std::fs::read_to_string(&path).unwrap();
            let root = parse_xml(&text).unwrap();
            root.find("Collection")
                .unwrap()
                .children
                .iter()
                .map(|set| {
                    read_vti(&dir.path().join(set.attr("file").unwrap()), None)
                        .unwrap()
                        .data
                })
                .collect()
        };
        assert_eq!(read_all(), vec![VolumeData::U8(vec![1, 1]); 3], "mixed set");
        write_pvd(&Artifact::Series(frames(3)), &path, &Provenance::default()).unwrap();
        assert_eq!(read_all(), vec![VolumeData::U8(vec![3, 3]); 3]);
        let folders = std::fs::read_dir(dir.path())
            .unwrap()
            .filter(|e| e.as_ref().unwrap().path().is_dir())
            .count();
        assert_eq!(folders, 1, "earlier frame folders are removed");
    }
}
