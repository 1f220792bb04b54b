//! Numerical kernels, free of framework types: discretized cell problems, the reference
//! Green operators applied by FFT, the solvers, and the post-processing of stiffness tensors.

pub mod composite;
pub mod constants;
pub mod elastic;
pub mod scalar;
pub mod solver;

use num_complex::Complex;

/// Discretization of the cell problem (eq. 3.3).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scheme {
    /// Staggered grid (Schneider, Ospald & Kabel 2016): displacement components on the voxel
    /// faces, normal strains at voxel centres, shear strains on the voxel edges with the
    /// solid-share-weighted harmonic mean of the four adjacent shear moduli.
    Staggered,
    /// Trilinear hexahedra, nodal displacements, 2x2x2 Gauss points (FANS; Leuschner &
    /// Fritzen 2018).
    Hex8,
    /// Trilinear hexahedra with one-point integration (= Willot 2015's rotated scheme).
    Rotated,
    /// Fourier-spectral derivatives at voxel centres (Moulinec & Suquet 1994).
    Spectral,
}

/// Isotropic elastic constants (Lame), Pa. Zero for pores.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Iso {
    pub lambda: f64,
    pub mu: f64,
}

impl Iso {
    pub const ZERO: Iso = Iso {
        lambda: 0.0,
        mu: 0.0,
    };
    pub fn from_e_nu(e: f64, nu: f64) -> Iso {
        Iso {
            lambda: e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
            mu: e / (2.0 * (1.0 + nu)),
        }
    }
    pub fn from_k_g(k: f64, g: f64) -> Iso {
        Iso {
            lambda: k - 2.0 * g / 3.0,
            mu: g,
        }
    }
    pub fn bulk(&self) -> f64 {
        self.lambda + 2.0 * self.mu / 3.0
    }
    pub fn is_zero(&self) -> bool {
        self.lambda == 0.0 && self.mu == 0.0
    }
    /// Largest and smallest eigenvalues of the stiffness (3K and 2G).
    pub fn eig_range(&self) -> (f64, f64) {
        let (a, b) = (3.0 * self.bulk(), 2.0 * self.mu);
        (a.max(b), a.min(b))
    }
    /// The 6x6 Voigt matrix (engineering shear strains).
    pub fn voigt(&self) -> [[f64; 6]; 6] {
        let mut c = [[0.0; 6]; 6];
        for i in 0..3 {
            for j in 0..3 {
                c[i][j] = self.lambda;
            }
            c[i][i] += 2.0 * self.mu;
            c[i + 3][i + 3] = self.mu;
        }
        c
    }
}

pub type C64 = Complex<f64>;

/// `e^{i 2 pi m / n}` and the signed frequency of index `m`.
pub fn phase(m: usize, n: usize) -> (C64, f64) {
    let xi = 2.0 * std::f64::consts::PI * m as f64 / n as f64;
    let signed = if 2 * m > n {
        m as f64 - n as f64
    } else {
        m as f64
    };
    (C64::new(xi.cos(), xi.sin()), signed)
}

/// Per-axis multiplier tables of a scheme: `minus` (backward difference, normal strains of
/// the staggered grid), `plus` (forward difference), `spectral` (i k, Nyquist set to zero
/// because its derivative of a real field is not real), `e` (the shift `e^{i xi}`).
pub struct AxisTables {
    pub e: Vec<C64>,
    pub plus: Vec<C64>,
    pub minus: Vec<C64>,
    pub spectral: Vec<C64>,
}

impl AxisTables {
    /// `count` frequencies of an axis of `n` voxels of edge `h`.
    pub fn new(count: usize, n: usize, h: f64) -> AxisTables {
        let mut t = AxisTables {
            e: vec![],
            plus: vec![],
            minus: vec![],
            spectral: vec![],
        };
        for m in 0..count {
            let (e, s) = phase(m, n);
            t.e.push(e);
            t.plus.push((e - 1.0) / h);
            t.minus.push((C64::new(1.0, 0.0) - e.conj()) / h);
            let k = if n % 2 == 0 && 2 * m == n {
                0.0
            } else {
                2.0 * std::f64::consts::PI * s / (n as f64 * h)
            };
            t.spectral.push(C64::new(0.0, k));
        }
        t
    }
}

