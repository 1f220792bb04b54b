//! The pore-space stages against independent references: local thickness of a voxelised
//! ball and of slabs (exact by construction) and against a brute-force painting of every
//! ball; two-point correlation and chord lengths of Boolean models (random overlapping
//! spheres, seeded) against their closed forms, with tolerances from the scatter between
//! realisations; geometric tortuosity of straight and zig-zag channels against hand-computed
//! path lengths; the formation factor of a straight tube bundle from conductivity.fft's
//! solver; and a pipeline running every stage on a voxelized RSA packing.

use grainpipe_analysis::chords::chord_counts;
use grainpipe_analysis::thickness::{ball_diameters, local_thickness};
use grainpipe_analysis::tortuosity::tortuosity;
use grainpipe_analysis::two_point::{pair_counts, radial_counts};
use grainpipe_core::testing::run_yaml;
use grainpipe_core::*;
use rand::{RngExt, SeedableRng};
use std::f64::consts::PI;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_geometry::register(&mut r);
    grainpipe_analysis::register(&mut r);
    r
}

fn idx(d: [usize; 3], x: usize, y: usize, z: usize) -> usize {
    x + d[0] * (y + d[1] * z)
}

// ---------------------------------------------------------------- local thickness

#[test]
fn ball_thickness_is_its_diameter_within_a_voxel_everywhere() {
    // Balls of radius 9.5 voxels (h = 2 um); the voxelised ball holds the voxel centres
    // within R. Centred on a voxel centre, every voxel of it must carry 2R to within one
    // voxel. Centred off the lattice (on a voxel corner, or anywhere) the largest ball about
    // a voxel centre is smaller by up to twice the offset (sqrt 3 h at a corner), and voxels
    // near the surface are reached only by balls about centres nearer to them: measured
    // 2R - 4.3 h .. 2R - 1.7 h at a corner. There the bounds checked are those of the
    // lattice-centred definition (porespy's too): nothing above 2R + h, the largest at least
    // 2R - (2 offset + 1) h, the volume-weighted mean at least 2R - 3 h.
    let h = 2e-6;
    let r = 9.5;
    for (centre, periodic) in [
        ([16.5, 16.5, 16.5], [false; 3]),
        ([16.5, 17.5, 15.5], [true; 3]),
        ([16.0, 16.0, 16.0], [true; 3]),
        ([15.3, 16.8, 16.1], [false, true, false]),
    ] {
        let d = [32, 33, 34];
        let mut mask = vec![false; d.iter().product()];
        for z in 0..d[2] {
            for y in 0..d[1] {
                for x in 0..d[0] {
                    let q = [x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5];
                    let s: f64 = (0..3).map(|a| (q[a] - centre[a]).powi(2)).sum();
                    mask[idx(d, x, y, z)] = s <= r * r;
                }
            }
        }
        let t = local_thickness(&mask, d, [h; 3], periodic);
        let (mut lo, mut hi, mut sum, mut count) = (f64::INFINITY, 0.0f64, 0.0, 0.0);
        for (i, &m) in mask.iter().enumerate() {
            if m {
                lo = lo.min(t[i]);
                hi = hi.max(t[i]);
                sum += t[i];
                count += 1.0;
            } else {
                assert_eq!(t[i], 0.0);
            }
        }
        let offset: f64 = centre
            .iter()
            .map(|c| (c - c.floor() - 0.5).powi(2))
            .sum::<f64>()
            .sqrt();
        println!(
            "ball at {centre:?} (offset {offset:.3} h): thickness {:.3} .. {:.3} voxels, mean \
             {:.3}, 2R = {}",
            lo / h,
            hi / h,
            sum / count / h,
            2.0 * r
        );
        assert!(hi <= (2.0 * r + 1.0) * h + 1e-12);
        if offset == 0.0 {
            assert!(lo >= (2.0 * r - 1.0) * h - 1e-12);
        } else {
            assert!(hi >= (2.0 * r - 2.0 * offset - 1.0) * h);
            assert!(sum / count >= (2.0 * r - 3.0) * h);
        }
    }
}

