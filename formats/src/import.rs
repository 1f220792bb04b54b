//! Import stages: a volume from a raw file, an HDF5 dataset, a NetCDF variable or a `.vti`
//! array, as a PhaseImage (`as: phase_image`, labels 0..=255) or a Field (`as: field`).
//!
//! Preflight opens the file and checks its header (raw: its size) against the declared
//! layout without reading the array; the array is read in `run`. Relative paths are relative
//! to the current working directory. Only the output chosen by `as` is produced: `image`
//! for a phase image, `field` for a field.

use crate::raw::{probe_raw, read_raw, Endian, RawDtype, RawLayout};
use crate::volume::{Probe, Volume};
use crate::{hdf5_plain, netcdf_io, vtk_xml};
use grainpipe_core::units::{Length, Q};
use grainpipe_core::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// What the imported array becomes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImportAs {
    #[default]
    PhaseImage,
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

const AS_DOC: &str = "`phase_image` (integer labels 0..=255) or `field`";
const SPACING_DOC: &str = "voxel size: one length or [x, y, z]; overrides the file's";
const ORIGIN_DOC: &str = "lower grid corner [x, y, z]; overrides the file's (default 0)";
const UNIT_DOC: &str = "unit of a field (overrides the file's)";
const PATH_DOC: &str = "input file (relative to the working directory)";

