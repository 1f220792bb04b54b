//! Connected components and percolation against independent references: shapes whose
//! answer is known by construction (bars, a helix winding around a periodic axis, a loop
//! that only crosses a periodic face, separated balls), and a breadth-first flood fill that
//! tracks unwrapped coordinates (a different algorithm from the union-find under test) on
//! random images with every combination of periodic axes.

use grainpipe_analysis::components::{label_components, Labeling, NONE};
use std::collections::VecDeque;

fn idx(d: [usize; 3], x: usize, y: usize, z: usize) -> usize {
    x + d[0] * (y + d[1] * z)
}

/// The voxels whose centre (index + 0.5) satisfies `f`.
fn mask(d: [usize; 3], f: impl Fn([f64; 3]) -> bool) -> Vec<bool> {
    let mut m = vec![false; d[0] * d[1] * d[2]];
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                m[idx(d, x, y, z)] = f([x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5]);
            }
        }
    }
    m
}

fn label(d: [usize; 3], periodic: [bool; 3], m: &[bool]) -> Labeling {
    label_components(d, periodic, |i| m[i])
}

/// Distance between a and b along axis `a`, through the periodic face when `wrap`.
fn sep(a: f64, b: f64, n: usize, wrap: bool) -> f64 {
    let d = (a - b).abs();
    if wrap {
        d.min(n as f64 - d)
    } else {
        d
    }
}

#[test]
fn bar_along_x_percolates_along_x_only() {
    let d = [30, 20, 16];
    // A square bar and a round cylinder along x, away from the y and z faces.
    let bar = mask(d, |c| {
        (5.0..11.0).contains(&c[1]) && (4.0..9.0).contains(&c[2])
    });
    let cyl = mask(d, |c| (c[1] - 10.0).powi(2) + (c[2] - 8.0).powi(2) < 16.0);
    for m in [&bar, &cyl] {
        for periodic in [[false; 3], [true; 3], [true, false, true]] {
            let l = label(d, periodic, m);
            assert_eq!(l.components.len(), 1, "{periodic:?}");
            assert_eq!(l.percolates(), [true, false, false], "{periodic:?}");
            assert_eq!(l.voxels(), m.iter().filter(|&&b| b).count() as u64);
            assert_eq!(l.percolating_voxels([true; 3]), l.voxels());
            assert_eq!(l.percolating_voxels([false, true, true]), 0);
        }
    }
    // A bar along x with one x plane missing: spans nothing in a non-periodic box; in a
    // periodic one it is a single piece crossing the face, which still does not wind.
    let cut = mask(d, |c| {
        (5.0..11.0).contains(&c[1]) && (4.0..9.0).contains(&c[2]) && !(12.0..13.0).contains(&c[0])
    });
    let open = label(d, [false; 3], &cut);
    assert_eq!(open.components.len(), 2);
    assert_eq!(open.percolates(), [false; 3]);
    let wrapped = label(d, [true; 3], &cut);
    assert_eq!(wrapped.components.len(), 1);
    assert_eq!(wrapped.percolates(), [false; 3]);
}

#[test]
fn helix_winding_around_periodic_z_percolates_along_z_only() {
    let d = [24, 24, 32];
    // A tube of radius 2.2 around x = 12 + 6 cos(2 pi z / 32), y = 12 + 6 sin(...): it closes
    // on itself through the periodic z face after one turn, as a ring around a torus.
    let curve: Vec<[f64; 3]> = (0..640)
        .map(|k| {
            let t = k as f64 / 640.0;
            let a = std::f64::consts::TAU * t;
            [12.0 + 6.0 * a.cos(), 12.0 + 6.0 * a.sin(), 32.0 * t]
        })
        .collect();
    let tube = |wrap_z: bool| {
        mask(d, |c| {
            curve.iter().any(|p| {
                let dz = sep(c[2], p[2], d[2], wrap_z);
                (c[0] - p[0]).powi(2) + (c[1] - p[1]).powi(2) + dz * dz < 2.2 * 2.2
            })
        })
    };
    let m = tube(true);
    let l = label(d, [true; 3], &m);
    assert_eq!(l.components.len(), 1);
    assert_eq!(l.components[0].winds, [false, false, true]);
    assert_eq!(l.percolates(), [false, false, true]);
    // Without periodic z the same voxels touch both z faces: spans z as well.
    let l = label(d, [true, true, false], &m);
    assert_eq!(l.percolates(), [false, false, true]);
}

