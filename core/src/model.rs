//! The volume data model shared by every stage. SI units throughout (metres, kilograms,
//! seconds, kelvin). Voxel arrays are stored x fastest: `index = x + nx * (y + ny * z)`.

use indexmap::IndexMap;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use std::fmt;

/// A regular voxel grid. `nz = 1` for 2-D images.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    pub dims: [usize; 3],
    /// Voxel edge lengths [m].
    pub spacing: [f64; 3],
    /// Position of the grid's lower corner (not of the first voxel centre) [m].
    pub origin: [f64; 3],
    pub periodic: [bool; 3],
}

impl Grid {
    /// The grid of voxels of edge about `voxel` that tiles the box `[min, max]` exactly: the
    /// count per axis is rounded and the spacing adjusted to it.
    pub fn tiling(min: [f64; 3], max: [f64; 3], periodic: [bool; 3], voxel: f64) -> Grid {
        let size = [0, 1, 2].map(|a| max[a] - min[a]);
        let dims = [0, 1, 2].map(|a| ((size[a] / voxel).round() as usize).max(1));
        Grid {
            dims,
            spacing: [0, 1, 2].map(|a| size[a] / dims[a] as f64),
            origin: min,
            periodic,
        }
    }

    /// Refuses a voxel that does not fit in the box along some axis: [`Grid::tiling`] would
    /// make that axis one voxel wide and stretch it to the box, an image with nothing of the
    /// geometry in it (a 1 mm voxel on a 400 um box gave solid fraction 0 against 0.30).
    pub fn check_tiling(min: [f64; 3], max: [f64; 3], voxel: f64) -> Result<(), String> {
        for a in 0..3 {
            let size = max[a] - min[a];
            // 1e-9: a box of exactly one voxel, up to rounding, is fine.
            if voxel > size * (1.0 + 1e-9) {
                return Err(format!(
                    "the voxel ({}) is larger than the box along {} ({}): the image would be \
                     one voxel across; use a voxel of at most {} (box / 20 = {} gives 20 voxels)",
                    crate::units::format_length(voxel),
                    ["x", "y", "z"][a],
                    crate::units::format_length(size),
                    crate::units::format_length(size),
                    crate::units::format_length(size / 20.0),
                ));
            }
        }
        Ok(())
    }

    /// Number of voxels. Saturates at `usize::MAX` instead of wrapping, so dims read from a
    /// file or a plugin that overflow give an impossible memory estimate (refused) and a
    /// length that no array matches, never a small wrapped count that passes size checks.
    pub fn voxel_count(&self) -> usize {
        self.checked_voxel_count().unwrap_or(usize::MAX)
    }
    /// Number of voxels, `None` when the product of the dims overflows.
    pub fn checked_voxel_count(&self) -> Option<usize> {
        checked_product(&self.dims)
    }
    /// Checks a grid that came from outside the program (a file header, a plugin, a cache
    /// entry): positive dims whose product, times `bytes_per_voxel`, is addressable, and
    /// finite positive spacing and finite origin.
    pub fn validate(&self, bytes_per_voxel: usize) -> Result<(), String> {
        if self.dims.contains(&0) {
            return Err(format!("grid dims {:?} contain a zero", self.dims));
        }
        match checked_product(&[self.voxel_count(), bytes_per_voxel.max(1)]) {
            Some(n) if n <= isize::MAX as usize && self.checked_voxel_count().is_some() => {}
            _ => {
                return Err(format!(
                    "grid dims {:?} give more voxels than this machine can address",
                    self.dims
                ))
            }
        }
        if self.spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(format!(
                "grid spacing {:?} is not three positive lengths",
                self.spacing
            ));
        }
        if self.origin.iter().any(|o| !o.is_finite()) {
            return Err(format!("grid origin {:?} is not finite", self.origin));
        }
        Ok(())
    }
    pub fn index(&self, x: usize, y: usize, z: usize) -> usize {
        x + self.dims[0] * (y + self.dims[1] * z)
    }
    /// Physical size of the grid [m].
    pub fn extent(&self) -> [f64; 3] {
        [0, 1, 2].map(|a| self.dims[a] as f64 * self.spacing[a])
    }
    pub fn voxel_center(&self, x: usize, y: usize, z: usize) -> [f64; 3] {
        let i = [x, y, z];
        [0, 1, 2].map(|a| self.origin[a] + (i[a] as f64 + 0.5) * self.spacing[a])
    }
    pub fn voxel_volume(&self) -> f64 {
        self.spacing.iter().product()
    }
}

