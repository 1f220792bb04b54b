//! Staggered (MAC) finite volumes for periodic Stokes flow on a voxel grid, in voxel units
//! (h = 1, mu = 1): the pore mask, the percolation analysis and the saddle-point operator.
//!
//! Unknowns: `u_a[i]` on the face between voxel `i` and `i + e_a` (a = x, y, z), `p[i]` at
//! voxel centres. A face carries an unknown only when both voxels it separates are fluid
//! (and belong to a percolating pore component); every other face is a no-slip wall.
//! The momentum row of an active face is the 7-point Laplacian in which
//! - a missing neighbour along the face normal is a wall face where u = 0 exactly, one cell
//!   away (coefficient 1);
//! - a missing transverse neighbour means a solid voxel beside the face: the wall is the voxel
//!   face half a cell away, imposed by the ghost value u_ghost = -u (coefficient 2).
//!
//! The system is symmetric: [[A, B^T], [B, 0]] with A = -Lap (walls included), B = -div,
//! B^T = grad, so that A u + grad p = f, -div u = 0 (eq. (3.6) with the paper's sign of p
//! flipped, which changes nothing in u).

use rayon::prelude::*;

/// Mask bit: the voxel is fluid in a percolating component.
pub const FLUID: u8 = 1;
/// Mask bit: the face between voxel i and i + e_a carries an unknown (bit `ACTIVE << a`).
pub const ACTIVE: u8 = 2;

#[inline]
pub fn active_bit(axis: usize) -> u8 {
    ACTIVE << axis
}

/// Periodic grid indexing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dims {
    pub n: [usize; 3],
}

impl Dims {
    pub fn new(n: [usize; 3]) -> Dims {
        Dims { n }
    }
    #[inline]
    pub fn len(&self) -> usize {
        self.n[0] * self.n[1] * self.n[2]
    }
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    #[inline]
    pub fn slab(&self) -> usize {
        self.n[0] * self.n[1]
    }
    #[inline]
    pub fn index(&self, x: usize, y: usize, z: usize) -> usize {
        x + self.n[0] * (y + self.n[1] * z)
    }
    #[inline]
    pub fn coords(&self, i: usize) -> [usize; 3] {
        let s = self.slab();
        [i % self.n[0], (i / self.n[0]) % self.n[1], i / s]
    }
    /// Neighbour indices in the order -x, +x, -y, +y, -z, +z (periodic).
    #[inline]
    pub fn neighbours(&self, x: usize, y: usize, z: usize) -> [usize; 6] {
        let [nx, ny, nz] = self.n;
        let xm = if x == 0 { nx - 1 } else { x - 1 };
        let xp = if x + 1 == nx { 0 } else { x + 1 };
        let ym = if y == 0 { ny - 1 } else { y - 1 };
        let yp = if y + 1 == ny { 0 } else { y + 1 };
        let zm = if z == 0 { nz - 1 } else { z - 1 };
        let zp = if z + 1 == nz { 0 } else { z + 1 };
        [
            self.index(xm, y, z),
            self.index(xp, y, z),
            self.index(x, ym, z),
            self.index(x, yp, z),
            self.index(x, y, zm),
            self.index(x, y, zp),
        ]
    }
}

/// Connected pore components (6-connectivity, periodic wrap) and which ones percolate.
#[derive(Clone, Debug)]
pub struct Percolation {
    /// Fluid voxels kept in the solve (in a component that wraps along at least one axis).
    pub kept: usize,
    /// Fluid voxels dropped because their component wraps along no axis.
    pub isolated: usize,
    /// Number of fluid components, and how many of them percolate.
    pub components: usize,
    pub percolating_components: usize,
    /// Whether some kept component connects to its own periodic image along each axis.
    pub percolates: [bool; 3],
}

