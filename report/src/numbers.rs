//! The numbers a report shows that it computes itself (rather than reads from a stage's
//! output): tensor symmetry errors, engineering constants and the isotropic approximation of
//! a stiffness, size statistics, confidence intervals and kernel density estimates.
//!
//! Stiffness matrices are Voigt (order 11, 22, 33, 23, 13, 12, engineering shear), as
//! `elasticity.fft` gives them. Distances use the Frobenius norm of the Mandel matrix, i.e.
//! the norm of the fourth-order tensor, so they do not depend on the Voigt scaling of shear.

// Index loops mirror the matrix formulas (C_ij, S_ij) they implement.
#![allow(clippy::needless_range_loop)]

pub type M6 = [[f64; 6]; 6];

const SQRT2: f64 = std::f64::consts::SQRT_2;
const MANDEL_W: [f64; 6] = [1.0, 1.0, 1.0, SQRT2, SQRT2, SQRT2];

/// A 6x6 matrix from row-major values, `None` unless there are 36 of them.
pub fn m6(values: &[f64]) -> Option<M6> {
    if values.len() != 36 {
        return None;
    }
    let mut m = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            m[i][j] = values[6 * i + j];
        }
    }
    Some(m)
}

fn to_mandel(c: &M6) -> M6 {
    let mut m = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            m[i][j] = MANDEL_W[i] * MANDEL_W[j] * c[i][j];
        }
    }
    m
}

/// Relative asymmetry `|A - A^T| / |A|` (Frobenius) of an n x n row-major matrix; with
/// `mandel` the Voigt shear rows and columns are weighted first (6x6 stiffness). NaN when an
/// entry is not finite (e.g. permeability columns of directions not solved).
pub fn symmetry_error(values: &[f64], n: usize, mandel: bool) -> f64 {
    if values.len() != n * n || values.iter().any(|v| !v.is_finite()) {
        return f64::NAN;
    }
    let w = |i: usize| if mandel && n == 6 { MANDEL_W[i] } else { 1.0 };
    let (mut num, mut den) = (0.0, 0.0);
    for i in 0..n {
        for j in 0..n {
            let a = w(i) * w(j) * values[n * i + j];
            let at = w(i) * w(j) * values[n * j + i];
            num += (a - at) * (a - at);
            den += a * a;
        }
    }
    if den > 0.0 {
        num.sqrt() / den.sqrt()
    } else {
        0.0
    }
}

/// Inverse of a 6x6 matrix (nalgebra's LU with partial pivoting); `None` when it is
/// singular relative to its largest entry or has a non-finite entry.
pub fn invert(c: &M6) -> Option<M6> {
    if c.iter().flatten().any(|v| !v.is_finite()) {
        return None;
    }
    let m = nalgebra::SMatrix::<f64, 6, 6>::from_fn(|i, j| c[i][j]);
    let lu = m.lu();
    // The smallest pivot of U against the scale of C: singular (or nearly so) below 1e-14.
    let scale = c.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    let u = lu.u();
    if (0..6).any(|i| u[(i, i)].abs() <= 1e-14 * scale) {
        return None;
    }
    let inv = lu.try_inverse()?;
    Some(std::array::from_fn(|i| {
        std::array::from_fn(|j| inv[(i, j)])
    }))
}

/// Names of [`engineering`]'s values, as in `elasticity.fft`'s `constants` table.
pub const ENGINEERING_NAMES: [&str; 12] = [
    "E_x", "E_y", "E_z", "G_yz", "G_zx", "G_xy", "nu_xy", "nu_xz", "nu_yz", "nu_yx", "nu_zx",
    "nu_zy",
];

/// Engineering constants of the symmetrized stiffness from its compliance S = C^-1:
/// E_i = 1/S_ii, G_yz = 1/S_44, G_zx = 1/S_55, G_xy = 1/S_66 and nu_ij = -S_ij / S_ii (the
/// lateral contraction along j under uniaxial stress along i). `None` when C is singular.
pub fn engineering(c: &M6) -> Option<[f64; 12]> {
    let mut cs = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            cs[i][j] = 0.5 * (c[i][j] + c[j][i]);
        }
    }
    let s = invert(&cs)?;
    let nu = |i: usize, j: usize| -s[i][j] / s[i][i];
    Some([
        1.0 / s[0][0],
        1.0 / s[1][1],
        1.0 / s[2][2],
        1.0 / s[3][3],
        1.0 / s[4][4],
        1.0 / s[5][5],
        nu(0, 1),
        nu(0, 2),
        nu(1, 2),
        nu(1, 0),
        nu(2, 0),
        nu(2, 1),
    ])
}

