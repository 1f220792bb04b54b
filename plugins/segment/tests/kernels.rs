//! The kernels against independent references: brute-force evaluations of the published
//! threshold criteria, naive 3-D convolutions and medians with their own boundary code,
//! brute-force block statistics, and hand-built label volumes.
#![allow(clippy::needless_range_loop)]

use grainpipe_core::Grid;
use grainpipe_segment::crop::{crop_grid, CropParams};
use grainpipe_segment::morph::{fill_holes, relabel, remove_specks};
use grainpipe_segment::otsu::{histogram, multi_otsu3, otsu};
use grainpipe_segment::resample::{crop, downsample_mean, downsample_mode};
use grainpipe_segment::smooth::{gaussian, median, Window};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A histogram of 256 bins: a sum of Gaussian bumps (centre, width, weight), rounded.
fn modes(bumps: &[(f64, f64, f64)]) -> Vec<u64> {
    (0..256)
        .map(|i| {
            let x = i as f64;
            bumps
                .iter()
                .map(|(c, w, a)| a * (-(x - c).powi(2) / (2.0 * w * w)).exp())
                .sum::<f64>()
                .round() as u64
        })
        .collect()
}

/// Between-class variance sum_c w_c (mu_c - mu_T)^2 of the classes cut after the bins in
/// `cuts`, each class's weight and mean summed from scratch (Otsu 1979, eq. 15 generalised).
fn between_class_variance(h: &[u64], cuts: &[usize]) -> f64 {
    let n: f64 = h.iter().map(|&c| c as f64).sum();
    let mu_t: f64 = h
        .iter()
        .enumerate()
        .map(|(i, &c)| i as f64 * c as f64)
        .sum::<f64>()
        / n;
    let mut bounds = vec![0usize];
    bounds.extend(cuts.iter().map(|k| k + 1));
    bounds.push(h.len());
    let mut s = 0.0;
    for w in bounds.windows(2) {
        let cnt: f64 = h[w[0]..w[1]].iter().map(|&c| c as f64).sum();
        if cnt == 0.0 {
            continue;
        }
        let mean: f64 = (w[0]..w[1]).map(|i| i as f64 * h[i] as f64).sum::<f64>() / cnt;
        s += cnt / n * (mean - mu_t).powi(2);
    }
    s
}

#[test]
fn otsu_equals_brute_force_of_the_published_criterion() {
    // Bimodal: modes at 60 and 180 of unequal weight and width.
    let h = modes(&[(60.0, 20.0, 900.0), (170.0, 30.0, 500.0)]);
    let k = otsu(&h).unwrap();
    let (mut best, mut best_k) = (-1.0, 0);
    for t in 0..255 {
        let v = between_class_variance(&h, &[t]);
        if v > best {
            best = v;
            best_k = t;
        }
    }
    // Exact: the same bin index.
    assert_eq!(k, best_k, "otsu {k}, brute force {best_k}");
    assert!(k > 60 && k < 170, "threshold {k} not between the modes");
    // The maximum is unique here (no tie decides the answer): the neighbours are lower.
    assert!(between_class_variance(&h, &[k - 1]) < best);
    assert!(between_class_variance(&h, &[k + 1]) < best);
}

#[test]
fn multi_otsu_separates_three_modes_and_equals_brute_force() {
    let h = modes(&[
        (40.0, 8.0, 700.0),
        (128.0, 10.0, 400.0),
        (210.0, 6.0, 900.0),
    ]);
    let [k1, k2] = multi_otsu3(&h).unwrap();
    let (mut best, mut arg) = (-1.0, [0, 0]);
    for a in 0..254 {
        for b in a + 1..255 {
            let v = between_class_variance(&h, &[a, b]);
            if v > best {
                best = v;
                arg = [a, b];
            }
        }
    }
    assert_eq!([k1, k2], arg, "multi-otsu vs brute force");
    assert!(40 < k1 && k1 < 128 && 128 < k2 && k2 < 210, "{k1} {k2}");
    // Well separated (the counts round to 0 between the modes): every bin of a mode is in
    // its own class.
    let occupied = |lo: usize, hi: usize| (lo..hi).filter(|&i| h[i] > 0).collect::<Vec<_>>();
    let (m1, m2, m3) = (occupied(0, 84), occupied(84, 169), occupied(169, 256));
    assert!(*m1.last().unwrap() <= k1 && k1 < m2[0], "k1 {k1}");
    assert!(*m2.last().unwrap() <= k2 && k2 < m3[0], "k2 {k2}");
}

