//! What the pore-space stages (`analysis.local_thickness`, `analysis.two_point`,
//! `analysis.chords`, `analysis.tortuosity`) share: the phase selection, the axes, the
//! memory estimate from the input's announced grid, the announced tables; and for their
//! kernels the voxel neighbourhood and the grid lines along an axis.

use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, InputMetas, Inputs, ParamChoice,
    PhaseImage, StageError,
};
use serde::{Deserialize, Serialize};

/// An axis of the image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Axis {
    /// Along x.
    X,
    /// Along y.
    Y,
    /// Along z.
    Z,
}

impl Axis {
    pub const ALL: [Axis; 3] = [Axis::X, Axis::Y, Axis::Z];
    pub fn index(self) -> usize {
        self as usize
    }
    pub fn name(self) -> &'static str {
        ["x", "y", "z"][self.index()]
    }
}

fn pore() -> Vec<u8> {
    vec![0]
}

/// The phase a pore-space measure is taken of.
#[params]
pub struct PhaseSelection {
    /// labels that together make the phase analysed (default: the pore space, label 0); run
    /// the stage once per phase for pore and solid measures, e.g. `phase: [1, 2]` for a
    /// solid made of grains and binder
    #[param(default = pore())]
    pub phase: Vec<u8>,
}

impl PhaseSelection {
    /// Refuses an empty or repeated label list.
    pub fn check(&self) -> Result<(), StageError> {
        if self.phase.is_empty() {
            return Err(StageError::param(
                "phase",
                "give at least one label, e.g. `phase: [0]` for the pore space",
            ));
        }
        for (k, l) in self.phase.iter().enumerate() {
            if self.phase[..k].contains(l) {
                return Err(StageError::param(
                    "phase",
                    format!("label {l} is listed twice"),
                ));
            }
        }
        Ok(())
    }

    /// Per voxel: whether it belongs to the phase.
    pub fn mask(&self, image: &PhaseImage) -> Result<Vec<bool>, StageError> {
        let n = image.grid.voxel_count();
        if image.labels.len() != n || n == 0 {
            return Err(StageError::input(
                "image",
                format!(
                    "{} labels for a grid of {:?} voxels",
                    image.labels.len(),
                    image.grid.dims
                ),
            ));
        }
        let mut member = [false; 256];
        for &l in &self.phase {
            member[l as usize] = true;
        }
        Ok(image.labels.iter().map(|&l| member[l as usize]).collect())
    }

    /// The input image of a stage and, per voxel, whether it belongs to the phase.
    pub fn image_and_mask<'a>(
        &self,
        inputs: &'a Inputs,
    ) -> Result<(&'a PhaseImage, Vec<bool>), StageError> {
        let image = input(inputs, "image", Artifact::as_phase_image)?;
        let mask = self.mask(image)?;
        Ok((image, mask))
    }

    /// The phase's name for tables: the phase-table names joined by `+`.
    pub fn name(&self, image: &PhaseImage) -> String {
        self.phase
            .iter()
            .map(|&l| {
                image
                    .phases
                    .iter()
                    .find(|p| p.id == l)
                    .map(|p| p.name.clone())
                    .unwrap_or_else(|| format!("phase{l}"))
            })
            .collect::<Vec<_>>()
            .join("+")
    }
}

/// Checks an axis list (non-empty, no repeats).
pub fn check_axes(key: &str, axes: &[Axis]) -> Result<(), StageError> {
    if axes.is_empty() {
        return Err(StageError::param(
            key,
            "give at least one axis, e.g. `[x, y, z]`",
        ));
    }
    for (k, a) in axes.iter().enumerate() {
        if axes[..k].contains(a) {
            return Err(StageError::param(
                key,
                format!("`{}` is listed twice", a.name()),
            ));
        }
    }
    Ok(())
}

/// Voxels of the input image as announced (its grid, else the count estimate; 0 unknown).
/// The longest edge of the announced image [voxels]: of its grid, or the cube root of its
/// announced voxel count.
pub fn announced_longest_edge(i: &InputMetas) -> u64 {
    i.get("image")
        .map(|m| {
            m.grid.as_ref().map_or_else(
                || (m.count_estimate as f64).cbrt().ceil() as u64,
                |g| g.dims.iter().copied().max().unwrap_or(0) as u64,
            )
        })
        .unwrap_or(0)
}

