//! Import stages: a volume from a raw file, an HDF5 dataset, a NetCDF variable, a `.vti`
//! array or a TIFF stack, as a PhaseImage (`as: phase_image`, labels 0..=255) or a Field
//! (`as: field`).
//!
//! Preflight reads only the file's header (raw: its size; TIFF: every page header) through
//! [`crate::headers`] and announces the exact grid of the output; the header and the grid go
//! to `run` in the plan, so `run` reads the voxel values and takes the geometry worked out
//! once. Relative paths are relative to the current working directory. Only the output chosen
//! by `as` is produced: `image` for a phase image, `field` for a field.

use crate::headers::{hdf5_header, netcdf_header, volume_geometry, vti_header, Header};
use crate::raw::{probe_raw, read_raw, Endian, RawDtype, RawLayout};
use crate::volume::{LabelScan, Volume};
use crate::{netcdf_io, vtk_xml};
use grainpipe_core::params::{choice_schema, choice_type_name, serde_word};
use grainpipe_core::units::{Length, Q};
use grainpipe_core::*;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::path::Path;

/// What the imported array becomes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum ImportAs {
    /// Integer labels 0..=255.
    #[default]
    PhaseImage,
    /// Values with a unit.
    Field,
}

/// One length for all three axes, or one per axis (x, y, z).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Lengths3 {
    One(Q<Length>),
    Three([Q<Length>; 3]),
}

impl Lengths3 {
    pub fn si(self) -> [f64; 3] {
        match self {
            Lengths3::One(q) => [q.si(); 3],
            Lengths3::Three(q) => q.map(|x| x.si()),
        }
    }
}

impl ParamType for Lengths3 {
    fn type_name() -> String {
        "length or [x, y, z]".into()
    }
    fn unit() -> &'static str {
        "m"
    }
    fn schema() -> Value {
        let q = <Q<Length> as ParamType>::schema();
        json!({"anyOf": [q.clone(), {"type": "array", "items": q, "minItems": 3, "maxItems": 3}]})
    }
}

/// Unit-only enums of the raw reader, described as choices by their serde names.
macro_rules! choice_param {
    ($t:ty, [$($v:expr),*]) => {
        impl ParamType for $t {
            fn type_name() -> String {
                choice_type_name(&Self::choice_words())
            }
            fn schema() -> Value {
                choice_schema(&Self::choice_words())
            }
        }
        impl ChoiceWords for $t {
            fn choice_words() -> Vec<(String, &'static str)> {
                [$($v),*].iter().map(|v| (serde_word(v), "")).collect()
            }
        }
    };
}

