//! `analysis.two_point`: the two-point correlation S2(r) of one phase along the axes, the
//! probability that two points a lag r apart along the axis both lie in the phase. The
//! kernel is [`pair_counts`] (plain slices).
//!
//! Method: for every grid line along the axis, the autocorrelation of its indicator by FFT
//! (rustfft): circular (length n) on a periodic axis, where every voxel has a partner at
//! every lag; zero-padded to at least 2n - 1 on a non-periodic axis, where it counts exactly
//! the pairs inside the image, n - k per line at lag k. The power spectra of the lines of a
//! plane (x, y) or row (z) are summed, transformed back once and rounded to the integer pair
//! counts, which are summed over planes as integers: exact, and independent of the thread
//! count. S2(k) = pairs in the phase / pairs.
//!
//! The radial average ([`radial_counts`]) is the same on the whole grid: one 3-D FFT
//! autocorrelation (zero-padded along non-periodic axes), its integer counts summed over the
//! displacements of each shell and divided by the pairs those displacements have.

use crate::pores::{announced_voxels, check_axes, table_rows, Axis, AxisLines, PhaseSelection};
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, InputMetas, Inputs, Outputs, PortSpec, Preflight,
    RunContext, StageError, StageInfo, Table, TypedStage,
};
use rayon::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;

/// Pair counts of the phase along `axis` for lags 0..=`max_lag` voxels: (pairs with both
/// voxels in the phase, all pairs) per lag. `periodic`: whether lines wrap along the axis.
pub fn pair_counts(
    mask: &[bool],
    dims: [usize; 3],
    axis: usize,
    periodic: bool,
    max_lag: usize,
) -> Vec<(u64, u64)> {
    let n = dims[axis];
    assert_eq!(mask.len(), dims.iter().product::<usize>());
    let max_lag = max_lag.min(n - 1);
    let lines_total = (mask.len() / n) as u64;
    let m = fft_len(n, periodic);
    let mut planner = FftPlanner::<f64>::new();
    let fwd = planner.plan_fft_forward(m);
    let inv = planner.plan_fft_inverse(m);
    let lines = AxisLines::new(dims, axis);
    let per_group: Vec<Vec<u64>> = (0..lines.groups)
        .into_par_iter()
        .map_init(
            || (Vec::<Complex<f64>>::new(), vec![Complex::default(); m]),
            |(buf, spectrum), g| {
                // The lines of the group, gathered into consecutive chunks of length m.
                buf.clear();
                buf.resize(lines.per_group * m, Complex::default());
                for l in 0..lines.per_group {
                    let s = lines.start(g, l);
                    for k in 0..n {
                        if mask[s + k * lines.stride] {
                            buf[l * m + k].re = 1.0;
                        }
                    }
                }
                fwd.process(buf);
                spectrum.iter_mut().for_each(|c| *c = Complex::default());
                for line in buf.chunks(m) {
                    for (s, c) in spectrum.iter_mut().zip(line) {
                        s.re += c.norm_sqr();
                    }
                }
                inv.process(spectrum);
                (0..=max_lag)
                    .map(|k| (spectrum[k].re / m as f64).round().max(0.0) as u64)
                    .collect()
            },
        )
        .collect();
    (0..=max_lag)
        .map(|k| {
            let both: u64 = per_group.iter().map(|c| c[k]).sum();
            let pairs = if periodic {
                lines_total * n as u64
            } else {
                lines_total * (n - k) as u64
            };
            (both, pairs)
        })
        .collect()
}

/// FFT length along an axis of `n` voxels: `n` when periodic, else at least 2n - 1 (so the
/// circular correlation holds the open one).
fn fft_len(n: usize, periodic: bool) -> usize {
    if periodic {
        n
    } else {
        (2 * n - 1).next_power_of_two().max(2)
    }
}

