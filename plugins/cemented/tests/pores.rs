//! analysis.pores: pore and void counts and volumes on hand-built images, contact closing,
//! partial coordination numbers on a hand-built packing.

#![allow(clippy::needless_range_loop)] // axis loops index several vectors

use grainpipe_cemented::common::{phases, Particles, LARGE, MATRIX, SMALL, VOID};
use grainpipe_cemented::pores::{analyse, contacts, partial_coordination, PoresParams};
use grainpipe_core::units::Q;
use grainpipe_core::{Domain, Grid, PhaseImage, Table};

fn image(nx: usize, ny: usize, f: impl Fn(usize, usize) -> u8) -> PhaseImage {
    let grid = Grid {
        dims: [nx, ny, 1],
        spacing: [1.0; 3],
        origin: [0.0, 0.0, -0.5],
        periodic: [false; 3],
    };
    let mut labels = vec![0u8; nx * ny];
    for y in 0..ny {
        for x in 0..nx {
            labels[x + nx * y] = f(x, y);
        }
    }
    PhaseImage {
        grid,
        labels,
        phases: phases(),
    }
}

fn col(t: &Table, name: &str) -> Vec<f64> {
    match &t.column(name).unwrap().data {
        grainpipe_core::ColumnData::F64(v) => v.clone(),
        grainpipe_core::ColumnData::I64(v) => v.iter().map(|&x| x as f64).collect(),
        _ => panic!(),
    }
}

fn no_particles() -> Particles {
    Particles {
        pos: vec![],
        radius: vec![],
        class: vec![],
        dim: 2,
    }
}

#[test]
fn three_cells_give_three_pores_and_three_voids() {
    // A particle frame with walls at x = 10 and 20: cells A (x 1..9), B (11..19), C (21..28),
    // y 1..8. A is empty; B has a matrix column at x = 15 that splits its void in two;
    // C is full of matrix.
    let img = image(30, 10, |x, y| {
        if x == 0 || x == 29 || y == 0 || y == 9 || x == 10 || x == 20 {
            LARGE
        } else if x == 15 || x > 20 {
            MATRIX
        } else {
            VOID
        }
    });
    let domain = Domain::boxed([0.0; 3], [30.0, 10.0, 1.0], [false; 3]);
    let out = analyse(&img, &no_particles(), &domain, &PoresParams::default()).unwrap();
    let pores = out["pores"].as_table().unwrap();
    let voids = out["voids"].as_table().unwrap();
    let mut pv = col(pores, "volume");
    pv.sort_by(f64::total_cmp);
    assert_eq!(pv, vec![64.0, 72.0, 72.0]);
    let mut vv = col(voids, "volume");
    vv.sort_by(f64::total_cmp);
    assert_eq!(vv, vec![32.0, 32.0, 72.0]);
    assert!(col(pores, "border").iter().all(|&b| b == 0.0));
    let s = out["summary"].as_table().unwrap();
    assert_eq!(col(s, "n_pores")[0], 3.0);
    assert_eq!(col(s, "n_voids")[0], 3.0);
    // S_m = rho_m / (1 - rho_p) = 72 / 208.
    assert!((col(s, "s_m")[0] - 72.0 / 208.0).abs() < 1e-12);
}

#[test]
fn border_regions_are_listed_but_not_counted() {
    // Open image: one void region touching the border, one enclosed matrix-ringed void.
    let img = image(20, 20, |x, y| {
        let (dx, dy) = (x as f64 - 10.0, y as f64 - 10.0);
        let r = (dx * dx + dy * dy).sqrt();
        if r < 3.0 {
            VOID
        } else if r < 5.0 {
            MATRIX
        } else if r < 7.0 {
            SMALL
        } else {
            VOID
        }
    });
    let domain = Domain::boxed([0.0; 3], [20.0, 20.0, 1.0], [false; 3]);
    let out = analyse(&img, &no_particles(), &domain, &PoresParams::default()).unwrap();
    let s = out["summary"].as_table().unwrap();
    assert_eq!(col(s, "n_voids")[0], 1.0);
    assert_eq!(col(s, "n_voids_border")[0], 1.0);
    assert_eq!(col(s, "n_pores")[0], 1.0);
    let p = PoresParams {
        include_border: true,
        ..Default::default()
    };
    let out = analyse(&img, &no_particles(), &domain, &p).unwrap();
    assert_eq!(col(out["summary"].as_table().unwrap(), "n_voids")[0], 2.0);
}

