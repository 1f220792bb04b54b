//! The elastic cell problem, eq. (3.3): find a periodic displacement fluctuation u with
//! div C(x) : (E + grad^s u) = 0, in the displacement form `K u = -B^T C E`, `K = B^T C B`,
//! for the four discretizations of [`Scheme`]. `B` maps the displacement to engineering
//! strains (Voigt order xx, yy, zz, yz, xz, xy) at the quadrature points; `K` is applied in
//! real space (staggered, hex8, rotated: local stencils) or by FFT (spectral), the
//! preconditioner `K0^{-1}` of a homogeneous isotropic reference medium by FFT, where `K0` is
//! a 3x3 Hermitian matrix per frequency.
//!
//! Pores (C = 0): the displacement inside a pore is not determined, K is only positive
//! semi-definite. The load `-B^T C E` lies in the range of K, so CG started from zero stays
//! consistent; the stresses (all that is averaged) are unique even though u is not
//! (Schneider 2016, 2021).

use num_complex::Complex;
use rayon::prelude::*;

use super::composite::{Composite, M6};
use super::solver::{dot, dot_lanes, CellProblem};
use super::{
    edge_weights, gauss_points, hermitian_inverse, nodal_gradient, AxisTables, Iso, Scheme, C64,
};
use crate::fft3::Fft3;
use crate::real::Real;
use std::sync::Arc;

/// The x line (y, z) of a component array.
#[inline(always)]
fn row_of<T>(a: &[T], nx: usize, ny: usize, y: usize, z: usize) -> &[T] {
    let b = nx * (y + ny * z);
    &a[b..b + nx]
}

/// Raw pointer shared by tasks that write disjoint index sets.
#[derive(Clone, Copy)]
struct Shared<T>(*mut T);
// SAFETY: only used where each task writes a disjoint set of indices (documented at use).
unsafe impl<T> Send for Shared<T> {}
unsafe impl<T> Sync for Shared<T> {}

impl<T> Shared<T> {
    /// The pointer; a method, so closures capture the `Shared` (Send) and not its field.
    #[inline(always)]
    fn ptr(self) -> *mut T {
        self.0
    }
}

/// Bytes per voxel of the solver state for `scheme` and `cg`, with `real` bytes per scalar
/// (8 or 4). Counts the CG vectors (u, r, z, p, q: 15 scalars; u, r, z: 9 for the fixed
/// point), the stencil scratch, the preconditioner table of the nodal schemes (9 scalars per
/// half-spectrum frequency), the FFT buffers and the labels.
pub fn bytes_per_voxel(scheme: Scheme, cg: bool, real: usize) -> f64 {
    let vectors = if cg { 15.0 } else { 9.0 };
    let scratch = match scheme {
        // edge moduli (3) + 3 half spectra (~3 scalars) + stress rings (<= 1); the six
        // stress fields of `stress_stats` exist only after the CG vectors are freed
        Scheme::Staggered => 3.0 + 3.0 + 1.0,
        // top-node forces (3) + 3 half spectra
        Scheme::Hex8 | Scheme::Rotated => 3.0 + 3.0,
        // strains/stresses (6) + 4 half spectra (~4)
        Scheme::Spectral => 6.0 + 4.0,
    };
    let table = match scheme {
        Scheme::Hex8 | Scheme::Rotated => 4.5,
        Scheme::Staggered | Scheme::Spectral => 0.0,
    };
    (vectors + scratch + table) * real as f64 + 1.0
}

pub struct Elastic<T: Real> {
    pub dims: [usize; 3],
    pub h: [f64; 3],
    pub scheme: Scheme,
    n: usize,
    labels: Vec<u8>,
    lam: [T; 256],
    mu: [T; 256],
    materials: [Iso; 256],
    /// Staggered: shear moduli of the yz, xz, xy edges (harmonic mean of 4 voxels).
    edge_mu: Vec<T>,
    reference: Iso,
    fft: Fft3<T>,
    /// Nodal schemes: `K0^{-1} / N` per frequency, 9 scalars (see `hermitian_inverse`) per
    /// frequency in the line order of [`Fft3::filter`] (kz fastest, then ky, then kx).
    pinv: Vec<T>,
    /// Staggered and spectral schemes: the normal-strain multiplier `m_d` of each axis, from
    /// which `K0^{-1}` is formed per frequency (see `precondition`); empty otherwise.
    green_axes: [Vec<Complex<T>>; 3],
    spec: Vec<Complex<T>>,
    scratch: Vec<T>,
    /// Staggered: per slab of z planes, a ring of three planes of the six stresses (see
    /// [`Self::staggered_apply`]).
    ring: Vec<T>,
    gauss: Vec<([f64; 3], f64)>,
    /// Nodal schemes: per label the 24 x 24 element stiffness `K_e` (column-major, dof
    /// `c * 8 + node`), empty for pores and for labels not in the image.
    element_matrices: Vec<Vec<T>>,
    tables: [AxisTables; 3],
    /// Composite voxels (laminate stiffnesses), `None` for a labels-only image.
    composite: Option<Arc<Composite<M6>>>,
}

impl<T: Real> Elastic<T> {
    /// `materials[label]` (zero = pore), `reference` the isotropic reference medium of the
    /// preconditioner.
    pub fn new(
        dims: [usize; 3],
        h: [f64; 3],
        labels: Vec<u8>,
        materials: [Iso; 256],
        scheme: Scheme,
        reference: Iso,
    ) -> Self {
        let n = dims.iter().product();
        assert_eq!(labels.len(), n);
        let fft = Fft3::<T>::new(dims);
        let nkx = fft.nkx;
        let tables = [
            AxisTables::new(nkx, dims[0], h[0]),
            AxisTables::new(dims[1], dims[1], h[1]),
            AxisTables::new(dims[2], dims[2], h[2]),
        ];
        let mut lam = [T::zero(); 256];
        let mut mu = [T::zero(); 256];
        for l in 0..256 {
            lam[l] = T::of(materials[l].lambda);
            mu[l] = T::of(materials[l].mu);
        }
        let spec_len = fft.spectrum_len();
        let (spec_n, scratch_n) = match scheme {
            Scheme::Staggered => (3 * spec_len, 0),
            Scheme::Hex8 | Scheme::Rotated => (3 * spec_len, 3 * n),
            Scheme::Spectral => (4 * spec_len, 6 * n),
        };
        let mut p = Elastic {
            dims,
            h,
            scheme,
            n,
            labels,
            lam,
            mu,
            materials,
            edge_mu: vec![],
            reference,
            fft,
            pinv: vec![],
            green_axes: [vec![], vec![], vec![]],
            spec: vec![Complex::new(T::zero(), T::zero()); spec_n],
            scratch: vec![T::zero(); scratch_n],
            ring: vec![],
            gauss: gauss_points(scheme),
            element_matrices: vec![],
            tables,
            composite: None,
        };
        if scheme == Scheme::Staggered {
            p.edge_mu = p.edge_moduli();
            // Two slabs per thread for balance, each at least 8 planes deep so the two
            // planes it recomputes stay a small share (and the rings, 18 planes a slab,
            // within the 1 scalar per voxel of `bytes_per_voxel` once nz >= 36 x threads).
            let slabs = (2 * rayon::current_num_threads()).min(dims[2] / 8).max(1);
            p.ring = vec![T::zero(); slabs * 18 * dims[0] * dims[1]];
        }
        match scheme {
            Scheme::Staggered | Scheme::Spectral => {
                p.green_axes = std::array::from_fn(|d| {
                    let t = &p.tables[d];
                    let m = if scheme == Scheme::Staggered {
                        &t.minus
                    } else {
                        &t.spectral
                    };
                    m.iter()
                        .map(|c| Complex::new(T::of(c.re), T::of(c.im)))
                        .collect()
                })
            }
            Scheme::Hex8 | Scheme::Rotated => {
                p.pinv = p.reference_inverse();
                p.element_matrices = p.element_stiffness();
            }
        }
        p
    }

    #[inline(always)]
    fn idx(&self, x: usize, y: usize, z: usize) -> usize {
        x + self.dims[0] * (y + self.dims[1] * z)
    }

    /// Gives the voxels of `composite` their laminate stiffness (Kabel, Merkert & Schneider
    /// 2015), applied at the Gauss points of the nodal schemes (hex8, rotated). The
    /// staggered and spectral schemes are refused: the staggered grid holds normal and
    /// shear strains at different places, so the laminate's couplings between them have no
    /// place (measured with them left out: no gain over labels on curved interfaces), and
    /// the spectral scheme has no element a voxel's stiffness belongs to.
    pub fn set_composite(&mut self, composite: Arc<Composite<M6>>) {
        assert_eq!(composite.slot.len(), self.n);
        assert!(
            self.scheme != Scheme::Spectral,
            "composite voxels need a local scheme"
        );
        self.composite = Some(composite);
        if self.scheme == Scheme::Staggered {
            self.edge_mu = self.edge_moduli();
        }
    }