/// In place, the 3-D FFT (forward or inverse) of `buf` on a grid of `m` points (x fastest).
fn fft3(buf: &mut [Complex<f64>], m: [usize; 3], inverse: bool) {
    let mut planner = FftPlanner::<f64>::new();
    let plans: Vec<_> = (0..3)
        .map(|a| {
            if inverse {
                planner.plan_fft_inverse(m[a])
            } else {
                planner.plan_fft_forward(m[a])
            }
        })
        .collect();
    let [mx, my, mz] = m;
    // x: contiguous lines.
    buf.par_chunks_mut(mx * my)
        .for_each(|plane| plans[0].process(plane));
    // y: per z plane, the columns gathered into one batch.
    buf.par_chunks_mut(mx * my).for_each_init(
        || vec![Complex::default(); mx * my],
        |t, plane| {
            for y in 0..my {
                for x in 0..mx {
                    t[x * my + y] = plane[x + mx * y];
                }
            }
            plans[1].process(t);
            for y in 0..my {
                for x in 0..mx {
                    plane[x + mx * y] = t[x * my + y];
                }
            }
        },
    );
    // z: per y row, the lines gathered from the shared buffer, transformed, then put back.
    let rows: Vec<Vec<Complex<f64>>> = (0..my)
        .into_par_iter()
        .map(|y| {
            let mut t = vec![Complex::default(); mx * mz];
            for z in 0..mz {
                for x in 0..mx {
                    t[x * mz + z] = buf[x + mx * (y + my * z)];
                }
            }
            plans[2].process(&mut t);
            t
        })
        .collect();
    for (y, t) in rows.iter().enumerate() {
        for z in 0..mz {
            for x in 0..mx {
                buf[x + mx * (y + my * z)] = t[x * mz + z];
            }
        }
    }
}

/// Radially averaged pair counts of the phase: for shells k = 0..=`shells` of displacements
/// d (any direction) with |d| / `width` rounded to k, (pairs with both voxels in the phase,
/// all pairs inside the image). By the 3-D FFT autocorrelation, zero-padded along
/// non-periodic axes (where a displacement d fits n_a - |d_a| times); exact integer counts.
pub fn radial_counts(
    mask: &[bool],
    dims: [usize; 3],
    spacing: [f64; 3],
    periodic: [bool; 3],
    width: f64,
    shells: usize,
) -> Vec<(u64, u64)> {
    assert_eq!(mask.len(), dims.iter().product::<usize>());
    let m: [usize; 3] = [0, 1, 2].map(|a| fft_len(dims[a], periodic[a]));
    let total = m[0] * m[1] * m[2];
    let mut buf = vec![Complex::<f64>::default(); total];
    let [nx, ny, _] = dims;
    buf.par_chunks_mut(m[0] * m[1])
        .enumerate()
        .filter(|(z, _)| *z < dims[2])
        .for_each(|(z, plane)| {
            for y in 0..ny {
                for x in 0..nx {
                    if mask[x + nx * (y + ny * z)] {
                        plane[x + m[0] * y].re = 1.0;
                    }
                }
            }
        });
    fft3(&mut buf, m, false);
    buf.par_iter_mut()
        .for_each(|c| *c = Complex::new(c.norm_sqr(), 0.0));
    fft3(&mut buf, m, true);
    // Displacement of FFT index j along axis a (None: not a displacement inside the image),
    // and the pairs it has there.
    let shift = |a: usize, j: usize| -> Option<(i64, u64)> {
        let (n, ma) = (dims[a] as i64, m[a] as i64);
        let d = if (j as i64) <= ma / 2 {
            j as i64
        } else {
            j as i64 - ma
        };
        if periodic[a] {
            // Each periodic displacement once: -n/2 < d <= n/2.
            Some((d, n as u64))
        } else if d.abs() < n {
            Some((d, (n - d.abs()) as u64))
        } else {
            None
        }
    };
    let per_plane: Vec<Vec<(u64, u64)>> = (0..m[2])
        .into_par_iter()
        .map(|kz| {
            let mut acc = vec![(0u64, 0u64); shells + 1];
            let Some((dz, pz)) = shift(2, kz) else {
                return acc;
            };
            for ky in 0..m[1] {
                let Some((dy, py)) = shift(1, ky) else {
                    continue;
                };
                for kx in 0..m[0] {
                    let Some((dx, px)) = shift(0, kx) else {
                        continue;
                    };
                    let r = ((dx as f64 * spacing[0]).powi(2)
                        + (dy as f64 * spacing[1]).powi(2)
                        + (dz as f64 * spacing[2]).powi(2))
                    .sqrt();
                    let k = (r / width).round() as usize;
                    if k > shells {
                        continue;
                    }
                    let c = buf[kx + m[0] * (ky + m[1] * kz)].re / total as f64;
                    acc[k].0 += c.round().max(0.0) as u64;
                    acc[k].1 += px * py * pz;
                }
            }
            acc
        })
        .collect();
    (0..=shells)
        .map(|k| {
            per_plane
                .iter()
                .fold((0, 0), |(a, b), p| (a + p[k].0, b + p[k].1))
        })
        .collect()
}

