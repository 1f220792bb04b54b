//! grainpipe-clumps: realistic sand grains and their approximation by clusters of
//! overlapping spheres (Donval et al. 2025, "A directional contraction method to model
//! sand-based binder jet 3D printed materials", section 2.1).
//!
//! Stages:
//! - `grains.from_labels`, `grains.from_meshes`, `grains.from_harmonics`, `grains.synthetic`:
//!   grain masks as a Collection of PhaseImage items plus size/shape statistics;
//! - `clumps.garcia`: Algorithm 1 with the paper's three accelerations;
//! - `clumps.library`: Sobol subsampling by bounding-sphere diameter, rescaling, export.
//!
//! See docs/stages/clumps.md.

pub mod clumps;
pub mod edt;
pub mod garcia;
pub mod grains;
pub mod mesh;
pub mod shape;

/// Adds the six stages and the `clump_json` exporter.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_stage(grains::FromLabels);
    r.add_stage(grains::FromMeshes);
    r.add_stage(grains::FromHarmonics);
    r.add_stage(grains::Synthetic);
    r.add_stage(clumps::Garcia);
    r.add_stage(clumps::Library);
    r.add_exporter(clumps::ClumpJsonExporter);
}
