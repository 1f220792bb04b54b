//! Star-shaped grains: radius functions on the sphere (spherical-harmonic expansions, read
//! from VCCTL coefficient files or drawn as Gaussian random fields), tabulated on a
//! (theta, phi) grid, mapped by a linear transform (scale, stretch, rotation) and voxelized.

use nalgebra::{Matrix3, Vector3};
use std::f64::consts::PI;
use std::path::Path;

/// A voxelization: dims, lower grid corner [same unit as the shape], mask (x fastest).
pub type Voxelized = ([usize; 3], [f64; 3], Vec<bool>);

/// Why a shape or a mesh could not be voxelized.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum VoxelizeError {
    #[error("the shape transform is singular")]
    SingularTransform,
    #[error("the {what} needs {} x {} x {} voxels: use a larger voxel_size", dims[0], dims[1], dims[2])]
    TooManyVoxels {
        /// "grain" or "mesh".
        what: &'static str,
        dims: [usize; 3],
    },
    #[error("{0} voxel rows cross the surface an odd number of times: the mesh is not closed")]
    OpenSurface(usize),
}

/// Orthonormal associated Legendre functions without the Condon-Shortley phase,
/// `Q_n^m(x) = sqrt((2n+1)/(4 pi) (n-m)!/(n+m)!) P_n^m(x)`, for 0 <= m <= n <= nmax, stored
/// at `n * (n + 1) / 2 + m`. Standard three-term recursion in n (stable for n ~ 100).
pub fn legendre_table(nmax: usize, x: f64, out: &mut Vec<f64>) {
    let s = (1.0 - x * x).max(0.0).sqrt();
    out.clear();
    out.resize((nmax + 1) * (nmax + 2) / 2, 0.0);
    let idx = |n: usize, m: usize| n * (n + 1) / 2 + m;
    let mut qmm = (1.0 / (4.0 * PI)).sqrt();
    for m in 0..=nmax {
        if m > 0 {
            qmm *= ((2 * m + 1) as f64 / (2 * m) as f64).sqrt() * s;
        }
        out[idx(m, m)] = qmm;
        if m < nmax {
            out[idx(m + 1, m)] = ((2 * m + 3) as f64).sqrt() * x * qmm;
        }
        for n in m + 2..=nmax {
            let (nf, mf) = (n as f64, m as f64);
            let a = ((4.0 * nf * nf - 1.0) / (nf * nf - mf * mf)).sqrt();
            let b = (((nf - 1.0).powi(2) - mf * mf) / (4.0 * (nf - 1.0).powi(2) - 1.0)).sqrt();
            out[idx(n, m)] = a * (x * out[idx(n - 1, m)] - b * out[idx(n - 2, m)]);
        }
    }
}

/// Largest violation of the reality condition a file may show, relative to its largest
/// coefficient: VCCTL files print 10 decimals of values up to ~2, so rounding leaves
/// ~1e-10; anything above 1e-6 is a different function, not rounding.
pub const REALITY_TOLERANCE: f64 = 1e-6;

/// A real radius function as complex SH coefficients `a_nm`, m >= 0 only (the negative
/// orders follow from `a_{n,-m} = (-1)^m conj(a_nm)`), with the complex orthonormal SH
/// `Y_n^m = (-1)^m Q_n^m(cos theta) e^{i m phi}` (Condon-Shortley phase, as in VCCTL's
/// genaggpack and scipy's `sph_harm_y`; see data/sand-grains/README.md).
#[derive(Clone, Debug)]
pub struct Harmonics {
    pub nmax: usize,
    /// (re, im) at `n * (n + 1) / 2 + m`.
    pub coef: Vec<(f64, f64)>,
}

