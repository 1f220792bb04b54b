//! `dem.compact`: soft-contact DEM compaction of disks (biaxial, 2-D) or spheres (triaxial,
//! 3-D) between servo-controlled walls under a confining pressure P (Heinze et al. 2020,
//! sec. II.B: k_n / P = 1e4, Coulomb friction 0.3).

use crate::common::{cross, dot, measure, sub, Particles, CLASS_ATTR, DISK_ATTR};
use grainpipe_core::spatial::CellList;
use grainpipe_core::units::{Density, Pressure, Q};
use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, Body, BodyAttribute, Domain, InputMetas, Inputs,
    Outputs, Packing, PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
};
use rayon::prelude::*;

/// Items per parallel task: below this a loop runs on one thread (rayon's split overhead
/// outweighs the work of small samples); the sums do not depend on it.
const CHUNK: usize = 2048;

#[params]
pub struct CompactParams {
    /// Confining pressure P applied by every wall.
    #[param(default = Q::new(1.0e5))]
    pub pressure: Q<Pressure>,
    /// k_n / P (2-D, stiffness per unit thickness) or k_n / (P <d>) (3-D, <d> the mean
    /// diameter); 1e4 in the paper: overlaps stay near 1e-4 of a diameter ("hard particles").
    #[param(default = 1.0e4)]
    pub stiffness_ratio: f64,
    /// Tangential to normal contact stiffness k_t / k_n.
    #[param(default = 0.5)]
    pub tangential_ratio: f64,
    /// Coulomb friction coefficient between particles (0.3 in the paper); walls are
    /// frictionless.
    #[param(default = 0.3)]
    pub friction: f64,
    /// Particle density; with a quasi-static end state it only sets the time scale.
    #[param(default = Q::new(2600.0))]
    pub density: Q<Density>,
    /// Density scaling for the quasi-static relaxation: every particle mass is raised to at
    /// least this fraction of the mean mass (0 = true masses). The end state is a static
    /// equilibrium, which masses do not enter (no gravity); the explicit step grows with the
    /// smallest mass.
    #[param(default = 0.0)]
    pub mass_floor: f64,
    /// Normal contact damping as a fraction of critical damping of the pair.
    #[param(default = 0.5)]
    pub damping_ratio: f64,
    /// Cundall's local (non-viscous) damping coefficient in [0, 1).
    #[param(default = 0.7)]
    pub local_damping: f64,
    /// Time step as a fraction of sqrt(m_min / k_n); the undamped single-contact stability
    /// limit is 2, several contacts per particle lower it, so at most 0.5 is accepted.
    #[param(default = 0.2)]
    pub time_step_factor: f64,
    /// Wall servo gain: the fraction of the stress error corrected per step.
    #[param(default = 0.2)]
    pub servo_gain: f64,
    /// Converged when every wall stress is within this fraction of P ...
    #[param(default = 0.01)]
    pub stress_tolerance: f64,
    /// ... and the mean net force on particles with contacts, over the mean normal contact
    /// force, is below this, as is the mean dashpot force over the mean normal force.
    #[param(default = 1.0e-3)]
    pub force_tolerance: f64,
    /// Steps between convergence checks.
    #[param(default = 100)]
    pub check_every: u64,
    /// The stage fails when not converged after this many steps.
    #[param(default = 1_000_000)]
    pub max_steps: u64,
    /// Work limit: refuse when particles x max_steps exceeds this.
    #[param(default = 5.0e10)]
    pub max_work: f64,
}

/// Everything the kernel needs, in SI.
#[derive(Clone, Debug)]
pub struct DemSpec {
    pub pressure: f64,
    pub stiffness_ratio: f64,
    pub tangential_ratio: f64,
    pub friction: f64,
    pub density: f64,
    pub mass_floor: f64,
    pub damping_ratio: f64,
    pub local_damping: f64,
    pub time_step_factor: f64,
    pub servo_gain: f64,
    pub stress_tolerance: f64,
    pub force_tolerance: f64,
    pub check_every: u64,
    pub max_steps: u64,
}

/// Largest confining pressure accepted [Pa].
pub const MAX_PRESSURE: f64 = 1e10;
/// Largest k_n / P accepted (the paper's is 1e4).
pub const MAX_STIFFNESS_RATIO: f64 = 1e8;

