//! grainpipe-peridynamics: bond-based peridynamics on a regular grid (Heinze et al. 2020)
//! and stress statistics per phase.
//!
//! - `peridynamics.bond_based` ([`bond_based`]): uniaxial tension of a phase image; CG, ADR
//!   or explicit dynamics; displacement and stress fields.
//! - `analysis.stress_stats` ([`stress_stats`]): per-phase PDFs of sigma / mean, variance,
//!   exponential-tail exponent, excess kurtosis.
//! - `pdf-png` ([`pdf_png`]): the exporter plotting stress_stats' PDFs (log y, tail fits).
//! - Kernels free of framework types: [`lattice`] (stencil, forces, stress), [`setup`]
//!   (bond classes, grips, floating clusters), [`solve`] (CG, ADR, explicit).

pub mod bond_based;
pub mod lattice;
pub mod multigrid;
pub mod pdf_png;
pub mod setup;
pub mod solve;
pub mod stress_stats;

/// Adds this crate's stages and its exporter.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(bond_based::BondBased);
    r.add_stage(stress_stats::StressStats);
    r.add_exporter(pdf_png::PdfPng);
}
