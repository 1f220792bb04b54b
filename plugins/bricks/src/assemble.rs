//! Builds the total domain from the unit brick and finds contacts and face lists.

use crate::fill::{Filler, Mode};
use grainpipe_core::spatial::CellList;
use grainpipe_core::Contact;
use rayon::prelude::*;

/// Spheres of the total domain, with the brick copy each came from.
pub struct Assembly {
    pub pos: Vec<[f64; 3]>,
    pub rad: Vec<f64>,
    pub brick: Vec<usize>,
    pub size: [f64; 3],
    /// Spheres of one unit brick (Method 2: with the face copies).
    pub unit_count: usize,
}

/// Method 1 (paper section 2.2): copy `(i, j, k)` is the unit brick reflected about its
/// faces an odd number of times along each axis where the index is odd, so spheres touching a
/// shared face touch their own mirror images.
pub fn reflect(f: &Filler, numbers: [usize; 3]) -> Assembly {
    let l = f.len;
    let n = f.pos.len();
    let total = n * numbers.iter().product::<usize>();
    let mut pos = Vec::with_capacity(total);
    let mut rad = Vec::with_capacity(total);
    let mut brick = Vec::with_capacity(total);
    let mut b = 0;
    for k in 0..numbers[2] {
        for j in 0..numbers[1] {
            for i in 0..numbers[0] {
                let idx = [i, j, k];
                for (p, r) in f.pos.iter().zip(&f.rad) {
                    pos.push([0, 1, 2].map(|a| {
                        let base = idx[a] as f64 * l[a];
                        if idx[a] % 2 == 1 {
                            base + (l[a] - p[a])
                        } else {
                            base + p[a]
                        }
                    }));
                    rad.push(*r);
                    brick.push(b);
                }
                b += 1;
            }
        }
    }
    Assembly {
        pos,
        rad,
        brick,
        // eq. (2.1): L_i = BrickSideLengths(i) x BrickNumbers(i).
        size: [0, 1, 2].map(|a| l[a] * numbers[a] as f64),
        unit_count: n,
    }
}

/// Method 2 (paper section 3): translated copies. A sphere centred on the plane `x_a = 0` of
/// the periodic unit brick also appears at `x_a = n_a L_a`, closing the last brick, so every
/// brick carries identical opposite faces and no sphere is duplicated on shared faces.
pub fn translate(f: &Filler, numbers: [usize; 3]) -> Assembly {
    let l = f.len;
    let mut pos = Vec::new();
    let mut rad = Vec::new();
    let mut brick = Vec::new();
    let range = |a: usize, on_plane: bool| 0..numbers[a] + usize::from(on_plane);
    for (s, (p, r)) in f.pos.iter().zip(&f.rad).enumerate() {
        let on = [0, 1, 2].map(|a| f.on_face[s] & (1 << a) != 0);
        for k in range(2, on[2]) {
            for j in range(1, on[1]) {
                for i in range(0, on[0]) {
                    let idx = [i, j, k];
                    pos.push([0, 1, 2].map(|a| p[a] + idx[a] as f64 * l[a]));
                    rad.push(*r);
                    // Copies closing the domain belong to the last brick of that axis.
                    let bi = [0, 1, 2].map(|a| idx[a].min(numbers[a] - 1));
                    brick.push(bi[0] + numbers[0] * (bi[1] + numbers[1] * bi[2]));
                }
            }
        }
    }
    let unit_count = f
        .on_face
        .iter()
        .map(|b| 1usize << b.count_ones())
        .sum::<usize>();
    Assembly {
        pos,
        rad,
        brick,
        size: [0, 1, 2].map(|a| l[a] * numbers[a] as f64),
        unit_count,
    }
}

/// Every pair whose surface gap is at most `max_gap` (negative gaps are overlaps).
/// Deterministic: per-sphere lists are computed in parallel and concatenated in order.
pub fn contacts(pos: &[[f64; 3]], rad: &[f64], size: [f64; 3], max_gap: f64) -> Vec<Contact> {
    if pos.is_empty() {
        return Vec::new();
    }
    let rmean = rad.iter().sum::<f64>() / rad.len() as f64;
    // Grid over the domain box; spheres sticking out are clamped into border cells.
    let mut g = CellList::new([0.0; 3], size, [false; 3], 2.0 * rmean);
    for (i, p) in pos.iter().enumerate() {
        g.insert(i as u32, *p);
    }
    let rmax = rad.iter().cloned().fold(0.0, f64::max);
    (0..pos.len())
        .into_par_iter()
        .map(|i| {
            let mut out = Vec::new();
            let c = pos[i];
            g.visit(c, rad[i] + rmax + max_gap, |j, _| {
                let j = j as usize;
                if j > i {
                    let d: f64 = (0..3).map(|a| (c[a] - pos[j][a]).powi(2)).sum();
                    let gap = d.sqrt() - rad[i] - rad[j];
                    if gap <= max_gap {
                        out.push(Contact { i, j, gap });
                    }
                }
                true
            });
            out.sort_by_key(|c| c.j);
            out
        })
        .collect::<Vec<_>>()
        .into_iter()
        .flatten()
        .collect()
}

/// The paper's ListXmin .. ListZmax for the total domain: Closed mode lists spheres whose
/// gap to the face is at most `max_gap` (touching it); Centered mode lists spheres centred on
/// the face (to a relative 1e-9 of the domain size).
pub fn face_lists(a: &Assembly, mode: Mode, max_gap: f64) -> [Vec<usize>; 6] {
    let mut faces: [Vec<usize>; 6] = Default::default();
    for (i, (p, r)) in a.pos.iter().zip(&a.rad).enumerate() {
        for (f, list) in faces.iter_mut().enumerate() {
            let ax = f / 2;
            let d = if f % 2 == 0 {
                p[ax]
            } else {
                a.size[ax] - p[ax]
            };
            let on = match mode {
                Mode::Closed => d - r <= max_gap,
                Mode::Centered => d.abs() <= 1e-9 * a.size[ax],
            };
            if on {
                list.push(i);
            }
        }
    }
    faces
}