impl CompactParams {
    pub fn spec(&self) -> Result<DemSpec, StageError> {
        let pos = |k: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(v)
            } else {
                Err(StageError::param(k, "must be positive"))
            }
        };
        let unit = |k: &str, v: f64, hi: f64| {
            if (0.0..hi).contains(&v) {
                Ok(v)
            } else {
                Err(StageError::param(k, format!("must be in [0, {hi})")))
            }
        };
        let s = DemSpec {
            pressure: pos("pressure", self.pressure.si())?,
            stiffness_ratio: pos("stiffness_ratio", self.stiffness_ratio)?,
            tangential_ratio: pos("tangential_ratio", self.tangential_ratio)?,
            friction: unit("friction", self.friction, 10.0)?,
            density: pos("density", self.density.si())?,
            mass_floor: unit("mass_floor", self.mass_floor, 1.0 + 1e-12)?,
            damping_ratio: unit("damping_ratio", self.damping_ratio, 1.0)?,
            local_damping: unit("local_damping", self.local_damping, 1.0)?,
            time_step_factor: pos("time_step_factor", self.time_step_factor)?,
            servo_gain: pos("servo_gain", self.servo_gain)?,
            stress_tolerance: pos("stress_tolerance", self.stress_tolerance)?,
            force_tolerance: pos("force_tolerance", self.force_tolerance)?,
            check_every: self.check_every,
            max_steps: self.max_steps,
        };
        // The normal stiffness is stiffness_ratio x pressure: at 1e300 Pa the forces overflow
        // and the run went on to max_steps with an infinite force ratio.
        if s.pressure > MAX_PRESSURE {
            return Err(StageError::param(
                "pressure",
                format!(
                    "{:.3e} Pa is above {MAX_PRESSURE:.0e} Pa: grains crush far below it (sand at \
                     10-100 MPa); check the unit (the paper's is 100 kPa)",
                    s.pressure
                ),
            ));
        }
        if s.stiffness_ratio > MAX_STIFFNESS_RATIO {
            return Err(StageError::param(
                "stiffness_ratio",
                format!(
                    "{:.3e} is above {MAX_STIFFNESS_RATIO:.0e}: the time step (sqrt(m/k_n)) \
                     becomes too small to compact in max_steps, and beyond it the forces lose \
                     their digits",
                    s.stiffness_ratio
                ),
            ));
        }
        if s.stiffness_ratio < 100.0 {
            return Err(StageError::param(
                "stiffness_ratio",
                "below 100 the overlaps exceed 1 % of a diameter: not a hard-particle packing",
            ));
        }
        if s.time_step_factor > 0.5 {
            return Err(StageError::param(
                "time_step_factor",
                format!(
                    "{} is above 0.5 sqrt(m_min/k_n); the explicit scheme is stable below \
                     2 sqrt(m/k) for one contact and several contacts lower the limit",
                    s.time_step_factor
                ),
            ));
        }
        if s.servo_gain > 0.5 {
            return Err(StageError::param("servo_gain", "must be at most 0.5"));
        }
        if s.stress_tolerance > 0.1 {
            return Err(StageError::param("stress_tolerance", "must be at most 0.1"));
        }
        if s.force_tolerance > 0.1 {
            return Err(StageError::param("force_tolerance", "must be at most 0.1"));
        }
        if s.check_every == 0 || s.max_steps == 0 || s.check_every > s.max_steps {
            return Err(StageError::param(
                "check_every",
                "must be at least 1 and at most max_steps",
            ));
        }
        Ok(s)
    }
}

/// The compacted state and how it was reached.
#[derive(Clone, Debug)]
pub struct DemResult {
    pub pos: Vec<[f64; 3]>,
    /// Final half-widths of the wall box along each axis (third unused in 2-D).
    pub half: [f64; 3],
    pub steps: u64,
    pub dt: f64,
    pub kn: f64,
    /// Mean stress on the two walls normal to each axis [Pa].
    pub wall_stress: [f64; 3],
    /// Mean |net force| / mean normal contact force.
    pub unbalanced: f64,
    /// Contacts per particle (overlapping pairs) at the end.
    pub contacts: Vec<u32>,
    pub n_contacts: usize,
    pub mean_contact_force: f64,
    pub max_overlap: f64,
    /// Final contact forces (i, j, force on j from i), pairs in contact only.
    pub contact_forces: Vec<(usize, usize, [f64; 3])>,
}

#[derive(Debug)]
pub enum DemError {
    NotConverged {
        steps: u64,
        stress: [f64; 3],
        unbalanced: f64,
    },
    Diverged(u64),
    Cancelled,
}

impl std::fmt::Display for DemError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DemError::NotConverged {
                steps,
                stress,
                unbalanced,
            } => write!(
                f,
                "DEM compaction not converged after {steps} steps: wall stresses {:.4e} {:.4e} \
                 {:.4e} Pa, unbalanced force ratio {unbalanced:.3e}; raise max_steps or loosen \
                 stress_tolerance / force_tolerance",
                stress[0], stress[1], stress[2]
            ),
            DemError::Diverged(s) => write!(
                f,
                "DEM compaction diverged at step {s} (non-finite positions); lower \
                 time_step_factor or servo_gain"
            ),
            DemError::Cancelled => write!(f, "cancelled"),
        }
    }
}

