//! Periodic 3-D real-to-complex FFT on an x-fastest voxel array (`index = x + nx (y + ny z)`),
//! built from realfft (x lines) and rustfft (y and z lines), parallel over independent lines
//! with rayon. Every line is transformed by the same plan whatever the thread count, so the
//! results are bit-identical across thread counts.

use num_complex::Complex;
use rayon::prelude::*;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::{Fft, FftPlanner};
use std::sync::Arc;

use crate::real::Real;

/// Plans for one grid. The half spectrum has `(nx/2 + 1) * ny * nz` entries, kx fastest.
pub struct Fft3<T: Real> {
    pub dims: [usize; 3],
    /// nx / 2 + 1.
    pub nkx: usize,
    r2c: Arc<dyn RealToComplex<T>>,
    c2r: Arc<dyn ComplexToReal<T>>,
    fy: Arc<dyn Fft<T>>,
    iy: Arc<dyn Fft<T>>,
    fz: Arc<dyn Fft<T>>,
    iz: Arc<dyn Fft<T>>,
}

impl<T: Real> Fft3<T> {
    pub fn new(dims: [usize; 3]) -> Self {
        let mut rp = RealFftPlanner::<T>::new();
        let mut cp = FftPlanner::<T>::new();
        Fft3 {
            dims,
            nkx: dims[0] / 2 + 1,
            r2c: rp.plan_fft_forward(dims[0]),
            c2r: rp.plan_fft_inverse(dims[0]),
            fy: cp.plan_fft_forward(dims[1]),
            iy: cp.plan_fft_inverse(dims[1]),
            fz: cp.plan_fft_forward(dims[2]),
            iz: cp.plan_fft_inverse(dims[2]),
        }
    }

    /// Number of complex entries of the half spectrum.
    pub fn spectrum_len(&self) -> usize {
        self.nkx * self.dims[1] * self.dims[2]
    }

    /// Forward transform (unnormalized) of `input` into `out`.
    pub fn forward(&self, input: &[T], out: &mut [Complex<T>]) {
        let [nx, ny, _] = self.dims;
        let nkx = self.nkx;
        // x lines: real to complex.
        out.par_chunks_mut(nkx * ny)
            .zip(input.par_chunks(nx * ny))
            .for_each(|(o, i)| {
                let mut line = self.r2c.make_input_vec();
                let mut scratch = self.r2c.make_scratch_vec();
                for y in 0..ny {
                    line.copy_from_slice(&i[y * nx..(y + 1) * nx]);
                    self.r2c
                        .process_with_scratch(
                            &mut line,
                            &mut o[y * nkx..(y + 1) * nkx],
                            &mut scratch,
                        )
                        .expect("realfft buffer sizes follow the plan");
                }
            });
        self.yz(out, true);
    }

    /// Inverse transform (unnormalized: the result is `N` times the original) of `spec` into
    /// `out`; `spec` is used as scratch.
    pub fn inverse(&self, spec: &mut [Complex<T>], out: &mut [T]) {
        let [nx, ny, _] = self.dims;
        let nkx = self.nkx;
        self.yz(spec, false);
        out.par_chunks_mut(nx * ny)
            .zip(spec.par_chunks_mut(nkx * ny))
            .for_each(|(o, s)| {
                let mut scratch = self.c2r.make_scratch_vec();
                for y in 0..ny {
                    let line = &mut s[y * nkx..(y + 1) * nkx];
                    // The imaginary parts of the zero and Nyquist bins of a real signal's
                    // spectrum are zero up to round-off; realfft refuses them otherwise.
                    line[0].im = T::zero();
                    if nx % 2 == 0 {
                        line[nkx - 1].im = T::zero();
                    }
                    self.c2r
                        .process_with_scratch(line, &mut o[y * nx..(y + 1) * nx], &mut scratch)
                        .expect("realfft buffer sizes follow the plan");
                }
            });
    }

