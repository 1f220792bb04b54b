//! Crop and block downsampling of voxel arrays (x fastest, `c` interleaved components per
//! voxel).

use rayon::prelude::*;

/// The box `start .. start + size` of an array of `dims` voxels with `c` components each.
/// The box must lie inside the array.
pub fn crop<T: Copy + Send + Sync>(
    data: &[T],
    dims: [usize; 3],
    c: usize,
    start: [usize; 3],
    size: [usize; 3],
) -> Vec<T> {
    let [nx, ny, _] = dims;
    let [sx, sy, sz] = size;
    assert!((0..3).all(|a| start[a] + size[a] <= dims[a]));
    assert_eq!(data.len(), dims.iter().product::<usize>() * c);
    let mut out = Vec::with_capacity(sx * sy * sz * c);
    for z in start[2]..start[2] + sz {
        for y in start[1]..start[1] + sy {
            let row = (start[0] + nx * (y + ny * z)) * c;
            out.extend_from_slice(&data[row..row + sx * c]);
        }
    }
    out
}

/// Output dims of a block downsample by `f` (which must divide every dim).
fn out_dims(dims: [usize; 3], f: [usize; 3]) -> [usize; 3] {
    assert!((0..3).all(|a| f[a] > 0 && dims[a] % f[a] == 0));
    [0, 1, 2].map(|a| dims[a] / f[a])
}

/// Block mode of labels: every output voxel takes the most frequent label of its
/// `f[0] x f[1] x f[2]` block, ties to the smallest label.
pub fn downsample_mode(labels: &[u8], dims: [usize; 3], f: [usize; 3]) -> Vec<u8> {
    let [mx, my, mz] = out_dims(dims, f);
    let [nx, ny, _] = dims;
    let mut out = vec![0u8; mx * my * mz];
    out.par_chunks_mut(mx).enumerate().for_each(|(row, line)| {
        let (oy, oz) = (row % my, row / my);
        let mut count = [0u32; 256];
        for (ox, o) in line.iter_mut().enumerate() {
            count.fill(0);
            for z in oz * f[2]..(oz + 1) * f[2] {
                for y in oy * f[1]..(oy + 1) * f[1] {
                    let base = nx * (y + ny * z);
                    for x in ox * f[0]..(ox + 1) * f[0] {
                        count[labels[base + x] as usize] += 1;
                    }
                }
            }
            // max_by_key keeps the last maximum: scan from 255 down so the smallest wins.
            *o = (0..=255u8)
                .rev()
                .max_by_key(|&l| count[l as usize])
                .unwrap_or(0);
        }
    });
    out
}

/// Block mean of `c`-component values: every output voxel takes the mean of each component
/// over its block, summed in raster order within the block.
pub fn downsample_mean(data: &[f64], dims: [usize; 3], c: usize, f: [usize; 3]) -> Vec<f64> {
    let [mx, my, mz] = out_dims(dims, f);
    let [nx, ny, _] = dims;
    let block = (f[0] * f[1] * f[2]) as f64;
    let mut out = vec![0.0; mx * my * mz * c];
    out.par_chunks_mut(mx * c)
        .enumerate()
        .for_each(|(row, line)| {
            let (oy, oz) = (row % my, row / my);
            for ox in 0..mx {
                let o = &mut line[ox * c..(ox + 1) * c];
                for z in oz * f[2]..(oz + 1) * f[2] {
                    for y in oy * f[1]..(oy + 1) * f[1] {
                        for x in ox * f[0]..(ox + 1) * f[0] {
                            let i = (x + nx * (y + ny * z)) * c;
                            for k in 0..c {
                                o[k] += data[i + k];
                            }
                        }
                    }
                }
                for v in o.iter_mut() {
                    *v /= block;
                }
            }
        });
    out
}
