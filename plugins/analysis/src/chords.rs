//! `analysis.chords`: chord-length distributions of one phase along the axes. A chord is a
//! maximal run of phase voxels along a grid line; its length is the run's voxel count times
//! the spacing. The kernel is [`chord_counts`] (plain slices).
//!
//! Along a periodic axis a run through the periodic face is one chord (joined across it);
//! a line entirely in the phase has no end and is counted as unbounded. Along a non-periodic
//! axis a run that touches either face of the image is cut by it, its true length unknown:
//! it is left out of the distribution and counted as cut (leaving it in would bias the
//! distribution short, leaving it out biases it slightly short of long chords; the count
//! says how much was left out).

use crate::pores::{
    announced_longest_edge, announced_voxels, check_axes, table_rows, Axis, AxisLines,
    PhaseSelection,
};
use grainpipe_core::{
    params, Artifact, ArtifactKind, InputMetas, Inputs, Outputs, PortSpec, Preflight, RunContext,
    StageError, StageInfo, Table, TypedStage,
};
use rayon::prelude::*;

/// Chords of the phase along one axis.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Chords {
    /// `counts[k]`: chords of k voxels (index 0 unused).
    pub counts: Vec<u64>,
    /// Runs cut by a non-periodic face (left out of `counts`).
    pub cut: u64,
    /// Lines entirely in the phase along a periodic axis (left out of `counts`).
    pub unbounded: u64,
    /// Phase voxels on the lines (all of them, in chords or not).
    pub voxels: u64,
    /// Boundaries between the phase and the rest crossed along the lines (across the
    /// periodic face too; not at a non-periodic face).
    pub crossings: u64,
}

impl Chords {
    pub fn chords(&self) -> u64 {
        self.counts.iter().sum()
    }
    /// Mean chord length in voxels (NaN without chords).
    pub fn mean(&self) -> f64 {
        let v: u64 = self
            .counts
            .iter()
            .enumerate()
            .map(|(k, &c)| k as u64 * c)
            .sum();
        v as f64 / self.chords() as f64
    }
    /// The stereological mean chord in voxels: twice the phase voxels over the boundary
    /// crossings, 4 phi / S_V for an isotropic structure; equal to [`Chords::mean`] when no
    /// chord is cut or unbounded, and not biased by them (NaN without crossings).
    pub fn stereological(&self) -> f64 {
        2.0 * self.voxels as f64 / self.crossings as f64
    }
}

/// The chords of the phase (`mask`, x fastest) along `axis`; `periodic`: whether the lines
/// wrap.
pub fn chord_counts(mask: &[bool], dims: [usize; 3], axis: usize, periodic: bool) -> Chords {
    let n = dims[axis];
    assert_eq!(mask.len(), dims.iter().product::<usize>());
    let lines = AxisLines::new(dims, axis);
    let parts: Vec<Chords> = (0..lines.groups)
        .into_par_iter()
        .map(|g| {
            let mut c = Chords {
                counts: vec![0; n + 1],
                cut: 0,
                unbounded: 0,
                voxels: 0,
                crossings: 0,
            };
            for l in 0..lines.per_group {
                let s = lines.start(g, l);
                let at = |k: usize| mask[s + k * lines.stride];
                line_chords(n, at, periodic, &mut c);
            }
            c
        })
        .collect();
    let mut total = Chords {
        counts: vec![0; n + 1],
        cut: 0,
        unbounded: 0,
        voxels: 0,
        crossings: 0,
    };
    for p in parts {
        for (t, c) in total.counts.iter_mut().zip(&p.counts) {
            *t += c;
        }
        total.cut += p.cut;
        total.unbounded += p.unbounded;
        total.voxels += p.voxels;
        total.crossings += p.crossings;
    }
    total
}

/// Adds the chords of one line of `n` voxels to `c`.
fn line_chords(n: usize, at: impl Fn(usize) -> bool, periodic: bool, c: &mut Chords) {
    // Runs as (start, length) in line order.
    let mut k = 0;
    let mut runs: Vec<(usize, usize)> = Vec::new();
    while k < n {
        if at(k) {
            let s = k;
            while k < n && at(k) {
                k += 1;
            }
            runs.push((s, k - s));
        } else {
            k += 1;
        }
    }
    if runs.is_empty() {
        return;
    }
    c.voxels += runs.iter().map(|r| r.1 as u64).sum::<u64>();
    // Every run has two ends; an end at a non-periodic face is no crossing, and on a
    // periodic line the runs at both ends are joined below (their shared face crosses
    // nothing).
    let ends: u64 = runs
        .iter()
        .map(|&(s, len)| u64::from(s > 0) + u64::from(s + len < n))
        .sum();
    c.crossings += ends;
    if periodic {
        if runs.len() == 1 && runs[0].1 == n {
            c.unbounded += 1;
            return;
        }
        // A run ending at the last voxel continues into the first one.
        let first = runs[0];
        let last = *runs.last().unwrap();
        // On a periodic line a run at a face crosses it into the other face's voxel: a
        // boundary unless that voxel is in the phase too (the runs join).
        let joined = runs.len() > 1 && first.0 == 0 && last.0 + last.1 == n;
        c.crossings +=
            u64::from(first.0 == 0 && !joined) + u64::from(last.0 + last.1 == n && !joined);
        if joined {
            runs.pop();
            runs[0].1 += last.1;
        }
        for (_, len) in runs {
            c.counts[len] += 1;
        }
    } else {
        for (s, len) in runs {
            if s == 0 || s + len == n {
                c.cut += 1;
            } else {
                c.counts[len] += 1;
            }
        }
    }
}

