//! `grains.from_harmonics`: star-shaped grains from spherical-harmonic coefficient files.

use super::{
    check_nonempty_items, check_voxel, de_resolved, grain_output_ports, item_outputs,
    preflight_grains, quantile, resolve_path, resolved, GrainItem, GrainMask,
};
use crate::shape::{Harmonics, RadiusTable, StarShape};
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::spatial::random_quaternion;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::*;
use nalgebra::{Matrix3, Quaternion, UnitQuaternion};
use rayon::prelude::*;
use std::path::PathBuf;

#[params]
pub struct HarmonicsParams {
    /// folder of `-anm-` .dat files (relative to the working directory; the shipped data/ folder is found from anywhere); rows with m < 0 must satisfy a_(n,-m) = (-1)^m conj(a_nm) within 1e-6 of the largest coefficient
    #[param(file, ty = "path", default = resolved("data/sand-grains/MA107-6-fine"))]
    #[serde(deserialize_with = "de_resolved")]
    pub directory: String,
    /// files to use inside `directory`; empty = every .dat file, sorted by name
    #[param(ty = "[file names]")]
    pub files: Vec<String>,
    /// grains to output; 0 = one per file; more than the files cycles through them (use random_rotation)
    pub count: usize,
    /// voxel edge of the masks (paper: 4 um CT)
    // Paper section 2.1: micro-CT at 4 um; GS14 sand, D50 = 140 um (section 4.3).
    #[param(default = Q::new(4e-6))]
    pub voxel_size: Q<Length>,
    /// median volume-equivalent diameter after one common rescaling (paper: GS14 sand, 140 um); ignored when `size` is set
    #[param(default = Q::new(140e-6))]
    pub d50: Q<Length>,
    /// law of the volume-equivalent diameter: grain sizes become its quantiles in the order of the natural sizes
    #[param(ty = "size distribution or null")]
    pub size: Option<SizeDistribution>,
    /// rotate each grain uniformly at random
    pub random_rotation: bool,
    /// truncate the expansion at this degree (files hold 30; VCCTL genaggpack uses 14)
    #[param(default = 30)]
    pub max_degree: usize,
}

pub struct FromHarmonics;

impl HarmonicsParams {
    fn file_list(&self) -> Result<Vec<PathBuf>, StageError> {
        let dir = resolve_path(&self.directory);
        let mut files: Vec<PathBuf> = if self.files.is_empty() {
            let rd = std::fs::read_dir(&dir).map_err(|e| {
                StageError::param(
                    "directory",
                    format!(
                        "{}: {e} (relative paths start at the working directory)",
                        dir.display()
                    ),
                )
            })?;
            rd.filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "dat"))
                .collect()
        } else {
            self.files.iter().map(|f| dir.join(f)).collect()
        };
        files.sort();
        if files.is_empty() {
            return Err(StageError::param(
                "directory",
                format!("{}: no .dat coefficient files", dir.display()),
            ));
        }
        for f in &files {
            if !f.is_file() {
                return Err(StageError::param(
                    "files",
                    format!("{}: not found", f.display()),
                ));
            }
        }
        Ok(files)
    }
}

/// What preflight works out once and run reuses: the parsed, tabulated shapes, their natural
/// sizes and every grain's file and target diameter.
pub struct HarmonicsPlan {
    names: Vec<String>,
    tables: Vec<RadiusTable>,
    /// (volume, area) of each table's surface at unit scale (file units, mm).
    va: Vec<(f64, f64)>,
    /// Natural volume-equivalent diameters [m].
    natural: Vec<f64>,
    /// File of grain k.
    pick: Vec<usize>,
    /// Volume-equivalent diameter of grain k [m].
    targets: Vec<f64>,
    /// Bytes the run holds at its peak (see [`peak_bytes`]).
    pub bytes: u64,
}

/// Bytes one grain's output holds beyond its labels: the PhaseImage and Collection entry
/// headers, the phase table, the item name and one stats row (measured with the example
/// `harmonics_memory`: a few hundred bytes, rounded up).
const PER_GRAIN_OVERHEAD: f64 = 1024.0;

/// Peak bytes of a run: the output labels (one byte per voxel of every grain's box) plus,
/// per worker thread, one grain in flight (its bool mask and its u8 labels, and its shape:
/// a copy of the radius table of `table_bytes` and the table's vertices for the volume and
/// area, three f64 per entry: 4 x `table_bytes`), plus the tables. Nothing else scales with
/// the count: grains are turned into their output item as soon as they are voxelized.
fn peak_bytes(boxes: &[f64], threads: usize, table_bytes: f64) -> u64 {
    let total: f64 = boxes.iter().sum();
    let largest = boxes.iter().copied().fold(0.0, f64::max);
    let in_flight = 2.0 * largest + 4.0 * table_bytes;
    (total + boxes.len() as f64 * PER_GRAIN_OVERHEAD + in_flight * threads as f64) as u64
        + (64 << 10)
}

