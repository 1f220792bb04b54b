//! Composite voxels (Kabel, Merkert & Schneider, CMAME 294 (2015) 168-188): a voxel cut by
//! an interface gets the effective stiffness (conductivity) of a rank-one laminate of its
//! phases, in their volume fractions, with lamination normal `n`: the strains (gradients)
//! tangential to the interface are continuous (Voigt along), the tractions (normal flux)
//! are continuous (Reuss across). A void phase makes the laminate traction-free across:
//! only the in-plane stiffness of the solid laminae remains (the "void lamina handled
//! stably": no division by a zero modulus, no penalty material).

use super::Iso;

pub type M6 = [[f64; 6]; 6];
type M3 = [[f64; 3]; 3];

/// Voigt index pairs (xx, yy, zz, yz, xz, xy).
const VOIGT: [(usize, usize); 6] = [(0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1)];

/// Stress of an isotropic phase for the symmetric strain `e`: `lambda tr(e) I + 2 mu e`.
fn stress(m: Iso, e: &M3) -> M3 {
    let tr = e[0][0] + e[1][1] + e[2][2];
    let mut s = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            s[i][j] = 2.0 * m.mu * e[i][j];
        }
        s[i][i] += m.lambda * tr;
    }
    s
}

fn mat_vec(a: &M3, v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| a[i][0] * v[0] + a[i][1] * v[1] + a[i][2] * v[2])
}

/// Inverse of the acoustic tensor `A = n.C.n = mu I + (lambda + mu) n n` of an isotropic
/// phase (`|n| = 1`): `(I - (lambda + mu) / (lambda + 2 mu) n n) / mu`.
fn acoustic_inverse(m: Iso, n: [f64; 3]) -> M3 {
    let b = (m.lambda + m.mu) / (m.lambda + 2.0 * m.mu);
    let mut a = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            a[i][j] = (f64::from(i == j) - b * n[i] * n[j]) / m.mu;
        }
    }
    a
}

fn inverse3(a: &M3) -> Option<M3> {
    let det = a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
        - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
        + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]);
    let scale = a.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
    if det.abs() <= 1e-14 * scale * scale * scale || !det.is_finite() {
        return None;
    }
    let mut inv = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let (r0, r1) = ((j + 1) % 3, (j + 2) % 3);
            let (c0, c1) = ((i + 1) % 3, (i + 2) % 3);
            inv[i][j] = (a[r0][c0] * a[r1][c1] - a[r0][c1] * a[r1][c0]) / det;
        }
    }
    Some(inv)
}

/// Whether a phase carries load in the laminate (a pore, or a degenerate material without
/// shear stiffness, counts as void).
fn is_solid(m: Iso) -> bool {
    m.mu > 0.0 && m.lambda + 2.0 * m.mu > 0.0
}