/// Per-pair contact state: the pair, its tangential spring and its force on `j` this step.
#[derive(Clone, Copy, Debug)]
struct Pair {
    i: u32,
    j: u32,
    xi: [f64; 3],
    force: [f64; 3],
    torque_i: [f64; 3],
    torque_j: [f64; 3],
    fn_mag: f64,
    /// |dashpot part| of the normal force.
    fd_mag: f64,
}

/// Verlet list of pairs closer than `skin` (surface gap), sorted by (i, j); the tangential
/// springs of pairs already in `old` are kept.
fn build_pairs(
    pos: &[[f64; 3]],
    radius: &[f64],
    lo: [f64; 3],
    len: [f64; 3],
    skin: f64,
    old: &[Pair],
) -> Vec<Pair> {
    let r_max = radius.iter().cloned().fold(0.0, f64::max);
    let mut cells = CellList::new(lo, len, [false; 3], 2.0 * r_max + skin);
    for (k, c) in pos.iter().enumerate() {
        cells.insert(k as u32, *c);
    }
    let mut out = Vec::new();
    let mut near = Vec::new();
    for i in 0..pos.len() {
        near.clear();
        cells.visit(pos[i], radius[i] + r_max + skin, |j, _| {
            if j as usize > i {
                let d = sub(pos[j as usize], pos[i]);
                let lim = radius[i] + radius[j as usize] + skin;
                if dot(d, d) < lim * lim {
                    near.push(j);
                }
            }
            true
        });
        near.sort_unstable();
        out.extend(near.iter().map(|&j| Pair {
            i: i as u32,
            j,
            xi: [0.0; 3],
            force: [0.0; 3],
            torque_i: [0.0; 3],
            torque_j: [0.0; 3],
            fn_mag: 0.0,
            fd_mag: 0.0,
        }));
    }
    // Carry the tangential springs over (both lists sorted by (i, j)).
    let mut k = 0;
    for p in out.iter_mut() {
        while k < old.len() && (old[k].i, old[k].j) < (p.i, p.j) {
            k += 1;
        }
        if k < old.len() && (old[k].i, old[k].j) == (p.i, p.j) {
            p.xi = old[k].xi;
        }
    }
    out
}

