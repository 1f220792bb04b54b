//! The one spatial index every stage shares: a uniform cell list over a box that is periodic
//! or not per axis, and the small geometric helpers that go with it (minimum image, uniformly
//! random orientation).
//!
//! Each item is stored once, at its position wrapped into the box. Queries on periodic axes
//! walk "virtual" cells beyond the box and report the period translation of what they find,
//! so every periodic image within reach is visited once, also when the reach exceeds the
//! period (thin bricks, layers squeezed between their own images).

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

/// Upper bound on cells per axis and in all; a cell list larger than this would cost more
/// memory than it saves time (and a typo in a length must not allocate gigabytes).
pub const MAX_CELLS_PER_AXIS: usize = 1024;
pub const MAX_CELLS: usize = 1 << 24;

/// A uniform cell list over the box `[min, min + len)`.
#[derive(Clone, Debug)]
pub struct CellList {
    min: [f64; 3],
    len: [f64; 3],
    periodic: [bool; 3],
    n: [i64; 3],
    h: [f64; 3],
    cells: Vec<Vec<u32>>,
    count: usize,
}

impl CellList {
    /// Cells of edge at least `target` where the box allows (exactly `len / n` per axis, so
    /// periods tile exactly), at most [`MAX_CELLS_PER_AXIS`] per axis and [`MAX_CELLS`] in all.
    pub fn new(min: [f64; 3], len: [f64; 3], periodic: [bool; 3], target: f64) -> Self {
        let n = Self::cell_counts(len, target);
        let h = [0, 1, 2].map(|a| len[a] / n[a] as f64);
        CellList {
            min,
            len,
            periodic,
            n,
            h,
            cells: vec![Vec::new(); (n[0] * n[1] * n[2]) as usize],
            count: 0,
        }
    }

    /// Heap bytes of a cell list over a box of `len` with cells of at least `target` holding
    /// `items` items, for memory estimates: a 24 B vector per cell (the same cell counts as
    /// [`CellList::new`]), and per item 4 B, doubled for the vectors' growth, with the first
    /// allocation of a cell at 16 B (four entries).
    pub fn memory_bytes(len: [f64; 3], target: f64, items: u64) -> u64 {
        let n = Self::cell_counts(len, target);
        let cells = (n[0] * n[1] * n[2]) as u64;
        24 * cells + 16 * items.min(cells) + 8 * items
    }

    fn cell_counts(len: [f64; 3], target: f64) -> [i64; 3] {
        let target = if target.is_finite() && target > 0.0 {
            target
        } else {
            f64::INFINITY
        };
        let mut n = [0, 1, 2].map(|a| {
            let k = (len[a] / target).floor();
            if k.is_finite() {
                (k as i64).clamp(1, MAX_CELLS_PER_AXIS as i64)
            } else {
                1
            }
        });
        // Coarsen the largest axis until the total fits.
        while (n[0] * n[1] * n[2]) as usize > MAX_CELLS {
            let a = (0..3).max_by_key(|&a| n[a]).expect("three axes");
            n[a] = (n[a] / 2).max(1);
        }
        n
    }

    /// Cells per axis.
    pub fn dims(&self) -> [usize; 3] {
        self.n.map(|k| k as usize)
    }

