//! Cell list (uniform spatial hash) over a box, periodic or not per axis.
//!
//! Each sphere is stored once, at its canonical position. Queries on periodic axes walk
//! "virtual" cells beyond the box and translate the spheres found there by whole periods, so
//! every periodic image within reach is visited, also when the reach exceeds the period
//! (thin bricks such as the paper's 0.12 x 30 r_mean powder bed).

pub struct CellGrid {
    len: [f64; 3],
    periodic: [bool; 3],
    n: [i64; 3],
    h: [f64; 3],
    cells: Vec<Vec<u32>>,
    /// Largest radius inserted so far.
    pub rmax: f64,
}

impl CellGrid {
    /// Cells of edge about `target` (exactly `len / n` per axis, so periods tile exactly).
    pub fn new(len: [f64; 3], periodic: [bool; 3], target: f64) -> Self {
        let n = [0, 1, 2].map(|a| ((len[a] / target).floor() as i64).clamp(1, 1024));
        let h = [0, 1, 2].map(|a| len[a] / n[a] as f64);
        let total = (n[0] * n[1] * n[2]) as usize;
        CellGrid {
            len,
            periodic,
            n,
            h,
            cells: vec![Vec::new(); total],
            rmax: 0.0,
        }
    }

    fn cell_coord(&self, a: usize, x: f64) -> i64 {
        let k = (x / self.h[a]).floor() as i64;
        if self.periodic[a] {
            k.rem_euclid(self.n[a])
        } else {
            k.clamp(0, self.n[a] - 1)
        }
    }

    pub fn insert(&mut self, idx: u32, c: [f64; 3], r: f64) {
        let k = [0, 1, 2].map(|a| self.cell_coord(a, c[a]));
        let cell = (k[0] + self.n[0] * (k[1] + self.n[1] * k[2])) as usize;
        self.cells[cell].push(idx);
        self.rmax = self.rmax.max(r);
    }

    /// Calls `f(index, shift)` for every stored sphere whose cell may hold an image within
    /// `reach` of `p`; `shift` is the period translation to add to the stored position.
    /// Stops early when `f` returns `false`; returns `false` if stopped.
    pub fn visit(&self, p: [f64; 3], reach: f64, mut f: impl FnMut(u32, [f64; 3]) -> bool) -> bool {
        let mut lo = [0i64; 3];
        let mut hi = [0i64; 3];
        for a in 0..3 {
            let l = ((p[a] - reach) / self.h[a]).floor() as i64;
            let u = ((p[a] + reach) / self.h[a]).floor() as i64;
            if self.periodic[a] {
                lo[a] = l;
                hi[a] = u;
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn periodic_visit_finds_every_image_once() {
        // Period 1, reach 2.4, point at the stored sphere: the images within reach are the
        // integer offsets with i^2 + j^2 + k^2 <= 5.76, i.e. 1 + 6 + 12 + 8 + 6 + 24 = 57;
        // the walk may visit more (whole cells), but never one image twice.
        let mut g = CellGrid::new([1.0; 3], [true; 3], 0.5);
        g.insert(0, [0.5; 3], 0.1);
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
}
