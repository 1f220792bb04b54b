//! The per-particle heat balance of section 5.1 on a contact graph, with explicit (forward
//! Euler, the paper's update) and implicit (backward Euler) steps and bond formation.
//!
//! State is the enthalpy E_i relative to the ambient temperature, so latent heat fits in
//! and the stored energy is exactly the sum of what the steps added.

use crate::params::BeamProfile;
use grainpipe_core::spatial::CellList;
use rayon::prelude::*;

/// Particles per parallel work item. Fixed (not derived from the thread count) so that
/// every partial sum is formed the same way under any pool size.
const CHUNK: usize = 2048;

/// Material and model constants in SI.
#[derive(Clone, Debug)]
pub struct Material {
    pub specific_heat: f64,
    pub density: f64,
    /// k_b [W/K].
    pub convection: f64,
    /// k_t [W/K].
    pub contact: f64,
    /// Conductance of a bonded pair [W/K].
    pub bonded: f64,
    /// T_R [K].
    pub ambient: f64,
    /// T_S [K].
    pub sintering: f64,
    /// (melting temperature [K], latent heat [J/kg]) when melting is modelled.
    pub melting: Option<(f64, f64)>,
}

/// The beam: power, radius and profile.
#[derive(Clone, Debug)]
pub struct Beam {
    pub power: f64,
    pub radius: f64,
    pub profile: BeamProfile,
}

impl Beam {
    /// Horizontal distance from the spot beyond which a particle gets nothing.
    pub fn reach(&self) -> f64 {
        match self.profile {
            BeamProfile::TopHat => self.radius,
            // exp(-8) = 3.4e-4 of the peak intensity at 2 r_L.
            BeamProfile::Gaussian => 2.0 * self.radius,
        }
    }

    /// Power into a particle of radius `r` whose centre is `d2` (squared horizontal
    /// distance) from the spot.
    #[inline]
    pub fn flux(&self, r: f64, d2: f64) -> f64 {
        let rl2 = self.radius * self.radius;
        match self.profile {
            // Section 5.1: q_i,laser = Q r_i^2 / r_L^2.
            BeamProfile::TopHat => {
                if d2 <= rl2 {
                    self.power * r * r / rl2
                } else {
                    0.0
                }
            }
            // Intensity 2Q/(pi r_L^2) exp(-2 d^2/r_L^2) times the cross-section pi r_i^2.
            BeamProfile::Gaussian => {
                if d2 <= 4.0 * rl2 {
                    2.0 * self.power * r * r / rl2 * (-2.0 * d2 / rl2).exp()
                } else {
                    0.0
                }
            }
        }
    }
}

/// The plan view (x-y) of the particles `ids`: a cell list over their x-y bounding box with
/// one cell along z, so a query at `[x, y, 0]` visits every listed particle within the
/// horizontal `reach` of (x, y) whatever its height (and possibly more: callers test exactly).
pub fn plan_view(ids: &[usize], pos: &[[f64; 3]], cell: f64) -> CellList {
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for &i in ids {
        for a in 0..2 {
            lo[a] = lo[a].min(pos[i][a]);
            hi[a] = hi[a].max(pos[i][a]);
        }
    }
    if ids.is_empty() {
        lo = [0.0; 2];
        hi = [0.0; 2];
    }
    // z: a box one cell high; every height is clamped into it.
    let mut g = CellList::new(
        [lo[0], lo[1], 0.0],
        [hi[0] - lo[0], hi[1] - lo[1], cell],
        [false; 3],
        cell,
    );
    for &i in ids {
        g.insert(i as u32, [pos[i][0], pos[i][1], 0.0]);
    }
    g
}

