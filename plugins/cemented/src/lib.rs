//! grainpipe-cemented: the sample chain of cemented granular materials (Heinze, Frank,
//! Lullien-Pellerin, George, Radjai & Delenne, Phys. Rev. E 101, 052901 (2020)):
//!
//! - `packing.poisson_disk`: two-step fast Poisson disk sampling of bidisperse disks/spheres
//!   (paper sec. II.A-B and appendix),
//! - `dem.compact`: soft-contact DEM compaction under a confining pressure (sec. II.B),
//! - `binder.bridges`: trapezoidal matrix bridges rasterised with the particles (sec. II.B),
//! - `analysis.pores`: single pores, single voids, matrix saturation and partial
//!   coordination numbers (sec. III, eqs. 8-9).
//!
//! Phase image convention shared with the peridynamics stages: 0 = pore (the paper's void),
//! 1 = large particle, 2 = small particle, 3 = matrix; the names are the phase vocabulary's
//! (docs/ARCHITECTURE.md, "Phase names").

// Axis loops (`for a in 0..dim`) index several 3-vectors at once; iterator chains would hide
// the vector algebra the comments cite.
#![allow(clippy::needless_range_loop)]

pub mod bridges;
pub mod common;
pub mod dem;
pub mod poisson;
pub mod pores;

/// Adds this crate's stages.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(poisson::PoissonDisk);
    r.add_stage(dem::Compact);
    r.add_stage(bridges::Bridges);
    r.add_stage(pores::Pores);
}
