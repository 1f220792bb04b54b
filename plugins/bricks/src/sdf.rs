//! Signed distance functions describing fill domains (negative inside).
//!
//! The filler only asks "is the sphere (c, r) inside?", answered by `sdf(c) <= -r`. This is
//! exact when the function is the exact distance inside the domain, which holds for the
//! primitives here and for intersections / subtractions of them (the inside distance of
//! `A minus B` is `min(dist to dA, dist to dB) = -max(sdf_A, -sdf_B)`). A new shape needs only
//! a new variant, not a new filler.

#[derive(Clone, Debug, PartialEq)]
pub enum Sdf {
    /// Axis-aligned box.
    Box { min: [f64; 3], max: [f64; 3] },
    /// Solid ball.
    Ball { center: [f64; 3], radius: f64 },
    /// Intersection of all parts (`max` of their distances).
    Intersect(Vec<Sdf>),
    /// `base` minus every solid in `cut`.
    Subtract { base: Box<Sdf>, cut: Vec<Sdf> },
}

impl Sdf {
    pub fn eval(&self, p: [f64; 3]) -> f64 {
        match self {
            Sdf::Box { min, max } => {
                let mut outside = 0.0f64;
                let mut inside = f64::NEG_INFINITY;
                for a in 0..3 {
                    let d = (min[a] - p[a]).max(p[a] - max[a]);
                    inside = inside.max(d);
                    outside += d.max(0.0).powi(2);
                }
                if inside > 0.0 {
                    outside.sqrt()
                } else {
                    inside
                }
            }
            Sdf::Ball { center, radius } => {
                let d2: f64 = (0..3).map(|a| (p[a] - center[a]).powi(2)).sum();
                d2.sqrt() - radius
            }
            Sdf::Intersect(parts) => parts
                .iter()
                .map(|s| s.eval(p))
                .fold(f64::NEG_INFINITY, f64::max),
            Sdf::Subtract { base, cut } => {
                cut.iter().map(|s| -s.eval(p)).fold(base.eval(p), f64::max)
            }
        }
    }

    /// True when the ball (c, r) lies inside, within `tol`.
    pub fn contains_ball(&self, c: [f64; 3], r: f64, tol: f64) -> bool {
        self.eval(c) <= -r + tol
    }

    /// Volume of `{sdf < 0}` inside the box `[lo, hi]`: exact for a plain box, else a
    /// midpoint rule on `n^3` cells (relative error ~ surface * h / volume / sqrt(boundary
    /// cells), below 1e-3 at n = 160 for the paper's hemispheres).
    pub fn volume(&self, lo: [f64; 3], hi: [f64; 3], n: usize) -> f64 {
        if let Sdf::Box { min, max } = self {
            return (0..3)
                .map(|a| (max[a].min(hi[a]) - min[a].max(lo[a])).max(0.0))
                .product();
        }
        let h = [0, 1, 2].map(|a| (hi[a] - lo[a]) / n as f64);
        let mut count = 0usize;
        for k in 0..n {
            for j in 0..n {
                for i in 0..n {
                    let p = [
                        lo[0] + (i as f64 + 0.5) * h[0],
                        lo[1] + (j as f64 + 0.5) * h[1],
                        lo[2] + (k as f64 + 0.5) * h[2],
                    ];
                    if self.eval(p) < 0.0 {
                        count += 1;
                    }
                }
            }
        }
        count as f64 * h[0] * h[1] * h[2]
    }

    /// Area of the part of the box face `axis = value` that lies inside the domain (points
    /// just inside the face are probed on an `n x n` midpoint grid; exact for a plain box).
    pub fn face_area(&self, lo: [f64; 3], hi: [f64; 3], axis: usize, inward: f64, n: usize) -> f64 {
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        let full = (hi[u] - lo[u]) * (hi[v] - lo[v]);
        if let Sdf::Box { .. } = self {
            return full;
        }
        let mut count = 0usize;
        for j in 0..n {
            for i in 0..n {
                let mut p = [0.0; 3];
                p[axis] = inward;
                p[u] = lo[u] + (i as f64 + 0.5) / n as f64 * (hi[u] - lo[u]);
                p[v] = lo[v] + (j as f64 + 0.5) / n as f64 * (hi[v] - lo[v]);
                if self.eval(p) < 0.0 {
                    count += 1;
                }
            }
        }
        full * count as f64 / (n * n) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn brick_minus_hemispheres_volume_matches_closed_form() {
        // Example 3A: unit cube minus two hemispheres of radius 0.5 on the x faces:
        // V = 1 - 2 * (2/3) pi 0.5^3 = 1 - pi/6.
        let cube = Sdf::Box {
            min: [0.0; 3],
            max: [1.0; 3],
        };
        let s = Sdf::Subtract {
            base: Box::new(cube),
            cut: vec![
                Sdf::Ball {
                    center: [0.0, 0.5, 0.5],
                    radius: 0.5,
                },
                Sdf::Ball {
                    center: [1.0, 0.5, 0.5],
                    radius: 0.5,
                },
            ],
        };
        let v = s.volume([0.0; 3], [1.0; 3], 160);
        // Midpoint rule on 160^3 cells: boundary-cell error well below 1e-3 of the volume.
        assert!((v - (1.0 - PI / 6.0)).abs() < 1e-3, "{v}");
        // Exact inside distance: (0.5, 0.5, 0.05) is 0.05 from the face z = 0 and
        // sqrt(0.25 + 0.2025) - 0.5 = 0.173 from the balls.
        assert!((s.eval([0.5, 0.5, 0.05]) + 0.05).abs() < 1e-15);
        // (0.2, 0.5, 0.5) is inside the first ball by 0.3: outside the domain.
        assert!((s.eval([0.2, 0.5, 0.5]) - 0.3).abs() < 1e-15);
        // The x face keeps its area outside the disk: 1 - pi/4.
        let a = s.face_area([0.0; 3], [1.0; 3], 0, 1e-9, 400);
        assert!((a - (1.0 - PI / 4.0)).abs() < 2e-3, "{a}");
    }
}
