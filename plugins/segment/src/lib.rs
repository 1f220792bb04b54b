//! grainpipe-segment: from a grey-value scan (a scalar `Field`) to a clean `PhaseImage`.
//!
//! Stages:
//! - `segment.threshold` ([`threshold`]): manual thresholds, Otsu (1979) or multi-Otsu
//!   (Liao et al. 2001) on a histogram of the field.
//! - `segment.crop` ([`crop`]): a subvolume of a phase image or a field.
//! - `segment.downsample` ([`downsample`]): block mode (labels) or block mean (fields).
//! - `segment.filter` ([`filter`]): median or Gaussian smoothing of a field.
//! - `segment.clean` ([`clean`]): speck removal, hole filling and relabelling of a phase
//!   image.
//!
//! Kernels free of framework types (plain slices and dims, x fastest):
//! [`otsu`], [`smooth`], [`resample`], [`morph`].

pub mod clean;
pub mod common;
pub mod crop;
pub mod downsample;
pub mod filter;
pub mod morph;
pub mod otsu;
pub mod resample;
pub mod smooth;
pub mod threshold;

/// Adds this crate's stages.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(threshold::Threshold);
    r.add_stage(crop::Crop);
    r.add_stage(downsample::Downsample);
    r.add_stage(filter::Filter);
    r.add_stage(clean::Clean);
}
