//! The in-between representation every volume reader returns (`Volume`) and the view every
//! volume writer takes (`VolumeRef`), so that PhaseImage/Field handling is written once.

use grainpipe_core::{Artifact, ComponentConvention, Field, FieldData, Grid, Phase, PhaseImage};

/// Element type of a volume read from a file.
#[derive(Clone, Debug, PartialEq)]
pub enum VolumeData {
    U8(Vec<u8>),
    U16(Vec<u16>),
    I32(Vec<i32>),
    F32(Vec<f32>),
    F64(Vec<f64>),
}

impl VolumeData {
    pub fn len(&self) -> usize {
        match self {
            VolumeData::U8(v) => v.len(),
            VolumeData::U16(v) => v.len(),
            VolumeData::I32(v) => v.len(),
            VolumeData::F32(v) => v.len(),
            VolumeData::F64(v) => v.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn get(&self, i: usize) -> f64 {
        match self {
            VolumeData::U8(v) => v[i] as f64,
            VolumeData::U16(v) => v[i] as f64,
            VolumeData::I32(v) => v[i] as f64,
            VolumeData::F32(v) => v[i] as f64,
            VolumeData::F64(v) => v[i],
        }
    }
}

/// A 3-D array read from a file, x fastest (`index = c + ncomp * (x + nx * (y + ny * z))`),
/// with whatever geometry and metadata the file carried.
#[derive(Clone, Debug, PartialEq)]
pub struct Volume {
    /// Array/dataset/variable name in the file.
    pub name: String,
    /// Unit string from the file ("" when none).
    pub unit: String,
    /// [nx, ny, nz].
    pub dims: [usize; 3],
    pub components: usize,
    /// What the components mean, when the file says (`Plain` otherwise).
    pub convention: ComponentConvention,
    /// Voxel size [m] when the file states it.
    pub spacing: Option<[f64; 3]>,
    /// Lower grid corner [m] when the file states it.
    pub origin: Option<[f64; 3]>,
    pub periodic: [bool; 3],
    pub data: VolumeData,
    /// Phase table when the file carries one.
    pub phases: Vec<Phase>,
}

impl Volume {
    fn grid(&self, what: &str) -> Result<Grid, String> {
        let spacing = self.spacing.ok_or_else(|| {
            format!("{what}: the file gives no voxel spacing; set `spacing` explicitly")
        })?;
        if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(format!(
                "{what}: spacing {spacing:?} must be three positive lengths"
            ));
        }
        Ok(Grid {
            dims: self.dims,
            spacing,
            origin: self.origin.unwrap_or([0.0; 3]),
            periodic: self.periodic,
        })
    }

    /// Converts to a labelled image; values must be integers in 0..=255.
    pub fn into_phase_image(self) -> Result<PhaseImage, String> {
        let what = format!("`{}`", self.name);
        if self.components != 1 {
            return Err(format!(
                "{what} has {} components; a phase image needs one label per voxel",
                self.components
            ));
        }
        let grid = self.grid(&what)?;
        let labels: Vec<u8> = match self.data {
            // moved, not copied: a volume may be most of the memory
            VolumeData::U8(v) => v,
            other => {
                let mut out = Vec::with_capacity(other.len());
                for i in 0..other.len() {
                    let x = other.get(i);
                    if !(0.0..=255.0).contains(&x) || x.fract() != 0.0 {
                        return Err(format!(
                            "{what}: voxel {i} holds {x}; phase labels must be integers 0..=255 \
                             (import it `as: field` instead, or relabel it first)"
                        ));
                    }
                    out.push(x as u8);
                }
                out
            }
        };
        let phases = if self.phases.is_empty() {
            default_phase_table(&labels)
        } else {
            self.phases
        };
        Ok(PhaseImage {
            grid,
            labels,
            phases,
        })
    }

    /// Converts to a field; f32 stays f32, everything else becomes f64.
    pub fn into_field(self) -> Result<Field, String> {
        let what = format!("`{}`", self.name);
        let grid = self.grid(&what)?;
        let data = match self.data {
            VolumeData::F32(v) => FieldData::F32(v),
            VolumeData::F64(v) => FieldData::F64(v),
            other => FieldData::F64((0..other.len()).map(|i| other.get(i)).collect()),
        };
        let convention = if self
            .convention
            .component_names(self.components, grid.dims[2])
            .is_some()
        {
            self.convention
        } else {
            ComponentConvention::Plain
        };
        Ok(Field {
            grid,
            name: self.name,
            unit: self.unit,
            components: self.components,
            convention,
            data,
        })
    }
}

/// "pore" for label 0 and "phase<k>" for every other label present: an imported label volume
/// says nothing about its materials (label k may be one grain each), so the vocabulary's
/// name for a label of unknown material is used rather than guessing `grain`.
pub fn default_phase_table(labels: &[u8]) -> Vec<Phase> {
    let mut seen = [false; 256];
    for &l in labels {
        seen[l as usize] = true;
    }
    (0..256usize)
        .filter(|&l| seen[l])
        .map(|l| Phase {
            id: l as u8,
            name: grainpipe_core::phases::unnamed(l as u8),
        })
        .collect()
}

/// A phase image or a field, as every volume writer sees it.
#[derive(Clone, Copy)]
pub(crate) enum VolumeRef<'a> {
    Phase(&'a PhaseImage),
    Field(&'a Field),
}

impl<'a> VolumeRef<'a> {
    pub fn from_artifact(a: &'a Artifact, format: &str) -> Result<Self, String> {
        match a {
            Artifact::PhaseImage(p) => Ok(VolumeRef::Phase(p)),
            Artifact::Field(f) => Ok(VolumeRef::Field(f)),
            other => Err(format!(
                "{format} takes a PhaseImage or a Field, not a {}",
                other.kind()
            )),
        }
    }
    pub fn grid(&self) -> &'a Grid {
        match self {
            VolumeRef::Phase(p) => &p.grid,
            VolumeRef::Field(f) => &f.grid,
        }
    }
    /// Array name: `phase` for images, the field's name otherwise.
    pub fn name(&self) -> &'a str {
        match self {
            VolumeRef::Phase(_) => "phase",
            VolumeRef::Field(f) => &f.name,
        }
    }
    pub fn unit(&self) -> &'a str {
        match self {
            VolumeRef::Phase(_) => "",
            VolumeRef::Field(f) => &f.unit,
        }
    }
    pub fn components(&self) -> usize {
        match self {
            VolumeRef::Phase(_) => 1,
            VolumeRef::Field(f) => f.components,
        }
    }
    pub fn convention(&self) -> ComponentConvention {
        match self {
            VolumeRef::Phase(_) => ComponentConvention::Plain,
            VolumeRef::Field(f) => f.convention,
        }
    }
    /// Checks that the array length matches the grid (a malformed artifact must not produce a
    /// file that opens with garbage).
    pub fn validate(&self) -> Result<(), String> {
        let n = grainpipe_core::checked_product(&[self.grid().voxel_count(), self.components()])
            .unwrap_or(usize::MAX);
        let len = match self {
            VolumeRef::Phase(p) => p.labels.len(),
            VolumeRef::Field(f) => f.data.len(),
        };
        if len != n {
            return Err(format!(
                "`{}` holds {len} values but its grid {:?} x {} components needs {n}",
                self.name(),
                self.grid().dims,
                self.components()
            ));
        }
        if self.components() == 0 {
            return Err(format!("`{}` has zero components", self.name()));
        }
        Ok(())
    }
}