/// The product of sizes read from a file, a plugin or a cache entry, `None` when it
/// overflows `usize`. Every product of untrusted dims goes through here (a wrapped product
/// passes size checks and then indexes out of bounds).
pub fn checked_product(factors: &[usize]) -> Option<usize> {
    factors.iter().try_fold(1usize, |a, &f| a.checked_mul(f))
}

/// A named phase of a [`PhaseImage`]. Label 0 is pore by convention.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Phase {
    pub id: u8,
    pub name: String,
}

/// A segmented (labelled) volume: one `u8` label per voxel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhaseImage {
    pub grid: Grid,
    pub labels: Vec<u8>,
    pub phases: Vec<Phase>,
}

impl PhaseImage {
    /// Volume fraction of voxels carrying `label`.
    pub fn fraction(&self, label: u8) -> f64 {
        if self.labels.is_empty() {
            return 0.0;
        }
        self.labels.iter().filter(|&&l| l == label).count() as f64 / self.labels.len() as f64
    }
}

/// Per-voxel values of one physical quantity.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum FieldData {
    F32(Vec<f32>),
    F64(Vec<f64>),
}

impl FieldData {
    pub fn len(&self) -> usize {
        match self {
            FieldData::F32(v) => v.len(),
            FieldData::F64(v) => v.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn get(&self, i: usize) -> f64 {
        match self {
            FieldData::F32(v) => v[i] as f64,
            FieldData::F64(v) => v[i],
        }
    }
}

/// What the components of a [`Field`] mean, so a strain field is not read as six scalars
/// and Voigt is not mistaken for Mandel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum ComponentConvention {
    /// One scalar, or components without a stated meaning.
    #[default]
    Plain,
    /// A vector: (x, y, z), or (x, y) on a 2-D grid.
    Vector,
    /// A symmetric second-order tensor in Voigt order (xx, yy, zz, yz, xz, xy), no factors;
    /// (xx, yy, xy) on a 2-D grid.
    Voigt,
    /// The same order with the shear components scaled by sqrt 2 (Mandel).
    Mandel,
    /// A full second-order tensor, row-major (xx, xy, xz, yx, yy, yz, zx, zy, zz).
    Tensor,
}

impl ComponentConvention {
    /// The name written into files (`plain`, `vector`, `voigt`, `mandel`, `tensor`).
    pub fn name(self) -> &'static str {
        match self {
            ComponentConvention::Plain => "plain",
            ComponentConvention::Vector => "vector",
            ComponentConvention::Voigt => "voigt",
            ComponentConvention::Mandel => "mandel",
            ComponentConvention::Tensor => "tensor",
        }
    }

    pub fn from_name(name: &str) -> Option<Self> {
        [
            ComponentConvention::Plain,
            ComponentConvention::Vector,
            ComponentConvention::Voigt,
            ComponentConvention::Mandel,
            ComponentConvention::Tensor,
        ]
        .into_iter()
        .find(|c| c.name() == name)
    }

    /// Component names for `n` components on a grid with `nz` layers, or `None` when the
    /// count does not fit the convention.
    pub fn component_names(self, n: usize, nz: usize) -> Option<Vec<String>> {
        let names: &[&str] = match (self, n, nz == 1) {
            (ComponentConvention::Plain, _, _) => {
                return Some((0..n).map(|k| format!("c{k}")).collect())
            }
            (ComponentConvention::Vector, 3, _) => &["x", "y", "z"],
            (ComponentConvention::Vector, 2, true) => &["x", "y"],
            (ComponentConvention::Voigt | ComponentConvention::Mandel, 6, _) => {
                &["xx", "yy", "zz", "yz", "xz", "xy"]
            }
            (ComponentConvention::Voigt | ComponentConvention::Mandel, 3, true) => {
                &["xx", "yy", "xy"]
            }
            (ComponentConvention::Tensor, 9, _) => {
                &["xx", "xy", "xz", "yx", "yy", "yz", "zx", "zy", "zz"]
            }
            (ComponentConvention::Tensor, 4, true) => &["xx", "xy", "yx", "yy"],
            _ => return None,
        };
        Some(names.iter().map(|s| s.to_string()).collect())
    }
}

/// A voxel field with `components` values per voxel (component fastest).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Field {
    pub grid: Grid,
    pub name: String,
    /// SI unit string, e.g. "K" or "Pa".
    pub unit: String,
    pub components: usize,
    /// What the components mean.
    pub convention: ComponentConvention,
    pub data: FieldData,
}

