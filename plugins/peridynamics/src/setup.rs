//! From a labelled image to a [`Lattice`] with grips: bond classes (section II.D), the
//! micromoduli (eq. (5) and its 3-D form), critical stretches, floating clusters and the
//! uniaxial-tension boundary values. Free of framework types.

use crate::lattice::{Lattice, Layout, Vec3};
use std::f64::consts::PI;

/// What a phase is made of, for bond classification.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// No nodes (voids, pores).
    Void,
    /// Particles: bonds inside one particle take the phase's modulus.
    Particle,
    /// Cementing matrix: matrix-matrix bonds take the phase's modulus.
    Matrix,
}

/// Material of one label.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PhaseSpec {
    pub role: Role,
    /// Young's modulus [Pa].
    pub e: f64,
    /// Critical energy release rate [J/m^2].
    pub gc: f64,
}

impl PhaseSpec {
    pub const VOID: PhaseSpec = PhaseSpec {
        role: Role::Void,
        e: 0.0,
        gc: 0.0,
    };
}

/// How particle identity is known.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Identity {
    /// Each face-connected region of one particle label is one particle (touching particles
    /// of the same label merge into one).
    Components,
    /// All voxels of a particle label are one particle (no interface between particles of
    /// the same phase).
    Phase,
    /// Given per voxel (x fastest), e.g. by the image maker from its packing: 1 + the
    /// particle's index on particle voxels (0 elsewhere). Touching particles stay apart.
    Given(std::sync::Arc<[u32]>),
}

/// How the grips hold the sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Grips {
    /// Every component prescribed on the grip layers (the paper's fixed lower boundary).
    Clamped,
    /// Only the load component prescribed; one grip node per cluster pinned transversally.
    Sliding,
}

/// Everything the lattice needs besides the image.
#[derive(Clone, Debug)]
pub struct Setup {
    /// Horizon in voxel edges.
    pub horizon: f64,
    pub interface: PhaseSpec,
    pub identity: Identity,
    pub breaking: bool,
    /// Load axis (0, 1, 2).
    pub axis: usize,
    pub grips: Grips,
    pub grip_layers: usize,
    /// Nominal strain between the inner grip layers.
    pub strain: f64,
    /// Refuse floating clusters instead of excluding them.
    pub fail_on_floating: bool,
    /// Factor on every bond constant (1: eq. (5); the calibrated micromodulus scales it so
    /// that the lattice's bulk modulus is E); the critical stretches are divided by its
    /// square root, which keeps each bond's fracture energy and so G_c.
    pub stiffness_scale: f64,
}

/// Micromodulus [Pa/m^3 in 2-D per unit thickness, Pa/m^4 in 3-D] of bond-based PD:
/// 2-D plane stress eq. (5), c = 6E/(pi h^3 (1 - nu)) with nu = 1/3 (= 9E/(pi h^3), Ha &
/// Bobaru 2010); 3-D c = 18K/(pi h^4) with K = E/(3(1 - 2 nu)), nu = 1/4 (Silling & Askari
/// 2005).
pub fn micromodulus(e: f64, h: f64, dim3: bool) -> f64 {
    if dim3 {
        let k = e / (3.0 * (1.0 - 2.0 * 0.25));
        18.0 * k / (PI * h.powi(4))
    } else {
        6.0 * e / (PI * h.powi(3) * (1.0 - 1.0 / 3.0))
    }
}

/// Bond constant k = c V_i V_j (eq. (7): k = c dx^4 in 2-D) in the lattice's scaled units
/// E_ref dx^(d-1), for a horizon of `h` voxel edges.
pub fn scaled_bond_constant(e: f64, e_ref: f64, h: f64, dim3: bool) -> f64 {
    // c dx^(2d) / (E_ref dx^(d-1)) with h = H dx: the dx powers cancel.
    micromodulus(e / e_ref, h, dim3)
}

/// Critical stretch from the critical energy release rate: 2-D plane stress
/// s_c = sqrt(4 pi G_c / (9 E h)) (Ha & Bobaru 2010), 3-D s_c = sqrt(5 G_c / (9 K h))
/// (Silling & Askari 2005), h in metres.
pub fn critical_stretch(e: f64, gc: f64, h: f64, dim3: bool) -> f64 {
    if dim3 {
        let k = e / (3.0 * (1.0 - 2.0 * 0.25));
        (5.0 * gc / (9.0 * k * h)).sqrt()
    } else {
        (4.0 * PI * gc / (9.0 * e * h)).sqrt()
    }
}

