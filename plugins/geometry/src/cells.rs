//! A uniform cell list over a (possibly periodic) box, for overlap and neighbour queries.

use grainpipe_core::{BodyShape, Packing};

pub struct CellList {
    size: [f64; 3],
    periodic: [bool; 3],
    n: [usize; 3],
    cell: [f64; 3],
    items: Vec<Vec<usize>>,
}

/// Minimum-image separation along one axis.
pub fn min_image(d: f64, length: f64, periodic: bool) -> f64 {
    if periodic {
        d - length * (d / length).round()
    } else {
        d
    }
}

impl CellList {
    /// Cells at least `min_cell` wide, so that touching spheres of radius <= min_cell / 2 are in
    /// neighbouring cells.
    pub fn new(size: [f64; 3], periodic: [bool; 3], min_cell: f64) -> Self {
        let n = [0, 1, 2].map(|a| ((size[a] / min_cell).floor() as usize).clamp(1, 1024));
        let cell = [0, 1, 2].map(|a| size[a] / n[a] as f64);
        CellList {
            size,
            periodic,
            n,
            cell,
            items: vec![Vec::new(); n[0] * n[1] * n[2]],
        }
    }

    fn coord(&self, x: f64, a: usize) -> usize {
        ((x / self.cell[a]).floor().max(0.0) as usize).min(self.n[a] - 1)
    }

    pub fn insert(&mut self, c: [f64; 3], id: usize) {
        let i = [0, 1, 2].map(|a| self.coord(c[a], a));
        self.items[i[0] + self.n[0] * (i[1] + self.n[1] * i[2])].push(id);
    }

    /// Calls `f` with each item in the 27 cells around `c` (each cell once, even when the
    /// grid is narrower than 3 cells on a periodic axis).
    pub fn for_neighbours(&self, c: [f64; 3], mut f: impl FnMut(usize) -> bool) -> bool {
        let i = [0, 1, 2].map(|a| self.coord(c[a], a) as i64);
        let mut ranges: [Vec<usize>; 3] = Default::default();
        for a in 0..3 {
            let n = self.n[a] as i64;
            let mut v: Vec<usize> = (-1..=1)
                .map(|d| i[a] + d)
                .filter_map(|j| {
                    if self.periodic[a] {
                        Some(j.rem_euclid(n) as usize)
                    } else if (0..n).contains(&j) {
                        Some(j as usize)
                    } else {
                        None
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
                    for &id in &self.items[x + self.n[0] * (y + self.n[1] * z)] {
                        if f(id) {
                            return true;
                        }
                    }
                }
            }
        }
        false
    }

    /// Minimum-image vector from `a` to `b`.
    pub fn separation(&self, a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|k| min_image(b[k] - a[k], self.size[k], self.periodic[k]))
    }

    /// Whether a sphere (c, r) overlaps any sphere body of `packing` stored in the list.
    pub fn overlaps(&self, c: [f64; 3], r: f64, packing: &Packing) -> bool {
        self.for_neighbours(c, |id| {
            let b = &packing.bodies[id];
            let rb = match b.shape {
                BodyShape::Sphere { radius } => radius,
                BodyShape::Clump { .. } => unreachable!("cell list holds spheres"),
            };
            let d = self.separation(c, b.position);
            let d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            d2 < (r + rb) * (r + rb)
        })
    }
}