impl Harmonics {
    /// Reads a VCCTL `-anm-` file: lines `n m Re(a_nm) Im(a_nm)`.
    pub fn read(path: &Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("{}: cannot read: {e}", path.display()))?;
        let mut rows = Vec::new();
        let mut nmax = 0usize;
        for (ln, line) in text.lines().enumerate() {
            let t: Vec<&str> = line.split_whitespace().collect();
            if t.is_empty() {
                continue;
            }
            if t.len() != 4 {
                return Err(format!(
                    "{}:{}: expected `n m Re Im`, got {} fields",
                    path.display(),
                    ln + 1,
                    t.len()
                ));
            }
            let bad = |what: &str| format!("{}:{}: bad {what}", path.display(), ln + 1);
            let n: i64 = t[0].parse().map_err(|_| bad("n"))?;
            let m: i64 = t[1].parse().map_err(|_| bad("m"))?;
            let re: f64 = t[2].parse().map_err(|_| bad("Re"))?;
            let im: f64 = t[3].parse().map_err(|_| bad("Im"))?;
            if n < 0 || m.abs() > n || !re.is_finite() || !im.is_finite() {
                return Err(bad("coefficient (needs |m| <= n, finite values)"));
            }
            nmax = nmax.max(n as usize);
            rows.push((n as usize, m, re, im, ln + 1));
        }
        if rows.is_empty() {
            return Err(format!("{}: no coefficients", path.display()));
        }
        let mut coef = vec![(0.0, 0.0); (nmax + 1) * (nmax + 2) / 2];
        let mut seen = vec![false; coef.len()];
        for &(n, m, re, im, _) in &rows {
            if m >= 0 {
                let k = n * (n + 1) / 2 + m as usize;
                coef[k] = (re, im);
                seen[k] = true;
            }
        }
        // A real radius needs a_{n,-m} = (-1)^m conj(a_nm) (so a_n0 is real); only m >= 0
        // is used, so a file breaking it would silently describe another grain.
        let largest = rows.iter().map(|r| r.2.hypot(r.3)).fold(0.0, f64::max);
        let tol = REALITY_TOLERANCE * largest;
        for &(n, m, re, im, line) in &rows {
            let k = n * (n + 1) / 2 + m.unsigned_abs() as usize;
            let (ar, ai) = coef[k];
            let sign = if m % 2 == 0 { 1.0 } else { -1.0 };
            let (er, ei) = if m < 0 {
                (sign * ar, -sign * ai)
            } else if m == 0 {
                (re, 0.0)
            } else {
                continue;
            };
            let dev = (re - er).hypot(im - ei);
            if dev > tol {
                let what = if m == 0 {
                    format!("a_{n},0 must be real")
                } else {
                    format!("a_{n},{m} must equal (-1)^{} conj(a_{n},{})", -m, -m)
                };
                return Err(format!(
                    "{}:{line}: coefficient (n, m) = ({n}, {m}) breaks the reality condition \
                     a_(n,-m) = (-1)^m conj(a_(n,m)) of a real radius ({what}): the violation \
                     is {dev:.3e}, the tolerance {tol:.3e} ({REALITY_TOLERANCE:e} of the \
                     largest coefficient {largest:.4e}); fix the file or drop its m < 0 rows",
                    path.display()
                ));
            }
        }
        if let Some(k) = seen.iter().position(|s| !s) {
            let n = ((((8 * k + 1) as f64).sqrt() - 1.0) / 2.0) as usize;
            return Err(format!(
                "{}: coefficient n = {n}, m = {} missing (need every 0 <= m <= n <= {nmax})",
                path.display(),
                k - n * (n + 1) / 2
            ));
        }
        Ok(Harmonics { nmax, coef })
    }

    /// Tabulates `r(theta_i, phi_j)` on `theta_i = i pi / nt` (i = 0..=nt),
    /// `phi_j = 2 pi j / np`.
    pub fn tabulate(&self, nt: usize, np: usize) -> RadiusTable {
        let mut r = vec![0.0; (nt + 1) * np];
        let mut q = Vec::new();
        let mut am = vec![(0.0, 0.0); self.nmax + 1];
        for i in 0..=nt {
            let th = i as f64 * PI / nt as f64;
            legendre_table(self.nmax, th.cos(), &mut q);
            // A_m(theta) = sum_n a_nm Q_n^m; r = sum_m w_m (-1)^m Re(A_m e^{i m phi}),
            // w_0 = 1, w_m = 2 (the -m terms are the conjugates).
            for (m, a) in am.iter_mut().enumerate() {
                let mut s = (0.0, 0.0);
                for n in m..=self.nmax {
                    let k = n * (n + 1) / 2 + m;
                    s.0 += self.coef[k].0 * q[k];
                    s.1 += self.coef[k].1 * q[k];
                }
                let w = if m == 0 { 1.0 } else { 2.0 } * if m % 2 == 1 { -1.0 } else { 1.0 };
                *a = (w * s.0, w * s.1);
            }
            for j in 0..np {
                let ph = 2.0 * PI * j as f64 / np as f64;
                let (s1, c1) = ph.sin_cos();
                // cos/sin(m phi) by the Chebyshev recurrence (one sin_cos per point).
                let (mut cm, mut sm) = (1.0, 0.0);
                let (mut cp, mut sp) = (c1, -s1); // m = -1
                let mut v = 0.0;
                for a in am.iter() {
                    v += a.0 * cm - a.1 * sm;
                    let (cn, sn) = (2.0 * c1 * cm - cp, 2.0 * c1 * sm - sp);
                    cp = cm;
                    sp = sm;
                    cm = cn;
                    sm = sn;
                }
                r[i * np + j] = v;
            }
        }
        RadiusTable { nt, np, r }
    }
}