    /// Shear modulus of each edge from the four voxels around it (the edge
    /// (i + e_b/2 + e_c/2) touches i, i + e_b, i + e_c, i + e_b + e_c): the harmonic mean of
    /// the solid ones times their share of the four. Exact for laminates (with or without
    /// void layers), zero inside pores.
    fn edge_moduli(&self) -> Vec<T> {
        let [nx, ny, nz] = self.dims;
        let n = self.n;
        let mut out = vec![T::zero(); 3 * n];
        let nxy = nx * ny;
        out.par_chunks_mut(nxy).enumerate().for_each(|(j, plane)| {
            let comp = j / nz;
            let z = j % nz;
            for y in 0..ny {
                for x in 0..nx {
                    let (xp, yp, zp) = ((x + 1) % nx, (y + 1) % ny, (z + 1) % nz);
                    let four = match comp {
                        0 => [(x, y, z), (x, yp, z), (x, y, zp), (x, yp, zp)],
                        1 => [(x, y, z), (xp, y, z), (x, y, zp), (xp, y, zp)],
                        _ => [(x, y, z), (xp, y, z), (x, yp, z), (xp, yp, z)],
                    };
                    let mut inv = 0.0;
                    let mut solid = 0.0;
                    for (a, b, c) in four {
                        let m = self.materials[self.labels[self.idx(a, b, c)] as usize].mu;
                        if m > 0.0 {
                            inv += 1.0 / m;
                            solid += 1.0;
                        }
                    }
                    // Solid part of the edge's dual cell times the harmonic mean of its solid
                    // voxels: harmonic between solids (exact for laminates), pores count as
                    // missing volume (a plain harmonic mean would zero every edge touching a
                    // pore and make pores half a voxel larger: +29 % stiffness loss on a
                    // 5-voxel spherical pore instead of +8 %).
                    plane[x + nx * y] = if solid == 0.0 {
                        T::zero()
                    } else {
                        T::of(solid / 4.0 * solid / inv)
                    };
                }
            }
        });
        out
    }

    /// Strain multipliers at one quadrature point: normal (per axis) and shear (per axis).
    fn symbol_points(&self, kx: usize, ky: usize, kz: usize) -> Vec<([C64; 3], [C64; 3], f64)> {
        let t = &self.tables;
        match self.scheme {
            Scheme::Staggered => vec![(
                [t[0].minus[kx], t[1].minus[ky], t[2].minus[kz]],
                [t[0].plus[kx], t[1].plus[ky], t[2].plus[kz]],
                1.0,
            )],
            Scheme::Spectral => {
                let g = [t[0].spectral[kx], t[1].spectral[ky], t[2].spectral[kz]];
                vec![(g, g, 1.0)]
            }
            Scheme::Hex8 | Scheme::Rotated => self
                .gauss
                .iter()
                .map(|&(p, w)| {
                    let g = nodal_gradient(t[0].e[kx], t[1].e[ky], t[2].e[kz], self.h, p);
                    (g, g, w)
                })
                .collect(),
        }
    }

    /// `K0(xi)^{-1} / N` for every half-spectrum frequency, `K0 = sum_q w_q B_q^H C0 B_q`, in
    /// the line order of [`Fft3::filter`] (the `1/N` of the inverse FFT folded in).
    fn reference_inverse(&self) -> Vec<T> {
        let [_, ny, nz] = self.dims;
        let nkx = self.fft.nkx;
        let c0 = self.reference;
        let inv_n = 1.0 / self.n as f64;
        // The largest trace sets the scale under which K0 counts as zero.
        let hmin = self.h.iter().cloned().fold(f64::INFINITY, f64::min);
        let scale = (c0.lambda.abs() + 2.0 * c0.mu) * 12.0 / (hmin * hmin);
        let mut out = vec![T::zero(); 9 * nkx * ny * nz];
        out.par_chunks_mut(9 * nz)
            .enumerate()
            .for_each(|(line, o)| {
                let (kx, ky) = (line / ny, line % ny);
                for kz in 0..nz {
                    let k = self.reference_symbol(kx, ky, kz);
                    let inv = hermitian_inverse(k, 1e-12 * scale);
                    for (d, v) in o[9 * kz..9 * kz + 9].iter_mut().zip(inv) {
                        *d = T::of(v * inv_n);
                    }
                }
            });
        out
    }

    /// The reference operator's symbol `K0(xi) = sum_q w_q B_q^H C0 B_q` at one frequency,
    /// in closed form for the isotropic `C0`. With `n` the normal-strain and `s` the
    /// shear-strain multipliers of a point (B's rows: `n_d` on `u_d`; yz -> (0, s_z, s_y),
    /// xz -> (s_z, 0, s_x), xy -> (s_y, s_x, 0)):
    /// `K_ab = lambda conj(n_a) n_b + 2 mu delta_ab |n_a|^2
    ///        + mu (delta_ab (|s|^2 - |s_a|^2) + (1 - delta_ab) s_a conj(s_b))`.
    ///
    /// Why closed form: the 6 x 6 Voigt product per point was most of the nodal schemes'
    /// setup.
    fn reference_symbol(&self, kx: usize, ky: usize, kz: usize) -> [[C64; 3]; 3] {
        let (lam, mu) = (self.reference.lambda, self.reference.mu);
        let mut k = [[C64::new(0.0, 0.0); 3]; 3];
        for (nm, sh, w) in self.symbol_points(kx, ky, kz) {
            let s2: f64 = sh.iter().map(|v| v.norm_sqr()).sum();
            for a in 0..3 {
                for b in 0..3 {
                    let mut v = nm[a].conj() * nm[b] * lam;
                    if a == b {
                        v += 2.0 * mu * nm[a].norm_sqr() + mu * (s2 - sh[a].norm_sqr());
                    } else {
                        v += sh[a] * sh[b].conj() * mu;
                    }
                    k[a][b] += v * w;
                }
            }
        }
        k
    }

    /// Staggered grid: stresses at voxel centres (normal) and edges (shear) into `scratch`
    /// (allocated here: the solver's `K u` does not need it, see [`Self::staggered_apply`]).
    fn staggered_stress(&mut self, u: &[T], load: Option<&[f64]>) {
        let [nx, ny, nz] = self.dims;
        let e = Self::load_of(load);
        let (n, nxy) = (self.n, nx * ny);
        let mut scratch = std::mem::take(&mut self.scratch);
        scratch.resize(6 * n, T::zero());
        let dst = Shared(scratch.as_mut_ptr());
        let this = &*self;
        (0..nz).into_par_iter().for_each(|z| {
            // SAFETY: task z alone writes plane z of each of the six components.
            let out = std::array::from_fn(|k| unsafe {
                std::slice::from_raw_parts_mut(dst.ptr().add(k * n + z * nxy), nxy)
            });
            this.stress_plane(z, u, &e, out);
        });
        self.scratch = scratch;
    }

    fn load_of(load: Option<&[f64]>) -> [T; 6] {
        match load {
            Some(l) => std::array::from_fn(|k| T::of(l[k])),
            None => [T::zero(); 6],
        }
    }