/// Why an implicit step failed.
#[derive(Debug, thiserror::Error)]
pub enum ThermalError {
    #[error(
        "conjugate gradients reached relative residual {residual:.3e} after {iterations} \
         iterations, above cg_tolerance {tolerance:.1e}"
    )]
    NotConverged {
        residual: f64,
        iterations: usize,
        tolerance: f64,
    },
    #[error("conjugate gradients diverged (non-finite residual)")]
    Diverged,
}

/// Per-step totals.
#[derive(Clone, Copy, Debug, Default)]
pub struct StepStats {
    /// Energy convected out during the step [J].
    pub convected: f64,
    pub max_t: f64,
    pub sum_t: f64,
    /// Conjugate-gradient iterations (implicit only).
    pub iterations: usize,
    /// Relative residual reached (implicit only).
    pub residual: f64,
}

/// The particle bed with its conduction graph and thermal state.
pub struct Bed {
    pub n: usize,
    pub pos: Vec<[f64; 3]>,
    /// Sphere (or volume-equivalent sphere) radius [m].
    pub radius: Vec<f64>,
    /// m_i C_p [J/K].
    pub cap: Vec<f64>,
    /// m_i L [J] (zero without melting).
    pub latent: Vec<f64>,
    pub mat: Material,
    // Conduction graph in CSR form, both directions of every pair.
    row: Vec<usize>,
    col: Vec<u32>,
    /// Conductance of each CSR entry [W/K].
    eg: Vec<f64>,
    /// Pair of each CSR entry.
    epair: Vec<u32>,
    pub pairs: Vec<[usize; 2]>,
    pair_edges: Vec<[usize; 2]>,
    pub bonded: Vec<bool>,
    /// Time each pair bonded [s] (NaN while unbonded).
    pub bond_time: Vec<f64>,
    /// sum_j k_ij + k_b per particle [W/K].
    pub ksum: Vec<f64>,
    /// Enthalpy relative to a particle at T_R [J].
    pub e: Vec<f64>,
    pub t: Vec<f64>,
    pub e0_total: f64,
    pub peak: Vec<f64>,
    pub time_above: Vec<f64>,
    // Scratch buffers.
    e_new: Vec<f64>,
    t_new: Vec<f64>,
    local: Vec<u32>,
    acc: Vec<f64>,
}

/// Global explicit step and the particles sub-cycled inside it.
#[derive(Clone, Debug)]
pub struct Multirate {
    pub dt: f64,
    pub stiff: Vec<usize>,
    pub is_stiff: Vec<bool>,
    /// Smallest limit among the stiff particles [s] (infinite when there are none).
    pub stiff_limit: f64,
    /// A particle is stiff when margin x its limit is below `dt`.
    pub margin: f64,
}