trait ChoiceWords {
    fn choice_words() -> Vec<(String, &'static str)>;
}

choice_param!(
    RawDtype,
    [
        RawDtype::U8,
        RawDtype::U16,
        RawDtype::I32,
        RawDtype::F32,
        RawDtype::F64
    ]
);
choice_param!(Endian, [Endian::Little, Endian::Big]);

/// The parameters every import stage ends with: what the array becomes, where its grid
/// starts and the unit of a field.
#[params]
pub struct ImportOptions {
    /// lower grid corner [x, y, z]; overrides the file's (default 0)
    #[param(ty = "[x, y, z]")]
    pub origin: Option<Lengths3>,
    /// `phase_image` (integer labels 0..=255) or `field`
    #[serde(rename = "as")]
    #[param(default = ImportAs::PhaseImage)]
    pub as_: ImportAs,
    /// unit of a field (overrides the file's)
    #[param(ty = "unit string")]
    pub unit: String,
    /// which axes [x, y, z] the image repeats along (a packing's box, a periodic simulation
    /// cell); overrides the file's. Default: what the file states (grainpipe's own .h5, .nc
    /// and .vti record it), else not periodic, which is what a CT scan or a cut sample is.
    /// The FFT and Stokes solvers need a `boundary:` for a non-periodic axis.
    #[param(ty = "[x, y, z]")]
    pub periodic: Option<[bool; 3]>,
}

/// What preflight learned from the file header and run needs: the header (to check the data
/// read against it) and the output grid (file geometry with the overrides applied).
#[derive(Clone, Debug, PartialEq)]
pub struct ImportPlan {
    pub header: Header,
    pub grid: Grid,
}

fn outputs() -> Vec<PortSpec> {
    vec![
        PortSpec::optional(
            "image",
            ArtifactKind::PhaseImage,
            "the labels (only with `as: phase_image`)",
        ),
        PortSpec::optional(
            "field",
            ArtifactKind::Field,
            "the values (only with `as: field`)",
        ),
    ]
}

fn port(as_: ImportAs) -> (&'static str, ArtifactKind) {
    match as_ {
        ImportAs::PhaseImage => ("image", ArtifactKind::PhaseImage),
        ImportAs::Field => ("field", ArtifactKind::Field),
    }
}

/// The file must exist and be readable before any format-specific check.
fn check_path(path: &str) -> Result<&Path, StageError> {
    if path.is_empty() {
        return Err(StageError::param("path", "no input file given"));
    }
    let p = Path::new(path);
    let meta = std::fs::metadata(p).map_err(|e| {
        StageError::param(
            "path",
            format!(
                "{}: {e} (relative paths start at {})",
                p.display(),
                std::env::current_dir()
                    .map(|d| d.display().to_string())
                    .unwrap_or_default()
            ),
        )
    })?;
    if !meta.is_file() {
        return Err(StageError::param(
            "path",
            format!("{} is not a file", p.display()),
        ));
    }
    std::fs::File::open(p)
        .map_err(|e| StageError::param("path", format!("{}: {e}", p.display())))?;
    Ok(p)
}

fn check_lengths(key: &str, v: Option<Lengths3>, positive: bool) -> Result<(), StageError> {
    if let Some(v) = v {
        let s = v.si();
        if s.iter().any(|x| !x.is_finite() || (positive && *x <= 0.0)) {
            return Err(StageError::param(
                key,
                format!(
                    "{s:?} m: must be {} lengths",
                    if positive { "positive" } else { "finite" }
                ),
            ));
        }
    }
    Ok(())
}

/// Common preflight: checks the header against `as`, works out the output grid (the file's
/// geometry, overridden by `spacing`/`origin`), estimates memory (the array as stored plus
/// the output) and announces the selected output on that grid.
///
/// The estimate is what the readers hold at their peak: the array as stored, the values as
/// read (widened to the reader's type), the output, and `file_bytes` for readers that hold
/// the file itself (a `.vti` is parsed in memory). It is checked against the memory available
/// before anything runs, so a small file declaring a huge (or hugely compressed) array is
/// refused with exit 2 instead of aborting on allocation.
fn preflight_common(
    info: &StageInfo,
    header: Header,
    spacing: Option<Lengths3>,
    o: &ImportOptions,
    file_bytes: u64,
) -> Result<Preflight<ImportPlan>, StageError> {
    let h = &header.probe;
    check_lengths("spacing", spacing, true)?;
    check_lengths("origin", o.origin, false)?;
    if o.origin.is_none() {
        if let Some(origin) = h.origin.filter(|x| x.iter().any(|v| !v.is_finite())) {
            return Err(StageError::param(
                "origin",
                format!(
                    "the file's origin {origin:?} m is not three finite lengths; set `origin` \
                     explicitly, e.g. `origin: [0, 0, 0]`"
                ),
            ));
        }
    }
    if o.as_ == ImportAs::PhaseImage && h.components != 1 {
        return Err(StageError::param(
            "as",
            format!(
                "the array has {} components; a phase image needs one label per voxel (use `as: field`)",
                h.components
            ),
        ));
    }
    let [x, y, z] = h.dims;
    let n = grainpipe_core::checked_product(&[x, y, z, h.components])
        .filter(|n| n.checked_mul(h.elem_bytes + 8).is_some())
        .ok_or_else(|| {
            StageError::param(
                "path",
                format!(
                    "the array's dims {:?} x {} components overflow; the header is corrupt",
                    h.dims, h.components
                ),
            )
        })?;
    if n == 0 {
        return Err(StageError::param(
            "path",
            format!("the array is empty (dims {:?})", h.dims),
        ));
    }
    let spacing = spacing.map(|s| s.si()).or(h.spacing).ok_or_else(|| {
        StageError::param(
            "spacing",
            "the file gives no voxel spacing; set `spacing` explicitly",
        )
    })?;
    if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(StageError::param(
            "spacing",
            format!("the file's spacing {spacing:?} m is not three positive lengths; set `spacing` explicitly"),
        ));
    }
    let grid = Grid {
        dims: h.dims,
        spacing,
        origin: o.origin.map(|o| o.si()).or(h.origin).unwrap_or([0.0; 3]),
        periodic: o.periodic.unwrap_or(header.periodic),
    };
    let out_bytes = match o.as_ {
        ImportAs::PhaseImage => 1,
        ImportAs::Field if h.elem_bytes == 4 && h.dtype.contains("32") => 4,
        ImportAs::Field => 8,
    };
    let (name, kind) = port(o.as_);
    let per_value =
        h.elem_bytes + crate::volume::volume_value_bytes(&h.dtype, h.elem_bytes) + out_bytes;
    let bytes = (n as u64)
        .saturating_mul(per_value as u64)
        .saturating_add(file_bytes);
    let mut pf = Preflight::from_info(info, bytes);
    pf.outputs.retain(|k, _| k == name);
    Ok(pf
        .announce(name, ArtifactMeta::on_grid(kind, grid.clone()))
        .with_plan(ImportPlan { header, grid }))
}