impl Field {
    /// A field of `data.len() / voxels` components with the given meaning; checks the length
    /// and that the component count fits the convention.
    pub fn new(
        grid: Grid,
        name: impl Into<String>,
        unit: impl Into<String>,
        convention: ComponentConvention,
        data: FieldData,
    ) -> Result<Field, String> {
        let name = name.into();
        let voxels = grid.voxel_count().max(1);
        if data.len() % voxels != 0 || data.is_empty() {
            return Err(format!(
                "field `{name}`: {} values do not fill {voxels} voxels evenly",
                data.len()
            ));
        }
        let components = data.len() / voxels;
        if convention
            .component_names(components, grid.dims[2])
            .is_none()
        {
            return Err(format!(
                "field `{name}`: {components} components do not fit the {} convention",
                convention.name()
            ));
        }
        Ok(Field {
            grid,
            name,
            unit: unit.into(),
            components,
            convention,
            data,
        })
    }

    /// Names of the components (`x`, `y`, `z`; `xx`, ...; `c0`, ... for plain fields).
    pub fn component_names(&self) -> Vec<String> {
        self.convention
            .component_names(self.components, self.grid.dims[2])
            .unwrap_or_else(|| (0..self.components).map(|k| format!("c{k}")).collect())
    }
}

/// One sphere of a clump, relative to the clump's centroid in its body frame [m].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClumpSphere {
    pub offset: [f64; 3],
    pub radius: f64,
}

/// A grain represented as a cluster of overlapping spheres.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Clump {
    pub spheres: Vec<ClumpSphere>,
    /// Volume of the union of the spheres [m^3].
    pub volume: f64,
    /// Radius of the smallest centroid-centred sphere enclosing the clump [m].
    pub bounding_radius: f64,
    /// Principal moments of inertia per unit density [m^5].
    pub principal_inertia: [f64; 3],
    /// Principal axes as rows, in the body frame.
    pub principal_axes: [[f64; 3]; 3],
    /// Where the grain came from (file name, label id, generator).
    pub source: String,
}

impl Clump {
    /// The clump scaled linearly by `s` about its centroid (volume x s^3, inertia x s^5).
    pub fn scaled(&self, s: f64) -> Clump {
        Clump {
            spheres: self
                .spheres
                .iter()
                .map(|x| ClumpSphere {
                    offset: x.offset.map(|v| v * s),
                    radius: x.radius * s,
                })
                .collect(),
            volume: self.volume * s.powi(3),
            bounding_radius: self.bounding_radius * s,
            principal_inertia: self.principal_inertia.map(|v| v * s.powi(5)),
            principal_axes: self.principal_axes,
            source: self.source.clone(),
        }
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ClumpLibrary {
    pub clumps: Vec<Clump>,
    pub source: String,
}

/// Solids cut out of a packing domain (the hemispheres of the paper's Example 3, ...).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ExcludedSolid {
    Sphere { center: [f64; 3], radius: f64 },
}

/// The region a packing fills.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Domain {
    pub min: [f64; 3],
    pub max: [f64; 3],
    pub periodic: [bool; 3],
    pub excluded: Vec<ExcludedSolid>,
}

impl Domain {
    pub fn boxed(min: [f64; 3], max: [f64; 3], periodic: [bool; 3]) -> Self {
        Domain {
            min,
            max,
            periodic,
            excluded: Vec::new(),
        }
    }
    pub fn size(&self) -> [f64; 3] {
        [0, 1, 2].map(|a| self.max[a] - self.min[a])
    }
    pub fn volume(&self) -> f64 {
        self.size().iter().product()
    }
}

/// The geometry of one body.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum BodyShape {
    Sphere {
        radius: f64,
    },
    /// Index into the packing's clump library.
    Clump {
        index: usize,
    },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Body {
    pub shape: BodyShape,
    /// Centroid [m].
    pub position: [f64; 3],
    /// Orientation quaternion (w, x, y, z), body frame -> world frame.
    pub orientation: [f64; 4],
    pub layer: u32,
    pub frozen: bool,
}

impl Body {
    pub fn sphere(position: [f64; 3], radius: f64) -> Self {
        Body {
            shape: BodyShape::Sphere { radius },
            position,
            orientation: [1.0, 0.0, 0.0, 0.0],
            layer: 0,
            frozen: false,
        }
    }
}

/// A per-body attribute (exported as VTK point data), e.g. peak temperature.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BodyAttribute {
    pub unit: String,
    pub values: Vec<f64>,
}