#[test]
fn histogram_bins_are_floor_of_scaled_value() {
    let v = [0.0, 0.49, 0.5, 0.99, 1.0, f64::NAN];
    assert_eq!(histogram(&v, 0.0, 1.0, 2), vec![2, 3]);
}

fn random_volume(dims: [usize; 3], seed: u64) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..dims.iter().product::<usize>())
        .map(|_| rng.random_range(0.0..1.0))
        .collect()
}

/// Index along an axis by folding at the faces (mirror with the edge repeated) or wrapping,
/// written independently of the kernel's closed form.
fn fold(mut i: isize, n: usize, periodic: bool) -> usize {
    let n = n as isize;
    if periodic {
        while i < 0 {
            i += n;
        }
        while i >= n {
            i -= n;
        }
    } else {
        while i < 0 || i >= n {
            if i < 0 {
                i = -i - 1;
            }
            if i >= n {
                i = 2 * n - 1 - i;
            }
        }
    }
    i as usize
}

fn at(v: &[f64], dims: [usize; 3], p: [isize; 3], periodic: [bool; 3]) -> f64 {
    let [x, y, z] = [0, 1, 2].map(|a| fold(p[a], dims[a], periodic[a]));
    v[x + dims[0] * (y + dims[1] * z)]
}

#[test]
fn median_equals_naive_median_including_boundaries() {
    let dims = [7, 6, 5];
    let periodic = [true, false, false];
    let v = random_volume(dims, 1);
    for (r, window) in [(1, Window::Cube), (2, Window::Ball), (3, Window::Cube)] {
        let m = median(&v, dims, periodic, r, window);
        let r = r as isize;
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let mut w = Vec::new();
                    for dz in -r..=r {
                        for dy in -r..=r {
                            for dx in -r..=r {
                                if window == Window::Ball && dx * dx + dy * dy + dz * dz > r * r {
                                    continue;
                                }
                                let p = [x as isize + dx, y as isize + dy, z as isize + dz];
                                w.push(at(&v, dims, p, periodic));
                            }
                        }
                    }
                    w.sort_by(|a, b| a.partial_cmp(b).unwrap());
                    let i = x + dims[0] * (y + dims[1] * z);
                    // Exact: the median is one of the values.
                    assert_eq!(m[i], w[w.len() / 2], "r {r} {window:?} at ({x},{y},{z})");
                }
            }
        }
    }
}

#[test]
fn gaussian_equals_naive_3d_convolution_including_boundaries() {
    let dims = [6, 5, 4];
    let periodic = [false, true, false];
    let v = random_volume(dims, 2);
    let sigma = [1.0, 0.7, 1.3];
    let truncate = 2.5;
    let g = gaussian(&v, dims, periodic, sigma, truncate);
    // The 3-D kernel as the normalised product of truncated 1-D Gaussians, radius
    // ceil(truncate sigma) (3, 2, 4 voxels: wider than the z axis, so the reflection folds
    // more than once).
    let rad = sigma.map(|s| (truncate * s).ceil() as isize);
    let w1 = |a: usize, d: isize| {
        let norm: f64 = (-rad[a]..=rad[a])
            .map(|k| (-(k * k) as f64 / (2.0 * sigma[a] * sigma[a])).exp())
            .sum();
        (-(d * d) as f64 / (2.0 * sigma[a] * sigma[a])).exp() / norm
    };
    let mut worst = 0.0f64;
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let mut acc = 0.0;
                for dz in -rad[2]..=rad[2] {
                    for dy in -rad[1]..=rad[1] {
                        for dx in -rad[0]..=rad[0] {
                            let p = [x as isize + dx, y as isize + dy, z as isize + dz];
                            acc += w1(0, dx) * w1(1, dy) * w1(2, dz) * at(&v, dims, p, periodic);
                        }
                    }
                }
                let i = x + dims[0] * (y + dims[1] * z);
                worst = worst.max((g[i] - acc).abs());
            }
        }
    }
    // Rounding only: the separable passes sum in another order.
    assert!(worst < 1e-13, "max |separable - naive| = {worst}");
}