/// The lattice with its boundary values.
pub struct Built {
    pub lattice: Lattice,
    /// Initial displacement minus the affine background (see [`Lattice::bg`]), in dx:
    /// zero except in extra grip layers.
    pub u0: Vec3<f64>,
    /// Nodes with material before exclusion.
    pub nodes: usize,
    /// Nodes excluded as floating (no bond path to a grip).
    pub floating_nodes: usize,
    /// Floating clusters.
    pub floating_clusters: usize,
    /// Components pinned by the zero-stiffness rule (a DOF with no bond along it).
    pub mechanism_dofs: usize,
    /// Particles found (regions of particle phases).
    pub particles: usize,
    /// Bonds (each once) of class particle, matrix, interface.
    pub bonds: [u64; 3],
    /// Prescribed displacement of the top grip [dx].
    pub top_displacement: f64,
    /// Gauge length between the inner grip layers [dx].
    pub gauge: f64,
    /// Reference modulus of the scaling [Pa].
    pub e_ref: f64,
}

/// Errors of the set-up.
#[derive(Debug, Clone, PartialEq)]
pub enum SetupError {
    /// Nothing connects to the grips.
    Unloaded,
    /// Floating clusters with `fail_on_floating`.
    Floating {
        clusters: usize,
        nodes: usize,
        at: [usize; 3],
    },
    /// Given particle ids that do not fit the image.
    Identity(String),
}

impl std::fmt::Display for SetupError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SetupError::Unloaded => write!(
                f,
                "no material node lies in a grip layer: the sample cannot be loaded"
            ),
            SetupError::Identity(text) => write!(f, "particles: {text}"),
            SetupError::Floating {
                clusters,
                nodes,
                at,
            } => write!(
                f,
                "{clusters} floating cluster(s) ({nodes} nodes, the first at voxel {at:?}) have \
                 no bond path to a grip; set floating: exclude to drop them"
            ),
        }
    }
}