    /// The six staggered stresses (Voigt order) on z plane `z` into `out[k]` (`nx * ny`
    /// each). Works row by row (x lines) with the periodic neighbours resolved once per row;
    /// the x wrap is peeled off (`x = 0` or `x = nx - 1` alone) so the inner loops have no
    /// branch and vectorize.
    #[inline]
    fn stress_plane<'u>(&self, z: usize, u: &'u [T], e: &[T; 6], out: [&mut [T]; 6]) {
        let [nx, ny, nz] = self.dims;
        let n = self.n;
        let ih = self.h.map(|h| T::of(1.0 / h));
        let (ux, rest) = u.split_at(n);
        let (uy, uz) = rest.split_at(n);
        let two = T::of(2.0);
        let zm = if z == 0 { nz - 1 } else { z - 1 };
        let zp = if z + 1 == nz { 0 } else { z + 1 };
        let [o0, o1, o2, o3, o4, o5] = out;
        let row = |a: &'u [T], yy: usize, zz: usize| row_of(a, nx, ny, yy, zz);
        for y in 0..ny {
            let ym = if y == 0 { ny - 1 } else { y - 1 };
            let yp = if y + 1 == ny { 0 } else { y + 1 };
            let base = nx * (y + ny * z);
            let r = nx * y..nx * y + nx;
            // eq. (3.3): normal strains at the centre from the face values, one Lame law
            // for the three normal stresses.
            {
                let (ax, ay, by, az, bz) = (
                    row(ux, y, z),
                    row(uy, y, z),
                    row(uy, ym, z),
                    row(uz, y, z),
                    row(uz, y, zm),
                );
                let labels = &self.labels[base..base + nx];
                let (s0, s1, s2) = (&mut o0[r.clone()], &mut o1[r.clone()], &mut o2[r.clone()]);
                let mut at = |x: usize, xm: usize| {
                    let exx = (ax[x] - ax[xm]) * ih[0] + e[0];
                    let eyy = (ay[x] - by[x]) * ih[1] + e[1];
                    let ezz = (az[x] - bz[x]) * ih[2] + e[2];
                    let l = labels[x] as usize;
                    let tr = (exx + eyy + ezz) * self.lam[l];
                    let m2 = two * self.mu[l];
                    s0[x] = tr + m2 * exx;
                    s1[x] = tr + m2 * eyy;
                    s2[x] = tr + m2 * ezz;
                };
                at(0, nx - 1);
                for x in 1..nx {
                    at(x, x - 1);
                }
            }
            {
                let (a0, a1, b0, b1) =
                    (row(uy, y, z), row(uy, y, zp), row(uz, y, z), row(uz, yp, z));
                let m = &self.edge_mu[base..base + nx];
                let o = &mut o3[r.clone()];
                for x in 0..nx {
                    let g = (a1[x] - a0[x]) * ih[2] + (b1[x] - b0[x]) * ih[1] + e[3];
                    o[x] = m[x] * g;
                }
            }
            {
                let (a0, a1, b0) = (row(ux, y, z), row(ux, y, zp), row(uz, y, z));
                let m = &self.edge_mu[n + base..n + base + nx];
                let o = &mut o4[r.clone()];
                let mut at = |x: usize, xp: usize| {
                    let g = (a1[x] - a0[x]) * ih[2] + (b0[xp] - b0[x]) * ih[0] + e[4];
                    o[x] = m[x] * g;
                };
                for x in 0..nx - 1 {
                    at(x, x + 1);
                }
                at(nx - 1, 0);
            }
            {
                let (a0, a1, b0) = (row(ux, y, z), row(ux, yp, z), row(uy, y, z));
                let m = &self.edge_mu[2 * n + base..2 * n + base + nx];
                let o = &mut o5[r];
                let mut at = |x: usize, xp: usize| {
                    let g = (a1[x] - a0[x]) * ih[1] + (b0[xp] - b0[x]) * ih[0] + e[5];
                    o[x] = m[x] * g;
                };
                for x in 0..nx - 1 {
                    at(x, x + 1);
                }
                at(nx - 1, 0);
            }
        }
    }
    /// `B^T` of the staggered grid: component `comp` of the divergence of the stresses on z
    /// plane `z` into `o` (`nx * ny`); `row(k, y, z)` is the x line of stress component `k`.
    #[inline]
    fn divergence_plane<'a, F>(&self, comp: usize, z: usize, row: F, o: &mut [T])
    where
        F: Fn(usize, usize, usize) -> &'a [T],
        T: 'a,
    {
        let [nx, ny, nz] = self.dims;
        let ih = self.h.map(|h| T::of(1.0 / h));
        let zm = if z == 0 { nz - 1 } else { z - 1 };
        let zp = if z + 1 == nz { 0 } else { z + 1 };
        for y in 0..ny {
            let ym = if y == 0 { ny - 1 } else { y - 1 };
            let yp = if y + 1 == ny { 0 } else { y + 1 };
            let o = &mut o[nx * y..nx * y + nx];
            match comp {
                0 => {
                    let (n0, s5, s5m, s4, s4m) = (
                        row(0, y, z),
                        row(5, y, z),
                        row(5, ym, z),
                        row(4, y, z),
                        row(4, y, zm),
                    );
                    let mut at = |x: usize, xp: usize| {
                        o[x] = (n0[x] - n0[xp]) * ih[0]
                            + (s5m[x] - s5[x]) * ih[1]
                            + (s4m[x] - s4[x]) * ih[2];
                    };
                    for x in 0..nx - 1 {
                        at(x, x + 1);
                    }
                    at(nx - 1, 0);
                }
                1 => {
                    let (n1, n1p, s5, s3, s3m) = (
                        row(1, y, z),
                        row(1, yp, z),
                        row(5, y, z),
                        row(3, y, z),
                        row(3, y, zm),
                    );
                    let mut at = |x: usize, xm: usize| {
                        o[x] = (n1[x] - n1p[x]) * ih[1]
                            + (s5[xm] - s5[x]) * ih[0]
                            + (s3m[x] - s3[x]) * ih[2];
                    };
                    at(0, nx - 1);
                    for x in 1..nx {
                        at(x, x - 1);
                    }
                }
                _ => {
                    let (n2, n2p, s4, s3, s3m) = (
                        row(2, y, z),
                        row(2, y, zp),
                        row(4, y, z),
                        row(3, y, z),
                        row(3, ym, z),
                    );
                    let mut at = |x: usize, xm: usize| {
                        o[x] = (n2[x] - n2p[x]) * ih[2]
                            + (s4[xm] - s4[x]) * ih[0]
                            + (s3m[x] - s3[x]) * ih[1];
                    };
                    at(0, nx - 1);
                    for x in 1..nx {
                        at(x, x - 1);
                    }
                }
            }
        }
    }

    /// Staggered `out = B^T C (E + B u)`, and `u . out` when `with_dot`.
    ///
    /// Why fused: the divergence of plane z needs the stresses of planes z - 1, z and z + 1
    /// only, so each task walks a slab of z planes keeping three stress planes in a ring
    /// (in cache) instead of writing the six stress fields to memory and reading them back
    /// (12 of the ~21 scalars per voxel the two sweeps moved). The two planes in front of a
    /// slab are computed twice; every value is computed by the same formula as before, so
    /// `out` is bit-identical. The dot product is summed per plane, then over the planes in
    /// order: independent of the slab and thread counts.
    fn staggered_apply(
        &mut self,
        u: &[T],
        load: Option<&[f64]>,
        out: &mut [T],
        with_dot: bool,
    ) -> f64 {
        let [nx, ny, nz] = self.dims;
        let n = self.n;
        let nxy = nx * ny;
        let e = Self::load_of(load);
        let slabs = self.ring.len() / (18 * nxy);
        let mut ring = std::mem::take(&mut self.ring);
        let dst = Shared(out.as_mut_ptr());
        let this = &*self;
        let per_slab: Vec<Vec<f64>> = ring
            .par_chunks_mut(18 * nxy)
            .enumerate()
            .map(|(s, buf)| {
                let (z0, z1) = (s * nz / slabs, (s + 1) * nz / slabs);
                // Ring slot of relative plane `rel` (plane z0 - 1 + rel).
                let fill = |buf: &mut [T], rel: usize, z: usize| {
                    let b = &mut buf[(rel % 3) * 6 * nxy..(rel % 3 + 1) * 6 * nxy];
                    let mut parts = b.chunks_mut(nxy);
                    let out = std::array::from_fn(|_| parts.next().expect("6 planes"));
                    this.stress_plane(z, u, &e, out);
                };
                fill(buf, 0, (z0 + nz - 1) % nz);
                fill(buf, 1, z0);
                let mut sums = Vec::with_capacity(z1 - z0);
                for z in z0..z1 {
                    let rel = z - z0 + 1;
                    fill(buf, rel + 1, (z + 1) % nz);
                    let zm = (z + nz - 1) % nz;
                    let b = &*buf;
                    // Planes equal in value share their data (nz = 1 or 2), so matching by
                    // plane index is exact.
                    let row = |k: usize, yy: usize, zz: usize| {
                        let r = if zz == z {
                            rel
                        } else if zz == zm {
                            rel - 1
                        } else {
                            rel + 1
                        };
                        let at = (r % 3) * 6 * nxy + k * nxy + nx * yy;
                        &b[at..at + nx]
                    };
                    let mut acc = 0.0;
                    for c in 0..3 {
                        // SAFETY: slab s alone writes planes z0..z1 of every component.
                        let o = unsafe {
                            std::slice::from_raw_parts_mut(dst.ptr().add(c * n + z * nxy), nxy)
                        };
                        this.divergence_plane(c, z, row, o);
                        if with_dot {
                            let p = &u[c * n + z * nxy..c * n + (z + 1) * nxy];
                            acc += dot_lanes(o, p);
                        }
                    }
                    sums.push(acc);
                }
                sums
            })
            .collect();
        self.ring = ring;
        per_slab.iter().flatten().sum()
    }

    /// Strain (engineering Voigt, without the load) and stress at Gauss point `g` of the
    /// element at (x, y, z) of a nodal scheme, from its 24 nodal values.
    #[inline(always)]
    fn element_gradients(h: [f64; 3], ue: &[[T; 8]; 3]) -> [[[T; 4]; 3]; 3] {
        // d[axis][comp][edge]: differences along `axis` on its 4 parallel edges, edge index
        // (j + 2k) over the two other axes in order.
        let ih = h.map(|h| T::of(1.0 / h));
        let mut d = [[[T::zero(); 4]; 3]; 3];
        for c in 0..3 {
            for a in 0..2 {
                for b in 0..2 {
                    // node index = dx + 2 dy + 4 dz
                    d[0][c][a + 2 * b] = (ue[c][1 + 2 * a + 4 * b] - ue[c][2 * a + 4 * b]) * ih[0];
                    d[1][c][a + 2 * b] = (ue[c][a + 2 + 4 * b] - ue[c][a + 4 * b]) * ih[1];
                    d[2][c][a + 2 * b] = (ue[c][a + 2 * b + 4] - ue[c][a + 2 * b]) * ih[2];
                }
            }
        }
        d
    }

    /// Quadrature of a nodal scheme: per Gauss point the linear weights `[1 - p, p]` of each
    /// axis and the point's weight.
    fn gauss_weights(gauss: &[([f64; 3], f64)]) -> Vec<([[T; 2]; 3], T)> {
        gauss
            .iter()
            .map(|&(p, w)| {
                (
                    [0, 1, 2].map(|a| [T::of(1.0 - p[a]), T::of(p[a])]),
                    T::of(w),
                )
            })
            .collect()
    }

    /// Nodal forces `B^T C (E + B u_e)` of one element with Lame constants `lam`, `mu`, by
    /// quadrature over `gauss` (see [`Self::gauss_weights`]).
    fn element_forces(
        h: [f64; 3],
        ue: &[[T; 8]; 3],
        e: [T; 6],
        (lam, mu): (T, T),
        gauss: &[([[T; 2]; 3], T)],
    ) -> [[T; 8]; 3] {
        let two = T::of(2.0);
        Self::element_forces_with(h, ue, gauss, |g| {
            let exx = g[0][0] + e[0];
            let eyy = g[1][1] + e[1];
            let ezz = g[2][2] + e[2];
            let tr = lam * (exx + eyy + ezz);
            let syz = mu * (g[1][2] + g[2][1] + e[3]);
            let sxz = mu * (g[0][2] + g[2][0] + e[4]);
            let sxy = mu * (g[0][1] + g[1][0] + e[5]);
            [
                [tr + two * mu * exx, sxy, sxz],
                [sxy, tr + two * mu * eyy, syz],
                [sxz, syz, tr + two * mu * ezz],
            ]
        })
    }

    /// Nodal forces `B^T C (E + B u_e)` of one element with a general (composite voxel)
    /// stiffness `c` (Voigt, engineering shear), by quadrature over `gauss`.
    fn element_forces_general(
        h: [f64; 3],
        ue: &[[T; 8]; 3],
        e: [T; 6],
        c: &M6,
        gauss: &[([[T; 2]; 3], T)],
    ) -> [[T; 8]; 3] {
        let c: [[T; 6]; 6] = c.map(|row| row.map(T::of));
        Self::element_forces_with(h, ue, gauss, |g| {
            let eps = [
                g[0][0] + e[0],
                g[1][1] + e[1],
                g[2][2] + e[2],
                g[1][2] + g[2][1] + e[3],
                g[0][2] + g[2][0] + e[4],
                g[0][1] + g[1][0] + e[5],
            ];
            let mut sv = [T::zero(); 6];
            for (i, row) in c.iter().enumerate() {
                for (j, &cij) in row.iter().enumerate() {
                    sv[i] = sv[i] + cij * eps[j];
                }
            }
            [
                [sv[0], sv[5], sv[4]],
                [sv[5], sv[1], sv[3]],
                [sv[4], sv[3], sv[2]],
            ]
        })
    }

    /// The quadrature of a nodal element: at each Gauss point the displacement gradient
    /// `g[axis][comp]` (without the load) goes to `stress(g)` (symmetric 3x3, load included),
    /// whose work against the edge differences gives the nodal forces.
    fn element_forces_with(
        h: [f64; 3],
        ue: &[[T; 8]; 3],
        gauss: &[([[T; 2]; 3], T)],
        stress: impl Fn(&[[T; 3]; 3]) -> [[T; 3]; 3],
    ) -> [[T; 8]; 3] {
        let ih = h.map(|h| T::of(1.0 / h));
        let d = Self::element_gradients(h, ue);
        let mut f = [[[T::zero(); 4]; 3]; 3];
        for (wt, w) in gauss {
            let ws = edge_weights(wt);
            // g[axis][comp] = d u_comp / d axis
            let mut g = [[T::zero(); 3]; 3];
            for a in 0..3 {
                for c in 0..3 {
                    g[a][c] = d[a][c][0] * ws[a][0]
                        + d[a][c][1] * ws[a][1]
                        + d[a][c][2] * ws[a][2]
                        + d[a][c][3] * ws[a][3];
                }
            }
            let s = stress(&g);
            for a in 0..3 {
                for c in 0..3 {
                    let v = *w * s[a][c];
                    for q in 0..4 {
                        f[a][c][q] = f[a][c][q] + v * ws[a][q];
                    }
                }
            }
        }
        Self::edges_to_nodes(&f, ih)
    }

    /// Edge forces `f[axis][comp][edge]` to the element's 8 nodes (the transpose of the
    /// differences of [`Self::element_gradients`]).
    fn edges_to_nodes(f: &[[[T; 4]; 3]; 3], ih: [T; 3]) -> [[T; 8]; 3] {
        let mut fn_ = [[T::zero(); 8]; 3];
        for c in 0..3 {
            for a in 0..2 {
                for b in 0..2 {
                    let q = a + 2 * b;
                    let fx = f[0][c][q] * ih[0];
                    fn_[c][1 + 2 * a + 4 * b] = fn_[c][1 + 2 * a + 4 * b] + fx;
                    fn_[c][2 * a + 4 * b] = fn_[c][2 * a + 4 * b] - fx;
                    let fy = f[1][c][q] * ih[1];
                    fn_[c][a + 2 + 4 * b] = fn_[c][a + 2 + 4 * b] + fy;
                    fn_[c][a + 4 * b] = fn_[c][a + 4 * b] - fy;
                    let fz = f[2][c][q] * ih[2];
                    fn_[c][a + 2 * b + 4] = fn_[c][a + 2 * b + 4] + fz;
                    fn_[c][a + 2 * b] = fn_[c][a + 2 * b] - fz;
                }
            }
        }
        fn_
    }

    /// Per label, the element stiffness of the nodal scheme: [`Self::element_forces`] of the
    /// 24 unit displacements (computed in f64 and rounded once, so f32 fields get the same
    /// matrix to the last bit of f32).
    fn element_stiffness(&self) -> Vec<Vec<T>> {
        let mut present = [false; 256];
        for &l in &self.labels {
            present[l as usize] = true;
        }
        (0..256)
            .map(|l| {
                let m = self.materials[l];
                if !present[l] || m.is_zero() {
                    return vec![];
                }
                let gauss = Elastic::<f64>::gauss_weights(&self.gauss);
                let mut k = Vec::with_capacity(576);
                for j in 0..24 {
                    let mut ue = [[0.0; 8]; 3];
                    ue[j / 8][j % 8] = 1.0;
                    let f = Elastic::<f64>::element_forces(
                        self.h,
                        &ue,
                        [0.0; 6],
                        (m.lambda, m.mu),
                        &gauss,
                    );
                    k.extend(f.iter().flatten().map(|&v| T::of(v)));
                }
                k
            })
            .collect()
    }

    /// Nodal schemes: `out = B^T C (E + B u)`. Without a load (every CG iteration) each
    /// element is one product with its stored stiffness (24 x 24, vectorises); with a load
    /// the quadrature of [`Self::element_forces`], which also carries the load term.
    fn nodal_apply(&mut self, u: &[T], load: Option<&[f64]>, out: &mut [T]) {
        match load {
            None => {
                let gauss = Self::gauss_weights(&self.gauss);
                self.nodal_sweep(u, out, |this, ue, v| {
                    if let Some(c) = this.composite.as_ref().and_then(|c| c.get(v)) {
                        return Self::element_forces_general(this.h, ue, [T::zero(); 6], c, &gauss);
                    }
                    let k = &this.element_matrices[this.labels[v] as usize];
                    let mut f = [T::zero(); 24];
                    if k.is_empty() {
                        return [[T::zero(); 8]; 3];
                    }
                    let flat: [T; 24] = std::array::from_fn(|j| ue[j / 8][j % 8]);
                    for (col, &uj) in k.chunks_exact(24).zip(&flat) {
                        for (fi, &kij) in f.iter_mut().zip(col) {
                            *fi = *fi + kij * uj;
                        }
                    }
                    std::array::from_fn(|c| std::array::from_fn(|i| f[c * 8 + i]))
                })
            }
            Some(l) => {
                let e: [T; 6] = std::array::from_fn(|k| T::of(l[k]));
                let gauss = Self::gauss_weights(&self.gauss);
                self.nodal_sweep(u, out, |this, ue, v| {
                    if let Some(c) = this.composite.as_ref().and_then(|c| c.get(v)) {
                        return Self::element_forces_general(this.h, ue, e, c, &gauss);
                    }
                    let l = this.labels[v] as usize;
                    let (lam, mu) = (this.lam[l], this.mu[l]);
                    if lam == T::zero() && mu == T::zero() {
                        return [[T::zero(); 8]; 3];
                    }
                    Self::element_forces(this.h, ue, e, (lam, mu), &gauss)
                })
            }
        }
    }

    /// Element by element: `forces(self, u_e, voxel)` gives the nodal forces of the element
    /// whose lower corner is each voxel. Each task owns one element plane and writes the
    /// forces of its bottom nodes into `out` and of its top nodes into the scratch plane; the
    /// planes are summed afterwards in a fixed order.
    fn nodal_sweep<F>(&mut self, u: &[T], out: &mut [T], forces: F)
    where
        F: Fn(&Self, &[[T; 8]; 3], usize) -> [[T; 8]; 3] + Sync,
    {
        let [nx, ny, nz] = self.dims;
        let n = self.n;
        let nxy = nx * ny;
        let mut scratch = std::mem::take(&mut self.scratch);
        let top = Shared(scratch.as_mut_ptr());
        let bottom = Shared(out.as_mut_ptr());
        let this = &*self;
        (0..nz).into_par_iter().for_each(|z| {
            let (top, bottom) = (top, bottom);
            let zp = (z + 1) % nz;
            for c in 0..3 {
                for k in 0..nxy {
                    // SAFETY: task z owns plane z of `out` and of `scratch` (all components).
                    unsafe {
                        *bottom.0.add(c * n + z * nxy + k) = T::zero();
                        *top.0.add(c * n + z * nxy + k) = T::zero();
                    }
                }
            }
            for y in 0..ny {
                let yp = (y + 1) % ny;
                for x in 0..nx {
                    let xp = (x + 1) % nx;
                    let nodes = [
                        this.idx(x, y, z),
                        this.idx(xp, y, z),
                        this.idx(x, yp, z),
                        this.idx(xp, yp, z),
                        this.idx(x, y, zp),
                        this.idx(xp, y, zp),
                        this.idx(x, yp, zp),
                        this.idx(xp, yp, zp),
                    ];
                    let ue: [[T; 8]; 3] =
                        std::array::from_fn(|c| std::array::from_fn(|k| u[c * n + nodes[k]]));
                    let fn_ = forces(this, &ue, nodes[0]);
                    for c in 0..3 {
                        for k in 0..8 {
                            let plane_index = nodes[k] % nxy;
                            // SAFETY: bottom nodes (k < 4) lie in plane z of `out`, top nodes
                            // in plane z of `scratch`, both owned by this task.
                            unsafe {
                                if k < 4 {
                                    let p = bottom.0.add(c * n + z * nxy + plane_index);
                                    *p = *p + fn_[c][k];
                                } else {
                                    let p = top.0.add(c * n + z * nxy + plane_index);
                                    *p = *p + fn_[c][k];
                                }
                            }
                        }
                    }
                }
            }
        });
        // Top-node forces of element plane z - 1 belong to node plane z.
        out.par_chunks_mut(nxy).enumerate().for_each(|(j, o)| {
            let c = j / nz;
            let z = j % nz;
            let zm = (z + nz - 1) % nz;
            let t = &scratch[c * n + zm * nxy..c * n + zm * nxy + nxy];
            o.iter_mut().zip(t).for_each(|(o, &t)| *o = *o + t);
        });
        self.scratch = scratch;
    }

    /// Spectral strain multipliers of Voigt component `k` acting on (u_x, u_y, u_z).
    fn spectral_row(&self, k: usize, kx: usize, ky: usize, kz: usize) -> [C64; 3] {
        let t = &self.tables;
        let g = [t[0].spectral[kx], t[1].spectral[ky], t[2].spectral[kz]];
        let z = C64::new(0.0, 0.0);
        match k {
            0 => [g[0], z, z],
            1 => [z, g[1], z],
            2 => [z, z, g[2]],
            3 => [z, g[2], g[1]],
            4 => [g[2], z, g[0]],
            _ => [g[1], g[0], z],
        }
    }

    /// Spectral: strains (without the load) of `u` at the voxel centres into `scratch`.
    fn spectral_strain(&mut self, u: &[T]) {
        let n = self.n;
        let sl = self.fft.spectrum_len();
        let mut spec = std::mem::take(&mut self.spec);
        let mut scratch = std::mem::take(&mut self.scratch);
        for c in 0..3 {
            self.fft
                .forward(&u[c * n..(c + 1) * n], &mut spec[c * sl..(c + 1) * sl]);
        }
        let inv_n = T::of(1.0 / n as f64);
        let (uhat, work) = spec.split_at_mut(3 * sl);
        for k in 0..6 {
            self.spectral_multiply(k, uhat, &mut work[..sl], false);
            self.fft
                .inverse(&mut work[..sl], &mut scratch[k * n..(k + 1) * n]);
            scratch[k * n..(k + 1) * n]
                .par_iter_mut()
                .for_each(|v| *v = *v * inv_n);
        }
        self.spec = spec;
        self.scratch = scratch;
    }

    /// `work = row_k . uhat` (or, with `transpose`, `uhat[c] += conj(row_k[c]) work`).
    fn spectral_multiply(
        &self,
        k: usize,
        uhat: &mut [Complex<T>],
        work: &mut [Complex<T>],
        transpose: bool,
    ) {
        let [_, ny, _] = self.dims;
        let nkx = self.fft.nkx;
        let sl = self.fft.spectrum_len();
        let cv = |c: C64| Complex::new(T::of(c.re), T::of(c.im));
        if transpose {
            let (u0, rest) = uhat.split_at_mut(sl);
            let (u1, u2) = rest.split_at_mut(sl);
            u0.par_chunks_mut(nkx)
                .zip(u1.par_chunks_mut(nkx))
                .zip(u2.par_chunks_mut(nkx))
                .zip(work.par_chunks(nkx))
                .enumerate()
                .for_each(|(row, (((a, b), c), w))| {
                    let (ky, kz) = (row % ny, row / ny);
                    for kx in 0..nkx {
                        let r = self.spectral_row(k, kx, ky, kz);
                        a[kx] = a[kx] + cv(r[0].conj()) * w[kx];
                        b[kx] = b[kx] + cv(r[1].conj()) * w[kx];
                        c[kx] = c[kx] + cv(r[2].conj()) * w[kx];
                    }
                });
        } else {
            let uhat = &*uhat;
            work.par_chunks_mut(nkx).enumerate().for_each(|(row, w)| {
                let (ky, kz) = (row % ny, row / ny);
                for kx in 0..nkx {
                    let r = self.spectral_row(k, kx, ky, kz);
                    let i = kx + nkx * row;
                    w[kx] =
                        cv(r[0]) * uhat[i] + cv(r[1]) * uhat[sl + i] + cv(r[2]) * uhat[2 * sl + i];
                }
            });
        }
    }

    fn spectral_apply(&mut self, u: &[T], load: Option<&[f64]>, out: &mut [T]) {
        let n = self.n;
        let sl = self.fft.spectrum_len();
        self.spectral_strain(u);
        // Stresses at the voxel centres, in place.
        let e: [T; 6] = match load {
            Some(l) => std::array::from_fn(|k| T::of(l[k])),
            None => [T::zero(); 6],
        };
        let two = T::of(2.0);
        {
            let (lam, mu, labels) = (&self.lam, &self.mu, &self.labels);
            let mut parts: Vec<&mut [T]> = self.scratch.chunks_mut(n).collect();
            let (a, rest) = parts.split_at_mut(3);
            let [s0, s1, s2] = a else { unreachable!() };
            let [s3, s4, s5] = rest else { unreachable!() };
            s0.par_iter_mut()
                .zip(s1.par_iter_mut())
                .zip(s2.par_iter_mut())
                .zip(s3.par_iter_mut())
                .zip(s4.par_iter_mut())
                .zip(s5.par_iter_mut())
                .enumerate()
                .for_each(|(i, (((((a, b), c), d), f), g))| {
                    let l = labels[i] as usize;
                    let (ex, ey, ez) = (*a + e[0], *b + e[1], *c + e[2]);
                    let tr = lam[l] * (ex + ey + ez);
                    *a = tr + two * mu[l] * ex;
                    *b = tr + two * mu[l] * ey;
                    *c = tr + two * mu[l] * ez;
                    *d = mu[l] * (*d + e[3]);
                    *f = mu[l] * (*f + e[4]);
                    *g = mu[l] * (*g + e[5]);
                });
        }
        let mut spec = std::mem::take(&mut self.spec);
        let (uhat, work) = spec.split_at_mut(3 * sl);
        uhat.par_iter_mut()
            .for_each(|v| *v = Complex::new(T::zero(), T::zero()));
        for k in 0..6 {
            self.fft
                .forward(&self.scratch[k * n..(k + 1) * n], &mut work[..sl]);
            self.spectral_multiply(k, uhat, &mut work[..sl], true);
        }
        let inv_n = T::of(1.0 / n as f64);
        for c in 0..3 {
            self.fft.inverse(
                &mut uhat[c * sl..(c + 1) * sl],
                &mut out[c * n..(c + 1) * n],
            );
            out[c * n..(c + 1) * n]
                .par_iter_mut()
                .for_each(|v| *v = *v * inv_n);
        }
        self.spec = spec;
    }

    /// Voxel-centred strain (with the load) and stress of a solution: staggered shear values
    /// are the mean of the voxel's four edges, nodal ones the Gauss-weighted mean. Writes
    /// the 6-component fields (component fastest) when `fields` is given, and returns per
    /// label the summed stress and the voxel count. The mean of the voxel stresses is the
    /// mean stress of eq. (3.4) exactly (each edge is shared by four voxels).
    pub fn stress_stats(
        &mut self,
        u: &[T],
        load: &[f64],
        mut fields: Option<(&mut [f64], &mut [f64])>,
    ) -> Vec<([f64; 6], u64)> {
        let [nx, ny, nz] = self.dims;
        let n = self.n;
        let nxy = nx * ny;
        if self.scheme == Scheme::Spectral {
            self.spectral_strain(u);
        }
        if self.scheme == Scheme::Staggered {
            // Strains at the staggered points: the stresses with unit moduli are not
            // enough (edges next to pores are zero), so strains are recomputed below.
            self.staggered_stress(u, Some(load));
        }
        let this = &*self;
        type PlaneStats = (Vec<([f64; 6], u64)>, Vec<[f64; 12]>);
        let per_plane: Vec<PlaneStats> = (0..nz)
            .into_par_iter()
            .map(|z| {
                let mut acc = vec![([0.0; 6], 0u64); 256];
                let mut vals = Vec::with_capacity(if fields.is_some() { nxy } else { 0 });
                for y in 0..ny {
                    for x in 0..nx {
                        let (eps, sig) = this.voxel_values(u, load, x, y, z);
                        let l = this.labels[this.idx(x, y, z)] as usize;
                        for k in 0..6 {
                            acc[l].0[k] += sig[k];
                        }
                        acc[l].1 += 1;
                        if vals.capacity() > 0 {
                            let mut v = [0.0; 12];
                            v[..6].copy_from_slice(&eps);
                            v[6..].copy_from_slice(&sig);
                            vals.push(v);
                        }
                    }
                }
                (acc, vals)
            })
            .collect();
        let mut total = vec![([0.0; 6], 0u64); 256];
        for (z, (acc, vals)) in per_plane.into_iter().enumerate() {
            for l in 0..256 {
                for k in 0..6 {
                    total[l].0[k] += acc[l].0[k];
                }
                total[l].1 += acc[l].1;
            }
            if let Some((eps, sig)) = fields.as_mut() {
                for (k, v) in vals.iter().enumerate() {
                    let i = z * nxy + k;
                    eps[6 * i..6 * i + 6].copy_from_slice(&v[..6]);
                    sig[6 * i..6 * i + 6].copy_from_slice(&v[6..]);
                }
            }
        }
        let _ = n;
        if self.scheme == Scheme::Staggered {
            // The six stress fields serve only this post-processing; the solver does not
            // need them, so they do not stay allocated between load cases.
            self.scratch = Vec::new();
        }
        total
    }

    /// Strain (load included) and stress at voxel (x, y, z).
    fn voxel_values(
        &self,
        u: &[T],
        load: &[f64],
        x: usize,
        y: usize,
        z: usize,
    ) -> ([f64; 6], [f64; 6]) {
        let [nx, ny, nz] = self.dims;
        let n = self.n;
        let i = self.idx(x, y, z);
        let c = match self.composite.as_ref().and_then(|c| c.get(i)) {
            Some(c) => *c,
            None => self.materials[self.labels[i] as usize].voigt(),
        };
        let stress_of = |eps: &[f64; 6]| {
            let mut s = [0.0; 6];
            for a in 0..6 {
                for b in 0..6 {
                    s[a] += c[a][b] * eps[b];
                }
            }
            s
        };
        let (xm, ym, zm) = ((x + nx - 1) % nx, (y + ny - 1) % ny, (z + nz - 1) % nz);
        let (xp, yp, zp) = ((x + 1) % nx, (y + 1) % ny, (z + 1) % nz);
        let g = |c: usize, j: usize| u[c * n + j].f64();
        match self.scheme {
            Scheme::Staggered => {
                let ih = self.h.map(|h| 1.0 / h);
                let mut eps = [0.0; 6];
                eps[0] = (g(0, i) - g(0, self.idx(xm, y, z))) * ih[0] + load[0];
                eps[1] = (g(1, i) - g(1, self.idx(x, ym, z))) * ih[1] + load[1];
                eps[2] = (g(2, i) - g(2, self.idx(x, y, zm))) * ih[2] + load[2];
                let mut sig = [0.0; 6];
                let s = &self.scratch;
                for k in 0..3 {
                    sig[k] = s[k * n + i].f64();
                }
                // Edge strain at the edge whose lower voxel is (a, b, c).
                let gam = |k: usize, a: usize, b: usize, cz: usize| {
                    let j = self.idx(a, b, cz);
                    let (ap, bp, cp) = ((a + 1) % nx, (b + 1) % ny, (cz + 1) % nz);
                    match k {
                        3 => {
                            (g(1, self.idx(a, b, cp)) - g(1, j)) * ih[2]
                                + (g(2, self.idx(a, bp, cz)) - g(2, j)) * ih[1]
                                + load[3]
                        }
                        4 => {
                            (g(0, self.idx(a, b, cp)) - g(0, j)) * ih[2]
                                + (g(2, self.idx(ap, b, cz)) - g(2, j)) * ih[0]
                                + load[4]
                        }
                        _ => {
                            (g(0, self.idx(a, bp, cz)) - g(0, j)) * ih[1]
                                + (g(1, self.idx(ap, b, cz)) - g(1, j)) * ih[0]
                                + load[5]
                        }
                    }
                };
                let edges = |k: usize| -> [(usize, usize, usize); 4] {
                    match k {
                        3 => [(x, y, z), (x, ym, z), (x, y, zm), (x, ym, zm)],
                        4 => [(x, y, z), (xm, y, z), (x, y, zm), (xm, y, zm)],
                        _ => [(x, y, z), (xm, y, z), (x, ym, z), (xm, ym, z)],
                    }
                };
                for k in 3..6 {
                    for (a, b, cz) in edges(k) {
                        eps[k] += 0.25 * gam(k, a, b, cz);
                        sig[k] += 0.25 * s[k * n + self.idx(a, b, cz)].f64();
                    }
                }
                (eps, sig)
            }
            Scheme::Spectral => {
                let mut eps = [0.0; 6];
                for k in 0..6 {
                    eps[k] = self.scratch[k * n + i].f64() + load[k];
                }
                (eps, stress_of(&eps))
            }
            Scheme::Hex8 | Scheme::Rotated => {
                let nodes = [
                    i,
                    self.idx(xp, y, z),
                    self.idx(x, yp, z),
                    self.idx(xp, yp, z),
                    self.idx(x, y, zp),
                    self.idx(xp, y, zp),
                    self.idx(x, yp, zp),
                    self.idx(xp, yp, zp),
                ];
                let ih = self.h.map(|h| 1.0 / h);
                let mut eps = [0.0; 6];
                for &(p, w) in &self.gauss {
                    let mut gr = [[0.0; 3]; 3];
                    for (k, &node) in nodes.iter().enumerate() {
                        let (dx, dy, dz) = (k & 1, (k >> 1) & 1, (k >> 2) & 1);
                        let s = |d: usize, t: f64| if d == 1 { t } else { 1.0 - t };
                        let ds = |d: usize| if d == 1 { 1.0 } else { -1.0 };
                        let grad = [
                            ds(dx) * ih[0] * s(dy, p[1]) * s(dz, p[2]),
                            ds(dy) * ih[1] * s(dx, p[0]) * s(dz, p[2]),
                            ds(dz) * ih[2] * s(dx, p[0]) * s(dy, p[1]),
                        ];
                        for a in 0..3 {
                            for cc in 0..3 {
                                gr[a][cc] += grad[a] * g(cc, node);
                            }
                        }
                    }
                    let e = [
                        gr[0][0],
                        gr[1][1],
                        gr[2][2],
                        gr[1][2] + gr[2][1],
                        gr[0][2] + gr[2][0],
                        gr[0][1] + gr[1][0],
                    ];
                    for k in 0..6 {
                        eps[k] += w * (e[k] + load[k]);
                    }
                }
                (eps, stress_of(&eps))
            }
        }
    }
    /// The multiplier `K0^{-1} / N` of [`Fft3::filter`] on the z lines of the spectrum: the
    /// stored table of the nodal schemes, the closed form of the staggered and spectral ones.
    fn green(&self) -> impl Fn(usize, usize, &mut [&mut [Complex<T>]; 3]) + Sync + '_ {
        let inv_n = 1.0 / self.n as f64;
        let [_, ny, nz] = self.dims;
        let pinv = &self.pinv;
        let table = self.green_axes[0].is_empty();
        // Both schemes have normal strains m_d u_d and shear strains p_c u_d + p_d u_c
        // with conj(p_d) = -m_d (staggered: forward and backward differences, spectral:
        // p = m = i k), so u^H K0 u = mu0 |m|^2 |u|^2 + (lambda0 + mu0) |m . u|^2, i.e.
        // K0 = mu0 s I + (lambda0 + mu0) conj(m) m^T with s = |m|^2, and by
        // Sherman-Morrison K0^{-1} r = (r - (lambda0 + mu0) / ((lambda0 + 2 mu0) s)
        // conj(m) (m . r)) / (mu0 s): the isotropic Green operator of Moulinec & Suquet
        // (1998) in discrete form. Formed per frequency from three axis tables instead of
        // a stored 9-scalar table (36 bytes per voxel less memory and traffic); zero where
        // s = 0 (the mean, and the spectral Nyquist planes' singular frequencies).
        let c0 = self.reference;
        let a = T::of(inv_n / c0.mu);
        let b = T::of((c0.lambda + c0.mu) / (c0.lambda + 2.0 * c0.mu));
        let [gx, gy, gz] = &self.green_axes;
        move |kx, ky, l| {
            if table {
                let line = &pinv[9 * nz * (kx * ny + ky)..9 * nz * (kx * ny + ky + 1)];
                for kz in 0..nz {
                    let p = &line[9 * kz..9 * kz + 9];
                    let o01 = Complex::new(p[3], p[4]);
                    let o02 = Complex::new(p[5], p[6]);
                    let o12 = Complex::new(p[7], p[8]);
                    let (x, y, w) = (l[0][kz], l[1][kz], l[2][kz]);
                    l[0][kz] = x * p[0] + o01 * y + o02 * w;
                    l[1][kz] = o01.conj() * x + y * p[1] + o12 * w;
                    l[2][kz] = o02.conj() * x + o12.conj() * y + w * p[2];
                }
                return;
            }
            let (mx, my) = (gx[kx], gy[ky]);
            let sxy = mx.norm_sqr() + my.norm_sqr();
            // Full runs of LANES frequencies in split real/imaginary arrays (they vectorize;
            // the complex type does not), the rest below. Same operations, in the same
            // order, as the complex expressions of the tail loop.
            let full = nz - nz % LANES;
            for k0 in (0..full).step_by(LANES) {
                let m: [Complex<T>; LANES] = std::array::from_fn(|i| gz[k0 + i]);
                let load = |c: usize| -> ([T; LANES], [T; LANES]) {
                    let v = &l[c][k0..k0 + LANES];
                    (
                        std::array::from_fn(|i| v[i].re),
                        std::array::from_fn(|i| v[i].im),
                    )
                };
                let [(xr, xi), (yr, yi), (wr, wi)] = [load(0), load(1), load(2)];
                let mut out = [[[T::zero(); LANES]; 2]; 3];
                for i in 0..LANES {
                    let (mzr, mzi) = (m[i].re, m[i].im);
                    let s = sxy + (mzr * mzr + mzi * mzi);
                    let is = s.recip();
                    let k = b * is;
                    let g = a * is;
                    let tr = ((mx.re * xr[i] - mx.im * xi[i]) + (my.re * yr[i] - my.im * yi[i]))
                        + (mzr * wr[i] - mzi * wi[i]);
                    let ti = ((mx.re * xi[i] + mx.im * xr[i]) + (my.re * yi[i] + my.im * yr[i]))
                        + (mzr * wi[i] + mzi * wr[i]);
                    let (tr, ti) = (tr * k, ti * k);
                    // conj(m) t with conj(m) = (m.re, -m.im), as num-complex forms it.
                    let part = |mr: T, mi: T, vr: T, vi: T| {
                        let ni = -mi;
                        [
                            (vr - (mr * tr - ni * ti)) * g,
                            (vi - (mr * ti + ni * tr)) * g,
                        ]
                    };
                    let zero = s == T::zero();
                    let pick = |v: [T; 2]| if zero { [T::zero(); 2] } else { v };
                    let [o0, o1, o2] = [
                        pick(part(mx.re, mx.im, xr[i], xi[i])),
                        pick(part(my.re, my.im, yr[i], yi[i])),
                        pick(part(mzr, mzi, wr[i], wi[i])),
                    ];
                    for (c, o) in [o0, o1, o2].into_iter().enumerate() {
                        out[c][0][i] = o[0];
                        out[c][1][i] = o[1];
                    }
                }
                for (c, o) in out.iter().enumerate() {
                    for (i, v) in l[c][k0..k0 + LANES].iter_mut().enumerate() {
                        *v = Complex::new(o[0][i], o[1][i]);
                    }
                }
            }
            for (kz, &mz) in gz.iter().enumerate().skip(full) {
                let s = sxy + mz.norm_sqr();
                if s == T::zero() {
                    l[0][kz] = Complex::new(T::zero(), T::zero());
                    l[1][kz] = Complex::new(T::zero(), T::zero());
                    l[2][kz] = Complex::new(T::zero(), T::zero());
                    continue;
                }
                let is = s.recip();
                let (x, y, w) = (l[0][kz], l[1][kz], l[2][kz]);
                let t = (mx * x + my * y + mz * w) * (b * is);
                let g = a * is;
                l[0][kz] = (x - mx.conj() * t) * g;
                l[1][kz] = (y - my.conj() * t) * g;
                l[2][kz] = (w - mz.conj() * t) * g;
            }
        }
    }
}

