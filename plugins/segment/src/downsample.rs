//! `segment.downsample`: coarser voxels by an integer factor; block mode of labels, block
//! mean of field values (kernels in [`crate::resample`]).

use crate::common::{
    connected_input, field_values, image_or_field_output, image_or_field_ports,
    image_or_field_preflight, same_precision, FIELD_BYTES,
};
use crate::resample::{downsample_mean, downsample_mode};
use grainpipe_core::{
    params, ArtifactKind, Grid, InputMetas, Inputs, Outputs, Preflight, RunContext, StageError,
    StageInfo, TypedStage,
};

#[params]
pub struct DownsampleParams {
    /// voxels per output voxel along each axis (a block of factor^3 voxels becomes one);
    /// must divide every dimension of more than one voxel
    #[param(default = 2)]
    pub factor: usize,
}

/// The factor per axis (1 on axes of one voxel) and the output grid, checked.
pub fn downsample_grid(factor: usize, g: &Grid) -> Result<([usize; 3], Grid), StageError> {
    if factor == 0 {
        return Err(StageError::param(
            "factor",
            "0: give a positive integer (1 copies the input)",
        ));
    }
    let f = g.dims.map(|n| if n > 1 { factor } else { 1 });
    if let Some(a) = (0..3).find(|&a| g.dims[a] % f[a] != 0) {
        let fits: Vec<usize> = (2..=16)
            .filter(|&k| g.dims.iter().all(|&n| n == 1 || n % k == 0))
            .collect();
        return Err(StageError::param(
            "factor",
            format!(
                "{factor} does not divide the {} voxels along {} (dims {:?}); no remainder is \
                 dropped silently: crop to {} voxels first with `segment.crop`{}",
                g.dims[a],
                ["x", "y", "z"][a],
                g.dims,
                g.dims[a] / factor * factor,
                if fits.is_empty() {
                    String::new()
                } else {
                    format!(", or use a factor of {fits:?}")
                }
            ),
        ));
    }
    let grid = Grid {
        dims: [0, 1, 2].map(|a| g.dims[a] / f[a]),
        spacing: [0, 1, 2].map(|a| g.spacing[a] * f[a] as f64),
        origin: g.origin,
        periodic: g.periodic,
    };
    Ok((f, grid))
}

pub struct Downsample;

impl TypedStage for Downsample {
    type Params = DownsampleParams;
    type Plan = ([usize; 3], Grid);

    fn info(&self) -> StageInfo {
        let (inputs, outputs) = image_or_field_ports();
        StageInfo::new(
            "segment.downsample",
            "1.0.0",
            "Coarsens a phase image (`image`) or a field (`field`) by an integer factor. Each \
             block of factor x factor x factor voxels becomes one voxel of factor times the \
             spacing, with the same lower corner and periodic axes. A phase image takes the \
             block's most frequent label (ties to the smallest label); a field the mean of \
             each component over the block. The factor must divide every dimension (axes of \
             one voxel are left alone); otherwise the step is refused with the crop that \
             would fit. Connect one input; the output of the same name is produced.",
        )
        .inputs(inputs)
        .outputs(outputs)
    }

    fn preflight(
        &self,
        p: &DownsampleParams,
        i: &InputMetas,
    ) -> Result<Preflight<([usize; 3], Grid)>, StageError> {
        let (port, kind, g) = connected_input(i)?;
        let (f, grid) = downsample_grid(p.factor, &g)?;
        // Fields are read as f64 (a copy of the input) before the block means.
        let bytes = if kind == ArtifactKind::Field {
            FIELD_BYTES * (g.voxel_count() + grid.voxel_count()) as u64
        } else {
            grid.voxel_count() as u64
        };
        Ok(image_or_field_preflight(&self.info(), bytes, port, kind, &grid).with_plan((f, grid)))
    }

    fn run(
        &self,
        _: &DownsampleParams,
        (f, grid): &([usize; 3], Grid),
        inputs: &Inputs,
        _: &RunContext,
    ) -> Result<Outputs, StageError> {
        image_or_field_output(
            inputs,
            grid,
            |im| downsample_mode(&im.labels, im.grid.dims, *f),
            |fd| {
                let mean =
                    downsample_mean(&field_values(&fd.data), fd.grid.dims, fd.components, *f);
                same_precision(&fd.data, mean)
            },
        )
    }
}
