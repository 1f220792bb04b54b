//! Linear-elastic checks against independent references: the lattice sum for a homogeneous
//! plate and the Voigt / Reuss mixture values for laminates.

mod common;
use common::*;
use grainpipe_core::units::Q;
use grainpipe_peridynamics::bond_based::{BondBasedParams, GripMode, InterfaceMaterial};

const E: f64 = 2e9;

fn plate_params() -> BondBasedParams {
    BondBasedParams {
        materials: materials(&[("matrix", matrix_material(E))]),
        grips: GripMode::Sliding,
        tolerance: 1e-6,
        ..Default::default()
    }
}

/// Homogeneous plate in uniaxial tension along y (sliding grips, free sides): in the bulk
/// (two horizons from every edge) sigma_yy equals the lattice's plane-stress modulus
/// E_lat = C11 - C12^2 / C11 (the stencil sum of the bond law, the continuum value of this
/// discretisation) times the local strain, within 1 %; sigma_xx vanishes.
#[test]
fn homogeneous_plate_bulk_stress_matches_the_lattice_modulus() {
    let (nx, ny) = (40, 48);
    let img = image(nx, ny, vec![3; nx * ny]);
    let p = plate_params();
    let r = run(&p, &img);
    let (c11, c12) = lattice_c(3.0);
    let e_lat = (c11 - c12 * c12 / c11) * E;
    let m = 6; // two horizons
    let (mut worst, mut sxx_max, mut syy_mean, mut cnt) = (0f64, 0f64, 0.0, 0.0);
    for y in m..ny - m {
        for x in m..nx - m {
            // Local strains by central differences of the displacement (units: dx).
            let eyy = (u2(&r, nx, x, y + 1, 1) - u2(&r, nx, x, y - 1, 1)) / (2.0 * DX);
            let exx = (u2(&r, nx, x + 1, y, 0) - u2(&r, nx, x - 1, y, 0)) / (2.0 * DX);
            let expect = (c11 * eyy + c12 * exx) * E;
            let syy = s2(&r, nx, x, y, 1);
            worst = worst.max((syy / expect - 1.0).abs());
            sxx_max = sxx_max.max(s2(&r, nx, x, y, 0).abs() / syy.abs());
            syy_mean += syy;
            cnt += 1.0;
        }
    }
    syy_mean /= cnt;
    assert!(
        worst < 0.01,
        "bulk sigma_yy off the lattice value by {worst:.4}"
    );
    assert!(
        sxx_max < 0.01,
        "bulk sigma_xx / sigma_yy up to {sxx_max:.4}"
    );
    // Lateral contraction of the bulk: nu_lat = C12 / C11 (1/3 in the continuum).
    let nu = {
        let (x0, x1, y) = (m, nx - 1 - m, ny / 2);
        let exx = (u2(&r, nx, x1, y, 0) - u2(&r, nx, x0, y, 0)) / ((x1 - x0) as f64 * DX);
        let eyy = (u2(&r, nx, nx / 2, ny - 1 - m, 1) - u2(&r, nx, nx / 2, m, 1))
            / ((ny - 1 - 2 * m) as f64 * DX);
        -exx / eyy
    };
    assert!(
        (nu - c12 / c11).abs() < 0.01,
        "nu = {nu}, lattice {}",
        c12 / c11
    );
    // Surface effect: the free side column carries less than the bulk.
    let edge: f64 = (m..ny - m).map(|y| s2(&r, nx, 0, y, 1)).sum::<f64>() / (ny - 2 * m) as f64;
    let e_cont = 9.0 / 8.0 * E * (1.0 - 1.0 / 9.0); // E / (1 - nu^2) (1 - nu^2) = E
    println!(
        "lattice E_lat = {:.4} E (continuum 1), nu_lat = {:.4}; bulk sigma_yy / (E_lat eps) \
         worst {:.2e}; edge column / bulk = {:.3}; effective modulus / E_lat = {:.4}; \
         continuum check {:.3}",
        e_lat / E,
        c12 / c11,
        worst,
        edge / syy_mean,
        col_f64(&r.report, "effective_modulus") / e_lat,
        e_cont / E
    );
    assert!(
        edge / syy_mean < 0.95,
        "no surface softening seen: {}",
        edge / syy_mean
    );
}

