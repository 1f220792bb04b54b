//! Post-processing of a 6x6 Voigt stiffness (engineering shear strains): orthotropic
//! engineering constants (Cowin 1985) and the closest isotropic, transversely isotropic (z)
//! and orthotropic stiffnesses with their relative distances, as in Table 7 of the paper.
//! Distances and projections use the Frobenius norm of the Mandel matrix, i.e. the norm of
//! the fourth-order tensor, so that the result does not depend on the Voigt scaling.

pub type M6 = [[f64; 6]; 6];

const W: [f64; 6] = [
    1.0,
    1.0,
    1.0,
    std::f64::consts::SQRT_2,
    std::f64::consts::SQRT_2,
    std::f64::consts::SQRT_2,
];

pub fn to_mandel(c: &M6) -> M6 {
    let mut m = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            m[i][j] = W[i] * W[j] * c[i][j];
        }
    }
    m
}

fn frob(a: &M6) -> f64 {
    a.iter().flatten().map(|x| x * x).sum::<f64>().sqrt()
}

fn inner(a: &M6, b: &M6) -> f64 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| x * y)
        .sum()
}

pub fn symmetrize(c: &M6) -> M6 {
    let mut s = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            s[i][j] = 0.5 * (c[i][j] + c[j][i]);
        }
    }
    s
}

/// Whether the symmetric part of `c` is positive definite: the Cholesky factorisation of its
/// Mandel form (a stiffness must store positive energy for every strain).
pub fn positive_definite(c: &M6) -> bool {
    let m = to_mandel(&symmetrize(c));
    nalgebra::Matrix6::from_fn(|i, j| m[i][j])
        .cholesky()
        .is_some()
}

/// Relative asymmetry `|C - C^T| / |C|` (Mandel norm).
pub fn asymmetry(c: &M6) -> f64 {
    let m = to_mandel(c);
    let mut d = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            d[i][j] = m[i][j] - m[j][i];
        }
    }
    frob(&d) / frob(&m).max(f64::MIN_POSITIVE)
}

/// Solves the small dense system `a x = b` by Gaussian elimination with partial pivoting;
/// `None` when a pivot is below `1e-12` of the largest entry.
pub fn solve_dense(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Option<Vec<f64>> {
    let n = b.len();
    let big = a.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
    for k in 0..n {
        let p = (k..n).max_by(|&i, &j| a[i][k].abs().total_cmp(&a[j][k].abs()))?;
        if a[p][k].abs() <= 1e-12 * big || a[p][k].is_nan() {
            return None;
        }
        a.swap(k, p);
        b.swap(k, p);
        for i in k + 1..n {
            let f = a[i][k] / a[k][k];
            for j in k..n {
                a[i][j] -= f * a[k][j];
            }
            b[i] -= f * b[k];
        }
    }
    let mut x = vec![0.0; n];
    for k in (0..n).rev() {
        let s: f64 = (k + 1..n).map(|j| a[k][j] * x[j]).sum();
        x[k] = (b[k] - s) / a[k][k];
    }
    Some(x)
}

/// Inverse of a 6x6 matrix, `None` when singular.
pub fn invert(c: &M6) -> Option<M6> {
    let mut s = [[0.0; 6]; 6];
    for j in 0..6 {
        let a: Vec<Vec<f64>> = c.iter().map(|r| r.to_vec()).collect();
        let mut b = vec![0.0; 6];
        b[j] = 1.0;
        let x = solve_dense(a, b)?;
        for i in 0..6 {
            s[i][j] = x[i];
        }
    }
    Some(s)
}

/// The symmetry classes of Table 7.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Class {
    Isotropic,
    TransverselyIsotropicZ,
    Orthotropic,
}

