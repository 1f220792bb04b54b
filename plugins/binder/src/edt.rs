//! Exact squared Euclidean distance transform on an anisotropic, partly periodic grid
//! (Felzenszwalb & Huttenlocher 2012: one lower envelope of parabolas per grid line and axis).
//! The closing baseline needs periodic wrap and physical spacing, which the clump
//! generator's transform (unit voxels, background outside the array) does not have.

use grainpipe_core::Grid;
use rayon::prelude::*;

const FAR: f64 = f64::INFINITY;

/// In place: `f[q] = min_p (w (q - p))^2 + f[p]` along one line; `periodic` lines wrap.
fn envelope(f: &mut [f64], w: f64, periodic: bool, scratch: &mut Scratch) {
    let n = f.len();
    // A periodic line is the middle third of three copies of itself.
    let copies = if periodic { 3 } else { 1 };
    let m = n * copies;
    scratch.resize(m);
    let Scratch { g, v, z, d } = scratch;
    for i in 0..m {
        g[i] = f[i % n];
    }
    let mut k = 0usize;
    let mut started = false;
    for q in 0..m {
        if g[q] == FAR {
            continue;
        }
        if !started {
            v[0] = q;
            z[0] = f64::NEG_INFINITY;
            z[1] = f64::INFINITY;
            started = true;
            continue;
        }
        loop {
            let p = v[k];
            let (qf, pf) = (q as f64 * w, p as f64 * w);
            let s = ((g[q] + qf * qf) - (g[p] + pf * pf)) / (2.0 * (qf - pf));
            if s <= z[k] {
                if k == 0 {
                    v[0] = q;
                    z[1] = f64::INFINITY;
                    break;
                }
                k -= 1;
                continue;
            }
            k += 1;
            v[k] = q;
            z[k] = s;
            z[k + 1] = f64::INFINITY;
            break;
        }
    }
    if !started {
        return;
    }
    let mut k = 0usize;
    for (q, dq) in d.iter_mut().enumerate().take(m) {
        let x = q as f64 * w;
        while z[k + 1] < x {
            k += 1;
        }
        let dx = x - v[k] as f64 * w;
        *dq = dx * dx + g[v[k]];
    }
    let off = if periodic { n } else { 0 };
    f.copy_from_slice(&d[off..off + n]);
}

#[derive(Default)]
struct Scratch {
    g: Vec<f64>,
    v: Vec<usize>,
    z: Vec<f64>,
    d: Vec<f64>,
}

impl Scratch {
    fn resize(&mut self, m: usize) {
        self.g.resize(m, 0.0);
        self.v.resize(m, 0);
        self.z.resize(m + 1, 0.0);
        self.d.resize(m, 0.0);
    }
}

/// Squared distance [m^2] from every voxel centre to the nearest centre of a voxel where
/// `feature` is true (infinite when there is none).
pub fn squared_distance(grid: &Grid, feature: impl Fn(usize) -> bool + Sync) -> Vec<f64> {
    let [nx, ny, nz] = grid.dims;
    let mut g: Vec<f64> = (0..nx * ny * nz)
        .into_par_iter()
        .map(|i| if feature(i) { 0.0 } else { FAR })
        .collect();
    // x lines are contiguous.
    g.par_chunks_mut(nx)
        .for_each_init(Scratch::default, |s, line| {
            envelope(line, grid.spacing[0], grid.periodic[0], s)
        });
    // y lines: one z-plane at a time per task.
    g.par_chunks_mut(nx * ny).for_each_init(
        || (Scratch::default(), vec![0.0; ny]),
        |(s, line), plane| {
            for x in 0..nx {
                for y in 0..ny {
                    line[y] = plane[x + nx * y];
                }
                envelope(line, grid.spacing[1], grid.periodic[1], s);
                for y in 0..ny {
                    plane[x + nx * y] = line[y];
                }
            }
        },
    );
    // z lines: gathered per y row into a transposed buffer.
    let rows: Vec<Vec<f64>> = (0..ny)
        .into_par_iter()
        .map_init(
            || (Scratch::default(), vec![0.0; nz]),
            |(s, line), y| {
                let mut out = vec![0.0; nx * nz];
                for x in 0..nx {
                    for z in 0..nz {
                        line[z] = g[x + nx * (y + ny * z)];
                    }
                    envelope(line, grid.spacing[2], grid.periodic[2], s);
                    out[x * nz..(x + 1) * nz].copy_from_slice(line);
                }
                out
            },
        )
        .collect();
    for (y, row) in rows.iter().enumerate() {
        for x in 0..nx {
            for z in 0..nz {
                g[x + nx * (y + ny * z)] = row[x * nz + z];
            }
        }
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_brute_force_with_wrap_and_anisotropy() {
        for periodic in [[true, true, true], [false, true, false]] {
            let grid = Grid {
                dims: [7, 5, 6],
                spacing: [1.0, 1.5, 0.7],
                origin: [0.0; 3],
                periodic,
            };
            let feat: Vec<bool> = (0..210).map(|i| (i * 37 + 11) % 29 == 0).collect();
            let d = squared_distance(&grid, |i| feat[i]);
            let ext = grid.extent();
            for (i, di) in d.iter().enumerate() {
                let p = grid.voxel_center(i % 7, (i / 7) % 5, i / 35);
                let mut best = FAR;
                for j in (0..210).filter(|&j| feat[j]) {
                    let q = grid.voxel_center(j % 7, (j / 7) % 5, j / 35);
                    let mut s = 0.0;
                    for a in 0..3 {
                        let mut dx = (p[a] - q[a]).abs();
                        if periodic[a] {
                            dx = dx.min(ext[a] - dx);
                        }
                        s += dx * dx;
                    }
                    best = best.min(s);
                }
                assert!((di - best).abs() < 1e-9, "voxel {i}: {di} vs {best}");
            }
        }
    }
}