/// Builds the mask (FLUID and ACTIVE bits) from `is_fluid`, keeping only components that
/// connect to their own periodic image along some axis: a component that does not can carry
/// no mean flow, and leaving it in would only add a singular block to the solve.
///
/// A component wraps along an axis when two paths to one voxel differ by a whole number of
/// periods: the breadth-first search stores each voxel's unwrapped image shift and compares it
/// when an edge closes a cycle.
pub fn build_mask(dims: Dims, is_fluid: &[bool]) -> (Vec<u8>, Percolation) {
    let n = dims.len();
    assert_eq!(is_fluid.len(), n);
    const UNSEEN: u32 = u32::MAX;
    let mut comp = vec![UNSEEN; n];
    let mut shift = vec![[0i32; 3]; n];
    let mut wraps: Vec<[bool; 3]> = Vec::new();
    let mut queue: Vec<u32> = Vec::new();
    for seed in 0..n {
        if !is_fluid[seed] || comp[seed] != UNSEEN {
            continue;
        }
        let id = wraps.len() as u32;
        let mut w = [false; 3];
        comp[seed] = id;
        shift[seed] = [0; 3];
        queue.clear();
        queue.push(seed as u32);
        let mut head = 0;
        while head < queue.len() {
            let i = queue[head] as usize;
            head += 1;
            let [x, y, z] = dims.coords(i);
            let c = [x, y, z];
            let nb = dims.neighbours(x, y, z);
            for (k, &j) in nb.iter().enumerate() {
                if !is_fluid[j] {
                    continue;
                }
                let axis = k / 2;
                let plus = k % 2 == 1;
                let mut s = shift[i];
                // Crossing the periodic boundary moves to the next image.
                if plus && c[axis] + 1 == dims.n[axis] {
                    s[axis] += 1;
                } else if !plus && c[axis] == 0 {
                    s[axis] -= 1;
                }
                if comp[j] == UNSEEN {
                    comp[j] = id;
                    shift[j] = s;
                    queue.push(j as u32);
                } else {
                    for a in 0..3 {
                        if shift[j][a] != s[a] {
                            w[a] = true;
                        }
                    }
                }
            }
        }
        wraps.push(w);
    }
    drop(shift);
    let keep: Vec<bool> = wraps.iter().map(|w| w.iter().any(|&b| b)).collect();
    let mut mask = vec![0u8; n];
    mask.par_iter_mut().enumerate().for_each(|(i, m)| {
        if comp[i] != UNSEEN && keep[comp[i] as usize] {
            *m = FLUID;
        }
    });
    let kept = mask.iter().filter(|&&m| m == FLUID).count();
    let fluid_total = is_fluid.iter().filter(|&&f| f).count();
    let mut percolates = [false; 3];
    for w in wraps.iter() {
        for a in 0..3 {
            percolates[a] |= w[a];
        }
    }
    drop(comp);
    set_active_faces(dims, &mut mask);
    let perc = Percolation {
        kept,
        isolated: fluid_total - kept,
        components: wraps.len(),
        percolating_components: keep.iter().filter(|&&k| k).count(),
        percolates,
    };
    (mask, perc)
}

fn set_active_faces(dims: Dims, mask: &mut [u8]) {
    let fluid: Vec<bool> = mask.iter().map(|&m| m & FLUID != 0).collect();
    let slab = dims.slab();
    mask.par_chunks_mut(slab).enumerate().for_each(|(z, s)| {
        for y in 0..dims.n[1] {
            for x in 0..dims.n[0] {
                let i = dims.index(x, y, z);
                if !fluid[i] {
                    continue;
                }
                let nb = dims.neighbours(x, y, z);
                for a in 0..3 {
                    if fluid[nb[2 * a + 1]] {
                        s[i - z * slab] |= active_bit(a);
                    }
                }
            }
        }
    });
}