/// The 6x6 Voigt stiffness (engineering shear strains) of a rank-one laminate of isotropic
/// phases `(fraction, material)` with unit normal `n`. Fractions are renormalised to sum 1.
///
/// For a mean strain `E`, phase q holds `E + sym(a_q (x) n)` with jump `a_q`; traction
/// continuity `(C_q : (E + sym(a_q (x) n))) n = t` gives `a_q = A_q^-1 (t - (C_q:E) n)`
/// with the acoustic tensor `A_q = n.C_q.n`, and `sum_q f_q a_q = 0` gives
/// `t = <A^-1>^-1 <A^-1 (C:E) n>`; with a void lamina `t = 0`. The laminate stress is
/// `sum_q f_q C_q : (E + sym(a_q (x) n))` over the solid phases (Milton 2002, ch. 9).
pub fn laminate_stiffness(phases: &[(f64, Iso)], n: [f64; 3]) -> M6 {
    let total: f64 = phases.iter().map(|p| p.0).sum();
    let mut out = [[0.0; 6]; 6];
    if total <= 0.0 {
        return out;
    }
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    let n = n.map(|c| c / len);
    let parts: Vec<(f64, Iso)> = phases
        .iter()
        .filter(|p| p.0 > 0.0)
        .map(|&(f, m)| (f / total, m))
        .collect();
    let void = parts.iter().any(|p| !is_solid(p.1));
    let solids: Vec<(f64, Iso, M3)> = parts
        .iter()
        .filter(|p| is_solid(p.1))
        .map(|&(f, m)| (f, m, acoustic_inverse(m, n)))
        .collect();
    if solids.is_empty() {
        return out;
    }
    // <A^-1>^-1, used only without a void lamina.
    let mut mean_inv = [[0.0; 3]; 3];
    for (f, _, ai) in &solids {
        for i in 0..3 {
            for j in 0..3 {
                mean_inv[i][j] += f * ai[i][j];
            }
        }
    }
    let stiff_t = if void { None } else { inverse3(&mean_inv) };
    for (col, &(k, l)) in VOIGT.iter().enumerate() {
        // Unit engineering strain: E_kl = E_lk = 1/2 off the diagonal.
        let mut e = [[0.0; 3]; 3];
        if k == l {
            e[k][k] = 1.0;
        } else {
            e[k][l] = 0.5;
            e[l][k] = 0.5;
        }
        let traction: Vec<[f64; 3]> = solids
            .iter()
            .map(|(_, m, _)| mat_vec(&stress(*m, &e), n))
            .collect();
        let t = match stiff_t {
            Some(st) => {
                let mut rhs = [0.0; 3];
                for ((f, _, ai), b) in solids.iter().zip(&traction) {
                    let v = mat_vec(ai, *b);
                    for i in 0..3 {
                        rhs[i] += f * v[i];
                    }
                }
                mat_vec(&st, rhs)
            }
            None => [0.0; 3],
        };
        let mut mean = [[0.0; 3]; 3];
        for ((f, m, ai), b) in solids.iter().zip(&traction) {
            let a = mat_vec(ai, [t[0] - b[0], t[1] - b[1], t[2] - b[2]]);
            let mut eq = e;
            for i in 0..3 {
                for j in 0..3 {
                    eq[i][j] += 0.5 * (a[i] * n[j] + n[i] * a[j]);
                }
            }
            let s = stress(*m, &eq);
            for i in 0..3 {
                for j in 0..3 {
                    mean[i][j] += f * s[i][j];
                }
            }
        }
        for (row, &(i, j)) in VOIGT.iter().enumerate() {
            out[row][col] = mean[i][j];
        }
    }
    // Exactly symmetric (the construction is, up to rounding).
    for i in 0..6 {
        for j in 0..i {
            let s = 0.5 * (out[i][j] + out[j][i]);
            out[i][j] = s;
            out[j][i] = s;
        }
    }
    out
}

/// The stiffness of a composite voxel under the `majority` rule for pores: the laminate of
/// its solid phases ([`laminate_stiffness`] without the void) where they fill at least half
/// of the voxel, a pore otherwise. Why not the exact void laminate: it is traction-free
/// across the lamina however thin, so a voxel 1 % pore loses all normal stiffness, and on
/// sand images the neighbouring void laminae of different normals leave near-mechanisms
/// (CG stalled at 1.2e-5 after 3000 iterations on the 8 um sand core, where the labels
/// converge in 87-131).
pub fn majority_pore_stiffness(phases: &[(f64, Iso)], n: [f64; 3]) -> M6 {
    let total: f64 = phases.iter().map(|p| p.0).sum();
    let solids: Vec<(f64, Iso)> = phases.iter().copied().filter(|p| is_solid(p.1)).collect();
    let solid: f64 = solids.iter().map(|p| p.0).sum();
    if solids.is_empty() || solid < 0.5 * total {
        return [[0.0; 6]; 6];
    }
    laminate_stiffness(&solids, n)
}

/// The conductivity of a composite voxel under the `majority` rule for pores (see
/// [`majority_pore_stiffness`]).
pub fn majority_pore_conductivity(phases: &[(f64, f64)], n: [f64; 3]) -> [[f64; 3]; 3] {
    let total: f64 = phases.iter().map(|p| p.0).sum();
    let solids: Vec<(f64, f64)> = phases.iter().copied().filter(|p| p.1 > 0.0).collect();
    let solid: f64 = solids.iter().map(|p| p.0).sum();
    if solids.is_empty() || solid < 0.5 * total {
        return [[0.0; 3]; 3];
    }
    laminate_conductivity(&solids, n)
}

/// The 3x3 conductivity of a rank-one laminate of phases `(fraction, k)` with unit normal
/// `n`: the arithmetic mean along the interface, the harmonic mean across it (zero with a
/// zero-conductivity lamina), `k = k_V (I - n n) + k_R n n`. Row-major.
pub fn laminate_conductivity(phases: &[(f64, f64)], n: [f64; 3]) -> [[f64; 3]; 3] {
    let total: f64 = phases.iter().map(|p| p.0).sum();
    let mut out = [[0.0; 3]; 3];
    if total <= 0.0 {
        return out;
    }
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    let n = n.map(|c| c / len);
    let mut kv = 0.0;
    let mut resist = 0.0;
    let mut blocked = false;
    for &(f, k) in phases.iter().filter(|p| p.0 > 0.0) {
        let f = f / total;
        kv += f * k;
        if k > 0.0 {
            resist += f / k;
        } else {
            blocked = true;
        }
    }
    let kr = if blocked || resist <= 0.0 {
        0.0
    } else {
        1.0 / resist
    };
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = (kr - kv) * n[i] * n[j] + if i == j { kv } else { 0.0 };
        }
    }
    out
}