#[test]
fn a_loop_that_only_crosses_the_periodic_face_does_not_percolate() {
    let d = [28, 12, 28];
    // A torus (ring radius 7, tube radius 2.5) in the x-z plane centred on the z face: cut
    // in two by the face in the image, one closed loop on the torus, winding number 0.
    let ring = |wrap: bool| {
        mask(d, |c| {
            let dx = c[0] - 14.0;
            let dz = sep(c[2], 0.0, d[2], wrap);
            let rho = (dx * dx + dz * dz).sqrt();
            (rho - 7.0).powi(2) + (c[1] - 6.0).powi(2) < 2.5 * 2.5
        })
    };
    let m = ring(true);
    let periodic = label(d, [true; 3], &m);
    assert_eq!(periodic.components.len(), 1);
    assert_eq!(periodic.percolates(), [false; 3]);
    // Non-periodic, the two halves are separate and each touches one z face only.
    let open = label(d, [false; 3], &m);
    assert_eq!(open.components.len(), 2);
    assert_eq!(open.percolates(), [false; 3]);
}

#[test]
fn separated_balls_are_one_component_each_even_across_periodic_faces() {
    let d = [40, 36, 32];
    // Centres (some on faces and a corner, so they wrap) with radii; gaps >= 2 voxels.
    let balls: [([f64; 3], f64); 6] = [
        ([0.0, 0.0, 0.0], 5.0),
        ([20.0, 18.0, 16.0], 6.0),
        ([39.0, 10.0, 8.0], 4.0),
        ([10.0, 35.5, 20.0], 4.5),
        ([30.0, 26.0, 31.0], 3.5),
        ([8.0, 14.0, 12.0], 3.0),
    ];
    let m = mask(d, |c| {
        balls.iter().any(|(p, r)| {
            (0..3)
                .map(|a| sep(c[a], p[a], d[a], true).powi(2))
                .sum::<f64>()
                < r * r
        })
    });
    let l = label(d, [true; 3], &m);
    assert_eq!(l.components.len(), balls.len());
    assert_eq!(l.percolates(), [false; 3]);
    // Each component holds exactly the voxels of one ball (counted directly).
    let mut sizes: Vec<u64> = l.components.iter().map(|c| c.voxels).collect();
    let mut want: Vec<u64> = balls
        .iter()
        .map(|(p, r)| {
            mask(d, |c| {
                (0..3)
                    .map(|a| sep(c[a], p[a], d[a], true).powi(2))
                    .sum::<f64>()
                    < r * r
            })
            .iter()
            .filter(|&&b| b)
            .count() as u64
        })
        .collect();
    sizes.sort();
    want.sort();
    assert_eq!(sizes, want);
}

#[test]
fn one_voxel_thick_periodic_axis_and_two_voxel_rings() {
    // A 2-D image with periodic z of one layer: every voxel touches its own image along z.
    let d = [5, 4, 1];
    let m = mask(d, |c| c[0] < 2.0 && c[1] < 1.0);
    let l = label(d, [false, false, true], &m);
    assert_eq!(l.components.len(), 1);
    assert_eq!(l.percolates(), [false, false, true]);
    // Two voxels along a periodic x of length 2 form an infinite line.
    let d = [2, 3, 3];
    let m = mask(d, |c| c[1] < 1.0 && c[2] < 1.0);
    assert_eq!(label(d, [true; 3], &m).percolates(), [true, false, false]);
    assert_eq!(label(d, [false; 3], &m).percolates(), [true, false, false]);
}

/// SplitMix64: a fixed pseudo-random stream for the random images.
fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E3779B97F4A7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
    z ^ (z >> 31)
}