    /// Number of items inserted.
    pub fn len(&self) -> usize {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    fn cell_coord(&self, a: usize, x: f64) -> i64 {
        let k = ((x - self.min[a]) / self.h[a]).floor();
        let k = if k.is_finite() { k as i64 } else { 0 };
        if self.periodic[a] {
            k.rem_euclid(self.n[a])
        } else {
            k.clamp(0, self.n[a] - 1)
        }
    }

    /// Stores item `idx` at `c` (positions outside the box go to the nearest cell on
    /// non-periodic axes and wrap on periodic ones).
    pub fn insert(&mut self, idx: u32, c: [f64; 3]) {
        let k = [0, 1, 2].map(|a| self.cell_coord(a, c[a]));
        let cell = (k[0] + self.n[0] * (k[1] + self.n[1] * k[2])) as usize;
        self.cells[cell].push(idx);
        self.count += 1;
    }

    /// Empties the list, keeping its cells.
    pub fn clear(&mut self) {
        self.cells.iter_mut().for_each(Vec::clear);
        self.count = 0;
    }

    /// Calls `f(idx, shift)` for every stored item whose cell may hold an image within
    /// `reach` of `p`; `shift` is the period translation to add to the item's stored position
    /// (zero on non-periodic axes). On a periodic axis an item can be reported once per image.
    /// Stops early when `f` returns `false`; returns `false` if stopped.
    pub fn visit(&self, p: [f64; 3], reach: f64, mut f: impl FnMut(u32, [f64; 3]) -> bool) -> bool {
        let mut lo = [0i64; 3];
        let mut hi = [0i64; 3];
        for a in 0..3 {
            let l = ((p[a] - reach - self.min[a]) / self.h[a]).floor() as i64;
            let u = ((p[a] + reach - self.min[a]) / self.h[a]).floor() as i64;
            if self.periodic[a] {
                lo[a] = l;
                hi[a] = u.max(l);
            } else {
                lo[a] = l.clamp(0, self.n[a] - 1);
                hi[a] = u.clamp(0, self.n[a] - 1);
            }
        }
        let wrap = |a: usize, k: i64| -> (i64, f64) {
            if self.periodic[a] {
                (
                    k.rem_euclid(self.n[a]),
                    k.div_euclid(self.n[a]) as f64 * self.len[a],
                )
            } else {
                (k, 0.0)
            }
        };
        for kz in lo[2]..=hi[2] {
            let (cz, sz) = wrap(2, kz);
            for ky in lo[1]..=hi[1] {
                let (cy, sy) = wrap(1, ky);
                for kx in lo[0]..=hi[0] {
                    let (cx, sx) = wrap(0, kx);
                    let cell = (cx + self.n[0] * (cy + self.n[1] * cz)) as usize;
                    for &j in &self.cells[cell] {
                        if !f(j, [sx, sy, sz]) {
                            return false;
                        }
                    }
                }
            }
        }
        true
    }

    /// Calls `f(idx)` once for each item stored in the 3x3x3 cells around `p` (each cell once,
    /// also when an axis has fewer than three cells). With cells at least as wide as the
    /// interaction range, this finds every neighbour; use [`min_image`] for the separation.
    pub fn visit_adjacent(&self, p: [f64; 3], mut f: impl FnMut(u32) -> bool) -> bool {
        let k = [0, 1, 2].map(|a| self.cell_coord(a, p[a]));
        let mut ranges: [Vec<i64>; 3] = Default::default();
        for a in 0..3 {
            let n = self.n[a];
            let mut v: Vec<i64> = (-1..=1)
                .map(|d| k[a] + d)
                .filter_map(|j| {
                    if self.periodic[a] {
                        Some(j.rem_euclid(n))
                    } else {
                        (0..n).contains(&j).then_some(j)
                    }
                })
                .collect();
            v.sort_unstable();
            v.dedup();
            ranges[a] = v;
        }
        for &z in &ranges[2] {
            for &y in &ranges[1] {
                for &x in &ranges[0] {
                    for &j in &self.cells[(x + self.n[0] * (y + self.n[1] * z)) as usize] {
                        if !f(j) {
                            return false;
                        }
                    }
                }
            }
        }
        true
    }

    /// Minimum-image vector from `a` to `b` in this box.
    pub fn separation(&self, a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|k| min_image(b[k] - a[k], self.len[k], self.periodic[k]))
    }
}

/// Minimum-image separation along one axis of length `length`.
pub fn min_image(d: f64, length: f64, periodic: bool) -> f64 {
    if periodic {
        d - length * (d / length).round()
    } else {
        d
    }
}

