//! `grains.from_harmonics`: star-shaped grains from spherical-harmonic coefficient files.

use super::{
    check_nonempty, check_voxel, de_resolved, grain_output_ports, grain_outputs, preflight_grains,
    quantile, resolve_path, resolved, GrainMask,
};
use crate::shape::{Harmonics, StarShape};
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::spatial::random_quaternion;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::*;
use nalgebra::{Matrix3, Quaternion, UnitQuaternion};
use rayon::prelude::*;
use std::path::PathBuf;

#[params]
pub struct HarmonicsParams {
    /// folder of `-anm-` .dat files (relative to the working directory; the shipped data/ folder is found from anywhere)
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

impl TypedStage for FromHarmonics {
    type Params = HarmonicsParams;
    /// The coefficient files, listed once in preflight.
    type Plan = Vec<PathBuf>;
    fn info(&self) -> StageInfo {
        StageInfo::new(
            "grains.from_harmonics",
            "1.1.0",
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
    ) -> Result<Preflight<Vec<PathBuf>>, StageError> {
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
        let n = if p.count == 0 { files.len() } else { p.count };
        let d = p
            .size
            .as_ref()
            .map(|s| s.practical_max())
            .unwrap_or(p.d50.si() * 2.0);
        let vox = (2.0 * d / p.voxel_size.si()).powi(3);
        if vox > 5e7 {
            return Err(StageError::param(
                "voxel_size",
                format!("a grain would need ~{vox:.0} voxels: use a larger voxel_size"),
            ));
        }
        let diameter = p.size.as_ref().map_or(p.d50.si(), |s| s.mean());
        Ok(preflight_grains(&self.info(), Some(n), vox, Some(diameter)).with_plan(files))
    }
    fn run(
        &self,
        p: &Self::Params,
        files: &Vec<PathBuf>,
        _: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let n = if p.count == 0 { files.len() } else { p.count };
        let nt = (4 * p.max_degree).max(60);
        let shapes: Vec<(String, Harmonics)> = files
            .iter()
            .map(|f| {
                let mut h = Harmonics::read(f).map_err(StageError::failed)?;
                if h.nmax > p.max_degree {
                    h.coef.truncate((p.max_degree + 1) * (p.max_degree + 2) / 2);
                    h.nmax = p.max_degree;
                }
                let name = f
                    .file_name()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default();
                Ok((name, h))
            })
            .collect::<Result<_, StageError>>()?;
        let tables: Vec<_> = shapes
            .par_iter()
            .map(|(_, h)| h.tabulate(nt, 2 * nt))
            .collect();
        if let Some((k, t)) = tables.iter().enumerate().find(|(_, t)| t.min() <= 0.0) {
            return Err(StageError::failed(format!(
                "{}: the radius function reaches {:.3e} <= 0: not a star-shaped grain",
                shapes[k].0,
                t.min()
            )));
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
        let targets: Vec<f64> = match &p.size {
            None => {
                let med = quantile(&pick.iter().map(|&i| natural[i]).collect::<Vec<_>>(), 0.5);
                pick.iter()
                    .map(|&i| natural[i] * p.d50.si() / med)
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
        let done = std::sync::atomic::AtomicU64::new(0);
        let grains: Vec<GrainMask> = (0..n)
            .into_par_iter()
            .map(|k| {
                let i = pick[k];
                let scale = targets[k] / natural[i] * 1e-3; // mm -> m and rescale
                let rot = if p.random_rotation {
                    let [w, x, y, z] = random_quaternion(&mut ctx.substream(k as u64));
                    *UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
                        .to_rotation_matrix()
                        .matrix()
                } else {
                    Matrix3::identity()
                };
                let shape = StarShape {
                    table: tables[i].clone(),
                    transform: rot * scale,
                };
                let (dims, origin, mask) = shape
                    .voxelize(p.voxel_size.si())
                    .map_err(|e| StageError::failed(e.to_string()))?;
                let area = va[i].1 * (scale * scale); // rotations keep the area
                let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                ctx.progress(d, n as u64)?;
                Ok(GrainMask {
                    dims,
                    voxel: p.voxel_size.si(),
                    origin,
                    mask,
                    source: shapes[i].0.clone(),
                    area: Some(area),
                })
            })
            .collect::<Result<_, StageError>>()?;
        check_nonempty(&grains)?;
        Ok(grain_outputs(&grains))
    }
}
