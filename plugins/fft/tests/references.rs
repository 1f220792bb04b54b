//! elasticity.fft against bounds and closed forms: Hashin-Shtrikman bounds on a random
//! two-phase image, the dilute spherical pore (Eshelby / Mori-Tanaka), rotation symmetry.
#![allow(clippy::needless_range_loop)]

mod common;
use common::*;
use grainpipe_fft::common::{Discretization, Solver};
use grainpipe_fft::kernel::constants::{project, Class};
use grainpipe_fft::kernel::Iso;

/// Bulk and shear modulus of the isotropic projection of a Voigt stiffness.
fn iso_kg(c: &M6) -> (f64, f64) {
    let (p, _) = project(c, Class::Isotropic);
    let lam = p[0][1];
    let mu = p[3][3];
    (lam + 2.0 * mu / 3.0, mu)
}

/// Hashin-Shtrikman (1963) bounds on (K, G) of an isotropic two-phase mix (phase 1 stiffer
/// in both moduli).
fn hs(k1: f64, g1: f64, f1: f64, k2: f64, g2: f64, f2: f64) -> [(f64, f64); 2] {
    let kb = |ka: f64, ga: f64, fa: f64, kb: f64, fb: f64| {
        ka + fb / (1.0 / (kb - ka) + 3.0 * fa / (3.0 * ka + 4.0 * ga))
    };
    let gb = |ka: f64, ga: f64, fa: f64, gb_: f64, fb: f64| {
        ga + fb
            / (1.0 / (gb_ - ga) + 6.0 * fa * (ka + 2.0 * ga) / (5.0 * ga * (3.0 * ka + 4.0 * ga)))
    };
    [
        (kb(k2, g2, f2, k1, f1), gb(k2, g2, f2, g1, f1)), // lower
        (kb(k1, g1, f1, k2, f2), gb(k1, g1, f1, g2, f2)), // upper
    ]
}

#[test]
fn random_two_phase_image_lies_within_hashin_shtrikman() {
    // 30 overlapping stiff spheres (E = 10, nu = 0.25) in a soft matrix (E = 1, nu = 0.35),
    // 32^3. The isotropic projection of the apparent stiffness must lie inside the HS bounds
    // (up to 2 % for the residual anisotropy of one finite sample).
    let img = spheres_image(32, &random_spheres(7, 30), 0.12, 2, 1);
    let f2 = img.fraction(2);
    let (m1, m2) = (Iso::from_e_nu(1.0, 0.35), Iso::from_e_nu(10.0, 0.25));
    let [lo, hi] = hs(m2.bulk(), m2.mu, f2, m1.bulk(), m1.mu, 1.0 - f2);
    assert!(lo.0 < hi.0 && lo.1 < hi.1);
    for d in [Discretization::Staggered, Discretization::Hex8] {
        let p = params(
            materials(&[(1, 1.0, 0.35), (2, 10.0, 0.25)]),
            d,
            Solver::Cg,
            1e-6,
        );
        let c = stiffness(&img, &p).unwrap().stiffness;
        let (k, g) = iso_kg(&c);
        assert!(
            k > 0.98 * lo.0 && k < 1.02 * hi.0,
            "{d:?} f {f2:.3}: K {k} not in [{}, {}]",
            lo.0,
            hi.0
        );
        assert!(
            g > 0.98 * lo.1 && g < 1.02 * hi.1,
            "{d:?} f {f2:.3}: G {g} not in [{}, {}]",
            lo.1,
            hi.1
        );
        // and strictly between the two phases' stiffness by a margin (not a trivial pass)
        assert!(k > 1.05 * m1.bulk() && g > 1.05 * m1.mu);
    }
}

