//! The scalar (thermal conduction) cell problem: find a periodic temperature fluctuation
//! `t` with `div k(x) (G + grad t) = 0` for a macroscopic gradient `G`, in the form
//! `K t = -B^T k G`, `K = B^T k B`; the apparent conductivity maps `G` to the mean of
//! `k (G + grad t)` (the flux with its sign flipped). Same discretizations as the elastic
//! problem: staggered = finite volumes with temperatures at voxel centres and the harmonic
//! mean of the two voxel conductivities on each face (exact for laminates in series); hex8
//! and rotated = nodal trilinear elements with 8 or 1 Gauss points; spectral = Fourier
//! derivatives at voxel centres. Zero-conductivity pores leave `t` undetermined inside them;
//! the flux is unique (see `elastic`).

use num_complex::Complex;
use rayon::prelude::*;

use super::composite::Composite;
use super::solver::CellProblem;
use super::{edge_weights, gauss_points, nodal_gradient, AxisTables, Scheme, C64};
use crate::fft3::Fft3;
use crate::real::Real;
use std::sync::Arc;

/// Bytes per voxel of the solver state (as [`super::elastic::bytes_per_voxel`]).
pub fn bytes_per_voxel(scheme: Scheme, cg: bool, real: usize) -> f64 {
    let vectors = if cg { 5.0 } else { 3.0 };
    let scratch = match scheme {
        Scheme::Staggered => 3.0 + 3.0 + 1.0,
        Scheme::Hex8 | Scheme::Rotated => 1.0 + 1.0,
        Scheme::Spectral => 3.0 + 2.0,
    };
    (vectors + scratch + 0.5) * real as f64 + 1.0
}

pub struct Scalar<T: Real> {
    pub dims: [usize; 3],
    pub h: [f64; 3],
    pub scheme: Scheme,
    n: usize,
    labels: Vec<u8>,
    k: [T; 256],
    kf: [f64; 256],
    /// Staggered: face conductivities (x, y, z faces).
    face_k: Vec<T>,
    reference: f64,
    fft: Fft3<T>,
    pinv: Vec<T>,
    spec: Vec<Complex<T>>,
    scratch: Vec<T>,
    gauss: Vec<([f64; 3], f64)>,
    tables: [AxisTables; 3],
    /// Composite voxels (laminate conductivity tensors), `None` for a labels-only image.
    composite: Option<Arc<Composite<[[f64; 3]; 3]>>>,
}

impl<T: Real> Scalar<T> {
    pub fn new(
        dims: [usize; 3],
        h: [f64; 3],
        labels: Vec<u8>,
        conductivities: [f64; 256],
        scheme: Scheme,
        reference: f64,
    ) -> Self {
        let n: usize = dims.iter().product();
        assert_eq!(labels.len(), n);
        let fft = Fft3::<T>::new(dims);
        let nkx = fft.nkx;
        let tables = [
            AxisTables::new(nkx, dims[0], h[0]),
            AxisTables::new(dims[1], dims[1], h[1]),
            AxisTables::new(dims[2], dims[2], h[2]),
        ];
        let sl = fft.spectrum_len();
        let (spec_n, scratch_n) = match scheme {
            Scheme::Staggered => (sl, 3 * n),
            Scheme::Hex8 | Scheme::Rotated => (sl, n),
            Scheme::Spectral => (2 * sl, 3 * n),
        };
        let mut p = Scalar {
            dims,
            h,
            scheme,
            n,
            labels,
            k: conductivities.map(T::of),
            kf: conductivities,
            face_k: vec![],
            reference,
            fft,
            pinv: vec![],
            spec: vec![Complex::new(T::zero(), T::zero()); spec_n],
            scratch: vec![T::zero(); scratch_n],
            gauss: gauss_points(scheme),
            tables,
            composite: None,
        };
        if scheme == Scheme::Staggered {
            p.face_k = p.face_conductivities();
        }
        p.pinv = p.reference_inverse();
        p
    }

    #[inline(always)]
    fn idx(&self, x: usize, y: usize, z: usize) -> usize {
        x + self.dims[0] * (y + self.dims[1] * z)
    }