    /// Applies a Fourier multiplier to `C` real fields at once: `output_c = F^-1 [f(F input)]_c`
    /// with `f` acting on the z lines of the half spectrum, `f(kx, ky, lines)` where
    /// `lines[c][kz]` is component `c` at frequency (kx, ky, kz). The result carries the
    /// factor `N` of the unnormalized inverse, so `f` should fold in `1/N`.
    ///
    /// Why not `forward` + multiply + `inverse`: the multiplier is local in frequency, so the
    /// spectrum may stay in whatever layout suits the transforms. Planes are kept y-transposed
    /// (`[kz][kx][ky]`, ky fastest, `spec` laid out so) and the z transforms, the multiplier
    /// and the inverse z transforms run on one gathered block of lines while it sits in
    /// cache. That removes the y scatter and gather, one z gather and scatter and the separate
    /// multiply and `1/N` sweeps: about 7 of the 12 sweeps of the spectrum per component.
    /// Every line is transformed by the same plan and the blocks are fixed by index, so the
    /// result does not depend on the thread count.
    pub fn filter<const C: usize, F>(
        &self,
        input: [&[T]; C],
        output: [&mut [T]; C],
        spec: &mut [Complex<T>],
        f: F,
    ) where
        F: Fn(usize, usize, &mut [&mut [Complex<T>]; C]) + Sync,
    {
        self.filter_planes(
            Inputs::Shared(input),
            output,
            spec,
            f,
            |_, _, _| {},
            |_, _, _, _| 0.0,
        );
    }

    /// [`Self::filter`] with a hook on each input plane before it is transformed,
    /// `pre(c, z, plane)` (it may rewrite the plane: the input is then updated in place), and
    /// one on each output plane once it is written, `post(c, z, input_plane, output_plane)`,
    /// whose values are summed over the planes in the fixed order (c, z).
    ///
    /// Why: a CG step updates its residual just before preconditioning it and needs
    /// `r . z` right after; done here, each plane of `r` and `z` is touched while it is in
    /// cache for the transforms, instead of in three extra sweeps of the whole vectors. The
    /// plane order of the sum does not depend on the thread count.
    pub fn filter_fused<const C: usize, F, Pre, Post>(
        &self,
        input: [&mut [T]; C],
        output: [&mut [T]; C],
        spec: &mut [Complex<T>],
        f: F,
        pre: Pre,
        post: Post,
    ) -> f64
    where
        F: Fn(usize, usize, &mut [&mut [Complex<T>]; C]) + Sync,
        Pre: Fn(usize, usize, &mut [T]) + Sync,
        Post: Fn(usize, usize, &[T], &[T]) -> f64 + Sync,
    {
        self.filter_planes(Inputs::Owned(input), output, spec, f, pre, post)
    }