#[test]
fn downsample_mode_and_mean_equal_brute_force() {
    let dims = [8, 6, 4];
    let f = [2, 3, 2];
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    // Few labels in blocks of 12, so ties happen.
    let labels: Vec<u8> = (0..192).map(|_| rng.random_range(0..4u8)).collect();
    let values: Vec<f64> = (0..192 * 3).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mode = downsample_mode(&labels, dims, f);
    let mean = downsample_mean(&values, dims, 3, f);
    let out = [4, 2, 2];
    let mut ties = 0;
    for oz in 0..out[2] {
        for oy in 0..out[1] {
            for ox in 0..out[0] {
                let mut block = Vec::new();
                for z in 0..dims[2] {
                    for y in 0..dims[1] {
                        for x in 0..dims[0] {
                            if x / f[0] == ox && y / f[1] == oy && z / f[2] == oz {
                                block.push(x + dims[0] * (y + dims[1] * z));
                            }
                        }
                    }
                }
                let count = |l: u8| block.iter().filter(|&&i| labels[i] == l).count();
                let top = (0..4u8).map(count).max().unwrap();
                let want = (0..4u8).find(|&l| count(l) == top).unwrap();
                ties += ((0..4u8).filter(|&l| count(l) == top).count() > 1) as usize;
                let o = ox + out[0] * (oy + out[1] * oz);
                assert_eq!(mode[o], want, "mode of block ({ox},{oy},{oz})");
                for c in 0..3 {
                    let m: f64 =
                        block.iter().map(|&i| values[3 * i + c]).sum::<f64>() / block.len() as f64;
                    assert!(
                        (mean[3 * o + c] - m).abs() < 1e-14,
                        "mean ({ox},{oy},{oz}) c{c}"
                    );
                }
            }
        }
    }
    assert!(ties > 0, "the draw should exercise the tie rule");
}

#[test]
fn crop_takes_the_box() {
    let dims = [5, 4, 3];
    let v: Vec<u32> = (0..60).flat_map(|i| [i, 1000 + i]).collect();
    let c = crop(&v, dims, 2, [1, 2, 1], [3, 2, 2]);
    let mut want = Vec::new();
    for z in 1..3 {
        for y in 2..4 {
            for x in 1..4 {
                let i = (x + 5 * (y + 4 * z)) as u32;
                want.extend([i, 1000 + i]);
            }
        }
    }
    assert_eq!(c, want);
}

fn idx(dims: [usize; 3], x: usize, y: usize, z: usize) -> usize {
    x + dims[0] * (y + dims[1] * z)
}

#[test]
fn specks_below_the_size_join_the_surrounding_phase() {
    let dims = [10, 10, 10];
    let mut l = vec![1u8; 1000];
    // A one-voxel pore speck, a 2-voxel pore speck, a 2 x 2 x 2 pore block (8 voxels, kept)
    // and a 3-voxel speck of phase 2 on the image face.
    l[idx(dims, 5, 5, 5)] = 0;
    l[idx(dims, 1, 1, 1)] = 0;
    l[idx(dims, 2, 1, 1)] = 0;
    for (x, y, z) in [(6, 6, 1), (7, 6, 1), (6, 7, 1), (7, 7, 1)] {
        l[idx(dims, x, y, z)] = 0;
        l[idx(dims, x, y, z + 1)] = 0;
    }
    for x in 0..3 {
        l[idx(dims, x, 8, 9)] = 2;
    }
    // A 1-voxel speck of phase 2 on top of the 8-voxel pore block: neighbours 1 pore
    // (below), 5 solid -> solid.
    l[idx(dims, 6, 6, 3)] = 2;
    let (out, r) = remove_specks(&l, dims, [false; 3], 5, |_| true);
    let mut want = vec![1u8; 1000];
    for (x, y, z) in [(6, 6, 1), (7, 6, 1), (6, 7, 1), (7, 7, 1)] {
        want[idx(dims, x, y, z)] = 0;
        want[idx(dims, x, y, z + 1)] = 0;
    }
    assert_eq!(out, want);
    assert_eq!(r.components, 4);
    assert_eq!(r.voxels, 1 + 2 + 3 + 1);
    // Only phase 2 judged: the pore specks stay.
    let (out2, r2) = remove_specks(&l, dims, [false; 3], 5, |p| p == 2);
    assert_eq!(r2.components, 2);
    assert_eq!(out2[idx(dims, 5, 5, 5)], 0);
    assert_eq!(out2[idx(dims, 6, 6, 3)], 1);
}

#[test]
fn speck_majority_ties_go_to_the_smallest_label() {
    // A 1 x 1 x 3 line: a 1-voxel speck of 3 between a voxel of 2 and one of 1.
    let dims = [3, 1, 1];
    let (out, _) = remove_specks(&[2, 3, 1], dims, [false; 3], 2, |l| l == 3);
    assert_eq!(out, vec![2, 1, 1]);
}