    /// Gives the voxels of `composite` their laminate conductivity tensor, applied at the
    /// Gauss points of the nodal schemes (hex8, rotated); see
    /// [`super::elastic::Elastic::set_composite`] for why the other schemes are refused.
    pub fn set_composite(&mut self, composite: Arc<Composite<[[f64; 3]; 3]>>) {
        assert_eq!(composite.slot.len(), self.n);
        assert!(
            self.scheme != Scheme::Spectral,
            "composite voxels need a local scheme"
        );
        self.composite = Some(composite);
        if self.scheme == Scheme::Staggered {
            self.face_k = self.face_conductivities();
        }
    }

    /// Conductivity tensor of voxel `v`.
    #[inline]
    fn voxel_k(&self, v: usize) -> [[f64; 3]; 3] {
        match self.composite.as_ref().and_then(|c| c.get(v)) {
            Some(k) => *k,
            None => {
                let k = self.kf[self.labels[v] as usize];
                [[k, 0.0, 0.0], [0.0, k, 0.0], [0.0, 0.0, k]]
            }
        }
    }

    /// Harmonic mean of the two voxels of each face (`i + e_d / 2`): exact in series.
    fn face_conductivities(&self) -> Vec<T> {
        let [nx, ny, nz] = self.dims;
        let mut out = vec![T::zero(); 3 * self.n];
        out.par_chunks_mut(nx * ny)
            .enumerate()
            .for_each(|(j, plane)| {
                let d = j / nz;
                let z = j % nz;
                for y in 0..ny {
                    for x in 0..nx {
                        let mut q = [x, y, z];
                        q[d] = (q[d] + 1) % self.dims[d];
                        let a = self.kf[self.labels[self.idx(x, y, z)] as usize];
                        let b = self.kf[self.labels[self.idx(q[0], q[1], q[2])] as usize];
                        plane[x + nx * y] = if a > 0.0 && b > 0.0 {
                            T::of(2.0 * a * b / (a + b))
                        } else {
                            T::zero()
                        };
                    }
                }
            });
        out
    }

    /// Gradient multipliers at the quadrature points (with weights).
    fn symbol_points(&self, kx: usize, ky: usize, kz: usize) -> Vec<([C64; 3], f64)> {
        let t = &self.tables;
        match self.scheme {
            Scheme::Staggered => vec![([t[0].plus[kx], t[1].plus[ky], t[2].plus[kz]], 1.0)],
            Scheme::Spectral => vec![(
                [t[0].spectral[kx], t[1].spectral[ky], t[2].spectral[kz]],
                1.0,
            )],
            Scheme::Hex8 | Scheme::Rotated => self
                .gauss
                .iter()
                .map(|&(p, w)| {
                    (
                        nodal_gradient(t[0].e[kx], t[1].e[ky], t[2].e[kz], self.h, p),
                        w,
                    )
                })
                .collect(),
        }
    }

    /// `K0^{-1} / N` per frequency in the line order of [`Fft3::filter`] (kz fastest, then ky,
    /// then kx), the `1/N` of the inverse FFT folded in.
    fn reference_inverse(&self) -> Vec<T> {
        let [_, ny, nz] = self.dims;
        let nkx = self.fft.nkx;
        let hmin = self.h.iter().cloned().fold(f64::INFINITY, f64::min);
        let zero_below = 1e-12 * 12.0 * self.reference / (hmin * hmin);
        let inv_n = 1.0 / self.n as f64;
        let mut out = vec![T::zero(); nkx * ny * nz];
        out.par_chunks_mut(nz).enumerate().for_each(|(line, o)| {
            let (kx, ky) = (line / ny, line % ny);
            for (kz, o) in o.iter_mut().enumerate() {
                let k0: f64 = self
                    .symbol_points(kx, ky, kz)
                    .iter()
                    .map(|(g, w)| w * self.reference * g.iter().map(|c| c.norm_sqr()).sum::<f64>())
                    .sum();
                *o = if k0 > zero_below {
                    T::of(inv_n / k0)
                } else {
                    T::zero()
                };
            }
        });
        out
    }