/// Diagonal of the velocity Laplacian at the active face `(a, c)` with neighbours `nb`.
#[inline]
pub fn face_diag(dims: Dims, mask: &[u8], a: usize, c: [usize; 3], nb: &[usize; 6]) -> f32 {
    let bit = active_bit(a);
    let mut d = 0.0;
    for (k, &j) in nb.iter().enumerate() {
        let b = k / 2;
        if dims.n[b] == 1 {
            continue; // a single layer couples only to itself: no term
        }
        d += if mask[j] & bit != 0 || b == a {
            // Active neighbour, or the wall is the next face along the normal, one cell away.
            1.0
        } else {
            // The neighbouring face has no unknown. If it touches a solid voxel it lies on the
            // solid surface, where u = 0 one cell away; only if both voxels beside it are
            // solid is the nearest wall the voxel face half a cell away (u_ghost = -u).
            let mut c2 = c;
            c2[a] = (c2[a] + 1) % dims.n[a];
            let plus = k % 2 == 1;
            c2[b] = if plus {
                (c2[b] + 1) % dims.n[b]
            } else {
                (c2[b] + dims.n[b] - 1) % dims.n[b]
            };
            let j2 = dims.index(c2[0], c2[1], c2[2]);
            let solid = (mask[j] & FLUID == 0) as u8 + (mask[j2] & FLUID == 0) as u8;
            if solid == 2 {
                2.0
            } else {
                1.0
            }
        };
    }
    d
}

/// The velocity-Laplacian diagonals of the three components ([x | y | z] blocks, one byte per
/// face: they are whole numbers up to 12), computed once from the wall rule.
pub fn diagonals(dims: Dims, mask: &[u8]) -> Vec<u8> {
    let n = dims.len();
    let mut d = vec![0u8; 3 * n];
    d.par_chunks_mut(dims.slab().max(1))
        .enumerate()
        .for_each(|(item, s)| {
            let nz = dims.n[2];
            let (a, z) = (item / nz, item % nz);
            for y in 0..dims.n[1] {
                for x in 0..dims.n[0] {
                    let i = dims.index(x, y, z);
                    if mask[i] & active_bit(a) != 0 {
                        let nb = dims.neighbours(x, y, z);
                        s[x + dims.n[0] * y] = face_diag(dims, mask, a, [x, y, z], &nb) as u8;
                    }
                }
            }
        });
    d
}

/// A stored velocity-Laplacian diagonal: the whole numbers of the label wall rule in one byte
/// ([`diagonals`]), or the real values of the sub-voxel wall rule ([`composite_diagonals`]).
pub trait DiagValue: Copy + Send + Sync + 'static {
    /// The diagonal entry.
    fn value(self) -> f32;
    /// `x / value`, as the fine Gauss-Seidel sweeps use it (the byte form multiplies by a
    /// tabulated reciprocal, see [`crate::multigrid`]).
    fn divide(self, x: f32) -> f32;
}

impl DiagValue for u8 {
    #[inline(always)]
    fn value(self) -> f32 {
        self as f32
    }
    #[inline(always)]
    fn divide(self, x: f32) -> f32 {
        x * crate::multigrid::INV_DIAG[self as usize]
    }
}

impl DiagValue for f32 {
    #[inline(always)]
    fn value(self) -> f32 {
        self
    }
    #[inline(always)]
    fn divide(self, x: f32) -> f32 {
        x / self
    }
}

/// Smallest wall distance (in voxels) of the sub-voxel wall rule: a face closer to the wall
/// is treated as this far (Gibou et al. 2002 clamp; its velocity is ~THETA_MIN of the
/// neighbours', so the error is of that order on a small velocity). Keeps diagonals <= 25.
pub const THETA_MIN: f64 = 0.05;
/// Largest wall distance of the sub-voxel wall rule (the wall beyond an inactive neighbour
/// face whose control volume is mostly fluid).
pub const THETA_MAX: f64 = 1.5;

/// Distance `theta` (voxels) from the velocity point of face `P` to the wall towards its
/// neighbour face `Q` (inactive), from the fluid fractions of the staggered control volumes
/// of `P`, of `Q` and of `R`, the face on the other side of `P` (each the mean of the fluid
/// fractions of the two voxels the face separates): the wall is where the fluid length along
/// the line R-P-Q ends. `Q` holds `phi_q` of fluid next to `P`; the solid `1 - phi_p` of `P`
/// lies on the `Q` side in the proportion of the solid of `Q` to that of `Q` and `R` (all of
/// it when `R` is pure fluid). For a plane wall that crosses the four edges along the line of
/// the cells it cuts, the fluid length is exact (the mean of a linear function over a square
/// is its centre value). With label fractions (0 or 1 per voxel) this is the label rule:
/// `Q` between two solid voxels gives 1/2 (ghost -u), `Q` touching one solid voxel gives 1.
#[inline]
pub fn wall_distance(phi_p: f64, phi_q: f64, phi_r: f64) -> f64 {
    let (sq, sr) = (1.0 - phi_q, 1.0 - phi_r);
    let s_q = if sq + sr > 0.0 {
        (1.0 - phi_p) * sq / (sq + sr)
    } else {
        0.0
    };
    (0.5 - s_q + phi_q).clamp(THETA_MIN, THETA_MAX)
}