/// Checks the volume read against the header preflight read (`geometry`: also the spacing,
/// origin and periodic axes, for readers that take them from the file), puts it on the
/// planned grid, applies the unit and converts.
fn finish(
    mut v: Volume,
    plan: &ImportPlan,
    path: &str,
    o: &ImportOptions,
    geometry: bool,
) -> Result<Outputs, StageError> {
    let h = &plan.header;
    let read = volume_geometry(&v);
    let agrees = if geometry {
        same_geometry(&read, &h.geometry())
    } else {
        (read.0, read.1) == (h.probe.dims, h.probe.components)
    };
    if !agrees {
        return Err(StageError::failed(format!(
            "{path}: the data does not match the header read before running (changed since?): \
             header {:?}, data {read:?}",
            h.geometry()
        )));
    }
    v.spacing = Some(plan.grid.spacing);
    v.origin = Some(plan.grid.origin);
    v.periodic = plan.grid.periodic;
    if !o.unit.is_empty() {
        v.unit = o.unit.clone();
    }
    if o.as_ == ImportAs::PhaseImage {
        check_labels(&v).map_err(|e| StageError::failed(format!("{path}: {e}")))?;
    }
    let art = match o.as_ {
        ImportAs::PhaseImage => v.into_phase_image().map(Artifact::PhaseImage),
        ImportAs::Field => v.into_field().map(Artifact::Field),
    }
    .map_err(|e| StageError::failed(format!("{path}: {e}")))?;
    let mut out = Outputs::new();
    out.insert(port(o.as_).0.to_string(), art);
    Ok(out)
}

/// Header and data agree, floats compared bit for bit (a NaN the file states is the same NaN
/// when read again, not "changed since").
fn same_geometry(a: &crate::headers::Geometry, b: &crate::headers::Geometry) -> bool {
    let bits = |v: Option<[f64; 3]>| v.map(|a| a.map(f64::to_bits));
    (a.0, a.1, bits(a.2), bits(a.3), a.4) == (b.0, b.1, bits(b.2), bits(b.3), b.4)
}

/// Arrays up to this size (as stored, declared by the header) are scanned at preflight to
/// check that their values are labels, so a wrong `as:` fails before any stage runs; larger
/// ones are checked at run time, after the memory check. The scan streams (blocks of
/// [`SCAN_BLOCK_BYTES`]) where the format allows it.
const PREFLIGHT_READ_BYTES: u64 = 256 << 20;

