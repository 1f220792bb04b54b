//! Clean-up of a label volume (x fastest): connected components of one phase that are too
//! small (specks) or enclosed (holes) are given the label that most of their face
//! neighbours carry. Components are those of `grainpipe_analysis::components` (6-connected,
//! periodic axes wrap).
//!
//! One pass per call: every component is judged, and its neighbours read, on the input
//! labels, so the order in which phases or components are visited does not matter and the
//! result does not depend on the number of threads.

use grainpipe_analysis::components::{label_components, Component, NONE};
use rayon::prelude::*;
use std::collections::HashMap;

/// What a pass changed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Reassigned {
    /// Components given another label.
    pub components: u64,
    /// Their voxels.
    pub voxels: u64,
}

impl std::ops::AddAssign for Reassigned {
    fn add_assign(&mut self, o: Reassigned) {
        self.components += o.components;
        self.voxels += o.voxels;
    }
}

/// Which voxels are face neighbours of voxel `i`: up to 6 indices (periodic axes wrap,
/// non-periodic faces have no neighbour beyond them).
fn neighbours(i: usize, dims: [usize; 3], periodic: [bool; 3]) -> impl Iterator<Item = usize> {
    let [nx, ny, _] = dims;
    let c = [i % nx, (i / nx) % ny, i / (nx * ny)];
    let stride = [1, nx, nx * ny];
    (0..6).filter_map(move |k| {
        let (a, up) = (k / 2, k % 2 == 1);
        let n = dims[a];
        if n < 2 {
            return None;
        }
        let to = if up {
            if c[a] + 1 < n {
                c[a] + 1
            } else if periodic[a] {
                0
            } else {
                return None;
            }
        } else if c[a] > 0 {
            c[a] - 1
        } else if periodic[a] {
            n - 1
        } else {
            return None;
        };
        Some(i - c[a] * stride[a] + to * stride[a])
    })
}

/// Reassigns, for every label `l` with `judge(l)`, the components of `l` for which
/// `select(component)` holds to the label most of their face neighbours carry (ties to the
/// smallest label). A component without neighbours of another label (a phase filling the
/// image) keeps its label. Reads `labels`, writes `out` (a copy of `labels` on entry).
fn reassign(
    labels: &[u8],
    out: &mut [u8],
    dims: [usize; 3],
    periodic: [bool; 3],
    judge: impl Fn(u8) -> bool,
    select: impl Fn(&Component) -> bool,
) -> Reassigned {
    let mut present = [false; 256];
    for &l in labels {
        present[l as usize] = true;
    }
    let mut done = Reassigned::default();
    for l in (0..=255u8).filter(|&l| present[l as usize] && judge(l)) {
        let lab = label_components(dims, periodic, |i| labels[i] == l);
        let chosen: Vec<bool> = lab.components.iter().map(&select).collect();
        if !chosen.iter().any(|&c| c) {
            continue;
        }
        let ids = &lab.ids;
        let plane = dims[0] * dims[1];
        // (component, neighbour label) -> count of faces, summed over z planes.
        let counts: HashMap<(u32, u8), u64> = (0..dims[2])
            .into_par_iter()
            .fold(HashMap::new, |mut m: HashMap<(u32, u8), u64>, z| {
                for (j, &c) in ids[z * plane..(z + 1) * plane].iter().enumerate() {
                    let i = z * plane + j;
                    if c == NONE || !chosen[c as usize] {
                        continue;
                    }
                    for n in neighbours(i, dims, periodic) {
                        let nl = labels[n];
                        if nl != l {
                            *m.entry((c, nl)).or_default() += 1;
                        }
                    }
                }
                m
            })
            .reduce(HashMap::new, |mut a, b| {
                for (k, v) in b {
                    *a.entry(k).or_default() += v;
                }
                a
            });
        // The majority label per chosen component, ties to the smallest label.
        let mut target: Vec<Option<(u64, u8)>> = vec![None; lab.components.len()];
        for (&(c, nl), &n) in &counts {
            let t = &mut target[c as usize];
            let better = match *t {
                None => true,
                Some((m, ml)) => n > m || (n == m && nl < ml),
            };
            if better {
                *t = Some((n, nl));
            }
        }
        for (c, t) in target.iter().enumerate() {
            if t.is_some() {
                done += Reassigned {
                    components: 1,
                    voxels: lab.components[c].voxels,
                };
            }
        }
        out.par_iter_mut().zip(ids.par_iter()).for_each(|(o, &c)| {
            if c != NONE {
                if let Some((_, nl)) = target[c as usize] {
                    *o = nl;
                }
            }
        });
    }
    done
}

/// Removes specks: components of the labels with `phase(l)` of fewer than `min_voxels`
/// voxels take the majority label of their face neighbours.
pub fn remove_specks(
    labels: &[u8],
    dims: [usize; 3],
    periodic: [bool; 3],
    min_voxels: u64,
    phase: impl Fn(u8) -> bool,
) -> (Vec<u8>, Reassigned) {
    let mut out = labels.to_vec();
    let r = reassign(labels, &mut out, dims, periodic, phase, |c| {
        c.voxels < min_voxels
    });
    (out, r)
}

/// Whether a component is enclosed: along every axis of more than one voxel it touches
/// neither image face (non-periodic axis) or does not wind around the box (periodic axis).
pub fn enclosed(c: &Component, dims: [usize; 3], periodic: [bool; 3]) -> bool {
    (0..3).all(|a| {
        dims[a] < 2
            || if periodic[a] {
                !c.winds[a]
            } else {
                !c.touches[a][0] && !c.touches[a][1]
            }
    })
}

/// Fills holes: enclosed components (see [`enclosed`]) of the labels with `phase(l)` take
/// the majority label of their face neighbours (the enclosing phase).
pub fn fill_holes(
    labels: &[u8],
    dims: [usize; 3],
    periodic: [bool; 3],
    phase: impl Fn(u8) -> bool,
) -> (Vec<u8>, Reassigned) {
    let mut out = labels.to_vec();
    let r = reassign(labels, &mut out, dims, periodic, phase, |c| {
        enclosed(c, dims, periodic)
    });
    (out, r)
}

/// Applies a label map in place: `map[l]` is the new label of `l`.
pub fn relabel(labels: &mut [u8], map: &[u8; 256]) {
    labels.par_iter_mut().for_each(|l| *l = map[*l as usize]);
}