    fn staggered_apply(&mut self, t: &[T], load: Option<&[f64]>, out: &mut [T]) {
        let [nx, ny, nz] = self.dims;
        let n = self.n;
        let nxy = nx * ny;
        let g: [T; 3] = match load {
            Some(l) => std::array::from_fn(|k| T::of(l[k])),
            None => [T::zero(); 3],
        };
        let ih = self.h.map(|h| T::of(1.0 / h));
        let mut scratch = std::mem::take(&mut self.scratch);
        let this = &*self;
        // Face fluxes k_f (G_d + (t[i + e_d] - t[i]) / h_d).
        scratch.par_chunks_mut(nxy).enumerate().for_each(|(j, o)| {
            let d = j / nz;
            let z = j % nz;
            let zp = if z + 1 == nz { 0 } else { z + 1 };
            for y in 0..ny {
                let yp = if y + 1 == ny { 0 } else { y + 1 };
                let a = row_of(t, nx, ny, y, z);
                let kf = &this.face_k[d * n + nx * (y + ny * z)..][..nx];
                let o = &mut o[nx * y..nx * y + nx];
                match d {
                    0 => {
                        for x in 0..nx {
                            let xp = if x + 1 == nx { 0 } else { x + 1 };
                            o[x] = kf[x] * ((a[xp] - a[x]) * ih[0] + g[0]);
                        }
                    }
                    1 => {
                        let b = row_of(t, nx, ny, yp, z);
                        for x in 0..nx {
                            o[x] = kf[x] * ((b[x] - a[x]) * ih[1] + g[1]);
                        }
                    }
                    _ => {
                        let b = row_of(t, nx, ny, y, zp);
                        for x in 0..nx {
                            o[x] = kf[x] * ((b[x] - a[x]) * ih[2] + g[2]);
                        }
                    }
                }
            }
        });
        // B^T q: (q_d[m - e_d] - q_d[m]) / h_d summed.
        out.par_chunks_mut(nxy).enumerate().for_each(|(z, o)| {
            let zm = if z == 0 { nz - 1 } else { z - 1 };
            for y in 0..ny {
                let ym = if y == 0 { ny - 1 } else { y - 1 };
                let qx = row_of(&scratch[..n], nx, ny, y, z);
                let qy = row_of(&scratch[n..2 * n], nx, ny, y, z);
                let qym = row_of(&scratch[n..2 * n], nx, ny, ym, z);
                let qz = row_of(&scratch[2 * n..], nx, ny, y, z);
                let qzm = row_of(&scratch[2 * n..], nx, ny, y, zm);
                let o = &mut o[nx * y..nx * y + nx];
                for x in 0..nx {
                    let xm = if x == 0 { nx - 1 } else { x - 1 };
                    o[x] = (qx[xm] - qx[x]) * ih[0]
                        + (qym[x] - qy[x]) * ih[1]
                        + (qzm[x] - qz[x]) * ih[2];
                }
            }
        });
        self.scratch = scratch;
    }