/// Compacts the particles inside the walls `centre +- half0` under the spec's pressure.
/// Deterministic: pair forces are computed independently and summed per particle in a fixed
/// order, so the thread count does not change the numbers.
pub fn compact(
    parts: &Particles,
    centre: [f64; 3],
    half0: [f64; 3],
    s: &DemSpec,
    mut progress: impl FnMut(u64, u64) -> Result<(), DemError>,
) -> Result<DemResult, DemError> {
    let n = parts.len();
    let dim = parts.dim;
    let r = &parts.radius;
    let mean_d = 2.0 * r.iter().sum::<f64>() / n.max(1) as f64;
    // k_n / P (2-D, per unit thickness) or k_n / (P <d>) (3-D): sec. II.B.
    let kn = if dim == 2 {
        s.stiffness_ratio * s.pressure
    } else {
        s.stiffness_ratio * s.pressure * mean_d
    };
    let kt = s.tangential_ratio * kn;
    let true_mass: Vec<f64> = r.iter().map(|&ri| s.density * measure(dim, ri)).collect();
    let floor = s.mass_floor * true_mass.iter().sum::<f64>() / n.max(1) as f64;
    let mass: Vec<f64> = true_mass.iter().map(|&m| m.max(floor)).collect();
    let inertia: Vec<f64> = r
        .iter()
        .zip(&mass)
        .map(|(&ri, &m)| if dim == 2 { 0.5 } else { 0.4 } * m * ri * ri)
        .collect();
    let m_min = mass.iter().cloned().fold(f64::INFINITY, f64::min);
    let r_min = r.iter().cloned().fold(f64::INFINITY, f64::min);
    // Explicit step from the stiffest contact on the lightest particle (checked <= 0.5 in
    // preflight against the single-contact limit 2 sqrt(m/k)).
    let dt = s.time_step_factor * (m_min / kn).sqrt();
    let damp = |m_eff: f64| 2.0 * s.damping_ratio * (m_eff * kn).sqrt();
    let mut x = parts.pos.clone();
    let mut v = vec![[0.0; 3]; n];
    let mut w = vec![[0.0; 3]; n];
    let mut half = half0;
    let skin = 0.4 * r_min;
    let mut x_ref = x.clone();
    let big = [0, 1, 2].map(|a| centre[a] - half0[a] - 2.0 * r_min);
    let big_len = [0, 1, 2].map(|a| 2.0 * half0[a] + 4.0 * r_min);
    let mut pairs = build_pairs(&x, r, big, big_len, skin, &[]);
    // CSR: for particle k, the (pair, is_j) entries in pair order.
    let adjacency = |pairs: &[Pair]| {
        let mut cnt = vec![0usize; n + 1];
        for p in pairs {
            cnt[p.i as usize + 1] += 1;
            cnt[p.j as usize + 1] += 1;
        }
        for k in 0..n {
            cnt[k + 1] += cnt[k];
        }
        let mut fill = cnt.clone();
        let mut e = vec![(0u32, false); cnt[n]];
        for (q, p) in pairs.iter().enumerate() {
            e[fill[p.i as usize]] = (q as u32, false);
            fill[p.i as usize] += 1;
            e[fill[p.j as usize]] = (q as u32, true);
            fill[p.j as usize] += 1;
        }
        (cnt, e)
    };
    let (mut start, mut entries) = adjacency(&pairs);
    let axes = dim;
    let mut force = vec![[0.0; 3]; n];
    let mut torque = vec![[0.0; 3]; n];
    let mut per = vec![([0.0; 3], [0.0; 3], [0.0; 3], [0u8; 3]); n];
    let mut step = 0u64;
    let total = s.max_steps;
    loop {
        // --- forces ---------------------------------------------------------------------
        pairs.par_iter_mut().with_min_len(CHUNK).for_each(|p| {
            let (i, j) = (p.i as usize, p.j as usize);
            let d = sub(x[j], x[i]);
            let dist = dot(d, d).sqrt();
            let overlap = r[i] + r[j] - dist;
            if overlap <= 0.0 || dist == 0.0 {
                p.xi = [0.0; 3];
                p.force = [0.0; 3];
                p.torque_i = [0.0; 3];
                p.torque_j = [0.0; 3];
                p.fn_mag = 0.0;
                p.fd_mag = 0.0;
                return;
            }
            let nrm = d.map(|c| c / dist);
            // Relative velocity of j's contact point with respect to i's.
            let vi = [0, 1, 2].map(|k| v[i][k] + cross(w[i], nrm.map(|c| c * r[i]))[k]);
            let vj = [0, 1, 2].map(|k| v[j][k] + cross(w[j], nrm.map(|c| -c * r[j]))[k]);
            let vr = sub(vj, vi);
            let vn = dot(vr, nrm);
            let vt = [0, 1, 2].map(|k| vr[k] - vn * nrm[k]);
            let m_eff = mass[i] * mass[j] / (mass[i] + mass[j]);
            // Linear spring-dashpot, no attraction.
            let fnm = (kn * overlap - damp(m_eff) * vn).max(0.0);
            p.fd_mag = (fnm - kn * overlap).abs();
            // Tangential spring in the current tangent plane, capped by Coulomb.
            let xn = dot(p.xi, nrm);
            let mut xi = [0, 1, 2].map(|k| p.xi[k] - xn * nrm[k] + vt[k] * dt);
            let ft_mag = kt * dot(xi, xi).sqrt();
            let cap = s.friction * fnm;
            if ft_mag > cap {
                let f = if ft_mag > 0.0 { cap / ft_mag } else { 0.0 };
                xi = xi.map(|c| c * f);
            }
            let f = [0, 1, 2].map(|k| fnm * nrm[k] - kt * xi[k]);
            p.xi = xi;
            p.force = f;
            p.fn_mag = fnm;
            // Torques: force -f at i's contact point r_i n, +f at j's point -r_j n.
            p.torque_i = cross(nrm.map(|c| c * r[i]), f.map(|c| -c));
            p.torque_j = cross(nrm.map(|c| -c * r[j]), f);
        });
        // Per particle, in pair order; walls are frictionless springs.
        let hw = half;
        per.par_iter_mut()
            .enumerate()
            .with_min_len(CHUNK)
            .for_each(|(k, out)| {
                let mut f = [0.0; 3];
                let mut t = [0.0; 3];
                for &(q, is_j) in &entries[start[k]..start[k + 1]] {
                    let p = &pairs[q as usize];
                    let (pf, pt) = if is_j {
                        (p.force, p.torque_j)
                    } else {
                        (p.force.map(|c| -c), p.torque_i)
                    };
                    for a in 0..3 {
                        f[a] += pf[a];
                        t[a] += pt[a];
                    }
                }
                let mut wf = [0.0; 3];
                let mut wc = [0u8; 3];
                for a in 0..axes {
                    let lo_gap = x[k][a] - (centre[a] - hw[a]) - r[k];
                    let hi_gap = (centre[a] + hw[a]) - x[k][a] - r[k];
                    // Walls are plain springs: the moving wall must not drag particles
                    // through a dashpot, and the wall stress is then k_n x overlap exactly.
                    if lo_gap < 0.0 {
                        let fw = -kn * lo_gap;
                        f[a] += fw;
                        wf[a] += fw;
                        wc[a] += 1;
                    }
                    if hi_gap < 0.0 {
                        let fw = -kn * hi_gap;
                        f[a] -= fw;
                        wf[a] += fw;
                        wc[a] += 1;
                    }
                }
                *out = (f, t, wf, wc);
            });
        let mut wall_force = [0.0f64; 3];
        let mut wall_contacts = [0usize; 3];
        for (k, &(f, t, wf, wc)) in per.iter().enumerate() {
            force[k] = f;
            torque[k] = t;
            for a in 0..3 {
                wall_force[a] += wf[a];
                wall_contacts[a] += wc[a] as usize;
            }
        }
        let area: [f64; 3] = [0, 1, 2].map(|a| {
            (0..axes)
                .filter(|&b| b != a)
                .map(|b| 2.0 * half[b])
                .product()
        });
        // Mean of the two opposite walls.
        let stress = [0, 1, 2].map(|a| {
            if a < axes {
                0.5 * wall_force[a] / area[a]
            } else {
                0.0
            }
        });
        // --- convergence ----------------------------------------------------------------
        if step % s.check_every == 0 {
            let stress_ok = (0..axes)
                .all(|a| (stress[a] - s.pressure).abs() <= s.stress_tolerance * s.pressure);
            let (unb, mean_net, mean_contact) = unbalanced(
                &force, &start, &entries, &pairs, &x, r, &centre, &half, axes,
            );
            // Dashpot forces must be negligible too: the state is at rest, not sliding.
            let (fd, fsum) = pairs
                .iter()
                .filter(|p| p.fn_mag > 0.0)
                .fold((0.0, 0.0), |(a, b), p| (a + p.fd_mag, b + p.fn_mag));
            let dash = if fsum > 0.0 { fd / fsum } else { f64::INFINITY };
            if stress_ok && unb <= s.force_tolerance && dash <= s.force_tolerance && step > 0 {
                return Ok(finish(x, half, step, dt, kn, stress, unb, &pairs, n));
            }
            if x.iter().any(|c| c.iter().any(|v| !v.is_finite()))
                || half.iter().any(|h| !h.is_finite())
                // (the ratio itself is infinite while no contact carries force)
                || unb.is_nan()
                || !(mean_net.is_finite() && mean_contact.is_finite())
                || stress.iter().any(|v| !v.is_finite())
            {
                return Err(DemError::Diverged(step));
            }
            if step >= s.max_steps {
                return Err(DemError::NotConverged {
                    steps: step,
                    stress,
                    unbalanced: unb,
                });
            }
            progress(step, total)?;
        }
        // --- integration (leapfrog with Cundall's local damping) -------------------------
        let alpha = s.local_damping;
        x.par_iter_mut()
            .zip(v.par_iter_mut())
            .zip(w.par_iter_mut())
            .enumerate()
            .with_min_len(CHUNK)
            .for_each(|(k, ((xk, vk), wk))| {
                for a in 0..3 {
                    let f = force[k][a] - alpha * force[k][a].abs() * vk[a].signum();
                    vk[a] += f / mass[k] * dt;
                    let t = torque[k][a] - alpha * torque[k][a].abs() * wk[a].signum();
                    wk[a] += t / inertia[k] * dt;
                }
                if dim == 2 {
                    vk[2] = 0.0;
                    wk[0] = 0.0;
                    wk[1] = 0.0;
                }
                for a in 0..3 {
                    xk[a] += vk[a] * dt;
                }
            });
        // Wall servo: move both walls of an axis by a fraction of the displacement that
        // would cancel the stress error if the contacting particles stayed put.
        let cap = 1e-3 * r_min;
        for a in 0..axes {
            let stiff = kn * (wall_contacts[a] as f64 / 2.0).max(1.0);
            let delta = s.servo_gain * (stress[a] - s.pressure) * area[a] / stiff;
            half[a] += delta.clamp(-cap, cap);
        }
        // Rebuild the Verlet list when some particle moved half the skin.
        let moved = x
            .iter()
            .zip(&x_ref)
            .map(|(a, b)| {
                let d = sub(*a, *b);
                dot(d, d)
            })
            .fold(0.0, f64::max)
            .sqrt();
        if moved > 0.5 * skin {
            pairs = build_pairs(&x, r, big, big_len, skin, &pairs);
            (start, entries) = adjacency(&pairs);
            x_ref.clone_from(&x);
        }
        step += 1;
    }
}