#[test]
fn slab_thickness_is_exact_for_even_and_odd_widths() {
    // Slabs of n = 1..9 voxels normal to each axis, solid on both sides, in boxes periodic
    // along the slab's plane (and not): every slab voxel carries exactly n h.
    let h = 1.5e-6;
    for axis in 0..3 {
        for n in 1..=9usize {
            for periodic_plane in [true, false] {
                let mut d = [6, 7, 8];
                d[axis] = n + 4;
                let mut periodic = [periodic_plane; 3];
                periodic[axis] = false;
                let mask: Vec<bool> = (0..d.iter().product())
                    .map(|i| {
                        let c = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])];
                        (2..2 + n).contains(&c[axis])
                    })
                    .collect();
                let t = local_thickness(&mask, d, [h; 3], periodic);
                for (i, &m) in mask.iter().enumerate() {
                    let want = if m { n as f64 * h } else { 0.0 };
                    assert!(
                        (t[i] - want).abs() < 1e-9 * h,
                        "axis {axis}, n {n}, voxel {i}: {} voxels, want {}",
                        t[i] / h,
                        want / h
                    );
                }
            }
        }
    }
}

#[test]
fn covering_equals_brute_force_painting_of_every_ball() {
    // Random two-phase images (periodic and not, anisotropic spacing): the ridge pruning and
    // plane-wise painting give the same map as painting every voxel's ball over every voxel.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    for (periodic, spacing) in [
        ([true; 3], [1.0, 1.0, 1.0]),
        ([false, true, false], [1.0, 1.3, 0.8]),
    ] {
        let d = [14, 12, 10];
        let n: usize = d.iter().product();
        // Blobs: union of a few random balls, so that thicknesses vary.
        let centres: Vec<[f64; 4]> = (0..12)
            .map(|_| {
                [
                    rng.random::<f64>() * 14.0,
                    rng.random::<f64>() * 12.0,
                    rng.random::<f64>() * 10.0,
                    1.0 + 3.0 * rng.random::<f64>(),
                ]
            })
            .collect();
        let mask: Vec<bool> = (0..n)
            .map(|i| {
                let c = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])];
                centres.iter().any(|b| {
                    (0..3)
                        .map(|a| {
                            let mut x = (c[a] as f64 + 0.5 - b[a]).abs();
                            if periodic[a] {
                                x = x.min(d[a] as f64 - x);
                            }
                            x * x
                        })
                        .sum::<f64>()
                        <= b[3] * b[3]
                })
            })
            .collect();
        let (d2, dia) = ball_diameters(&mask, d, spacing, periodic);
        let fast = local_thickness(&mask, d, spacing, periodic);
        let mut brute = vec![0.0f64; n];
        for c in (0..n).filter(|&c| mask[c]) {
            let cc = [c % d[0], (c / d[0]) % d[1], c / (d[0] * d[1])];
            for x in (0..n).filter(|&x| mask[x]) {
                let xc = [x % d[0], (x / d[0]) % d[1], x / (d[0] * d[1])];
                let s: f64 = (0..3)
                    .map(|a| {
                        let mut t = (cc[a] as f64 - xc[a] as f64).abs();
                        if periodic[a] {
                            t = t.min(d[a] as f64 - t);
                        }
                        (t * spacing[a]).powi(2)
                    })
                    .sum();
                if s < d2[c] * (1.0 - 1e-12) {
                    brute[x] = brute[x].max(dia[c]);
                }
            }
        }
        let diff = fast
            .iter()
            .zip(&brute)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let phase = mask.iter().filter(|&&m| m).count();
        println!("{phase} phase voxels, largest difference {diff}");
        assert!(phase > n / 10 && phase < n * 9 / 10);
        assert!(diff < 1e-12, "{diff}");
    }
}

// ---------------------------------------------------------------- Boolean model

/// A Boolean model: `count` balls of radius `r` voxels, centres uniform in a periodic box of
/// `l`^3 voxels; true where the voxel centre is in no ball (the pore phase).
fn boolean_pores(seed: u64, l: usize, r: f64, count: usize) -> Vec<bool> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let d = [l; 3];
    let mut pore = vec![true; l * l * l];
    let k = r.ceil() as i64 + 1;
    for _ in 0..count {
        let c = [0; 3].map(|_: i32| rng.random::<f64>() * l as f64);
        let base = c.map(|v| v.floor() as i64);
        for dz in -k..=k {
            for dy in -k..=k {
                for dx in -k..=k {
                    let v = [base[0] + dx, base[1] + dy, base[2] + dz];
                    let s: f64 = (0..3).map(|a| (v[a] as f64 + 0.5 - c[a]).powi(2)).sum();
                    if s <= r * r {
                        let w = v.map(|t| t.rem_euclid(l as i64) as usize);
                        pore[idx(d, w[0], w[1], w[2])] = false;
                    }
                }
            }
        }
    }
    pore
}