/// Bytes of one block of a streamed label scan.
pub(crate) const SCAN_BLOCK_BYTES: usize = 8 << 20;

/// The first voxel whose value is not a phase label (an integer 0..=255), as (x, y, z) and
/// the value, with what to do about it.
fn check_labels(v: &Volume) -> Result<(), String> {
    if matches!(v.data, crate::volume::VolumeData::U8(_)) || v.components != 1 {
        return Ok(());
    }
    let mut scan = LabelScan::default();
    scan.feed((0..v.data.len()).map(|i| v.data.get(i)));
    scan.result(v.dims)
}

/// Scans the values at preflight when the array the header declares is small enough
/// (`as: phase_image` only; 8-bit unsigned arrays hold labels whatever their values) and
/// checks that they are labels; the error goes to the `as` key. `scan` feeds the values to
/// the [`LabelScan`] block by block. Nothing is read for an array larger than
/// [`PREFLIGHT_READ_BYTES`]: the sizes in a header are not trusted before the memory check.
fn preflight_labels(
    path: &Path,
    o: &ImportOptions,
    h: &Header,
    scan: impl FnOnce(&mut LabelScan) -> Result<(), String>,
) -> Result<(), StageError> {
    let p = &h.probe;
    if o.as_ != ImportAs::PhaseImage
        || p.components != 1
        || crate::volume::volume_value_bytes(&p.dtype, p.elem_bytes) == 1
    {
        return Ok(());
    }
    let declared =
        grainpipe_core::checked_product(&[p.dims[0], p.dims[1], p.dims[2], p.elem_bytes]);
    if declared.is_none_or(|b| b as u64 > PREFLIGHT_READ_BYTES) {
        return Ok(());
    }
    let mut s = LabelScan::default();
    scan(&mut s).map_err(|e| StageError::param("path", e))?;
    s.result(p.dims)
        .map_err(|e| StageError::param("as", format!("{}: {e}", path.display())))
}

/// Every dataset path in an HDF5 file, for "no such dataset" messages.
fn hdf5_datasets(path: &Path) -> Vec<String> {
    fn walk(g: &hdf5_metno::Group, prefix: &str, out: &mut Vec<String>) {
        for name in g.member_names().unwrap_or_default() {
            let full = format!("{prefix}{name}");
            if let Ok(sub) = g.group(&name) {
                walk(&sub, &format!("{full}/"), out);
            } else if g.dataset(&name).is_ok() {
                out.push(full);
            }
        }
    }
    let mut out = Vec::new();
    if let Ok(f) = hdf5_metno::File::open(path) {
        walk(&f, "", &mut out);
    }
    out
}

/// A dataset name that is not in the file: which datasets are, and the closest one.
fn missing_dataset(path: &Path, dataset: &str, e: String) -> String {
    let all = hdf5_datasets(path);
    if dataset.is_empty() || all.is_empty() || all.iter().any(|d| d == dataset) {
        return e;
    }
    let hint = match grainpipe_core::registry::closest(dataset, all.iter().map(|s| s.as_str())) {
        Some(c) => format!("; did you mean `{c}`?"),
        None => String::new(),
    };
    format!(
        "{}: no dataset `{dataset}`; the file holds {}{hint}",
        path.display(),
        all.iter()
            .map(|d| format!("`{d}`"))
            .collect::<Vec<_>>()
            .join(", ")
    )
}

// ---------------------------------------------------------------------------------------

#[params]
pub struct RawParams {
    /// input file (relative to the working directory)
    #[param(file, ty = "path")]
    pub path: String,
    /// voxels along x, y, z
    #[param(ty = "[nx, ny, nz]")]
    pub dims: [usize; 3],
    /// element type: u8, u16, i32, f32 or f64
    // The choice words are the Rust type names the registry's check refuses in a type column.
    #[param(ty = "element type name", default = RawDtype::U8)]
    pub dtype: RawDtype,
    /// byte order
    #[param(default = Endian::Little)]
    pub endian: Endian,
    /// bytes to skip at the start of the file
    pub header_bytes: u64,
    /// voxel size (required)
    #[param(ty = "length or [x, y, z]")]
    pub spacing: Option<Lengths3>,
    #[param(flatten)]
    pub options: ImportOptions,
}

