//! grainpipe-fft: FFT homogenization of periodic voxel images (Donval et al. 2025,
//! sections 3.2 and 3.4): `elasticity.fft` (apparent stiffness, eq. 3.2-3.5) and
//! `conductivity.fft` (apparent thermal conductivity, the scalar analogue).
//!
//! The numerical kernels (`kernel`, `fft3`) know nothing of the framework; the stage files
//! map parameters and artifacts onto them.

// The kernels index small fixed arrays by Voigt component, axis and node exactly as the
// equations do; iterator rewrites would hide that correspondence.
#![allow(clippy::needless_range_loop)]

pub mod common;
pub mod conductivity;
pub mod elasticity;
pub mod fft3;
pub mod kernel;
pub mod real;

/// Adds this crate's stages.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(elasticity::ElasticityFft);
    r.add_stage(conductivity::ConductivityFft);
}
