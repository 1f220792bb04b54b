//! The peridynamic lattice on a regular grid, free of framework types.
//!
//! Every node is a voxel centre. Bonds are not stored: the neighbours of a node are a fixed
//! list of grid offsets (all lattice vectors with |xi| <= h), so a bond is identified by its
//! node and its offset index. Per node the lattice keeps a region id (u32: 0 = no material,
//! 1.. = particle or matrix region), the bond constant of bonds inside its own region (f32)
//! and the Dirichlet flags (u8); displacements, forces and solver vectors are f32, one array
//! per component. Arrays are padded by the horizon on every non-trivial axis so the inner
//! loops need no bounds checks: padding nodes have region 0 and bond to nothing.
//!
//! Units inside the kernels are scaled: lengths in voxel edges dx, bond constants and forces
//! in E_ref dx^(d-1) (d = 2 or 3), stresses in E_ref, time in dx sqrt(rho / E_ref). The stage
//! converts to SI.

use rayon::prelude::*;

/// One neighbour offset of the fixed stencil.
#[derive(Clone, Copy, Debug)]
pub struct Offset {
    /// Linear offset in the padded array.
    pub d: isize,
    /// Lattice vector xi = x_j - x_i in voxel edges.
    pub xi: [f32; 3],
    /// |xi|.
    pub len: f32,
}

/// Grid geometry with the stencil.
#[derive(Clone, Debug)]
pub struct Layout {
    /// Nodes per axis (unpadded).
    pub dims: [usize; 3],
    /// Padding per axis (the horizon, rounded down, on axes with more than one node).
    pub pad: [usize; 3],
    /// Padded dims.
    pub pdims: [usize; 3],
    /// Whether the problem is three-dimensional (nz > 1).
    pub dim3: bool,
    /// The full neighbour stencil (both orientations of every bond).
    pub offsets: Vec<Offset>,
    /// Horizon in voxel edges.
    pub horizon: f64,
}

impl Layout {
    pub fn new(dims: [usize; 3], horizon: f64) -> Layout {
        let dim3 = dims[2] > 1;
        let r = horizon.floor() as usize;
        let pad = [r, r, if dim3 { r } else { 0 }];
        let pdims = [0, 1, 2].map(|a| dims[a] + 2 * pad[a]);
        let mut offsets = Vec::new();
        let ri = r as isize;
        let rz = if dim3 { ri } else { 0 };
        // A tiny tolerance keeps lattice points lying exactly on the horizon (h = 3 dx: the
        // 28 neighbours of the paper's Fig. 2b include (3, 0)).
        let h2 = horizon * horizon * (1.0 + 1e-9);
        for oz in -rz..=rz {
            for oy in -ri..=ri {
                for ox in -ri..=ri {
                    let l2 = (ox * ox + oy * oy + oz * oz) as f64;
                    if l2 == 0.0 || l2 > h2 {
                        continue;
                    }
                    let d = ox + pdims[0] as isize * (oy + pdims[1] as isize * oz);
                    offsets.push(Offset {
                        d,
                        xi: [ox as f32, oy as f32, oz as f32],
                        len: l2.sqrt() as f32,
                    });
                }
            }
        }
        Layout {
            dims,
            pad,
            pdims,
            dim3,
            offsets,
            horizon,
        }
    }