/// Volume of the union of two balls of radius `r` at distance `s`.
fn union_volume(r: f64, s: f64) -> f64 {
    let v = 4.0 / 3.0 * PI * r.powi(3);
    let lens = if s < 2.0 * r {
        PI / 12.0 * (4.0 * r + s) * (2.0 * r - s).powi(2)
    } else {
        0.0
    };
    2.0 * v - lens
}

/// Mean and standard error of the mean.
fn mean_se(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, (var / n).sqrt())
}

const L: usize = 64;
const R: f64 = 4.0;
const BALLS: usize = 680; // pore fraction about 0.5
const SEEDS: u64 = 8;

/// S2 of the Boolean model with `BALLS` balls (binomial, not Poisson: a fixed count in the
/// box): a point pair is pore when no ball covers either point.
fn s2_exact(s: f64) -> f64 {
    (1.0 - union_volume(R, s) / (L as f64).powi(3)).powi(BALLS as i32)
}

#[test]
fn two_point_correlation_of_a_boolean_model_matches_the_closed_form() {
    // S2(r) = (1 - V2(r) / |box|)^N (-> exp(-rho V2(r)) for a Poisson count). Voxel centres
    // are points, so the estimate is unbiased: only the statistical error remains, which is
    // estimated from 8 realisations (mean of x, y, z per realisation); tolerance 4 standard
    // errors of the mean. The same images declared non-periodic test the n - k normalisation.
    let d = [L; 3];
    let lags = 14; // up to 3.5 R
    let mut per_seed: Vec<Vec<[f64; 2]>> = Vec::new();
    for seed in 0..SEEDS {
        let pore = boolean_pores(seed, L, R, BALLS);
        let mut s = vec![[0.0; 2]; lags + 1];
        for axis in 0..3 {
            for (j, periodic) in [true, false].into_iter().enumerate() {
                let c = pair_counts(&pore, d, axis, periodic, lags);
                for k in 0..=lags {
                    s[k][j] += c[k].0 as f64 / c[k].1 as f64 / 3.0;
                    if periodic {
                        assert_eq!(c[k].1, (L * L * L) as u64);
                    } else {
                        assert_eq!(c[k].1, (L * L * (L - k)) as u64);
                    }
                }
            }
        }
        per_seed.push(s);
    }
    for j in 0..2 {
        for k in 0..=lags {
            let v: Vec<f64> = per_seed.iter().map(|s| s[k][j]).collect();
            let (m, se) = mean_se(&v);
            let want = s2_exact(k as f64);
            println!(
                "{} lag {k:2}: S2 {m:.5} +- {se:.5}, closed form {want:.5}, {:+.2} se",
                ["periodic", "cut"][j],
                (m - want) / se
            );
            assert!(se < 0.01, "the test has no power: se {se}");
            assert!(
                (m - want).abs() < 4.0 * se,
                "lag {k}: {m} +- {se} vs {want}"
            );
        }
    }
    // Exactness of the FFT pair counts: S2(0) is the voxel count, S2 at lag 1 the direct
    // count of neighbouring pairs.
    let pore = boolean_pores(99, L, R, BALLS);
    let c = pair_counts(&pore, d, 1, false, 1);
    assert_eq!(c[0].0, pore.iter().filter(|&&p| p).count() as u64);
    let direct = (0..L * L * L)
        .filter(|&i| (i / L) % L + 1 < L && pore[i] && pore[i + L])
        .count() as u64;
    assert_eq!(c[1].0, direct);
}