    fn nodal_apply(&mut self, t: &[T], load: Option<&[f64]>, out: &mut [T]) {
        let [nx, ny, nz] = self.dims;
        let nxy = nx * ny;
        let g: [T; 3] = match load {
            Some(l) => std::array::from_fn(|k| T::of(l[k])),
            None => [T::zero(); 3],
        };
        let ih = self.h.map(|h| T::of(1.0 / h));
        let gauss: Vec<([[T; 2]; 3], T)> = self
            .gauss
            .iter()
            .map(|&(p, w)| {
                (
                    [0, 1, 2].map(|a| [T::of(1.0 - p[a]), T::of(p[a])]),
                    T::of(w),
                )
            })
            .collect();
        let mut scratch = std::mem::take(&mut self.scratch);
        let this = &*self;
        // Each element plane z writes its bottom nodes into `out` plane z and its top nodes
        // into `scratch` plane z (disjoint chunks), summed afterwards in a fixed order.
        out.par_chunks_mut(nxy)
            .zip(scratch.par_chunks_mut(nxy))
            .enumerate()
            .for_each(|(z, (bottom, top))| {
                bottom.iter_mut().for_each(|v| *v = T::zero());
                top.iter_mut().for_each(|v| *v = T::zero());
                let zp = (z + 1) % nz;
                for y in 0..ny {
                    let yp = (y + 1) % ny;
                    for x in 0..nx {
                        let xp = (x + 1) % nx;
                        let v = this.idx(x, y, z);
                        let kc = this.composite.as_ref().and_then(|c| c.get(v));
                        let k = this.k[this.labels[v] as usize];
                        if kc.is_none() && k == T::zero() {
                            continue;
                        }
                        let kt: Option<[[T; 3]; 3]> = kc.map(|m| m.map(|r| r.map(T::of)));
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
                        let te: [T; 8] = std::array::from_fn(|q| t[nodes[q]]);
                        // differences along each axis on its 4 edges (index a + 2 b)
                        let mut d = [[T::zero(); 4]; 3];
                        for a in 0..2 {
                            for b in 0..2 {
                                d[0][a + 2 * b] =
                                    (te[1 + 2 * a + 4 * b] - te[2 * a + 4 * b]) * ih[0];
                                d[1][a + 2 * b] = (te[a + 2 + 4 * b] - te[a + 4 * b]) * ih[1];
                                d[2][a + 2 * b] = (te[a + 2 * b + 4] - te[a + 2 * b]) * ih[2];
                            }
                        }
                        let mut f = [[T::zero(); 4]; 3];
                        for (wt, w) in &gauss {
                            let ws = edge_weights(wt);
                            let gr: [T; 3] = std::array::from_fn(|ax| {
                                d[ax][0] * ws[ax][0]
                                    + d[ax][1] * ws[ax][1]
                                    + d[ax][2] * ws[ax][2]
                                    + d[ax][3] * ws[ax][3]
                                    + g[ax]
                            });
                            for ax in 0..3 {
                                let flux = match &kt {
                                    Some(m) => {
                                        m[ax][0] * gr[0] + m[ax][1] * gr[1] + m[ax][2] * gr[2]
                                    }
                                    None => k * gr[ax],
                                };
                                let q = *w * flux;
                                for e in 0..4 {
                                    f[ax][e] = f[ax][e] + q * ws[ax][e];
                                }
                            }
                        }
                        let mut fnode = [T::zero(); 8];
                        for a in 0..2 {
                            for b in 0..2 {
                                let e = a + 2 * b;
                                let fx = f[0][e] * ih[0];
                                fnode[1 + 2 * a + 4 * b] = fnode[1 + 2 * a + 4 * b] + fx;
                                fnode[2 * a + 4 * b] = fnode[2 * a + 4 * b] - fx;
                                let fy = f[1][e] * ih[1];
                                fnode[a + 2 + 4 * b] = fnode[a + 2 + 4 * b] + fy;
                                fnode[a + 4 * b] = fnode[a + 4 * b] - fy;
                                let fz = f[2][e] * ih[2];
                                fnode[a + 2 * b + 4] = fnode[a + 2 * b + 4] + fz;
                                fnode[a + 2 * b] = fnode[a + 2 * b] - fz;
                            }
                        }
                        for q in 0..8 {
                            let pi = nodes[q] % nxy;
                            if q < 4 {
                                bottom[pi] = bottom[pi] + fnode[q];
                            } else {
                                top[pi] = top[pi] + fnode[q];
                            }
                        }
                    }
                }
            });
        out.par_chunks_mut(nxy).enumerate().for_each(|(z, o)| {
            let zm = (z + nz - 1) % nz;
            let tp = &scratch[zm * nxy..zm * nxy + nxy];
            o.iter_mut().zip(tp).for_each(|(o, &t)| *o = *o + t);
        });
        self.scratch = scratch;
    }

