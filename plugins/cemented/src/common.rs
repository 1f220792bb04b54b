//! Conventions shared by the stages of this crate: particle classes, 2-D samples, labels.

use grainpipe_core::{BodyShape, Packing, Phase, StageError};

/// Per-body attribute holding the particle class: [`LARGE`] or [`SMALL`].
pub const CLASS_ATTR: &str = "class";
/// Per-body attribute: 1 when the body is a disk of a 2-D sample (unit thickness), 0 for a
/// sphere. The data model only knows spheres, so the dimension travels with the bodies.
pub const DISK_ATTR: &str = "disk";

/// Phase labels (shared with `peridynamics.bond_based` and `analysis.stress_stats`). Label 0
/// is the phase `pore` of the vocabulary (the paper's "void": empty space); `VOID` keeps the
/// paper's word because `analysis.pores` measures the paper's single voids on it.
pub const VOID: u8 = 0;
pub const LARGE: u8 = 1;
pub const SMALL: u8 = 2;
pub const MATRIX: u8 = 3;

/// The phase table of the images this crate writes, in the vocabulary of
/// [`grainpipe_core::phases`]: `pore`, and the paper's classes `large`, `small`, `matrix`.
pub fn phases() -> Vec<Phase> {
    use grainpipe_core::phases::{LARGE as L, MATRIX as M, PORE, SMALL as S};
    [(VOID, PORE), (LARGE, L), (SMALL, S), (MATRIX, M)]
        .into_iter()
        .map(|(id, name)| Phase {
            id,
            name: name.to_string(),
        })
        .collect()
}

/// The particles of a packing as plain arrays (positions, radii, classes) plus its dimension.
#[derive(Clone, Debug)]
pub struct Particles {
    pub pos: Vec<[f64; 3]>,
    pub radius: Vec<f64>,
    /// [`LARGE`] or [`SMALL`].
    pub class: Vec<u8>,
    /// 2 for disks, 3 for spheres.
    pub dim: usize,
}

impl Particles {
    /// Reads sphere bodies and the `class` attribute (required) and `disk` attribute (absent =
    /// spheres) of a packing; `port` names the input in errors.
    pub fn from_packing(p: &Packing, port: &str) -> Result<Particles, StageError> {
        let n = p.bodies.len();
        let mut pos = Vec::with_capacity(n);
        let mut radius = Vec::with_capacity(n);
        for (i, b) in p.bodies.iter().enumerate() {
            match b.shape {
                BodyShape::Sphere { radius: r } => {
                    pos.push(b.position);
                    radius.push(r);
                }
                BodyShape::Clump { .. } => {
                    return Err(StageError::input(
                        port,
                        format!("body {i} is a clump; this stage takes disks or spheres"),
                    ))
                }
            }
        }
        let class = match p.attributes.get(CLASS_ATTR) {
            Some(a) if a.values.len() == n => a
                .values
                .iter()
                .enumerate()
                .map(|(i, &v)| {
                    if v == LARGE as f64 {
                        Ok(LARGE)
                    } else if v == SMALL as f64 {
                        Ok(SMALL)
                    } else {
                        Err(StageError::input(
                            port,
                            format!("body {i} has class {v}; expected 1 (large) or 2 (small)"),
                        ))
                    }
                })
                .collect::<Result<Vec<u8>, StageError>>()?,
            _ => {
                return Err(StageError::input(
                    port,
                    format!(
                        "the packing needs a per-body `{CLASS_ATTR}` attribute (1 = large, \
                         2 = small), as packing.poisson_disk writes"
                    ),
                ))
            }
        };
        let dim = match p.attributes.get(DISK_ATTR) {
            Some(a) if a.values.len() == n && n > 0 => {
                if a.values.iter().all(|&v| v == 1.0) {
                    2
                } else if a.values.iter().all(|&v| v == 0.0) {
                    3
                } else {
                    return Err(StageError::input(
                        port,
                        "the `disk` attribute mixes disks and spheres",
                    ));
                }
            }
            _ => 3,
        };
        Ok(Particles {
            pos,
            radius,
            class,
            dim,
        })
    }

    pub fn len(&self) -> usize {
        self.radius.len()
    }

    pub fn is_empty(&self) -> bool {
        self.radius.is_empty()
    }

    /// Area (2-D, per unit thickness) or volume (3-D) of particle `i`.
    pub fn measure(&self, i: usize) -> f64 {
        measure(self.dim, self.radius[i])
    }
}

/// Area of a disk (dim 2) or volume of a sphere (dim 3) of radius `r`.
pub fn measure(dim: usize, r: f64) -> f64 {
    use std::f64::consts::PI;
    if dim == 2 {
        PI * r * r
    } else {
        4.0 / 3.0 * PI * r * r * r
    }
}

pub fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

pub fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
