//! grainpipe-sintering: laser heating of particle beds with bond formation, after section 5
//! of the sphere-filling Method 1/2 paper, and a top-view PNG exporter for bond graphs.

pub mod params;
pub mod path;
pub mod png;
pub mod stage;
pub mod thermal;

pub use params::LaserParams;
pub use png::BondGraphPng;
pub use stage::{simulate, validity_warning, LaserSintering, RunResult};

pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(LaserSintering);
    r.add_exporter(BondGraphPng);
}