/// Voigt basis matrices of a class (engineering shear strains).
fn basis(class: Class) -> Vec<M6> {
    let unit = |entries: &[(usize, usize, f64)]| {
        let mut m = [[0.0; 6]; 6];
        for &(i, j, v) in entries {
            m[i][j] += v;
            if i != j {
                m[j][i] += v;
            }
        }
        m
    };
    match class {
        Class::Isotropic => vec![
            // lambda: the 3x3 block of ones
            unit(&[
                (0, 0, 1.0),
                (1, 1, 1.0),
                (2, 2, 1.0),
                (0, 1, 1.0),
                (0, 2, 1.0),
                (1, 2, 1.0),
            ]),
            // mu: 2 on the normal diagonal, 1 on the shear diagonal
            unit(&[
                (0, 0, 2.0),
                (1, 1, 2.0),
                (2, 2, 2.0),
                (3, 3, 1.0),
                (4, 4, 1.0),
                (5, 5, 1.0),
            ]),
        ],
        Class::TransverselyIsotropicZ => vec![
            // C11 = C22, C66 = (C11 - C12) / 2
            unit(&[(0, 0, 1.0), (1, 1, 1.0), (5, 5, 0.5)]),
            unit(&[(0, 1, 1.0), (5, 5, -0.5)]),
            unit(&[(0, 2, 1.0), (1, 2, 1.0)]),
            unit(&[(2, 2, 1.0)]),
            unit(&[(3, 3, 1.0), (4, 4, 1.0)]),
        ],
        Class::Orthotropic => {
            let mut v = vec![];
            for (i, j) in [
                (0, 0),
                (1, 1),
                (2, 2),
                (0, 1),
                (0, 2),
                (1, 2),
                (3, 3),
                (4, 4),
                (5, 5),
            ] {
                v.push(unit(&[(i, j, 1.0)]));
            }
            v
        }
    }
}

/// The closest stiffness of `class` to `c` (orthogonal projection in the tensor norm) and
/// the relative distance `|C - P C| / |C|`.
pub fn project(c: &M6, class: Class) -> (M6, f64) {
    let cm = to_mandel(c);
    let b: Vec<M6> = basis(class);
    let bm: Vec<M6> = b.iter().map(to_mandel).collect();
    let k = b.len();
    let gram: Vec<Vec<f64>> = (0..k)
        .map(|i| (0..k).map(|j| inner(&bm[i], &bm[j])).collect())
        .collect();
    let rhs: Vec<f64> = (0..k).map(|i| inner(&bm[i], &cm)).collect();
    let x = solve_dense(gram, rhs).expect("the basis of a symmetry class is independent");
    let mut p = [[0.0; 6]; 6];
    for (xi, bi) in x.iter().zip(&b) {
        for i in 0..6 {
            for j in 0..6 {
                p[i][j] += xi * bi[i][j];
            }
        }
    }
    let pm = to_mandel(&p);
    let mut d = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            d[i][j] = cm[i][j] - pm[i][j];
        }
    }
    (p, frob(&d) / frob(&cm).max(f64::MIN_POSITIVE))
}

/// Orthotropic engineering constants of a stiffness (Cowin 1985):
/// `[E_x, E_y, E_z, G_yz, G_zx, G_xy, nu_xy, nu_xz, nu_yz, nu_yx, nu_zx, nu_zy]` with
/// `nu_ij = -S_ji / S_ii` (contraction along j under uniaxial stress along i). NaN when the
/// stiffness is singular (e.g. a layer of void across the cell).
pub fn engineering(c: &M6) -> [f64; 12] {
    let Some(s) = invert(&symmetrize(c)) else {
        return [f64::NAN; 12];
    };
    let nu = |i: usize, j: usize| -s[j][i] / s[i][i];
    [
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
    ]
}

