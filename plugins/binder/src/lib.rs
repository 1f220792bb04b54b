//! grainpipe-binder: level-set and closing binders.

/// Adds this crate's stages.
pub fn register(_r: &mut grainpipe_core::Registry) {}
