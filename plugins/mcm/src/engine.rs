//! Overlap removal for clusters of overlapping spheres (Donval et al. 2025, section 2.2):
//! the overlap energy of eqs. (2.4)-(2.6), its gradient with respect to centroids and
//! orientations, FIRE minimisation with rotations through the exponential map (eq. 2.8),
//! Verlet lists built from a periodic cell list over bounding spheres (Remark 3), periodic
//! images in x, y, z (Remark 4), a minimum gap (Remark 5) and the soft layer box (Remark 4).

use nalgebra::{UnitQuaternion, Vector3};
use rayon::prelude::*;

type V3 = Vector3<f64>;

/// A rigid grain shape: spheres (offset in the body frame, radius).
#[derive(Clone, Debug)]
pub struct Shape {
    pub offsets: Vec<V3>,
    pub radii: Vec<f64>,
    /// max |offset| + radius.
    pub bound: f64,
}

impl Shape {
    pub fn new(spheres: impl IntoIterator<Item = ([f64; 3], f64)>) -> Self {
        let (offsets, radii): (Vec<V3>, Vec<f64>) =
            spheres.into_iter().map(|(o, r)| (V3::from(o), r)).unzip();
        let bound = offsets
            .iter()
            .zip(&radii)
            .map(|(o, r)| o.norm() + r)
            .fold(0.0, f64::max);
        Shape {
            offsets,
            radii,
            bound,
        }
    }
}

#[derive(Clone, Debug)]
pub struct Grain {
    pub shape: usize,
    pub pos: V3,
    pub rot: UnitQuaternion<f64>,
    pub frozen: bool,
    /// Soft box on the centroid's z (Remark 4), `None` in mcm.classic.
    pub zbox: Option<(f64, f64)>,
}

/// One neighbour image: body `j` displaced by `shift` (periodic image, already including the
/// offset between wrapped and unwrapped positions at list-build time).
#[derive(Clone, Copy, Debug)]
struct Nb {
    j: usize,
    shift: V3,
}

pub struct System {
    pub shapes: Vec<Shape>,
    pub grains: Vec<Grain>,
    /// Periodic cell size.
    pub cell: [f64; 3],
    /// Gap added to every sphere pair's contact distance (Remark 5 plus the convergence margin).
    pub gap: f64,
    /// Overlap tolerance: converged when every delta_ij and every box violation is below it.
    pub tol: f64,
    nbs: Vec<Vec<Nb>>,
    moved: Vec<f64>,
    skin: f64,
}

/// Outcome of one minimisation.
#[derive(Clone, Copy, Debug)]
pub struct Minimised {
    pub converged: bool,
    pub iterations: usize,
    pub energy: f64,
    pub max_delta: f64,
}

struct Eval {
    force: Vec<V3>,
    torque: Vec<V3>,
    energy: f64,
    max_violation: f64,
}

impl System {
    pub fn new(shapes: Vec<Shape>, grains: Vec<Grain>, cell: [f64; 3], gap: f64, tol: f64) -> Self {
        let n = grains.len();
        System {
            shapes,
            grains,
            cell,
            gap,
            tol,
            nbs: vec![Vec::new(); n],
            moved: vec![f64::INFINITY; n],
            skin: 0.0,
        }
    }

    fn bound(&self, i: usize) -> f64 {
        self.shapes[self.grains[i].shape].bound
    }