/// The velocity-Laplacian diagonals of the sub-voxel wall rule ([x | y | z] blocks, f32, 0
/// off the active faces): as [`diagonals`], but a missing neighbour face `Q` of the active
/// face `P` adds `1 / theta` with the wall distance `theta` of [`wall_distance`] computed
/// from the voxels' fluid fractions `phi` (1 = fluid), instead of the whole numbers 1 or 2.
/// This is the symmetric Dirichlet treatment of Gibou, Fedkiw, Cheng & Kang (J. Comput.
/// Phys. 176 (2002) 205-227): the ghost value beyond the wall is the linear extrapolation
/// through u = 0 at distance theta, `u_g = u (1 - 1/theta)`, which only changes the
/// diagonal, so the operator stays symmetric positive definite (an M-matrix), and the
/// solution is second-order accurate for a wall anywhere between the grid points.
/// With `phi` in {0, 1} matching the mask, the values are those of [`diagonals`].
pub fn composite_diagonals(dims: Dims, mask: &[u8], phi: &[f32]) -> Vec<f32> {
    composite_walls(dims, mask, phi).0
}

/// [`composite_diagonals`] and the force weights of the active faces ([x | y | z] blocks):
/// the product over the axes of the extent `(theta_- + theta_+) / 2` of the face's dual
/// cell (`theta = 1` towards an active neighbour), by which the body force of the face's
/// row is scaled. Along one axis this turns the symmetric row into the Shortley-Weller
/// difference (exact for a parabola, a wall at any distance) multiplied through by the
/// dual-cell extent; only the right-hand side changes, so the operator stays symmetric.
pub fn composite_walls(dims: Dims, mask: &[u8], phi: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let n = dims.len();
    assert_eq!(phi.len(), n);
    let mut d = vec![0f32; 3 * n];
    let mut wt = vec![0f32; 3 * n];
    d.par_chunks_mut(dims.slab().max(1))
        .zip(wt.par_chunks_mut(dims.slab().max(1)))
        .enumerate()
        .for_each(|(item, (s, ws))| {
            let nz = dims.n[2];
            let (a, z) = (item / nz, item % nz);
            let bit = active_bit(a);
            // Fluid fraction of the staggered control volume of face (a, j).
            let face = |j: usize| {
                let c = dims.coords(j);
                let mut c2 = c;
                c2[a] = (c2[a] + 1) % dims.n[a];
                0.5 * (phi[j] as f64 + phi[dims.index(c2[0], c2[1], c2[2])] as f64)
            };
            for y in 0..dims.n[1] {
                for x in 0..dims.n[0] {
                    let i = dims.index(x, y, z);
                    if mask[i] & bit == 0 {
                        continue;
                    }
                    let nb = dims.neighbours(x, y, z);
                    let phi_p = face(i);
                    let mut diag = 0.0f64;
                    let mut weight = 1.0f64;
                    for b in 0..3 {
                        if dims.n[b] == 1 {
                            continue;
                        }
                        let mut extent = 0.0;
                        for k in [2 * b, 2 * b + 1] {
                            let j = nb[k];
                            let theta = if mask[j] & bit != 0 {
                                1.0
                            } else {
                                wall_distance(phi_p, face(j), face(nb[k ^ 1]))
                            };
                            diag += 1.0 / theta;
                            extent += 0.5 * theta;
                        }
                        weight *= extent;
                    }
                    s[x + dims.n[0] * y] = diag as f32;
                    ws[x + dims.n[0] * y] = weight as f32;
                }
            }
        });
    (d, wt)
}

