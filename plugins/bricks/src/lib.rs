//! grainpipe-bricks: sphere filling of bricks and signed-distance domains after the Matlab
//! Method 1 / Method 2 procedures of the sphere-filling paper
//! (`../shared/papers/sphere-filling-method1-method2-laser-sintering.md`), fast.
//!
//! Stages: `bricks.method1`, `bricks.method2`, `bricks.curved`.

pub mod assemble;
pub mod fill;
pub mod sdf;
pub mod stages;

pub use stages::{
    BrickParams, Curved, CurvedParams, Method1, Method1Params, Method2, Method2Params, UnitBrick,
};

/// Registers the brick stages.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(Method1);
    r.add_stage(Method2);
    r.add_stage(Curved);
}