/// Voxels of the box [`StarShape::voxelize`] allocates for extents `e` (before the empty
/// layer) at voxel `h`: one layer below, the rounding of both ends, one above.
fn box_voxels(e: [f64; 3], h: f64) -> f64 {
    e.iter().map(|x| x / h + 3.0).product()
}

/// Mean bounding-box extents of a unit-scale shape over rotations: the identity when grains
/// keep the files' orientation, else the mean over a fixed set of 24 rotations (the cube's
/// rotation group applied after a generic tilt), which estimates the expected box of a
/// uniformly random rotation.
fn mean_extents(table: &RadiusTable, rotate: bool) -> [f64; 3] {
    let rots: Vec<Matrix3<f64>> = if rotate {
        let tilt = *UnitQuaternion::from_euler_angles(0.37, 0.91, 1.73)
            .to_rotation_matrix()
            .matrix();
        (0..24)
            .map(|k| {
                let (a, b, c) = ((k % 4) as f64, ((k / 4) % 3) as f64, (k / 12) as f64);
                let r = UnitQuaternion::from_euler_angles(
                    c * std::f64::consts::PI,
                    b * std::f64::consts::FRAC_PI_2,
                    a * std::f64::consts::FRAC_PI_2,
                );
                *r.to_rotation_matrix().matrix() * tilt
            })
            .collect()
    } else {
        vec![Matrix3::identity()]
    };
    let mut e = [0.0; 3];
    for r in &rots {
        let (lo, hi) = StarShape {
            table: table.clone(),
            transform: *r,
        }
        .bbox();
        for a in 0..3 {
            e[a] += (hi[a] - lo[a]) / rots.len() as f64;
        }
    }
    e
}

impl HarmonicsParams {
    fn plan(&self, files: &[PathBuf]) -> Result<HarmonicsPlan, StageError> {
        let n = if self.count == 0 {
            files.len()
        } else {
            self.count
        };
        let nt = (4 * self.max_degree).max(60);
        let shapes: Vec<(String, Harmonics)> = files
            .iter()
            .map(|f| {
                let mut h = Harmonics::read(f).map_err(|e| StageError::param("directory", e))?;
                if h.nmax > self.max_degree {
                    h.coef
                        .truncate((self.max_degree + 1) * (self.max_degree + 2) / 2);
                    h.nmax = self.max_degree;
                }
                let name = f
                    .file_name()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default();
                Ok((name, h))
            })
            .collect::<Result<_, StageError>>()?;
        let tables: Vec<RadiusTable> = shapes
            .par_iter()
            .map(|(_, h)| h.tabulate(nt, 2 * nt))
            .collect();
        if let Some((k, t)) = tables.iter().enumerate().find(|(_, t)| t.min() <= 0.0) {
            return Err(StageError::param(
                "directory",
                format!(
                    "{}: the radius function reaches {:.3e} <= 0: not a star-shaped grain",
                    shapes[k].0,
                    t.min()
                ),
            ));
        }
        // Natural sizes (the files are in mm: README of data/sand-grains).
        let va: Vec<(f64, f64)> = tables
            .par_iter()
            .map(|t| {
                StarShape {
                    table: t.clone(),
                    transform: Matrix3::identity(),
                }
                .volume_area()
            })
            .collect();
        let natural: Vec<f64> = va
            .iter()
            .map(|(v, _)| (6.0 * v / std::f64::consts::PI).cbrt() * 1e-3)
            .collect();
        let pick: Vec<usize> = (0..n).map(|k| k % files.len()).collect();
        let targets: Vec<f64> = match &self.size {
            None => {
                let med = quantile(&pick.iter().map(|&i| natural[i]).collect::<Vec<_>>(), 0.5);
                pick.iter()
                    .map(|&i| natural[i] * self.d50.si() / med)
                    .collect()
            }
            Some(dist) => {
                // Quantile mapping: the k-th smallest natural grain gets quantile (k+1/2)/n.
                let mut order: Vec<usize> = (0..n).collect();
                order.sort_by(|&a, &b| {
                    natural[pick[a]]
                        .total_cmp(&natural[pick[b]])
                        .then(a.cmp(&b))
                });
                let mut t = vec![0.0; n];
                for (rank, &k) in order.iter().enumerate() {
                    t[k] = dist.quantile((rank as f64 + 0.5) / n as f64);
                }
                t
            }
        };
        let ext: Vec<[f64; 3]> = tables
            .par_iter()
            .map(|t| mean_extents(t, self.random_rotation))
            .collect();
        let h = self.voxel_size.si();
        let boxes: Vec<f64> = (0..n)
            .map(|k| {
                let s = targets[k] / natural[pick[k]] * 1e-3;
                box_voxels(ext[pick[k]].map(|e| e * s), h)
            })
            .collect();
        if let Some(k) = (0..n).max_by(|&a, &b| boxes[a].total_cmp(&boxes[b])) {
            if boxes[k] > 5e7 {
                return Err(StageError::param(
                    "voxel_size",
                    format!(
                        "grain {k} ({}, d_eq {:.1} um) would need ~{:.0} voxels (limit 5e7): use \
                         a larger voxel_size",
                        shapes[pick[k]].0,
                        targets[k] * 1e6,
                        boxes[k]
                    ),
                ));
            }
        }
        Ok(HarmonicsPlan {
            names: shapes.into_iter().map(|(s, _)| s).collect(),
            tables,
            va,
            natural,
            pick,
            targets,
            bytes: peak_bytes(
                &boxes,
                rayon::current_num_threads(),
                ((nt + 1) * 2 * nt * 8) as f64,
            ),
        })
    }
}