/// The saddle-point operator on vectors laid out as [u_x | u_y | u_z | p], each block one
/// value per voxel (zero where there is no unknown).
pub struct Stokes<'a, D: DiagValue = u8> {
    pub dims: Dims,
    pub mask: &'a [u8],
    /// From [`diagonals`] or [`composite_diagonals`].
    pub diag: &'a [D],
    /// Body-force weight per face ([x | y | z] blocks, see [`composite_walls`]); `None`: 1
    /// on every active face.
    pub force: Option<&'a [f32]>,
}

impl<D: DiagValue> Stokes<'_, D> {
    pub fn len(&self) -> usize {
        4 * self.dims.len()
    }
    pub fn is_empty(&self) -> bool {
        self.dims.is_empty()
    }

    /// Row `(block, x, y, z)` of K applied to `v`.
    #[inline]
    pub fn row(&self, v: &[f32], block: usize, x: usize, y: usize, z: usize) -> f32 {
        let i = self.dims.index(x, y, z);
        self.row_at(v, block, i, &self.dims.neighbours(x, y, z))
    }

    /// Row `(block, i)` of K applied to `v`, given the neighbours `nb` of voxel `i` in the
    /// order of [`Dims::neighbours`].
    #[inline]
    pub fn row_at(&self, v: &[f32], block: usize, i: usize, nb: &[usize; 6]) -> f32 {
        self.row_of::<true>(v, block, i, nb)
    }

    /// [`Stokes::row_at`] for a `v` that is zero off the unknowns (inactive faces, solid
    /// pressures), as every preconditioned vector is: the neighbour sum needs no mask tests
    /// (adding the zeros is exact), the same value.
    #[inline(always)]
    fn row_at_zero_off(&self, v: &[f32], block: usize, i: usize, nb: &[usize; 6]) -> f32 {
        self.row_of::<false>(v, block, i, nb)
    }

    /// The row, testing each velocity neighbour's mask bit only when `MASK_TESTS` (a `v`
    /// that may be non-zero on inactive faces).
    #[inline(always)]
    fn row_of<const MASK_TESTS: bool>(
        &self,
        v: &[f32],
        block: usize,
        i: usize,
        nb: &[usize; 6],
    ) -> f32 {
        let n = self.dims.len();
        let m = self.mask[i];
        if block < 3 {
            let a = block;
            let bit = active_bit(a);
            if m & bit == 0 {
                return 0.0;
            }
            let u = &v[a * n..(a + 1) * n];
            let mut sum = 0.0f32;
            for (k, &j) in nb.iter().enumerate() {
                if self.dims.n[k / 2] > 1 && (!MASK_TESTS || self.mask[j] & bit != 0) {
                    sum += u[j];
                }
            }
            let p = &v[3 * n..];
            self.diag[a * n + i].value() * u[i] - sum + (p[nb[2 * a + 1]] - p[i])
        } else {
            if m & FLUID == 0 {
                return 0.0;
            }
            // -div u: the inactive faces hold zeros.
            let mut div = 0.0f32;
            for a in 0..3 {
                div += v[a * n + i] - v[a * n + nb[2 * a]];
            }
            -div
        }
    }

    /// Calls `f(block, z, row values of K v in that slab)` for every (block, z-slab) in parallel
    /// and returns the per-slab results in a fixed order.
    pub fn map_slabs<R: Send, F>(&self, v: &[f32], f: F) -> Vec<R>
    where
        F: Fn(usize, usize, &[f32]) -> R + Sync + Send,
    {
        let nz = self.dims.n[2];
        (0..4 * nz)
            .into_par_iter()
            .map_init(
                || vec![0f32; self.dims.slab()],
                |buf, item| {
                    let (block, z) = (item / nz, item % nz);
                    for y in 0..self.dims.n[1] {
                        for x in 0..self.dims.n[0] {
                            buf[x + self.dims.n[0] * y] = self.row(v, block, x, y, z);
                        }
                    }
                    f(block, z, buf)
                },
            )
            .collect()
    }

    /// <v, K v> reduced slab by slab in a fixed order.
    pub fn quad(&self, v: &[f32]) -> f64 {
        let slab = self.dims.slab();
        let n = self.dims.len();
        self.map_slabs(v, |block, z, kv| {
            let off = block * n + z * slab;
            dot32(kv, &v[off..off + slab])
        })
        .iter()
        .sum::<f64>()
    }

    /// out <- K (s v) - b * out, returning <K (s v), s v> (reduced slab by slab in a fixed
    /// order), for `v` zero off the unknowns (a preconditioned vector): the first half of the Lanczos recurrence, without a K v buffer, with one
    /// operator application per iteration and the scaling of v folded in.
    pub fn apply_shift_quad(&self, v: &[f32], out: &mut [f32], b: f64, s: f64) -> f64 {
        let slab = self.dims.slab();
        let nz = self.dims.n[2];
        let b = b as f32;
        let sf = s as f32;
        out.par_chunks_mut(slab)
            .enumerate()
            .map(|(item, o)| {
                let (block, z) = (item / nz, item % nz);
                let mut q = 0.0f64;
                let [nx, ny, nz] = self.dims.n;
                let zm = if z == 0 { nz - 1 } else { z - 1 };
                let zp = if z + 1 == nz { 0 } else { z + 1 };
                for y in 0..ny {
                    // Neighbour indices per row: the values of `Dims::neighbours` without its
                    // per-point wrap tests.
                    let ym = if y == 0 { ny - 1 } else { y - 1 };
                    let yp = if y + 1 == ny { 0 } else { y + 1 };
                    let row = self.dims.index(0, y, z);
                    let (rym, ryp) = (self.dims.index(0, ym, z), self.dims.index(0, yp, z));
                    let (rzm, rzp) = (self.dims.index(0, y, zm), self.dims.index(0, y, zp));
                    for x in 0..nx {
                        let l = x + nx * y;
                        let xm = if x == 0 { nx - 1 } else { x - 1 };
                        let xp = if x + 1 == nx { 0 } else { x + 1 };
                        let nb = [row + xm, row + xp, rym + x, ryp + x, rzm + x, rzp + x];
                        let kv = self.row_at_zero_off(v, block, row + x, &nb);
                        q += kv as f64 * v[item * slab + l] as f64;
                        o[l] = sf * kv - b * o[l];
                    }
                }
                q
            })
            .collect::<Vec<f64>>()
            .iter()
            .sum::<f64>()
            * (s * s)
    }

    /// ||b - K v||^2 split into (velocity rows, pressure rows) for the unit body force along
    /// `axis` (b = 1 on the active faces of that component), without storing b.
    pub fn residual_sq(&self, v: &[f32], axis: usize) -> (f64, f64) {
        let slab = self.dims.slab();
        let bit = active_bit(axis);
        let parts = self.map_slabs(v, |block, z, kv| {
            let m = &self.mask[z * slab..(z + 1) * slab];
            let off = block.min(2) * self.dims.len() + z * slab;
            let s: f64 = kv
                .iter()
                .zip(m)
                .enumerate()
                .map(|(l, (&k, &mm))| {
                    let r = if block == axis && mm & bit != 0 {
                        self.force.map_or(1.0, |w| w[off + l] as f64)
                    } else {
                        0.0
                    };
                    let d = r - k as f64;
                    d * d
                })
                .sum();
            (block, s)
        });
        let mut vel = 0.0;
        let mut pre = 0.0;
        for (b, s) in parts {
            if b < 3 {
                vel += s;
            } else {
                pre += s;
            }
        }
        (vel, pre)
    }
}

/// Dot product of two f32 slices accumulated in f64 (sequential: callers chunk it).
#[inline]
pub fn dot32(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(&x, &y)| x as f64 * y as f64).sum()
}

/// Chunk length of parallel reductions; fixed so the sums do not depend on the thread count.
pub const CHUNK: usize = 1 << 14;

/// <a, b> in fixed chunks.
pub fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.par_chunks(CHUNK)
        .zip(b.par_chunks(CHUNK))
        .map(|(x, y)| dot32(x, y))
        .collect::<Vec<f64>>()
        .iter()
        .sum()
}
