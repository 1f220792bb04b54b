//! `analysis.tortuosity`: geometric tortuosity of one phase along the axes. The kernel is
//! [`geodesic`] (plain slices).
//!
//! The geodesic distance from the inlet face (the first layer of voxels normal to the axis)
//! through the phase is found by Dijkstra's algorithm on the 26-connected voxel graph, each
//! step weighted by its physical length (h, h sqrt 2, h sqrt 3 for cubic voxels): the
//! shortest path through the phase among those that move between voxels sharing a face, an
//! edge or a corner. The tortuosity of an outlet voxel (last layer) is its geodesic distance
//! over the straight distance between the layers' centres, (n - 1) h; the stage averages it
//! over the outlet voxels reached. Lateral periodic axes wrap; along the axis measured the
//! image is cut at its faces (a periodic axis is treated as inlet and outlet faces). On the
//! lattice a straight path along an axis, a face or a space diagonal is exact; a path in
//! another direction is measured as a staircase of such steps, at most 8 % long (the
//! 26-neighbour metric's largest error, at about 22 degrees off an axis in a plane).

use crate::pores::{
    announced_voxels, check_axes, coords, neighbour, neighbour_steps, table_rows, Axis,
    PhaseSelection,
};
use grainpipe_core::{
    params, Artifact, ArtifactKind, InputMetas, Inputs, Outputs, PortSpec, Preflight, RunContext,
    StageError, StageInfo, Table, TypedStage,
};
use rayon::prelude::*;
use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// Geodesic distance [m] through the phase from the layer `axis = 0` to every voxel
/// (infinite where unreachable or outside the phase); 26-connected, steps of their physical
/// length; `periodic` lateral axes wrap, the axis itself never does.
pub fn geodesic(
    mask: &[bool],
    dims: [usize; 3],
    spacing: [f64; 3],
    periodic: [bool; 3],
    axis: usize,
) -> Vec<f64> {
    let n = dims.iter().product::<usize>();
    assert_eq!(mask.len(), n);
    let mut dist = vec![f64::INFINITY; n];
    let mut heap = BinaryHeap::new();
    for (i, d) in dist.iter_mut().enumerate() {
        if mask[i] && coords(dims, i)[axis] == 0 {
            *d = 0.0;
            heap.push(Entry(0.0, i));
        }
    }
    let steps = neighbour_steps(spacing);
    let wrap = lateral_wrap(dims, periodic, axis);
    while let Some(Entry(d, i)) = heap.pop() {
        if d > dist[i] {
            continue;
        }
        let c = coords(dims, i);
        for &(o, len) in &steps {
            let Some(j) = neighbour(dims, wrap, c, o) else {
                continue;
            };
            if mask[j] && d + len < dist[j] {
                dist[j] = d + len;
                heap.push(Entry(d + len, j));
            }
        }
    }
    dist
}

/// The axes that wrap for paths along `axis`: the periodic lateral ones of more than two
/// voxels (the axis itself never does).
fn lateral_wrap(dims: [usize; 3], periodic: [bool; 3], axis: usize) -> [bool; 3] {
    [0, 1, 2].map(|a| a != axis && periodic[a] && dims[a] > 2)
}

/// Heap entry ordered by distance, smallest first (then by index, for a fixed order).
#[derive(PartialEq)]
struct Entry(f64, usize);
impl Eq for Entry {}
impl Ord for Entry {
    fn cmp(&self, o: &Self) -> Ordering {
        o.0.total_cmp(&self.0).then(o.1.cmp(&self.1))
    }
}
impl PartialOrd for Entry {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}

/// Tortuosity along one axis.
#[derive(Clone, Debug, PartialEq)]
pub struct AxisTortuosity {
    /// Mean over the outlet voxels reached of geodesic / straight length (NaN if none).
    pub mean: f64,
    /// Smallest over the outlet voxels reached.
    pub min: f64,
    /// Straight distance between the inlet and outlet layers' centres [m].
    pub straight: f64,
    /// Outlet voxels of the phase reached from the inlet / outlet voxels of the phase.
    pub outlet_reached: f64,
    /// Phase voxels on a path from inlet to outlet / phase voxels.
    pub connected: f64,
}