#[params]
pub struct TwoPointParams {
    #[param(flatten)]
    pub selection: PhaseSelection,
    /// axes along which S2 is measured
    #[param(default = Axis::ALL.to_vec())]
    pub axes: Vec<Axis>,
    /// largest lag (default: half the image along each axis; at most the image length
    /// less one voxel on a non-periodic axis, half of it on a periodic one)
    pub max_lag: Option<Q<Length>>,
    /// also the radial (direction-averaged) S2 from the 3-D autocorrelation, in shells one
    /// smallest spacing wide up to `max_lag` (default: half the image's shortest side);
    /// costs 16 bytes per voxel of the zero-padded grid (8 times the image when no axis
    /// is periodic), twice during the transform
    #[param(default = false)]
    pub radial: bool,
}

pub struct TwoPoint;

/// The longest lag (in voxels) along an axis of `n` voxels: half the axis when periodic,
/// else all of it less one voxel.
fn lag_cap(n: usize, periodic: bool) -> usize {
    if periodic {
        n / 2
    } else {
        n - 1
    }
}

/// Lags (in voxels) measured along an axis of `n` voxels of edge `h`.
fn lags(p: &TwoPointParams, n: usize, h: f64, periodic: bool) -> usize {
    let cap = lag_cap(n, periodic);
    match p.max_lag {
        Some(l) => ((l.si() / h + 1e-9).floor() as usize).min(cap),
        None => (n / 2).min(cap),
    }
}