pub fn announced_voxels(i: &InputMetas) -> u64 {
    i.get("image")
        .map(|m| {
            m.grid
                .as_ref()
                .map_or(m.count_estimate, |g| g.voxel_count() as u64)
        })
        .unwrap_or(0)
}

/// The announcement of a table of exactly `rows` rows.
pub fn table_rows(rows: u64) -> ArtifactMeta {
    ArtifactMeta::of(ArtifactKind::Table).with_count(rows, Some([rows, rows]))
}

/// Linear index of voxel (x, y, z).
#[inline]
pub fn at(dims: [usize; 3], c: [usize; 3]) -> usize {
    c[0] + dims[0] * (c[1] + dims[1] * c[2])
}

/// Coordinates of linear index `i`.
#[inline]
pub fn coords(dims: [usize; 3], i: usize) -> [usize; 3] {
    [
        i % dims[0],
        (i / dims[0]) % dims[1],
        i / (dims[0] * dims[1]),
    ]
}

/// The 26 neighbour offsets of a voxel (x fastest, then y, then z), each with its physical
/// length.
pub fn neighbour_steps(spacing: [f64; 3]) -> Vec<([i64; 3], f64)> {
    let mut steps = Vec::with_capacity(26);
    for dz in -1i64..=1 {
        for dy in -1i64..=1 {
            for dx in -1i64..=1 {
                if (dx, dy, dz) != (0, 0, 0) {
                    let len = ((dx as f64 * spacing[0]).powi(2)
                        + (dy as f64 * spacing[1]).powi(2)
                        + (dz as f64 * spacing[2]).powi(2))
                    .sqrt();
                    steps.push(([dx, dy, dz], len));
                }
            }
        }
    }
    steps
}

/// Coordinate `t` on an axis of `n` voxels: itself inside the axis, wrapped onto it when
/// `wrap`, else None (past a face).
#[inline]
pub fn wrap_coord(t: i64, n: usize, wrap: bool) -> Option<usize> {
    let m = n as i64;
    if (0..m).contains(&t) {
        Some(t as usize)
    } else if wrap {
        Some(t.rem_euclid(m) as usize)
    } else {
        None
    }
}

/// Index of voxel `c` shifted by `o`, None past a face; the axes `wrap` marks wrap, except
/// one of a single voxel (a voxel is not its own neighbour).
#[inline]
pub fn neighbour(dims: [usize; 3], wrap: [bool; 3], c: [usize; 3], o: [i64; 3]) -> Option<usize> {
    let mut q = [0usize; 3];
    for a in 0..3 {
        q[a] = wrap_coord(c[a] as i64 + o[a], dims[a], wrap[a] && dims[a] > 1)?;
    }
    Some(at(dims, q))
}

/// The grid lines along one axis, in groups of lines sharing a z plane (x and y axes) or a
/// y row (z axis), so that the voxels of a group lie together in memory.
#[derive(Clone, Copy, Debug)]
pub struct AxisLines {
    dims: [usize; 3],
    axis: usize,
    /// Number of groups.
    pub groups: usize,
    /// Lines per group.
    pub per_group: usize,
    /// Index step between successive voxels of a line.
    pub stride: usize,
}

impl AxisLines {
    pub fn new(dims: [usize; 3], axis: usize) -> Self {
        let [nx, ny, nz] = dims;
        let (groups, per_group, stride) = match axis {
            0 => (nz, ny, 1),
            1 => (nz, nx, nx),
            _ => (ny, nx, nx * ny),
        };
        AxisLines {
            dims,
            axis,
            groups,
            per_group,
            stride,
        }
    }

    /// Index of the first voxel of line `l` of group `g`.
    #[inline]
    pub fn start(&self, g: usize, l: usize) -> usize {
        let [nx, ny, _] = self.dims;
        match self.axis {
            0 => nx * (l + ny * g),
            1 => l + nx * ny * g,
            _ => l + nx * g,
        }
    }
}
