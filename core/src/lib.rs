//! grainpipe-core: the volume data model, the stage contract, the registry and the YAML
//! pipeline engine. The core knows no plugin; plugins fill a [`Registry`].

pub mod boundary;
pub mod cache;
pub mod distributions;
pub mod engine;
pub mod fsutil;
pub mod model;
pub mod params;
pub mod phases;
pub mod pipeline;
pub mod plugin_host;
pub mod raster;
pub mod registry;
pub mod resolution;
pub mod spatial;
pub mod stage;
pub mod subvoxel;
pub mod suggest;
pub mod testing;
pub mod units;
pub mod values;

// Lets `#[params]`-generated code name this crate from inside it too.
extern crate self as grainpipe_core;

pub use grainpipe_derive::{params, ParamChoice};
pub use model::*;
pub use params::{ParamType, Params};
pub use registry::{Exporter, Registry};
pub use serde_json;
pub use stage::{
    announced_grid, input, InputMetas, Inputs, Outputs, ParamSpec, PortSpec, Preflight, Prepared,
    ResidualProgress, RunContext, Stage, StageError, StageInfo, TypedStage,
};

/// grainpipe's version, recorded in every output's provenance.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// Derives a 64-bit seed from a parent seed and a label (stable across platforms and
/// releases: BLAKE3 of the little-endian seed and the label bytes).
pub fn derive_seed(seed: u64, label: &[u8]) -> u64 {
    let mut h = blake3::Hasher::new();
    h.update(&seed.to_le_bytes());
    h.update(label);
    let out = h.finalize();
    u64::from_le_bytes(out.as_bytes()[..8].try_into().expect("8 bytes"))
}