impl Bed {
    /// `pairs` are conduction pairs (i != j, each once); `initially_bonded[p]` marks pairs
    /// that start bonded; `volume[i]` gives the mass m_i = rho V_i.
    pub fn new(
        pos: Vec<[f64; 3]>,
        radius: Vec<f64>,
        volume: &[f64],
        pairs: Vec<[usize; 2]>,
        initially_bonded: Vec<bool>,
        mat: Material,
        t0: Vec<f64>,
    ) -> Bed {
        let n = pos.len();
        let cap: Vec<f64> = volume
            .iter()
            .map(|v| mat.density * v * mat.specific_heat) // m_i = (4 pi/3) rho r_i^3
            .collect();
        let latent: Vec<f64> = match mat.melting {
            Some((_, l)) => volume.iter().map(|v| mat.density * v * l).collect(),
            None => vec![0.0; n],
        };
        let mut deg = vec![0usize; n + 1];
        for p in &pairs {
            deg[p[0] + 1] += 1;
            deg[p[1] + 1] += 1;
        }
        for i in 0..n {
            deg[i + 1] += deg[i];
        }
        let row = deg;
        let m = row[n];
        let mut fill = row.clone();
        let mut col = vec![0u32; m];
        let mut eg = vec![0.0; m];
        let mut epair = vec![0u32; m];
        let mut pair_edges = Vec::with_capacity(pairs.len());
        for (k, p) in pairs.iter().enumerate() {
            let g = if initially_bonded[k] {
                mat.bonded
            } else {
                mat.contact
            };
            let mut ed = [0; 2];
            for (s, (a, b)) in [(p[0], p[1]), (p[1], p[0])].into_iter().enumerate() {
                let e = fill[a];
                fill[a] += 1;
                col[e] = b as u32;
                eg[e] = g;
                epair[e] = k as u32;
                ed[s] = e;
            }
            pair_edges.push(ed);
        }
        let mut bed = Bed {
            n,
            pos,
            radius,
            cap,
            latent,
            row,
            col,
            eg,
            epair,
            bond_time: initially_bonded
                .iter()
                .map(|&b| if b { 0.0 } else { f64::NAN })
                .collect(),
            bonded: initially_bonded,
            pair_edges,
            pairs,
            ksum: vec![0.0; n],
            e: vec![0.0; n],
            peak: t0.clone(),
            t: t0,
            e0_total: 0.0,
            time_above: vec![0.0; n],
            e_new: vec![0.0; n],
            t_new: vec![0.0; n],
            local: Vec::new(),
            acc: Vec::new(),
            mat,
        };
        bed.recompute_ksum();
        for i in 0..n {
            bed.e[i] = bed.enthalpy(i, bed.t[i]);
        }
        bed.e0_total = bed.e.iter().sum();
        bed
    }

    fn recompute_ksum(&mut self) {
        for i in 0..self.n {
            let s: f64 = self.eg[self.row[i]..self.row[i + 1]].iter().sum();
            self.ksum[i] = s + self.mat.convection;
        }
    }

