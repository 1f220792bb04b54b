//! Laser paths: timed straight segments, built from a raster or a CSV polyline.

use crate::params::ScanAxis;

/// Why a CSV path was refused.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum PathError {
    #[error("the CSV is empty")]
    Empty,
    #[error("header `{0}` must name columns x and y")]
    Header(String),
    #[error("line {line}: missing column {column}")]
    MissingColumn { line: usize, column: usize },
    #[error("line {line}: `{value}` is not a number")]
    NotANumber { line: usize, value: String },
    #[error("a path needs at least 2 vertices, found {0}")]
    TooFewVertices(usize),
}

/// One straight move of the spot from `a` (at `t0`) to `b` (at `t1`), laser on or off.
#[derive(Clone, Debug, PartialEq)]
pub struct Segment {
    pub a: [f64; 2],
    pub b: [f64; 2],
    pub t0: f64,
    pub t1: f64,
    pub on: bool,
}

/// A laser path in the x-y plane, segments in increasing time without gaps.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LaserPath {
    pub segments: Vec<Segment>,
}

impl LaserPath {
    /// Time at which the path ends [s].
    pub fn duration(&self) -> f64 {
        self.segments.last().map(|s| s.t1).unwrap_or(0.0)
    }

    /// Spot position at time `t`, or `None` when the laser is off (or the path has ended).
    pub fn spot(&self, t: f64) -> Option<[f64; 2]> {
        // Segments are few (tens); a binary search keeps long CSV paths cheap too.
        let k = self.segments.partition_point(|s| s.t1 <= t);
        let s = self.segments.get(k)?;
        if !s.on || t < s.t0 {
            return None;
        }
        let f = if s.t1 > s.t0 {
            (t - s.t0) / (s.t1 - s.t0)
        } else {
            0.0
        };
        Some([0, 1].map(|a| s.a[a] + f * (s.b[a] - s.a[a])))
    }

    /// Quadrature points of the lit part of [a, b]: (spot, weight) with weights summing to
    /// the lit fraction of the interval. Each lit piece of a segment gets midpoint samples
    /// at most `spacing` apart along the path, so switch-on and switch-off instants (ends
    /// of scan lines) are exact whatever the step length.
    pub fn samples(&self, a: f64, b: f64, spacing: f64, out: &mut Vec<([f64; 2], f64)>) {
        out.clear();
        if b <= a {
            return;
        }
        let k = self.segments.partition_point(|s| s.t1 <= a);
        for s in &self.segments[k..] {
            if s.t0 >= b {
                break;
            }
            if !s.on || s.t1 <= s.t0 {
                continue;
            }
            let (p0, p1) = (s.t0.max(a), s.t1.min(b));
            if p1 <= p0 {
                continue;
            }
            let speed = dist(s.a, s.b) / (s.t1 - s.t0);
            let nq = ((speed * (p1 - p0) / spacing).ceil() as usize).max(1);
            let w = (p1 - p0) / (b - a) / nq as f64;
            for q in 0..nq {
                let t = p0 + (q as f64 + 0.5) * (p1 - p0) / nq as f64;
                let f = (t - s.t0) / (s.t1 - s.t0);
                out.push(([0, 1].map(|c| s.a[c] + f * (s.b[c] - s.a[c])), w));
            }
        }
    }

    /// Builds a path that visits `points` at `speed`; `on[k]` says whether the laser is on
    /// while travelling to point k (k >= 1).
    pub fn polyline(points: &[[f64; 2]], on: &[bool], speed: f64) -> LaserPath {
        let mut t = 0.0;
        let mut segments = Vec::new();
        for k in 1..points.len() {
            let len = dist(points[k - 1], points[k]);
            let t1 = t + len / speed;
            segments.push(Segment {
                a: points[k - 1],
                b: points[k],
                t0: t,
                t1,
                on: on[k],
            });
            t = t1;
        }
        LaserPath { segments }
    }

    /// `passes` scan lines of length `length`, `hatch` apart, centred on `center`, along
    /// `axis`; every other line reversed when `alternate`. The beam jumps between lines in
    /// zero time with the laser off.
    pub fn raster(
        center: [f64; 2],
        length: f64,
        hatch: f64,
        passes: u32,
        alternate: bool,
        axis: ScanAxis,
        speed: f64,
    ) -> LaserPath {
        let (u, v) = match axis {
            ScanAxis::X => (0, 1),
            ScanAxis::Y => (1, 0),
        };
        let mut t = 0.0;
        let mut segments = Vec::new();
        for k in 0..passes {
            let off = (k as f64 - (passes as f64 - 1.0) / 2.0) * hatch;
            let mut a = [0.0; 2];
            let mut b = [0.0; 2];
            a[u] = center[u] - length / 2.0;
            b[u] = center[u] + length / 2.0;
            a[v] = center[v] + off;
            b[v] = center[v] + off;
            if alternate && k % 2 == 1 {
                std::mem::swap(&mut a, &mut b);
            }
            let t1 = t + length / speed;
            segments.push(Segment {
                a,
                b,
                t0: t,
                t1,
                on: true,
            });
            t = t1;
        }
        LaserPath { segments }
    }