    /// Number of padded nodes.
    pub fn len(&self) -> usize {
        self.pdims.iter().product()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Number of displacement components.
    pub fn ncomp(&self) -> usize {
        if self.dim3 {
            3
        } else {
            2
        }
    }
    /// Padded index of unpadded node (x, y, z).
    pub fn pidx(&self, x: usize, y: usize, z: usize) -> usize {
        (x + self.pad[0]) + self.pdims[0] * ((y + self.pad[1]) + self.pdims[1] * (z + self.pad[2]))
    }
    /// Unpadded (x, y, z) of a padded index, or None for a padding node.
    pub fn coords(&self, p: usize) -> Option<[usize; 3]> {
        let px = p % self.pdims[0];
        let py = (p / self.pdims[0]) % self.pdims[1];
        let pz = p / (self.pdims[0] * self.pdims[1]);
        let c = [px, py, pz];
        let mut out = [0; 3];
        for a in 0..3 {
            if c[a] < self.pad[a] || c[a] >= self.pad[a] + self.dims[a] {
                return None;
            }
            out[a] = c[a] - self.pad[a];
        }
        Some(out)
    }
    /// Padded rows (x lines) that hold unpadded nodes: (row index, padded start of the
    /// first unpadded node).
    fn row_start(&self, row: usize) -> Option<usize> {
        let py = row % self.pdims[1];
        let pz = row / self.pdims[1];
        if py < self.pad[1]
            || py >= self.pad[1] + self.dims[1]
            || pz < self.pad[2]
            || pz >= self.pad[2] + self.dims[2]
        {
            return None;
        }
        Some(row * self.pdims[0] + self.pad[0])
    }
    /// Padded start of the first unpadded node of padded row `row`, None for padding rows.
    pub fn row_start_pub(&self, row: usize) -> Option<usize> {
        self.row_start(row)
    }
    /// Number of padded rows.
    pub fn rows(&self) -> usize {
        self.pdims[1] * self.pdims[2]
    }
    /// Bytes of stencil-independent lattice data per node (region, bond constant, flags).
    pub const NODE_BYTES: usize = 4 + 4 + 1;
}

/// A displacement-like field: one array per component over the padded grid (f32 for forces
/// and solver vectors, f64 for the displacement itself).
#[derive(Clone, Debug, PartialEq)]
pub struct Vec3<T = f32> {
    pub c: Vec<Vec<T>>,
}

impl<T: Default + Clone> Vec3<T> {
    pub fn zeros(layout: &Layout) -> Vec3<T> {
        Vec3 {
            c: (0..layout.ncomp())
                .map(|_| vec![T::default(); layout.len()])
                .collect(),
        }
    }
}

/// A displacement value: differences of neighbours are what the bonds see, taken in the
/// storage precision and rounded to f32 (f64 displacements keep elongations of order
/// strain x dx exact to f32 precision while u itself grows to strain x n dx).
pub trait Real: Copy + Send + Sync + 'static {
    fn sub32(self, other: Self) -> f32;
}
/// Whether the bond loops may use AVX2 (detected once per force evaluation).
fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

impl Real for f32 {
    #[inline(always)]
    fn sub32(self, other: Self) -> f32 {
        self - other
    }
}
impl Real for f64 {
    #[inline(always)]
    fn sub32(self, other: Self) -> f32 {
        (self - other) as f32
    }
}

/// The material lattice: per-node region and bond constant, Dirichlet flags.
#[derive(Clone, Debug)]
pub struct Lattice {
    pub layout: Layout,
    /// Region id per padded node: 0 = no node (void, padding, excluded), equal ids = same
    /// particle or matrix region (bond takes the node's own constant), different non-zero
    /// ids = interface bond.
    pub region: Vec<u32>,
    /// Bond constant (scaled) of bonds inside the node's own region.
    pub kself: Vec<f32>,
    /// Bond constant (scaled) of interface bonds.
    pub kint: f32,
    /// Dirichlet flags per node: bit a = component a prescribed.
    pub fixed: Vec<u8>,
    /// Critical stretch of bonds inside the node's region (only with breaking).
    pub sc_self: Vec<f32>,
    /// Critical stretch of interface bonds.
    pub sc_int: f32,
    /// Uniform background strain (diagonal, per component): the displacement is stored as
    /// u = diag(bg) x + w and only w lives in the f32 arrays, so bond elongations of order
    /// strain x |xi| keep their f32 precision on large grids (u itself grows to strain x n).
    pub bg: [f32; 3],
}

/// Result of one force sweep.
#[derive(Clone, Copy, Debug, Default)]
pub struct Sweep {
    /// Strain energy (scaled units).
    pub energy: f64,
    /// Bonds found beyond their critical stretch in this sweep (counted from both ends).
    pub newly_broken: u64,
}

#[inline(always)]
fn bond_k(ri: u32, rj: u32, ki: f32, kint: f32) -> f32 {
    // Section II.D: same region -> the region's own constant (particle or matrix bond);
    // different regions -> interface bond; a node without material bonds to nothing.
    // Either end without material: no bond. A void node next to material must not take the
    // interface constant: its visits of the bond would add energy the material does not
    // store (2x the grip work on a plate with a hole) and forces on a node with no unknowns.
    let k = if ri == rj { ki } else { kint };
    if ri == 0 || rj == 0 {
        0.0
    } else {
        k
    }
}