/// Bodies placed in a domain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Packing {
    pub domain: Domain,
    pub bodies: Vec<Body>,
    /// Needed when any body is a [`BodyShape::Clump`].
    pub library: Option<ClumpLibrary>,
    /// Named per-body values, each with one value per body.
    pub attributes: IndexMap<String, BodyAttribute>,
}

/// A sphere in world coordinates, belonging to body `body`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldSphere {
    pub center: [f64; 3],
    pub radius: f64,
    pub body: usize,
}

/// Rotates `v` by the unit quaternion `q` = (w, x, y, z).
pub fn rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let [w, x, y, z] = q;
    // v' = v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)
    let u = [x, y, z];
    let c1 = cross(u, v);
    let c2 = cross(u, c1);
    [0, 1, 2].map(|a| v[a] + 2.0 * (w * c1[a] + c2[a]))
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

impl Packing {
    pub fn new(domain: Domain) -> Self {
        Packing {
            domain,
            bodies: Vec::new(),
            library: None,
            attributes: IndexMap::new(),
        }
    }

    /// Every sphere of every body in world coordinates (clumps expanded).
    pub fn world_spheres(&self) -> Vec<WorldSphere> {
        let mut out = Vec::with_capacity(self.bodies.len());
        for (b, body) in self.bodies.iter().enumerate() {
            match &body.shape {
                BodyShape::Sphere { radius } => out.push(WorldSphere {
                    center: body.position,
                    radius: *radius,
                    body: b,
                }),
                BodyShape::Clump { index } => {
                    let clump = &self
                        .library
                        .as_ref()
                        .expect("clump body without library")
                        .clumps[*index];
                    for s in &clump.spheres {
                        let r = rotate(body.orientation, s.offset);
                        out.push(WorldSphere {
                            center: [0, 1, 2].map(|a| body.position[a] + r[a]),
                            radius: s.radius,
                            body: b,
                        });
                    }
                }
            }
        }
        out
    }

    /// Volume of one body [m^3] (clump volumes are the union volumes of the library).
    pub fn body_volume(&self, body: &Body) -> f64 {
        match &body.shape {
            BodyShape::Sphere { radius } => 4.0 / 3.0 * PI * radius.powi(3),
            BodyShape::Clump { index } => self
                .library
                .as_ref()
                .map(|l| l.clumps[*index].volume)
                .unwrap_or(0.0),
        }
    }

    /// Sum of body volumes [m^3]; equals the solid volume when bodies do not overlap.
    pub fn solid_volume(&self) -> f64 {
        self.bodies.iter().map(|b| self.body_volume(b)).sum()
    }

    /// Analytic solid volume fraction (bodies assumed non-overlapping, excluded solids not
    /// subtracted from the box volume).
    /// Mean volume-equivalent diameter of the bodies [m] (0 without bodies).
    pub fn mean_diameter(&self) -> f64 {
        let n = self.bodies.len().max(1) as f64;
        self.bodies
            .iter()
            .map(|b| (6.0 * self.body_volume(b) / PI).cbrt())
            .sum::<f64>()
            / n
    }

    pub fn volume_fraction(&self) -> f64 {
        self.solid_volume() / self.domain.volume()
    }
}

/// Index of a face of the domain box, in the order xmin, xmax, ymin, ymax, zmin, zmax.
pub const FACE_NAMES: [&str; 6] = ["xmin", "xmax", "ymin", "ymax", "zmin", "zmax"];

/// A pair of bodies in (or near) contact.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Contact {
    pub i: usize,
    pub j: usize,
    /// Surface separation [m]; negative for overlap.
    pub gap: f64,
}

/// Contacts between bodies of a packing, the bodies on each domain face and bonds.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ContactGraph {
    pub contacts: Vec<Contact>,
    /// Bodies on each face, in [`FACE_NAMES`] order (the paper's ListXmin .. ListZmax).
    pub faces: [Vec<usize>; 6],
    /// Bonded pairs (i < j), e.g. sinter necks, cement bridges, peridynamic bonds.
    pub bonds: Vec<[usize; 2]>,
    /// Named per-bond values, each with one value per entry of `bonds` (neck radius, stretch,
    /// damage, ...).
    pub bond_attributes: IndexMap<String, BodyAttribute>,
    /// Body positions, so the graph can be drawn on its own (lines between centres).
    pub positions: Vec<[f64; 3]>,
    /// Body radii [m], one per position, so the bodies can be glyphed from the graph alone;
    /// empty when the bodies are not spheres.
    #[serde(default)]
    pub radii: Vec<f64>,
}

