//! `segment.crop`: a box of voxels out of a phase image or a field (kernel
//! [`crate::resample::crop`]).

use crate::common::{
    connected_input, image_or_field_output, image_or_field_ports, image_or_field_preflight,
    FIELD_BYTES,
};
use crate::resample::crop;
use grainpipe_core::{
    params, ArtifactKind, FieldData, Grid, InputMetas, Inputs, Outputs, Preflight, RunContext,
    StageError, StageInfo, TypedStage,
};

#[params]
pub struct CropParams {
    /// first voxel of the box along x, y, z (0-based voxel indices of the input)
    #[param(ty = "[x, y, z] voxel indices")]
    pub start: [usize; 3],
    /// voxels of the box along x, y, z; 0 on an axis takes everything from `start` to the
    /// end of that axis
    #[param(ty = "[x, y, z] voxel counts")]
    pub size: [usize; 3],
}

/// The grid of the box, checked against the input grid.
pub fn crop_grid(p: &CropParams, g: &Grid) -> Result<(Grid, [usize; 3]), StageError> {
    for (a, axis) in ["x", "y", "z"].into_iter().enumerate() {
        if p.start[a] >= g.dims[a] {
            return Err(StageError::param(
                "start",
                format!(
                    "start {} along {} is outside the input's {} voxels (0..={})",
                    p.start[a],
                    axis,
                    g.dims[a],
                    g.dims[a] - 1
                ),
            ));
        }
    }
    let size = [0, 1, 2].map(|a| {
        if p.size[a] == 0 {
            g.dims[a] - p.start[a]
        } else {
            p.size[a]
        }
    });
    for (a, axis) in ["x", "y", "z"].into_iter().enumerate() {
        if p.start[a] + size[a] > g.dims[a] {
            return Err(StageError::param(
                "size",
                format!(
                    "{} voxels from {} along {} run past the input's {} voxels: at most {} \
                     fit (or 0 for the rest of the axis)",
                    size[a],
                    p.start[a],
                    axis,
                    g.dims[a],
                    g.dims[a] - p.start[a]
                ),
            ));
        }
    }
    let grid = Grid {
        dims: size,
        spacing: g.spacing,
        origin: [0, 1, 2].map(|a| g.origin[a] + p.start[a] as f64 * g.spacing[a]),
        // An axis stays periodic only when it is kept whole.
        periodic: [0, 1, 2].map(|a| g.periodic[a] && size[a] == g.dims[a]),
    };
    Ok((grid, size))
}

pub struct Crop;

impl TypedStage for Crop {
    type Params = CropParams;
    type Plan = (Grid, [usize; 3]);

    fn info(&self) -> StageInfo {
        let (inputs, outputs) = image_or_field_ports();
        StageInfo::new(
            "segment.crop",
            "1.0.0",
            "Cuts a box of voxels out of a phase image or a field. The box is `start .. \
             start + size` (voxel indices of the input, x, y, z), of a phase image (`image`) \
             or a field (`field`, any components); the output has the same spacing and its lower corner at the box's corner (origin + \
             start x spacing), so it stays in place in physical space. An axis that is cut \
             is no longer periodic; an axis kept whole keeps its periodicity. Connect one \
             input; the output of the same name is produced.",
        )
        .inputs(inputs)
        .outputs(outputs)
    }

    fn preflight(
        &self,
        p: &CropParams,
        i: &InputMetas,
    ) -> Result<Preflight<(Grid, [usize; 3])>, StageError> {
        let (port, kind, g) = connected_input(i)?;
        let (grid, size) = crop_grid(p, &g)?;
        let per_voxel = if kind == ArtifactKind::Field {
            FIELD_BYTES
        } else {
            1
        };
        let bytes = per_voxel * grid.voxel_count() as u64;
        Ok(
            image_or_field_preflight(&self.info(), bytes, port, kind, &grid)
                .with_plan((grid, size)),
        )
    }

    fn run(
        &self,
        p: &CropParams,
        (grid, size): &(Grid, [usize; 3]),
        inputs: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        image_or_field_output(
            inputs,
            grid,
            |im| crop(&im.labels, im.grid.dims, 1, p.start, *size),
            |f| {
                let c = f.components;
                match &f.data {
                    FieldData::F32(v) => FieldData::F32(crop(v, f.grid.dims, c, p.start, *size)),
                    FieldData::F64(v) => FieldData::F64(crop(v, f.grid.dims, c, p.start, *size)),
                }
            },
        )
    }
}
