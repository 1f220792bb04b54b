//! `analysis.phases`: per-phase volume fraction, specific surface, connected components and
//! percolation of a phase image, as a table (one row per label). The kernels are in
//! [`crate::components`] and [`crate::surface`].

use crate::components::label_components;
use crate::surface::{face_surface, specific_surface, transitions};
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, InputMetas, Inputs, Outputs, PhaseImage,
    PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
};
use rayon::prelude::*;

#[params]
pub struct PhasesParams {
    /// labels to analyse, one row each in this order (default: every label present in the
    /// image or named in its phase table, ascending)
    pub labels: Vec<u8>,
}

pub struct Phases;

impl TypedStage for Phases {
    type Params = PhasesParams;
    type Plan = ();

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "analysis.phases",
            "1.0.0",
            "Per phase of a phase image: volume fraction (voxel count), specific surface \
             (interface area per image volume, 1/m) by the Cauchy-Crofton formula over 13 \
             lattice directions (Legland et al. 2007 weights) and as the counted voxel-face \
             area (the staircase area, 1.5 times a smooth isotropic surface), connected \
             components by faces (6-connectivity; periodic axes wrap), the largest \
             component's share of the phase, and percolation along x, y, z: on a \
             non-periodic axis one component touches both faces, on a periodic axis one \
             component connects to its own periodic image (winding), so a component that \
             merely crosses the periodic face does not count.",
        )
        .inputs(vec![PortSpec::new(
            "image",
            ArtifactKind::PhaseImage,
            "any labelled image",
        )])
        .outputs(vec![PortSpec::new(
            "phases",
            ArtifactKind::Table,
            "one row per label: fractions, surfaces, components, percolation",
        )])
    }

    fn preflight(&self, p: &PhasesParams, i: &InputMetas) -> Result<Preflight, StageError> {
        for (k, l) in p.labels.iter().enumerate() {
            if p.labels[..k].contains(l) {
                return Err(StageError::param(
                    "labels",
                    format!("label {l} is listed twice"),
                ));
            }
        }
        // The component ids (4 bytes per voxel) dominate; the per-label tables of the
        // labeling (provisional labels, union-find, voxel counts: ~100 B per slab-local
        // component) are counted at 1 byte per voxel; the image is the input's.
        let voxels = i
            .get("image")
            .map(|m| {
                m.grid
                    .as_ref()
                    .map_or(m.count_estimate, |g| g.voxel_count() as u64)
            })
            .unwrap_or(0);
        let mut table = ArtifactMeta::of(ArtifactKind::Table);
        if !p.labels.is_empty() {
            let n = p.labels.len() as u64;
            table = table.with_count(n, Some([n, n]));
        }
        Ok(Preflight::from_info(&self.info(), 5 * voxels + (64 << 10)).announce("phases", table))
    }

    fn run(
        &self,
        p: &PhasesParams,
        _: &(),
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let image = input(inputs, "image", Artifact::as_phase_image)?;
        let table = analyse(image, &p.labels, ctx)?;
        let mut out = Outputs::new();
        out.insert("phases".into(), Artifact::Table(table));
        Ok(out)
    }
}

/// The table of `analysis.phases` for `image` (rows: `labels`, or every label present or
/// named).
pub fn analyse(image: &PhaseImage, labels: &[u8], ctx: &RunContext) -> Result<Table, StageError> {
    let g = &image.grid;
    let n = g.voxel_count();
    if image.labels.len() != n || n == 0 {
        return Err(StageError::input(
            "image",
            format!(
                "{} labels for a grid of {:?} voxels",
                image.labels.len(),
                g.dims
            ),
        ));
    }
    let histogram = image
        .labels
        .par_chunks(1 << 16)
        .fold(
            || [0u64; 256],
            |mut h, c| {
                for &l in c {
                    h[l as usize] += 1;
                }
                h
            },
        )
        .reduce(
            || [0u64; 256],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x += y;
                }
                a
            },
        );
    let rows: Vec<u8> = if labels.is_empty() {
        (0..=255u8)
            .filter(|&l| histogram[l as usize] > 0 || image.phases.iter().any(|ph| ph.id == l))
            .collect()
    } else {
        labels.to_vec()
    };
    let t = transitions(&image.labels, g.dims, g.periodic);
    let mut cols = Columns::default();
    for (k, &l) in rows.iter().enumerate() {
        let voxels = histogram[l as usize];
        let name = image
            .phases
            .iter()
            .find(|ph| ph.id == l)
            .map(|ph| ph.name.clone())
            .unwrap_or_else(|| format!("phase{l}"));
        let lab = label_components(g.dims, g.periodic, |i| image.labels[i] == l);
        let share = |v: u64| {
            if voxels == 0 {
                0.0
            } else {
                v as f64 / voxels as f64
            }
        };
        cols.label.push(l as i64);
        cols.phase.push(name);
        cols.voxels.push(voxels as i64);
        cols.fraction.push(voxels as f64 / n as f64);
        cols.surface.push(specific_surface(&t, l, g.spacing));
        cols.faces.push(face_surface(&t, l, g.spacing));
        cols.components.push(lab.components.len() as i64);
        cols.largest.push(share(lab.largest()));
        // A one-voxel axis is spanned by every component: it says nothing about connectivity.
        let along = g.dims.map(|n| n > 1);
        cols.percolating.push(share(lab.percolating_voxels(along)));
        let perc = lab.percolates();
        for (col, p) in cols.percolates.iter_mut().zip(perc) {
            col.push(p as i64);
        }
        ctx.progress(k as u64 + 1, rows.len() as u64)?;
    }
    Ok(cols.table())
}

#[derive(Default)]
struct Columns {
    label: Vec<i64>,
    phase: Vec<String>,
    voxels: Vec<i64>,
    fraction: Vec<f64>,
    surface: Vec<f64>,
    faces: Vec<f64>,
    components: Vec<i64>,
    largest: Vec<f64>,
    percolating: Vec<f64>,
    percolates: [Vec<i64>; 3],
}

impl Columns {
    fn table(self) -> Table {
        let [px, py, pz] = self.percolates;
        Table::new("phases")
            .with_i64("label", "", self.label)
            .with_str("phase", self.phase)
            .with_i64("voxels", "", self.voxels)
            .with_f64("volume_fraction", "1", self.fraction)
            .with_f64("specific_surface", "1/m", self.surface)
            .with_f64("specific_surface_faces", "1/m", self.faces)
            .with_i64("components", "", self.components)
            .with_f64("largest_component_fraction", "1", self.largest)
            .with_f64("percolating_fraction", "1", self.percolating)
            .with_i64("percolates_x", "", px)
            .with_i64("percolates_y", "", py)
            .with_i64("percolates_z", "", pz)
    }
}