/// Mean |net force| over particles with at least one contact (walls included) divided by
/// the mean normal contact force; also (mean net, mean contact).
#[allow(clippy::too_many_arguments)]
fn unbalanced(
    force: &[[f64; 3]],
    start: &[usize],
    entries: &[(u32, bool)],
    pairs: &[Pair],
    x: &[[f64; 3]],
    r: &[f64],
    centre: &[f64; 3],
    half: &[f64; 3],
    axes: usize,
) -> (f64, f64, f64) {
    let mut net = 0.0;
    let mut nc = 0usize;
    for k in 0..force.len() {
        let touching = entries[start[k]..start[k + 1]]
            .iter()
            .any(|&(q, _)| pairs[q as usize].fn_mag > 0.0)
            || (0..axes).any(|a| (x[k][a] - centre[a]).abs() + r[k] > half[a]);
        if touching {
            net += dot(force[k], force[k]).sqrt();
            nc += 1;
        }
    }
    let (sum, cnt) = pairs
        .iter()
        .filter(|p| p.fn_mag > 0.0)
        .fold((0.0, 0usize), |(s, c), p| (s + p.fn_mag, c + 1));
    if cnt == 0 || nc == 0 {
        return (f64::INFINITY, 0.0, 0.0);
    }
    let mean_c = sum / cnt as f64;
    let mean_net = net / nc as f64;
    (mean_net / mean_c, mean_net, mean_c)
}