/// Frequencies per run of the closed-form Green operator in [`Elastic::green`].
const LANES: usize = 8;

impl<T: Real> CellProblem<T> for Elastic<T> {
    fn unknowns(&self) -> usize {
        3 * self.n
    }

    fn apply(&mut self, u: &[T], load: Option<&[f64]>, out: &mut [T]) {
        match self.scheme {
            Scheme::Staggered => {
                self.staggered_apply(u, load, out, false);
            }
            Scheme::Hex8 | Scheme::Rotated => self.nodal_apply(u, load, out),
            Scheme::Spectral => self.spectral_apply(u, load, out),
        }
    }

    fn apply_dot(&mut self, p: &[T], out: &mut [T]) -> f64 {
        match self.scheme {
            Scheme::Staggered => self.staggered_apply(p, None, out, true),
            _ => {
                self.apply(p, None, out);
                dot(p, out)
            }
        }
    }

    fn precondition(&mut self, r: &[T], z: &mut [T]) {
        let n = self.n;
        let mut spec = std::mem::take(&mut self.spec);
        let (r0, rest) = r.split_at(n);
        let (r1, r2) = rest.split_at(n);
        let (z0, rest) = z.split_at_mut(n);
        let (z1, z2) = rest.split_at_mut(n);
        self.fft
            .filter([r0, r1, r2], [z0, z1, z2], &mut spec, self.green());
        self.spec = spec;
    }

