//! How the image solvers (`elasticity.fft`, `conductivity.fft`, `stokes.permeability`)
//! close a cell whose image is not periodic along some axis: a CT scan or a cut sample.
//!
//! The solvers are periodic cell problems. An image states its periodic axes (a packing's
//! box is periodic; an import is not unless its file or `periodic:` says so), and where it
//! is not periodic the user chooses the boundary: glue opposite faces anyway (`periodic`,
//! warned), reflect the image (`mirror`), or, for flow, the permeameter (`walls`). Nothing is
//! guessed: a solver on a non-periodic image without a choice stops at preflight.
//!
//! The mirror kernels here work on plain slices and dims (x fastest) so that the solvers'
//! kernels, Python and MPI can use them without the framework types.

use crate::model::{Grid, PhaseImage};
use crate::stage::StageError;
use crate::subvoxel::Subvoxel;
use crate::{params, ParamChoice};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// How a solver closes the cell along the axes where the image is not periodic.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Boundary {
    /// The image is the periodic cell. Exact for a periodic image (a packing's box); on an
    /// image that is not periodic its opposite faces are glued together (a jump in the
    /// material at the faces, flow across them): allowed, warned, and recorded with the
    /// parameters in the provenance.
    Periodic,
    /// The image reflected across each axis along which it is not periodic: a periodic
    /// cell twice as long there (8 times the voxels for a scan), without jumps at the faces;
    /// the standard way to homogenise a sample with periodic solvers. The results are those
    /// of the mirrored cell (its normal-shear couplings vanish by symmetry); fields are
    /// given on the input's grid.
    Mirror,
    /// stokes.permeability only: the laboratory permeameter. No-slip walls on the faces of
    /// the non-periodic axes beside the flow, and fluid buffer layers (`buffer_voxels`)
    /// joining the outlet to the inlet along a non-periodic flow axis; the apparent
    /// permeability per direction from the flow rate and the pressure drop between the
    /// inlet and outlet faces.
    Walls,
}

impl Boundary {
    pub fn name(self) -> &'static str {
        match self {
            Boundary::Periodic => "periodic",
            Boundary::Mirror => "mirror",
            Boundary::Walls => "walls",
        }
    }
}

/// The boundary choice shared by the image solvers.
#[params]
pub struct BoundaryParams {
    /// How the cell is closed where the image is not periodic: `periodic`, `mirror` or
    /// (stokes.permeability) `walls`. Default: `periodic` for an image periodic along every
    /// axis; any other image needs a choice (preflight names them).
    pub boundary: Option<Boundary>,
}

/// What a boundary choice means for one image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ResolvedBoundary {
    pub boundary: Boundary,
    /// Axes along which the image is not periodic.
    pub open: [bool; 3],
    /// Axes the image is reflected across (`mirror`: the open axes).
    pub mirror: [bool; 3],
}

/// The axes set in `mask` as "x, z" ("" when none).
pub fn axis_list(mask: [bool; 3]) -> String {
    ["x", "y", "z"]
        .iter()
        .zip(mask)
        .filter(|(_, m)| *m)
        .map(|(a, _)| *a)
        .collect::<Vec<_>>()
        .join(", ")
}

impl BoundaryParams {
    /// The boundary for an image periodic along `periodic`, for a solver that offers
    /// `allowed`; an error on the key `boundary` naming the choices when the image is not
    /// periodic and none was made, or when the choice is not offered.
    pub fn resolve(
        &self,
        periodic: [bool; 3],
        allowed: &[Boundary],
    ) -> Result<ResolvedBoundary, StageError> {
        let open = periodic.map(|p| !p);
        let names = allowed
            .iter()
            .map(|b| format!("`{}`", b.name()))
            .collect::<Vec<_>>()
            .join(", ");
        let boundary = match self.boundary {
            Some(b) if !allowed.contains(&b) => {
                return Err(StageError::param(
                    "boundary",
                    format!(
                        "`{}` is not a boundary of this solver (walls are the permeameter of \
                         stokes.permeability); choose one of {names}",
                        b.name()
                    ),
                ))
            }
            Some(b) => b,
            None if open.iter().any(|&o| o) => {
                let walls = if allowed.contains(&Boundary::Walls) {
                    ", `walls` (no-slip side walls and inlet/outlet buffers: the permeameter)"
                } else {
                    ""
                };
                return Err(StageError::param(
                    "boundary",
                    format!(
                        "the image is not periodic along {} (a scan or a cut sample; an \
                         import states its periodic axes with `periodic: [x, y, z]`), so the \
                         periodic cell problem needs a boundary: `mirror` (the image reflected \
                         across those axes, {}x the voxels, no jumps at the faces){walls}, or \
                         `periodic` to glue its opposite faces anyway",
                        axis_list(open),
                        1 << open.iter().filter(|&&o| o).count()
                    ),
                ));
            }
            None => Boundary::Periodic,
        };
        Ok(ResolvedBoundary {
            boundary,
            open,
            mirror: if boundary == Boundary::Mirror {
                open
            } else {
                [false; 3]
            },
        })
    }
}