    /// Rebuilds the Verlet lists: cell list over bounding spheres with every periodic image
    /// inside the cut-off (so cells smaller than the cut-off are handled; Remark 3).
    pub fn rebuild(&mut self) {
        let n = self.grains.len();
        // Verlet skin: 0.3 mean bounding radii (lists rebuilt after half a skin of motion).
        self.skin = 0.3 * (0..n).map(|i| self.bound(i)).sum::<f64>() / n.max(1) as f64;
        let bmax = (0..n).map(|i| self.bound(i)).fold(0.0, f64::max);
        let cut = 2.0 * bmax + self.gap + self.skin;
        let l = self.cell;
        let nc: [usize; 3] = [0, 1, 2].map(|a| ((l[a] / cut).floor() as usize).clamp(1, 64));
        let cs: [f64; 3] = [0, 1, 2].map(|a| l[a] / nc[a] as f64);
        let mut wrapped = Vec::with_capacity(n);
        let mut cells: Vec<Vec<usize>> = vec![Vec::new(); nc[0] * nc[1] * nc[2]];
        for (i, g) in self.grains.iter().enumerate() {
            let w: [f64; 3] = [0, 1, 2].map(|a| g.pos[a].rem_euclid(l[a]));
            let c: [usize; 3] = [0, 1, 2].map(|a| ((w[a] / cs[a]) as usize).min(nc[a] - 1));
            cells[(c[2] * nc[1] + c[1]) * nc[0] + c[0]].push(i);
            wrapped.push((V3::from(w), c));
        }
        let reach: [i64; 3] = [0, 1, 2].map(|a| (cut / cs[a]).ceil() as i64);
        let grains = &self.grains;
        let shapes = &self.shapes;
        let gap = self.gap;
        let skin = self.skin;
        self.nbs = (0..n)
            .into_par_iter()
            .map(|i| {
                let (wi, ci) = wrapped[i];
                let bi = shapes[grains[i].shape].bound;
                let mut out = Vec::new();
                for dz in -reach[2]..=reach[2] {
                    for dy in -reach[1]..=reach[1] {
                        for dx in -reach[0]..=reach[0] {
                            let d = [dx, dy, dz];
                            let mut idx = [0usize; 3];
                            let mut img = V3::zeros();
                            for a in 0..3 {
                                let c = ci[a] as i64 + d[a];
                                let k = c.div_euclid(nc[a] as i64);
                                idx[a] = c.rem_euclid(nc[a] as i64) as usize;
                                img[a] = k as f64 * l[a];
                            }
                            for &j in &cells[(idx[2] * nc[1] + idx[1]) * nc[0] + idx[0]] {
                                if j == i && img == V3::zeros() {
                                    continue;
                                }
                                let (wj, _) = wrapped[j];
                                let bj = shapes[grains[j].shape].bound;
                                let sep = wi - (wj + img);
                                if sep.norm() < bi + bj + gap + skin {
                                    // shift such that pos_i - (pos_j + shift) = sep
                                    let shift = img + (wj - grains[j].pos) - (wi - grains[i].pos);
                                    out.push(Nb { j, shift });
                                }
                            }
                        }
                    }
                }
                out
            })
            .collect();
        self.moved = vec![0.0; n];
    }

    fn world(&self) -> Vec<Vec<V3>> {
        self.grains
            .par_iter()
            .map(|g| {
                self.shapes[g.shape]
                    .offsets
                    .iter()
                    .map(|o| g.rot * o)
                    .collect()
            })
            .collect()
    }