    /// Spectral: gradients of `t` (without the load) at the voxel centres into `scratch`.
    fn spectral_gradient(&mut self, t: &[T]) {
        let n = self.n;
        let sl = self.fft.spectrum_len();
        let [_, ny, _] = self.dims;
        let nkx = self.fft.nkx;
        let mut spec = std::mem::take(&mut self.spec);
        let mut scratch = std::mem::take(&mut self.scratch);
        let (that, work) = spec.split_at_mut(sl);
        self.fft.forward(t, that);
        let inv_n = T::of(1.0 / n as f64);
        for d in 0..3 {
            let that = &*that;
            work.par_chunks_mut(nkx).enumerate().for_each(|(row, w)| {
                let (ky, kz) = (row % ny, row / ny);
                for kx in 0..nkx {
                    let g = self.tables[d].spectral[[kx, ky, kz][d]];
                    w[kx] = Complex::new(T::of(g.re), T::of(g.im)) * that[kx + nkx * row];
                }
            });
            self.fft.inverse(work, &mut scratch[d * n..(d + 1) * n]);
            scratch[d * n..(d + 1) * n]
                .par_iter_mut()
                .for_each(|v| *v = *v * inv_n);
        }
        self.spec = spec;
        self.scratch = scratch;
    }

    fn spectral_apply(&mut self, t: &[T], load: Option<&[f64]>, out: &mut [T]) {
        let n = self.n;
        let sl = self.fft.spectrum_len();
        let [_, ny, _] = self.dims;
        let nkx = self.fft.nkx;
        self.spectral_gradient(t);
        let g: [T; 3] = match load {
            Some(l) => std::array::from_fn(|k| T::of(l[k])),
            None => [T::zero(); 3],
        };
        for d in 0..3 {
            let (k, labels) = (&self.k, &self.labels);
            self.scratch[d * n..(d + 1) * n]
                .par_iter_mut()
                .enumerate()
                .for_each(|(i, v)| *v = k[labels[i] as usize] * (*v + g[d]));
        }
        let mut spec = std::mem::take(&mut self.spec);
        let (acc, work) = spec.split_at_mut(sl);
        acc.par_iter_mut()
            .for_each(|v| *v = Complex::new(T::zero(), T::zero()));
        for d in 0..3 {
            self.fft.forward(&self.scratch[d * n..(d + 1) * n], work);
            let work = &*work;
            acc.par_chunks_mut(nkx).enumerate().for_each(|(row, a)| {
                let (ky, kz) = (row % ny, row / ny);
                for kx in 0..nkx {
                    let gm = self.tables[d].spectral[[kx, ky, kz][d]].conj();
                    a[kx] = a[kx] + Complex::new(T::of(gm.re), T::of(gm.im)) * work[kx + nkx * row];
                }
            });
        }
        self.fft.inverse(acc, out);
        let inv_n = T::of(1.0 / n as f64);
        out.par_iter_mut().for_each(|v| *v = *v * inv_n);
        self.spec = spec;
    }

    /// Per label: the summed flux `k (G + grad t)` (voxel values: staggered = mean of the
    /// voxel's two faces per axis, nodal = Gauss-weighted mean) and the voxel count; the
    /// voxel fluxes average to the exact mean flux.
    pub fn flux_stats(&mut self, t: &[T], load: &[f64]) -> Vec<([f64; 3], u64)> {
        let [nx, ny, nz] = self.dims;
        if self.scheme == Scheme::Spectral {
            self.spectral_gradient(t);
        }
        let this = &*self;
        let per_plane: Vec<Vec<([f64; 3], u64)>> = (0..nz)
            .into_par_iter()
            .map(|z| {
                let mut acc = vec![([0.0; 3], 0u64); 256];
                for y in 0..ny {
                    for x in 0..nx {
                        let i = this.idx(x, y, z);
                        let l = this.labels[i] as usize;
                        let q = this.voxel_flux(t, load, x, y, z);
                        for d in 0..3 {
                            acc[l].0[d] += q[d];
                        }
                        acc[l].1 += 1;
                    }
                }
                acc
            })
            .collect();
        let mut total = vec![([0.0; 3], 0u64); 256];
        for acc in per_plane {
            for l in 0..256 {
                for d in 0..3 {
                    total[l].0[d] += acc[l].0[d];
                }
                total[l].1 += acc[l].1;
            }
        }
        total
    }

