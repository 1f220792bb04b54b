//! The level-set binder against what its definition (Donval et al. 2025, eq. 2.14-2.15)
//! implies independently of the code: bridges at contacts only, growing with a, symmetric,
//! exact fractions, periodic invariance, and grid independence against the closing.

use grainpipe_binder::components::count_components;
use grainpipe_binder::smooth_union::{smooth_union, BinderTarget, SmoothUnion, SmoothUnionSpec};
use grainpipe_core::{Body, Domain, Grid, Packing, StageError};

const H: f64 = 1e-6;

fn packing(l: [f64; 3], spheres: &[([f64; 3], f64)]) -> Packing {
    let mut p = Packing::new(Domain::boxed([0.0; 3], l, [true; 3]));
    for &(c, r) in spheres {
        p.bodies.push(Body::sphere(c, r));
    }
    p
}

fn grid(p: &Packing, h: f64) -> Grid {
    Grid::tiling(p.domain.min, p.domain.max, p.domain.periodic, h)
}

fn run(p: &Packing, h: f64, grain: Option<u64>, binder: BinderTarget, ss: usize) -> SmoothUnion {
    run_over(p, h, grain, binder, ss, false)
}

fn run_over(
    p: &Packing,
    h: f64,
    grain: Option<u64>,
    binder: BinderTarget,
    ss: usize,
    per_body: bool,
) -> SmoothUnion {
    let spec = SmoothUnionSpec {
        k: 5,
        per_body,
        supersampling: ss,
        grain_voxels: grain,
        binder,
        initial_scale_bound: 0.5 * h,
        max_scale: 20.0 * h,
    };
    smooth_union::<StageError, _>(&grid(p, h), &p.world_spheres(), &spec, &|_, _| Ok(())).unwrap()
}

fn count(l: &[u8], v: u8) -> usize {
    l.iter().filter(|&&x| x == v).count()
}

/// Two spheres of radius 10 voxels touching at x = 32 voxels, the contact plane on a voxel
/// face so the grid is mirror symmetric about it; their periodic images are 20 voxels away.
fn touching(gap: f64) -> Packing {
    let r = 10.0 * H;
    packing(
        [64.0 * H, 40.0 * H, 40.0 * H],
        &[
            ([32.0 * H - r - gap / 2.0, 20.0 * H, 20.0 * H], r),
            ([32.0 * H + r + gap / 2.0, 20.0 * H, 20.0 * H], r),
        ],
    )
}

#[test]
fn bridge_grows_with_a_at_the_contact_symmetric_and_leaves_the_grains_alone() {
    let p = touching(0.0);
    let g = grid(&p, H);
    let [nx, ny, _] = g.dims;
    let mut last = 0;
    let mut grains: Option<Vec<bool>> = None;
    for a in [1.0, 1.5, 2.5, 4.0] {
        let res = run(&p, H, None, BinderTarget::Scale(a * H), 1);
        let l = &res.labels;
        let binder = count(l, 2);
        assert!(
            binder > last,
            "a = {a} voxels: {binder} binder voxels, not more than {last}"
        );
        last = binder;
        let g1: Vec<bool> = l.iter().map(|&x| x == 1).collect();
        match &grains {
            None => grains = Some(g1),
            Some(g0) => assert_eq!(g0, &g1, "binder changed the grain voxels (a = {a})"),
        }
        for (i, &v) in l.iter().enumerate() {
            let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
            // Mirror about the contact plane x = 32 voxels, and about y and z through the axis.
            let mx = g.index(nx - 1 - x, y, z);
            let my = g.index(x, ny - 1 - y, z);
            assert_eq!(v, l[mx], "not mirror symmetric at ({x}, {y}, {z})");
            assert_eq!(v, l[my], "not symmetric about the axis at ({x}, {y}, {z})");
            // A two-sphere smooth union adds material only near the contact: where the
            // second sphere is much further than the first, LSE = d1 - a ln(1 + e^-(d2-d1)/a)
            // differs from d1 by less than a e^-(d2-d1)/a. The periodic images, at least 20
            // voxels off, add less than 4 e^-5 < 0.03 voxels.
            if v == 2 {
                let c = g.voxel_center(x, y, z);
                let ext = g.extent();
                let d: Vec<f64> = p
                    .world_spheres()
                    .iter()
                    .map(|s| {
                        let q: f64 = (0..3)
                            .map(|k| {
                                let d = (c[k] - s.center[k]).abs();
                                d.min(ext[k] - d).powi(2)
                            })
                            .sum();
                        q.sqrt() - s.radius
                    })
                    .collect();
                let (d1, d2) = (d[0].min(d[1]), d[0].max(d[1]));
                assert!(
                    a * H * (-(d2 - d1) / (a * H)).exp() + 0.03 * H >= d1,
                    "binder at ({x}, {y}, {z}) away from the contact (d1 {d1:e}, d2 {d2:e})"
                );
            }
        }
    }
}