#[test]
fn radial_two_point_correlation_matches_the_closed_form_and_brute_force() {
    // Brute force on a small random image (anisotropic spacing, mixed periodicity): every
    // voxel pair inside the image, binned by |d| / width rounded.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let d = [6, 5, 7];
    let (spacing, periodic) = ([1.0, 1.2, 0.9], [true, false, false]);
    let mask: Vec<bool> = (0..210).map(|_| rng.random::<f64>() < 0.4).collect();
    let c = radial_counts(&mask, d, spacing, periodic, 0.9, 4);
    let mut brute = vec![(0u64, 0u64); 5];
    for i in 0..210 {
        let p = [i % 6, (i / 6) % 5, i / 30];
        for dz in -6i64..=6 {
            for dy in -4i64..=4 {
                for dx in -3i64..=3 {
                    // Periodic x: each displacement once, -3 < dx <= 3.
                    if dx == -3 {
                        continue;
                    }
                    let (y, z) = (p[1] as i64 + dy, p[2] as i64 + dz);
                    if !(0..5).contains(&y) || !(0..7).contains(&z) {
                        continue;
                    }
                    let x = (p[0] as i64 + dx).rem_euclid(6);
                    let r = ((dx as f64 * 1.0).powi(2)
                        + (dy as f64 * 1.2).powi(2)
                        + (dz as f64 * 0.9).powi(2))
                    .sqrt();
                    let k = (r / 0.9).round() as usize;
                    if k <= 4 {
                        let j = x as usize + 6 * (y as usize + 5 * z as usize);
                        brute[k].1 += 1;
                        brute[k].0 += u64::from(mask[i] && mask[j]);
                    }
                }
            }
        }
    }
    assert_eq!(c, brute);
    // Boolean models (as in the axial test): the shell average of the closed form, each
    // displacement weighted by its pairs, within 4 standard errors over 8 realisations;
    // periodic, and the same images taken as open (zero-padded).
    let shells = 12;
    let expected = |open: bool, k: usize| {
        let (mut num, mut den) = (0.0, 0.0);
        let r = shells as i64 + 1;
        for dz in -r..=r {
            for dy in -r..=r {
                for dx in -r..=r {
                    let len = ((dx * dx + dy * dy + dz * dz) as f64).sqrt();
                    if (len.round() as usize) != k {
                        continue;
                    }
                    let w = if open {
                        [dx, dy, dz]
                            .iter()
                            .map(|v| (L as i64 - v.abs()) as f64)
                            .product::<f64>()
                    } else {
                        1.0
                    };
                    num += w * s2_exact(len);
                    den += w;
                }
            }
        }
        num / den
    };
    let mut per_seed = vec![Vec::new(); 2];
    for seed in 0..SEEDS {
        let pore = boolean_pores(seed, L, R, BALLS);
        for (j, open) in [false, true].into_iter().enumerate() {
            let c = radial_counts(&pore, [L; 3], [1.0; 3], [!open; 3], 1.0, shells);
            per_seed[j].push(
                c.iter()
                    .map(|&(b, a)| b as f64 / a as f64)
                    .collect::<Vec<_>>(),
            );
        }
    }
    for (j, open) in [false, true].into_iter().enumerate() {
        for k in 0..=shells {
            let v: Vec<f64> = per_seed[j].iter().map(|s| s[k]).collect();
            let (m, se) = mean_se(&v);
            let want = expected(open, k);
            println!(
                "radial {} shell {k:2}: S2 {m:.5} +- {se:.5}, closed form {want:.5}, {:+.2} se",
                ["periodic", "open"][j],
                (m - want) / se
            );
            assert!(
                se < 0.01 && (m - want).abs() < 4.0 * se,
                "shell {k}: {m} vs {want}"
            );
        }
    }
}