    fn voxel_flux(&self, t: &[T], load: &[f64], x: usize, y: usize, z: usize) -> [f64; 3] {
        let [nx, ny, nz] = self.dims;
        let n = self.n;
        let i = self.idx(x, y, z);
        let k = self.kf[self.labels[i] as usize];
        let kt = self.voxel_k(i);
        let tv = |j: usize| t[j].f64();
        match self.scheme {
            Scheme::Staggered => {
                let mut q = [0.0; 3];
                let c = [x, y, z];
                for d in 0..3 {
                    // faces i + e_d / 2 and i - e_d / 2, each shared by two voxels
                    let mut cp = c;
                    cp[d] = (c[d] + 1) % self.dims[d];
                    let mut cm = c;
                    cm[d] = (c[d] + self.dims[d] - 1) % self.dims[d];
                    let jp = self.idx(cp[0], cp[1], cp[2]);
                    let jm = self.idx(cm[0], cm[1], cm[2]);
                    let ih = 1.0 / self.h[d];
                    let fp = self.face_k[d * n + i].f64() * ((tv(jp) - tv(i)) * ih + load[d]);
                    let fm = self.face_k[d * n + jm].f64() * ((tv(i) - tv(jm)) * ih + load[d]);
                    q[d] = 0.5 * (fp + fm);
                }
                q
            }
            Scheme::Spectral => {
                std::array::from_fn(|d| k * (self.scratch[d * n + i].f64() + load[d]))
            }
            Scheme::Hex8 | Scheme::Rotated => {
                let (xp, yp, zp) = ((x + 1) % nx, (y + 1) % ny, (z + 1) % nz);
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
                let mut q = [0.0; 3];
                for &(p, w) in &self.gauss {
                    let mut gr = [load[0], load[1], load[2]];
                    for (m, &node) in nodes.iter().enumerate() {
                        let (dx, dy, dz) = (m & 1, (m >> 1) & 1, (m >> 2) & 1);
                        let s = |d: usize, t: f64| if d == 1 { t } else { 1.0 - t };
                        let ds = |d: usize| if d == 1 { 1.0 } else { -1.0 };
                        let grad = [
                            ds(dx) / self.h[0] * s(dy, p[1]) * s(dz, p[2]),
                            ds(dy) / self.h[1] * s(dx, p[0]) * s(dz, p[2]),
                            ds(dz) / self.h[2] * s(dx, p[0]) * s(dy, p[1]),
                        ];
                        for d in 0..3 {
                            gr[d] += grad[d] * tv(node);
                        }
                    }
                    for d in 0..3 {
                        q[d] += w * (kt[d][0] * gr[0] + kt[d][1] * gr[1] + kt[d][2] * gr[2]);
                    }
                }
                q
            }
        }
    }
}

#[inline(always)]
fn row_of<T>(a: &[T], nx: usize, ny: usize, y: usize, z: usize) -> &[T] {
    let b = nx * (y + ny * z);
    &a[b..b + nx]
}

impl<T: Real> CellProblem<T> for Scalar<T> {
    fn unknowns(&self) -> usize {
        self.n
    }
    fn apply(&mut self, t: &[T], load: Option<&[f64]>, out: &mut [T]) {
        match self.scheme {
            Scheme::Staggered => self.staggered_apply(t, load, out),
            Scheme::Hex8 | Scheme::Rotated => self.nodal_apply(t, load, out),
            Scheme::Spectral => self.spectral_apply(t, load, out),
        }
    }
    fn precondition(&mut self, r: &[T], z: &mut [T]) {
        let mut spec = std::mem::take(&mut self.spec);
        let [_, ny, nz] = self.dims;
        let pinv = &self.pinv;
        self.fft.filter([r], [z], &mut spec, |kx, ky, l| {
            let p = &pinv[nz * (kx * ny + ky)..nz * (kx * ny + ky + 1)];
            l[0].iter_mut().zip(p).for_each(|(v, &p)| *v = *v * p);
        });
        self.spec = spec;
    }
    fn load_energy(&self, load: &[f64]) -> f64 {
        self.reference * load.iter().map(|g| g * g).sum::<f64>() * self.n as f64
    }
}