    /// Reads a polyline CSV: a header line naming `x`, `y` and optionally `on`, then one
    /// vertex per line; coordinates are multiplied by `unit` [m].
    pub fn from_csv(text: &str, unit: f64, speed: f64) -> Result<LaserPath, PathError> {
        let mut lines = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
        let (_, header) = lines.next().ok_or(PathError::Empty)?;
        let names: Vec<String> = header
            .split(',')
            .map(|s| s.trim().to_ascii_lowercase())
            .collect();
        let col = |n: &str| names.iter().position(|c| c == n);
        let (ix, iy) = match (col("x"), col("y")) {
            (Some(x), Some(y)) => (x, y),
            _ => return Err(PathError::Header(header.to_string())),
        };
        let ion = col("on");
        let mut pts = Vec::new();
        let mut on = Vec::new();
        for (ln, line) in lines {
            let f: Vec<&str> = line.split(',').map(|s| s.trim()).collect();
            let num = |i: usize| -> Result<f64, PathError> {
                let s = f.get(i).ok_or(PathError::MissingColumn {
                    line: ln + 1,
                    column: i + 1,
                })?;
                s.parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| PathError::NotANumber {
                        line: ln + 1,
                        value: s.to_string(),
                    })
            };
            pts.push([num(ix)? * unit, num(iy)? * unit]);
            on.push(match ion {
                Some(i) => num(i)? != 0.0,
                None => true,
            });
        }
        if pts.len() < 2 {
            return Err(PathError::TooFewVertices(pts.len()));
        }
        Ok(LaserPath::polyline(&pts, &on, speed))
    }
}

fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn serpentine_raster_timing_and_positions() {
        // 5 lines of 500 um at 1 m/s: each takes exactly 500 us.
        let p = LaserPath::raster([0.0, 0.0], 500e-6, 100e-6, 5, true, ScanAxis::X, 1.0);
        assert!((p.duration() - 2.5e-3).abs() < 1e-15);
        let s = p.spot(250e-6).unwrap(); // middle of line 0
        assert!(s[0].abs() < 1e-15 && (s[1] + 200e-6).abs() < 1e-15);
        let s = p.spot(600e-6).unwrap(); // line 1 runs backwards: 100 um from its start at +250
        assert!((s[0] - 150e-6).abs() < 1e-12 && (s[1] + 100e-6).abs() < 1e-15);
        assert!(p.spot(2.6e-3).is_none());
        // An interval straddling the end of line 0 (t = 500 us): only its first 10 us
        // are lit on line 0, the rest on line 1; weights add up to the lit fraction 1.
        let mut q = Vec::new();
        p.samples(490e-6, 510e-6, 1e-3, &mut q);
        assert_eq!(q.len(), 2);
        assert!((q[0].1 - 0.5).abs() < 1e-12 && (q[1].1 - 0.5).abs() < 1e-12);
        assert!((q[0].0[0] - 245e-6).abs() < 1e-12 && (q[1].0[0] - 245e-6).abs() < 1e-12);
        p.samples(2.49e-3, 2.6e-3, 1e-3, &mut q);
        let lit: f64 = q.iter().map(|s| s.1).sum();
        assert!((lit - 10.0 / 110.0).abs() < 1e-9, "{lit}");
    }

    #[test]
    fn csv_polyline_with_laser_off_leg() {
        let csv = "x,y,on\n0,0,1\n100,0,1\n100,100,0\n0,100,1\n";
        let p = LaserPath::from_csv(csv, 1e-6, 0.5).unwrap();
        // 300 um at 0.5 m/s = 600 us.
        assert!((p.duration() - 600e-6).abs() < 1e-15);
        assert!(p.spot(300e-6).is_none(), "second leg is a jump");
        assert!(p.spot(500e-6).is_some());
        assert!(LaserPath::from_csv("a,b\n1,2\n", 1.0, 1.0).is_err());
        assert!(LaserPath::from_csv("x,y\n1,zz\n2,3\n", 1.0, 1.0).is_err());
    }
}