impl RawParams {
    fn layout(&self) -> RawLayout {
        RawLayout {
            dims: self.dims,
            dtype: self.dtype,
            endian: self.endian,
            header_bytes: self.header_bytes,
        }
    }
}

pub struct ImportRaw;

impl TypedStage for ImportRaw {
    type Params = RawParams;
    type Plan = ImportPlan;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "import.raw",
            "1.1.0",
            "Reads a headerless raw volume (x fastest, then y, then z) whose dims, element \
             type, byte order and voxel size are given here; preflight checks the file size.",
        )
        .outputs(outputs())
    }

    fn preflight(
        &self,
        p: &RawParams,
        _: &InputMetas,
    ) -> Result<Preflight<ImportPlan>, StageError> {
        if p.dims.contains(&0) {
            return Err(StageError::param(
                "dims",
                format!(
                    "{:?}: give the number of voxels along x, y, z (all > 0)",
                    p.dims
                ),
            ));
        }
        if p.spacing.is_none() {
            return Err(StageError::param(
                "spacing",
                "a raw file has no geometry: give the voxel size, e.g. `spacing: 10 um`",
            ));
        }
        let path = check_path(&p.path)?;
        let probe = probe_raw(path, &p.layout()).map_err(|e| StageError::param("dims", e))?;
        let pf = preflight_common(&self.info(), probe.into(), p.spacing, &p.options, 0)?;
        preflight_labels(path, &p.options, &pf.plan.header, |s| {
            crate::raw::scan_raw(path, &p.layout(), s)
        })?;
        Ok(pf)
    }

    fn run(
        &self,
        p: &RawParams,
        plan: &ImportPlan,
        _: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        let g = &plan.grid;
        let v = read_raw(Path::new(&p.path), &p.layout(), g.spacing, g.origin)
            .map_err(StageError::failed)?;
        finish(v, plan, &p.path, &p.options, false)
    }
}

// ---------------------------------------------------------------------------------------

/// An import of one named array of a self-describing file: `$key` names the array, `$header`
/// reads the file's header, `$read` the array.
/// `$scan` feeds the array's values to a [`LabelScan`] (streaming where the format allows),
/// `$held` gives the bytes of the file the reader holds in memory besides the array.
macro_rules! named_import {
    ($stage:ident, $params:ident, $id:expr, $key:ident, $key_doc:tt, $doc:expr,
     $header:expr, $read:expr, $scan:expr, $held:expr) => {
        #[params]
        pub struct $params {
            /// input file (relative to the working directory)
            #[param(file, ty = "path")]
            pub path: String,
            #[doc = $key_doc]
            pub $key: String,
            /// voxel size: one length or [x, y, z]; overrides the file's
            #[param(ty = "length or [x, y, z]")]
            pub spacing: Option<Lengths3>,
            #[param(flatten)]
            pub options: ImportOptions,
        }

        pub struct $stage;

        impl TypedStage for $stage {
            type Params = $params;
            type Plan = ImportPlan;
            fn info(&self) -> StageInfo {
                StageInfo::new($id, "1.1.0", $doc).outputs(outputs())
            }

            fn preflight(
                &self,
                p: &$params,
                _: &InputMetas,
            ) -> Result<Preflight<ImportPlan>, StageError> {
                let path = check_path(&p.path)?;
                #[allow(clippy::redundant_closure_call)]
                let header = ($header)(path, p.$key.as_str())
                    .map_err(|e| StageError::param(stringify!($key), e))?;
                #[allow(clippy::redundant_closure_call)]
                let held: u64 = ($held)(path);
                let pf = preflight_common(&self.info(), header, p.spacing, &p.options, held)?;
                #[allow(clippy::redundant_closure_call)]
                preflight_labels(path, &p.options, &pf.plan.header, |s| {
                    ($scan)(path, p.$key.as_str(), s)
                })?;
                Ok(pf)
            }

            fn run(
                &self,
                p: &$params,
                plan: &ImportPlan,
                _: &Inputs,
                _: &RunContext,
            ) -> Result<Outputs, StageError> {
                #[allow(clippy::redundant_closure_call)]
                let v = ($read)(Path::new(&p.path), p.$key.as_str()).map_err(StageError::failed)?;
                finish(v, plan, &p.path, &p.options, true)
            }
        }
    };
}