#[test]
fn target_fraction_is_hit_and_the_same_a_bridges_no_gap_of_half_a_radius() {
    // Off-grid positions so that no two voxels share a threshold.
    let r = 10.0 * H;
    let l = [64.0 * H, 40.0 * H, 40.0 * H];
    let p = packing(
        l,
        &[
            ([32.13 * H - r, 20.31 * H, 19.77 * H], r),
            ([32.13 * H + r, 20.31 * H, 19.77 * H], r),
        ],
    );
    let n = grid(&p, H).voxel_count() as u64;
    let target = n / 200; // 0.5 % of the cell
    let res = run(&p, H, None, BinderTarget::Voxels(target), 2);
    let got = count(&res.labels, 2) as u64;
    assert!(
        got.abs_diff(target) <= 1,
        "{got} binder voxels for a target of {target}"
    );
    // The same a with the spheres half a radius apart: the mid-plane distance 2.5 voxels
    // needs a >= 2.5 / ln 2 voxels for LSE <= 0 there (eq. 2.14 with two equal terms).
    assert!(res.scale < 2.5 * H / 2f64.ln());
    let apart = touching(0.5 * r);
    let res2 = run(&apart, H, None, BinderTarget::Scale(res.scale), 2);
    // The binder may coat the facing caps, but sand and binder stay two separate bodies.
    let solid: Vec<u8> = res2.labels.iter().map(|&l| u8::from(l != 0)).collect();
    let g2 = grid(&apart, H);
    assert_eq!(
        count_components(&g2, &solid, 1),
        2,
        "a bridge across a gap of half a radius"
    );
    // ... while the touching pair is one body.
    let solid: Vec<u8> = res.labels.iter().map(|&l| u8::from(l != 0)).collect();
    assert_eq!(count_components(&grid(&p, H), &solid, 1), 1);
}

#[test]
fn exact_fractions_hold_to_one_voxel_for_a_random_packing() {
    // 60 spheres of mixed radii, non-overlapping, by dart throwing with a fixed sequence.
    let l = 60.0 * H;
    let mut s: Vec<([f64; 3], f64)> = Vec::new();
    let mut x = 0.123456789f64;
    let mut next = || {
        x = (x * 9301.0 + 0.49297).fract();
        x
    };
    while s.len() < 60 {
        let r = (3.0 + 3.0 * next()) * H;
        let c = [next() * l, next() * l, next() * l];
        let ok = s.iter().all(|(c2, r2)| {
            let d2: f64 = (0..3)
                .map(|a| {
                    let d = (c[a] - c2[a]).abs();
                    d.min(l - d).powi(2)
                })
                .sum();
            d2.sqrt() > r + r2 + 0.7 * H
        });
        if ok {
            s.push((c, r));
        }
    }
    let p = packing([l; 3], &s);
    for h in [2.0 * H, 1.0 * H] {
        let g = grid(&p, h);
        let n = g.voxel_count() as u64;
        let sand = (p.volume_fraction() * n as f64).round() as u64;
        let binder = (0.03 * n as f64).round() as u64;
        let res = run(&p, h, Some(sand), BinderTarget::Voxels(binder), 2);
        let got_sand = count(&res.labels, 1) as u64;
        let got_binder = count(&res.labels, 2) as u64;
        assert!(
            got_sand.abs_diff(sand) <= 1,
            "h {h}: sand {got_sand} vs {sand}"
        );
        assert!(
            got_binder.abs_diff(binder) <= 1,
            "h {h}: binder {got_binder} vs {binder}"
        );
        // The radius correction is a fraction of a voxel.
        assert!(
            res.delta.abs() < 0.5 * h,
            "radius correction {} at h {h}",
            res.delta
        );
    }
}