#[params]
pub struct ChordsParams {
    #[param(flatten)]
    pub selection: PhaseSelection,
    /// axes along which chords are measured
    #[param(default = Axis::ALL.to_vec())]
    pub axes: Vec<Axis>,
}

pub struct ChordLengths;

impl TypedStage for ChordLengths {
    type Params = ChordsParams;
    type Plan = ();

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "analysis.chords",
            "1.0.0",
            "Chord-length distributions of a phase along x, y and z: a chord is a maximal \
             run of phase voxels along a grid line, of length (voxels x spacing). Along a \
             periodic axis runs join across the periodic face and a line wholly in the \
             phase is counted as unbounded; along a non-periodic axis runs that touch \
             either face of the image are cut, left out of the distribution and counted. \
             The mean of the chords counted is biased short when many runs are cut or \
             unbounded (long runs are the likeliest to be); the stereological mean chord, \
             twice the phase length on the lines over the boundary crossings (4 phi / S_V \
             for an isotropic structure), is not. For a Boolean model (random overlapping \
             spheres) the pore chords are exponential with mean 4 phi / S_V; on the voxel \
             lattice their voxel counts are geometric. Memory: the image mask.",
        )
        .inputs(vec![PortSpec::new(
            "image",
            ArtifactKind::PhaseImage,
            "any labelled image",
        )])
        .outputs(vec![
            PortSpec::new(
                "summary",
                ArtifactKind::Table,
                "one row per axis: chords counted, chords cut by a non-periodic face, \
                 unbounded lines, mean chord length (m), stereological mean chord 2 x phase \
                 length / boundary crossings (m; 4 phi / S_V, cut and unbounded runs included)",
            ),
            PortSpec::new(
                "distribution",
                ArtifactKind::Table,
                "one row per axis and chord length up to the longest: length (m), voxels, \
                 count, number fraction and length-weighted fraction",
            ),
        ])
    }

    fn preflight(&self, p: &ChordsParams, i: &InputMetas) -> Result<Preflight, StageError> {
        p.selection.check()?;
        check_axes("axes", &p.axes)?;
        let rows = p.axes.len() as u64;
        // The phase mask (1 B per voxel); per line group (a plane, at most the longest edge
        // d of them) its chord counts of d + 1 u64; the tables, d + 1 rows per axis.
        let d = announced_longest_edge(i) + 1;
        let memory = announced_voxels(i) + 8 * d * d + rows * 48 * d + (64 << 10);
        Ok(Preflight::from_info(&self.info(), memory).announce("summary", table_rows(rows)))
    }

    fn run(
        &self,
        p: &ChordsParams,
        _: &(),
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let (image, mask) = p.selection.image_and_mask(inputs)?;
        let g = &image.grid;
        // The columns of the summary and of the distribution.
        let mut s: (Vec<_>, Vec<_>, Vec<_>, Vec<_>, Vec<_>, Vec<_>) = Default::default();
        let mut d: (Vec<_>, Vec<_>, Vec<_>, Vec<_>, Vec<_>, Vec<_>) = Default::default();
        for (j, a) in p.axes.iter().enumerate() {
            let k = a.index();
            let h = g.spacing[k];
            let c = chord_counts(&mask, g.dims, k, g.periodic[k]);
            let chords = c.chords();
            s.0.push(a.name().to_string());
            s.1.push(chords as i64);
            s.2.push(c.cut as i64);
            s.3.push(c.unbounded as i64);
            s.4.push(c.mean() * h);
            s.5.push(c.stereological() * h);
            let longest = c.counts.iter().rposition(|&x| x > 0).unwrap_or(0);
            let voxels: u64 = c
                .counts
                .iter()
                .enumerate()
                .map(|(k, &x)| k as u64 * x)
                .sum();
            for (len, &count) in c.counts.iter().enumerate().take(longest + 1).skip(1) {
                d.0.push(a.name().to_string());
                d.1.push(len as f64 * h);
                d.2.push(len as i64);
                d.3.push(count as i64);
                d.4.push(count as f64 / chords as f64);
                d.5.push((len as u64 * count) as f64 / voxels as f64);
            }
            ctx.progress(j as u64 + 1, p.axes.len() as u64)?;
        }
        let summary = Table::new("chords")
            .with_str("axis", s.0)
            .with_i64("chords", "", s.1)
            .with_i64("cut", "", s.2)
            .with_i64("unbounded", "", s.3)
            .with_f64("mean_chord", "m", s.4)
            .with_f64("stereological_chord", "m", s.5);
        let distribution = Table::new("chord_distribution")
            .with_str("axis", d.0)
            .with_f64("length", "m", d.1)
            .with_i64("voxels", "", d.2)
            .with_i64("count", "", d.3)
            .with_f64("fraction", "1", d.4)
            .with_f64("length_fraction", "1", d.5);
        let mut out = Outputs::new();
        out.insert("summary".into(), Artifact::Table(summary));
        out.insert("distribution".into(), Artifact::Table(distribution));
        Ok(out)
    }
}