/// The engineering constants of the closest orthotropic stiffness to `c` (as
/// `engineering(&project(c, Class::Orthotropic).0)`) from the columns that were computed
/// (`ran[k]`: the load case of Voigt column k ran). The orthotropic projection keeps the normal
/// 3x3 block and the shear diagonal and drops the rest, so E_x, E_y, E_z and the Poisson
/// ratios need only the three normal load cases (the inverse of the normal block), and each
/// shear modulus only its own shear case; what was not computed is NaN, as is everything
/// without the three normal cases or with a singular normal block.
pub fn orthotropic_from_columns(c: &M6, ran: [bool; 6]) -> [f64; 12] {
    if !(ran[0] && ran[1] && ran[2]) {
        return [f64::NAN; 12];
    }
    // The projection itself: the normal block and the shear diagonal, with 1 standing in for
    // a shear case that did not run (so the block stays invertible; its modulus is NaN).
    let mut p = [[0.0; 6]; 6];
    for i in 0..3 {
        p[i][..3].copy_from_slice(&c[i][..3]);
    }
    for k in 3..6 {
        p[k][k] = if ran[k] { c[k][k] } else { 1.0 };
    }
    let mut e = engineering(&p);
    for k in 3..6 {
        if !ran[k] {
            e[k] = f64::NAN;
        }
    }
    e
}

pub const ENGINEERING_NAMES: [&str; 12] = [
    "E_x", "E_y", "E_z", "G_yz", "G_zx", "G_xy", "nu_xy", "nu_xz", "nu_yz", "nu_yx", "nu_zx",
    "nu_zy",
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernel::Iso;

    #[test]
    fn isotropic_round_trip() {
        let c = Iso::from_e_nu(70e9, 0.3).voigt();
        let e = engineering(&c);
        assert!((e[0] / 70e9 - 1.0).abs() < 1e-12);
        assert!((e[3] / (70e9 / 2.6) - 1.0).abs() < 1e-12);
        assert!((e[6] - 0.3).abs() < 1e-12);
        for class in [
            Class::Isotropic,
            Class::TransverselyIsotropicZ,
            Class::Orthotropic,
        ] {
            let (_, d) = project(&c, class);
            assert!(d < 1e-14);
        }
    }

    /// The constants from the computed columns equal those of the projection (a Gram solve
    /// over the class basis) on a fully anisotropic stiffness, and need only the normal
    /// columns for E and nu.
    #[test]
    fn orthotropic_constants_from_the_normal_columns_equal_the_projection() {
        // A positive definite, fully anisotropic stiffness: D + 0.2 * (R + R^T), R fixed.
        let mut c = [[0.0; 6]; 6];
        for i in 0..6 {
            for j in 0..6 {
                let r = ((i * 7 + j * 3) % 11) as f64 / 11.0 - 0.5;
                let rt = ((j * 7 + i * 3) % 11) as f64 / 11.0 - 0.5;
                c[i][j] = 1e9 * (0.2 * (r + rt) + if i == j { 5.0 + i as f64 } else { 0.0 });
            }
        }
        for i in 0..3 {
            for j in 0..3 {
                if i != j {
                    c[i][j] += 1.5e9;
                }
            }
        }
        let want = engineering(&project(&c, Class::Orthotropic).0);
        let full = orthotropic_from_columns(&c, [true; 6]);
        for k in 0..12 {
            assert!(
                (full[k] / want[k] - 1.0).abs() < 1e-12,
                "{k}: {} {}",
                full[k],
                want[k]
            );
        }
        // Only the normal cases: columns 3-5 of the apparent stiffness are zero then.
        let mut normal = c;
        for row in normal.iter_mut() {
            for v in row.iter_mut().skip(3) {
                *v = 0.0;
            }
        }
        let got = orthotropic_from_columns(&normal, [true, true, true, false, false, false]);
        for k in (0..3).chain(6..12) {
            assert!(
                (got[k] / want[k] - 1.0).abs() < 1e-12,
                "{k}: {} {}",
                got[k],
                want[k]
            );
        }
        assert!(got[3..6].iter().all(|g| g.is_nan()));
        assert!(orthotropic_from_columns(&c, [true, true, false, true, true, true])[0].is_nan());
    }
}