fn opt(s: &str) -> Option<&str> {
    (!s.is_empty()).then_some(s)
}

fn need<'a>(key: &str, s: &'a str) -> Result<&'a str, String> {
    if s.is_empty() {
        Err(format!("give the `{key}` to read"))
    } else {
        Ok(s)
    }
}

named_import!(ImportHdf5, Hdf5Params, "import.hdf5", dataset,
    "dataset path inside the file, e.g. `labels` or `group/data` (shape (z, y, x), (y, x) or (z, y, x, c))",
    "Reads one HDF5 dataset as a volume; spacing/origin (x, y, z, metres) or ImageJ's \
     element_size_um are taken from its attributes when present.",
    |p: &Path, k: &str| need("dataset", k)
        .and_then(|k| hdf5_header(p, k).map_err(|e| missing_dataset(p, k, e))),
    |p: &Path, k: &str| need("dataset", k).and_then(|k| crate::hdf5_plain::read_hdf5_dataset(p, k)),
    |p: &Path, k: &str, s: &mut LabelScan| crate::hdf5_plain::scan_hdf5_dataset(p, k, s),
    |_: &Path| 0);

named_import!(
    ImportNetcdf,
    NetcdfParams,
    "import.netcdf",
    variable,
    "variable name (dimensions (z, y, x), (y, x) or (z, y, x, component))",
    "Reads one NetCDF variable as a volume; the grid comes from global spacing/origin \
     attributes or from uniform CF coordinate variables (converted through their units).",
    |p: &Path, k: &str| need("variable", k).and_then(|k| netcdf_header(p, k)),
    |p: &Path, k: &str| need("variable", k).and_then(|k| netcdf_io::read_netcdf_variable(p, k)),
    |p: &Path, k: &str, s: &mut LabelScan| netcdf_io::scan_netcdf_variable(p, k, s),
    |_: &Path| 0
);

named_import!(
    ImportVti,
    VtiParams,
    "import.vti",
    array,
    "array name (default: the active cell scalars, else the first cell or point array)",
    "Reads one array of a VTK XML ImageData file (ascii, binary, appended, zlib); point data \
     is taken as voxel centres. Phase tables written by grainpipe are kept.",
    |p: &Path, k: &str| vti_header(p, opt(k)),
    |p: &Path, k: &str| vtk_xml::read_vti(p, opt(k)),
    // The array declared is at most PREFLIGHT_READ_BYTES: read in full.
    |p: &Path, k: &str, s: &mut LabelScan| vtk_xml::read_vti(p, opt(k))
        .map(|v| { s.feed((0..v.data.len()).map(|i| v.data.get(i))) }),
    // The file is read and parsed in memory: its bytes, the XML text and the appended block.
    |p: &Path| std::fs::metadata(p).map_or(0, |m| m.len().saturating_mul(3))
);

// ---------------------------------------------------------------------------------------

#[params]
pub struct TiffParams {
    /// multi-page TIFF file, or directory of .tif/.tiff slices (relative to the working directory)
    #[param(file, ty = "path")]
    pub path: String,
    /// voxel size: one length or [x, y, z]; overrides the stack's calibration (grainpipe or
    /// ImageJ description, or resolution tags in cm; inch tags are ignored), required when
    /// the stack has none
    #[param(ty = "length or [x, y, z]")]
    pub spacing: Option<Lengths3>,
    #[param(flatten)]
    pub options: ImportOptions,
}

pub struct ImportTiff;

