//! grainpipe-stokes: Stokes permeability of voxel pore spaces (Donval et al. 2025, section 3.3).
//!
//! The stage lives in [`permeability`]; the numerics, free of framework types, in [`mac`]
//! (MAC discretisation, wall rule, percolation), [`multigrid`] (velocity-block V-cycle),
//! [`minres`] (the Krylov solver) and [`solver`] (load cases in voxel units).

pub mod mac;
pub mod minres;
pub mod multigrid;
pub mod permeability;
pub mod solver;
pub mod walls;

/// Adds this crate's stages.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(permeability::PermeabilityStage);
}