/// Three disks of radius 10 px with 2 px gaps around a central interstice.
fn three_disks() -> (PhaseImage, Particles) {
    let r = 10.0;
    let d = 22.0;
    let c = [
        [40.0, 30.0, 0.0],
        [40.0 + d, 30.0, 0.0],
        [40.0 + 0.5 * d, 30.0 + d * 3f64.sqrt() / 2.0, 0.0],
    ];
    let img = image(100, 80, |x, y| {
        let p = [x as f64 + 0.5, y as f64 + 0.5];
        if c.iter()
            .any(|k| (p[0] - k[0]).powi(2) + (p[1] - k[1]).powi(2) < r * r)
        {
            LARGE
        } else {
            VOID
        }
    });
    let parts = Particles {
        pos: c.to_vec(),
        radius: vec![r; 3],
        class: vec![LARGE; 3],
        dim: 2,
    };
    (img, parts)
}

#[test]
fn contacts_within_the_horizon_close_the_interstice() {
    let (img, parts) = three_disks();
    let domain = Domain::boxed([0.0, 0.0, -0.5], [100.0, 80.0, 0.5], [false; 3]);
    let open = PoresParams {
        close_contacts: false,
        include_border: true,
        horizon: Some(Q::new(3.0)),
        ..Default::default()
    };
    let out = analyse(&img, &parts, &domain, &open).unwrap();
    assert_eq!(col(out["summary"].as_table().unwrap(), "n_pores")[0], 1.0);
    let closed = PoresParams {
        close_contacts: true,
        ..open
    };
    let out = analyse(&img, &parts, &domain, &closed).unwrap();
    let pores = out["pores"].as_table().unwrap();
    assert_eq!(pores.rows(), 2);
    let inner: Vec<f64> = col(pores, "volume")
        .into_iter()
        .zip(col(pores, "border"))
        .filter(|(_, b)| *b == 0.0)
        .map(|(v, _)| v)
        .collect();
    assert_eq!(inner.len(), 1);
    // Curvilinear triangle between three disks: sqrt(3)/4 D^2 - pi r^2 / 2 = 52.5 px^2, plus
    // the three 2-px necks up to the wall lines (about 3 x 2 x 1 px): 15 % tolerance.
    let exact = 3f64.sqrt() / 4.0 * 22.0 * 22.0 - std::f64::consts::PI * 100.0 / 2.0;
    assert!(
        (inner[0] - exact).abs() <= 0.15 * exact,
        "{} vs {exact}",
        inner[0]
    );
    // Phase volumes add up: every non-particle voxel belongs to exactly one pore.
    let np = img
        .labels
        .iter()
        .filter(|&&l| l == VOID || l == MATRIX)
        .count() as f64;
    assert_eq!(col(pores, "volume").iter().sum::<f64>(), np);
}

#[test]
fn partial_coordination_numbers_of_a_hand_built_packing() {
    // L1-L2 gap 0.05, L1-S1 gap 0.05, S1-S2 gap 0.05, S3 0.2 away from L2 (beyond h = 0.1).
    let parts = Particles {
        pos: vec![
            [0.0, 0.0, 0.0],
            [2.05, 0.0, 0.0],
            [0.0, 1.55, 0.0],
            [0.0, 2.6, 0.0],
            [2.05, -1.7, 0.0],
        ],
        radius: vec![1.0, 1.0, 0.5, 0.5, 0.5],
        class: vec![LARGE, LARGE, SMALL, SMALL, SMALL],
        dim: 2,
    };
    let domain = Domain::boxed([-5.0, -5.0, -1.0], [5.0, 5.0, 1.0], [false; 3]);
    let pairs = contacts(&parts, &domain, 0.1);
    assert_eq!(pairs.len(), 3);
    let (z, n) = partial_coordination(&parts, &pairs, &[true; 5]);
    assert_eq!(n, [2, 3]);
    assert!((z[0][0] - 1.0).abs() < 1e-15);
    assert!((z[0][1] - 0.5).abs() < 1e-15);
    assert!((z[1][0] - 1.0 / 3.0).abs() < 1e-15);
    assert!((z[1][1] - 2.0 / 3.0).abs() < 1e-15);
    // A horizon of 0.25 adds the L2-S3 contact.
    let pairs = contacts(&parts, &domain, 0.25);
    let (z, _) = partial_coordination(&parts, &pairs, &[true; 5]);
    assert!((z[0][1] - 1.0).abs() < 1e-15 && (z[1][0] - 2.0 / 3.0).abs() < 1e-15);
}
