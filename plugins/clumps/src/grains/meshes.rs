//! `grains.from_meshes`: one grain per closed triangle surface.

use super::{
    check_nonempty, check_voxel, de_resolved_list, grain_output_ports, grain_outputs,
    preflight_grains, resolve_path, GrainMask,
};
use crate::mesh::Mesh;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::*;
use std::path::PathBuf;

#[params]
pub struct MeshesParams {
    /// .stl / .obj files, one closed surface per grain (relative to the working directory)
    #[param(file, ty = "[paths]")]
    #[serde(deserialize_with = "de_resolved_list")]
    pub files: Vec<String>,
    /// voxel edge of the masks
    #[param(default = Q::new(4e-6))]
    pub voxel_size: Q<Length>,
    /// length of one mesh coordinate unit (STL/OBJ carry none)
    #[param(default = Q::new(1e-3))]
    pub mesh_unit: Q<Length>,
}

pub struct FromMeshes;

impl TypedStage for FromMeshes {
    type Params = MeshesParams;
    /// The mesh files, found once in preflight.
    type Plan = Vec<PathBuf>;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "grains.from_meshes",
            "1.1.0",
            "Grains from closed triangle surfaces (STL ASCII or binary, OBJ), one grain \
             per file, voxelized by ray parity (a voxel is inside when a ray from its \
             centre crosses the surface an odd number of times).",
        )
        .outputs(grain_output_ports())
    }
    fn preflight(
        &self,
        p: &Self::Params,
        _: &InputMetas,
    ) -> Result<Preflight<Vec<PathBuf>>, StageError> {
        check_voxel("voxel_size", p.voxel_size.si())?;
        check_voxel("mesh_unit", p.mesh_unit.si())?;
        if p.files.is_empty() {
            return Err(StageError::param(
                "files",
                "list at least one .stl or .obj file",
            ));
        }
        let mut paths = Vec::with_capacity(p.files.len());
        for f in &p.files {
            let path = resolve_path(f);
            if !path.is_file() {
                return Err(StageError::param(
                    "files",
                    format!("{}: not found", path.display()),
                ));
            }
            let ext = path
                .extension()
                .and_then(|e| e.to_str())
                .unwrap_or("")
                .to_ascii_lowercase();
            if ext != "stl" && ext != "obj" {
                return Err(StageError::param(
                    "files",
                    format!("{f}: expected .stl or .obj"),
                ));
            }
            paths.push(path);
        }
        // Memory from the meshes themselves (read here for their boxes): per grain its
        // mask and its labels (2 B per voxel of its box, kept: the grains are kept); for the
        // grain being voxelized its ray crossings (a 24 B vector and ~2 crossings of 8 B per
        // y-z row of its box) and its mesh (vertices and triangles, 48 B per vertex and
        // triangle, and the edge map of the closedness check, ~64 B per edge, 1.5 per
        // triangle).
        let h = p.voxel_size.si();
        let mut voxels = 0.0;
        let mut in_flight: f64 = 0.0;
        for path in &paths {
            let m = Mesh::read(path).map_err(|e| StageError::param("files", e))?;
            let s = p.mesh_unit.si();
            let mut lo = [f64::INFINITY; 3];
            let mut hi = [f64::NEG_INFINITY; 3];
            for v in &m.vertices {
                for a in 0..3 {
                    lo[a] = lo[a].min(v[a] * s);
                    hi[a] = hi[a].max(v[a] * s);
                }
            }
            let dims = [0, 1, 2].map(|a| ((hi[a] - lo[a]) / h).max(0.0) + 3.0);
            voxels += dims[0] * dims[1] * dims[2];
            let rows = dims[1] * dims[2];
            let mesh = 24.0 * (m.vertices.len() + m.triangles.len()) as f64
                + 96.0 * m.triangles.len() as f64;
            in_flight = in_flight.max(40.0 * rows + mesh);
        }
        let mut pf = preflight_grains(&self.info(), Some(p.files.len()), 0.0, None);
        pf.memory_bytes = (2.0 * voxels + in_flight) as u64 + (64 << 10);
        Ok(pf.with_plan(paths))
    }
    fn run(
        &self,
        p: &Self::Params,
        paths: &Vec<PathBuf>,
        _: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let mut grains = Vec::new();
        for (k, (f, path)) in p.files.iter().zip(paths).enumerate() {
            let mut m = Mesh::read(path).map_err(StageError::failed)?;
            let open = m.open_edges();
            if open > 0 {
                return Err(StageError::failed(format!(
                    "{f}: {open} edges are not shared by exactly two triangles: the surface is not closed"
                )));
            }
            m.scale(p.mesh_unit.si());
            let (dims, origin, mask) = m
                .voxelize(p.voxel_size.si())
                .map_err(|e| StageError::failed(format!("{f}: {e}")))?;
            let area = m.volume_area().1;
            grains.push(GrainMask {
                dims,
                voxel: p.voxel_size.si(),
                origin,
                mask,
                source: f.clone(),
                area: Some(area),
            });
            ctx.progress(k as u64 + 1, p.files.len() as u64)?;
        }
        check_nonempty(&grains)?;
        Ok(grain_outputs(grains))
    }
}