impl ContactGraph {
    /// Checks that pairs refer to known positions and every bond attribute has one value per
    /// bond (a malformed graph must not produce a file that opens with garbage).
    pub fn validate(&self) -> Result<(), String> {
        let n = self.positions.len();
        let pairs = self
            .contacts
            .iter()
            .map(|c| [c.i, c.j])
            .chain(self.bonds.iter().copied());
        for [i, j] in pairs {
            if i >= n || j >= n {
                return Err(format!(
                    "contact graph pair ({i}, {j}) refers past its {n} positions"
                ));
            }
        }
        if !self.radii.is_empty() && self.radii.len() != n {
            return Err(format!(
                "contact graph has {} radii for {n} positions",
                self.radii.len()
            ));
        }
        for (name, a) in &self.bond_attributes {
            if a.values.len() != self.bonds.len() {
                return Err(format!(
                    "bond attribute `{name}` has {} values for {} bonds",
                    a.values.len(),
                    self.bonds.len()
                ));
            }
        }
        Ok(())
    }
}

/// Values of one table column.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ColumnData {
    F64(Vec<f64>),
    I64(Vec<i64>),
    Str(Vec<String>),
}

impl ColumnData {
    pub fn len(&self) -> usize {
        match self {
            ColumnData::F64(v) => v.len(),
            ColumnData::I64(v) => v.len(),
            ColumnData::Str(v) => v.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Column {
    pub name: String,
    pub unit: String,
    pub data: ColumnData,
}

/// Named columns of equal length, each with a unit.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Table {
    pub name: String,
    pub columns: Vec<Column>,
}

impl Table {
    pub fn new(name: impl Into<String>) -> Self {
        Table {
            name: name.into(),
            columns: Vec::new(),
        }
    }
    pub fn with_f64(mut self, name: &str, unit: &str, values: Vec<f64>) -> Self {
        self.columns.push(Column {
            name: name.into(),
            unit: unit.into(),
            data: ColumnData::F64(values),
        });
        self
    }
    pub fn with_i64(mut self, name: &str, unit: &str, values: Vec<i64>) -> Self {
        self.columns.push(Column {
            name: name.into(),
            unit: unit.into(),
            data: ColumnData::I64(values),
        });
        self
    }
    pub fn with_str(mut self, name: &str, values: Vec<String>) -> Self {
        self.columns.push(Column {
            name: name.into(),
            unit: String::new(),
            data: ColumnData::Str(values),
        });
        self
    }
    pub fn rows(&self) -> usize {
        self.columns.first().map(|c| c.data.len()).unwrap_or(0)
    }
    pub fn column(&self, name: &str) -> Option<&Column> {
        self.columns.iter().find(|c| c.name == name)
    }
    pub fn f64_column(&self, name: &str) -> Option<&[f64]> {
        match &self.column(name)?.data {
            ColumnData::F64(v) => Some(v),
            _ => None,
        }
    }
    /// Checks that every column has the same length.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.rows();
        for c in &self.columns {
            if c.data.len() != n {
                return Err(format!(
                    "table `{}`: column `{}` has {} rows, expected {n}",
                    self.name,
                    c.name,
                    c.data.len()
                ));
            }
        }
        Ok(())
    }
}

/// How a symmetric tensor is laid out in its matrix form.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum TensorConvention {
    /// Full components, row-major.
    Plain,
    /// 6x6 in Voigt notation (order 11, 22, 33, 23, 13, 12; no sqrt(2) factors).
    Voigt,
    /// 6x6 in Mandel notation (order 11, 22, 33, 23, 13, 12; shear rows/columns scaled by sqrt 2).
    Mandel,
}

/// A small dense tensor (stiffness, permeability, orientation tensor, ...).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tensor {
    pub name: String,
    pub unit: String,
    pub shape: Vec<usize>,
    /// Row-major values.
    pub values: Vec<f64>,
    pub convention: TensorConvention,
}

/// A time series of artifacts of one kind (e.g. temperature snapshots of a packing).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Series {
    /// (time [s], frame) in increasing time.
    pub frames: Vec<(f64, Artifact)>,
}

/// Named artifacts that belong together but are not a time series: the grains of a sample,
/// the realizations of an ensemble, the load cases of a homogenization. (A [`Series`] is
/// ordered by physical time; a collection by item.)
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Collection {
    /// (name, item), in order.
    pub items: Vec<(String, Artifact)>,
}

impl Collection {
    pub fn len(&self) -> usize {
        self.items.len()
    }
    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }
    /// The item called `name`.
    pub fn get(&self, name: &str) -> Option<&Artifact> {
        self.items.iter().find(|(n, _)| n == name).map(|(_, a)| a)
    }
}