/// Gauss points of a nodal scheme: local coordinates in [0, 1]^3 and weights.
pub fn gauss_points(scheme: Scheme) -> Vec<([f64; 3], f64)> {
    match scheme {
        Scheme::Hex8 => {
            let a = 0.5 - 0.5 / 3f64.sqrt();
            let b = 0.5 + 0.5 / 3f64.sqrt();
            let mut v = vec![];
            for z in [a, b] {
                for y in [a, b] {
                    for x in [a, b] {
                        v.push(([x, y, z], 0.125));
                    }
                }
            }
            v
        }
        _ => vec![([0.5; 3], 1.0)],
    }
}

/// Gradient multipliers (x, y, z) of the trilinear interpolation at local point `p` of the
/// element whose lower corner node is the voxel index: eq. (3.3)'s grad u at that point.
pub fn nodal_gradient(ex: C64, ey: C64, ez: C64, h: [f64; 3], p: [f64; 3]) -> [C64; 3] {
    let lerp = |e: C64, t: f64| C64::new(1.0 - t, 0.0) + e * t;
    [
        (ex - 1.0) / h[0] * lerp(ey, p[1]) * lerp(ez, p[2]),
        (ey - 1.0) / h[1] * lerp(ex, p[0]) * lerp(ez, p[2]),
        (ez - 1.0) / h[2] * lerp(ex, p[0]) * lerp(ey, p[1]),
    ]
}

/// Inverse of a Hermitian positive semi-definite 3x3 matrix, packed as
/// `[a00, a11, a22, re a01, im a01, re a02, im a02, re a12, im a12]`; zero when the matrix is
/// (numerically) zero, which happens only where the discrete gradient vanishes (the mean and
/// the hourglass modes of the rotated scheme).
pub fn hermitian_inverse(a: [[C64; 3]; 3], zero_below: f64) -> [f64; 9] {
    let tr = a[0][0].re + a[1][1].re + a[2][2].re;
    if tr <= zero_below || tr.is_nan() {
        return [0.0; 9];
    }
    let m = |i: usize, j: usize| a[i][j];
    let cof = |i: usize, j: usize| {
        let r: Vec<usize> = (0..3).filter(|&k| k != i).collect();
        let c: Vec<usize> = (0..3).filter(|&k| k != j).collect();
        let d = m(r[0], c[0]) * m(r[1], c[1]) - m(r[0], c[1]) * m(r[1], c[0]);
        if (i + j) % 2 == 0 {
            d
        } else {
            -d
        }
    };
    let det = m(0, 0) * cof(0, 0) + m(0, 1) * cof(0, 1) + m(0, 2) * cof(0, 2);
    if det.re.abs() <= 1e-13 * tr * tr * tr || det.re.is_nan() {
        return [0.0; 9];
    }
    // inv[i][j] = cof(j, i) / det.
    let inv = |i: usize, j: usize| cof(j, i) / det;
    let (i01, i02, i12) = (inv(0, 1), inv(0, 2), inv(1, 2));
    [
        inv(0, 0).re,
        inv(1, 1).re,
        inv(2, 2).re,
        i01.re,
        i01.im,
        i02.re,
        i02.im,
        i12.re,
        i12.im,
    ]
}

/// Bilinear weights, at one Gauss point, of the 4 element edges parallel to each axis (edge
/// `j + 2 k` over the two other axes in order), from the point's linear weights
/// `wt[axis] = [1 - p, p]`: a nodal difference along an axis is interpolated to the point
/// with them.
pub fn edge_weights<T: crate::real::Real>(wt: &[[T; 2]; 3]) -> [[T; 4]; 3] {
    let we = |a: usize, b: usize| {
        [
            wt[a][0] * wt[b][0],
            wt[a][1] * wt[b][0],
            wt[a][0] * wt[b][1],
            wt[a][1] * wt[b][1],
        ]
    };
    [we(1, 2), we(0, 2), we(0, 1)]
}