#[test]
fn dilute_spherical_pore_matches_mori_tanaka() {
    // One spherical pore of porosity ~1.6 % per cell (32^3, radius 5 voxels): the loss of
    // bulk and shear stiffness is f (1 + 3K/4G) and f 15 (1 - nu) / (7 - 5 nu) to first
    // order in f (Eshelby; Mori-Tanaka K (1-f)/(1 + f 3K/4G), G (1-f)/(1 + f 6(K+2G)/(9K+8G))).
    // The staircase pore carries a few per cent error in the loss (measured: staggered 8 % in
    // bulk, 5 % in shear; hex8 3.5 %, 2 %): 12 % of it is allowed.
    let n = 32;
    let img = spheres_image(n, &[[0.5; 3]], 5.0 / n as f64, 0, 1);
    let f = img.fraction(0);
    let m = Iso::from_e_nu(1.0, 0.3);
    let (k0, g0) = (m.bulk(), m.mu);
    let k_mt = k0 * (1.0 - f) / (1.0 + f * 3.0 * k0 / (4.0 * g0));
    let g_mt = g0 * (1.0 - f) / (1.0 + f * 6.0 * (k0 + 2.0 * g0) / (9.0 * k0 + 8.0 * g0));
    for d in [Discretization::Staggered, Discretization::Hex8] {
        let p = params(materials(&[(1, 1.0, 0.3)]), d, Solver::Cg, 1e-7);
        let c = stiffness(&img, &p).unwrap().stiffness;
        // cubic symmetry: the bulk modulus is exact from C11 + 2 C12; the shear modulus is
        // the isotropic average.
        let k = (c[0][0] + 2.0 * c[0][1]) / 3.0;
        let (_, g) = iso_kg(&c);
        let (dk, dk_mt) = (1.0 - k / k0, 1.0 - k_mt / k0);
        let (dg, dg_mt) = (1.0 - g / g0, 1.0 - g_mt / g0);
        assert!(
            (dk / dk_mt - 1.0).abs() < 0.12,
            "{d:?} f {f:.4}: bulk loss {dk:.4} vs {dk_mt:.4}"
        );
        assert!(
            (dg / dg_mt - 1.0).abs() < 0.12,
            "{d:?} f {f:.4}: shear loss {dg:.4} vs {dg_mt:.4}"
        );
    }
}

/// Voigt strain transform of the rotation x' = y, y' = -x (signed permutation).
fn rotate_z(c: &M6) -> M6 {
    // eps'_k = s_k eps_{perm[k]}
    let perm = [1, 0, 2, 4, 3, 5];
    let sign = [1.0, 1.0, 1.0, -1.0, 1.0, -1.0];
    let mut out = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            out[i][j] = sign[i] * sign[j] * c[perm[i]][perm[j]];
        }
    }
    out
}

#[test]
fn a_rotated_image_gives_the_rotated_tensor_and_the_tensor_is_symmetric() {
    // A three-phase anisotropic image on a 12 x 10 x 8 grid, and the same image turned by 90
    // degrees about z (x' = y, y' = nx - 1 - x).
    let (nx, ny, nz) = (12, 10, 8);
    let mut s = 3u64;
    let labels: Vec<u8> = (0..nx * ny * nz)
        .map(|_| {
            let v = lcg(&mut s);
            if v < 0.3 {
                0
            } else if v < 0.8 {
                1
            } else {
                2
            }
        })
        .collect();
    let a = image([nx, ny, nz], 1e-6, |x, y, z| labels[x + nx * (y + ny * z)]);
    let b = image([ny, nx, nz], 1e-6, |xp, yp, z| {
        labels[(nx - 1 - yp) + nx * (xp + ny * z)]
    });
    let mats = materials(&[(1, 66.9e9, 0.25), (2, 43e9, 0.17)]);
    for d in [Discretization::Staggered, Discretization::Hex8] {
        let p = params(mats.clone(), d, Solver::Cg, 1e-9);
        let ca = stiffness(&a, &p).unwrap().stiffness;
        let cb = stiffness(&b, &p).unwrap().stiffness;
        let e = rel(&cb, &rotate_z(&ca));
        assert!(e < 1e-6, "{d:?}: rotated image differs by {e:.3e}");
        let mut t = ca;
        for i in 0..6 {
            for j in 0..6 {
                t[i][j] = ca[j][i];
            }
        }
        let asym = rel(&ca, &t);
        assert!(asym < 1e-6, "{d:?}: asymmetry {asym:.3e}");
    }
}