#[test]
fn whole_period_shifts_give_the_same_image() {
    let l = [30.0 * H, 26.0 * H, 22.0 * H];
    let base = [
        ([3.3 * H, 4.1 * H, 2.2 * H], 6.0 * H),
        ([15.2 * H, 6.0 * H, 5.1 * H], 5.5 * H),
        ([9.0 * H, 16.7 * H, 14.9 * H], 7.0 * H),
        ([25.6 * H, 21.3 * H, 19.8 * H], 4.5 * H),
    ];
    let a = run(&packing(l, &base), H, None, BinderTarget::Voxels(400), 2);
    let shifted: Vec<([f64; 3], f64)> = base
        .iter()
        .map(|&(c, r)| ([c[0] + 2.0 * l[0], c[1] - l[1], c[2] + 3.0 * l[2]], r))
        .collect();
    let b = run(&packing(l, &shifted), H, None, BinderTarget::Voxels(400), 2);
    let differ = a
        .labels
        .iter()
        .zip(&b.labels)
        .filter(|(x, y)| x != y)
        .count();
    // Positions shifted by whole periods agree to rounding (1e-16 relative), which can flip
    // only a voxel whose threshold ties the selected one.
    assert!(differ <= 2, "{differ} voxels differ");
    assert!((a.scale - b.scale).abs() < 1e-9 * a.scale);
}

#[test]
fn smoothing_over_grains_puts_no_binder_inside_one_grain() {
    // One grain made of two overlapping spheres (a clump): over spheres the smooth minimum
    // fills the ridge where the spheres meet; over grains a lone grain has one distance, for
    // which LSE is the distance itself (eq. 2.14 with one term), so no binder at any a.
    let r = 8.0 * H;
    let mut p = packing([48.0 * H; 3], &[]);
    // Make both spheres one body: a clump of two.
    let mut lib = grainpipe_core::ClumpLibrary::default();
    lib.clumps.push(grainpipe_core::Clump {
        spheres: vec![
            grainpipe_core::ClumpSphere {
                offset: [-4.5 * H, 0.0, 0.0],
                radius: r,
            },
            grainpipe_core::ClumpSphere {
                offset: [4.5 * H, 0.0, 0.0],
                radius: r,
            },
        ],
        volume: 0.0,
        bounding_radius: 12.5 * H,
        principal_inertia: [1.0; 3],
        principal_axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        source: "two spheres".into(),
    });
    p.bodies = vec![grainpipe_core::Body {
        shape: grainpipe_core::BodyShape::Clump { index: 0 },
        position: [24.8 * H, 24.1 * H, 23.9 * H],
        orientation: [1.0, 0.0, 0.0, 0.0],
        layer: 0,
        frozen: false,
    }];
    p.library = Some(lib);
    let spheres = run_over(&p, H, None, BinderTarget::Scale(2.0 * H), 1, false);
    let grains = run_over(&p, H, None, BinderTarget::Scale(2.0 * H), 1, true);
    assert!(
        count(&spheres.labels, 2) > 0,
        "no ridge filling over spheres"
    );
    assert_eq!(count(&grains.labels, 2), 0, "binder inside a lone grain");
    assert_eq!(count(&spheres.labels, 1), count(&grains.labels, 1));
}
