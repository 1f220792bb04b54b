//! `grains.from_labels`: one mask per grain id of a segmented scan.

use super::{grain_output_ports, grain_outputs, preflight_grains, GrainMask};
use grainpipe_core::*;

#[params]
pub struct LabelsParams {
    /// drop grains touching the z faces (paper), any face, or none
    #[param(ty = "one of: z, all, none", default = "z".into())]
    pub drop_touching: String,
    /// label of the pore space
    pub background: i64,
    /// drop grains with fewer voxels (segmentation debris)
    #[param(default = 8)]
    pub min_voxels: usize,
    /// keep only the largest 26-connected part of each label
    #[param(default = true)]
    pub largest_component: bool,
}

pub struct FromLabels;

/// Splits a label volume into one mask per label (bounding box plus one empty layer).
pub fn split_labels(
    labels: &[i64],
    grid: &Grid,
    p: &LabelsParams,
) -> Result<Vec<GrainMask>, String> {
    let [nx, ny, nz] = grid.dims;
    use std::collections::BTreeMap;
    // label -> (min, max, touches x, y, z faces)
    let mut boxes: BTreeMap<i64, ([usize; 3], [usize; 3])> = BTreeMap::new();
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let l = labels[x + nx * (y + ny * z)];
                if l == p.background {
                    continue;
                }
                let e = boxes.entry(l).or_insert(([x, y, z], [x, y, z]));
                for (a, v) in [x, y, z].into_iter().enumerate() {
                    e.0[a] = e.0[a].min(v);
                    e.1[a] = e.1[a].max(v);
                }
            }
        }
    }
    let mut out = Vec::new();
    for (l, (lo, hi)) in boxes {
        let touches = |a: usize| lo[a] == 0 || hi[a] == grid.dims[a] - 1;
        let drop = match p.drop_touching.as_str() {
            "z" => touches(2),
            "all" => touches(0) || touches(1) || touches(2),
            _ => false,
        };
        if drop {
            continue;
        }
        let dims = [0, 1, 2].map(|a| hi[a] - lo[a] + 3);
        let mut mask = vec![false; dims[0] * dims[1] * dims[2]];
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    if labels[x + nx * (y + ny * z)] == l {
                        mask[(x - lo[0] + 1)
                            + dims[0] * ((y - lo[1] + 1) + dims[1] * (z - lo[2] + 1))] = true;
                    }
                }
            }
        }
        if p.largest_component {
            keep_largest_component(&mut mask, dims);
        }
        if mask.iter().filter(|&&b| b).count() < p.min_voxels {
            continue;
        }
        let h = grid.spacing[0];
        out.push(GrainMask {
            dims,
            voxel: h,
            origin: [0, 1, 2].map(|a| grid.origin[a] + (lo[a] as f64 - 1.0) * grid.spacing[a]),
            mask,
            source: format!("label {l}"),
            area: None,
        });
    }
    Ok(out)
}

/// Keeps the largest 26-connected component (the clump is one connected body).
pub fn keep_largest_component(mask: &mut [bool], dims: [usize; 3]) {
    let [nx, ny, nz] = dims;
    let mut comp = vec![u32::MAX; mask.len()];
    let mut sizes = Vec::new();
    let mut stack = Vec::new();
    for start in 0..mask.len() {
        if !mask[start] || comp[start] != u32::MAX {
            continue;
        }
        let id = sizes.len() as u32;
        let mut size = 0usize;
        comp[start] = id;
        stack.push(start);
        while let Some(i) = stack.pop() {
            size += 1;
            let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
            for dz in -1i64..=1 {
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let (qx, qy, qz) = (x as i64 + dx, y as i64 + dy, z as i64 + dz);
                        if qx < 0
                            || qy < 0
                            || qz < 0
                            || qx >= nx as i64
                            || qy >= ny as i64
                            || qz >= nz as i64
                        {
                            continue;
                        }
                        let q = qx as usize + nx * (qy as usize + ny * qz as usize);
                        if mask[q] && comp[q] == u32::MAX {
                            comp[q] = id;
                            stack.push(q);
                        }
                    }
                }
            }
        }
        sizes.push(size);
    }
    if sizes.len() <= 1 {
        return;
    }
    let best = (0..sizes.len())
        .max_by_key(|&k| (sizes[k], std::cmp::Reverse(k)))
        .unwrap() as u32;
    for (m, c) in mask.iter_mut().zip(comp) {
        if c != best {
            *m = false;
        }
    }
}