/// A uniformly distributed orientation, as a unit quaternion (w, x, y, z): a normalised
/// 4-D standard Gaussian (Muller 1959; Shoemake 1992), four normal draws per call.
pub fn random_quaternion<R: Rng + ?Sized>(rng: &mut R) -> [f64; 4] {
    let q: [f64; 4] = [0; 4].map(|_| StandardNormal.sample(rng));
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    q.map(|v| v / n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    #[test]
    fn periodic_visit_finds_every_image_within_reach_exactly_once() {
        // Period 1, reach 2.4, point at the stored item: the images within reach are the
        // integer offsets with i^2 + j^2 + k^2 <= 5.76: 1 + 6 + 12 + 8 + 6 + 24 = 57.
        let mut g = CellList::new([0.0; 3], [1.0; 3], [true; 3], 0.5);
        g.insert(0, [0.5; 3]);
        let mut images = Vec::new();
        g.visit([0.5; 3], 2.4, |_, s| {
            images.push(s);
            true
        });
        let within = images
            .iter()
            .filter(|s| s.iter().map(|x| x * x).sum::<f64>() <= 2.4 * 2.4)
            .count();
        assert_eq!(within, 57);
        let mut dedup = images.clone();
        dedup.sort_by(|a, b| a.partial_cmp(b).unwrap());
        dedup.dedup();
        assert_eq!(dedup.len(), images.len(), "an image visited twice");
    }

    #[test]
    fn neighbours_match_brute_force_in_a_shifted_mixed_box() {
        // 400 random points in [-1, 2) x [0, 1) x [5, 5.5), periodic in x and z only.
        let min = [-1.0, 0.0, 5.0];
        let len = [3.0, 1.0, 0.5];
        let periodic = [true, false, true];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let pts: Vec<[f64; 3]> = (0..400)
            .map(|_| [0, 1, 2].map(|a| min[a] + rng.random::<f64>() * len[a]))
            .collect();
        let r = 0.2;
        let mut g = CellList::new(min, len, periodic, r);
        for (i, p) in pts.iter().enumerate() {
            g.insert(i as u32, *p);
        }
        for (i, p) in pts.iter().enumerate().step_by(7) {
            let mut found = Vec::new();
            g.visit_adjacent(*p, |j| {
                let d = g.separation(*p, pts[j as usize]);
                if j as usize != i && d.iter().map(|x| x * x).sum::<f64>() < r * r {
                    found.push(j as usize);
                }
                true
            });
            found.sort_unstable();
            let brute: Vec<usize> = (0..pts.len())
                .filter(|&j| {
                    let d = [0, 1, 2].map(|a| min_image(pts[j][a] - p[a], len[a], periodic[a]));
                    j != i && d.iter().map(|x| x * x).sum::<f64>() < r * r
                })
                .collect();
            assert_eq!(found, brute, "point {i}");
        }
    }

    #[test]
    fn a_huge_box_with_a_tiny_cell_stays_bounded() {
        let g = CellList::new([0.0; 3], [1.0; 3], [true; 3], 1e-9);
        let d = g.dims();
        assert!(d.iter().product::<usize>() <= MAX_CELLS && d.iter().all(|&k| k <= 1024));
    }

    #[test]
    fn random_orientations_are_unit_and_isotropic() {
        // The mean of the rotated z axis over many draws vanishes (isotropy) within
        // 4 standard errors (1/sqrt(3 n) per component).
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let n = 20_000;
        let mut mean = [0.0; 3];
        for _ in 0..n {
            let q = random_quaternion(&mut rng);
            assert!((q.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-12);
            let z = crate::model::rotate(q, [0.0, 0.0, 1.0]);
            for a in 0..3 {
                mean[a] += z[a] / n as f64;
            }
        }
        let se = 1.0 / (3.0 * n as f64).sqrt();
        assert!(mean.iter().all(|m| m.abs() < 4.0 * se), "{mean:?}");
    }
}