/// `r(theta, phi)` on a regular grid including the poles.
#[derive(Clone, Debug)]
pub struct RadiusTable {
    pub nt: usize,
    pub np: usize,
    pub r: Vec<f64>,
}

impl RadiusTable {
    pub fn min(&self) -> f64 {
        self.r.iter().copied().fold(f64::INFINITY, f64::min)
    }
    /// Bilinear interpolation at the direction `u` (unit vector).
    pub fn at(&self, u: [f64; 3]) -> f64 {
        let th = u[2].clamp(-1.0, 1.0).acos();
        let mut ph = u[1].atan2(u[0]);
        if ph < 0.0 {
            ph += 2.0 * PI;
        }
        let fi = (th / PI * self.nt as f64).min(self.nt as f64 - 1e-9);
        let fj = ph / (2.0 * PI) * self.np as f64;
        let (i, j) = (fi as usize, (fj as usize) % self.np);
        let (ti, tj) = (fi - i as f64, fj - fj.floor());
        let j1 = (j + 1) % self.np;
        let g = |i: usize, j: usize| self.r[i * self.np + j];
        (1.0 - ti) * ((1.0 - tj) * g(i, j) + tj * g(i, j1))
            + ti * ((1.0 - tj) * g(i + 1, j) + tj * g(i + 1, j1))
    }
}

/// A star-shaped solid `{ A (s u) : u unit, 0 <= s <= r(u) }`.
#[derive(Clone, Debug)]
pub struct StarShape {
    pub table: RadiusTable,
    pub transform: Matrix3<f64>,
}

impl StarShape {
    /// Surface points at the table nodes, row-major.
    fn vertices(&self) -> Vec<Vector3<f64>> {
        let (nt, np) = (self.table.nt, self.table.np);
        let phis: Vec<(f64, f64)> = (0..np)
            .map(|j| (2.0 * PI * j as f64 / np as f64).sin_cos())
            .collect();
        let mut out = Vec::with_capacity((nt + 1) * np);
        for i in 0..=nt {
            let (st, ct) = (i as f64 * PI / nt as f64).sin_cos();
            for (j, &(sp, cp)) in phis.iter().enumerate() {
                let u = Vector3::new(st * cp, st * sp, ct);
                out.push(self.transform * (u * self.table.r[i * np + j]));
            }
        }
        out
    }