#[allow(clippy::too_many_arguments)]
fn finish(
    x: Vec<[f64; 3]>,
    half: [f64; 3],
    steps: u64,
    dt: f64,
    kn: f64,
    stress: [f64; 3],
    unb: f64,
    pairs: &[Pair],
    n: usize,
) -> DemResult {
    let mut contacts = vec![0u32; n];
    let mut nc = 0;
    let mut sum = 0.0;
    for p in pairs.iter().filter(|p| p.fn_mag > 0.0) {
        contacts[p.i as usize] += 1;
        contacts[p.j as usize] += 1;
        nc += 1;
        sum += p.fn_mag;
    }
    DemResult {
        pos: x,
        half,
        steps,
        dt,
        kn,
        wall_stress: stress,
        unbalanced: unb,
        contacts,
        n_contacts: nc,
        mean_contact_force: if nc > 0 { sum / nc as f64 } else { 0.0 },
        max_overlap: pairs.iter().map(|p| p.fn_mag / kn).fold(0.0, f64::max),
        contact_forces: pairs
            .iter()
            .filter(|p| p.fn_mag > 0.0)
            .map(|p| (p.i as usize, p.j as usize, p.force))
            .collect(),
    }
}

/// Mean contacts per particle after removing rattlers (fewer than `min_contacts`, wall
/// contacts included), repeatedly, as is usual for jammed packings; (Z, non-rattler count).
/// Frictionless particles need d + 1 contacts; frictional ones can rest on 2 opposite
/// contacts inside their friction cones.
pub fn coordination_without_rattlers(
    n: usize,
    min_contacts: usize,
    pairs: &[(usize, usize)],
    wall_contacts: &[usize],
) -> (f64, usize) {
    let mut alive = vec![true; n];
    loop {
        // Wall contacts hold particles too (they count toward the d + 1, not toward Z).
        let mut z = vec![0usize; n];
        for &(i, j) in pairs {
            if alive[i] && alive[j] {
                z[i] += 1;
                z[j] += 1;
            }
        }
        let mut changed = false;
        for k in 0..n {
            if alive[k] && z[k] + wall_contacts[k] < min_contacts {
                alive[k] = false;
                changed = true;
            }
        }
        if !changed {
            let m = alive.iter().filter(|&&a| a).count();
            let s: usize = (0..n).filter(|&k| alive[k]).map(|k| z[k]).sum();
            return (if m > 0 { s as f64 / m as f64 } else { 0.0 }, m);
        }
    }
}