#[test]
fn pore_chords_of_a_boolean_model_follow_the_exponential_law() {
    // A line meets the balls as a 1-D Boolean model of segments: pore chords are exponential
    // with mean 4 phi / S_V = 1 / (rho pi R^2). On the lattice the run of pore voxels is
    // geometric: after a pore voxel the next is pore with probability q = S2(h) / phi, so the
    // mean run is 1 / (1 - q) voxels (= lambda / h + 1/2 to first order) and the fraction of
    // runs longer than k voxels q^k. q from the closed form of S2 (binomial count). The
    // mean is checked against 1 / (1 - q) within 4 standard errors over 8 realisations,
    // and against the continuum 1 / (rho pi R^2) + 1/2 voxel within 1 %; the survival at
    // 1, 2 and 3 mean chords within 4 standard errors.
    let d = [L; 3];
    let phi = s2_exact(0.0);
    let q = s2_exact(1.0) / phi;
    let lattice_mean = 1.0 / (1.0 - q);
    let rho = BALLS as f64 / (L as f64).powi(3);
    let continuum = 1.0 / (rho * PI * R * R);
    let mut means = Vec::new();
    let survivals = [8usize, 16, 24];
    let mut surv: Vec<Vec<f64>> = vec![Vec::new(); survivals.len()];
    for seed in 0..SEEDS {
        let pore = boolean_pores(100 + seed, L, R, BALLS);
        let mut counts = vec![0u64; L + 1];
        for axis in 0..3 {
            let c = chord_counts(&pore, d, axis, true);
            assert_eq!(c.cut, 0);
            for (t, x) in counts.iter_mut().zip(&c.counts) {
                *t += x;
            }
        }
        let total: u64 = counts.iter().sum();
        let voxels: u64 = counts.iter().enumerate().map(|(k, &c)| k as u64 * c).sum();
        means.push(voxels as f64 / total as f64);
        for (j, &k) in survivals.iter().enumerate() {
            let longer: u64 = counts[k + 1..].iter().sum();
            surv[j].push(longer as f64 / total as f64);
        }
    }
    let (m, se) = mean_se(&means);
    println!(
        "mean pore chord {m:.4} +- {se:.4} voxels; lattice 1/(1-q) {lattice_mean:.4}; \
         continuum 1/(rho pi R^2) {continuum:.4} (+ 1/2 = {:.4})",
        continuum + 0.5
    );
    assert!(se < 0.1 && (m - lattice_mean).abs() < 4.0 * se);
    assert!(((continuum + 0.5) / m - 1.0).abs() < 0.01);
    for (j, &k) in survivals.iter().enumerate() {
        let (s, se) = mean_se(&surv[j]);
        let want = q.powi(k as i32);
        println!("P(chord > {k}) = {s:.5} +- {se:.5}, q^k = {want:.5}");
        assert!((s - want).abs() < 4.0 * se + 1e-4, "{k}: {s} vs {want}");
    }
}

#[test]
fn chords_cut_by_non_periodic_faces_are_counted_not_measured() {
    // Along x, the line 1101110011: cut at both faces, one chord of 3 inside.
    let d = [10, 1, 1];
    let mask: Vec<bool> = "1101110011".chars().map(|c| c == '1').collect();
    let cut = chord_counts(&mask, d, 0, false);
    assert_eq!((cut.chords(), cut.cut, cut.counts[3]), (1, 2, 1));
    assert_eq!((cut.voxels, cut.crossings), (7, 4));
    // Periodic: the runs at both ends join into one chord of 4.
    let wrap = chord_counts(&mask, d, 0, true);
    assert_eq!(
        (wrap.chords(), wrap.cut, wrap.counts[3], wrap.counts[4]),
        (2, 0, 1, 1)
    );
    assert_eq!((wrap.voxels, wrap.crossings), (7, 4));
    assert_eq!(wrap.stereological(), wrap.mean());
    // A run at one periodic face only crosses it.
    let one = chord_counts(&[true, true, false, false], [4, 1, 1], 0, true);
    assert_eq!(
        (one.chords(), one.crossings, one.stereological()),
        (1, 2, 2.0)
    );
    let full = chord_counts(&[true; 10], d, 0, true);
    assert_eq!((full.chords(), full.unbounded), (0, 1));
}

// ---------------------------------------------------------------- tortuosity

#[test]
fn straight_channels_have_tortuosity_one() {
    // Four straight square tubes along z (3 x 3 voxels) in a box periodic in x and y.
    let d = [16, 16, 20];
    let mask: Vec<bool> = (0..d.iter().product())
        .map(|i| {
            // x in {7, 0, 1} (one tube crosses the periodic face x), y in {2, 3, 4} mod 8.
            let (x, y) = (i % 16, (i / 16) % 16);
            (x + 1) % 8 < 3 && (y + 6) % 8 < 3
        })
        .collect();
    let t = tortuosity(&mask, d, [1e-6; 3], [true, true, false], 2);
    assert!((t.mean - 1.0).abs() < 1e-12 && (t.min - 1.0).abs() < 1e-12);
    assert!((t.straight - 19e-6).abs() < 1e-18);
    assert_eq!((t.outlet_reached, t.connected), (1.0, 1.0));
    // Across the tubes nothing connects (the axis measured does not wrap).
    let x = tortuosity(&mask, d, [1e-6; 3], [true, true, false], 0);
    assert!(x.mean.is_nan());
    assert_eq!((x.outlet_reached, x.connected), (0.0, 0.0));
}