    /// Volume and surface area of the triangulated table surface (error O(grid step^2)).
    pub fn volume_area(&self) -> (f64, f64) {
        let (nt, np) = (self.table.nt, self.table.np);
        let vx = self.vertices();
        let mut vol = 0.0;
        let mut area = 0.0;
        for i in 0..nt {
            for j in 0..np {
                let j1 = (j + 1) % np;
                let (a, b, c, d) = (
                    vx[i * np + j],
                    vx[(i + 1) * np + j],
                    vx[(i + 1) * np + j1],
                    vx[i * np + j1],
                );
                for (p, q, r) in [(a, b, c), (a, c, d)] {
                    vol += p.dot(&q.cross(&r)) / 6.0;
                    area += 0.5 * (q - p).cross(&(r - p)).norm();
                }
            }
        }
        (vol.abs(), area)
    }

    /// Radius of the smallest sphere about the solid's centroid (of the triangulated table
    /// surface, error O(grid step^2)) that holds every table vertex: half the grain's
    /// bounding diameter as `clumps.garcia` measures it about the clump's centroid.
    pub fn bounding_radius(&self) -> f64 {
        let (nt, np) = (self.table.nt, self.table.np);
        let vx = self.vertices();
        let (mut vol, mut m) = (0.0, Vector3::zeros());
        for i in 0..nt {
            for j in 0..np {
                let j1 = (j + 1) % np;
                let (a, b, c, d) = (
                    vx[i * np + j],
                    vx[(i + 1) * np + j],
                    vx[(i + 1) * np + j1],
                    vx[i * np + j1],
                );
                for (p, q, r) in [(a, b, c), (a, c, d)] {
                    // Tetrahedron (origin, p, q, r): signed volume, centroid (p + q + r) / 4.
                    let v = p.dot(&q.cross(&r)) / 6.0;
                    vol += v;
                    m += (p + q + r) * (v / 4.0);
                }
            }
        }
        let c = if vol.abs() > 0.0 { m / vol } else { m };
        vx.iter().map(|v| (v - c).norm()).fold(0.0, f64::max)
    }

    /// Axis-aligned bounding box of the table vertices.
    pub fn bbox(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for v in self.vertices() {
            for a in 0..3 {
                lo[a] = lo[a].min(v[a]);
                hi[a] = hi[a].max(v[a]);
            }
        }
        (lo, hi)
    }

    /// Voxel mask at voxel size `h` (voxel centres inside the solid), with one empty voxel
    /// layer around. Returns (dims, origin of the lower grid corner, mask).
    pub fn voxelize(&self, h: f64) -> Result<Voxelized, VoxelizeError> {
        let inv = self
            .transform
            .try_inverse()
            .ok_or(VoxelizeError::SingularTransform)?;
        let (lo, hi) = self.bbox();
        let start = lo.map(|v| ((v / h).floor() - 1.0) * h);
        let dims = [0, 1, 2].map(|a| (((hi[a] - start[a]) / h).ceil() as usize) + 1);
        let n = dims[0] * dims[1] * dims[2];
        if n > 400_000_000 {
            return Err(VoxelizeError::TooManyVoxels {
                what: "grain",
                dims,
            });
        }
        let mut mask = vec![false; n];
        // Points nearer than the smallest tabulated radius are inside and points beyond the
        // largest are outside (up to the bilinear interpolation, which stays between the
        // table's extremes): only the shell between needs the angles.
        let rmin = self.table.min();
        let rmax = self.table.r.iter().copied().fold(0.0, f64::max);
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let p = Vector3::new(
                        start[0] + (x as f64 + 0.5) * h,
                        start[1] + (y as f64 + 0.5) * h,
                        start[2] + (z as f64 + 0.5) * h,
                    );
                    let q = inv * p;
                    let rho = q.norm();
                    let inside = if rho <= rmin {
                        true
                    } else if rho > rmax {
                        false
                    } else {
                        rho <= self.table.at([q[0] / rho, q[1] / rho, q[2] / rho])
                    };
                    mask[x + dims[0] * (y + dims[1] * z)] = inside;
                }
            }
        }
        Ok((dims, start, mask))
    }
}