/// Anything a stage takes or gives.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Artifact {
    PhaseImage(PhaseImage),
    Field(Field),
    ClumpLibrary(ClumpLibrary),
    Packing(Packing),
    ContactGraph(ContactGraph),
    Table(Table),
    Tensor(Tensor),
    Series(Series),
    Collection(Collection),
}

/// The kind of an [`Artifact`], used to type-check pipelines before anything runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ArtifactKind {
    PhaseImage,
    Field,
    ClumpLibrary,
    Packing,
    ContactGraph,
    Table,
    Tensor,
    Series,
    Collection,
}

impl fmt::Display for ArtifactKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{self:?}")
    }
}

impl Artifact {
    /// Checks the artifact's internal consistency: array lengths agree with the grid and
    /// component count, bodies refer to clumps that exist, table columns and attributes have
    /// one value per row or body, series and collections recursively. Artifacts that come from
    /// outside a stage's own code (cache entries, plugins) are checked with this before use,
    /// so a malformed one is an error instead of an index panic further down.
    pub fn validate(&self) -> Result<(), String> {
        match self {
            Artifact::PhaseImage(x) => {
                x.grid.validate(1)?;
                if x.labels.len() != x.grid.voxel_count() {
                    return Err(format!(
                        "phase image has {} labels for a {:?} grid",
                        x.labels.len(),
                        x.grid.dims
                    ));
                }
            }
            Artifact::Field(x) => {
                x.grid.validate(8)?;
                let want = checked_product(&[x.grid.voxel_count(), x.components]);
                if x.components == 0 || want != Some(x.data.len()) {
                    return Err(format!(
                        "field `{}` has {} values for a {:?} grid of {} components",
                        x.name,
                        x.data.len(),
                        x.grid.dims,
                        x.components
                    ));
                }
            }
            Artifact::ClumpLibrary(_) => {}
            Artifact::Tensor(t) => {
                if checked_product(&t.shape) != Some(t.values.len()) {
                    return Err(format!(
                        "tensor `{}` has {} values for shape {:?}",
                        t.name,
                        t.values.len(),
                        t.shape
                    ));
                }
            }
            Artifact::Packing(p) => {
                let clumps = p.library.as_ref().map(|l| l.clumps.len()).unwrap_or(0);
                for (k, b) in p.bodies.iter().enumerate() {
                    if let BodyShape::Clump { index } = b.shape {
                        if index >= clumps {
                            return Err(format!(
                                "body {k} refers to clump {index} of a library of {clumps}"
                            ));
                        }
                    }
                }
                for (name, a) in &p.attributes {
                    if a.values.len() != p.bodies.len() {
                        return Err(format!(
                            "body attribute `{name}` has {} values for {} bodies",
                            a.values.len(),
                            p.bodies.len()
                        ));
                    }
                }
            }
            Artifact::ContactGraph(g) => g.validate()?,
            Artifact::Table(t) => t.validate()?,
            Artifact::Series(s) => {
                for (_, f) in &s.frames {
                    f.validate()?;
                }
            }
            Artifact::Collection(c) => {
                for (name, item) in &c.items {
                    item.validate().map_err(|e| format!("item `{name}`: {e}"))?;
                }
            }
        }
        Ok(())
    }

    pub fn kind(&self) -> ArtifactKind {
        match self {
            Artifact::PhaseImage(_) => ArtifactKind::PhaseImage,
            Artifact::Field(_) => ArtifactKind::Field,
            Artifact::ClumpLibrary(_) => ArtifactKind::ClumpLibrary,
            Artifact::Packing(_) => ArtifactKind::Packing,
            Artifact::ContactGraph(_) => ArtifactKind::ContactGraph,
            Artifact::Table(_) => ArtifactKind::Table,
            Artifact::Tensor(_) => ArtifactKind::Tensor,
            Artifact::Series(_) => ArtifactKind::Series,
            Artifact::Collection(_) => ArtifactKind::Collection,
        }
    }
}

macro_rules! artifact_accessors {
    ($($fn_name:ident => $variant:ident),* $(,)?) => {
        impl Artifact {
            $(
                pub fn $fn_name(&self) -> Option<&$variant> {
                    match self {
                        Artifact::$variant(x) => Some(x),
                        _ => None,
                    }
                }
            )*
        }
    };
}

artifact_accessors! {
    as_phase_image => PhaseImage,
    as_field => Field,
    as_clump_library => ClumpLibrary,
    as_packing => Packing,
    as_contact_graph => ContactGraph,
    as_table => Table,
    as_tensor => Tensor,
    as_series => Series,
    as_collection => Collection,
}

