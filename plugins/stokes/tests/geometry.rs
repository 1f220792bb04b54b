//! Symmetries of the discrete problem, percolation, isolated pores and thread-count
//! independence, on an irregular image with off-diagonal permeability.
#![allow(clippy::needless_range_loop)] // index loops mirror the voxel formulas

mod common;

use grainpipe_stokes::mac::Dims;
use grainpipe_stokes::solver::symmetry_error;

/// Overlapping balls at fixed pseudo-random centres in a non-cubic periodic box: no symmetry,
/// so kappa has off-diagonal terms.
fn irregular(dims: Dims) -> Vec<bool> {
    let mut fluid = vec![true; dims.len()];
    let centres = [
        [3.1, 4.7, 2.2, 3.6],
        [12.4, 9.3, 7.8, 4.1],
        [7.9, 15.2, 11.5, 3.3],
        [17.3, 3.9, 13.1, 4.4],
        [2.6, 11.8, 8.4, 2.9],
        [14.8, 16.1, 2.7, 3.8],
    ];
    for i in 0..dims.len() {
        let p = dims.coords(i);
        for c in &centres {
            let d2: f64 = (0..3)
                .map(|a| {
                    let l = dims.n[a] as f64;
                    let mut d = (p[a] as f64 + 0.5 - c[a]).abs();
                    d = d.min(l - d);
                    d * d
                })
                .sum();
            if d2 <= c[3] * c[3] {
                fluid[i] = false;
            }
        }
    }
    fluid
}

fn transform(
    dims: Dims,
    fluid: &[bool],
    map: impl Fn([usize; 3]) -> [usize; 3],
    out: Dims,
) -> Vec<bool> {
    let mut t = vec![false; out.len()];
    for i in 0..dims.len() {
        let q = map(dims.coords(i));
        t[out.index(q[0], q[1], q[2])] = fluid[i];
    }
    t
}

fn close(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3], tol: f64) -> bool {
    let scale = a.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
    (0..3).all(|i| (0..3).all(|j| (a[i][j] - b[i][j]).abs() <= tol * scale))
}

#[test]
fn tensor_is_symmetric_and_follows_mirrors_and_rotations() {
    let dims = Dims::new([20, 20, 16]);
    let fluid = irregular(dims);
    let k = common::solve(dims, &fluid, &[0, 1, 2], 1e-7).kappa;
    // The discrete operator is symmetric, so kappa is, up to the solver tolerance.
    assert!(
        symmetry_error(&k) < 1e-5,
        "symmetry error {}",
        symmetry_error(&k)
    );
    let off = k[0][1].abs().max(k[0][2].abs()).max(k[1][2].abs());
    assert!(
        off > 1e-3 * k[0][0],
        "the test image needs off-diagonal terms: {k:?}"
    );

    // Mirror x -> -x: kappa' = M kappa M with M = diag(-1, 1, 1).
    let n = dims.n;
    let m = transform(dims, &fluid, |p| [n[0] - 1 - p[0], p[1], p[2]], dims);
    let km = common::solve(dims, &m, &[0, 1, 2], 1e-7).kappa;
    let s = [-1.0, 1.0, 1.0];
    let expect: [[f64; 3]; 3] =
        std::array::from_fn(|i| std::array::from_fn(|j| s[i] * s[j] * k[i][j]));
    assert!(close(&km, &expect, 1e-5), "mirrored {km:?} vs {expect:?}");

    // Rotation by 90 degrees about z: (x, y) -> (n - 1 - y, x), so e_x -> e_y, e_y -> -e_x.
    let r = transform(
        dims,
        &fluid,
        |p| [n[1] - 1 - p[1], p[0], p[2]],
        Dims::new([n[1], n[0], n[2]]),
    );
    let kr = common::solve(Dims::new([n[1], n[0], n[2]]), &r, &[0, 1, 2], 1e-7).kappa;
    // R = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]; kappa' = R kappa R^T.
    let rot = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
    let expect: [[f64; 3]; 3] = std::array::from_fn(|i| {
        std::array::from_fn(|j| {
            let mut v = 0.0;
            for a in 0..3 {
                for b in 0..3 {
                    v += rot[i][a] * k[a][b] * rot[j][b];
                }
            }
            v
        })
    });
    assert!(close(&kr, &expect, 1e-5), "rotated {kr:?} vs {expect:?}");
}