impl HarmonicsPlan {
    /// Name, volume and bounding diameter of each grain, from its file's table at its target
    /// size (rotations change neither).
    fn item_sizes(&self) -> Vec<ItemSize> {
        let unit: Vec<f64> = self
            .tables
            .par_iter()
            .map(|t| {
                StarShape {
                    table: t.clone(),
                    transform: Matrix3::identity(),
                }
                .bounding_radius()
            })
            .collect();
        (0..self.targets.len())
            .map(|k| {
                let i = self.pick[k];
                let scale = self.targets[k] / self.natural[i] * 1e-3;
                ItemSize {
                    name: self.names[i].clone(),
                    volume: std::f64::consts::PI / 6.0 * self.targets[k].powi(3),
                    bounding_diameter: 2.0 * unit[i] * scale,
                }
            })
            .collect()
    }
}

impl TypedStage for FromHarmonics {
    type Params = HarmonicsParams;
    /// The coefficient files read, checked and tabulated once in preflight.
    type Plan = HarmonicsPlan;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "grains.from_harmonics",
            "1.2.0",
            "Star-shaped grains from spherical-harmonic coefficient files (VCCTL `-anm-` \
             format, the real sand grains of data/sand-grains/), rescaled to a target \
             size and voxelized: the default grain source of the sand-core pipelines.",
        )
        .outputs(grain_output_ports())
    }
    fn preflight(
        &self,
        p: &Self::Params,
        _: &InputMetas,
    ) -> Result<Preflight<HarmonicsPlan>, StageError> {
        check_voxel("voxel_size", p.voxel_size.si())?;
        check_voxel("d50", p.d50.si())?;
        if let Some(d) = &p.size {
            d.validate()
                .map_err(|(k, m)| StageError::param(&format!("size.{k}"), m))?;
        }
        if p.max_degree == 0 || p.max_degree > 200 {
            return Err(StageError::param("max_degree", "must be in 1..=200"));
        }
        let files = p.file_list()?;
        let plan = p.plan(&files)?;
        let n = plan.targets.len();
        let diameter = p.size.as_ref().map_or(p.d50.si(), |s| s.mean());
        let mut pf = preflight_grains(&self.info(), Some(n), 0.0, Some(diameter));
        pf.memory_bytes = plan.bytes;
        // Every grain's size is known here: downstream preflights (a size cap in
        // clumps.library) read it.
        if let Some(g) = pf.outputs.get_mut("grains") {
            g.item_sizes = Some(plan.item_sizes());
        }
        Ok(pf.with_plan(plan))
    }
    fn run(
        &self,
        p: &Self::Params,
        plan: &HarmonicsPlan,
        _: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let n = plan.targets.len();
        let done = std::sync::atomic::AtomicU64::new(0);
        // Each grain becomes its output item (labels and stats) as soon as it is voxelized,
        // so the masks of all grains never coexist with their images.
        let items: Vec<GrainItem> = (0..n)
            .into_par_iter()
            .map(|k| {
                let i = plan.pick[k];
                let scale = plan.targets[k] / plan.natural[i] * 1e-3; // mm -> m and rescale
                let rot = if p.random_rotation {
                    let [w, x, y, z] = random_quaternion(&mut ctx.substream(k as u64));
                    *UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
                        .to_rotation_matrix()
                        .matrix()
                } else {
                    Matrix3::identity()
                };
                let shape = StarShape {
                    table: plan.tables[i].clone(),
                    transform: rot * scale,
                };
                let (dims, origin, mask) = shape
                    .voxelize(p.voxel_size.si())
                    .map_err(|e| StageError::failed(e.to_string()))?;
                let area = plan.va[i].1 * (scale * scale); // rotations keep the area
                let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                ctx.progress(d, n as u64)?;
                Ok(GrainMask {
                    dims,
                    voxel: p.voxel_size.si(),
                    origin,
                    mask,
                    source: plan.names[i].clone(),
                    area: Some(area),
                }
                .into_item())
            })
            .collect::<Result<_, StageError>>()?;
        check_nonempty_items(&items)?;
        Ok(item_outputs(items))
    }
}