    fn filter_planes<const C: usize, F, Pre, Post>(
        &self,
        mut input: Inputs<'_, T, C>,
        output: [&mut [T]; C],
        spec: &mut [Complex<T>],
        f: F,
        pre: Pre,
        post: Post,
    ) -> f64
    where
        F: Fn(usize, usize, &mut [&mut [Complex<T>]; C]) + Sync,
        Pre: Fn(usize, usize, &mut [T]) + Sync,
        Post: Fn(usize, usize, &[T], &[T]) -> f64 + Sync,
    {
        let [nx, ny, nz] = self.dims;
        let nkx = self.nkx;
        let plane = nkx * ny;
        let sl = self.spectrum_len();
        assert!(spec.len() >= C * sl);
        let zero = Complex::new(T::zero(), T::zero());
        let yscratch = self
            .fy
            .get_outofplace_scratch_len()
            .max(self.iy.get_outofplace_scratch_len());
        // x (real to complex) then y, plane by plane, into the transposed plane layout.
        {
            let mut jobs: Vec<PlaneJob<'_, T>> = Vec::with_capacity(C * nz);
            match &mut input {
                Inputs::Shared(i) => {
                    for (c, s) in spec[..C * sl].chunks_mut(sl).enumerate() {
                        jobs.extend(
                            i[c].chunks(nx * ny)
                                .zip(s.chunks_mut(plane))
                                .enumerate()
                                .map(|(z, (i, o))| (c * nz + z, Plane::Shared(i), o)),
                        );
                    }
                }
                Inputs::Owned(i) => {
                    for ((c, s), i) in spec[..C * sl].chunks_mut(sl).enumerate().zip(i.iter_mut()) {
                        jobs.extend(
                            i.chunks_mut(nx * ny)
                                .zip(s.chunks_mut(plane))
                                .enumerate()
                                .map(|(z, (i, o))| (c * nz + z, Plane::Owned(i), o)),
                        );
                    }
                }
            }
            jobs.par_iter_mut().for_each_init(
                || {
                    (
                        self.r2c.make_input_vec(),
                        self.r2c.make_scratch_vec(),
                        vec![zero; plane],
                        vec![zero; plane],
                        vec![zero; yscratch],
                    )
                },
                |(line, xs, rows, cols, ys), (j, i, o)| {
                    let i: &[T] = match i {
                        Plane::Shared(i) => i,
                        Plane::Owned(i) => {
                            pre(*j / nz, *j % nz, i);
                            i
                        }
                    };
                    for y in 0..ny {
                        line.copy_from_slice(&i[y * nx..(y + 1) * nx]);
                        self.r2c
                            .process_with_scratch(line, &mut rows[y * nkx..(y + 1) * nkx], xs)
                            .expect("realfft buffer sizes follow the plan");
                    }
                    transpose(rows, cols, ny, nkx);
                    self.fy.process_outofplace_with_scratch(cols, o, ys);
                },
            );
        }
        // z lines, a block of consecutive (kx, ky) at a time: forward, multiplier, inverse.
        {
            let ptr = SendPtr(spec.as_mut_ptr());
            let zscratch = self
                .fz
                .get_inplace_scratch_len()
                .max(self.iz.get_inplace_scratch_len());
            let blocks = plane.div_ceil(ZBLOCK);
            (0..blocks).into_par_iter().for_each_init(
                || (vec![zero; C * ZBLOCK * nz], vec![zero; zscratch]),
                |(buf, zs), blk| {
                    let p = &ptr;
                    let m0 = blk * ZBLOCK;
                    let bl = ZBLOCK.min(plane - m0);
                    for c in 0..C {
                        let b = &mut buf[c * ZBLOCK * nz..];
                        for z in 0..nz {
                            let at = c * sl + z * plane + m0;
                            for k in 0..bl {
                                // SAFETY: block `blk` alone touches (kx, ky) in m0..m0 + bl.
                                b[k * nz + z] = unsafe { *p.0.add(at + k) };
                            }
                        }
                    }
                    for c in 0..C {
                        let b = &mut buf[c * ZBLOCK * nz..c * ZBLOCK * nz + bl * nz];
                        self.fz.process_with_scratch(b, zs);
                    }
                    for k in 0..bl {
                        let (kx, ky) = ((m0 + k) / ny, (m0 + k) % ny);
                        let mut parts = buf.chunks_mut(ZBLOCK * nz);
                        let mut lines: [&mut [Complex<T>]; C] = std::array::from_fn(|_| {
                            &mut parts.next().expect("C blocks")[k * nz..(k + 1) * nz]
                        });
                        f(kx, ky, &mut lines);
                    }
                    for c in 0..C {
                        let b = &mut buf[c * ZBLOCK * nz..c * ZBLOCK * nz + bl * nz];
                        self.iz.process_with_scratch(b, zs);
                    }
                    for c in 0..C {
                        let b = &buf[c * ZBLOCK * nz..];
                        for z in 0..nz {
                            let at = c * sl + z * plane + m0;
                            for k in 0..bl {
                                // SAFETY: as above.
                                unsafe { *p.0.add(at + k) = b[k * nz + z] };
                            }
                        }
                    }
                },
            );
        }
        // Inverse y then x (complex to real), plane by plane.
        {
            let input: [&[T]; C] = match &input {
                Inputs::Shared(i) => *i,
                Inputs::Owned(i) => std::array::from_fn(|c| &*i[c]),
            };
            let mut jobs: Vec<(&mut [Complex<T>], &mut [T])> = Vec::with_capacity(C * nz);
            for (s, o) in spec[..C * sl].chunks_mut(sl).zip(output) {
                jobs.extend(s.chunks_mut(plane).zip(o.chunks_mut(nx * ny)));
            }
            let sums: Vec<f64> = jobs
                .par_iter_mut()
                .enumerate()
                .map_init(
                    || {
                        (
                            self.c2r.make_scratch_vec(),
                            vec![zero; plane],
                            vec![zero; plane],
                            vec![zero; yscratch],
                        )
                    },
                    |(xs, rows, cols, ys), (j, (s, o))| {
                        self.iy.process_outofplace_with_scratch(s, cols, ys);
                        transpose(cols, rows, nkx, ny);
                        for y in 0..ny {
                            let line = &mut rows[y * nkx..(y + 1) * nkx];
                            // As in `inverse`: realfft refuses round-off imaginary parts there.
                            line[0].im = T::zero();
                            if nx % 2 == 0 {
                                line[nkx - 1].im = T::zero();
                            }
                            self.c2r
                                .process_with_scratch(line, &mut o[y * nx..(y + 1) * nx], xs)
                                .expect("realfft buffer sizes follow the plan");
                        }
                        let (c, z) = (j / nz, j % nz);
                        post(c, z, &input[c][z * nx * ny..(z + 1) * nx * ny], o)
                    },
                )
                .collect();
            sums.iter().sum()
        }
    }

