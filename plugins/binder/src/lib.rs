//! grainpipe-binder: three-phase images from packings: pore (0), grain (1,
//! the sand) and binder (2). The level-set
//! binder of Donval et al. (2025), section 2.3, and the morphological closing it replaces
//! (Schneider et al. 2018) as the baseline. See docs/stages/binder.md.

pub mod closing;
mod common;
pub mod components;
pub mod edt;
pub mod levelset;
pub mod smooth_union;

/// Adds `binder.levelset` and `binder.closing`.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(levelset::LevelSet);
    r.add_stage(closing::Closing);
}