    fn precondition_dot(&mut self, step: Option<(f64, &[T])>, r: &mut [T], z: &mut [T]) -> f64 {
        let n = self.n;
        let nxy = self.dims[0] * self.dims[1];
        let mut spec = std::mem::take(&mut self.spec);
        let (r0, rest) = r.split_at_mut(n);
        let (r1, r2) = rest.split_at_mut(n);
        let (z0, rest) = z.split_at_mut(n);
        let (z1, z2) = rest.split_at_mut(n);
        let step = step.map(|(a, q)| (T::of(a), q));
        // Same formula per element as a separate `r -= alpha q` sweep.
        let pre = |c: usize, z: usize, plane: &mut [T]| {
            if let Some((a, q)) = step {
                let q = &q[c * n + z * nxy..c * n + (z + 1) * nxy];
                plane.iter_mut().zip(q).for_each(|(r, &q)| *r = *r - a * q);
            }
        };
        let post = |_: usize, _: usize, r: &[T], z: &[T]| dot_lanes(r, z);
        let rz = self.fft.filter_fused(
            [r0, r1, r2],
            [z0, z1, z2],
            &mut spec,
            self.green(),
            pre,
            post,
        );
        self.spec = spec;
        rz
    }

    fn load_energy(&self, load: &[f64]) -> f64 {
        let c = self.reference.voigt();
        let mut e = 0.0;
        for a in 0..6 {
            for b in 0..6 {
                e += load[a] * c[a][b] * load[b];
            }
        }
        e * self.n as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The preconditioner (fused FFT filter; closed-form Green operator for staggered and
    /// spectral, reordered table for the nodal schemes) against the textbook route: forward
    /// FFT, `hermitian_inverse` of `K0` per frequency, inverse FFT, `1/N`.
    #[test]
    fn preconditioner_matches_explicit_inverse() {
        let dims = [6, 5, 4];
        let n: usize = dims.iter().product();
        let h = [1.0, 0.8, 1.3];
        let labels: Vec<u8> = (0..n).map(|i| (i * 7 % 3) as u8).collect();
        let mut mats = [Iso::ZERO; 256];
        mats[1] = Iso::from_e_nu(2.0, 0.25);
        mats[2] = Iso::from_e_nu(1.0, 0.3);
        let c0 = Iso::from_e_nu(1.5, 0.2);
        let r: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.61).sin()).collect();
        for scheme in [
            Scheme::Staggered,
            Scheme::Spectral,
            Scheme::Hex8,
            Scheme::Rotated,
        ] {
            let mut p = Elastic::<f64>::new(dims, h, labels.clone(), mats, scheme, c0);
            let mut z = vec![0.0; 3 * n];
            p.precondition(&r, &mut z);
            let f = Fft3::<f64>::new(dims);
            let (nkx, sl) = (f.nkx, f.spectrum_len());
            let mut spec = vec![Complex::new(0.0, 0.0); 3 * sl];
            for c in 0..3 {
                f.forward(&r[c * n..(c + 1) * n], &mut spec[c * sl..(c + 1) * sl]);
            }
            let scale = (c0.lambda + 2.0 * c0.mu) * 12.0 / (0.8 * 0.8);
            for kz in 0..dims[2] {
                for ky in 0..dims[1] {
                    for kx in 0..nkx {
                        let k = p.reference_symbol(kx, ky, kz);
                        let v = hermitian_inverse(k, 1e-12 * scale);
                        let m = [
                            [
                                C64::new(v[0], 0.0),
                                C64::new(v[3], v[4]),
                                C64::new(v[5], v[6]),
                            ],
                            [
                                C64::new(v[3], -v[4]),
                                C64::new(v[1], 0.0),
                                C64::new(v[7], v[8]),
                            ],
                            [
                                C64::new(v[5], -v[6]),
                                C64::new(v[7], -v[8]),
                                C64::new(v[2], 0.0),
                            ],
                        ];
                        let i = kx + nkx * (ky + dims[1] * kz);
                        let x = [spec[i], spec[sl + i], spec[2 * sl + i]];
                        for a in 0..3 {
                            spec[a * sl + i] = m[a][0] * x[0] + m[a][1] * x[1] + m[a][2] * x[2];
                        }
                    }
                }
            }
            let mut want = vec![0.0; 3 * n];
            for c in 0..3 {
                f.inverse(
                    &mut spec[c * sl..(c + 1) * sl],
                    &mut want[c * n..(c + 1) * n],
                );
            }
            let top = want.iter().fold(0.0f64, |a, v| a.max(v.abs())) / n as f64;
            for i in 0..3 * n {
                assert!(
                    (z[i] - want[i] / n as f64).abs() <= 1e-12 * top,
                    "{scheme:?} at {i}: {} vs {}",
                    z[i],
                    want[i] / n as f64
                );
            }
        }
    }