/// Little-endian encoding of plain numbers (VTK XML binary arrays, raw files).
pub(crate) trait Le: Copy {
    const SIZE: usize;
    fn put(self, out: &mut Vec<u8>);
    fn from_bytes(b: &[u8], little: bool) -> Self;
}

macro_rules! impl_le {
    ($($t:ty),*) => {$(
        impl Le for $t {
            const SIZE: usize = std::mem::size_of::<$t>();
            fn put(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
            fn from_bytes(b: &[u8], little: bool) -> Self {
                let a = b.try_into().expect("slice of the element size");
                if little { <$t>::from_le_bytes(a) } else { <$t>::from_be_bytes(a) }
            }
        }
    )*};
}
impl_le!(u8, i8, u16, i16, u32, i32, u64, i64, f32, f64);

pub(crate) fn to_le_bytes<T: Le>(v: &[T]) -> Vec<u8> {
    let mut out = Vec::with_capacity(v.len() * T::SIZE);
    for &x in v {
        x.put(&mut out);
    }
    out
}

pub(crate) fn from_bytes<T: Le>(b: &[u8], little: bool) -> Vec<T> {
    b.chunks_exact(T::SIZE)
        .map(|c| T::from_bytes(c, little))
        .collect()
}

/// Spacing and origin (each if the file gives it) and periodic axes, as a reader derives
/// them from a file's attributes: shared by the full readers and the header readers.
pub(crate) type StatedGrid = (Option<[f64; 3]>, Option<[f64; 3]>, [bool; 3]);

/// What an import preflight learns from a file header without reading the array.
#[derive(Clone, Debug, PartialEq)]
pub struct Probe {
    /// [nx, ny, nz].
    pub dims: [usize; 3],
    pub components: usize,
    /// Element type as the file names it.
    pub dtype: String,
    pub elem_bytes: usize,
    pub spacing: Option<[f64; 3]>,
    pub origin: Option<[f64; 3]>,
}

/// Memory a reader may allocate for the data a file declares [bytes]: what the system can
/// still give (the budget `pipe run`/`pipe validate` hold the plan to), or no limit where it
/// is unknown. Readers compare a declared size against it before allocating, so a small file
/// declaring a huge array fails with a message instead of aborting on allocation.
pub fn memory_budget() -> u64 {
    grainpipe_core::engine::available_memory().unwrap_or(u64::MAX)
}

/// Refuses to read `what` when the `bytes` it declares (`None`: the size overflows) exceed
/// [`memory_budget`].
pub fn check_declared(what: &str, bytes: Option<u64>) -> Result<(), String> {
    let budget = memory_budget();
    match bytes {
        Some(b) if b <= budget => Ok(()),
        Some(b) => Err(format!(
            "{what} declares {} of data, more than the {} of memory available; the file \
             is corrupt or too large for this machine",
            grainpipe_core::engine::human_bytes(b),
            grainpipe_core::engine::human_bytes(budget)
        )),
        None => Err(format!(
            "{what} declares a size that overflows; the file is corrupt"
        )),
    }
}

/// Bytes of one value of the [`VolumeData`] a reader makes of `elem_bytes`-wide file elements
/// of type `dtype` (as the header readers name it), at most: unsigned 8-bit stays 8-bit,
/// signed 8-bit and 16-bit become at most i32, 32-bit stays or becomes f64 (u32), 64-bit
/// stays 64-bit.
pub fn volume_value_bytes(dtype: &str, elem_bytes: usize) -> usize {
    let signed8 = !["u8", "UInt8", "Unsigned(", "(U8)", "Boolean"]
        .iter()
        .any(|s| dtype.contains(s));
    // u32 (and a 32-bit TIFF page, which may be u32) widens to f64.
    let unsigned32 = ["UInt32", "Unsigned(", "(U32)", "32-bit"]
        .iter()
        .any(|s| dtype.contains(s));
    match elem_bytes {
        1 if !signed8 => 1,
        1 | 2 => 4,
        4 if !unsigned32 => 4,
        _ => 8,
    }
}

/// The scan of values that must be phase labels (integers 0..=255), fed in blocks so a
/// volume need not be in memory: the first value that is not a label, and the range of all.
#[derive(Clone, Debug)]
pub struct LabelScan {
    seen: usize,
    first_bad: Option<(usize, f64)>,
    lo: f64,
    hi: f64,
}

impl Default for LabelScan {
    fn default() -> Self {
        LabelScan {
            seen: 0,
            first_bad: None,
            lo: f64::INFINITY,
            hi: f64::NEG_INFINITY,
        }
    }
}

impl LabelScan {
    /// The next values, in file order (x fastest).
    pub fn feed(&mut self, values: impl Iterator<Item = f64>) {
        for x in values {
            if self.first_bad.is_none() && (!(0.0..=255.0).contains(&x) || x.fract() != 0.0) {
                self.first_bad = Some((self.seen, x));
            }
            self.lo = self.lo.min(x);
            self.hi = self.hi.max(x);
            self.seen += 1;
        }
    }

    /// The first voxel whose value is not a phase label, as (x, y, z) and the value, with
    /// what to do about it.
    pub fn result(&self, dims: [usize; 3]) -> Result<(), String> {
        let Some((i, v)) = self.first_bad else {
            return Ok(());
        };
        let [nx, ny, _] = dims;
        let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
        Err(format!(
            "voxel (x={x}, y={y}, z={z}) holds {v}; phase labels are integers 0..=255 (values \
             span {} .. {}): import it with `as: field`, or relabel/threshold it first",
            self.lo, self.hi
        ))
    }
}
