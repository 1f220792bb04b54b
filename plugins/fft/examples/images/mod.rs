//! Test images shared by the FFT benchmark drivers (`fft_bench`, `fft_study`).

use grainpipe_core::{Grid, Phase, PhaseImage};

/// The pore is the set of voxel centres within r of the cell centre, r from the nominal
/// porosity 0.2 (r = 0.3628 of the cell: no overlap with the periodic images). The voxel
/// porosity differs from 0.2 by O(1/n); it is printed so the reference can account for it.
pub fn sphere_pore(n: usize) -> PhaseImage {
    let r = (0.2 * 3.0 / (4.0 * std::f64::consts::PI)).cbrt() * n as f64;
    let c = n as f64 / 2.0;
    let mut labels = vec![1u8; n * n * n];
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let d2: f64 = [x, y, z]
                    .iter()
                    .map(|&p| (p as f64 + 0.5 - c).powi(2))
                    .sum();
                if d2 < r * r {
                    labels[x + n * (y + n * z)] = 0;
                }
            }
        }
    }
    PhaseImage {
        grid: Grid {
            dims: [n; 3],
            spacing: [1.0 / n as f64; 3],
            origin: [0.0; 3],
            periodic: [true; 3],
        },
        labels,
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 1,
                name: "solid".into(),
            },
        ],
    }
}