impl ResolvedBoundary {
    /// The warning a run gives for this choice: faces glued by `periodic`, or a choice
    /// that changes nothing on a periodic image.
    pub fn warning(&self) -> Option<String> {
        let open = axis_list(self.open);
        match self.boundary {
            Boundary::Periodic if !open.is_empty() => Some(format!(
                "boundary: periodic on an image that is not periodic along {open}: its \
                 opposite faces are glued together (material jumps and flow across them); \
                 `mirror` avoids the jumps"
            )),
            Boundary::Mirror | Boundary::Walls if open.is_empty() => Some(format!(
                "boundary: {} on an image periodic along every axis changes nothing; the \
                 periodic cell is solved",
                self.boundary.name()
            )),
            _ => None,
        }
    }

    /// The voxel count the solver holds: the input's, times 2 per mirrored axis.
    pub fn voxel_factor(&self) -> u64 {
        1 << self.mirror.iter().filter(|&&m| m).count()
    }

    /// The grid solved on: the mirrored cell (periodic along every axis) or the input's.
    pub fn solved_grid(&self, grid: &Grid) -> Grid {
        let mut g = grid.clone();
        if self.boundary == Boundary::Mirror {
            g.dims = mirrored_dims(grid.dims, self.mirror);
            g.periodic = [true; 3];
        }
        g
    }
}

/// Dims of the image reflected across `axes`.
pub fn mirrored_dims(dims: [usize; 3], axes: [bool; 3]) -> [usize; 3] {
    [0, 1, 2].map(|a| if axes[a] { 2 * dims[a] } else { dims[a] })
}

/// The voxel of the input (dims `dims`) that voxel `at` of the mirrored image shows, and
/// along which axes it is a reflection.
#[inline]
pub fn mirror_source(at: [usize; 3], dims: [usize; 3]) -> ([usize; 3], [bool; 3]) {
    let mut src = [0; 3];
    let mut flipped = [false; 3];
    for a in 0..3 {
        if at[a] < dims[a] {
            src[a] = at[a];
        } else {
            src[a] = 2 * dims[a] - 1 - at[a];
            flipped[a] = true;
        }
    }
    (src, flipped)
}

/// `data` (`comps` values per voxel, x fastest, dims `dims`) reflected across `axes`;
/// `flip(values, flipped_axes)` adjusts the values of a reflected voxel (a vector's
/// components along a reflected axis change sign).
pub fn mirror_with<T, F>(
    data: &[T],
    comps: usize,
    dims: [usize; 3],
    axes: [bool; 3],
    flip: F,
) -> Vec<T>
where
    T: Copy + Send + Sync + Default,
    F: Fn(&mut [T], [bool; 3]) + Sync,
{
    assert_eq!(data.len(), comps * dims.iter().product::<usize>());
    let out_dims = mirrored_dims(dims, axes);
    let plane = out_dims[0] * out_dims[1] * comps;
    let mut out = vec![T::default(); plane * out_dims[2]];
    out.par_chunks_mut(plane.max(1))
        .enumerate()
        .for_each(|(z, slab)| {
            for y in 0..out_dims[1] {
                for x in 0..out_dims[0] {
                    let (s, flipped) = mirror_source([x, y, z], dims);
                    let from = comps * (s[0] + dims[0] * (s[1] + dims[1] * s[2]));
                    let to = comps * (x + out_dims[0] * y);
                    let v = &mut slab[to..to + comps];
                    v.copy_from_slice(&data[from..from + comps]);
                    if flipped.iter().any(|&f| f) {
                        flip(v, flipped);
                    }
                }
            }
        });
    out
}

/// Scalars (labels, fractions) reflected across `axes`.
pub fn mirror<T: Copy + Send + Sync + Default>(
    data: &[T],
    comps: usize,
    dims: [usize; 3],
    axes: [bool; 3],
) -> Vec<T> {
    mirror_with(data, comps, dims, axes, |_, _| {})
}

/// The image reflected across `axes`: periodic along every axis, same origin and spacing.
pub fn mirror_image(image: &PhaseImage, axes: [bool; 3]) -> PhaseImage {
    let g = &image.grid;
    PhaseImage {
        grid: Grid {
            dims: mirrored_dims(g.dims, axes),
            periodic: [true; 3],
            ..g.clone()
        },
        labels: mirror(&image.labels, 1, g.dims, axes),
        phases: image.phases.clone(),
    }
}