#[test]
fn zig_zag_channel_tortuosity_is_its_hand_computed_path_length() {
    // A one-voxel chain along x in each z layer (3 layers): 6 steps along x, 6 diagonal steps
    // (x+1, y+1), 6 along x, 6 diagonal (x+1, y-1), twice: 48 steps, 24 of length h and
    // 24 of h sqrt 2, so geodesic / straight = (24 + 24 sqrt 2) / 48 = (1 + sqrt 2) / 2.
    // An isolated pocket then lowers the connected fraction.
    let d = [49, 10, 3];
    let mut mask = vec![false; d.iter().product()];
    let mut y = 1usize;
    let mut path = vec![(0usize, y)];
    for x in 1..49 {
        let phase = (x - 1) % 24;
        if (6..12).contains(&phase) {
            y += 1;
        } else if (18..24).contains(&phase) {
            y -= 1;
        }
        path.push((x, y));
    }
    for &(x, y) in &path {
        for z in 0..3 {
            mask[idx(d, x, y, z)] = true;
        }
    }
    let t = tortuosity(&mask, d, [2e-6; 3], [false; 3], 0);
    let want = (1.0 + 2f64.sqrt()) / 2.0;
    println!("zig-zag tortuosity {} (hand: {want})", t.mean);
    assert!((t.mean - want).abs() < 1e-12 && (t.min - want).abs() < 1e-12);
    assert_eq!(t.outlet_reached, 1.0);
    // An isolated pocket of 3 voxels: not connected.
    mask[idx(d, 40, 9, 1)] = true;
    mask[idx(d, 41, 9, 1)] = true;
    mask[idx(d, 42, 9, 1)] = true;
    let t = tortuosity(&mask, d, [2e-6; 3], [false; 3], 0);
    let phase = (49 * 3 + 3) as f64;
    assert!((t.connected - 147.0 / phase).abs() < 1e-15);
    // The same channel with anisotropic voxels (h_y = 2 h_x): diagonal steps are sqrt 5 h_x.
    let t = tortuosity(&mask, d, [1e-6, 2e-6, 1e-6], [false; 3], 0);
    let want = (24.0 + 24.0 * 5f64.sqrt()) / 48.0;
    assert!((t.mean - want).abs() < 1e-12, "{} vs {want}", t.mean);
}

// ---------------------------------------------------------------- conductivity recipe

#[test]
fn straight_tube_bundle_formation_factor_is_one_over_porosity() {
    // The formation factor recipe: conductivity.fft's solver on the pore phase (pore 1, solid
    // 0). Straight square tubes along z (4 x 4 of 12 x 12 voxels, periodic): the pore
    // conducts in parallel along z, k_zz = phi, F = 1 / phi, tortuosity factor phi F = 1.
    use grainpipe_core::units::Q;
    use grainpipe_fft::common::{Discretization, Solver};
    use grainpipe_fft::conductivity::{solve_all, ConductivityParams, GradientCase};
    let d = [12, 12, 6];
    let h = 1e-6;
    let labels: Vec<u8> = (0..d.iter().product())
        .map(|i: usize| {
            let (x, y) = (i % 12, (i / 12) % 12);
            u8::from(!(x % 6 < 2 && y % 6 < 2))
        })
        .collect();
    let image = PhaseImage {
        grid: Grid {
            dims: d,
            spacing: [h; 3],
            origin: [0.0; 3],
            periodic: [true; 3],
        },
        labels,
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 1,
                name: "solid".into(),
            },
        ],
    };
    let phi = image.fraction(0);
    let p = ConductivityParams {
        conductivities: [("pore", 1.0), ("solid", 0.0)]
            .iter()
            .map(|&(n, v)| (n.to_string(), Q::new(v)))
            .collect(),
        load_cases: vec![GradientCase::Z],
        discretization: Discretization::Staggered,
        solver: Solver::Cg,
        tolerance: 1e-10,
        ..Default::default()
    };
    let k = grainpipe_fft::common::resolve("conductivities", &p.conductivities, &image, 0.0, |q| {
        Ok(q.si())
    })
    .unwrap();
    let rep = grainpipe_core::stage::SilentReporter;
    let ctx = RunContext::new(1, &rep);
    let (sigma, _) = solve_all::<f64>(&p, &image, &k, None, &ctx).unwrap();
    let f = 1.0 / sigma[2][2];
    println!("phi {phi}, k_zz {}, F {f}, phi F {}", sigma[2][2], phi * f);
    assert!((f * phi - 1.0).abs() < 1e-8, "F {f}, 1/phi {}", 1.0 / phi);
}