/// What preflight knows about an artifact before it exists: its kind, and whatever the
/// parameters and the inputs' metadata determine (the grid of voxel artifacts, the box,
/// periodicity and body-count bounds of packings). The engine holds the produced artifact to
/// every field that is set ([`ArtifactMeta::check`]).
#[derive(Clone, Debug, PartialEq)]
pub struct ArtifactMeta {
    pub kind: ArtifactKind,
    pub grid: Option<Grid>,
    /// Estimated number of items (bodies, clumps, contacts, rows, frames) for memory
    /// estimates; 0 when unknown. Not checked.
    pub count_estimate: u64,
    /// Inclusive bounds on that number, when the parameters fix them. Checked.
    pub count_bounds: Option<[u64; 2]>,
    /// The box of a packing (min, max corners) when known before running.
    pub domain_box: Option<([f64; 3], [f64; 3])>,
    /// The periodic axes of a packing's domain when known before running.
    pub periodic: Option<[bool; 3]>,
    /// A typical body size (mean diameter) [m] when known before running. Not checked.
    pub length_scale: Option<f64>,
    /// The exact mean volume-equivalent body diameter of a packing [m], when the parameters
    /// fix it (equal spheres). Checked to 1e-9 relative.
    pub mean_diameter: Option<f64>,
    /// Per-item sizes of a grain collection or clump library when preflight knows them
    /// (e.g. from coefficient files), for downstream preflight checks such as a size cap.
    /// Estimates, not checked.
    pub item_sizes: Option<Vec<ItemSize>>,
    /// The phase table of a phase image when the parameters fix it (ids and names). Checked:
    /// the produced image has exactly these phases. Exports check phase selections against it.
    pub phases: Option<Vec<Phase>>,
}

/// What preflight knows of one grain: its name, volume [m^3] and bounding-sphere diameter
/// about its centroid [m].
#[derive(Clone, Debug, PartialEq)]
pub struct ItemSize {
    pub name: String,
    pub volume: f64,
    pub bounding_diameter: f64,
}

impl ArtifactMeta {
    pub fn of(kind: ArtifactKind) -> Self {
        ArtifactMeta {
            kind,
            grid: None,
            count_estimate: 0,
            count_bounds: None,
            domain_box: None,
            periodic: None,
            length_scale: None,
            mean_diameter: None,
            item_sizes: None,
            phases: None,
        }
    }

    /// A voxel artifact on a known grid.
    pub fn on_grid(kind: ArtifactKind, grid: Grid) -> Self {
        ArtifactMeta {
            count_estimate: grid.voxel_count() as u64,
            grid: Some(grid),
            ..ArtifactMeta::of(kind)
        }
    }

    /// A packing whose domain box and periodicity are known.
    pub fn packing(min: [f64; 3], max: [f64; 3], periodic: [bool; 3]) -> Self {
        ArtifactMeta {
            domain_box: Some((min, max)),
            periodic: Some(periodic),
            ..ArtifactMeta::of(ArtifactKind::Packing)
        }
    }

    pub fn with_count(mut self, estimate: u64, bounds: Option<[u64; 2]>) -> Self {
        self.count_estimate = estimate;
        self.count_bounds = bounds;
        self
    }

    /// Announces the exact phase table of a phase image.
    pub fn with_phases(mut self, phases: Vec<Phase>) -> Self {
        self.phases = Some(phases);
        self
    }

    pub fn with_length_scale(mut self, length: f64) -> Self {
        self.length_scale = Some(length);
        self
    }

    /// Announces the exact mean volume-equivalent diameter (and uses it as length scale).
    pub fn with_mean_diameter(mut self, diameter: f64) -> Self {
        self.mean_diameter = Some(diameter);
        self.length_scale = Some(diameter);
        self
    }

    /// The number of items in `a` that `count_bounds` speaks of.
    pub fn count_of(a: &Artifact) -> u64 {
        (match a {
            Artifact::PhaseImage(x) => x.labels.len(),
            Artifact::Field(x) => x.grid.voxel_count(),
            Artifact::ClumpLibrary(x) => x.clumps.len(),
            Artifact::Packing(x) => x.bodies.len(),
            Artifact::ContactGraph(x) => x.contacts.len(),
            Artifact::Table(x) => x.rows(),
            Artifact::Tensor(x) => x.values.len(),
            Artifact::Series(x) => x.frames.len(),
            Artifact::Collection(x) => x.items.len(),
        }) as u64
    }