/// The `origin`, `as` and `unit` parameters every import stage ends with.
fn trailing_specs() -> [ParamSpec; 3] {
    [
        ParamSpec {
            name: "origin",
            ty: "[x, y, z]",
            unit: "m",
            doc: ORIGIN_DOC,
        },
        ParamSpec {
            name: "as",
            ty: "one of: phase_image, field",
            unit: "",
            doc: AS_DOC,
        },
        ParamSpec {
            name: "unit",
            ty: "unit string",
            unit: "",
            doc: UNIT_DOC,
        },
    ]
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

/// Common preflight: checks the probed shape against `as` and estimates memory (the array as
/// stored plus the output).
fn preflight_common(
    probe: Probe,
    as_: ImportAs,
    spacing: Option<Lengths3>,
    origin: Option<Lengths3>,
) -> Result<Preflight, StageError> {
    check_lengths("spacing", spacing, true)?;
    check_lengths("origin", origin, false)?;
    if as_ == ImportAs::PhaseImage && probe.components != 1 {
        return Err(StageError::param(
            "as",
            format!(
                "the array has {} components; a phase image needs one label per voxel (use `as: field`)",
                probe.components
            ),
        ));
    }
    let n = probe.dims.iter().product::<usize>() * probe.components;
    if n == 0 {
        return Err(StageError::param(
            "path",
            format!("the array is empty (dims {:?})", probe.dims),
        ));
    }
    let out_bytes = match as_ {
        ImportAs::PhaseImage => 1,
        ImportAs::Field if probe.elem_bytes == 4 && probe.dtype.contains("32") => 4,
        ImportAs::Field => 8,
    };
    let spacing = spacing.map(|s| s.si()).or(probe.spacing);
    let grid = spacing.map(|spacing| Grid {
        dims: probe.dims,
        spacing,
        origin: origin.map(|o| o.si()).or(probe.origin).unwrap_or([0.0; 3]),
        periodic: [false; 3],
    });
    let (name, kind) = port(as_);
    let mut meta = ArtifactMeta::of(kind);
    meta.grid = grid;
    meta.count_estimate = n as u64;
    Ok(Preflight {
        outputs: [(name.to_string(), meta)].into_iter().collect(),
        memory_bytes: (n * (probe.elem_bytes + out_bytes)) as u64,
    })
}

/// Applies overrides and converts.
fn finish(
    mut v: Volume,
    path: &str,
    as_: ImportAs,
    spacing: Option<Lengths3>,
    origin: Option<Lengths3>,
    unit: &str,
) -> Result<Outputs, StageError> {
    if let Some(s) = spacing {
        v.spacing = Some(s.si());
    }
    if let Some(o) = origin {
        v.origin = Some(o.si());
    }
    if !unit.is_empty() {
        v.unit = unit.to_string();
    }
    let art = match as_ {
        ImportAs::PhaseImage => v.into_phase_image().map(Artifact::PhaseImage),
        ImportAs::Field => v.into_field().map(Artifact::Field),
    }
    .map_err(|e| StageError::failed(format!("{path}: {e}")))?;
    let mut out = Outputs::new();
    out.insert(port(as_).0.to_string(), art);
    Ok(out)
}

fn read_failed(e: String) -> StageError {
    StageError::failed(e)
}

// ---------------------------------------------------------------------------------------

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RawParams {
    pub path: String,
    /// [nx, ny, nz].
    pub dims: [usize; 3],
    pub dtype: RawDtype,
    pub endian: Endian,
    pub header_bytes: u64,
    pub spacing: Option<Lengths3>,
    pub origin: Option<Lengths3>,
    #[serde(rename = "as")]
    pub as_: ImportAs,
    pub unit: String,
}

impl Default for RawParams {
    fn default() -> Self {
        RawParams {
            path: String::new(),
            dims: [0; 3],
            dtype: RawDtype::U8,
            endian: Endian::Little,
            header_bytes: 0,
            spacing: None,
            origin: None,
            as_: ImportAs::PhaseImage,
            unit: String::new(),
        }
    }
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
    fn info(&self) -> StageInfo {
        StageInfo {
            id: "import.raw",
            version: "1.0.0",
            doc: "Reads a headerless raw volume (x fastest, then y, then z) whose dims, element \
                  type, byte order and voxel size are given here; preflight checks the file size.",
            params: vec![
                ParamSpec {
                    name: "path",
                    ty: "path",
                    unit: "",
                    doc: PATH_DOC,
                },
                ParamSpec {
                    name: "dims",
                    ty: "[nx, ny, nz]",
                    unit: "",
                    doc: "voxels along x, y, z",
                },
                ParamSpec {
                    name: "dtype",
                    ty: "one of: u8, u16, i32, f32, f64",
                    unit: "",
                    doc: "element type",
                },
                ParamSpec {
                    name: "endian",
                    ty: "one of: little, big",
                    unit: "",
                    doc: "byte order",
                },
                ParamSpec {
                    name: "header_bytes",
                    ty: "integer",
                    unit: "",
                    doc: "bytes to skip at the start of the file",
                },
                ParamSpec {
                    name: "spacing",
                    ty: "length or [x, y, z]",
                    unit: "m",
                    doc: "voxel size (required)",
                },
            ]
            .into_iter()
            .chain(trailing_specs())
            .collect(),
            inputs: vec![],
            outputs: outputs(),
        }
    }

    fn preflight(&self, p: &RawParams, _: &InputMetas) -> Result<Preflight, StageError> {
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
        preflight_common(probe, p.as_, p.spacing, p.origin)
    }

    fn run(&self, p: &RawParams, _: &Inputs, _: &RunContext) -> Result<Outputs, StageError> {
        let spacing = p
            .spacing
            .ok_or_else(|| StageError::param("spacing", "a raw file needs the voxel size"))?
            .si();
        let origin = p.origin.map(|o| o.si()).unwrap_or([0.0; 3]);
        let v = read_raw(Path::new(&p.path), &p.layout(), spacing, origin).map_err(read_failed)?;
        finish(v, &p.path, p.as_, p.spacing, p.origin, &p.unit)
    }
}

// ---------------------------------------------------------------------------------------

macro_rules! named_import {
    ($stage:ident, $params:ident, $id:expr, $key:ident, $key_doc:expr, $doc:expr,
     $probe:expr, $read:expr) => {
        #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
        #[serde(deny_unknown_fields, default)]
        pub struct $params {
            pub path: String,
            pub $key: String,
            pub spacing: Option<Lengths3>,
            pub origin: Option<Lengths3>,
            #[serde(rename = "as")]
            pub as_: ImportAs,
            pub unit: String,
        }

        impl Default for $params {
            fn default() -> Self {
                $params {
                    path: String::new(),
                    $key: String::new(),
                    spacing: None,
                    origin: None,
                    as_: ImportAs::PhaseImage,
                    unit: String::new(),
                }
            }
        }

        pub struct $stage;

        impl TypedStage for $stage {
            type Params = $params;
            fn info(&self) -> StageInfo {
                StageInfo {
                    id: $id,
                    version: "1.0.0",
                    doc: $doc,
                    params: vec![
                        ParamSpec {
                            name: "path",
                            ty: "path",
                            unit: "",
                            doc: PATH_DOC,
                        },
                        ParamSpec {
                            name: stringify!($key),
                            ty: "string",
                            unit: "",
                            doc: $key_doc,
                        },
                        ParamSpec {
                            name: "spacing",
                            ty: "length or [x, y, z]",
                            unit: "m",
                            doc: SPACING_DOC,
                        },
                    ]
                    .into_iter()
                    .chain(trailing_specs())
                    .collect(),
                    inputs: vec![],
                    outputs: outputs(),
                }
            }

            fn preflight(&self, p: &$params, _: &InputMetas) -> Result<Preflight, StageError> {
                let path = check_path(&p.path)?;
                #[allow(clippy::redundant_closure_call)]
                let probe = ($probe)(path, p.$key.as_str())
                    .map_err(|e| StageError::param(stringify!($key), e))?;
                preflight_common(probe, p.as_, p.spacing, p.origin)
            }

            fn run(&self, p: &$params, _: &Inputs, _: &RunContext) -> Result<Outputs, StageError> {
                #[allow(clippy::redundant_closure_call)]
                let v = ($read)(Path::new(&p.path), p.$key.as_str()).map_err(read_failed)?;
                finish(v, &p.path, p.as_, p.spacing, p.origin, &p.unit)
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
    |p: &Path, k: &str| need("dataset", k).and_then(|k| hdf5_plain::probe_hdf5_dataset(p, k)),
    |p: &Path, k: &str| need("dataset", k).and_then(|k| hdf5_plain::read_hdf5_dataset(p, k)));

named_import!(
    ImportNetcdf,
    NetcdfParams,
    "import.netcdf",
    variable,
    "variable name (dimensions (z, y, x), (y, x) or (z, y, x, component))",
    "Reads one NetCDF variable as a volume; the grid comes from global spacing/origin \
     attributes or from uniform CF coordinate variables (converted through their units).",
    |p: &Path, k: &str| need("variable", k).and_then(|k| netcdf_io::probe_netcdf_variable(p, k)),
    |p: &Path, k: &str| need("variable", k).and_then(|k| netcdf_io::read_netcdf_variable(p, k))
);

named_import!(
    ImportVti,
    VtiParams,
    "import.vti",
    array,
    "array name (default: the active cell scalars, else the first cell or point array)",
    "Reads one array of a VTK XML ImageData file (ascii, binary, appended, zlib); point data \
     is taken as voxel centres. Phase tables written by grainpipe are kept.",
    |p: &Path, k: &str| vtk_xml::probe_vti(p, opt(k)),
    |p: &Path, k: &str| vtk_xml::read_vti(p, opt(k))
);

// ---------------------------------------------------------------------------------------

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TiffParams {
    pub path: String,
    pub spacing: Option<Lengths3>,
    pub origin: Option<Lengths3>,
    #[serde(rename = "as")]
    pub as_: ImportAs,
    pub unit: String,
}

pub struct ImportTiff;

impl TypedStage for ImportTiff {
    type Params = TiffParams;
    fn info(&self) -> StageInfo {
        StageInfo {
            id: "import.tiff",
            version: "1.0.0",
            doc: "Reads a TIFF stack as a volume: a multi-page TIFF (page k = slice z = k) or a \
                  directory of single-page TIFFs in file-name order, as CT software writes them. \
                  Grayscale 8/16/32/64-bit pages; row r of a page is y = r. Preflight reads every \
                  page header and checks that all pages share size and type.",
            params: vec![
                ParamSpec { name: "path", ty: "path", unit: "", doc: "multi-page TIFF file, or directory of .tif/.tiff slices (relative to the working directory)" },
                ParamSpec { name: "spacing", ty: "length or [x, y, z]", unit: "m", doc: "voxel size (required: TIFF resolution tags are not trusted)" },
            ]
            .into_iter()
            .chain(trailing_specs())
            .collect(),
            inputs: vec![],
            outputs: outputs(),
        }
    }

    fn preflight(&self, p: &TiffParams, _: &InputMetas) -> Result<Preflight, StageError> {
        if p.spacing.is_none() {
            return Err(StageError::param(
                "spacing",
                "give the voxel size of the stack, e.g. `spacing: 4 um`",
            ));
        }
        let path = Path::new(&p.path);
        if !path.is_dir() {
            check_path(&p.path)?;
        }
        let probe = crate::tiff_io::probe_tiff(path).map_err(|e| StageError::param("path", e))?;
        preflight_common(probe, p.as_, p.spacing, p.origin)
    }

    fn run(&self, p: &TiffParams, _: &Inputs, _: &RunContext) -> Result<Outputs, StageError> {
        let v = crate::tiff_io::read_tiff(Path::new(&p.path)).map_err(read_failed)?;
        finish(v, &p.path, p.as_, p.spacing, p.origin, &p.unit)
    }
}