/// Geometric tortuosity of the phase along `axis` (see the module documentation).
pub fn tortuosity(
    mask: &[bool],
    dims: [usize; 3],
    spacing: [f64; 3],
    periodic: [bool; 3],
    axis: usize,
) -> AxisTortuosity {
    let straight = (dims[axis] as f64 - 1.0) * spacing[axis];
    let dist = geodesic(mask, dims, spacing, periodic, axis);
    let last = dims[axis] - 1;
    let (mut sum, mut min, mut reached, mut outlet) = (0.0, f64::INFINITY, 0u64, 0u64);
    for (i, &d) in dist.iter().enumerate() {
        if mask[i] && coords(dims, i)[axis] == last {
            outlet += 1;
            if d.is_finite() {
                reached += 1;
                sum += d / straight;
                min = min.min(d / straight);
            }
        }
    }
    // Voxels on an inlet-outlet path: reached from the inlet, and in a component (of the
    // reached voxels, 26-connected) holding a reached outlet voxel; flood from those.
    let mut on_path = vec![false; mask.len()];
    let mut stack: Vec<usize> = (0..mask.len())
        .filter(|&i| dist[i].is_finite() && coords(dims, i)[axis] == last)
        .collect();
    for &i in &stack {
        on_path[i] = true;
    }
    let wrap = lateral_wrap(dims, periodic, axis);
    let steps = neighbour_steps(spacing);
    while let Some(i) = stack.pop() {
        let c = coords(dims, i);
        for &(o, _) in &steps {
            let Some(j) = neighbour(dims, wrap, c, o) else {
                continue;
            };
            if dist[j].is_finite() && !on_path[j] {
                on_path[j] = true;
                stack.push(j);
            }
        }
    }
    let phase = mask.iter().filter(|&&m| m).count() as f64;
    let connected = on_path.iter().filter(|&&m| m).count() as f64;
    let frac = |a: f64, b: f64| if b == 0.0 { f64::NAN } else { a / b };
    AxisTortuosity {
        mean: frac(sum, reached as f64),
        min: if reached > 0 { min } else { f64::NAN },
        straight,
        outlet_reached: frac(reached as f64, outlet as f64),
        connected: frac(connected, phase),
    }
}

#[params]
pub struct TortuosityParams {
    #[param(flatten)]
    pub selection: PhaseSelection,
    /// axes along which the tortuosity is measured (inlet at the lower face, outlet at the
    /// upper one)
    #[param(default = Axis::ALL.to_vec())]
    pub axes: Vec<Axis>,
}

pub struct Tortuosity;

impl TypedStage for Tortuosity {
    type Params = TortuosityParams;
    type Plan = ();

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "analysis.tortuosity",
            "1.0.0",
            "Geometric tortuosity of a phase along x, y and z: the geodesic distance through \
             the phase from the inlet layer (lowest voxels along the axis) to each outlet \
             voxel (highest layer), by Dijkstra's algorithm on the 26-connected voxel graph \
             with steps of their physical length, over the straight distance (n - 1) h \
             between the layers, averaged over the outlet voxels reached. Lateral periodic \
             axes wrap; the axis measured is cut at its faces. Also the fraction of the \
             outlet reached and of the phase on an inlet-outlet path. For the formation and \
             tortuosity factors run conductivity.fft on the pore phase (see \
             docs/stages/analysis.md). Memory: about 20 bytes per voxel per axis (the axes \
             run in parallel).",
        )
        .inputs(vec![PortSpec::new(
            "image",
            ArtifactKind::PhaseImage,
            "any labelled image",
        )])
        .outputs(vec![PortSpec::new(
            "tortuosity",
            ArtifactKind::Table,
            "one row per axis: mean and smallest geometric tortuosity, straight length (m), \
             outlet fraction reached, fraction of the phase connecting inlet and outlet",
        )])
    }

    fn preflight(&self, p: &TortuosityParams, i: &InputMetas) -> Result<Preflight, StageError> {
        p.selection.check()?;
        check_axes("axes", &p.axes)?;
        if let Some(g) = i.get("image").and_then(|m| m.grid.as_ref()) {
            for a in &p.axes {
                if g.dims[a.index()] < 2 {
                    return Err(StageError::param(
                        "axes",
                        format!(
                            "the image is one voxel thick along {}: leave `{}` out of `axes`",
                            a.name(),
                            a.name()
                        ),
                    ));
                }
            }
        }
        // Per axis: distances 8, path flags 1, the heap and the flood stack (16 bytes per
        // entry, a small share of the voxels at a time in practice: 11 bytes per voxel per
        // axis were measured in all); the mask 1.
        let voxels = announced_voxels(i);
        let rows = p.axes.len() as u64;
        Ok(
            Preflight::from_info(&self.info(), voxels + 20 * rows * voxels)
                .announce("tortuosity", table_rows(rows)),
        )
    }

    fn run(
        &self,
        p: &TortuosityParams,
        _: &(),
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let (image, mask) = p.selection.image_and_mask(inputs)?;
        let g = &image.grid;
        ctx.progress(0, 1)?;
        let rows: Vec<AxisTortuosity> = p
            .axes
            .par_iter()
            .map(|a| tortuosity(&mask, g.dims, g.spacing, g.periodic, a.index()))
            .collect();
        ctx.progress(1, 1)?;
        let table = Table::new("tortuosity")
            .with_str(
                "axis",
                p.axes.iter().map(|a| a.name().to_string()).collect(),
            )
            .with_f64("tortuosity", "1", rows.iter().map(|r| r.mean).collect())
            .with_f64("tortuosity_min", "1", rows.iter().map(|r| r.min).collect())
            .with_f64(
                "straight_length",
                "m",
                rows.iter().map(|r| r.straight).collect(),
            )
            .with_f64(
                "outlet_fraction",
                "1",
                rows.iter().map(|r| r.outlet_reached).collect(),
            )
            .with_f64(
                "connected_fraction",
                "1",
                rows.iter().map(|r| r.connected).collect(),
            );
        let mut out = Outputs::new();
        out.insert("tortuosity".into(), Artifact::Table(table));
        Ok(out)
    }
}