/// The composite voxels of an image: per voxel the slot of its laminate property
/// (`u32::MAX` for a pure voxel, which keeps its label's material) and the properties.
/// Shared by the load cases solved at once.
#[derive(Clone, Debug, Default)]
pub struct Composite<M> {
    pub slot: Vec<u32>,
    pub values: Vec<M>,
}

impl<M> Composite<M> {
    /// An empty table for `n` voxels.
    pub fn new(n: usize) -> Self {
        Composite {
            slot: vec![u32::MAX; n],
            values: vec![],
        }
    }
    /// Gives voxel `v` the laminate property `m`.
    pub fn push(&mut self, v: usize, m: M) {
        self.slot[v] = self.values.len() as u32;
        self.values.push(m);
    }
    /// The laminate property of voxel `v`, `None` for a pure voxel.
    #[inline(always)]
    pub fn get(&self, v: usize) -> Option<&M> {
        match self.slot[v] {
            u32::MAX => None,
            s => Some(&self.values[s as usize]),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Backus (1962) averages of isotropic layers normal to z, an independent closed form.
    fn backus(phases: &[(f64, Iso)]) -> M6 {
        let avg = |g: &dyn Fn(Iso) -> f64| phases.iter().map(|&(f, m)| f * g(m)).sum::<f64>();
        let c33 = 1.0 / avg(&|m| 1.0 / (m.lambda + 2.0 * m.mu));
        let r = avg(&|m| m.lambda / (m.lambda + 2.0 * m.mu));
        let c13 = c33 * r;
        let c11 = avg(&|m| 4.0 * m.mu * (m.lambda + m.mu) / (m.lambda + 2.0 * m.mu)) + r * r * c33;
        let c66 = avg(&|m| m.mu);
        let c12 = c11 - 2.0 * c66;
        let c44 = 1.0 / avg(&|m| 1.0 / m.mu);
        let mut c = [[0.0; 6]; 6];
        c[0][0] = c11;
        c[1][1] = c11;
        c[2][2] = c33;
        c[0][1] = c12;
        c[1][0] = c12;
        c[0][2] = c13;
        c[2][0] = c13;
        c[1][2] = c13;
        c[2][1] = c13;
        c[3][3] = c44;
        c[4][4] = c44;
        c[5][5] = c66;
        c
    }

    /// Rotates a Voigt stiffness (engineering shear) by `r` through the fourth-order tensor.
    fn rotate(c: &M6, r: &M3) -> M6 {
        let vi = |i: usize, j: usize| match (i.min(j), i.max(j)) {
            (0, 0) => 0,
            (1, 1) => 1,
            (2, 2) => 2,
            (1, 2) => 3,
            (0, 2) => 4,
            _ => 5,
        };
        let t = |i: usize, j: usize, k: usize, l: usize| c[vi(i, j)][vi(k, l)];
        let mut out = [[0.0; 6]; 6];
        for (a, &(i, j)) in VOIGT.iter().enumerate() {
            for (b, &(k, l)) in VOIGT.iter().enumerate() {
                let mut s = 0.0;
                for p in 0..3 {
                    for q in 0..3 {
                        for u in 0..3 {
                            for v in 0..3 {
                                s += r[i][p] * r[j][q] * r[k][u] * r[l][v] * t(p, q, u, v);
                            }
                        }
                    }
                }
                out[a][b] = s;
            }
        }
        out
    }

    fn close(a: &M6, b: &M6, tol: f64) {
        let scale = b.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
        for i in 0..6 {
            for j in 0..6 {
                assert!(
                    (a[i][j] - b[i][j]).abs() <= tol * scale,
                    "[{i}][{j}]: {} vs {}",
                    a[i][j],
                    b[i][j]
                );
            }
        }
    }

    /// Along z the laminate is Backus's; at any angle it is Backus's rotated, to 1e-12.
    #[test]
    fn laminate_is_backus_at_any_angle() {
        let sand = Iso::from_e_nu(66.9e9, 0.25);
        let binder = Iso::from_e_nu(43e9, 0.17);
        let phases = [(0.37, sand), (0.63, binder)];
        close(
            &laminate_stiffness(&phases, [0.0, 0.0, 1.0]),
            &backus(&phases),
            1e-12,
        );
        // Rotation taking e_z to n: r = rotation about axis (e_z x n).
        let normals: [[f64; 3]; 3] = [[1.0, 2.0, 3.0], [0.3, -0.9, 0.1], [1.0, 0.0, 0.0]];
        for n in normals {
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            let n: [f64; 3] = n.map(|c| c / l);
            // Orthonormal frame with third axis n: r's columns are (t1, t2, n).
            let helper = if n[0].abs() < 0.9 {
                [1.0, 0.0, 0.0]
            } else {
                [0.0, 1.0, 0.0]
            };
            let cross = |a: [f64; 3], b: [f64; 3]| {
                [
                    a[1] * b[2] - a[2] * b[1],
                    a[2] * b[0] - a[0] * b[2],
                    a[0] * b[1] - a[1] * b[0],
                ]
            };
            let t1 = cross(helper, n);
            let l1 = (t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2]).sqrt();
            let t1 = t1.map(|c| c / l1);
            let t2 = cross(n, t1);
            let r = [0, 1, 2].map(|i| [t1[i], t2[i], n[i]]);
            close(
                &laminate_stiffness(&phases, n),
                &rotate(&backus(&phases), &r),
                1e-12,
            );
        }
    }

    /// One phase is that phase; a void lamina leaves the in-plane (plane-stress) stiffness
    /// of the solid times its fraction and nothing across.
    #[test]
    fn single_phase_and_void_lamina() {
        let m = Iso::from_e_nu(10.0, 0.3);
        close(
            &laminate_stiffness(&[(1.0, m)], [0.6, 0.8, 0.0]),
            &m.voigt(),
            1e-14,
        );
        let c = laminate_stiffness(&[(0.4, m), (0.6, Iso::ZERO)], [0.0, 0.0, 1.0]);
        // plane stress: Q11 = E / (1 - nu^2), Q12 = nu Q11, Q66 = G
        let q11 = 10.0 / (1.0 - 0.09);
        let mut want = [[0.0; 6]; 6];
        want[0][0] = 0.4 * q11;
        want[1][1] = 0.4 * q11;
        want[0][1] = 0.4 * 0.3 * q11;
        want[1][0] = 0.4 * 0.3 * q11;
        want[5][5] = 0.4 * m.mu;
        close(&c, &want, 1e-13);
    }

    /// The majority rule: a voxel at least half solid is the laminate of its solid phases
    /// (the pore share dropped), one less than half solid is pore.
    #[test]
    fn majority_rule_for_pores() {
        let sand = Iso::from_e_nu(66.9e9, 0.25);
        let binder = Iso::from_e_nu(43e9, 0.17);
        let n = [0.0, 0.6, 0.8];
        let c = majority_pore_stiffness(&[(0.3, sand), (0.3, binder), (0.4, Iso::ZERO)], n);
        close(
            &c,
            &laminate_stiffness(&[(0.5, sand), (0.5, binder)], n),
            1e-14,
        );
        let c = majority_pore_stiffness(&[(0.2, sand), (0.2, binder), (0.6, Iso::ZERO)], n);
        assert_eq!(c, [[0.0; 6]; 6]);
        let k = majority_pore_conductivity(&[(0.55, 2.0), (0.45, 0.0)], n);
        assert!((k[0][0] - 2.0).abs() < 1e-15 && k[0][1] == 0.0);
        assert_eq!(
            majority_pore_conductivity(&[(0.45, 2.0), (0.55, 0.0)], n),
            [[0.0; 3]; 3]
        );
    }

    #[test]
    fn conductivity_laminate() {
        let k = laminate_conductivity(&[(0.25, 4.0), (0.75, 1.0)], [0.0, 0.6, 0.8]);
        let kv = 0.25 * 4.0 + 0.75;
        let kr = 1.0 / (0.25 / 4.0 + 0.75);
        // along n: kr; along a tangent: kv
        let n = [0.0, 0.6, 0.8];
        let t = [0.0, 0.8, -0.6];
        let quad = |v: [f64; 3]| {
            (0..3)
                .map(|i| (0..3).map(|j| v[i] * k[i][j] * v[j]).sum::<f64>())
                .sum::<f64>()
        };
        assert!((quad(n) - kr).abs() < 1e-14);
        assert!((quad(t) - kv).abs() < 1e-14);
        assert!((quad([1.0, 0.0, 0.0]) - kv).abs() < 1e-14);
        let blocked = laminate_conductivity(&[(0.5, 2.0), (0.5, 0.0)], [1.0, 0.0, 0.0]);
        assert_eq!(blocked[0][0], 0.0);
        assert!((blocked[1][1] - 1.0).abs() < 1e-15);
    }
}
