//! grainpipe-fft: FFT homogenization.

/// Adds this crate's stages.
pub fn register(_r: &mut grainpipe_core::Registry) {}
