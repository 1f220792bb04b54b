//! Pieces the segment stages share: sizes given in voxels or in physical units, reading a
//! scalar field, and the choice between a phase image and a field on the same stage.

use grainpipe_core::params::ParamType;
use grainpipe_core::units::{parse_quantity, Dim, Q};
use grainpipe_core::{
    Artifact, ArtifactKind, ArtifactMeta, Field, FieldData, Grid, InputMetas, Inputs, Outputs,
    PhaseImage, PortSpec, Preflight, StageError, StageInfo,
};
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use serde_json::{json, Value};
use std::marker::PhantomData;

/// A size given as a plain number of voxels (`2`, `1.5`) or as a string with a unit of
/// dimension `D` (`"3 um"` for a length, `"1000 um^3"` for a volume).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum VoxelsOr<D: Dim> {
    Voxels(f64),
    Physical(Q<D>),
}

impl<D: Dim> Default for VoxelsOr<D> {
    fn default() -> Self {
        VoxelsOr::Voxels(0.0)
    }
}

impl<D: Dim> VoxelsOr<D> {
    /// The value as a number of voxels along each axis, for a length (`per_voxel` = the
    /// spacing), or as a count of voxels, for a volume (`per_voxel` = the voxel volume,
    /// one entry).
    pub fn in_voxels(&self, per_voxel: f64) -> f64 {
        match self {
            VoxelsOr::Voxels(v) => *v,
            VoxelsOr::Physical(q) => q.0 / per_voxel,
        }
    }
    pub fn is_finite_non_negative(&self) -> bool {
        let v = match self {
            VoxelsOr::Voxels(v) => *v,
            VoxelsOr::Physical(q) => q.0,
        };
        v.is_finite() && v >= 0.0
    }
}

// A plain number stays a number (voxels); a physical value is written back as a string
// with its SI unit, so the canonical parameters (and the cache key) keep the distinction.
impl<D: Dim> Serialize for VoxelsOr<D> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            VoxelsOr::Voxels(v) => s.serialize_f64(*v),
            VoxelsOr::Physical(q) => s.serialize_str(&format!("{:e} {}", q.0, D::SI_UNIT)),
        }
    }
}

impl<'de, D: Dim> Deserialize<'de> for VoxelsOr<D> {
    fn deserialize<De: Deserializer<'de>>(d: De) -> Result<Self, De::Error> {
        struct V<D>(PhantomData<D>);
        impl<D: Dim> serde::de::Visitor<'_> for V<D> {
            type Value = VoxelsOr<D>;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                write!(
                    f,
                    "a number of voxels or a string with a unit of {}",
                    D::SI_UNIT
                )
            }
            fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<Self::Value, E> {
                Ok(VoxelsOr::Voxels(v))
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<Self::Value, E> {
                Ok(VoxelsOr::Voxels(v as f64))
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<Self::Value, E> {
                Ok(VoxelsOr::Voxels(v as f64))
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<Self::Value, E> {
                let q = parse_quantity(v).map_err(E::custom)?;
                if q.dim == grainpipe_core::units::Dimension::NONE {
                    return Ok(VoxelsOr::Voxels(q.value));
                }
                if q.dim != D::DIM {
                    return Err(E::custom(format!(
                        "`{v}` has dimension {} but this parameter takes voxels (a plain \
                         number) or {}",
                        q.dim,
                        D::SI_UNIT
                    )));
                }
                Ok(VoxelsOr::Physical(Q::new(q.value)))
            }
        }
        d.deserialize_any(V(PhantomData))
    }
}

impl<D: Dim> ParamType for VoxelsOr<D> {
    fn type_name() -> String {
        format!("voxels, or a {} with a unit", D::NAME)
    }
    fn schema() -> Value {
        json!({"anyOf": [
            {"type": "number"},
            {"type": "string", "description": format!("a number with a unit of the dimension of {}", D::SI_UNIT)},
        ]})
    }
}

/// The values of a one-component field as f64, with an error naming `port` otherwise.
pub fn scalar_values(f: &Field, port: &str) -> Result<Vec<f64>, StageError> {
    if f.components != 1 {
        return Err(StageError::input(
            port,
            format!(
                "field `{}` has {} components; this stage takes scalar grey values (one per voxel)",
                f.name, f.components
            ),
        ));
    }
    Ok(field_values(&f.data))
}

/// Every value of a field as f64.
pub fn field_values(d: &FieldData) -> Vec<f64> {
    match d {
        FieldData::F32(v) => v.iter().map(|&x| x as f64).collect(),
        FieldData::F64(v) => v.clone(),
    }
}