impl TypedStage for ImportTiff {
    type Params = TiffParams;
    type Plan = ImportPlan;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "import.tiff",
            "1.1.0",
            "Reads a TIFF stack as a volume: a multi-page TIFF (page k = slice z = k) or a \
             directory of single-page TIFFs in natural file-name order (s2 before s10), as CT \
             software writes them. \
             Grayscale 8/16/32/64-bit pages; row r of a page is y = r. Preflight reads every \
             page header and checks that all pages share size and type. The voxel size, \
             origin and phase names written by the `tiff` exporter come back; so does an \
             ImageJ/Fiji calibration.",
        )
        .outputs(outputs())
    }

    fn preflight(
        &self,
        p: &TiffParams,
        _: &InputMetas,
    ) -> Result<Preflight<ImportPlan>, StageError> {
        let path = Path::new(&p.path);
        if !path.is_dir() {
            check_path(&p.path)?;
        }
        let header = crate::tiff_io::tiff_header(path).map_err(|e| StageError::param("path", e))?;
        if p.spacing.is_none() && header.probe.spacing.is_none() {
            return Err(StageError::param(
                "spacing",
                "the stack states no voxel size (no ImageJ calibration, no resolution in cm); \
                 give it, e.g. `spacing: 4 um`",
            ));
        }
        preflight_common(&self.info(), header, p.spacing, &p.options, 0)
    }

    fn run(
        &self,
        p: &TiffParams,
        plan: &ImportPlan,
        _: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        let v = crate::tiff_io::read_tiff(Path::new(&p.path)).map_err(StageError::failed)?;
        finish(v, plan, &p.path, &p.options, true)
    }
}

#[cfg(test)]
mod tests {
    //! Preflight knows every grid: for each format, the grid an import announces before
    //! running equals the grid of what it imports (the engine checks this on every run; the
    //! tests also compare the two exactly).

    use crate::headers::testdata::{field, image, write_cf_nc, write_plain_h5};
    use crate::{write_h5, write_nc, write_vti};
    use grainpipe_core::testing::run_yaml;
    use grainpipe_core::*;
    use serde_json::json;

    fn registry() -> Registry {
        let mut r = Registry::new();
        crate::register(&mut r);
        r
    }

    #[test]
    fn import_stages_describe_themselves_consistently() {
        registry().check_consistency().unwrap();
    }

    fn grid_of(a: &Artifact) -> &Grid {
        match a {
            Artifact::PhaseImage(x) => &x.grid,
            Artifact::Field(x) => &x.grid,
            other => panic!("imported a {}", other.kind()),
        }
    }

    /// Runs `stage` with `with` as a one-step pipeline through the engine (which holds the
    /// output to the announcement) and returns the output at `port`, after checking that the
    /// grid announced by preflight is exactly the grid imported.
    fn import(stage: &str, with: serde_json::Value, port: &str) -> Artifact {
        let reg = registry();
        let st = reg.stage(stage).unwrap().stage.clone();
        let params = st.normalize_params(&with).unwrap();
        let (pf, _) = st.preflight(&params, &InputMetas::new()).unwrap();
        assert_eq!(pf.outputs.keys().collect::<Vec<_>>(), [port], "{stage}");
        let announced = pf.outputs[port].grid.clone().expect("a grid is announced");
        let yaml = format!("name: t\nstages:\n  - id: imp\n    use: {stage}\n    with: {with}\n");
        let res = run_yaml(&reg, &yaml).unwrap_or_else(|e| panic!("{stage}: {e}"));
        let a = res.artifact(&format!("imp.{port}")).clone();
        assert_eq!(grid_of(&a), &announced, "{stage}");
        a
    }