    /// Overlap energy (eq. 2.6) plus the soft-box penalty, forces = -grad_c E and torques
    /// = -grad_R E as axial vectors. Each body's force is summed over its own neighbour
    /// list in list order, so the result does not depend on the number of threads.
    fn evaluate(&self) -> Eval {
        let world = self.world();
        let gap = self.gap;
        let per: Vec<(V3, V3, f64, f64)> = (0..self.grains.len())
            .into_par_iter()
            .map(|i| {
                let gi = &self.grains[i];
                let si = &self.shapes[gi.shape];
                let mut f = V3::zeros();
                let mut t = V3::zeros();
                let mut e = 0.0;
                let mut vmax: f64 = 0.0;
                if gi.frozen {
                    // Frozen grains do not move: their pairs with mobile grains are counted
                    // from the mobile side, frozen-frozen overlaps and frozen soft boxes are
                    // constants of the layer being packed (at most the previous layer's tol).
                    return (f, t, e, vmax);
                }
                for nb in &self.nbs[i] {
                    let gj = &self.grains[nb.j];
                    let sj = &self.shapes[gj.shape];
                    let cj = gj.pos + nb.shift;
                    let sep = gi.pos - cj;
                    if sep.norm() >= si.bound + sj.bound + gap {
                        continue;
                    }
                    // Remark 3: only spheres inside the other's bounding sphere can touch.
                    let ai: Vec<usize> = (0..si.radii.len())
                        .filter(|&a| {
                            (gi.pos + world[i][a] - cj).norm() < si.radii[a] + sj.bound + gap
                        })
                        .collect();
                    if ai.is_empty() {
                        continue;
                    }
                    // eq. (2.4): delta_ij is the largest sphere-pair overlap.
                    let mut best = 0.0;
                    let mut arg: Option<(usize, V3)> = None;
                    for b in 0..sj.radii.len() {
                        let pb = cj + world[nb.j][b];
                        if (pb - gi.pos).norm() >= sj.radii[b] + si.bound + gap {
                            continue;
                        }
                        for &a in &ai {
                            let pa = gi.pos + world[i][a];
                            let d = pa - pb;
                            let delta = si.radii[a] + sj.radii[b] + gap - d.norm();
                            if delta > best {
                                best = delta;
                                arg = Some((a, d));
                            }
                        }
                    }
                    if let Some((a, d)) = arg {
                        let nrm = d.norm();
                        let n = if nrm > 1e-300 {
                            d / nrm
                        } else if sep.norm() > 1e-300 {
                            sep / sep.norm()
                        } else {
                            V3::x()
                        };
                        // -dE/dc_i of 1/2 delta^2 (each pair is met from both sides; the
                        // energy counts 1/2 of each side).
                        let fi = n * best;
                        f += fi;
                        t += world[i][a].cross(&fi);
                        e += if gj.frozen { 0.5 } else { 0.25 } * best * best;
                        vmax = vmax.max(best);
                    }
                }
                if let Some((lo, hi)) = gi.zbox {
                    // Remark 4: soft box on the centroid, quadratic penalty.
                    let z = gi.pos.z;
                    let v = if z < lo {
                        lo - z
                    } else if z > hi {
                        hi - z
                    } else {
                        0.0
                    };
                    f.z += v;
                    e += 0.5 * v * v;
                    vmax = vmax.max(v.abs());
                }
                (f, t, e, vmax)
            })
            .collect();
        let mut energy = 0.0;
        let mut max_violation: f64 = 0.0;
        for p in &per {
            energy += p.2;
            max_violation = max_violation.max(p.3);
        }
        Eval {
            force: per.iter().map(|p| p.0).collect(),
            torque: per.iter().map(|p| p.1).collect(),
            energy,
            max_violation,
        }
    }

    /// Current overlap energy and largest violation.
    pub fn energy(&mut self) -> (f64, f64) {
        self.rebuild();
        let e = self.evaluate();
        (e.energy, e.max_violation)
    }