/// The closest isotropic stiffness (orthogonal projection in the Mandel norm onto
/// 3k J + 2g K, J the spherical and K the deviatoric projector).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Isotropic {
    /// Bulk modulus k [Pa].
    pub bulk: f64,
    /// Shear modulus g [Pa].
    pub shear: f64,
    /// Young's modulus 9kg / (3k + g) [Pa].
    pub young: f64,
    /// Poisson's ratio (3k - 2g) / (2(3k + g)).
    pub poisson: f64,
    /// `|C - C_iso| / |C|` in the Mandel norm, C symmetrized.
    pub relative_error: f64,
}

pub fn isotropic(c: &M6) -> Isotropic {
    let mut m = to_mandel(c);
    for i in 0..6 {
        for j in 0..i {
            let s = 0.5 * (m[i][j] + m[j][i]);
            m[i][j] = s;
            m[j][i] = s;
        }
    }
    // J:C = sum of the normal 3x3 block / 3 (J:J = 1), K:C = trace - J:C (K:K = 5).
    let block: f64 = (0..3)
        .flat_map(|i| (0..3).map(move |j| (i, j)))
        .map(|(i, j)| m[i][j])
        .sum();
    let jc = block / 3.0;
    let trace: f64 = (0..6).map(|i| m[i][i]).sum();
    let kc = trace - jc;
    let three_k = jc;
    let two_g = kc / 5.0;
    let mut diff = 0.0;
    let mut norm = 0.0;
    for i in 0..6 {
        for j in 0..6 {
            let jij = if i < 3 && j < 3 { 1.0 / 3.0 } else { 0.0 };
            let kij = if i == j { 1.0 } else { 0.0 } - jij;
            let iso = three_k * jij + two_g * kij;
            diff += (m[i][j] - iso).powi(2);
            norm += m[i][j].powi(2);
        }
    }
    let (k, g) = (three_k / 3.0, two_g / 2.0);
    Isotropic {
        bulk: k,
        shear: g,
        young: 9.0 * k * g / (3.0 * k + g),
        poisson: (3.0 * k - 2.0 * g) / (2.0 * (3.0 * k + g)),
        relative_error: if norm > 0.0 {
            (diff / norm).sqrt()
        } else {
            f64::NAN
        },
    }
}

/// Isotropic Voigt stiffness of Young's modulus `e` and Poisson's ratio `nu`.
pub fn isotropic_stiffness(e: f64, nu: f64) -> M6 {
    let lambda = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
    let mu = e / (2.0 * (1.0 + nu));
    let mut c = [[0.0; 6]; 6];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = lambda + if i == j { 2.0 * mu } else { 0.0 };
        }
        c[i + 3][i + 3] = mu;
    }
    c
}

/// Mean, sample standard deviation and the half-width of the two-sided 90 % confidence
/// interval of the mean (Student t, n - 1 degrees of freedom). NaN parts when n < 2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Summary {
    pub n: usize,
    pub mean: f64,
    pub std: f64,
    pub ci90: f64,
    pub min: f64,
    pub max: f64,
}

pub fn summary(values: &[f64]) -> Summary {
    let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    let n = v.len();
    let mean = v.iter().sum::<f64>() / n as f64;
    let (std, ci90) = if n >= 2 {
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        let s = var.sqrt();
        (s, t95(n - 1) * s / (n as f64).sqrt())
    } else {
        (f64::NAN, f64::NAN)
    };
    Summary {
        n,
        mean,
        std,
        ci90,
        min: v.iter().copied().fold(f64::INFINITY, f64::min),
        max: v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    }
}

