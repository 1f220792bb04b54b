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
