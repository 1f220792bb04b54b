//! Helpers shared by the tests: images, the stage run without the pipeline engine, and the
//! independent references (closed-form laminate stiffness).
#![allow(dead_code)]

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{Grid, Phase, PhaseImage, RunContext, StageError};
use grainpipe_fft::common::{Discretization, Material, Solver};
use grainpipe_fft::elasticity::{solve_all, ElasticResult, ElasticityParams};
use grainpipe_fft::kernel::Iso;
use indexmap::IndexMap;

pub fn image(dims: [usize; 3], h: f64, label: impl Fn(usize, usize, usize) -> u8) -> PhaseImage {
    let mut labels = Vec::with_capacity(dims.iter().product());
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                labels.push(label(x, y, z));
            }
        }
    }
    let mut ids: Vec<u8> = labels.clone();
    ids.sort();
    ids.dedup();
    PhaseImage {
        grid: Grid {
            dims,
            spacing: [h; 3],
            origin: [0.0; 3],
            periodic: [true; 3],
        },
        labels,
        phases: ids
            .iter()
            .map(|&id| Phase {
                id,
                name: if id == 0 {
                    "pore".into()
                } else {
                    format!("m{id}")
                },
            })
            .collect(),
    }
}

pub fn materials(list: &[(u8, f64, f64)]) -> IndexMap<String, Material> {
    list.iter()
        .map(|&(l, e, nu)| (l.to_string(), Material::e_nu(e, nu)))
        .collect()
}

pub fn params(
    mats: IndexMap<String, Material>,
    d: Discretization,
    s: Solver,
    tol: f64,
) -> ElasticityParams {
    ElasticityParams {
        materials: mats,
        discretization: d,
        solver: s,
        tolerance: tol,
        ..Default::default()
    }
}

/// Runs the stage's solver on an image (no engine), with per-label materials resolved as
/// the stage does.
pub fn stiffness(img: &PhaseImage, p: &ElasticityParams) -> Result<ElasticResult, StageError> {
    let mats =
        grainpipe_fft::common::resolve("materials", &p.materials, img, Iso::ZERO, |m| m.iso())?;
    let rep = SilentReporter;
    let ctx = RunContext::new(1, &rep);
    match p.precision {
        grainpipe_fft::common::Precision::F64 => solve_all::<f64>(p, img, &mats, None, &ctx),
        grainpipe_fft::common::Precision::F32 => solve_all::<f32>(p, img, &mats, None, &ctx),
    }
}

pub type M6 = [[f64; 6]; 6];

fn sub(m: &M6, r: &[usize], c: &[usize]) -> Vec<Vec<f64>> {
    r.iter()
        .map(|&i| c.iter().map(|&j| m[i][j]).collect())
        .collect()
}

fn inv3(a: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let n = a.len();
    let mut m: Vec<Vec<f64>> = a.to_vec();
    let mut inv: Vec<Vec<f64>> = (0..n)
        .map(|i| (0..n).map(|j| if i == j { 1.0 } else { 0.0 }).collect())
        .collect();
    for k in 0..n {
        let p = m[k][k];
        for j in 0..n {
            m[k][j] /= p;
            inv[k][j] /= p;
        }
        for i in 0..n {
            if i != k {
                let f = m[i][k];
                for j in 0..n {
                    m[i][j] -= f * m[k][j];
                    inv[i][j] -= f * inv[k][j];
                }
            }
        }
    }
    inv
}

fn mul(a: &[Vec<f64>], b: &[Vec<f64>]) -> Vec<Vec<f64>> {
    (0..a.len())
        .map(|i| {
            (0..b[0].len())
                .map(|j| (0..b.len()).map(|k| a[i][k] * b[k][j]).sum())
                .collect()
        })
        .collect()
}

fn add(a: &mut [Vec<f64>], b: &[Vec<f64>], f: f64) {
    for i in 0..a.len() {
        for j in 0..a[0].len() {
            a[i][j] += f * b[i][j];
        }
    }
}

fn zeros(r: usize, c: usize) -> Vec<Vec<f64>> {
    vec![vec![0.0; c]; r]
}