/// Values in the precision of `like` (f32 fields stay f32).
pub fn same_precision(like: &FieldData, v: Vec<f64>) -> FieldData {
    match like {
        FieldData::F32(_) => FieldData::F32(v.into_iter().map(|x| x as f32).collect()),
        FieldData::F64(_) => FieldData::F64(v),
    }
}

/// A field like `f` (name, unit, convention) with other values on another grid.
pub fn field_like(f: &Field, grid: Grid, data: FieldData) -> Result<Field, StageError> {
    Field::new(grid, f.name.clone(), f.unit.clone(), f.convention, data).map_err(StageError::failed)
}

/// The two optional inputs of the stages that take either a phase image or a field, and
/// the outputs of the same names.
pub fn image_or_field_ports() -> (Vec<PortSpec>, Vec<PortSpec>) {
    (
        vec![
            PortSpec::optional(
                "image",
                ArtifactKind::PhaseImage,
                "a phase image (connect this or `field`)",
            ),
            PortSpec::optional(
                "field",
                ArtifactKind::Field,
                "a field of any number of components (connect this or `image`)",
            ),
        ],
        vec![
            PortSpec::optional(
                "image",
                ArtifactKind::PhaseImage,
                "the result, when `image` is connected",
            ),
            PortSpec::optional(
                "field",
                ArtifactKind::Field,
                "the result, when `field` is connected",
            ),
        ],
    )
}

/// Which of `image` / `field` is connected (exactly one must be) and its announced grid.
pub fn connected_input(i: &InputMetas) -> Result<(&'static str, ArtifactKind, Grid), StageError> {
    let (port, kind) = match (i.contains_key("image"), i.contains_key("field")) {
        (true, false) => ("image", ArtifactKind::PhaseImage),
        (false, true) => ("field", ArtifactKind::Field),
        (true, true) => {
            return Err(StageError::input(
                "field",
                "connect either `image` or `field`, not both (use two steps)",
            ))
        }
        (false, false) => {
            return Err(StageError::input(
                "image",
                "nothing connected: connect a phase image as `image` or a field as `field`",
            ))
        }
    };
    let grid = grainpipe_core::announced_grid(i, port)?;
    Ok((port, kind, grid))
}

/// What a segmentation step holds beside its voxel arrays: the phase table and metadata of
/// the output, the summary tables, the histograms (tens of KiB; rounded up).
pub const TABLES_BYTES: u64 = 64 << 10;

/// The preflight of a stage that takes either a phase image or a field: only the output named
/// like the connected input `port`, announced as `kind` on the output `grid`. The memory is
/// `memory_bytes` (the stage's arrays) plus [`TABLES_BYTES`].
pub fn image_or_field_preflight(
    info: &StageInfo,
    memory_bytes: u64,
    port: &str,
    kind: ArtifactKind,
    grid: &Grid,
) -> Preflight {
    let mut pf = Preflight::from_info(info, memory_bytes + TABLES_BYTES);
    pf.outputs.retain(|k, _| k == port);
    pf.announce(port, ArtifactMeta::on_grid(kind, grid.clone()))
}

/// The output of a stage that takes either a phase image or a field, under the name of the
/// connected input and on `grid`: the image with the labels `labels` makes of it (phase
/// table kept), or the field with the values `values` makes of it (name, unit and
/// convention kept).
pub fn image_or_field_output(
    inputs: &Inputs,
    grid: &Grid,
    labels: impl FnOnce(&PhaseImage) -> Vec<u8>,
    values: impl FnOnce(&Field) -> FieldData,
) -> Result<Outputs, StageError> {
    let mut out = Outputs::new();
    if inputs.contains_key("image") {
        let im = grainpipe_core::input(inputs, "image", Artifact::as_phase_image)?;
        out.insert(
            "image".into(),
            Artifact::PhaseImage(PhaseImage {
                grid: grid.clone(),
                labels: labels(im),
                phases: im.phases.clone(),
            }),
        );
    } else {
        let f = grainpipe_core::input(inputs, "field", Artifact::as_field)?;
        let data = values(f);
        out.insert(
            "field".into(),
            Artifact::Field(field_like(f, grid.clone(), data)?),
        );
    }
    Ok(out)
}

/// Bytes per voxel of a field for memory estimates when its precision and components are
/// not known before running (f64, one component; fields of more components cost more).
pub const FIELD_BYTES: u64 = 8;