/// Overlapping pairs of a set of particles (brute force over a cell list), for reports and tests.
pub fn overlapping_pairs(pos: &[[f64; 3]], radius: &[f64]) -> Vec<(usize, usize)> {
    let n = pos.len();
    if n == 0 {
        return Vec::new();
    }
    // The cell list spans the centres padded by the largest radius (a fixed 1 m margin gave
    // millimetre grains a box of ~1000^3 cells, capped at MAX_CELLS: 400 MB of empty cells).
    let pad = radius
        .iter()
        .cloned()
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    let lo = [0, 1, 2].map(|a| pos.iter().map(|c| c[a]).fold(f64::INFINITY, f64::min) - pad);
    let hi = [0, 1, 2].map(|a| pos.iter().map(|c| c[a]).fold(f64::NEG_INFINITY, f64::max) + pad);
    let pairs = build_pairs(pos, radius, lo, [0, 1, 2].map(|a| hi[a] - lo[a]), 0.0, &[]);
    pairs
        .iter()
        .filter(|p| {
            let d = sub(pos[p.j as usize], pos[p.i as usize]);
            dot(d, d).sqrt() < radius[p.i as usize] + radius[p.j as usize]
        })
        .map(|p| (p.i as usize, p.j as usize))
        .collect()
}

/// Peak memory of compacting `n` particles [bytes]. Per particle: the particles read from
/// the packing (position, radius, class: 33 B), the integrator's arrays (position, its
/// reference copy, velocity, spin, force, torque: 6 x 24 B; true mass, mass, inertia: 24 B;
/// the per-particle force sums: 80 B), the CSR start (8 B), the cell list (4 B per particle
/// plus at most one 24 B cell per particle, as cells are at least one diameter wide) and the
/// output (a `Body` per particle, the coordination arrays). Pairs: a disk touches at most 6
/// neighbours of its size within the skin (a sphere 12), i.e. 3 (2-D) or 6 (3-D) pairs per
/// particle; with bidisperse sizes small ones crowd a large one, and the dimension is only
/// known at run time, so 8 are counted. Each pair is a 120 B `Pair` and two 8 B CSR entries, and the Verlet rebuild holds
/// the old and the new list: 2 x 136 B per pair. The final overlap count builds one more
/// pair list and its (i, j) copy (16 B per pair).
fn memory(n: u64) -> u64 {
    let body = std::mem::size_of::<Body>() as u64;
    let per_particle = 33 + 6 * 24 + 24 + 80 + 8 + 4 + 24 + body + 8 + 8 + 1 + 8;
    let pairs_per_particle = 8;
    let per_pair = 2 * (std::mem::size_of::<Pair>() as u64 + 16) + 16;
    n * (per_particle + pairs_per_particle * per_pair) + 64 * 1024
}

pub struct Compact;