/// Bond constant of the bond from padded node i to padded node j (0 when either has no
/// material), as the force sweeps use it.
#[inline(always)]
pub fn bond_k_pub(lat: &Lattice, i: usize, j: usize) -> f32 {
    if lat.region[i] == 0 {
        return 0.0;
    }
    bond_k(lat.region[i], lat.region[j], lat.kself[i], lat.kint)
}

/// Slices of a row shifted by a stencil offset (the neighbour j of node i = start + x).
#[inline(always)]
fn shifted<T>(v: &[T], start: usize, d: isize, n: usize) -> &[T] {
    let s = (start as isize + d) as usize;
    &v[s..s + n]
}

/// How bond forces depend on the displacement.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ForceLaw {
    /// Eq. (4), (6): f = c s n with the deformed direction n (what the paper integrates).
    Nonlinear,
    /// Linearised about the reference: f = k (e . eta) / |xi| e (the operator CG inverts).
    Linear,
}

impl Lattice {
    /// Internal force per node, f_i = sum_j f_ij (eq. (7) without inertia), into `out`
    /// (zero on region-0 nodes); returns the strain energy sum_bonds k s^2 |xi| / 2 and,
    /// with `broken`, flags bonds beyond their critical stretch (both ends see the same
    /// stretch, bit for bit, so the flags stay symmetric without cross-node writes).
    /// `background`: add the uniform strain `bg` (false to apply the linear operator to a
    /// search direction).
    pub fn forces<T: Real>(
        &self,
        u: &Vec3<T>,
        law: ForceLaw,
        out: &mut Vec3,
        broken: Option<&mut [u64]>,
        background: bool,
    ) -> Sweep {
        let bg = if background { self.bg } else { [0.0; 3] };
        let l = &self.layout;
        let px = l.pdims[0];
        let words = broken_words(l);
        let rows: Vec<(usize, Vec<&mut [f32]>)> = {
            let mut it: Vec<_> = out.c.iter_mut().map(|c| c.chunks_mut(px)).collect();
            let mut rows = Vec::with_capacity(l.rows());
            for r in 0..l.rows() {
                let row: Vec<&mut [f32]> = it.iter_mut().map(|c| c.next().unwrap()).collect();
                rows.push((r, row));
            }
            rows
        };
        let broken_rows: Vec<Option<&mut [u64]>> = match broken {
            Some(b) => b.chunks_mut(px * words).map(Some).collect(),
            None => (0..l.rows()).map(|_| None).collect(),
        };
        let avx2 = has_avx2();
        let sums: Vec<Sweep> = rows
            .into_par_iter()
            .zip(broken_rows)
            .map(|((r, mut row), brow)| {
                if avx2 {
                    // SAFETY: the CPU has AVX2 (checked at run time just above).
                    #[cfg(target_arch = "x86_64")]
                    unsafe {
                        return self.force_row_avx2(u, law, r, &mut row, brow, bg, words);
                    }
                }
                self.force_row(u, law, r, &mut row, brow, bg, words)
            })
            .collect();
        // Summed in row order: the same numbers for any thread count.
        let mut total = Sweep::default();
        for s in sums {
            total.energy += s.energy;
            total.newly_broken += s.newly_broken;
        }
        total
    }