    /// Complex transforms along y (per z plane) and z (per y row).
    fn yz(&self, data: &mut [Complex<T>], forward: bool) {
        let [_, ny, nz] = self.dims;
        let nkx = self.nkx;
        let (fy, fz) = if forward {
            (&self.fy, &self.fz)
        } else {
            (&self.iy, &self.iz)
        };
        if ny > 1 {
            // The transpose buffer and scratch are made once per rayon job, not per plane: at
            // 140^3 a plane buffer is ~160 kB, above glibc's initial mmap threshold, so a fresh
            // `vec!` per plane costs an mmap, page faults and zeroing every time.
            let zero = Complex::new(T::zero(), T::zero());
            data.par_chunks_mut(nkx * ny).for_each_init(
                || {
                    (
                        vec![zero; nkx * ny],
                        vec![zero; fy.get_inplace_scratch_len()],
                    )
                },
                |(buf, scratch), plane| {
                    // Gather the plane transposed (ny contiguous per kx), transform all lines at
                    // once, scatter back.
                    for y in 0..ny {
                        for kx in 0..nkx {
                            buf[kx * ny + y] = plane[y * nkx + kx];
                        }
                    }
                    fy.process_with_scratch(buf, scratch);
                    for y in 0..ny {
                        for kx in 0..nkx {
                            plane[y * nkx + kx] = buf[kx * ny + y];
                        }
                    }
                },
            );
        }
        if nz > 1 {
            // Lines along z have stride nkx * ny; each task owns the rows of one y, so the
            // data is shared through a raw pointer with disjoint index sets.
            let ptr = SendPtr(data.as_mut_ptr());
            let stride = nkx * ny;
            let zero = Complex::new(T::zero(), T::zero());
            (0..ny).into_par_iter().for_each_init(
                || {
                    (
                        vec![zero; nkx * nz],
                        vec![zero; fz.get_inplace_scratch_len()],
                    )
                },
                |(buf, scratch), y| {
                    let p = &ptr;
                    for z in 0..nz {
                        for kx in 0..nkx {
                            // SAFETY: index kx + nkx*y + stride*z is touched only by task y.
                            buf[kx * nz + z] = unsafe { *p.0.add(kx + nkx * y + stride * z) };
                        }
                    }
                    fz.process_with_scratch(buf, scratch);
                    for z in 0..nz {
                        for kx in 0..nkx {
                            // SAFETY: as above, disjoint across tasks.
                            unsafe { *p.0.add(kx + nkx * y + stride * z) = buf[kx * nz + z] };
                        }
                    }
                },
            );
        }
    }
}