impl TypedStage for TwoPoint {
    type Params = TwoPointParams;
    type Plan = ();

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "analysis.two_point",
            "1.0.0",
            "Two-point correlation S2(r) of a phase along x, y and z: the probability that \
             two voxel centres a lag r apart along the axis both lie in the phase (S2(0) is \
             its volume fraction, S2 tends to its square at long range). Computed by FFT \
             autocorrelation of every grid line: circular on a periodic axis, zero-padded \
             on a non-periodic one, where each lag is normalised by the pairs that fit in \
             the image (n - k per line). Pair counts are exact integers. Memory: the image \
             mask plus one plane of lines as complex numbers per thread.",
        )
        .inputs(vec![PortSpec::new(
            "image",
            ArtifactKind::PhaseImage,
            "any labelled image",
        )])
        .outputs(vec![
            PortSpec::new(
                "s2",
                ArtifactKind::Table,
                "one row per axis and lag: axis, lag in voxels and in m, S2, the pairs counted",
            ),
            PortSpec::optional(
                "radial",
                ArtifactKind::Table,
                "with radial: true, one row per shell: lag (m, the shell's centre), S2 \
                 averaged over the directions (pairs-weighted), the pairs counted",
            ),
        ])
    }

    fn preflight(&self, p: &TwoPointParams, i: &InputMetas) -> Result<Preflight, StageError> {
        p.selection.check()?;
        check_axes("axes", &p.axes)?;
        if let Some(l) = p.max_lag {
            if !(l.si() >= 0.0 && l.si().is_finite()) {
                return Err(StageError::param(
                    "max_lag",
                    format!("must be a non-negative length, got {} m", l.si()),
                ));
            }
        }
        let voxels = announced_voxels(i);
        let mut table = ArtifactMeta::of(ArtifactKind::Table);
        if let Some(g) = i.get("image").and_then(|m| m.grid.clone()) {
            let rows: u64 = p
                .axes
                .iter()
                .map(|a| {
                    let k = a.index();
                    lags(p, g.dims[k], g.spacing[k], g.periodic[k]) as u64 + 1
                })
                .sum();
            table = table_rows(rows);
            for a in &p.axes {
                let k = a.index();
                if let Some(l) = p.max_lag {
                    let cap = lag_cap(g.dims[k], g.periodic[k]);
                    if l.si() > (cap as f64 + 0.5) * g.spacing[k] {
                        return Err(StageError::param(
                            "max_lag",
                            format!(
                                "{} m is longer than the image allows along {} ({} voxels of \
                                 {} m, {}: at most {} m); leave it out for half the image",
                                l.si(),
                                a.name(),
                                g.dims[k],
                                g.spacing[k],
                                if g.periodic[k] {
                                    "periodic"
                                } else {
                                    "not periodic"
                                },
                                cap as f64 * g.spacing[k]
                            ),
                        ));
                    }
                }
            }
        }
        // The mask (1 byte per voxel); a plane of padded lines per thread (32 bytes per
        // voxel of a plane) is small beside it. The radial average: the padded grid as
        // complex numbers, twice during the z transform.
        let padded = i
            .get("image")
            .and_then(|m| m.grid.as_ref())
            .map_or(8 * voxels, |g| {
                (0..3)
                    .map(|a| fft_len(g.dims[a], g.periodic[a]) as u64)
                    .product()
            });
        // Per worker thread, one plane of padded lines (32 B per voxel of a padded plane).
        let plane = i
            .get("image")
            .and_then(|m| m.grid.as_ref())
            .map_or(voxels, |g| {
                (0..2)
                    .map(|a| fft_len(g.dims[a], g.periodic[a]) as u64)
                    .product()
            });
        let threads = rayon::current_num_threads() as u64;
        let memory =
            voxels + threads * 32 * plane + if p.radial { 32 * padded } else { 0 } + (64 << 10);
        let mut pf = Preflight::from_info(&self.info(), memory).announce("s2", table);
        if !p.radial {
            pf.outputs.retain(|k, _| k != "radial");
        }
        Ok(pf)
    }

    fn run(
        &self,
        p: &TwoPointParams,
        _: &(),
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let (image, mask) = p.selection.image_and_mask(inputs)?;
        let g = &image.grid;
        let (mut axis, mut lag_v, mut lag, mut s2, mut pairs) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (j, a) in p.axes.iter().enumerate() {
            let k = a.index();
            let max = lags(p, g.dims[k], g.spacing[k], g.periodic[k]);
            let counts = pair_counts(&mask, g.dims, k, g.periodic[k], max);
            for (l, (both, all)) in counts.into_iter().enumerate() {
                axis.push(a.name().to_string());
                lag_v.push(l as i64);
                lag.push(l as f64 * g.spacing[k]);
                s2.push(both as f64 / all as f64);
                pairs.push(all as i64);
            }
            ctx.progress(j as u64 + 1, p.axes.len() as u64)?;
        }
        let mut out = Outputs::new();
        if p.radial {
            let width = g.spacing.iter().copied().fold(f64::INFINITY, f64::min);
            let radius = match p.max_lag {
                Some(l) => l.si(),
                None => (0..3)
                    .map(|a| (g.dims[a] / 2) as f64 * g.spacing[a])
                    .fold(f64::INFINITY, f64::min),
            };
            let shells = (radius / width + 1e-9).floor() as usize;
            let c = radial_counts(&mask, g.dims, g.spacing, g.periodic, width, shells);
            let ratio = |(b, a): (u64, u64)| {
                if a == 0 {
                    f64::NAN
                } else {
                    b as f64 / a as f64
                }
            };
            out.insert(
                "radial".into(),
                Artifact::Table(
                    Table::new("two_point_radial")
                        .with_f64("lag", "m", (0..=shells).map(|k| k as f64 * width).collect())
                        .with_f64("s2", "1", c.iter().map(|&x| ratio(x)).collect())
                        .with_i64("pairs", "", c.iter().map(|x| x.1 as i64).collect()),
                ),
            );
        }
        let table = Table::new("two_point")
            .with_str("axis", axis)
            .with_i64("lag_voxels", "", lag_v)
            .with_f64("lag", "m", lag)
            .with_f64("s2", "1", s2)
            .with_i64("pairs", "", pairs);
        out.insert("s2".into(), Artifact::Table(table));
        Ok(out)
    }
}