#[test]
fn enclosed_holes_are_filled_and_open_pores_kept() {
    let dims = [9, 9, 9];
    // Pore everywhere; a solid box shell x, y, z in 2..=6 with a cavity 3..=5 (27 voxels)
    // and a 1-voxel lump of phase 2 at its centre (enclosed too, but only pore holes are
    // asked for).
    let mut l = vec![0u8; 729];
    for z in 2..=6 {
        for y in 2..=6 {
            for x in 2..=6 {
                let shell = [x, y, z].iter().any(|&c| c == 2 || c == 6);
                l[idx(dims, x, y, z)] = if shell { 1 } else { 0 };
            }
        }
    }
    l[idx(dims, 4, 4, 4)] = 2;
    let (out, r) = fill_holes(&l, dims, [false; 3], |p| p == 0);
    let mut want = l.clone();
    for z in 3..=5 {
        for y in 3..=5 {
            for x in 3..=5 {
                if (x, y, z) != (4, 4, 4) {
                    want[idx(dims, x, y, z)] = 1;
                }
            }
        }
    }
    assert_eq!(out, want);
    assert_eq!((r.components, r.voxels), (1, 26));
    // Periodic on every axis: the outer pore winds around the box, so it is not a hole.
    let (out_p, r_p) = fill_holes(&l, dims, [true; 3], |p| p == 0);
    assert_eq!(out_p, want);
    assert_eq!(r_p.components, 1);
    // Open the shell to the outside through one face voxel: the cavity is no longer
    // enclosed.
    let mut open = l.clone();
    open[idx(dims, 4, 4, 2)] = 0;
    let (out_o, r_o) = fill_holes(&open, dims, [false; 3], |p| p == 0);
    assert_eq!(out_o, open);
    assert_eq!(r_o.components, 0);
    // A pore pocket touching the image face (z = 0) is not enclosed either, even when
    // surrounded by solid otherwise.
    let mut slab = vec![1u8; 729];
    slab[idx(dims, 4, 4, 0)] = 0;
    slab[idx(dims, 4, 4, 4)] = 0;
    let (out_s, _) = fill_holes(&slab, dims, [false; 3], |p| p == 0);
    assert_eq!(out_s[idx(dims, 4, 4, 0)], 0);
    assert_eq!(out_s[idx(dims, 4, 4, 4)], 1);
    // On a periodic z axis the same face pocket is enclosed (its neighbour across the face
    // is solid).
    let (out_z, _) = fill_holes(&slab, dims, [false, false, true], |p| p == 0);
    assert_eq!(out_z[idx(dims, 4, 4, 0)], 1);
}

#[test]
fn relabel_maps_every_voxel() {
    let mut l = vec![0u8, 1, 2, 3, 2];
    let mut map: [u8; 256] = std::array::from_fn(|i| i as u8);
    map[2] = 1;
    map[3] = 7;
    relabel(&mut l, &map);
    assert_eq!(l, vec![0, 1, 1, 7, 1]);
}

#[test]
fn crop_shifts_the_origin_and_keeps_periodicity_only_on_whole_axes() {
    let g = Grid {
        dims: [10, 8, 6],
        spacing: [1e-6, 2e-6, 3e-6],
        origin: [1e-3, 0.0, -1e-3],
        periodic: [true, true, true],
    };
    let p = CropParams {
        start: [2, 0, 1],
        size: [5, 0, 5],
    };
    let (c, size) = crop_grid(&p, &g).unwrap();
    assert_eq!(size, [5, 8, 5]);
    assert_eq!(c.dims, [5, 8, 5]);
    assert_eq!(c.periodic, [false, true, false]);
    let want = [1e-3 + 2e-6, 0.0, -1e-3 + 3e-6];
    for a in 0..3 {
        assert!((c.origin[a] - want[a]).abs() < 1e-18, "origin {a}");
    }
    assert_eq!(c.spacing, g.spacing);
}

#[test]
fn kernels_do_not_depend_on_the_thread_count() {
    let dims = [23, 17, 11];
    let v = random_volume(dims, 4);
    let labels: Vec<u8> = v.iter().map(|x| (x * 3.0) as u8).collect();
    let run = || {
        (
            median(&v, dims, [false, true, false], 1, Window::Ball),
            gaussian(&v, dims, [true, false, false], [1.5, 0.8, 1.0], 3.0),
            remove_specks(&labels, dims, [false; 3], 4, |_| true).0,
            fill_holes(&labels, dims, [true; 3], |l| l == 1).0,
        )
    };
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(run);
    let three = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap()
        .install(run);
    // Bitwise equal, and the clean-up changed something (else the comparison is empty).
    assert!(one == three);
    assert_ne!(one.2, labels);
    assert_ne!(one.3, labels);
}