/// Reference: flood fill from each unvisited voxel, remembering the unwrapped coordinates
/// each voxel was first reached at; reaching it again at other coordinates means the
/// component meets its own periodic image. Returns (voxels, percolates) per component in
/// raster order of first voxel.
fn flood(d: [usize; 3], periodic: [bool; 3], m: &[bool]) -> Vec<(u64, [bool; 3])> {
    let n = m.len();
    let mut seen: Vec<Option<[i64; 3]>> = vec![None; n];
    let mut out = Vec::new();
    for start in 0..n {
        if !m[start] || seen[start].is_some() {
            continue;
        }
        let c0 = [start % d[0], (start / d[0]) % d[1], start / (d[0] * d[1])].map(|v| v as i64);
        seen[start] = Some(c0);
        let mut q = VecDeque::from([c0]);
        let (mut count, mut winds) = (0u64, [false; 3]);
        let mut lo = [i64::MAX; 3];
        let mut hi = [i64::MIN; 3];
        while let Some(u) = q.pop_front() {
            count += 1;
            for a in 0..3 {
                lo[a] = lo[a].min(u[a]);
                hi[a] = hi[a].max(u[a]);
            }
            for a in 0..3 {
                for s in [-1i64, 1] {
                    let mut v = u;
                    v[a] += s;
                    let w = [0, 1, 2].map(|b| v[b].rem_euclid(d[b] as i64));
                    if !periodic[a] && w[a] != v[a] {
                        continue;
                    }
                    let i = (w[0] + d[0] as i64 * (w[1] + d[1] as i64 * w[2])) as usize;
                    if !m[i] {
                        continue;
                    }
                    match seen[i] {
                        None => {
                            seen[i] = Some(v);
                            q.push_back(v);
                        }
                        Some(p) => {
                            for b in 0..3 {
                                winds[b] |= p[b] != v[b];
                            }
                        }
                    }
                }
            }
        }
        let perc = [0, 1, 2].map(|a| {
            if periodic[a] {
                winds[a]
            } else {
                lo[a] == 0 && hi[a] == d[a] as i64 - 1
            }
        });
        out.push((count, perc));
    }
    out
}

#[test]
fn random_images_agree_with_a_flood_fill_for_every_periodicity() {
    let d = [23, 17, 19];
    let mut state = 42u64;
    for fill in [0.25, 0.32, 0.45] {
        // 0.3116 is the site percolation threshold of the simple cubic lattice: below,
        // between and above it, so spanning and non-spanning clusters both occur.
        let m: Vec<bool> = (0..d.iter().product::<usize>())
            .map(|_| (splitmix(&mut state) >> 11) as f64 / (1u64 << 53) as f64)
            .map(|u| u < fill)
            .collect();
        for bits in 0..8 {
            let periodic = [bits & 1 != 0, bits & 2 != 0, bits & 4 != 0];
            let want = flood(d, periodic, &m);
            let got = label(d, periodic, &m);
            let got: Vec<(u64, [bool; 3])> = got
                .components
                .iter()
                .map(|c| (c.voxels, c.percolates))
                .collect();
            assert_eq!(got, want, "fill {fill}, periodic {periodic:?}");
        }
    }
}

#[test]
fn labels_do_not_depend_on_the_thread_count() {
    let d = [31, 29, 37];
    let mut state = 7u64;
    let m: Vec<bool> = (0..d.iter().product::<usize>())
        .map(|_| splitmix(&mut state) % 100 < 33)
        .collect();
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| label(d, [true, false, true], &m))
    };
    let one = run(1);
    assert!(one.components.len() > 10);
    for t in [2, 3, 5] {
        let other = run(t);
        assert_eq!(other.ids, one.ids, "{t} threads");
        assert_eq!(other.components, one.components, "{t} threads");
    }
    // Ids: NONE exactly outside the phase.
    assert!(one.ids.iter().zip(&m).all(|(&i, &b)| (i == NONE) != b));
}
