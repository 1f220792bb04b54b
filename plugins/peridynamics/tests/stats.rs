//! `analysis.stress_stats` against distributions with known moments and tails, and the two
//! stages chained through the pipeline engine.

mod common;
use common::*;
use grainpipe_core::{ComponentConvention, Field, FieldData, PhaseImage};
use grainpipe_peridynamics::stress_stats::{analyse, StressStatsParams};

/// A 2-D stress field (xx, yy, xy) with sigma_yy from `f(label, k)`.
fn field_for(img: &PhaseImage, mut f: impl FnMut(u8) -> f64) -> Field {
    let mut data = Vec::with_capacity(img.labels.len() * 3);
    for &l in &img.labels {
        let s = if l == 0 { 0.0 } else { f(l) };
        data.extend_from_slice(&[0.1 * s as f32, s as f32, 0.0]);
    }
    Field::new(
        img.grid.clone(),
        "stress",
        "Pa",
        ComponentConvention::Voigt,
        FieldData::F32(data),
    )
    .unwrap()
}

#[test]
fn moments_and_tail_exponent_of_known_distributions() {
    let (nx, ny) = (400, 500);
    // Left half "large": exponential with mean 1 MPa (pdf of x = s/mean is exp(-x): s = 1,
    // variance 1, excess kurtosis 6). Right part "matrix": uniform on [0, 2] MPa (variance of
    // x 1/3, excess kurtosis -1.2). A void strip is skipped.
    let labels: Vec<u8> = (0..nx * ny)
        .map(|i| match i % nx {
            x if x < 200 => 1,
            x if x < 390 => 3,
            _ => 0,
        })
        .collect();
    let img = image(nx, ny, labels);
    let mut rng = Rng(3);
    let field = field_for(&img, |l| {
        let u = rng.next();
        if l == 1 {
            -(1.0 - u).ln() * 1e6
        } else {
            2.0 * u * 1e6
        }
    });
    let p = StressStatsParams {
        range: [0.0, 8.0],
        bins: 80,
        tail_from: 1.0,
        ..Default::default()
    };
    let (stats, centres) = analyse(&p, &field, &img).unwrap();
    assert_eq!(stats.len(), 2);
    assert_eq!(centres.len(), 80);
    let large = &stats[0];
    let matrix = &stats[1];
    assert_eq!(large.name, "large");
    assert_eq!(large.nodes, 200 * ny);
    assert!((large.mean / 1e6 - 1.0).abs() < 0.01, "{}", large.mean);
    assert!((large.variance - 1.0).abs() < 0.05, "{}", large.variance);
    // The sample kurtosis of an exponential converges slowly (its standard error is about
    // sqrt(mu8 / n) = 0.6 at n = 1e5): a loose check here, the uniform below is tight.
    assert!(
        (large.excess_kurtosis - 6.0).abs() < 1.5,
        "{}",
        large.excess_kurtosis
    );
    let s = large.tail_exponent.unwrap();
    assert!((s - 1.0).abs() < 0.03, "tail exponent {s}");
    assert!(large.tail_r2 > 0.99);
    assert!(
        (matrix.variance - 1.0 / 3.0).abs() < 0.01,
        "{}",
        matrix.variance
    );
    assert!(
        (matrix.excess_kurtosis + 1.2).abs() < 0.03,
        "{}",
        matrix.excess_kurtosis
    );
    // The PDF integrates to the share inside the range.
    let w = centres[1] - centres[0];
    let mass: f64 = large.pdf.iter().sum::<f64>() * w;
    assert!((mass - (1.0 - large.outside as f64 / large.nodes as f64)).abs() < 1e-9);
    // Uniform on [0, 2]: no qualifying tail beyond x = 2 -> fit over [1, 2] is flat-ish.
    let p = StressStatsParams {
        tail_from: 2.5,
        ..p
    };
    let (stats, _) = analyse(&p, &field, &img).unwrap();
    assert!(stats[1].tail_exponent.is_none());
}

#[test]
fn missing_component_and_grid_mismatch_are_refused() {
    let img = image(10, 10, vec![3; 100]);
    let f = field_for(&img, |_| 1.0);
    let p = StressStatsParams {
        component: grainpipe_peridynamics::stress_stats::Component::Zz,
        ..Default::default()
    };
    let e = analyse(&p, &f, &img).unwrap_err();
    assert!(e.to_string().contains("component"), "{e}");
    let other = image(10, 11, vec![3; 110]);
    let e = analyse(&StressStatsParams::default(), &f, &other).unwrap_err();
    assert!(e.to_string().contains("grid"), "{e}");
}

/// Issue 34, item 4: `margin: k` leaves out the k voxel layers along the image's in-plane
/// faces. A plate whose outer 3 layers carry 0.78 MPa and whose interior carries 1 MPa: with
/// margin 3 exactly the (nx - 6)(ny - 6) interior nodes remain, mean 1 MPa and variance 0;
/// with margin 0 the side layers enter the mean by their share.
#[test]
fn margin_leaves_out_the_boundary_layers() {
    let (nx, ny) = (30, 40);
    let img = image(nx, ny, vec![1; nx * ny]);
    let mut k = 0usize;
    let field = field_for(&img, |_| {
        let (x, y) = (k % nx, k / nx);
        k += 1;
        if x < 3 || x >= nx - 3 || y < 3 || y >= ny - 3 {
            0.78e6
        } else {
            1e6
        }
    });
    let p = StressStatsParams {
        margin: 3,
        ..Default::default()
    };
    let (stats, _) = analyse(&p, &field, &img).unwrap();
    assert_eq!(stats[0].nodes, (nx - 6) * (ny - 6));
    assert!(
        (stats[0].mean - 1e6).abs() < 1e-6 * 1e6,
        "{}",
        stats[0].mean
    );
    assert!(stats[0].variance.abs() < 1e-12);
    let (all, _) = analyse(&StressStatsParams::default(), &field, &img).unwrap();
    let interior = ((nx - 6) * (ny - 6)) as f64;
    let expect = (interior * 1e6 + ((nx * ny) as f64 - interior) * 0.78e6) / (nx * ny) as f64;
    assert_eq!(all[0].nodes, nx * ny);
    assert!((all[0].mean - expect).abs() < 1e-6 * expect);
}
