//! Specific surface (interface area per volume) of every label of a voxel image.
//!
//! Two estimators, both from transition counts `T_k(l)`: the number of voxel pairs
//! (p, p + o_k) where exactly one voxel has label `l`, along 13 lattice directions o_k (the 3
//! axes, 6 face diagonals, 4 space diagonals; each counted once, not with its opposite).
//! Pairs crossing a periodic face are counted with the wrapped neighbour; on a non-periodic
//! axis lines end at the image border, which is not an interface.
//!
//! - **Face count** `S_faces = sum_axes T_a(l) * (face area normal to a) / V`: the area of the
//!   voxel staircase. Exact for surfaces made of voxel faces (axis-aligned slabs), but it
//!   overestimates a smooth surface by the mean of |n_x| + |n_y| + |n_z| over its normals,
//!   which is 3/2 for isotropic orientations (a sphere) and up to sqrt 3 for a plane normal to
//!   a space diagonal.
//! - **Crofton** (Cauchy-Crofton formula, discretised after Ohser & Muecklich 2000 and
//!   Legland, Kieu & Devaux 2007, Image Anal. Stereol. 26:83-92): S_V = 2 * mean over
//!   directions of P_L, the number of interface crossings per unit line length;
//!   `S = 2 * sum_k w_k T_k / (N |o_k|)` with `N` the number of voxels (the lines of
//!   direction k through every voxel; so, like the face count, it is an area per image
//!   volume and the border of a non-periodic image is not an interface) and `w_k` the
//!   fraction of the unit sphere closest to direction +-o_k (its spherical Voronoi cell).
//!   For cubic voxels the weights are Legland's published values; for other spacings they
//!   are computed by quadrature over the sphere. Unbiased for isotropic structures (within
//!   the discretisation error of the digitised surface: 0.3 % for a ball of radius 20
//!   voxels, see the tests). For a single plane the response 2 sum_k w_k |n . o_k| lies between
//!   0.927 (normal along an axis) and 1.023 depending on the orientation, against 0.667 to
//!   1.155 for the three axes alone (the face count times 2/3).
//!
//! An axis one voxel thick is taken as extruded (neighbour = itself), so a 2-D image gives
//! the surface per volume of the prism it is the section of, i.e. its perimeter per area.

use rayon::prelude::*;

/// The 13 directions: 3 axes, 6 face diagonals, 4 space diagonals.
pub const DIRECTIONS: [[i32; 3]; 13] = [
    [1, 0, 0],
    [0, 1, 0],
    [0, 0, 1],
    [1, 1, 0],
    [1, -1, 0],
    [1, 0, 1],
    [1, 0, -1],
    [0, 1, 1],
    [0, 1, -1],
    [1, 1, 1],
    [1, 1, -1],
    [1, -1, 1],
    [1, -1, -1],
];

/// Legland et al. (2007): the spherical Voronoi cell areas of the 26 lattice directions
/// around an axis, a face diagonal and a space diagonal, over 4 pi, times 2 for +-o.
pub const CUBIC_WEIGHTS: [f64; 3] = [
    0.04577789120476 * 2.0,
    0.03698062787608 * 2.0,
    0.03519563978232 * 2.0,
];

/// Transition counts of an image.
#[derive(Clone, Debug, PartialEq)]
pub struct Transitions {
    /// Per direction of [`DIRECTIONS`] and label: pairs with exactly one voxel of the label.
    pub counts: Vec<[u64; 256]>,
    pub dims: [usize; 3],
}

