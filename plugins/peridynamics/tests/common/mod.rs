//! Helpers shared by the peridynamics tests: images, runs, lattice reference values.
#![allow(dead_code)]

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::units::Q;
use grainpipe_core::{Grid, Phase, PhaseImage, RunContext};
use grainpipe_peridynamics::bond_based::{
    resolve_phases, solve_image, BondBasedParams, PhaseMaterial, PhaseRole, RunResult,
};
use indexmap::IndexMap;

pub const DX: f64 = 1e-6;

pub fn image(nx: usize, ny: usize, labels: Vec<u8>) -> PhaseImage {
    PhaseImage {
        grid: Grid {
            dims: [nx, ny, 1],
            spacing: [DX; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
        labels,
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 1,
                name: "large".into(),
            },
            Phase {
                id: 2,
                name: "small".into(),
            },
            Phase {
                id: 3,
                name: "matrix".into(),
            },
        ],
    }
}

/// A 3-D image (cubic voxels of edge DX) with the sample chain's phases.
pub fn image3(dims: [usize; 3], labels: Vec<u8>) -> PhaseImage {
    let mut img = image(dims[0], dims[1] * dims[2], labels);
    img.grid.dims = dims;
    img
}

pub fn matrix_material(e: f64) -> PhaseMaterial {
    PhaseMaterial {
        role: PhaseRole::Matrix,
        e: Q::new(e),
        toughness: Q::new(10.0),
    }
}

pub fn particle_material(e: f64) -> PhaseMaterial {
    PhaseMaterial {
        role: PhaseRole::Particle,
        e: Q::new(e),
        toughness: Q::new(30.0),
    }
}

pub fn run(p: &BondBasedParams, img: &PhaseImage) -> RunResult {
    try_run(p, img).unwrap_or_else(|e| panic!("{e}"))
}

pub fn try_run(
    p: &BondBasedParams,
    img: &PhaseImage,
) -> Result<RunResult, grainpipe_core::StageError> {
    let phases = resolve_phases(&p.materials, img)?;
    let rep = SilentReporter;
    let ctx = RunContext::new(1, &rep);
    solve_image(p, p.horizon, img, &phases, &ctx)
}

/// Materials map with one entry.
pub fn materials(entries: &[(&str, PhaseMaterial)]) -> IndexMap<String, PhaseMaterial> {
    entries
        .iter()
        .map(|(k, v)| (k.to_string(), v.clone()))
        .collect()
}

/// Lattice stiffness of a homogeneous 2-D plate (plane stress, scaled by E): the discrete
/// sum C_abcd = (c dx^2 / 2) sum_j xi_a xi_b xi_c xi_d / |xi|^3 over the stencil (what the
/// bond law gives under a uniform strain), with c dx^4 = 9 E dx / (pi H^3). Returns
/// (C11, C12) / E.
pub fn lattice_c(h: f64) -> (f64, f64) {
    let k = 9.0 / (std::f64::consts::PI * h.powi(3));
    let r = h.floor() as i32;
    let (mut c11, mut c12) = (0.0, 0.0);
    for y in -r..=r {
        for x in -r..=r {
            let l2 = (x * x + y * y) as f64;
            if l2 == 0.0 || l2 > h * h * (1.0 + 1e-9) {
                continue;
            }
            let l3 = l2.powf(1.5);
            c11 += (x as f64).powi(4) / l3;
            c12 += (x as f64).powi(2) * (y as f64).powi(2) / l3;
        }
    }
    (0.5 * k * c11, 0.5 * k * c12)
}

/// Lattice stiffness of a homogeneous 3-D body (scaled by E): the stencil sum
/// C_abcd = (c dx^4 / 2) sum_j m_a m_b m_c m_d / |m|^3 over integer offsets m within the
/// horizon, with c = 18K / (pi h^4), K = E / (3 (1 - 2 nu)), nu = 1/4, so c dx^4 = 12 E / (pi H^4)
/// for H = h / dx. (The integral over the ball gives C11 = 6/5 E, C12 = 2/5 E.) Returns
/// (C11, C12) / E.
pub fn lattice_c3(h: f64) -> (f64, f64) {
    let k = 12.0 / (std::f64::consts::PI * h.powi(4));
    let r = h.floor() as i32;
    let (mut c11, mut c12) = (0.0, 0.0);
    for z in -r..=r {
        for y in -r..=r {
            for x in -r..=r {
                let l2 = (x * x + y * y + z * z) as f64;
                if l2 == 0.0 || l2 > h * h * (1.0 + 1e-9) {
                    continue;
                }
                let l3 = l2.powf(1.5);
                c11 += (x as f64).powi(4) / l3;
                c12 += (x as f64).powi(2) * (y as f64).powi(2) / l3;
            }
        }
    }
    (0.5 * k * c11, 0.5 * k * c12)
}

/// Component `c` of the 3-D stress (xx, yy, zz, yz, xz, xy) at node (x, y, z).
pub fn s3(r: &RunResult, d: [usize; 3], [x, y, z]: [usize; 3], c: usize) -> f64 {
    r.stress[(x + d[0] * (y + d[1] * z)) * 6 + c] as f64
}

/// Component `c` of the 3-D displacement at node (x, y, z).
pub fn u3(r: &RunResult, d: [usize; 3], [x, y, z]: [usize; 3], c: usize) -> f64 {
    r.displacement[(x + d[0] * (y + d[1] * z)) * 3 + c] as f64
}

/// Component `c` of the 2-D stress (xx, yy, xy) at node (x, y).
pub fn s2(r: &RunResult, nx: usize, x: usize, y: usize, c: usize) -> f64 {
    r.stress[(x + nx * y) * 3 + c] as f64
}

/// Component `c` of the 2-D displacement at node (x, y).
pub fn u2(r: &RunResult, nx: usize, x: usize, y: usize, c: usize) -> f64 {
    r.displacement[(x + nx * y) * 2 + c] as f64
}

pub fn col_f64(t: &grainpipe_core::Table, name: &str) -> f64 {
    t.f64_column(name)
        .unwrap_or_else(|| panic!("column {name}"))[0]
}

pub fn col_i64(t: &grainpipe_core::Table, name: &str) -> i64 {
    match &t
        .column(name)
        .unwrap_or_else(|| panic!("column {name}"))
        .data
    {
        grainpipe_core::ColumnData::I64(v) => v[0],
        _ => panic!("column {name} is not integer"),
    }
}

/// Deterministic pseudo-random numbers in [0, 1) (splitmix64).
pub struct Rng(pub u64);
impl Rng {
    pub fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Disks of label `lab` painted into `labels` (nx wide).
pub fn paint_disk(labels: &mut [u8], nx: usize, cx: f64, cy: f64, r: f64, lab: u8) {
    let ny = labels.len() / nx;
    for y in 0..ny {
        for x in 0..nx {
            let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
            if dx * dx + dy * dy <= r * r {
                labels[x + nx * y] = lab;
            }
        }
    }
}
