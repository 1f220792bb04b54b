//! grainpipe-mcm: the mechanical contraction method (MCM, Williams and Philipse 2003;
//! Schneider et al. 2018) and the stacked MCM of Donval et al. (2025), section 2.2,
//! Algorithm 2. See docs/stages/mcm.md.

pub mod engine;
pub mod fabric;
pub mod pack;
pub mod stages;

/// Adds `mcm.classic` and `mcm.stacked`.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(stages::Classic);
    r.add_stage(stages::Stacked);
}