/// The input fields of [`Fft3::filter_planes`]: read only, or updated in place by its `pre`.
enum Inputs<'a, T, const C: usize> {
    Shared([&'a [T]; C]),
    Owned([&'a mut [T]; C]),
}

/// Plane index `c * nz + z`, input plane, its spectrum plane.
type PlaneJob<'a, T> = (usize, Plane<'a, T>, &'a mut [Complex<T>]);

/// One z plane of an input field (see [`Inputs`]).
enum Plane<'a, T> {
    Shared(&'a [T]),
    Owned(&'a mut [T]),
}

/// Lines per block of the z pass of [`Fft3::filter`]. Why 64: the gather reads, per plane, a
/// run of 64 consecutive spectrum entries (512 bytes in f32, 1 kB in f64) where 16 gave the
/// hardware prefetcher runs of only 2-4 cache lines between jumps of a plane; the block, 3
/// components x 64 lines x 140 points, is 215 kB (f32) or 430 kB (f64), still inside L2.
/// Measured at 140^3, one thread: the filter of 3 fields takes 0.094-0.096 s instead of
/// 0.106-0.107 s (f32) and 0.134-0.139 s instead of 0.138-0.152 s (f64).
const ZBLOCK: usize = 64;

/// `dst[c * rows + r] = src[r * cols + c]` for a `rows x cols` matrix, in tiles so that both
/// sides stay in L1 for the whole tile.
fn transpose<C: Copy>(src: &[C], dst: &mut [C], rows: usize, cols: usize) {
    const TILE: usize = 8;
    for r0 in (0..rows).step_by(TILE) {
        for c0 in (0..cols).step_by(TILE) {
            for r in r0..(r0 + TILE).min(rows) {
                for c in c0..(c0 + TILE).min(cols) {
                    dst[c * rows + r] = src[r * cols + c];
                }
            }
        }
    }
}

struct SendPtr<C>(*mut C);
// SAFETY: used only with disjoint index sets per task (see `yz`).
unsafe impl<C> Send for SendPtr<C> {}
unsafe impl<C> Sync for SendPtr<C> {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_single_mode() {
        let dims = [6, 5, 4];
        let n: usize = dims.iter().product();
        let f = Fft3::<f64>::new(dims);
        let (kx, ky, kz) = (1usize, 2usize, 3usize);
        let input: Vec<f64> = (0..n)
            .map(|i| {
                let (x, y, z) = (i % 6, (i / 6) % 5, i / 30);
                let ph = 2.0
                    * std::f64::consts::PI
                    * (kx as f64 * x as f64 / 6.0
                        + ky as f64 * y as f64 / 5.0
                        + kz as f64 * z as f64 / 4.0);
                ph.cos()
            })
            .collect();
        let mut spec = vec![Complex::new(0.0, 0.0); f.spectrum_len()];
        f.forward(&input, &mut spec);
        // cos -> n/2 at (kx, ky, kz) (its conjugate partner sits in the other half).
        let at = spec[kx + f.nkx * (ky + 5 * kz)];
        assert!((at.re - n as f64 / 2.0).abs() < 1e-9 && at.im.abs() < 1e-9);
        let mut back = vec![0.0; n];
        f.inverse(&mut spec, &mut back);
        for i in 0..n {
            assert!((back[i] / n as f64 - input[i]).abs() < 1e-12);
        }
    }
}