/// Sub-voxel geometry reflected across `axes`: the fractions copied, each normal reflected.
pub fn mirror_subvoxel(sv: &Subvoxel, dims: [usize; 3], axes: [bool; 3]) -> Subvoxel {
    Subvoxel {
        phases: sv.phases,
        fractions: mirror(&sv.fractions, sv.phases, dims, axes),
        normals: mirror_with(&sv.normals, 1, dims, axes, |n, flipped| {
            for a in 0..3 {
                if flipped[a] {
                    n[0][a] = -n[0][a];
                }
            }
        }),
    }
}

/// The box of dims `small` at the lower corner of `data` (`comps` values per voxel, dims
/// `big`): a mirrored cell's field on the input's grid.
pub fn crop_lower<T: Copy + Send + Sync>(
    data: &[T],
    comps: usize,
    big: [usize; 3],
    small: [usize; 3],
) -> Vec<T> {
    assert!((0..3).all(|a| small[a] <= big[a]));
    assert_eq!(data.len(), comps * big.iter().product::<usize>());
    let row = small[0] * comps;
    (0..small[2])
        .into_par_iter()
        .flat_map_iter(|z| {
            (0..small[1]).flat_map(move |y| {
                let from = comps * big[0] * (y + big[1] * z);
                data[from..from + row].iter().copied()
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn resolve(
        b: Option<Boundary>,
        periodic: [bool; 3],
        allowed: &[Boundary],
    ) -> Result<ResolvedBoundary, String> {
        BoundaryParams { boundary: b }
            .resolve(periodic, allowed)
            .map_err(|e| e.to_string())
    }

    #[test]
    fn no_choice_on_a_scan_is_an_error_naming_the_axes_and_the_choices() {
        let fft = [Boundary::Periodic, Boundary::Mirror];
        let all = [Boundary::Periodic, Boundary::Mirror, Boundary::Walls];
        let e = resolve(None, [true, false, false], &fft).unwrap_err();
        assert!(
            e.contains("y, z")
                && e.contains("`mirror`")
                && e.contains("`periodic`")
                && e.contains("4x"),
            "{e}"
        );
        assert!(!e.contains("walls"), "{e}");
        let e = resolve(None, [false; 3], &all).unwrap_err();
        assert!(e.contains("`walls`") && e.contains("8x"), "{e}");
        let e = resolve(Some(Boundary::Walls), [false; 3], &fft).unwrap_err();
        assert!(e.contains("stokes.permeability"), "{e}");
        // periodic images need no choice; mirror reflects only the open axes
        assert_eq!(
            resolve(None, [true; 3], &fft).unwrap().boundary,
            Boundary::Periodic
        );
        let r = resolve(Some(Boundary::Mirror), [true, false, false], &fft).unwrap();
        assert_eq!(r.mirror, [false, true, true]);
        assert_eq!(r.voxel_factor(), 4);
        assert!(r.warning().is_none());
        let forced = resolve(Some(Boundary::Periodic), [false, true, true], &fft).unwrap();
        assert!(
            forced.warning().unwrap().contains("glued"),
            "{:?}",
            forced.warning()
        );
        assert_eq!(forced.voxel_factor(), 1);
    }

    #[test]
    fn the_mirror_reflects_each_open_axis_and_crop_undoes_it() {
        let dims = [3, 2, 2];
        let data: Vec<u32> = (0..12).collect();
        let axes = [true, false, true];
        let m = mirror(&data, 1, dims, axes);
        let md = mirrored_dims(dims, axes);
        assert_eq!(md, [6, 2, 4]);
        // brute force: m(x, y, z) = data(x or 5 - x, y, z or 3 - z)
        for z in 0..4 {
            for y in 0..2 {
                for x in 0..6 {
                    let sx = if x < 3 { x } else { 5 - x };
                    let sz = if z < 2 { z } else { 3 - z };
                    assert_eq!(m[x + 6 * (y + 2 * z)], data[sx + 3 * (y + 2 * sz)]);
                }
            }
        }
        assert_eq!(crop_lower(&m, 1, md, dims), data);
        // vectors: the component along a reflected axis changes sign
        let normals = vec![[0.6f32, 0.0, 0.8]; 12];
        let sv = Subvoxel {
            phases: 1,
            fractions: vec![1.0; 12],
            normals,
        };
        let msv = mirror_subvoxel(&sv, dims, axes);
        assert_eq!(msv.normals[0], [0.6, 0.0, 0.8]);
        assert_eq!(msv.normals[5], [-0.6, 0.0, 0.8]);
        assert_eq!(msv.normals[5 + 6 * 2 * 3], [-0.6, 0.0, -0.8]);
    }
}