    #[test]
    fn raw_import_announces_its_grid() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("labels.raw");
        let img = image([4, 3, 2]);
        std::fs::write(&p, &img.labels).unwrap();
        let a = import(
            "import.raw",
            json!({"path": p, "dims": [4, 3, 2], "spacing": [1.5e-6, 2.5e-6, 4e-6],
                   "origin": [-1e-4, 3e-5, 7.25e-3]}),
            "image",
        );
        let got = a.as_phase_image().unwrap();
        assert_eq!(got.labels, img.labels);
        assert_eq!(
            got.grid,
            Grid {
                periodic: [false; 3],
                ..img.grid
            }
        );
    }

    #[test]
    fn hdf5_import_announces_its_grid_with_the_file_s_periodic_axes() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("i.h5");
        let img = image([5, 4, 3]);
        write_h5(
            &Artifact::PhaseImage(img.clone()),
            &p,
            &Provenance::default(),
        )
        .unwrap();
        let a = import(
            "import.hdf5",
            json!({"path": p, "dataset": "phase"}),
            "image",
        );
        assert_eq!(a.as_phase_image().unwrap(), &img);
        // ImageJ's element_size_um, imported as a field with an origin override.
        let q = d.path().join("ij.h5");
        write_plain_h5(&q, "v", &[2, 3, 4], Some([2.0, 1.0, 1.0]));
        let a = import(
            "import.hdf5",
            json!({"path": q, "dataset": "v", "as": "field", "origin": "1 um", "unit": "K"}),
            "field",
        );
        let f = a.as_field().unwrap();
        assert_eq!(f.grid.spacing, [1e-6, 1e-6, 2e-6]);
        assert_eq!(f.grid.origin, [1e-6; 3]);
        assert_eq!(f.unit, "K");
    }

    #[test]
    fn hdf5_without_a_voxel_size_is_refused_before_running() {
        let d = tempfile::tempdir().unwrap();
        let q = d.path().join("bare.h5");
        write_plain_h5(&q, "v", &[2, 2], None);
        let st = registry().stage("import.hdf5").unwrap().stage.clone();
        let params = st
            .normalize_params(&json!({"path": q, "dataset": "v"}))
            .unwrap();
        match st.preflight(&params, &InputMetas::new()) {
            Err(StageError::InvalidParam { key, .. }) => assert_eq!(key, "spacing"),
            other => panic!("expected a spacing error, got {other:?}"),
        }
    }

    #[test]
    fn netcdf_import_announces_its_grid() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("i.nc");
        let img = image([5, 4, 3]);
        write_nc(
            &Artifact::PhaseImage(img.clone()),
            &p,
            &Provenance::default(),
        )
        .unwrap();
        let a = import(
            "import.netcdf",
            json!({"path": p, "variable": "phase"}),
            "image",
        );
        assert_eq!(a.as_phase_image().unwrap(), &img);
        // CF coordinates in micrometres, no grainpipe attributes.
        let q = d.path().join("cf.nc");
        write_cf_nc(&q, &[("y", 3, 3.0, 0.0), ("x", 4, 2.0, 10.0)]);
        let a = import(
            "import.netcdf",
            json!({"path": q, "variable": "labels"}),
            "image",
        );
        assert_eq!(a.as_phase_image().unwrap().grid.dims, [4, 3, 1]);
    }

    #[test]
    fn vti_import_announces_its_grid() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("f.vti");
        let f = field([3, 2, 4], 3);
        write_vti(&Artifact::Field(f.clone()), &p, &Provenance::default()).unwrap();
        let a = import("import.vti", json!({"path": p, "as": "field"}), "field");
        assert_eq!(a.as_field().unwrap(), &f);
        // Point data on an offset extent, with a spacing override.
        let q = d.path().join("points.vti");
        std::fs::write(
            &q,
            "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"1.0\">\n\
             <ImageData WholeExtent=\"1 3 0 1 0 0\" Origin=\"1 2 3\" Spacing=\"0.5 0.25 1\">\n\
             <Piece Extent=\"1 3 0 1 0 0\"><PointData Scalars=\"l\">\n\
             <DataArray type=\"UInt8\" Name=\"l\" format=\"ascii\">0 1 2 3 4 5</DataArray>\n\
             </PointData><CellData></CellData></Piece></ImageData></VTKFile>\n",
        )
        .unwrap();
        import("import.vti", json!({"path": q}), "image");
        let a = import("import.vti", json!({"path": q, "spacing": 2.0}), "image");
        assert_eq!(a.as_phase_image().unwrap().grid.spacing, [2.0; 3]);
    }
}