/// Counts the label transitions along the 13 directions (parallel over z planes; integer
/// sums, so the result does not depend on the thread count).
pub fn transitions(labels: &[u8], dims: [usize; 3], periodic: [bool; 3]) -> Transitions {
    let [nx, ny, nz] = dims;
    assert_eq!(labels.len(), nx * ny * nz, "labels do not fill the grid");
    // A one-voxel axis is an extrusion: the neighbour along it is the voxel itself.
    let wrap: [bool; 3] = [0, 1, 2].map(|a| periodic[a] || dims[a] == 1);
    // Neighbour coordinate along one axis, or None past a non-periodic border.
    let step = |c: usize, d: i32, a: usize| -> Option<usize> {
        let n = dims[a] as i64;
        let t = c as i64 + d as i64;
        if (0..n).contains(&t) {
            Some(t as usize)
        } else if wrap[a] {
            Some(t.rem_euclid(n) as usize)
        } else {
            None
        }
    };
    let counts = (0..nz)
        .into_par_iter()
        .fold(
            || vec![[0u64; 256]; 13],
            |mut acc, z| {
                for (k, o) in DIRECTIONS.iter().enumerate() {
                    let Some(z2) = step(z, o[2], 2) else { continue };
                    for y in 0..ny {
                        let Some(y2) = step(y, o[1], 1) else { continue };
                        let row = nx * (y + ny * z);
                        let row2 = nx * (y2 + ny * z2);
                        let c = &mut acc[k];
                        for x in 0..nx {
                            let Some(x2) = step(x, o[0], 0) else { continue };
                            let (a, b) = (labels[row + x], labels[row2 + x2]);
                            if a != b {
                                c[a as usize] += 1;
                                c[b as usize] += 1;
                            }
                        }
                    }
                }
                acc
            },
        )
        .reduce(
            || vec![[0u64; 256]; 13],
            |mut a, b| {
                for (ak, bk) in a.iter_mut().zip(&b) {
                    for (x, y) in ak.iter_mut().zip(bk) {
                        *x += y;
                    }
                }
                a
            },
        );
    Transitions { counts, dims }
}

/// Length of direction `o` on a grid of `spacing` [m].
fn length(o: [i32; 3], spacing: [f64; 3]) -> f64 {
    (0..3)
        .map(|a| (o[a] as f64 * spacing[a]).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// Crofton weights of the 13 directions (sum 1): Legland's values for cubic voxels,
/// otherwise the spherical Voronoi cells of the physical directions by quadrature.
pub fn direction_weights(spacing: [f64; 3]) -> [f64; 13] {
    let cubic = (0..3).all(|a| (spacing[a] - spacing[0]).abs() <= 1e-12 * spacing[0].abs());
    if cubic {
        return std::array::from_fn(|k| CUBIC_WEIGHTS[[0, 0, 0, 1, 1, 1, 1, 1, 1, 2, 2, 2, 2][k]]);
    }
    voronoi_weights(spacing, 600)
}

/// Fraction of the unit sphere nearer to +-o_k (physical) than to any other direction, by a
/// midpoint rule on an equal-area grid (uniform in cos(theta) and phi, `n` x 2n cells).
pub fn voronoi_weights(spacing: [f64; 3], n: usize) -> [f64; 13] {
    let dirs: Vec<[f64; 3]> = DIRECTIONS
        .iter()
        .map(|o| {
            let l = length(*o, spacing);
            [0, 1, 2].map(|a| o[a] as f64 * spacing[a] / l)
        })
        .collect();
    let m = 2 * n;
    let hits: Vec<[u64; 13]> = (0..n)
        .into_par_iter()
        .map(|i| {
            let mut h = [0u64; 13];
            let c = -1.0 + (i as f64 + 0.5) * 2.0 / n as f64;
            let s = (1.0 - c * c).sqrt();
            for j in 0..m {
                let phi = (j as f64 + 0.5) * std::f64::consts::TAU / m as f64;
                let u = [s * phi.cos(), s * phi.sin(), c];
                // Nearest of +-o_k: the largest |u . o_k|.
                let mut best = (0, -1.0);
                for (k, d) in dirs.iter().enumerate() {
                    let dot = (u[0] * d[0] + u[1] * d[1] + u[2] * d[2]).abs();
                    if dot > best.1 {
                        best = (k, dot);
                    }
                }
                h[best.0] += 1;
            }
            h
        })
        .collect();
    let total = (n * m) as f64;
    std::array::from_fn(|k| hits.iter().map(|h| h[k]).sum::<u64>() as f64 / total)
}

/// Crofton estimate of the specific surface of `label` [1/m].
pub fn specific_surface(t: &Transitions, label: u8, spacing: [f64; 3]) -> f64 {
    let w = direction_weights(spacing);
    let n = t.dims.iter().product::<usize>() as f64;
    2.0 * (0..13)
        .map(|k| w[k] * t.counts[k][label as usize] as f64 / (n * length(DIRECTIONS[k], spacing)))
        .sum::<f64>()
}

/// Area of the voxel faces between `label` and other labels per image volume [1/m].
pub fn face_surface(t: &Transitions, label: u8, spacing: [f64; 3]) -> f64 {
    let n = t.dims.iter().product::<usize>() as f64;
    (0..3)
        .map(|a| t.counts[a][label as usize] as f64 / (n * spacing[a]))
        .sum()
}