    /// Checks a produced artifact against this announcement; the message says what differs.
    pub fn check(&self, a: &Artifact) -> Result<(), String> {
        if a.kind() != self.kind {
            return Err(format!("announced a {} but gave a {}", self.kind, a.kind()));
        }
        if let Some(g) = &self.grid {
            let got = match a {
                Artifact::PhaseImage(x) => Some(&x.grid),
                Artifact::Field(x) => Some(&x.grid),
                _ => None,
            };
            if let Some(got) = got {
                if !grids_agree(g, got) {
                    return Err(format!("announced the grid {g:?} but gave {got:?}"));
                }
            }
        }
        if let (Some(announced), Artifact::PhaseImage(img)) = (&self.phases, a) {
            let key = |t: &[Phase]| {
                let mut v: Vec<(u8, String)> = t.iter().map(|p| (p.id, p.name.clone())).collect();
                v.sort();
                v
            };
            if key(announced) != key(&img.phases) {
                return Err(format!(
                    "announced the phases {:?} but gave {:?}",
                    key(announced),
                    key(&img.phases)
                ));
            }
        }
        if let Artifact::Packing(p) = a {
            if let Some((min, max)) = self.domain_box {
                let scale = (0..3)
                    .map(|k| (max[k] - min[k]).abs())
                    .fold(0.0f64, f64::max)
                    .max(f64::MIN_POSITIVE);
                let close =
                    |u: [f64; 3], v: [f64; 3]| (0..3).all(|k| (u[k] - v[k]).abs() <= 1e-9 * scale);
                if !close(min, p.domain.min) || !close(max, p.domain.max) {
                    return Err(format!(
                        "announced the domain box {min:?}..{max:?} but gave {:?}..{:?}",
                        p.domain.min, p.domain.max
                    ));
                }
            }
            if let Some(d) = self.mean_diameter {
                let got = p.mean_diameter();
                if (got - d).abs() > 1e-9 * d.abs() {
                    return Err(format!(
                        "announced a mean body diameter of {d:e} m but gave {got:e} m"
                    ));
                }
            }
            if let Some(per) = self.periodic {
                if per != p.domain.periodic {
                    return Err(format!(
                        "announced periodic axes {per:?} but gave {:?}",
                        p.domain.periodic
                    ));
                }
            }
        }
        if let Some([lo, hi]) = self.count_bounds {
            let n = Self::count_of(a);
            if n < lo || n > hi {
                return Err(format!(
                    "announced between {lo} and {hi} items but gave {n}"
                ));
            }
        }
        Ok(())
    }
}

/// Same dims and periodicity; spacing and origin equal to 1e-6 of a voxel.
pub fn grids_agree(a: &Grid, b: &Grid) -> bool {
    a.dims == b.dims
        && a.periodic == b.periodic
        && (0..3).all(|k| {
            let tol = 1e-6 * a.spacing[k].abs().max(f64::MIN_POSITIVE);
            (a.spacing[k] - b.spacing[k]).abs() <= tol && (a.origin[k] - b.origin[k]).abs() <= tol
        })
}

/// Metadata about how an artifact was made, written into every exported file.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    pub entries: IndexMap<String, String>,
}

impl Provenance {
    /// Entries whose values are unsigned integers (the 64-bit seeds): formats with numbers
    /// write them as numbers, so a reader gets the seed exactly and as an integer.
    pub const INTEGER_KEYS: [&'static str; 2] = ["seed", "stage_seed"];

    /// The value of `key` as a number when it is one of [`Self::INTEGER_KEYS`] and parses.
    pub fn integer(&self, key: &str) -> Option<u64> {
        if !Self::INTEGER_KEYS.contains(&key) {
            return None;
        }
        self.entries.get(key)?.parse().ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternion_rotation_matches_rotation_matrix() {
        // 90 degrees about z: x -> y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let v = rotate([h, 0.0, 0.0, h], [1.0, 0.0, 0.0]);
        assert!((v[0]).abs() < 1e-15 && (v[1] - 1.0).abs() < 1e-15 && v[2].abs() < 1e-15);
    }

    #[test]
    fn sphere_packing_fraction_is_analytic() {
        let mut p = Packing::new(Domain::boxed([0.0; 3], [1.0; 3], [true; 3]));
        p.bodies.push(Body::sphere([0.5; 3], 0.25));
        let expected = 4.0 / 3.0 * PI * 0.25f64.powi(3);
        assert!((p.volume_fraction() - expected).abs() < 1e-15);
    }
}