/// Two-phase laminate (E and E/4, layers 12 voxels thick, equal fractions, interface bonds
/// with the soft modulus as in Table I): tension along the layers gives the Voigt mean, across
/// them the Reuss mean of the lattice moduli, within the discretisation error stated here.
#[test]
fn laminate_voigt_and_reuss() {
    let (c11, c12) = lattice_c(3.0);
    let e_lat = c11 - c12 * c12 / c11;
    let (e1, e2) = (4.0 * E, E);
    let mats = materials(&[
        ("large", matrix_material(e1)),
        ("matrix", matrix_material(e2)),
    ]);
    let t = 12;
    let m = 6;
    // Parallel: stripes along y (layers normal to x), load along y.
    let (nx, ny) = (48, 40);
    let labels: Vec<u8> = (0..nx * ny)
        .map(|i| if (i % nx) / t % 2 == 0 { 1 } else { 3 })
        .collect();
    // A bond half in each layer is two springs in series: the harmonic mean makes the
    // interface perfectly bonded, as the mixture laws assume (Table I's E_i = E_m would
    // model a weaker interface).
    let p = BondBasedParams {
        materials: mats.clone(),
        interface: InterfaceMaterial {
            e: Q::new(2.0 * e1 * e2 / (e1 + e2)),
            toughness: Q::new(10.0),
        },
        grips: GripMode::Sliding,
        tolerance: 1e-6,
        ..Default::default()
    };
    let r = run(&p, &image(nx, ny, labels));
    // Mean stress over whole layers of the bulk rows / bulk strain.
    let (y0, y1) = (m, ny - 1 - m);
    // Columns two horizons from the free sides (the surface layer is softer, see the plate
    // test); the Voigt reference is the mean modulus of the same columns.
    let (xa, xb) = (m, nx - m);
    let mut s = 0.0;
    let mut eps = 0.0;
    let mut voigt = 0.0;
    for x in xa..xb {
        for y in y0..=y1 {
            s += s2(&r, nx, x, y, 1);
        }
        eps += (u2(&r, nx, x, y1, 1) - u2(&r, nx, x, y0, 1)) / ((y1 - y0) as f64 * DX);
        voigt += if x / t % 2 == 0 { e1 } else { e2 } * e_lat;
    }
    s /= ((xb - xa) * (y1 - y0 + 1)) as f64;
    eps /= (xb - xa) as f64;
    voigt /= (xb - xa) as f64;
    let par = s / eps / voigt - 1.0;
    // Perpendicular: layers normal to y, load along y; whole periods between the rows.
    let (nx, ny) = (40, 4 * t + 2 * m + 1);
    let labels: Vec<u8> = (0..nx * ny)
        .map(|i| {
            if ((i / nx) + t - m) / t % 2 == 0 {
                1
            } else {
                3
            }
        })
        .collect();
    let r = run(&p, &image(nx, ny, labels));
    let (y0, y1) = (m, m + 4 * t);
    let (xa, xb) = (m, nx - m);
    let mut s = 0.0;
    let mut eps = 0.0;
    for x in xa..xb {
        for y in y0..y1 {
            s += s2(&r, nx, x, y, 1);
        }
        eps += (u2(&r, nx, x, y1, 1) - u2(&r, nx, x, y0, 1)) / ((y1 - y0) as f64 * DX);
    }
    s /= ((xb - xa) * (y1 - y0)) as f64;
    eps /= (xb - xa) as f64;
    let reuss = 1.0 / (0.5 / e1 + 0.5 / e2) * e_lat;
    let perp = s / eps / reuss - 1.0;
    println!("laminate: parallel / Voigt - 1 = {par:.4}, perpendicular / Reuss - 1 = {perp:.4}");
    // Discretisation error: the free sides soften a 2h band (about -3 % over 48 columns,
    // see the plate test) in the parallel case; across the layers the interface bonds (soft
    // modulus) and the lateral mismatch of the layers act within h of each interface.
    assert!(par.abs() < 0.04, "parallel: {par:.4} off Voigt");
    assert!(perp.abs() < 0.04, "perpendicular: {perp:.4} off Reuss");
}
