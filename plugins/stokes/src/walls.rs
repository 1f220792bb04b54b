//! The permeameter (`boundary: walls`) on the periodic MAC solver, in voxel units (h = 1,
//! mu = 1, body force f = 1), free of framework types.
//!
//! A laboratory permeameter holds the sample in an impermeable sleeve between an inlet and an
//! outlet reservoir. Here, for a flow along axis `a`, the sample is padded at its high end:
//! - one solid voxel layer across every non-periodic axis beside the flow: with the periodic
//!   wrap it is a no-slip wall on both faces of the sample (the MAC walls sit on voxel faces,
//!   so the walls are exactly the sample's faces);
//! - `buffer` fluid voxel layers along a non-periodic flow axis: the reservoirs, joining the
//!   outlet to the inlet through the wrap, where the flow leaving the sample redistributes
//!   before it enters again.
//!
//! The padded cell is solved by the periodic solver under a uniform body force. The driving
//! pressure is the total pressure P = p - f x (`p` the periodic pressure of the solve, eq.
//! (3.6) with the body force as a potential); the apparent permeability is Darcy's law over
//! the sample, kappa = mu Q L / (A dP), with Q the flow rate (the same through every
//! section; from the solver's cell mean, so with its quadrature), A the sample's cross-section, L its length and dP the drop of the cross-section
//! mean of P between the inlet and outlet faces, each extrapolated linearly from the two
//! buffer layers next to the face (exact for the developed flow of a duct, whose pressure
//! is linear). Along a periodic flow axis there is no buffer: dP = f L and kappa = mu Q / A.

use rayon::prelude::*;

/// Where the sample sits in the padded cell of one flow direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WallsLayout {
    /// Dims of the sample.
    pub sample: [usize; 3],
    /// Dims of the padded cell.
    pub padded: [usize; 3],
    /// Flow axis.
    pub flow: usize,
    /// Axes with a wall layer.
    pub walls: [bool; 3],
    /// Buffer layers along the flow axis (0 when it is periodic).
    pub buffer: usize,
}

impl WallsLayout {
    /// The padded cell for a flow along `flow` through a sample of dims `sample` that is
    /// periodic along `periodic`, with `buffer` reservoir layers on a non-periodic flow axis.
    pub fn new(sample: [usize; 3], periodic: [bool; 3], flow: usize, buffer: usize) -> Self {
        let walls = [0, 1, 2].map(|b| b != flow && !periodic[b]);
        let buffer = if periodic[flow] { 0 } else { buffer };
        let padded = [0, 1, 2].map(|b| {
            sample[b]
                + if b == flow {
                    buffer
                } else {
                    usize::from(walls[b])
                }
        });
        WallsLayout {
            sample,
            padded,
            flow,
            walls,
            buffer,
        }
    }

    pub fn padded_len(&self) -> usize {
        self.padded.iter().product()
    }

    /// Voxels of the buffer layers inside the sleeve (all fluid).
    pub fn buffer_voxels(&self) -> usize {
        self.buffer * self.cross_section()
    }

    /// Voxel faces of the sample's cross-section normal to the flow.
    pub fn cross_section(&self) -> usize {
        (0..3)
            .filter(|&b| b != self.flow)
            .map(|b| self.sample[b])
            .product()
    }

    /// `data` (one value per sample voxel, x fastest) in the padded cell: `solid` in the wall
    /// layers (also where they cross the buffer), `fluid` in the buffer layers.
    pub fn pad<T: Copy + Send + Sync>(&self, data: &[T], solid: T, fluid: T) -> Vec<T> {
        let [sx, sy, sz] = self.sample;
        assert_eq!(data.len(), sx * sy * sz);
        let [px, py, pz] = self.padded;
        let mut out = vec![solid; px * py * pz];
        out.par_chunks_mut(px * py)
            .enumerate()
            .for_each(|(z, plane)| {
                for y in 0..py {
                    for x in 0..px {
                        let at = [x, y, z];
                        let v = if (0..3).any(|b| b != self.flow && at[b] >= self.sample[b]) {
                            solid
                        } else if at[self.flow] >= self.sample[self.flow] {
                            fluid
                        } else {
                            data[x + sx * (y + sy * z)]
                        };
                        plane[x + px * y] = v;
                    }
                }
            });
        out
    }

    /// Sum over the sample's cross-section of `v` (a padded-cell array) at flow coordinate
    /// `c`, and the number of voxels summed.
    fn layer_sum(&self, v: &[f32], c: usize) -> (f64, usize) {
        let a = self.flow;
        let [px, py, _] = self.padded;
        let (b1, b2) = match a {
            0 => (1, 2),
            1 => (0, 2),
            _ => (0, 1),
        };
        let mut sum = 0.0;
        for j in 0..self.sample[b2] {
            for i in 0..self.sample[b1] {
                let mut at = [0; 3];
                at[a] = c;
                at[b1] = i;
                at[b2] = j;
                sum += v[at[0] + px * (at[1] + py * at[2])] as f64;
            }
        }
        (sum, self.sample[b1] * self.sample[b2])
    }