    /// FIRE (Bitzek et al. 2006) on centroids and rotation vectors scaled by the bounding
    /// radius (so both are lengths with unit mass). Orientation updates are
    /// R <- exp([omega dt]x) R (eq. 2.8). Stops when every violation is below `tol`.
    pub fn minimise(&mut self, max_iter: usize) -> Minimised {
        const N_MIN: usize = 5;
        const F_INC: f64 = 1.1;
        const F_DEC: f64 = 0.5;
        const ALPHA0: f64 = 0.1;
        const F_ALPHA: f64 = 0.99;
        let n = self.grains.len();
        let bmin = (0..n).map(|i| self.bound(i)).fold(f64::INFINITY, f64::min);
        // Forces are overlaps (lengths) with unit stiffness: dt ~ 0.1-0.5 is stable for a
        // dozen contacts per grain.
        let dt_max = 0.5;
        let mut dt = 0.1;
        let mut alpha = ALPHA0;
        let mut npos = 0usize;
        let max_step = 0.1 * bmin;
        let mut v = vec![V3::zeros(); n];
        let mut w = vec![V3::zeros(); n];
        if self.moved.len() != n || self.moved.iter().any(|m| !m.is_finite()) {
            self.rebuild();
        }
        let mut ev = self.evaluate();
        for it in 0..max_iter {
            if ev.max_violation <= self.tol {
                return Minimised {
                    converged: true,
                    iterations: it,
                    energy: ev.energy,
                    max_delta: ev.max_violation,
                };
            }
            let b: Vec<f64> = (0..n).map(|i| self.bound(i)).collect();
            let gf: Vec<V3> = (0..n).map(|i| ev.torque[i] / b[i]).collect();
            let mut p = 0.0;
            let mut vn = 0.0;
            let mut fnorm = 0.0;
            for i in 0..n {
                p += ev.force[i].dot(&v[i]) + gf[i].dot(&w[i]);
                vn += v[i].norm_squared() + w[i].norm_squared();
                fnorm += ev.force[i].norm_squared() + gf[i].norm_squared();
            }
            let (vn, fnorm) = (vn.sqrt(), fnorm.sqrt());
            if p > 0.0 {
                if fnorm > 0.0 {
                    let c = alpha * vn / fnorm;
                    for i in 0..n {
                        v[i] = v[i] * (1.0 - alpha) + ev.force[i] * c;
                        w[i] = w[i] * (1.0 - alpha) + gf[i] * c;
                    }
                }
                npos += 1;
                if npos > N_MIN {
                    dt = (dt * F_INC).min(dt_max);
                    alpha *= F_ALPHA;
                }
            } else {
                npos = 0;
                dt *= F_DEC;
                alpha = ALPHA0;
                v.iter_mut().for_each(|x| *x = V3::zeros());
                w.iter_mut().for_each(|x| *x = V3::zeros());
            }
            let mut max_moved: f64 = 0.0;
            for i in 0..n {
                if self.grains[i].frozen {
                    continue;
                }
                v[i] += ev.force[i] * dt;
                w[i] += gf[i] * dt;
                let mut dx = v[i] * dt;
                let mut dth = w[i] * dt;
                let s = (dx.norm() + dth.norm()) / max_step;
                if s > 1.0 {
                    dx /= s;
                    dth /= s;
                }
                self.grains[i].pos += dx;
                // eq. (2.8): rotation through the exponential map of the axial vector.
                let ang = dth / b[i];
                self.grains[i].rot = UnitQuaternion::from_scaled_axis(ang) * self.grains[i].rot;
                self.moved[i] += dx.norm() + dth.norm();
                max_moved = max_moved.max(self.moved[i]);
            }
            if 2.0 * max_moved > self.skin {
                self.rebuild();
            }
            ev = self.evaluate();
        }
        Minimised {
            converged: ev.max_violation <= self.tol,
            iterations: max_iter,
            energy: ev.energy,
            max_delta: ev.max_violation,
        }
    }

    /// Largest overlap delta_ij (eq. 2.4, with the gap) of grain `i` against grains `others`,
    /// over the periodic images within one cell of the minimum image (brute force; used for
    /// the initial placement only).
    pub fn max_overlap(&self, i: usize, others: std::ops::Range<usize>) -> f64 {
        let gi = &self.grains[i];
        let si = &self.shapes[gi.shape];
        let wi: Vec<V3> = si.offsets.iter().map(|o| gi.pos + gi.rot * o).collect();
        let mut worst: f64 = 0.0;
        for j in others {
            if j == i {
                continue;
            }
            let gj = &self.grains[j];
            let sj = &self.shapes[gj.shape];
            let mut d = gi.pos - gj.pos;
            for a in 0..3 {
                d[a] -= self.cell[a] * (d[a] / self.cell[a]).round();
            }
            let mut wj: Option<Vec<V3>> = None;
            for k in 0..27 {
                let img = V3::new(
                    (k % 3) as f64 - 1.0,
                    ((k / 3) % 3) as f64 - 1.0,
                    (k / 9) as f64 - 1.0,
                );
                let shift = V3::new(
                    img.x * self.cell[0],
                    img.y * self.cell[1],
                    img.z * self.cell[2],
                );
                // pos_j seen from i: pos_i - d + shift
                let cj = gi.pos - d + shift;
                if (gi.pos - cj).norm() >= si.bound + sj.bound + self.gap {
                    continue;
                }
                let wj = wj.get_or_insert_with(|| sj.offsets.iter().map(|o| gj.rot * o).collect());
                for (a, pa) in wi.iter().enumerate() {
                    for (b, ob) in wj.iter().enumerate() {
                        let delta = si.radii[a] + sj.radii[b] + self.gap - (pa - (cj + ob)).norm();
                        worst = worst.max(delta);
                    }
                }
            }
        }
        worst
    }

    /// Marks the lists stale (after a contraction moved every centroid).
    pub fn invalidate(&mut self) {
        self.moved = vec![f64::INFINITY; self.grains.len()];
    }
}