/// A Gaussian random field on the sphere with angular power spectrum `C_n = K n^-beta` for
/// `nmin <= n <= nmax`, scaled so its point variance `sum_n (2n+1) C_n / (4 pi)` is
/// `sigma^2` (addition theorem). Returned as complex coefficients of a real function.
pub fn gaussian_random_field<R: rand::Rng + ?Sized>(
    rng: &mut R,
    nmin: usize,
    nmax: usize,
    beta: f64,
    sigma: f64,
) -> Harmonics {
    use rand_distr::{Distribution, StandardNormal};
    let var_unit: f64 = (nmin..=nmax)
        .map(|n| (2 * n + 1) as f64 * (n as f64).powf(-beta) / (4.0 * PI))
        .sum();
    let k = sigma * sigma / var_unit;
    let mut coef = vec![(0.0, 0.0); (nmax + 1) * (nmax + 2) / 2];
    for n in nmin..=nmax {
        let cn = k * (n as f64).powf(-beta);
        for m in 0..=n {
            let g1: f64 = StandardNormal.sample(rng);
            let g2: f64 = StandardNormal.sample(rng);
            // Real basis coefficients b ~ N(0, C_n); in complex form a_n0 = b_0 and, for
            // m > 0, a_nm = (-1)^m (b_c - i b_s) / sqrt(2) gives
            // 2 (-1)^m Re(a_nm Q e^{i m phi}) = sqrt(2) Q (b_c cos + b_s sin).
            let (re, im) = if m == 0 {
                (g1 * cn.sqrt(), 0.0)
            } else {
                let sgn = if m % 2 == 1 { -1.0 } else { 1.0 };
                (sgn * g1 * (cn / 2.0).sqrt(), -sgn * g2 * (cn / 2.0).sqrt())
            };
            coef[n * (n + 1) / 2 + m] = (re, im);
        }
    }
    Harmonics { nmax, coef }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn legendre_matches_closed_forms() {
        // Q_1^1 = sqrt(3/(8 pi)) sin, Q_2^0 = sqrt(5/(16 pi)) (3x^2 - 1),
        // Q_2^2 = sqrt(15/(32 pi)) sin^2 (standard orthonormal SH tables, no CS phase).
        let x: f64 = 0.3;
        let s = (1.0 - x * x).sqrt();
        let mut q = Vec::new();
        legendre_table(4, x, &mut q);
        assert!((q[2] - (3.0 / (8.0 * PI)).sqrt() * s).abs() < 1e-14);
        assert!((q[3] - (5.0 / (16.0 * PI)).sqrt() * (3.0 * x * x - 1.0)).abs() < 1e-14);
        assert!((q[5] - (15.0 / (32.0 * PI)).sqrt() * s * s).abs() < 1e-14);
    }

    #[test]
    fn sphere_table_volume_is_analytic() {
        // a_00 = 2 sqrt(pi) gives r = 1 (Y_0^0 = 1/sqrt(4 pi)); volume 4/3 pi. Tolerance:
        // the inscribed polyhedron of a 90 x 180 grid loses ~ (pi/90)^2 / 3 ~ 4e-4.
        let mut coef = vec![(0.0, 0.0); 3];
        coef[0] = (2.0 * PI.sqrt(), 0.0);
        let h = Harmonics { nmax: 1, coef };
        let s = StarShape {
            table: h.tabulate(90, 180),
            transform: Matrix3::identity(),
        };
        let (v, a) = s.volume_area();
        assert!((v / (4.0 / 3.0 * PI) - 1.0).abs() < 1e-3, "{v}");
        assert!((a / (4.0 * PI) - 1.0).abs() < 1e-3, "{a}");
    }
}
