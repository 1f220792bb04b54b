//! grainpipe-analysis: image analysis.
//!
//! - `analysis.phases` ([`phases`]): per-phase volume fractions, specific surface, connected
//!   components and percolation of a phase image.
//! - `analysis.ensemble` ([`ensemble`]): ensemble statistics and the Kanit et al. RVE
//!   analysis of a table of realizations (also used by `pipe sweep`).
//! - Pore-space measures of one phase (what a porespy user expects): `analysis.local_thickness`
//!   ([`thickness`]), `analysis.two_point` ([`two_point`]), `analysis.chords` ([`chords`]),
//!   `analysis.tortuosity` ([`tortuosity`]); their shared parameters and lattice helpers in
//!   [`pores`].
//! - Kernels free of framework types: [`components`] (6-connected labelling with periodic
//!   winding), [`surface`] (transition counts, Crofton and face-count surface estimates),
//!   [`thickness::local_thickness`], [`two_point::pair_counts`], [`chords::chord_counts`],
//!   [`tortuosity::geodesic`].

pub mod chords;
pub mod components;
pub mod ensemble;
pub mod phases;
pub mod pores;
pub mod surface;
pub mod thickness;
pub mod tortuosity;
pub mod two_point;

/// Adds this crate's stages.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(phases::Phases);
    r.add_stage(ensemble::Ensemble);
    r.add_stage(thickness::LocalThickness);
    r.add_stage(two_point::TwoPoint);
    r.add_stage(chords::ChordLengths);
    r.add_stage(tortuosity::Tortuosity);
}