/// Refuses non-cubic voxels, naming the input that brought them.
fn check_cubic(port: &str, s: [f64; 3]) -> Result<(), StageError> {
    if (s[1] / s[0] - 1.0).abs() > 1e-6 || (s[2] / s[0] - 1.0).abs() > 1e-6 {
        return Err(StageError::input(
            port,
            format!(
                "voxels must be cubic, spacing is {s:?} m: resample the scan to cubic voxels \
                 before importing it (or set `spacing` on the import.* stage when the file's \
                 spacing is wrong)"
            ),
        ));
    }
    Ok(())
}

impl TypedStage for FromLabels {
    type Params = LabelsParams;
    type Plan = ();
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "grains.from_labels",
            "1.2.0",
            "One mask per grain from a segmented scan whose labels are grain ids (read it \
             with import.raw / import.hdf5 / import.netcdf / import.vti). A PhaseImage \
             holds at most 255 grain ids (u8 labels); connect a Field of integer values \
             (import.* with `as: field`) for more. Grains touching the top/bottom are \
             dropped as incomplete (paper, section 2.1).",
        )
        .inputs(vec![
            PortSpec::optional(
                "labels",
                ArtifactKind::PhaseImage,
                "grain ids as u8 labels (<= 255 grains)",
            ),
            PortSpec::optional(
                "field",
                ArtifactKind::Field,
                "grain ids as integer values of a 1-component field (any count)",
            ),
        ])
        .outputs(grain_output_ports())
    }
    fn preflight(&self, p: &Self::Params, inputs: &InputMetas) -> Result<Preflight, StageError> {
        if !["z", "all", "none"].contains(&p.drop_touching.as_str()) {
            return Err(StageError::param(
                "drop_touching",
                format!("`{}`: use z, all or none", p.drop_touching),
            ));
        }
        let n_in = inputs.contains_key("labels") as usize + inputs.contains_key("field") as usize;
        if n_in != 1 {
            return Err(StageError::input(
                "labels",
                "connect exactly one of `labels` (PhaseImage) or `field` (Field)",
            ));
        }
        let meta = inputs
            .get("labels")
            .or_else(|| inputs.get("field"))
            .unwrap();
        let mem = meta
            .grid
            .as_ref()
            .map(|g| g.voxel_count() as u64 * 10)
            .unwrap_or(0);
        let port = if inputs.contains_key("labels") {
            "labels"
        } else {
            "field"
        };
        if let Some(g) = &meta.grid {
            check_cubic(port, g.spacing)?;
        }
        // The number of grains is known only once the labels are read; the memory is the
        // label volume's (10 B per voxel: masks, component ids, the grains' images) and the
        // per-grain tables (64 KiB, rounded up).
        let mut pf = preflight_grains(&self.info(), None, 0.0, None);
        pf.memory_bytes = mem + (64 << 10);
        Ok(pf)
    }
    fn run(
        &self,
        p: &Self::Params,
        _: &(),
        inputs: &Inputs,
        _ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let (labels, grid): (Vec<i64>, Grid) = if let Some(a) = inputs.get("labels") {
            let img = a
                .as_phase_image()
                .ok_or_else(|| StageError::input("labels", format!("got a {}", a.kind())))?;
            (
                img.labels.iter().map(|&l| l as i64).collect(),
                img.grid.clone(),
            )
        } else {
            let f = input(inputs, "field", Artifact::as_field)?;
            if f.components != 1 {
                return Err(StageError::input(
                    "field",
                    format!("needs 1 component, got {}", f.components),
                ));
            }
            let mut v = Vec::with_capacity(f.data.len());
            for i in 0..f.data.len() {
                let x = f.data.get(i);
                if x.fract() != 0.0 || !x.is_finite() {
                    return Err(StageError::input(
                        "field",
                        format!("value {x} at voxel {i} is not an integer grain id"),
                    ));
                }
                v.push(x as i64);
            }
            (v, f.grid.clone())
        };
        let port = if inputs.contains_key("labels") {
            "labels"
        } else {
            "field"
        };
        check_cubic(port, grid.spacing)?;
        let grains = split_labels(&labels, &grid, p).map_err(StageError::failed)?;
        if grains.is_empty() {
            return Err(StageError::failed(
                "no grain left after dropping border grains and those under min_voxels",
            ));
        }
        Ok(grain_outputs(grains))
    }
}