/// Hashin's neutral composite sphere: a core (K1, G1) of volume fraction c inside a shell
/// (K2, G2), embedded in a matrix of bulk modulus
///   K* = K2 + c (K1 - K2) / (1 + (1 - c) (K1 - K2) / (K2 + 4 G2 / 3)),
/// leaves a hydrostatic strain field in the matrix undisturbed (Hashin 1962), whatever the
/// matrix shear modulus. So the periodic cell's apparent bulk modulus, sum_ij C_ij / 9 over
/// the normal block, is exactly K*, for any arrangement — up to the staircase discretisation of
/// the two spheres, for which the realized voxel fractions enter c (measured at 40^3:
/// staggered +0.46 %, hex8 +1.25 %; 2 % allowed).
#[test]
fn hashin_coated_sphere_is_neutral_under_hydrostatic_load() {
    let n = 40;
    let (a, b) = (14.5, 19.0); // core and shell radius [voxels]
    let img = image([n; 3], 1.0 / n as f64, |x, y, z| {
        let r2: f64 = [x, y, z]
            .iter()
            .map(|&v| (v as f64 + 0.5 - n as f64 / 2.0).powi(2))
            .sum();
        if r2 < a * a {
            1
        } else if r2 < b * b {
            2
        } else {
            3
        }
    });
    let (n1, n2) = (img.fraction(1), img.fraction(2));
    let c = n1 / (n1 + n2);
    let (core, shell) = (Iso::from_e_nu(20.0, 0.2), Iso::from_e_nu(1.5, 0.3));
    let (k1, k2, g2) = (core.bulk(), shell.bulk(), shell.mu);
    let k_star = k2 + c * (k1 - k2) / (1.0 + (1.0 - c) * (k1 - k2) / (k2 + 4.0 * g2 / 3.0));
    // A matrix of bulk modulus K* and an unrelated shear modulus (nu = 0.3 at K*).
    let e_m = 3.0 * k_star * (1.0 - 2.0 * 0.3);
    // Reuss and Voigt bounds on the bulk modulus of the whole cell, to show the test can
    // tell a right answer from a merely plausible one.
    let f = [n1, n2, img.fraction(3)];
    let ks = [k1, k2, k_star];
    let voigt: f64 = (0..3).map(|i| f[i] * ks[i]).sum();
    let reuss = 1.0 / (0..3).map(|i| f[i] / ks[i]).sum::<f64>();
    for d in [Discretization::Staggered, Discretization::Hex8] {
        let mut p = params(
            materials(&[(1, 20.0, 0.2), (2, 1.5, 0.3), (3, e_m, 0.3)]),
            d,
            Solver::Cg,
            1e-7,
        );
        p.load_cases = vec![
            grainpipe_fft::elasticity::LoadCase::Xx,
            grainpipe_fft::elasticity::LoadCase::Yy,
            grainpipe_fft::elasticity::LoadCase::Zz,
        ];
        let cst = stiffness(&img, &p).unwrap().stiffness;
        let k: f64 = (0..3)
            .flat_map(|i| (0..3).map(move |j| (i, j)))
            .map(|(i, j)| cst[i][j])
            .sum::<f64>()
            / 9.0;
        eprintln!(
            "{d:?}: c {c:.4}, K {k:.5}, K* {k_star:.5} ({:+.3} %), Reuss {reuss:.4}, Voigt {voigt:.4}",
            100.0 * (k / k_star - 1.0)
        );
        assert!(
            (k / k_star - 1.0).abs() < 0.02,
            "{d:?}: K {k} vs Hashin K* {k_star}"
        );
        // and the error is small against the spread a wrong mixing rule would show
        assert!((k / k_star - 1.0).abs() < 0.05 * (voigt - reuss) / k_star);
    }
}
