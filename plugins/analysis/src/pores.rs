//! What the pore-space stages (`analysis.local_thickness`, `analysis.two_point`,
//! `analysis.chords`, `analysis.tortuosity`) share: the phase selection, the axes, the
//! memory estimate from the input's announced grid.

use grainpipe_core::{params, InputMetas, ParamChoice, PhaseImage, StageError};
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
pub fn announced_voxels(i: &InputMetas) -> u64 {
    i.get("image")
        .map(|m| {
            m.grid
                .as_ref()
                .map_or(m.count_estimate, |g| g.voxel_count() as u64)
        })
        .unwrap_or(0)
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