// ---------------------------------------------------------------- pipeline

#[test]
fn pipeline_runs_every_pore_stage_on_a_packing() {
    // An RSA packing (R = 20 um, 10 voxels) voxelized at 2 um in a periodic 160 um box; each
    // stage on the pore phase (and the solid's thickness), cross-checked against
    // analysis.phases and the packing.
    let yaml = "name: t\nseed: 11\nstages:\n\
        - id: pack\n  use: packing.rsa\n  with: { size: [160 um, 160 um, 160 um], radius: { kind: fixed, value: 20 um }, volume_fraction: 0.3 }\n\
        - id: vox\n  use: voxelize.packing\n  in: { packing: pack.packing }\n  with: { voxel_size: 2 um }\n\
        - id: ph\n  use: analysis.phases\n  in: { image: vox.image }\n\
        - id: lt\n  use: analysis.local_thickness\n  in: { image: vox.image }\n  with: { bins: 20, field: true }\n\
        - id: lts\n  use: analysis.local_thickness\n  in: { image: vox.image }\n  with: { phase: [1] }\n\
        - id: s2\n  use: analysis.two_point\n  in: { image: vox.image }\n  with: { max_lag: 40 um, radial: true }\n\
        - id: ch\n  use: analysis.chords\n  in: { image: vox.image }\n\
        - id: tau\n  use: analysis.tortuosity\n  in: { image: vox.image }\n  with: { axes: [z, x] }\n";
    let res = run_yaml(&registry(), yaml).unwrap_or_else(|e| panic!("{e}"));
    let phi = res.column("ph.phases", "volume_fraction")[0];
    let sv = res.column("ph.phases", "specific_surface")[0];
    // Local thickness: fractions sum to 1, cumulative ends at 1, the field matches.
    let frac = res.column("lt.distribution", "volume_fraction");
    assert_eq!(frac.len(), 20);
    assert!((frac.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    assert!((res.column("lt.distribution", "cumulative")[19] - 1.0).abs() < 1e-12);
    assert_eq!(res.value("lt.summary", "volume_fraction"), phi);
    let field = res.artifact("lt.thickness").as_field().unwrap();
    assert_eq!(field.unit, "m");
    // The solid's largest thickness: the spheres' diameter 2R, less up to 2 offset + 1
    // voxel for spheres centred off the lattice (see the ball test), at most 2R + h.
    let solid_max = res.value("lts.summary", "max_thickness");
    println!(
        "solid max thickness {solid_max}, pore mean {}",
        res.value("lt.summary", "mean_thickness")
    );
    assert!(solid_max <= 42e-6 && solid_max >= 40e-6 - (3f64.sqrt() + 1.0) * 2e-6);
    // Two-point: S2(0) = phi on every axis, lag in m.
    let s2 = res.column("s2.s2", "s2");
    let lag = res.column("s2.s2", "lag");
    assert_eq!(s2.len(), 3 * 21);
    for a in 0..3 {
        assert!((s2[21 * a] - phi).abs() < 1e-12);
        assert!((lag[21 * a + 20] - 40e-6).abs() < 1e-15);
        // Long range: towards phi^2 (within the packing's short-range order).
        assert!(s2[21 * a + 20] < phi && s2[21 * a + 20] > phi * phi * 0.8);
    }
    // Radial S2: 21 shells of 2 um, S2(0) = phi; the 2 um shell (|d| 0.5 to 1.5 voxels) holds
    // the face diagonals too, so it lies a little below the axial S2 at one voxel.
    let radial = res.column("s2.radial", "s2");
    assert_eq!(radial.len(), 21);
    assert!((radial[0] - phi).abs() < 1e-12);
    let axial1 = [s2[1], s2[22], s2[43]];
    println!("S2 at 2 um: radial {}, axial {axial1:?}", radial[1]);
    assert!((radial[1] - axial1.iter().sum::<f64>() / 3.0).abs() < 0.01);
    // Chords: the stereological mean pore chord = 4 phi / S_V (Cauchy, S_V by Crofton from
    // analysis.phases) within 2 %. The mean of the chords counted is shorter: lines wholly
    // in the pore (about a tenth in this 80-voxel box) are left out as unbounded; with
    // their length included it is the stereological one.
    let mean = res.column("ch.summary", "mean_chord");
    let stereo = res.column("ch.summary", "stereological_chord");
    let unbounded = res.column("ch.summary", "unbounded");
    let chords = res.column("ch.summary", "chords");
    let cauchy = 4.0 * phi / sv;
    for a in 0..3 {
        println!(
            "pore chord: mean {:.4e}, stereological {:.4e}, 4 phi / S_V {cauchy:.4e}, \
             {} unbounded of {} lines",
            mean[a],
            stereo[a],
            unbounded[a],
            80 * 80
        );
        assert!((stereo[a] / cauchy - 1.0).abs() < 0.02);
        let with_unbounded = (mean[a] * chords[a] + unbounded[a] * 160e-6) / chords[a];
        assert!((with_unbounded / stereo[a] - 1.0).abs() < 1e-12);
        assert!(mean[a] < stereo[a]);
    }
    assert_eq!(res.column("ch.summary", "cut"), vec![0.0; 3]);
    // Tortuosity of a loose packing's pores: connected, between 1 and 1.2.
    let tau = res.column("tau.tortuosity", "tortuosity");
    println!("tortuosity {tau:?}");
    for t in &tau {
        assert!(*t > 1.0 && *t < 1.2);
    }
    assert_eq!(
        res.column("tau.tortuosity", "outlet_fraction"),
        vec![1.0, 1.0]
    );
}

#[test]
fn preflight_names_the_parameter() {
    let yaml = "name: t\nseed: 1\nstages:\n\
        - id: pack\n  use: packing.rsa\n  with: { size: [40 um, 40 um, 40 um], radius: { kind: fixed, value: 5 um }, volume_fraction: 0.2 }\n\
        - id: vox\n  use: voxelize.packing\n  in: { packing: pack.packing }\n  with: { voxel_size: 2 um }\n\
        - id: s2\n  use: analysis.two_point\n  in: { image: vox.image }\n  with: { max_lag: 1 mm, phase: [0, 0] }\n\
        - id: lt\n  use: analysis.local_thickness\n  in: { image: vox.image }\n  with: { bins: 0 }\n\
        - id: tau\n  use: analysis.tortuosity\n  in: { image: vox.image }\n  with: { axes: [x, x] }\n";
    let Err(e) = run_yaml(&registry(), yaml) else {
        panic!("bad parameters accepted")
    };
    let all = std::iter::once(&e)
        .chain(&e.related)
        .map(|e| format!("{} {:?}", e.message, e.loc))
        .collect::<Vec<_>>()
        .join("\n");
    println!("{all}");
    for want in ["label 0 is listed twice", "bins", "`x` is listed twice"] {
        assert!(all.contains(want), "no `{want}` in {all}");
    }
}

#[test]
fn kernels_give_the_same_results_on_1_and_3_threads() {
    let pore = boolean_pores(7, 40, 3.0, 400);
    let d = [40; 3];
    let run = || {
        let t = local_thickness(&pore, d, [1.0, 1.1, 0.9], [true, false, true]);
        let s: Vec<_> = (0..3)
            .map(|a| pair_counts(&pore, d, a, a != 1, 20))
            .collect();
        let c: Vec<_> = (0..3).map(|a| chord_counts(&pore, d, a, a != 1)).collect();
        let g = tortuosity(&pore, d, [1.0; 3], [true, false, true], 2);
        let r = radial_counts(&pore, d, [1.0, 1.1, 0.9], [true, false, true], 0.9, 15);
        (t, s, c, g, r)
    };
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    let one = pool(1).install(run);
    let three = pool(3).install(run);
    assert!(one.0 == three.0 && one.1 == three.1 && one.2 == three.2 && one.3 == three.3);
    assert_eq!(one.4, three.4);
}