/// Face-connected components of each particle label (4-connectivity in 2-D, 6 in 3-D):
/// particle id per voxel (0 for other voxels) and the count.
fn particle_ids(dims: [usize; 3], labels: &[u8], is_particle: &[bool; 256]) -> (Vec<u32>, usize) {
    let n = labels.len();
    let mut id = vec![0u32; n];
    let mut next = 0u32;
    let mut stack = Vec::new();
    let [nx, ny, nz] = dims;
    for s in 0..n {
        if id[s] != 0 || !is_particle[labels[s] as usize] {
            continue;
        }
        next += 1;
        id[s] = next;
        stack.push(s);
        while let Some(i) = stack.pop() {
            let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
            let mut visit = |j: usize| {
                if id[j] == 0 && labels[j] == labels[i] {
                    id[j] = next;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < nx {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - nx);
            }
            if y + 1 < ny {
                visit(i + nx);
            }
            if z > 0 {
                visit(i - nx * ny);
            }
            if z + 1 < nz {
                visit(i + nx * ny);
            }
        }
    }
    (id, next as usize)
}

/// Builds the lattice of an image of `dims` voxels with `labels` (x fastest), the phase of
/// each label in `phases`, and the boundary values of uniaxial tension.
pub fn build(
    dims: [usize; 3],
    labels: &[u8],
    phases: &[PhaseSpec; 256],
    dx: f64,
    s: &Setup,
) -> Result<Built, SetupError> {
    let layout = Layout::new(dims, s.horizon);
    let dim3 = layout.dim3;
    let np = layout.len();
    let e_ref = phases
        .iter()
        .filter(|p| p.role != Role::Void)
        .map(|p| p.e)
        .chain(std::iter::once(s.interface.e))
        .fold(0.0, f64::max);
    let h_m = s.horizon * dx;
    let mut is_particle = [false; 256];
    for (l, p) in phases.iter().enumerate() {
        is_particle[l] = p.role == Role::Particle;
    }
    let given;
    let (pid, nparticles): (&[u32], usize) = match &s.identity {
        Identity::Components => {
            given = particle_ids(dims, labels, &is_particle);
            (&given.0, given.1)
        }
        Identity::Phase => {
            given = (vec![0; labels.len()], 0);
            (&given.0, 0)
        }
        Identity::Given(ids) => {
            if ids.len() != labels.len() {
                return Err(SetupError::Identity(format!(
                    "the particle ids have {} values for {} voxels",
                    ids.len(),
                    labels.len()
                )));
            }
            let mut seen = std::collections::BTreeSet::new();
            for (v, (&id, &l)) in ids.iter().zip(labels).enumerate() {
                if is_particle[l as usize] {
                    if id == 0 {
                        let [nx, ny, _] = dims;
                        return Err(SetupError::Identity(format!(
                            "voxel ({}, {}, {}) is of a particle phase (label {l}) but has no \
                             particle id",
                            v % nx,
                            (v / nx) % ny,
                            v / (nx * ny)
                        )));
                    }
                    seen.insert(id);
                }
            }
            (ids, seen.len())
        }
    };
    let mut region = vec![0u32; np];
    let mut kself = vec![0f32; np];
    let mut sc_self = if s.breaking {
        vec![0f32; np]
    } else {
        Vec::new()
    };
    let [nx, ny, nz] = dims;
    let mut particles_by_phase = [false; 256];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let v = x + nx * (y + ny * z);
                let lab = labels[v] as usize;
                let ph = phases[lab];
                if ph.role == Role::Void {
                    continue;
                }
                let i = layout.pidx(x, y, z);
                // Region ids: 1 + label for matrix phases (and particle phases without
                // identity), 257 + particle id for particles found as components.
                region[i] = match (ph.role, &s.identity) {
                    (Role::Particle, Identity::Components | Identity::Given(_)) => 257 + pid[v],
                    _ => 1 + lab as u32,
                };
                if ph.role == Role::Particle {
                    particles_by_phase[lab] = true;
                }
                kself[i] =
                    (s.stiffness_scale * scaled_bond_constant(ph.e, e_ref, s.horizon, dim3)) as f32;
                if s.breaking {
                    sc_self[i] = (critical_stretch(ph.e, ph.gc, h_m, dim3)
                        / s.stiffness_scale.sqrt()) as f32;
                }
            }
        }
    }
    let particles = match s.identity {
        Identity::Components | Identity::Given(_) => nparticles,
        Identity::Phase => particles_by_phase.iter().filter(|&&b| b).count(),
    };
    let kint =
        (s.stiffness_scale * scaled_bond_constant(s.interface.e, e_ref, s.horizon, dim3)) as f32;
    let sc_int = if s.breaking {
        (critical_stretch(s.interface.e, s.interface.gc, h_m, dim3) / s.stiffness_scale.sqrt())
            as f32
    } else {
        f32::INFINITY
    };
    let mut lat = Lattice {
        layout,
        region,
        kself,
        kint,
        fixed: vec![0u8; np],
        sc_self,
        sc_int,
        bg: [0.0; 3],
    };
    let nodes = lat.region.iter().filter(|&&r| r != 0).count();

    // Grips along the load axis.
    let a = s.axis;
    let na = dims[a];
    let g = s.grip_layers;
    let layer = |i: usize| lat.layout.coords(i).map(|c| c[a]);
    let grip = |c: usize| c < g || c + g >= na;

    // Floating clusters: components over bonds that contain no grip node.
    let comp = lat.components();
    let mut supported = std::collections::HashSet::new();
    for (i, &c) in comp.iter().enumerate() {
        if c != u32::MAX && layer(i).map(grip).unwrap_or(false) {
            supported.insert(c);
        }
    }
    if supported.is_empty() {
        return Err(SetupError::Unloaded);
    }
    let mut floating_nodes = 0;
    let mut floating_roots = std::collections::BTreeSet::new();
    let mut first_floating = None;
    for (i, &c) in comp.iter().enumerate() {
        if c != u32::MAX && !supported.contains(&c) {
            floating_nodes += 1;
            floating_roots.insert(c);
            if first_floating.is_none() {
                first_floating = lat.layout.coords(i);
            }
        }
    }
    if floating_nodes > 0 && s.fail_on_floating {
        return Err(SetupError::Floating {
            clusters: floating_roots.len(),
            nodes: floating_nodes,
            at: first_floating.unwrap_or([0; 3]),
        });
    }
    for (i, &c) in comp.iter().enumerate() {
        if c != u32::MAX && !supported.contains(&c) {
            // Excluded: no bonds, no unknowns, zero displacement and stress.
            lat.region[i] = 0;
            lat.kself[i] = 0.0;
        }
    }

    // Boundary values: bottom grip at 0, top grip displaced by strain x gauge; affine guess
    // in between (exact for a homogeneous bar far from the surfaces).
    let gauge = (na as f64 - 2.0 * g as f64 + 1.0).max(1.0);
    let top = s.strain * gauge;
    let mut u0: Vec3<f64> = Vec3::zeros(&lat.layout);
    let all_bits: u8 = if dim3 { 0b111 } else { 0b11 };
    let mut pinned_cluster = std::collections::HashSet::new();
    for (i, &ci) in comp.iter().enumerate() {
        if lat.region[i] == 0 {
            continue;
        }
        let c = layer(i).expect("material nodes are unpadded");
        // Stored: the deviation from the affine field strain x (c - (g - 1)), which the
        // lattice's background strain carries (zero inside the gauge, non-zero only in
        // extra grip layers that are held rigid).
        let affine = c as f64 - (g as f64 - 1.0);
        let val = (affine.clamp(0.0, gauge) - affine) * s.strain;
        u0.c[a][i] = val;
        if grip(c) {
            lat.fixed[i] = match s.grips {
                Grips::Clamped => all_bits,
                Grips::Sliding => {
                    // One node per cluster pinned transversally removes the rigid
                    // translation; the grip layer itself prevents rotation in 2-D.
                    if pinned_cluster.insert(ci) {
                        all_bits
                    } else {
                        1 << a
                    }
                }
            };
        }
    }
    lat.bg[a] = s.strain as f32;
    // A DOF with no stiffness along it (e.g. a one-voxel line) is a mechanism: pin it.
    let (diag, _): (Vec3, Vec3) = lat.stiffness_bounds();
    let mut mechanism_dofs = 0;
    for i in 0..np {
        if lat.region[i] == 0 {
            continue;
        }
        for (b, d) in diag.c.iter().enumerate() {
            if d[i] <= 0.0 && lat.fixed[i] & (1 << b) == 0 {
                lat.fixed[i] |= 1 << b;
                mechanism_dofs += 1;
            }
        }
    }
    // Bond census by class (each bond once: positive half of the stencil).
    let mut bonds = [0u64; 3];
    for i in 0..np {
        let ri = lat.region[i];
        if ri == 0 {
            continue;
        }
        for o in lat.layout.offsets.iter().filter(|o| o.d > 0) {
            let rj = lat.region[(i as isize + o.d) as usize];
            if rj == 0 {
                continue;
            }
            let class = if ri != rj {
                2
            } else if ri >= 257 || is_particle[(ri - 1) as usize] {
                0
            } else {
                1
            };
            bonds[class] += 1;
        }
    }
    Ok(Built {
        lattice: lat,
        u0,
        nodes,
        floating_nodes,
        floating_clusters: floating_roots.len(),
        mechanism_dofs,
        particles,
        bonds,
        top_displacement: top,
        gauge,
        e_ref,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stencil_of_the_paper_has_28_neighbours() {
        let l = Layout::new([16, 16, 1], 3.0);
        assert_eq!(l.offsets.len(), 28);
        let l3 = Layout::new([16, 16, 16], 3.0);
        assert_eq!(l3.offsets.len(), 122);
    }

    #[test]
    fn micromodulus_matches_the_paper() {
        // eq. (5) with nu = 1/3: c = 9 E / (pi h^3).
        let c = micromodulus(1.0, 2.0, false);
        assert!((c - 9.0 / (PI * 8.0)).abs() < 1e-12);
        // 3-D: 18 K / (pi h^4), K = 2E/3 for nu = 1/4.
        let c = micromodulus(3.0, 1.0, true);
        assert!((c - 18.0 * 2.0 / PI).abs() < 1e-12);
    }
}