/// The 0.95 quantile of Student's t with `df` degrees of freedom (the two-sided 90 %
/// interval), from statrs; NaN for df = 0.
pub fn t95(df: usize) -> f64 {
    use statrs::distribution::{ContinuousCDF, StudentsT};
    if df == 0 {
        return f64::NAN;
    }
    StudentsT::new(0.0, 1.0, df as f64)
        .map(|t| t.inverse_cdf(0.95))
        .unwrap_or(f64::NAN)
}

pub use grainpipe_charts::violin::{kde, percentile};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn isotropic_round_trip() {
        let (e, nu) = (66.9e9, 0.25);
        let c = isotropic_stiffness(e, nu);
        let k = engineering(&c).unwrap();
        for v in &k[..3] {
            assert!((v / e - 1.0).abs() < 1e-12);
        }
        let g = e / (2.0 * (1.0 + nu));
        for v in &k[3..6] {
            assert!((v / g - 1.0).abs() < 1e-12);
        }
        for v in &k[6..] {
            assert!((v - nu).abs() < 1e-12);
        }
        let iso = isotropic(&c);
        assert!(iso.relative_error < 1e-14);
        assert!((iso.young / e - 1.0).abs() < 1e-12);
        assert!((iso.poisson - nu).abs() < 1e-12);
        assert!((iso.bulk / (e / (3.0 * (1.0 - 2.0 * nu))) - 1.0).abs() < 1e-12);
        assert_eq!(symmetry_error(&c.concat(), 6, true), 0.0);
    }

    #[test]
    fn cubic_stiffness_isotropic_error_by_hand() {
        // Cubic: C11 = 3, C12 = 1, C44 (Voigt) = 2 -> Mandel diagonal shear 4, so
        // J:C = (3*3 + 6*1)/3 = 5 = 3k, K:C = (9 + 12) - 5 = 16 = 5 (2g), 2g = 3.2. The
        // isotropic normal block is 5/3 + 3.2 (delta - 1/3): 3.8 on the diagonal, 0.6 off
        // it; the residual is -0.8 on three, 0.4 on six entries, and 4 - 3.2 = 0.8 on the
        // three shear ones (orthogonal to J and to the identity, as a projection's must be).
        let mut c = [[0.0; 6]; 6];
        for i in 0..3 {
            for j in 0..3 {
                c[i][j] = if i == j { 3.0 } else { 1.0 };
            }
            c[i + 3][i + 3] = 2.0;
        }
        let iso = isotropic(&c);
        let diff = (3.0 * 0.8f64.powi(2) + 6.0 * 0.4f64.powi(2) + 3.0 * 0.8f64.powi(2)).sqrt();
        let norm = (3.0 * 9.0 + 6.0 * 1.0 + 3.0 * 16.0f64).sqrt();
        assert!((iso.relative_error - diff / norm).abs() < 1e-12);
        assert!((iso.shear - 1.6).abs() < 1e-12);
        assert!((iso.bulk - 5.0 / 3.0).abs() < 1e-12);
    }

    /// The symmetrized apparent stiffness of pipelines/sandcore.yaml (out/sandcore, seed
    /// 42): our isotropic projection and constants agree with those `elasticity.fft` wrote
    /// (an independent implementation) in constants.csv.
    #[test]
    fn agrees_with_elasticity_fft_constants() {
        let c = m6(&[
            5555951264.871831,
            1109513288.987693,
            940472980.639416,
            46115047.560202695,
            75628875.37074722,
            -155863520.28107685,
            1109484382.8750916,
            5176412242.290199,
            852083328.5242864,
            64066804.14990066,
            -33819559.2571739,
            -200967137.71415856,
            940486979.7279739,
            852091157.217001,
            4803085448.504121,
            -17064574.692145914,
            -26994224.357562058,
            -13281732.386025203,
            46124160.682990745,
            64062942.66182218,
            -17057242.106171224,
            1929767167.5993087,
            -116946398.65442625,
            50978721.43883765,
            75625621.3132288,
            -33835233.06276886,
            -26978701.782438383,
            -116950534.83751738,
            2031735325.2673619,
            81873126.58089678,
            -155858806.99934205,
            -200956314.6474411,
            -13276047.154019432,
            50978166.67739614,
            81866866.44406438,
            2200593707.2650905,
        ])
        .unwrap();
        let iso = isotropic(&c);
        assert!((iso.relative_error - 0.0858130082020918).abs() < 1e-9);
        assert!((iso.young / 4818549041.433589 - 1.0).abs() < 1e-9);
        assert!((iso.poisson - 0.16129496463829568).abs() < 1e-9);
        let k = engineering(&c).unwrap();
        let apparent = [5183730894.844404, 4843845858.919685, 4553008925.649688];
        for (a, b) in k.iter().zip(apparent) {
            assert!((a / b - 1.0).abs() < 1e-9, "{a} vs {b}");
        }
        assert!((k[6] - 0.18535626166020783).abs() < 1e-9);
        assert!((k[9] - 0.1732028877811916).abs() < 1e-9);
        // Nearly symmetric: the largest asymmetry is 3e4 Pa on 5e9.
        let e = symmetry_error(&c.concat(), 6, true);
        assert!(e > 0.0 && e < 1e-5, "{e}");
    }

    #[test]
    fn inverse_of_a_stiffness_and_a_singular_matrix() {
        let c = isotropic_stiffness(10.0, 0.3);
        let s = invert(&c).unwrap();
        for i in 0..6 {
            for j in 0..6 {
                let p: f64 = (0..6).map(|k| c[i][k] * s[k][j]).sum();
                assert!((p - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        let mut z = c;
        z[5] = [0.0; 6];
        assert!(invert(&z).is_none());
        z = c;
        z[0][0] = f64::NAN;
        assert!(invert(&z).is_none());
    }

    #[test]
    fn symmetry_error_of_a_known_matrix() {
        // A = [[1, 2], [0, 1]]: A - A^T has two entries of 2, |A|^2 = 6.
        let e = symmetry_error(&[1.0, 2.0, 0.0, 1.0], 2, false);
        assert!((e - (8.0f64 / 6.0).sqrt()).abs() < 1e-15);
        assert!(symmetry_error(&[1.0, f64::NAN, 0.0, 1.0], 2, false).is_nan());
    }

    /// Student t quantiles checked by integrating the density numerically (Simpson) from 0
    /// to the quantile: the area must be 0.45.
    #[test]
    fn t_quantiles_integrate_to_0_95() {
        fn ln_gamma(x: f64) -> f64 {
            // Stirling series with shift: accurate to ~1e-12 for x >= 0.5 after shifting.
            let mut x = x;
            let mut acc = 0.0;
            while x < 10.0 {
                acc -= x.ln();
                x += 1.0;
            }
            acc + (x - 0.5) * x.ln() - x
                + 0.5 * (2.0 * std::f64::consts::PI).ln()
                + 1.0 / (12.0 * x)
                - 1.0 / (360.0 * x.powi(3))
                + 1.0 / (1260.0 * x.powi(5))
        }
        for df in [1usize, 2, 5, 10, 29, 30, 31, 60, 200] {
            let v = df as f64;
            let c = (ln_gamma((v + 1.0) / 2.0) - ln_gamma(v / 2.0)).exp()
                / (v * std::f64::consts::PI).sqrt();
            let pdf = |t: f64| c * (1.0 + t * t / v).powf(-(v + 1.0) / 2.0);
            let t = t95(df);
            let n = 2000;
            let h = t / n as f64;
            let mut s = pdf(0.0) + pdf(t);
            for i in 1..n {
                s += if i % 2 == 1 { 4.0 } else { 2.0 } * pdf(i as f64 * h);
            }
            let area = s * h / 3.0;
            assert!((area - 0.45).abs() < 2e-5, "df {df}: t {t} area {area}");
        }
    }

    /// The density and percentile re-exported from grainpipe-charts are tested there
    /// (`violin::tests::kde_integrates_to_one`, the same assertions).
    #[test]
    fn summary_of_five_values() {
        let s = summary(&[1.0, 2.0, 3.0, 4.0, 5.0]);
        assert_eq!(s.mean, 3.0);
        assert!((s.std - 2.5f64.sqrt()).abs() < 1e-15);
        assert!((s.ci90 - 2.131847 * 2.5f64.sqrt() / 5f64.sqrt()).abs() < 1e-6);
    }
}
