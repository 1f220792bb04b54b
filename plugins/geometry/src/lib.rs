//! Basic geometry stages: `packing.rsa` (random sequential addition of spheres) and
//! `voxelize.packing` (spheres and clumps to a phase image).

pub mod rsa;
pub mod voxelize;

use grainpipe_core::Registry;

pub fn register(r: &mut Registry) {
    r.add_stage(rsa::Rsa);
    r.add_stage(voxelize::Voxelize);
}
