//! grainpipe-analysis: image analysis.
//!
//! - `analysis.phases` ([`phases`]): per-phase volume fractions, specific surface, connected
//!   components and percolation of a phase image.
//! - `analysis.ensemble` ([`ensemble`]): ensemble statistics and the Kanit et al. RVE
//!   analysis of a table of realizations (also used by `pipe sweep`).
//! - Kernels free of framework types: [`components`] (6-connected labelling with periodic
//!   winding) and [`surface`] (transition counts, Crofton and face-count surface estimates).

pub mod components;
pub mod ensemble;
pub mod phases;
pub mod surface;

/// Adds this crate's stages.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(phases::Phases);
    r.add_stage(ensemble::Ensemble);
}