#[test]
fn closed_wall_gives_zero_with_a_note_and_no_solve() {
    // The irregular image with a solid layer z = 0: nothing percolates along z.
    let dims = Dims::new([20, 20, 16]);
    let mut fluid = irregular(dims);
    for i in 0..dims.len() {
        if dims.coords(i)[2] == 0 {
            fluid[i] = false;
        }
    }
    let r = common::solve(dims, &fluid, &[0, 1, 2], 1e-6);
    assert!(!r.percolation.percolates[2]);
    assert!(r.percolation.percolates[0] && r.percolation.percolates[1]);
    let z = r.cases.iter().find(|c| c.axis == 2).unwrap();
    assert_eq!(z.iterations, 0);
    assert!(z
        .note
        .as_deref()
        .unwrap()
        .contains("does not percolate along z"));
    for i in 0..3 {
        assert_eq!(r.kappa[i][2], 0.0);
        // Flow driven along x or y cannot cross the wall either: exactly 0 by mass balance
        // through every z-plane of the discrete solution, up to the tolerance.
        assert!(r.kappa[2][i].abs() < 1e-5 * r.kappa[0][0]);
    }
    assert!(r.kappa[0][0] > 0.0 && r.kappa[1][1] > 0.0);

    // A fully closed pore space: every direction 0, nothing solved.
    let closed: Vec<bool> = (0..dims.len())
        .map(|i| dims.coords(i).iter().all(|&c| c % 5 != 0))
        .collect();
    let r = common::solve(dims, &closed, &[0, 1, 2], 1e-6);
    assert_eq!(r.percolation.percolating_components, 0);
    assert!(r.percolation.components > 1);
    assert!(r
        .cases
        .iter()
        .all(|c| c.iterations == 0 && c.note.is_some()));
    assert_eq!(r.kappa, [[0.0; 3]; 3]);
}

#[test]
fn isolated_pores_are_excluded_and_change_nothing() {
    let dims = Dims::new([20, 20, 16]);
    let fluid = irregular(dims);
    // Fill the ball around centre 2 solid, then carve a closed cavity in it.
    let mut with_cavity = fluid.clone();
    let mut filled = fluid.clone();
    for i in 0..dims.len() {
        let p = dims.coords(i).map(|v| v as f64 + 0.5);
        let d2 = (p[0] - 12.4).powi(2) + (p[1] - 9.3).powi(2) + (p[2] - 7.8).powi(2);
        if d2 <= 4.1 * 4.1 {
            filled[i] = false;
            with_cavity[i] = d2 <= 2.0 * 2.0;
        }
    }
    let a = common::solve(dims, &filled, &[0], 1e-6);
    let b = common::solve(dims, &with_cavity, &[0], 1e-6);
    let cavity = with_cavity.iter().filter(|&&f| f).count() - filled.iter().filter(|&&f| f).count();
    assert!(cavity > 0);
    assert_eq!(b.percolation.isolated, a.percolation.isolated + cavity);
    assert_eq!(a.kappa, b.kappa, "a closed cavity must not change kappa");
    assert!(b.porosity > a.porosity && b.connected_porosity == a.connected_porosity);
}

#[test]
fn results_do_not_depend_on_the_thread_count() {
    let dims = Dims::new([21, 20, 15]); // odd sizes exercise the sequential seam of the smoother
    let fluid = irregular(dims);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| common::solve(dims, &fluid, &[0, 2], 1e-6))
    };
    let one = run(1);
    let three = run(3);
    assert_eq!(one.kappa, three.kappa);
    assert_eq!(one.cases[0].iterations, three.cases[0].iterations);
    assert_eq!(one.cases[1].history, three.cases[1].history);
}