    /// The forces of one grid row (x line) into `row`: every offset's bonds of its nodes.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn force_row<T: Real>(
        &self,
        u: &Vec3<T>,
        law: ForceLaw,
        r: usize,
        row: &mut [&mut [f32]],
        mut brow: Option<&mut [u64]>,
        bg: [f32; 3],
        words: usize,
    ) -> Sweep {
        let l = &self.layout;
        let nx = l.dims[0];
        for c in row.iter_mut() {
            c.fill(0.0);
        }
        let Some(start) = l.row_start(r) else {
            return Sweep::default();
        };
        let mut sweep = Sweep::default();
        let mut acc = [vec![0f32; nx], vec![0f32; nx], vec![0f32; nx]];
        let mut en = vec![0f32; nx];
        let ri = &self.region[start..start + nx];
        let ki = &self.kself[start..start + nx];
        for (oi, o) in l.offsets.iter().enumerate() {
            let rj = shifted(&self.region, start, o.d, nx);
            let brow = brow.as_deref_mut().map(|b| {
                let s = l.pad[0] * words;
                &mut b[s..s + nx * words]
            });
            if l.dim3 {
                sweep.newly_broken += self.row3(
                    u, law, start, o, oi, ri, rj, ki, &mut acc, &mut en, brow, bg,
                );
            } else {
                sweep.newly_broken += self.row2(
                    u, law, start, o, oi, ri, rj, ki, &mut acc, &mut en, brow, bg,
                );
            }
        }
        for (c, a) in row.iter_mut().zip(acc.iter()) {
            c[l.pad[0]..l.pad[0] + nx].copy_from_slice(a);
        }
        // Each bond is visited from both ends: half its energy per visit.
        sweep.energy = en.iter().map(|&e| e as f64).sum::<f64>() * 0.5;
        sweep
    }

    /// [`Self::force_row`] compiled for AVX2: the bond loops run 8 f32 lanes wide (sqrt and
    /// division included) instead of SSE2's 4. Rust never contracts a * b + c into an FMA on
    /// its own, so the numbers are bit for bit those of the SSE2 path.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn force_row_avx2<T: Real>(
        &self,
        u: &Vec3<T>,
        law: ForceLaw,
        r: usize,
        row: &mut [&mut [f32]],
        brow: Option<&mut [u64]>,
        bg: [f32; 3],
        words: usize,
    ) -> Sweep {
        self.force_row(u, law, r, row, brow, bg, words)
    }

    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn row2<T: Real>(
        &self,
        u: &Vec3<T>,
        law: ForceLaw,
        start: usize,
        o: &Offset,
        oi: usize,
        ri: &[u32],
        rj: &[u32],
        ki: &[f32],
        acc: &mut [Vec<f32>; 3],
        en: &mut [f32],
        broken: Option<&mut [u64]>,
        bg: [f32; 3],
    ) -> u64 {
        let nx = ri.len();
        // Background elongation of this offset: constant along the row.
        let (gx, gy) = (bg[0] * o.xi[0], bg[1] * o.xi[1]);
        let (uxi, uyi) = (&u.c[0][start..start + nx], &u.c[1][start..start + nx]);
        let uxj = shifted(&u.c[0], start, o.d, nx);
        let uyj = shifted(&u.c[1], start, o.d, nx);
        let [xx, xy, _] = o.xi;
        let l0 = o.len;
        let inv_l0 = 1.0 / l0;
        let kint = self.kint;
        let [ax, ay, _] = acc;
        // Equal lengths let the compiler drop the bounds checks and vectorise over x.
        let (ax, ay, en) = (&mut ax[..nx], &mut ay[..nx], &mut en[..nx]);
        let (uxi, uyi, uxj, uyj, rj, ki) = (
            &uxi[..nx],
            &uyi[..nx],
            &uxj[..nx],
            &uyj[..nx],
            &rj[..nx],
            &ki[..nx],
        );
        let mut newly = 0;
        match (law, broken) {
            (ForceLaw::Linear, _) => {
                // f = k (xi . eta) / |xi|^3 xi  (linearised eq. (6))
                let g = inv_l0 * inv_l0 * inv_l0;
                for x in 0..nx {
                    let k = bond_k(ri[x], rj[x], ki[x], kint);
                    let ex = uxj[x].sub32(uxi[x]) + gx;
                    let ey = uyj[x].sub32(uyi[x]) + gy;
                    let t = k * (xx * ex + xy * ey) * g;
                    ax[x] += t * xx;
                    ay[x] += t * xy;
                    // energy k s^2 |xi| / 2 with s = t |xi| / k
                    en[x] += 0.5 * t * (xx * ex + xy * ey);
                }
            }
            (ForceLaw::Nonlinear, None) => {
                for x in 0..nx {
                    let k = bond_k(ri[x], rj[x], ki[x], kint);
                    let ex = uxj[x].sub32(uxi[x]) + gx;
                    let ey = uyj[x].sub32(uyi[x]) + gy;
                    // l^2 - l0^2 = 2 xi.eta + eta.eta keeps the stretch accurate in f32.
                    let num = 2.0 * (xx * ex + xy * ey) + ex * ex + ey * ey;
                    let l = (l0 * l0 + num).sqrt();
                    let s = num / ((l + l0) * l0); // eq. (4)
                    let t = k * s / l; // eq. (6): |f| = c s along n = (xi + eta) / l
                    ax[x] += t * (xx + ex);
                    ay[x] += t * (xy + ey);
                    en[x] += 0.5 * k * s * s * l0;
                }
            }
            (ForceLaw::Nonlinear, Some(b)) => {
                let words = b.len() / nx;
                let (w, bit) = (oi / 64, 1u64 << (oi % 64));
                let sci = &self.sc_self[start..start + nx];
                for x in 0..nx {
                    if b[x * words + w] & bit != 0 {
                        continue;
                    }
                    let k = bond_k(ri[x], rj[x], ki[x], kint);
                    let ex = uxj[x].sub32(uxi[x]) + gx;
                    let ey = uyj[x].sub32(uyi[x]) + gy;
                    let num = 2.0 * (xx * ex + xy * ey) + ex * ex + ey * ey;
                    let l = (l0 * l0 + num).sqrt();
                    let s = num / ((l + l0) * l0);
                    let sc = if ri[x] == rj[x] { sci[x] } else { self.sc_int };
                    if k > 0.0 && s > sc {
                        b[x * words + w] |= bit;
                        newly += 1;
                        continue;
                    }
                    let t = k * s / l;
                    ax[x] += t * (xx + ex);
                    ay[x] += t * (xy + ey);
                    en[x] += 0.5 * k * s * s * l0;
                }
            }
        }
        newly
    }

    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn row3<T: Real>(
        &self,
        u: &Vec3<T>,
        law: ForceLaw,
        start: usize,
        o: &Offset,
        oi: usize,
        ri: &[u32],
        rj: &[u32],
        ki: &[f32],
        acc: &mut [Vec<f32>; 3],
        en: &mut [f32],
        broken: Option<&mut [u64]>,
        bg: [f32; 3],
    ) -> u64 {
        let nx = ri.len();
        let (gx, gy, gz) = (bg[0] * o.xi[0], bg[1] * o.xi[1], bg[2] * o.xi[2]);
        let ui: Vec<&[T]> = (0..3).map(|a| &u.c[a][start..start + nx]).collect();
        let uj: Vec<&[T]> = (0..3).map(|a| shifted(&u.c[a], start, o.d, nx)).collect();
        let (uxi, uyi, uzi) = (ui[0], ui[1], ui[2]);
        let (uxj, uyj, uzj) = (uj[0], uj[1], uj[2]);
        let [xx, xy, xz] = o.xi;
        let l0 = o.len;
        let inv_l0 = 1.0 / l0;
        let kint = self.kint;
        let [ax, ay, az] = acc;
        let mut newly = 0;
        let sci = &self.sc_self[..];
        let words = broken.as_ref().map(|b| b.len() / nx).unwrap_or(0);
        let (w, bit) = (oi / 64, 1u64 << (oi % 64));
        let mut b = broken;
        for x in 0..nx {
            if let Some(b) = b.as_deref() {
                if b[x * words + w] & bit != 0 {
                    continue;
                }
            }
            let k = bond_k(ri[x], rj[x], ki[x], kint);
            let ex = uxj[x].sub32(uxi[x]) + gx;
            let ey = uyj[x].sub32(uyi[x]) + gy;
            let ez = uzj[x].sub32(uzi[x]) + gz;
            match law {
                ForceLaw::Linear => {
                    let g = inv_l0 * inv_l0 * inv_l0;
                    let t = k * (xx * ex + xy * ey + xz * ez) * g;
                    ax[x] += t * xx;
                    ay[x] += t * xy;
                    az[x] += t * xz;
                    en[x] += 0.5 * t * (xx * ex + xy * ey + xz * ez);
                }
                ForceLaw::Nonlinear => {
                    let num = 2.0 * (xx * ex + xy * ey + xz * ez) + ex * ex + ey * ey + ez * ez;
                    let l = (l0 * l0 + num).sqrt();
                    let s = num / ((l + l0) * l0);
                    if let Some(b) = b.as_deref_mut() {
                        let sc = if ri[x] == rj[x] {
                            sci[start + x]
                        } else {
                            self.sc_int
                        };
                        if k > 0.0 && s > sc {
                            b[x * words + w] |= bit;
                            newly += 1;
                            continue;
                        }
                    }
                    let t = k * s / l;
                    ax[x] += t * (xx + ex);
                    ay[x] += t * (xy + ey);
                    az[x] += t * (xz + ez);
                    en[x] += 0.5 * k * s * s * l0;
                }
            }
        }
        newly
    }

    /// Per node and component: the diagonal of the linear stiffness matrix
    /// (sum_j k/|xi| e_a^2) and the Gershgorin row sum sum_j 2 k/|xi| |e_a| sum_b |e_b|
    /// (Kilic & Madenci 2010, eq. (13): the ADR density is a quarter of it).
    pub fn stiffness_bounds(&self) -> (Vec3, Vec3) {
        let l = &self.layout;
        let mut diag = Vec3::zeros(l);
        let mut gersh = Vec3::zeros(l);
        let nc = l.ncomp();
        let n = l.len();
        let per_node: Vec<([f32; 3], [f32; 3])> = (0..n)
            .into_par_iter()
            .map(|i| {
                let mut dg = [0f32; 3];
                let mut gs = [0f32; 3];
                if self.region[i] == 0 {
                    return (dg, gs);
                }
                for o in &l.offsets {
                    let j = (i as isize + o.d) as usize;
                    let k = bond_k(self.region[i], self.region[j], self.kself[i], self.kint);
                    if k == 0.0 {
                        continue;
                    }
                    let kl = k / o.len;
                    let e = o.xi.map(|v| v / o.len);
                    let sum_abs: f32 = e.iter().map(|v| v.abs()).sum();
                    for a in 0..nc {
                        dg[a] += kl * e[a] * e[a];
                        gs[a] += 2.0 * kl * e[a].abs() * sum_abs;
                    }
                }
                (dg, gs)
            })
            .collect();
        for (i, (dg, gs)) in per_node.into_iter().enumerate() {
            for a in 0..nc {
                diag.c[a][i] = dg[a];
                gersh.c[a][i] = gs[a];
            }
        }
        (diag, gersh)
    }

    /// Per node: sum_j k_ij / |xi_ij| (Silling & Askari 2005, eq. (20): the explicit step
    /// is stable when dt < sqrt(2 rho / sum_j V_j c / |xi|), here sqrt(2 m_i / this)).
    pub fn spring_sums(&self) -> Vec<f32> {
        let l = &self.layout;
        (0..l.len())
            .into_par_iter()
            .map(|i| {
                if self.region[i] == 0 {
                    return 0.0;
                }
                l.offsets
                    .iter()
                    .map(|o| {
                        let j = (i as isize + o.d) as usize;
                        bond_k(self.region[i], self.region[j], self.kself[i], self.kint) / o.len
                    })
                    .sum()
            })
            .collect()
    }

    /// Nodal stress sigma_i = 1/(2 V_i) sum_j f_ij (x) xi_ij (section II.C), in E_ref, Voigt
    /// order (xx, yy, xy) in 2-D, (xx, yy, zz, yz, xz, xy) in 3-D; per unpadded node.
    pub fn stress<T: Real>(&self, u: &Vec3<T>, law: ForceLaw, broken: Option<&[u64]>) -> Vec<f32> {
        let l = &self.layout;
        let nc = if l.dim3 { 6 } else { 3 };
        let words = broken_words(l);
        let [nx, ny, nz] = l.dims;
        let mut out = vec![0f32; nx * ny * nz * nc];
        out.par_chunks_mut(nx * nc)
            .enumerate()
            .for_each(|(row, chunk)| {
                let (y, z) = (row % ny, row / ny);
                for x in 0..nx {
                    let i = l.pidx(x, y, z);
                    if self.region[i] == 0 {
                        continue;
                    }
                    let mut s = [0f64; 6];
                    for (oi, o) in l.offsets.iter().enumerate() {
                        let j = (i as isize + o.d) as usize;
                        if let Some(b) = broken {
                            if b[i * words + oi / 64] & (1u64 << (oi % 64)) != 0 {
                                continue;
                            }
                        }
                        let k = bond_k(self.region[i], self.region[j], self.kself[i], self.kint);
                        if k == 0.0 {
                            continue;
                        }
                        let eta: [f32; 3] = [0, 1, 2].map(|a| {
                            if a < l.ncomp() {
                                u.c[a][j].sub32(u.c[a][i]) + self.bg[a] * o.xi[a]
                            } else {
                                0.0
                            }
                        });
                        let xi = o.xi;
                        let dot = xi[0] * eta[0] + xi[1] * eta[1] + xi[2] * eta[2];
                        let f: [f64; 3] = match law {
                            ForceLaw::Linear => {
                                let t = k * dot / (o.len * o.len * o.len);
                                xi.map(|v| (t * v) as f64)
                            }
                            ForceLaw::Nonlinear => {
                                let num =
                                    2.0 * dot + eta[0] * eta[0] + eta[1] * eta[1] + eta[2] * eta[2];
                                let len = (o.len * o.len + num).sqrt();
                                let st = num / ((len + o.len) * o.len);
                                let t = k * st / len;
                                [0, 1, 2].map(|a| (t * (xi[a] + eta[a])) as f64)
                            }
                        };
                        let x = xi.map(|v| v as f64);
                        s[0] += f[0] * x[0];
                        s[1] += f[1] * x[1];
                        s[2] += f[2] * x[2];
                        s[3] += 0.5 * (f[1] * x[2] + f[2] * x[1]);
                        s[4] += 0.5 * (f[0] * x[2] + f[2] * x[0]);
                        s[5] += 0.5 * (f[0] * x[1] + f[1] * x[0]);
                    }
                    let c = &mut chunk[x * nc..(x + 1) * nc];
                    if l.dim3 {
                        for (k, v) in c.iter_mut().enumerate() {
                            *v = (0.5 * s[k]) as f32;
                        }
                    } else {
                        c[0] = (0.5 * s[0]) as f32;
                        c[1] = (0.5 * s[1]) as f32;
                        c[2] = (0.5 * s[5]) as f32;
                    }
                }
            });
        out
    }

    /// Connected components of the nodes over existing bonds (union-find over the stencil);
    /// returns the component root per padded node (u32::MAX for region-0 nodes).
    pub fn components(&self) -> Vec<u32> {
        let n = self.layout.len();
        let mut parent: Vec<u32> = (0..n as u32).collect();
        fn find(p: &mut [u32], mut a: u32) -> u32 {
            while p[a as usize] != a {
                let g = p[p[a as usize] as usize];
                p[a as usize] = g;
                a = g;
            }
            a
        }
        // Positive half of the stencil suffices: every bond is seen from one end.
        for i in 0..n {
            if self.region[i] == 0 {
                continue;
            }
            for o in self.layout.offsets.iter().filter(|o| o.d > 0) {
                let j = (i as isize + o.d) as usize;
                if self.region[j] == 0 {
                    continue;
                }
                let (a, b) = (find(&mut parent, i as u32), find(&mut parent, j as u32));
                if a != b {
                    // The smaller root wins: labels do not depend on visiting order.
                    let (lo, hi) = if a < b { (a, b) } else { (b, a) };
                    parent[hi as usize] = lo;
                }
            }
        }
        (0..n)
            .map(|i| {
                if self.region[i] == 0 {
                    u32::MAX
                } else {
                    find(&mut parent, i as u32)
                }
            })
            .collect()
    }
}

/// u64 words of broken-bond flags per node.
pub fn broken_words(l: &Layout) -> usize {
    l.offsets.len().div_ceil(64)
}

/// Deterministic dot product of two fields over the padded nodes (row partials summed in
/// order).
pub fn dot(l: &Layout, a: &Vec3, b: &Vec3) -> f64 {
    let px = l.pdims[0];
    let mut total = 0.0;
    for (ca, cb) in a.c.iter().zip(b.c.iter()) {
        let parts: Vec<f64> = ca
            .par_chunks(px)
            .zip(cb.par_chunks(px))
            .map(|(x, y)| x.iter().zip(y).map(|(&p, &q)| p as f64 * q as f64).sum())
            .collect();
        total += parts.iter().sum::<f64>();
    }
    total
}

/// Zeroes the prescribed components (and nodes without material) of `v`.
pub fn mask_fixed(lat: &Lattice, v: &mut Vec3) {
    for (a, c) in v.c.iter_mut().enumerate() {
        c.par_iter_mut().enumerate().for_each(|(i, x)| {
            if lat.region[i] == 0 || lat.fixed[i] & (1 << a) != 0 {
                *x = 0.0;
            }
        });
    }
}
