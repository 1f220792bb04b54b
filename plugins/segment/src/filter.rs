//! `segment.filter`: median or Gaussian smoothing of a scalar field (kernels in
//! [`crate::smooth`]).

use crate::common::{field_like, same_precision, scalar_values, VoxelsOr};
use crate::smooth::{gaussian, gaussian_radius, median, Window};
use grainpipe_core::units::Length;
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, InputMetas, Inputs, Outputs, ParamChoice,
    PortSpec, Preflight, RunContext, StageError, StageInfo, TypedStage,
};

/// The smoothing filter.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum FilterMethod {
    /// Median over a window of `radius` voxels (edge-preserving, removes salt-and-pepper
    /// noise).
    Median,
    /// Separable Gaussian of standard deviation `sigma`, truncated at `truncate` sigma.
    Gaussian,
}

/// The shape of the median window.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum WindowShape {
    /// Every voxel within `radius` along each axis: (2 radius + 1)^3 voxels.
    Cube,
    /// Voxels whose centre lies within `radius` voxels of the centre voxel's (a digital
    /// ball).
    Ball,
}

#[params]
pub struct FilterParams {
    /// `median` or `gaussian`
    #[param(default = FilterMethod::Median)]
    pub method: FilterMethod,
    /// `median`: half-width of the window in voxels (1 gives 3 x 3 x 3)
    #[param(default = 1)]
    pub radius: usize,
    /// `median`: `cube` or `ball` window
    #[param(default = WindowShape::Cube)]
    pub window: WindowShape,
    /// `gaussian`: standard deviation, in voxels (a plain number, the same on every axis) or
    /// as a length (`"3 um"`, divided by each axis's spacing)
    #[param(default = VoxelsOr::Voxels(1.0))]
    pub sigma: VoxelsOr<Length>,
    /// `gaussian`: the kernel is cut at ceil(truncate x sigma) voxels either side of the
    /// centre and renormalised to sum 1
    #[param(default = 4.0)]
    pub truncate: f64,
}

/// Median windows up to this radius (a cube of 25^3 voxels per output voxel).
const MAX_MEDIAN_RADIUS: usize = 12;

pub struct Filter;

impl TypedStage for Filter {
    type Params = FilterParams;
    type Plan = ();

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "segment.filter",
            "1.0.0",
            "Smooths a scalar grey-value field before thresholding, by a median or a \
             Gaussian filter. Median: the median of the cubic or ball-shaped window of `radius` voxels around each voxel (the window \
             holds an odd number of voxels, so the median is one of the values). Gaussian: \
             a separable Gaussian (one 1-D pass along x, y, then z) of standard deviation \
             `sigma` in voxels or as a length, truncated at ceil(truncate x sigma) voxels and \
             renormalised. Boundaries: a periodic axis wraps; a non-periodic axis is \
             mirrored about the image face with the edge voxel repeated (... c b a | a b c \
             ...). Computed in double precision; the output keeps the input's name, unit \
             and precision.",
        )
        .inputs(vec![PortSpec::new(
            "field",
            ArtifactKind::Field,
            "scalar grey values (one component)",
        )])
        .outputs(vec![PortSpec::new(
            "field",
            ArtifactKind::Field,
            "the smoothed values on the same grid",
        )])
    }

    fn preflight(&self, p: &FilterParams, i: &InputMetas) -> Result<Preflight, StageError> {
        match p.method {
            FilterMethod::Median => {
                if p.radius == 0 || p.radius > MAX_MEDIAN_RADIUS {
                    return Err(StageError::param(
                        "radius",
                        format!(
                            "{}: give 1 to {MAX_MEDIAN_RADIUS} voxels (1 is a 3 x 3 x 3 window); \
                             for wider smoothing downsample first or use `method: gaussian`",
                            p.radius
                        ),
                    ));
                }
            }
            FilterMethod::Gaussian => {
                if !p.sigma.is_finite_non_negative() || p.sigma.in_voxels(1.0) == 0.0 {
                    return Err(StageError::param(
                        "sigma",
                        "give a positive standard deviation, e.g. `sigma: 1.5` (voxels) or \
                         `sigma: \"3 um\"`",
                    ));
                }
                if !(p.truncate.is_finite() && p.truncate > 0.0) {
                    return Err(StageError::param(
                        "truncate",
                        format!(
                            "{}: give a positive number of sigmas (4 is usual)",
                            p.truncate
                        ),
                    ));
                }
            }
        }
        let grid = i.get("field").and_then(|m| m.grid.clone());
        if let (FilterMethod::Gaussian, Some(g)) = (p.method, &grid) {
            let s = sigmas(&p.sigma, &g.spacing);
            if let Some(a) =
                (0..3).find(|&a| gaussian_radius(s[a], p.truncate) > 4 * g.dims[a].max(16))
            {
                return Err(StageError::param(
                    "sigma",
                    format!(
                        "{:.3} voxels along {} reach {} voxels either side, far beyond the \
                         {} voxels of the image; was the unit meant to be smaller?",
                        s[a],
                        ["x", "y", "z"][a],
                        gaussian_radius(s[a], p.truncate),
                        g.dims[a]
                    ),
                ));
            }
        }
        let voxels = i
            .get("field")
            .map(|m| {
                grid.as_ref()
                    .map_or(m.count_estimate, |g| g.voxel_count() as u64)
            })
            .unwrap_or(0);
        // Input copy, one pass buffer and the output, in f64.
        let meta = match grid {
            Some(g) => ArtifactMeta::on_grid(ArtifactKind::Field, g),
            None => ArtifactMeta::of(ArtifactKind::Field),
        };
        Ok(Preflight::from_info(&self.info(), 24 * voxels).announce("field", meta))
    }

    fn run(
        &self,
        p: &FilterParams,
        _: &(),
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let f = input(inputs, "field", Artifact::as_field)?;
        let values = scalar_values(f, "field")?;
        let g = &f.grid;
        ctx.progress(0, 1)?;
        let smoothed = match p.method {
            FilterMethod::Median => {
                let w = match p.window {
                    WindowShape::Cube => Window::Cube,
                    WindowShape::Ball => Window::Ball,
                };
                median(&values, g.dims, g.periodic, p.radius, w)
            }
            FilterMethod::Gaussian => gaussian(
                &values,
                g.dims,
                g.periodic,
                sigmas(&p.sigma, &g.spacing),
                p.truncate,
            ),
        };
        ctx.progress(1, 1)?;
        let data = same_precision(&f.data, smoothed);
        let mut out = Outputs::new();
        out.insert(
            "field".into(),
            Artifact::Field(field_like(f, g.clone(), data)?),
        );
        Ok(out)
    }
}

/// Sigma in voxels along each axis.
pub fn sigmas(sigma: &VoxelsOr<Length>, spacing: &[f64; 3]) -> [f64; 3] {
    spacing.map(|s| sigma.in_voxels(s))
}