    /// The stored element stiffness of the nodal schemes against the quadrature it replaces
    /// in CG iterations: `K u` with no load (matrix route) equals `K u` with a zero load
    /// (quadrature route) to round-off, on anisotropic voxels and three phases with pores;
    /// and each element matrix is symmetric with the six rigid motions in its null space.
    #[test]
    fn nodal_element_matrices_match_quadrature() {
        let dims = [5, 4, 6];
        let n: usize = dims.iter().product();
        let h = [1.0, 0.7, 1.4];
        let labels: Vec<u8> = (0..n).map(|i| (i * 5 % 3) as u8).collect();
        let mut mats = [Iso::ZERO; 256];
        mats[1] = Iso::from_e_nu(3.0, 0.25);
        mats[2] = Iso::from_e_nu(1.0, 0.35);
        let c0 = Iso::from_e_nu(2.0, 0.3);
        let u: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.37).cos()).collect();
        for scheme in [Scheme::Hex8, Scheme::Rotated] {
            let mut p = Elastic::<f64>::new(dims, h, labels.clone(), mats, scheme, c0);
            let (mut by_matrix, mut by_quadrature) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
            p.apply(&u, None, &mut by_matrix);
            p.apply(&u, Some(&[0.0; 6]), &mut by_quadrature);
            let scale = by_quadrature.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (a, b) in by_matrix.iter().zip(&by_quadrature) {
                assert!((a - b).abs() <= 1e-12 * scale, "{scheme:?}: {a} vs {b}");
            }
            for l in [1usize, 2] {
                let k = &p.element_matrices[l];
                let kij = |i: usize, j: usize| k[j * 24 + i];
                let big = k.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                for i in 0..24 {
                    for j in 0..24 {
                        assert!((kij(i, j) - kij(j, i)).abs() <= 1e-12 * big);
                    }
                }
                // Node k at (k & 1, k >> 1 & 1, k >> 2) h: translations and infinitesimal
                // rotations u = w x r.
                let pos = |k: usize| {
                    [
                        (k & 1) as f64 * h[0],
                        (k >> 1 & 1) as f64 * h[1],
                        (k >> 2) as f64 * h[2],
                    ]
                };
                let mut motions: Vec<[f64; 24]> = vec![];
                for c in 0..3 {
                    let mut m = [0.0; 24];
                    (0..8).for_each(|k| m[c * 8 + k] = 1.0);
                    motions.push(m);
                }
                for (a, b) in [(1, 2), (2, 0), (0, 1)] {
                    let mut m = [0.0; 24];
                    for k in 0..8 {
                        m[a * 8 + k] = -pos(k)[b];
                        m[b * 8 + k] = pos(k)[a];
                    }
                    motions.push(m);
                }
                for m in motions {
                    for i in 0..24 {
                        let f: f64 = (0..24).map(|j| kij(i, j) * m[j]).sum();
                        assert!(f.abs() <= 1e-12 * big, "{scheme:?}: rigid motion gives {f}");
                    }
                }
            }
            assert!(p.element_matrices[0].is_empty(), "pores need no matrix");
        }
    }
    /// The closed-form reference symbol against the product `B^H C0 B` with the full Voigt
    /// matrix, for every scheme at every frequency of a small anisotropic grid.
    #[test]
    fn reference_symbol_matches_the_voigt_product() {
        let dims = [5, 4, 6];
        let n: usize = dims.iter().product();
        let h = [1.0, 0.7, 1.4];
        let mats = [Iso::from_e_nu(1.0, 0.3); 256];
        let c0 = Iso::from_e_nu(2.0, 0.2);
        for scheme in [
            Scheme::Staggered,
            Scheme::Spectral,
            Scheme::Hex8,
            Scheme::Rotated,
        ] {
            let p = Elastic::<f64>::new(dims, h, vec![1; n], mats, scheme, c0);
            let c = c0.voigt();
            for kx in 0..p.fft.nkx {
                for ky in 0..dims[1] {
                    for kz in 0..dims[2] {
                        let mut want = [[C64::new(0.0, 0.0); 3]; 3];
                        for (nm, sh, w) in p.symbol_points(kx, ky, kz) {
                            let z = C64::new(0.0, 0.0);
                            let rows = [
                                [nm[0], z, z],
                                [z, nm[1], z],
                                [z, z, nm[2]],
                                [z, sh[2], sh[1]],
                                [sh[2], z, sh[0]],
                                [sh[1], sh[0], z],
                            ];
                            for a in 0..3 {
                                for b in 0..3 {
                                    for i in 0..6 {
                                        for j in 0..6 {
                                            want[a][b] +=
                                                rows[i][a].conj() * c[i][j] * rows[j][b] * w;
                                        }
                                    }
                                }
                            }
                        }
                        let got = p.reference_symbol(kx, ky, kz);
                        for a in 0..3 {
                            for b in 0..3 {
                                assert!(
                                    (got[a][b] - want[a][b]).norm()
                                        <= 1e-12 * (1.0 + want[a][b].norm()),
                                    "{scheme:?} ({kx},{ky},{kz}) [{a}][{b}]: {} vs {}",
                                    got[a][b],
                                    want[a][b]
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn fused_preconditioner_matches_its_definition() {
        let dims = [6, 5, 4];
        let n: usize = dims.iter().product();
        let labels: Vec<u8> = (0..n).map(|i| (i * 7 % 3) as u8).collect();
        let mut mats = [Iso::ZERO; 256];
        mats[1] = Iso::from_e_nu(2.0, 0.25);
        mats[2] = Iso::from_e_nu(1.0, 0.3);
        let c0 = Iso::from_e_nu(1.5, 0.2);
        for scheme in [Scheme::Staggered, Scheme::Hex8] {
            let mut p =
                Elastic::<f64>::new(dims, [1.0, 0.8, 1.3], labels.clone(), mats, scheme, c0);
            crate::kernel::solver::check_precondition_dot(&mut p, 0.61);
        }
    }
}