impl TypedStage for Compact {
    type Params = CompactParams;
    type Plan = DemSpec;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "dem.compact",
            "1.0.0",
            "Densifies a disk (2-D, biaxial) or sphere (3-D, triaxial) packing by soft-contact \
             DEM between frictionless walls servo-controlled to a confining pressure P \
             (Heinze et al., Phys. Rev. E 101, 052901 (2020), sec. II.B): linear spring-dashpot \
             normal contacts with k_n/P = 1e4 (2-D; k_n/(P <d>) in 3-D), tangential springs \
             capped by Coulomb friction 0.3 (Cundall & Strack), rotations, Cundall local \
             damping, leapfrog integration with dt = f sqrt(m_min/k_n), f <= 0.5, and a Verlet \
             list over the shared cell list. Converged when every wall stress is within \
             stress_tolerance of P and the mean net force on contacting particles is below \
             force_tolerance times the mean normal contact force; otherwise the stage fails \
             after max_steps with the values reached. The box stays centred where it was; \
             output bodies keep their `class` and gain `contacts`.",
        )
        .inputs(vec![PortSpec::new(
            "packing",
            ArtifactKind::Packing,
            "disks or spheres in a non-periodic box (packing.poisson_disk)",
        )])
        .outputs(vec![
            PortSpec::new("packing", ArtifactKind::Packing, "the compacted packing"),
            PortSpec::new(
                "report",
                ArtifactKind::Table,
                "packing fraction, coordination, steps, wall stresses, force imbalance",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &CompactParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<DemSpec>, StageError> {
        let s = p.spec()?;
        let up = inputs.get("packing");
        if let Some(per) = up.and_then(|m| m.periodic) {
            if per.iter().any(|&b| b) {
                return Err(StageError::input(
                    "packing",
                    "the packing is periodic; dem.compact compresses between walls (set \
                     periodic: false upstream)",
                ));
            }
        }
        let n = up.map(|m| m.count_estimate).unwrap_or(0);
        let work = n as f64 * s.max_steps as f64;
        if work > p.max_work {
            return Err(StageError::param(
                "max_steps",
                format!(
                    "about {n} particles x {} steps = {work:.2e} particle-steps exceeds \
                     max_work = {:.2e}",
                    s.max_steps, p.max_work
                ),
            ));
        }
        let mut meta = ArtifactMeta::of(ArtifactKind::Packing).with_count(n, None);
        if let Some(per) = up.and_then(|m| m.periodic) {
            meta.periodic = Some(per);
        }
        if let Some(l) = up.and_then(|m| m.length_scale) {
            meta = meta.with_length_scale(l);
        }
        Ok(Preflight::from_info(&self.info(), memory(n))
            .announce("packing", meta)
            .announce(
                "report",
                ArtifactMeta::of(ArtifactKind::Table).with_count(1, Some([1, 1])),
            )
            .with_plan(s))
    }

    fn run(
        &self,
        _p: &CompactParams,
        s: &DemSpec,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let pk = grainpipe_core::stage::input(inputs, "packing", Artifact::as_packing)?;
        if pk.domain.periodic.iter().any(|&b| b) {
            return Err(StageError::input(
                "packing",
                "periodic packings are not compacted between walls",
            ));
        }
        let parts = Particles::from_packing(pk, "packing")?;
        if parts.is_empty() {
            return Err(StageError::input("packing", "no particles"));
        }
        let centre = [0, 1, 2].map(|a| 0.5 * (pk.domain.min[a] + pk.domain.max[a]));
        let half0 = pk.domain.size().map(|l| 0.5 * l);
        let res = compact(&parts, centre, half0, s, |k, t| {
            ctx.progress(k, t).map_err(|_| DemError::Cancelled)
        })
        .map_err(|e| match e {
            DemError::Cancelled => StageError::Cancelled,
            e => StageError::failed(e.to_string()),
        })?;
        let dim = parts.dim;
        let mut domain = Domain::boxed(pk.domain.min, pk.domain.max, pk.domain.periodic);
        for a in 0..dim {
            domain.min[a] = centre[a] - res.half[a];
            domain.max[a] = centre[a] + res.half[a];
        }
        let box_measure: f64 = (0..dim).map(|a| 2.0 * res.half[a]).product();
        let solid: f64 = (0..parts.len()).map(|i| parts.measure(i)).sum();
        let pairs = overlapping_pairs(&res.pos, &parts.radius);
        let walls: Vec<usize> = (0..parts.len())
            .map(|k| {
                (0..dim)
                    .filter(|&a| (res.pos[k][a] - centre[a]).abs() + parts.radius[k] > res.half[a])
                    .count()
            })
            .collect();
        let min_contacts = if s.friction > 0.0 { 2 } else { dim + 1 };
        let (z_nr, n_nr) = coordination_without_rattlers(parts.len(), min_contacts, &pairs, &walls);
        let mut out_pk = Packing::new(domain);
        out_pk.bodies = res
            .pos
            .iter()
            .zip(&parts.radius)
            .map(|(c, r)| Body::sphere(*c, *r))
            .collect();
        for key in [CLASS_ATTR, DISK_ATTR] {
            if let Some(a) = pk.attributes.get(key) {
                out_pk.attributes.insert(key.into(), a.clone());
            }
        }
        out_pk.attributes.insert(
            "contacts".into(),
            BodyAttribute {
                unit: String::new(),
                values: res.contacts.iter().map(|&c| c as f64).collect(),
            },
        );
        let report = Table::new("dem_compact")
            .with_f64("packing_fraction", "", vec![solid / box_measure])
            .with_f64(
                "coordination",
                "",
                vec![2.0 * res.n_contacts as f64 / parts.len() as f64],
            )
            .with_f64("coordination_no_rattlers", "", vec![z_nr])
            .with_i64("non_rattlers", "", vec![n_nr as i64])
            .with_i64("contacts", "", vec![res.n_contacts as i64])
            .with_i64("steps", "", vec![res.steps as i64])
            .with_f64("mass_floor", "", vec![s.mass_floor])
            .with_f64("time_step", "s", vec![res.dt])
            .with_f64("kn", if dim == 2 { "Pa" } else { "N/m" }, vec![res.kn])
            .with_f64("wall_stress_x", "Pa", vec![res.wall_stress[0]])
            .with_f64("wall_stress_y", "Pa", vec![res.wall_stress[1]])
            .with_f64("wall_stress_z", "Pa", vec![res.wall_stress[2]])
            .with_f64("pressure", "Pa", vec![s.pressure])
            .with_f64("unbalanced_force_ratio", "", vec![res.unbalanced])
            .with_f64(
                "mean_contact_force",
                if dim == 2 { "N/m" } else { "N" },
                vec![res.mean_contact_force],
            )
            .with_f64("max_overlap", "m", vec![res.max_overlap]);
        let mut out = Outputs::new();
        out.insert("packing".into(), Artifact::Packing(out_pk));
        out.insert("report".into(), Artifact::Table(report));
        Ok(out)
    }
}