    pub fn neighbours(&self, i: usize) -> impl Iterator<Item = usize> + '_ {
        self.col[self.row[i]..self.row[i + 1]]
            .iter()
            .map(|&c| c as usize)
    }

    /// Explicit stability limit min_i m_i C_p / (sum_j k_ij + k_b) [s]; infinite when no
    /// particle exchanges heat.
    pub fn stability_limit(&self) -> f64 {
        self.cap
            .iter()
            .zip(&self.ksum)
            .filter(|(_, &k)| k > 0.0)
            .map(|(c, k)| c / k)
            .fold(f64::INFINITY, f64::min)
    }

    fn enthalpy(&self, i: usize, t: f64) -> f64 {
        let c = self.cap[i];
        match self.mat.melting {
            Some((tm, _)) if t > tm => c * (t - self.mat.ambient) + self.latent[i],
            _ => c * (t - self.mat.ambient),
        }
    }

    #[inline]
    fn temperature(mat: &Material, cap: f64, latent: f64, e: f64) -> f64 {
        match mat.melting {
            None => mat.ambient + e / cap,
            Some((tm, _)) => {
                let em = cap * (tm - mat.ambient);
                if e <= em {
                    mat.ambient + e / cap
                } else if e <= em + latent {
                    // Melting plateau: the energy goes into latent heat.
                    tm
                } else {
                    tm + (e - em - latent) / cap
                }
            }
        }
    }

    /// Energy stored since the start [J].
    pub fn stored(&self) -> f64 {
        self.e.iter().sum::<f64>() - self.e0_total
    }

    /// Forward Euler step of section 5.1: T_i += dt q_i / (m_i C_p), with
    /// q_i = q_i,laser + k_b (T_R - T_i) + sum_j k_ij (T_j - T_i).
    pub fn explicit_step(&mut self, dt: f64, qlas: &[f64]) -> StepStats {
        let Bed {
            row,
            col,
            eg,
            t,
            e,
            e_new,
            t_new,
            peak,
            time_above,
            cap,
            latent,
            mat,
            ..
        } = self;
        let (row, col, eg, t, e, cap, latent, mat) =
            (&*row, &*col, &*eg, &*t, &*e, &*cap, &*latent, &*mat);
        let kb = mat.convection;
        let tr = mat.ambient;
        let ts = mat.sintering;
        let parts: Vec<StepStats> = e_new
            .par_chunks_mut(CHUNK)
            .zip(t_new.par_chunks_mut(CHUNK))
            .zip(peak.par_chunks_mut(CHUNK))
            .zip(time_above.par_chunks_mut(CHUNK))
            .enumerate()
            .map(|(c, (((en, tn), pk), ta))| {
                let mut st = StepStats {
                    max_t: f64::NEG_INFINITY,
                    ..Default::default()
                };
                for k in 0..en.len() {
                    let i = c * CHUNK + k;
                    let ti = t[i];
                    // q_i,conv = k_b (T_R - T_i)
                    let mut q = qlas[i] + kb * (tr - ti);
                    // q_ij = k_t (T_j - T_i)
                    for ed in row[i]..row[i + 1] {
                        q += eg[ed] * (t[col[ed] as usize] - ti);
                    }
                    st.convected += kb * (ti - tr);
                    en[k] = e[i] + dt * q;
                    let tnew = Bed::temperature(mat, cap[i], latent[i], en[k]);
                    tn[k] = tnew;
                    pk[k] = pk[k].max(tnew);
                    if tnew > ts {
                        ta[k] += dt;
                    }
                    st.max_t = st.max_t.max(tnew);
                    st.sum_t += tnew;
                }
                st.convected *= dt;
                st
            })
            .collect();
        std::mem::swap(&mut self.e, &mut self.e_new);
        std::mem::swap(&mut self.t, &mut self.t_new);
        combine(&parts)
    }

    /// Per-particle explicit limits m_i C_p / (sum_j k_ij + k_b) [s].
    pub fn limits(&self) -> Vec<f64> {
        self.cap
            .iter()
            .zip(&self.ksum)
            .map(|(c, &k)| if k > 0.0 { c / k } else { f64::INFINITY })
            .collect()
    }

    /// Chooses the global explicit step and the stiff particles to sub-cycle.
    ///
    /// Particle limits span orders of magnitude (m_i ~ r_i^3 while k_t is the same for every
    /// contact), so one global step at the smallest limit wastes work on all others. A
    /// particle is stiff when safety x its limit is below the global step; the global step
    /// (`fixed`, or at most `dt_max`) minimises the work (N - k)/dt + 2 k/(safety L_min) over
    /// the number k of stiff particles (a stiff particle-step counts double: sequential).
    pub fn plan(&self, dt_max: f64, safety: f64, fixed: Option<f64>) -> Multirate {
        let lim = self.limits();
        let mut order: Vec<usize> = (0..self.n).collect();
        order.sort_by(|&a, &b| lim[a].total_cmp(&lim[b]).then(a.cmp(&b)));
        let l0 = lim[order[0]];
        let dt = match fixed {
            Some(d) => d,
            None => {
                let n = self.n as f64;
                let mut best = (f64::INFINITY, (safety * l0).min(dt_max));
                for k in 0..=self.n / 4 {
                    let dt = (safety * lim[order[k]]).min(dt_max);
                    let cost = (n - k as f64) / dt + 2.0 * k as f64 / (safety * l0);
                    if cost < best.0 {
                        best = (cost, dt);
                    }
                    if dt >= dt_max {
                        break;
                    }
                }
                best.1
            }
        };
        // Stiff: the global step would break the particle's own limit (with the safety
        // margin for automatic steps; a user dt is accepted up to the limit itself).
        let margin = if fixed.is_some() { 1.0 } else { safety };
        let is_stiff: Vec<bool> = lim
            .iter()
            .map(|&l| margin * l * (1.0 + 1e-12) < dt)
            .collect();
        let stiff: Vec<usize> = (0..self.n).filter(|&i| is_stiff[i]).collect();
        let stiff_limit = stiff.iter().map(|&i| lim[i]).fold(f64::INFINITY, f64::min);
        Multirate {
            dt,
            stiff,
            is_stiff,
            stiff_limit,
            margin,
        }
    }

    /// Keeps `plan` valid after the conductance sums of `changed` particles grew (bonding):
    /// a particle whose limit now breaks the global step joins the sub-cycled set. The
    /// global step itself is kept, so bonding costs no re-sort.
    pub fn update_plan(&self, plan: &mut Multirate, changed: &[usize]) {
        let mut added = false;
        for &i in changed {
            let l = if self.ksum[i] > 0.0 {
                self.cap[i] / self.ksum[i]
            } else {
                f64::INFINITY
            };
            if plan.is_stiff[i] {
                plan.stiff_limit = plan.stiff_limit.min(l);
            } else if plan.margin * l * (1.0 + 1e-12) < plan.dt {
                plan.is_stiff[i] = true;
                plan.stiff_limit = plan.stiff_limit.min(l);
                added = true;
            }
        }
        if added {
            plan.stiff = (0..self.n).filter(|&i| plan.is_stiff[i]).collect();
        }
    }

    /// Explicit step of length `dt` with the stiff particles of `plan` sub-cycled at
    /// safety x their smallest limit. During the sub-cycle the other particles' temperatures
    /// are held; the energy each stiff-to-regular contact carries is accumulated and handed
    /// to the regular particle, so energy is conserved to round-off and every update stays
    /// a convex combination (discrete maximum principle, hence stable).
    pub fn explicit_step_multirate(
        &mut self,
        dt: f64,
        qlas: &[f64],
        plan: &Multirate,
        safety: f64,
    ) -> (StepStats, u64) {
        let kb = self.mat.convection;
        let tr = self.mat.ambient;
        let ts = self.mat.sintering;
        let ns = (dt / (safety * plan.stiff_limit)).ceil().max(1.0);
        let ds = dt / ns;
        let m = plan.stiff.len();
        let mut local = std::mem::take(&mut self.local);
        local.clear();
        local.resize(self.n, u32::MAX);
        for (k, &i) in plan.stiff.iter().enumerate() {
            local[i] = k as u32;
        }
        let mut acc = std::mem::take(&mut self.acc);
        acc.clear();
        acc.resize(self.n, 0.0);
        let mut es: Vec<f64> = plan.stiff.iter().map(|&i| self.e[i]).collect();
        let mut tsv: Vec<f64> = plan.stiff.iter().map(|&i| self.t[i]).collect();
        let mut es_new = vec![0.0; m];
        let mut ts_new = vec![0.0; m];
        let mut stiff_conv = 0.0;
        for _ in 0..ns as u64 {
            for (k, &i) in plan.stiff.iter().enumerate() {
                let ti = tsv[k];
                let mut q = qlas[i] + kb * (tr - ti);
                for ed in self.row[i]..self.row[i + 1] {
                    let j = self.col[ed] as usize;
                    let lj = local[j];
                    if lj != u32::MAX {
                        q += self.eg[ed] * (tsv[lj as usize] - ti);
                    } else {
                        let f = self.eg[ed] * (self.t[j] - ti);
                        q += f;
                        acc[j] -= ds * f;
                    }
                }
                stiff_conv += ds * kb * (ti - tr);
                es_new[k] = es[k] + ds * q;
                let tn = Bed::temperature(&self.mat, self.cap[i], self.latent[i], es_new[k]);
                ts_new[k] = tn;
                self.peak[i] = self.peak[i].max(tn);
            }
            std::mem::swap(&mut es, &mut es_new);
            std::mem::swap(&mut tsv, &mut ts_new);
        }
        let Bed {
            row,
            col,
            eg,
            t,
            e,
            e_new,
            t_new,
            peak,
            time_above,
            cap,
            latent,
            mat,
            ..
        } = self;
        let (row, col, eg, t, e, cap, latent, mat) =
            (&*row, &*col, &*eg, &*t, &*e, &*cap, &*latent, &*mat);
        let (local_r, acc_r, es_r, ts_r) = (&local, &acc, &es, &tsv);
        let parts: Vec<StepStats> = e_new
            .par_chunks_mut(CHUNK)
            .zip(t_new.par_chunks_mut(CHUNK))
            .zip(peak.par_chunks_mut(CHUNK))
            .zip(time_above.par_chunks_mut(CHUNK))
            .enumerate()
            .map(|(c, (((en, tn), pk), ta))| {
                let mut st = StepStats {
                    max_t: f64::NEG_INFINITY,
                    ..Default::default()
                };
                for k in 0..en.len() {
                    let i = c * CHUNK + k;
                    let li = local_r[i];
                    let tnew = if li != u32::MAX {
                        en[k] = es_r[li as usize];
                        ts_r[li as usize]
                    } else {
                        let ti = t[i];
                        let mut q = qlas[i] + kb * (tr - ti);
                        for ed in row[i]..row[i + 1] {
                            let j = col[ed] as usize;
                            if local_r[j] == u32::MAX {
                                q += eg[ed] * (t[j] - ti);
                            }
                        }
                        st.convected += dt * kb * (ti - tr);
                        en[k] = e[i] + dt * q + acc_r[i];
                        Bed::temperature(mat, cap[i], latent[i], en[k])
                    };
                    tn[k] = tnew;
                    pk[k] = pk[k].max(tnew);
                    if tnew > ts {
                        ta[k] += dt;
                    }
                    st.max_t = st.max_t.max(tnew);
                    st.sum_t += tnew;
                }
                st
            })
            .collect();
        std::mem::swap(&mut self.e, &mut self.e_new);
        std::mem::swap(&mut self.t, &mut self.t_new);
        self.local = local;
        self.acc = acc;
        let mut st = combine(&parts);
        st.convected += stiff_conv;
        (st, ns as u64)
    }

    /// Backward Euler step: (C/dt + K + k_b) T' = C/dt T + k_b T_R + q_laser, solved by
    /// Jacobi-preconditioned conjugate gradients (the matrix is symmetric positive definite
    /// when k_b > 0 or dt is finite). Not available with melting.
    pub fn implicit_step(
        &mut self,
        dt: f64,
        qlas: &[f64],
        tol: f64,
    ) -> Result<StepStats, ThermalError> {
        let n = self.n;
        let kb = self.mat.convection;
        let tr = self.mat.ambient;
        let diag: Vec<f64> = (0..n).map(|i| self.cap[i] / dt + self.ksum[i]).collect();
        let b: Vec<f64> = (0..n)
            .map(|i| self.cap[i] / dt * self.t[i] + kb * tr + qlas[i])
            .collect();
        let (row, col, eg) = (&self.row, &self.col, &self.eg);
        let matvec = |x: &[f64], y: &mut [f64]| {
            y.par_chunks_mut(CHUNK).enumerate().for_each(|(c, yc)| {
                for (k, yk) in yc.iter_mut().enumerate() {
                    let i = c * CHUNK + k;
                    let mut s = diag[i] * x[i];
                    for ed in row[i]..row[i + 1] {
                        s -= eg[ed] * x[col[ed] as usize];
                    }
                    *yk = s;
                }
            })
        };
        let mut x = self.t.clone();
        let mut r = vec![0.0; n];
        matvec(&x, &mut r);
        for i in 0..n {
            r[i] = b[i] - r[i];
        }
        let bnorm = dot(&b, &b).sqrt().max(f64::MIN_POSITIVE);
        let mut z: Vec<f64> = (0..n).map(|i| r[i] / diag[i]).collect();
        let mut p = z.clone();
        let mut rz = dot(&r, &z);
        let mut ap = vec![0.0; n];
        let mut it = 0;
        let mut rel = dot(&r, &r).sqrt() / bnorm;
        let max_it = 10 * n + 100;
        while rel > tol {
            if it >= max_it {
                return Err(ThermalError::NotConverged {
                    residual: rel,
                    iterations: it,
                    tolerance: tol,
                });
            }
            matvec(&p, &mut ap);
            let alpha = rz / dot(&p, &ap);
            for i in 0..n {
                x[i] += alpha * p[i];
                r[i] -= alpha * ap[i];
            }
            for i in 0..n {
                z[i] = r[i] / diag[i];
            }
            let rz_new = dot(&r, &z);
            let beta = rz_new / rz;
            rz = rz_new;
            for i in 0..n {
                p[i] = z[i] + beta * p[i];
            }
            rel = dot(&r, &r).sqrt() / bnorm;
            it += 1;
            if !rel.is_finite() {
                return Err(ThermalError::Diverged);
            }
        }
        let mut st = StepStats {
            max_t: f64::NEG_INFINITY,
            iterations: it,
            residual: rel,
            ..Default::default()
        };
        let ts = self.mat.sintering;
        for (i, &xi) in x.iter().enumerate() {
            // Backward Euler convects at the new temperature.
            st.convected += dt * kb * (xi - tr);
            self.e[i] = self.cap[i] * (xi - tr);
            self.peak[i] = self.peak[i].max(xi);
            if xi > ts {
                self.time_above[i] += dt;
            }
            st.max_t = st.max_t.max(xi);
            st.sum_t += xi;
        }
        self.t = x;
        Ok(st)
    }

    /// Bonds every unbonded contact whose two particles both exceed T_S (section 5.1).
    /// Returns (new bonds, whether conductances changed); the particles whose conductance
    /// sum changed are appended to `changed_particles`.
    pub fn form_bonds(&mut self, time: f64, changed_particles: &mut Vec<usize>) -> (usize, bool) {
        let ts = self.mat.sintering;
        let mut new = 0;
        let mut changed = false;
        for i in 0..self.n {
            if self.t[i] <= ts {
                continue;
            }
            for ed in self.row[i]..self.row[i + 1] {
                let j = self.col[ed] as usize;
                let p = self.epair[ed] as usize;
                if j > i && !self.bonded[p] && self.t[j] > ts {
                    self.bonded[p] = true;
                    self.bond_time[p] = time;
                    new += 1;
                    let g = self.mat.bonded;
                    let [e1, e2] = self.pair_edges[p];
                    if self.eg[e1] != g {
                        let d = g - self.eg[e1];
                        self.eg[e1] = g;
                        self.eg[e2] = g;
                        self.ksum[i] += d;
                        self.ksum[j] += d;
                        changed_particles.push(i);
                        changed_particles.push(j);
                        changed = true;
                    }
                }
            }
        }
        (new, changed)
    }

    pub fn bond_count(&self) -> usize {
        self.bonded.iter().filter(|&&b| b).count()
    }

    /// Particles with at least one bond.
    pub fn bonded_particles(&self) -> usize {
        let mut has = vec![false; self.n];
        for (p, &b) in self.pairs.iter().zip(&self.bonded) {
            if b {
                has[p[0]] = true;
                has[p[1]] = true;
            }
        }
        has.iter().filter(|&&b| b).count()
    }
}

fn combine(parts: &[StepStats]) -> StepStats {
    let mut st = StepStats {
        max_t: f64::NEG_INFINITY,
        ..Default::default()
    };
    for p in parts {
        st.convected += p.convected;
        st.max_t = st.max_t.max(p.max_t);
        st.sum_t += p.sum_t;
    }
    st
}

/// Dot product with a fixed chunked summation order (thread-count independent).
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let parts: Vec<f64> = a
        .par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(x, y)| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>())
        .collect();
    parts.iter().sum()
}
