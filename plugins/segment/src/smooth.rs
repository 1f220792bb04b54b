//! Smoothing kernels on a scalar volume (x fastest): median over a cubic or spherical window
//! and a separable, truncated Gaussian.
//!
//! Boundaries: a periodic axis wraps; a non-periodic axis is reflected about the image face
//! with the edge voxel repeated (`... c b a | a b c ...`, "half-sample symmetric", scipy's
//! `reflect`), repeatedly when the window is wider than the image.
//!
//! Every output voxel is computed by one thread from the input alone, so results do not
//! depend on the number of threads.

use rayon::prelude::*;

/// The index of the voxel at signed position `i` along an axis of `n` voxels.
pub fn boundary_index(i: isize, n: usize, periodic: bool) -> usize {
    let n = n as isize;
    if periodic {
        i.rem_euclid(n) as usize
    } else {
        let m = i.rem_euclid(2 * n);
        (if m < n { m } else { 2 * n - 1 - m }) as usize
    }
}

/// The shape of a median window.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Window {
    /// Every offset with `|dx|, |dy|, |dz| <= r`: (2r + 1)^3 voxels.
    Cube,
    /// Offsets with `dx^2 + dy^2 + dz^2 <= r^2`.
    Ball,
}

/// The offsets of a window of radius `r` in voxels, in raster order.
pub fn window_offsets(r: usize, window: Window) -> Vec<[isize; 3]> {
    let r = r as isize;
    let mut out = Vec::new();
    for dz in -r..=r {
        for dy in -r..=r {
            for dx in -r..=r {
                if window == Window::Cube || dx * dx + dy * dy + dz * dz <= r * r {
                    out.push([dx, dy, dz]);
                }
            }
        }
    }
    out
}

/// Median over the window around every voxel. Windows are symmetric and hold the centre, so
/// they have an odd number of voxels and the median is one of the values. NaNs sort last.
pub fn median(
    data: &[f64],
    dims: [usize; 3],
    periodic: [bool; 3],
    r: usize,
    window: Window,
) -> Vec<f64> {
    let [nx, ny, nz] = dims;
    assert_eq!(data.len(), nx * ny * nz);
    let offsets = window_offsets(r, window);
    let mid = offsets.len() / 2;
    // Per axis, the index of every position from -r to n - 1 + r.
    let maps: Vec<Vec<usize>> = (0..3)
        .map(|a| {
            (-(r as isize)..(dims[a] + r) as isize)
                .map(|i| boundary_index(i, dims[a], periodic[a]))
                .collect()
        })
        .collect();
    let mut out = vec![0.0; data.len()];
    out.par_chunks_mut(nx).enumerate().for_each_init(
        || Vec::with_capacity(offsets.len()),
        |buf: &mut Vec<f64>, (row, line)| {
            let (y, z) = (row % ny, row / ny);
            for (x, o) in line.iter_mut().enumerate() {
                buf.clear();
                for d in &offsets {
                    let xi = maps[0][(x as isize + d[0]) as usize + r];
                    let yi = maps[1][(y as isize + d[1]) as usize + r];
                    let zi = maps[2][(z as isize + d[2]) as usize + r];
                    buf.push(data[xi + nx * (yi + ny * zi)]);
                }
                let (_, m, _) = buf.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
                *o = *m;
            }
        },
    );
    out
}

/// The weights of a Gaussian of standard deviation `sigma` (voxels) truncated at `radius`
/// voxels either side: `w_k = exp(-k^2 / (2 sigma^2))` for `k = -radius..=radius`, normalised
/// to sum 1. `sigma == 0` gives the identity.
pub fn gaussian_weights(sigma: f64, radius: usize) -> Vec<f64> {
    if sigma <= 0.0 {
        return vec![1.0];
    }
    let r = radius as isize;
    let w: Vec<f64> = (-r..=r)
        .map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let s: f64 = w.iter().sum();
    w.into_iter().map(|x| x / s).collect()
}

/// The truncation radius of a Gaussian: `ceil(truncate * sigma)` voxels.
pub fn gaussian_radius(sigma: f64, truncate: f64) -> usize {
    (truncate * sigma).ceil().max(0.0) as usize
}

/// One 1-D convolution pass along `axis` with the symmetric `weights` (odd length).
pub fn convolve_axis(
    data: &[f64],
    dims: [usize; 3],
    periodic: bool,
    axis: usize,
    weights: &[f64],
) -> Vec<f64> {
    let [nx, ny, _] = dims;
    let n = dims[axis];
    let r = weights.len() / 2;
    let map: Vec<usize> = (-(r as isize)..(n + r) as isize)
        .map(|i| boundary_index(i, n, periodic))
        .collect();
    let stride = [1, nx, nx * ny][axis];
    let mut out = vec![0.0; data.len()];
    // Whole z planes in parallel; within a plane every line along `axis` starts at a voxel
    // whose coordinate along `axis` is 0.
    out.par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(z, plane)| {
            for (j, o) in plane.iter_mut().enumerate() {
                let i = z * nx * ny + j;
                let c = [j % nx, j / nx, z][axis];
                let start = i - c * stride;
                let mut acc = 0.0;
                for (k, w) in weights.iter().enumerate() {
                    acc += w * data[start + map[c + k] * stride];
                }
                *o = acc;
            }
        });
    out
}

/// Separable Gaussian: one pass per axis (x, then y, then z) with the per-axis `sigma`
/// (voxels) truncated at `ceil(truncate * sigma)` voxels. Axes of one voxel are left alone.
pub fn gaussian(
    data: &[f64],
    dims: [usize; 3],
    periodic: [bool; 3],
    sigma: [f64; 3],
    truncate: f64,
) -> Vec<f64> {
    assert_eq!(data.len(), dims.iter().product::<usize>());
    let mut cur = data.to_vec();
    for a in 0..3 {
        if dims[a] < 2 || sigma[a] <= 0.0 {
            continue;
        }
        let w = gaussian_weights(sigma[a], gaussian_radius(sigma[a], truncate));
        cur = convolve_axis(&cur, dims, periodic[a], a, &w);
    }
    cur
}
