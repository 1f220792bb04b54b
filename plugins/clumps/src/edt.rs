//! Exact squared Euclidean distance transform (Felzenszwalb & Huttenlocher 2012, "Distance
//! transforms of sampled functions"): one 1-D lower-envelope pass per axis, O(N) overall.
//!
//! This replaces the radius growing of Garcia's original method (paper, section 2.1, item 1:
//! "determining the distance from each voxel center within the initial particle to the
//! boundary ... closely related to computing the Euclidean distance transform").

/// 1-D squared distance transform of `f` (in place), `f[i] = min_j (i - j)^2 + f[j]`.
/// `v`, `z` and `d` are scratch buffers of length >= n (+1 for `z`).
fn dt1d(f: &mut [f64], v: &mut [usize], z: &mut [f64], d: &mut [f64]) {
    let n = f.len();
    if n == 0 {
        return;
    }
    let mut k = 0usize;
    v[0] = 0;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    for q in 1..n {
        if f[q] >= INF {
            continue;
        }
        // Skip leading infinite samples: the envelope starts at the first finite one.
        if f[v[0]] >= INF {
            v[0] = q;
            continue;
        }
        loop {
            let p = v[k];
            let s = ((f[q] + (q * q) as f64) - (f[p] + (p * p) as f64)) / (2.0 * (q - p) as f64);
            if s <= z[k] && k > 0 {
                k -= 1;
                continue;
            }
            if s <= z[k] {
                // k == 0: q dominates p everywhere.
                v[0] = q;
                z[1] = f64::INFINITY;
                break;
            }
            k += 1;
            v[k] = q;
            z[k] = s;
            z[k + 1] = f64::INFINITY;
            break;
        }
    }
    if f[v[0]] >= INF {
        return; // all infinite: nothing to propagate
    }
    let mut k = 0usize;
    for (q, dq) in d.iter_mut().enumerate().take(n) {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let p = v[k];
        let dx = q as f64 - p as f64;
        *dq = dx * dx + f[p];
    }
    f.copy_from_slice(&d[..n]);
}

const INF: f64 = 1e30;

/// Squared distance (in voxel units) from every voxel centre of `mask` (x fastest, dims
/// `[nx, ny, nz]`) to the nearest centre of a background voxel; voxels outside the array
/// count as background. Background voxels get 0. Values are exact integers.
pub fn squared_edt(mask: &[bool], dims: [usize; 3]) -> Vec<u32> {
    let [nx, ny, nz] = dims;
    // Pad by one background voxel on every side so the array border is background.
    let (px, py, pz) = (nx + 2, ny + 2, nz + 2);
    let mut g = vec![0.0f64; px * py * pz];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                if mask[x + nx * (y + ny * z)] {
                    g[(x + 1) + px * ((y + 1) + py * (z + 1))] = INF;
                }
            }
        }
    }
    let m = px.max(py).max(pz);
    let mut f = vec![0.0; m];
    let mut v = vec![0usize; m];
    let mut zb = vec![0.0; m + 1];
    let mut d = vec![0.0; m];
    // x pass
    for z in 0..pz {
        for y in 0..py {
            let base = px * (y + py * z);
            dt1d(&mut g[base..base + px], &mut v, &mut zb, &mut d);
        }
    }
    // y pass
    for z in 0..pz {
        for x in 0..px {
            for y in 0..py {
                f[y] = g[x + px * (y + py * z)];
            }
            dt1d(&mut f[..py], &mut v, &mut zb, &mut d);
            for y in 0..py {
                g[x + px * (y + py * z)] = f[y];
            }
        }
    }
    // z pass
    for y in 0..py {
        for x in 0..px {
            for z in 0..pz {
                f[z] = g[x + px * (y + py * z)];
            }
            dt1d(&mut f[..pz], &mut v, &mut zb, &mut d);
            for z in 0..pz {
                g[x + px * (y + py * z)] = f[z];
            }
        }
    }
    let mut out = vec![0u32; nx * ny * nz];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                out[x + nx * (y + ny * z)] = g[(x + 1) + px * ((y + 1) + py * (z + 1))] as u32;
            }
        }
    }
    out
}

/// Brute-force reference (O(N^2)), for tests.
pub fn squared_edt_brute(mask: &[bool], dims: [usize; 3]) -> Vec<u32> {
    let [nx, ny, nz] = dims;
    let mut bg = Vec::new();
    for z in -1..=nz as i64 {
        for y in -1..=ny as i64 {
            for x in -1..=nx as i64 {
                let inside = x >= 0
                    && y >= 0
                    && z >= 0
                    && (x as usize) < nx
                    && (y as usize) < ny
                    && (z as usize) < nz
                    && mask[x as usize + nx * (y as usize + ny * z as usize)];
                if !inside {
                    bg.push([x, y, z]);
                }
            }
        }
    }
    let mut out = vec![0u32; nx * ny * nz];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let i = x + nx * (y + ny * z);
                if !mask[i] {
                    continue;
                }
                let p = [x as i64, y as i64, z as i64];
                out[i] = bg
                    .iter()
                    .map(|b| {
                        ((b[0] - p[0]).pow(2) + (b[1] - p[1]).pow(2) + (b[2] - p[2]).pow(2)) as u32
                    })
                    .min()
                    .unwrap();
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    #[test]
    fn matches_brute_force_on_random_masks() {
        // Independent reference: exhaustive minimum over all background centres.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for dims in [[7, 5, 6], [12, 9, 4], [1, 8, 3], [10, 10, 10]] {
            let n = dims[0] * dims[1] * dims[2];
            for density in [0.5, 0.8, 0.97] {
                let mask: Vec<bool> = (0..n).map(|_| rng.random::<f64>() < density).collect();
                assert_eq!(squared_edt(&mask, dims), squared_edt_brute(&mask, dims));
            }
        }
    }
}