/// Exact stiffness of a laminate of layers normal to `axis` (volume fraction, stiffness;
/// `None` = void): the traction components t (normal and the two shears through `axis`) are
/// continuous, the in-plane strains p uniform (Backus 1962 / the classical layered-medium
/// formulas): C_tt = <C_tt^-1>^-1, C_tp = C_tt <C_tt^-1 C_tp>,
/// C_pp = <C_pp - C_pt C_tt^-1 C_tp> + <C_pt C_tt^-1> C_tt <C_tt^-1 C_tp>.
pub fn laminate(axis: usize, layers: &[(f64, Option<Iso>)]) -> M6 {
    let (t, p): (Vec<usize>, Vec<usize>) = match axis {
        0 => (vec![0, 4, 5], vec![1, 2, 3]),
        1 => (vec![1, 3, 5], vec![0, 2, 4]),
        _ => (vec![2, 3, 4], vec![0, 1, 5]),
    };
    let void = layers.iter().any(|l| l.1.is_none());
    let mut s_tt = zeros(3, 3); // <C_tt^-1>
    let mut a_tp = zeros(3, 3); // <C_tt^-1 C_tp>
    let mut a_pt = zeros(3, 3); // <C_pt C_tt^-1>
    let mut c_pp = zeros(3, 3); // <C_pp - C_pt C_tt^-1 C_tp>
    for (f, m) in layers {
        let Some(m) = m else { continue };
        let c = m.voigt();
        let itt = inv3(&sub(&c, &t, &t));
        let ctp = sub(&c, &t, &p);
        let cpt = sub(&c, &p, &t);
        add(&mut s_tt, &itt, *f);
        add(&mut a_tp, &mul(&itt, &ctp), *f);
        add(&mut a_pt, &mul(&cpt, &itt), *f);
        let mut schur = sub(&c, &p, &p);
        add(&mut schur, &mul(&cpt, &mul(&itt, &ctp)), -1.0);
        add(&mut c_pp, &schur, *f);
    }
    let mut out = [[0.0; 6]; 6];
    if void {
        for i in 0..3 {
            for j in 0..3 {
                out[p[i]][p[j]] = c_pp[i][j];
            }
        }
        return out;
    }
    let ctt = inv3(&s_tt);
    let ctp = mul(&ctt, &a_tp);
    let mut cpp = c_pp.clone();
    add(&mut cpp, &mul(&a_pt, &ctp), 1.0);
    for i in 0..3 {
        for j in 0..3 {
            out[t[i]][t[j]] = ctt[i][j];
            out[t[i]][p[j]] = ctp[i][j];
            out[p[i]][t[j]] = ctp[j][i];
            out[p[i]][p[j]] = cpp[i][j];
        }
    }
    out
}

/// Frobenius distance relative to the reference.
pub fn rel(a: &M6, b: &M6) -> f64 {
    let d: f64 = (0..6)
        .flat_map(|i| (0..6).map(move |j| (i, j)))
        .map(|(i, j)| (a[i][j] - b[i][j]).powi(2))
        .sum();
    let n: f64 = b.iter().flatten().map(|x| x * x).sum();
    (d / n).sqrt()
}

/// Deterministic pseudo-random numbers in [0, 1) (the tests need fixed geometries, not
/// statistical quality).
pub fn lcg(s: &mut u64) -> f64 {
    *s = s
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (*s >> 11) as f64 / (1u64 << 53) as f64
}

/// `count` random sphere centres in the unit cube and their common radius.
pub fn random_spheres(seed: u64, count: usize) -> Vec<[f64; 3]> {
    let mut s = seed;
    (0..count)
        .map(|_| [lcg(&mut s), lcg(&mut s), lcg(&mut s)])
        .collect()
}

/// Periodic overlapping spheres (radius `r` in cell units) voxelized at `n`^3: `inside`
/// where a voxel centre lies in a sphere, else `outside`.
pub fn spheres_image(
    n: usize,
    centres: &[[f64; 3]],
    r: f64,
    inside: u8,
    outside: u8,
) -> PhaseImage {
    image([n; 3], 1.0 / n as f64, |x, y, z| {
        let p = [x, y, z].map(|v| (v as f64 + 0.5) / n as f64);
        let hit = centres.iter().any(|c| {
            (0..3)
                .map(|a| {
                    let d = (p[a] - c[a]).abs();
                    let d = d.min(1.0 - d);
                    d * d
                })
                .sum::<f64>()
                < r * r
        });
        if hit {
            inside
        } else {
            outside
        }
    })
}