    /// The permeameter's reading from the solution `[u_x | u_y | u_z | p]` of the padded
    /// cell under a unit body force along the flow axis, and the solver's cell mean of the
    /// velocity along the flow (`mean_velocity`, with the quadrature weights of sub-voxel
    /// walls where they are used).
    pub fn apparent(&self, solution: &[f32], mean_velocity: f64) -> Permeameter {
        let n = self.padded_len();
        assert_eq!(solution.len(), 4 * n);
        let a = self.flow;
        let length = self.sample[a];
        let total = self.padded[a];
        let u = &solution[a * n..(a + 1) * n];
        let p = &solution[3 * n..];
        // u_a[i] is on the face between voxel i and i + e_a: the outlet face is the +a face
        // of the sample's last layer, the inlet face the +a face of the cell's last layer
        // (the wrap joins it to the sample's first).
        let q_out = self.layer_sum(u, length - 1).0;
        let q_in = self.layer_sum(u, total - 1).0;
        let area = self.cross_section() as f64;
        // The flow rate is the same through every cross-section (div u = 0), so the cell
        // mean times the cell's cross-section is it, with the solver's own quadrature of the
        // profile (the sub-voxel walls weight the faces next to a wall); with label walls it
        // is the plain sum over any one section. The two face sums check the mass balance.
        let q = mean_velocity * (n / total) as f64;
        let (pressure_drop, outlet_pressure) = if self.buffer == 0 {
            // Periodic along the flow: the body force alone drives it, f L. The total
            // pressure at the inlet face is about the first layer's mean of p (P = p - x at
            // its centre x = 1/2, plus the mean gradient 1 over half a voxel), L less at the
            // outlet.
            let (s, m) = self.layer_sum(p, 0);
            (length as f64, s / m as f64 - length as f64)
        } else {
            // Total pressure P = p - x at the centre x of buffer layer c (x unwrapped so the
            // inlet side lies before 0), extrapolated to the faces at x = 0 and x = L.
            let total_p = |c: usize, x: f64| {
                let (s, m) = self.layer_sum(p, c);
                s / m as f64 - x
            };
            let l = length as f64;
            let out1 = total_p(length, l + 0.5);
            let out2 = total_p(length + 1, l + 1.5);
            let in1 = total_p(total - 1, -0.5);
            let in2 = total_p(total - 2, -1.5);
            let p_inlet = in1 + 0.5 * (in1 - in2);
            let p_outlet = out1 - 0.5 * (out2 - out1);
            (p_inlet - p_outlet, p_outlet)
        };
        Permeameter {
            kappa: q * length as f64 / (area * pressure_drop),
            flow_rate: q,
            pressure_drop,
            outlet_pressure,
            imbalance: if q != 0.0 {
                (q_in - q_out).abs() / q.abs()
            } else {
                0.0
            },
        }
    }
}

/// What the permeameter reads, in voxel units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Permeameter {
    /// Apparent permeability / h^2 along the flow.
    pub kappa: f64,
    /// Flow rate through the sample: the cell mean of the velocity times the cell's
    /// cross-section.
    pub flow_rate: f64,
    /// Drop of the total pressure from the inlet to the outlet face.
    pub pressure_drop: f64,
    /// Total pressure at the outlet face (the solve's pressure is defined up to a constant).
    pub outlet_pressure: f64,
    /// |Q_in - Q_out| / Q: the mass balance of the sample.
    pub imbalance: f64,
}

/// Smallest buffer: the pressure at each face is extrapolated from two buffer layers.
pub const MIN_BUFFER: usize = 2;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_padded_cell_has_walls_beside_and_buffers_along_the_flow() {
        let l = WallsLayout::new([4, 3, 2], [false, true, false], 0, 3);
        assert_eq!(l.walls, [false, false, true]);
        assert_eq!(l.padded, [7, 3, 3]);
        assert_eq!(l.cross_section(), 6);
        let data: Vec<u8> = (0..24).map(|i| 10 + i as u8).collect();
        let p = l.pad(&data, 0, 1);
        for z in 0..3 {
            for y in 0..3 {
                for x in 0..7 {
                    let want = if z >= 2 {
                        0
                    } else if x >= 4 {
                        1
                    } else {
                        data[x + 4 * (y + 3 * z)]
                    };
                    assert_eq!(p[x + 7 * (y + 3 * z)], want, "{x} {y} {z}");
                }
            }
        }
        // a periodic flow axis gets no buffer
        assert_eq!(
            WallsLayout::new([4, 3, 2], [true; 3], 0, 3).padded,
            [4, 3, 2]
        );
    }
}
