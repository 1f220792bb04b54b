//! Grain masks travelling between stages, their size/shape statistics, and the four
//! `grains.*` stages.
//!
//! A set of grains is a `Series` of `PhaseImage` frames: frame k (time = k) is a small
//! image holding grain k alone, label 1 = grain, 0 = outside, voxels cubic, the grid origin
//! at the grain's physical position. Phase 1's name carries the grain's source (file name,
//! label id or generator). See docs/stages/clumps.md for why.

use crate::mesh::Mesh;
use crate::shape::{gaussian_random_field, random_rotation, Harmonics, StarShape};
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::*;
use nalgebra::{Matrix3, SymmetricEigen};
use rand::SeedableRng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// One grain as a cubic-voxel mask.
#[derive(Clone, Debug)]
pub struct GrainMask {
    pub dims: [usize; 3],
    /// Voxel edge [m].
    pub voxel: f64,
    /// Lower grid corner [m].
    pub origin: [f64; 3],
    pub mask: Vec<bool>,
    pub source: String,
    /// Surface area when known from the shape itself (meshes, harmonics) [m^2].
    pub area: Option<f64>,
}

impl GrainMask {
    pub fn voxels(&self) -> usize {
        self.mask.iter().filter(|&&b| b).count()
    }

    pub fn to_phase_image(&self) -> PhaseImage {
        PhaseImage {
            grid: Grid {
                dims: self.dims,
                spacing: [self.voxel; 3],
                origin: self.origin,
                periodic: [false; 3],
            },
            labels: self.mask.iter().map(|&b| b as u8).collect(),
            phases: vec![
                Phase {
                    id: 0,
                    name: "outside".into(),
                },
                Phase {
                    id: 1,
                    name: self.source.clone(),
                },
            ],
        }
    }

    /// Any non-zero label is grain.
    pub fn from_phase_image(img: &PhaseImage) -> Result<GrainMask, String> {
        let s = img.grid.spacing;
        if s[0].partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
            || (s[1] / s[0] - 1.0).abs() > 1e-6
            || (s[2] / s[0] - 1.0).abs() > 1e-6
        {
            return Err(format!(
                "voxels must be cubic (spacing {:?} m): resample the image first",
                s
            ));
        }
        if img.labels.len() != img.grid.voxel_count() {
            return Err("label count does not match the grid".into());
        }
        let source = img
            .phases
            .iter()
            .find(|p| p.id == 1)
            .map(|p| p.name.clone())
            .unwrap_or_default();
        Ok(GrainMask {
            dims: img.grid.dims,
            voxel: s[0],
            origin: img.grid.origin,
            mask: img.labels.iter().map(|&l| l != 0).collect(),
            source,
            area: None,
        })
    }
}

/// Wraps grains into the Series that travels between stages.
pub fn grains_to_series(grains: &[GrainMask]) -> Series {
    Series {
        frames: grains
            .iter()
            .enumerate()
            .map(|(k, g)| (k as f64, Artifact::PhaseImage(g.to_phase_image())))
            .collect(),
    }
}

pub fn series_to_grains(s: &Series) -> Result<Vec<GrainMask>, String> {
    s.frames
        .iter()
        .enumerate()
        .map(|(k, (_, f))| match f {
            Artifact::PhaseImage(img) => {
                GrainMask::from_phase_image(img).map_err(|e| format!("frame {k}: {e}"))
            }
            other => Err(format!(
                "frame {k} is a {}, expected a PhaseImage",
                other.kind()
            )),
        })
        .collect()
}

/// Size and shape statistics of one grain mask.
#[derive(Clone, Debug, Default)]
pub struct GrainStats {
    pub voxels: usize,
    pub volume: f64,
    /// Volume-equivalent diameter [m].
    pub d_eq: f64,
    /// Diameter of the centroid-centred sphere enclosing every voxel centre, plus one voxel [m].
    pub d_bound: f64,
    /// Extents along the principal axes of inertia, longest first [m].
    pub length: f64,
    pub width: f64,
    pub thickness: f64,
    /// Wadell sphericity pi^(1/3) (6 V)^(2/3) / A.
    pub sphericity: f64,
}

impl GrainStats {
    pub fn of(g: &GrainMask) -> GrainStats {
        let h = g.voxel;
        let [nx, ny, nz] = g.dims;
        let mut n = 0.0;
        let mut s = [0.0; 3];
        let mut ss = [[0.0; 3]; 3];
        let mut faces = 0usize;
        let at = |x: i64, y: i64, z: i64| {
            x >= 0
                && y >= 0
                && z >= 0
                && (x as usize) < nx
                && (y as usize) < ny
                && (z as usize) < nz
                && g.mask[x as usize + nx * (y as usize + ny * z as usize)]
        };
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    if !g.mask[x + nx * (y + ny * z)] {
                        continue;
                    }
                    let p = [x as f64, y as f64, z as f64];
                    n += 1.0;
                    for i in 0..3 {
                        s[i] += p[i];
                        for j in 0..3 {
                            ss[i][j] += p[i] * p[j];
                        }
                    }
                    let (xi, yi, zi) = (x as i64, y as i64, z as i64);
                    for (dx, dy, dz) in [
                        (1, 0, 0),
                        (-1, 0, 0),
                        (0, 1, 0),
                        (0, -1, 0),
                        (0, 0, 1),
                        (0, 0, -1),
                    ] {
                        if !at(xi + dx, yi + dy, zi + dz) {
                            faces += 1;
                        }
                    }
                }
            }
        }
        if n == 0.0 {
            return GrainStats::default();
        }
        let c = s.map(|v| v / n);
        let cov = Matrix3::from_fn(|i, j| ss[i][j] / n - c[i] * c[j]);
        let eig = SymmetricEigen::new(cov);
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        let mut rmax: f64 = 0.0;
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    if !g.mask[x + nx * (y + ny * z)] {
                        continue;
                    }
                    let d =
                        nalgebra::Vector3::new(x as f64 - c[0], y as f64 - c[1], z as f64 - c[2]);
                    rmax = rmax.max(d.norm());
                    for a in 0..3 {
                        let t = eig.eigenvectors.column(a).dot(&d);
                        lo[a] = lo[a].min(t);
                        hi[a] = hi[a].max(t);
                    }
                }
            }
        }
        let mut ext: Vec<f64> = (0..3).map(|a| (hi[a] - lo[a] + 1.0) * h).collect();
        ext.sort_by(|a, b| b.total_cmp(a));
        let volume = n * h * h * h;
        // A voxel surface overestimates the area of a smooth surface by 3/2 on average over
        // orientations (mean |n_x| + |n_y| + |n_z| = 3/2), hence the 2/3 when no exact area.
        let area = g.area.unwrap_or(faces as f64 * h * h * 2.0 / 3.0);
        GrainStats {
            voxels: n as usize,
            volume,
            d_eq: (6.0 * volume / std::f64::consts::PI).cbrt(),
            d_bound: 2.0 * rmax * h + h,
            length: ext[0],
            width: ext[1],
            thickness: ext[2],
            sphericity: std::f64::consts::PI.cbrt() * (6.0 * volume).powf(2.0 / 3.0) / area,
        }
    }
}

/// Number-weighted quantile by linear interpolation between order statistics.
pub fn quantile(values: &[f64], p: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let x = p * (v.len() - 1) as f64;
    let i = x.floor() as usize;
    let t = x - i as f64;
    if i + 1 < v.len() {
        v[i] * (1.0 - t) + v[i + 1] * t
    } else {
        v[i]
    }
}

/// Per-grain table and the D10/D50/D90 summary.
pub fn stats_tables(grains: &[GrainMask]) -> (Table, Table) {
    let st: Vec<GrainStats> = grains.par_iter().map(GrainStats::of).collect();
    let col = |f: &dyn Fn(&GrainStats) -> f64| st.iter().map(f).collect::<Vec<f64>>();
    let table = Table::new("grains")
        .with_i64("grain", "", (0..grains.len() as i64).collect())
        .with_str("source", grains.iter().map(|g| g.source.clone()).collect())
        .with_i64("voxels", "", st.iter().map(|s| s.voxels as i64).collect())
        .with_f64("volume", "m^3", col(&|s| s.volume))
        .with_f64("d_eq", "m", col(&|s| s.d_eq))
        .with_f64("d_bound", "m", col(&|s| s.d_bound))
        .with_f64("length", "m", col(&|s| s.length))
        .with_f64("width", "m", col(&|s| s.width))
        .with_f64("thickness", "m", col(&|s| s.thickness))
        .with_f64("elongation", "", col(&|s| s.width / s.length))
        .with_f64("flatness", "", col(&|s| s.thickness / s.width))
        .with_f64("sphericity", "", col(&|s| s.sphericity));
    let deq = col(&|s| s.d_eq);
    let db = col(&|s| s.d_bound);
    let names = ["D10", "D50", "D90", "mean"];
    let q = |v: &[f64]| {
        vec![
            quantile(v, 0.1),
            quantile(v, 0.5),
            quantile(v, 0.9),
            v.iter().sum::<f64>() / v.len().max(1) as f64,
        ]
    };
    let summary = Table::new("grain_size_summary")
        .with_str("statistic", names.iter().map(|s| s.to_string()).collect())
        .with_f64("d_eq", "m", q(&deq))
        .with_f64("d_bound", "m", q(&db));
    (table, summary)
}

fn grain_outputs(grains: &[GrainMask]) -> Outputs {
    let (t, s) = stats_tables(grains);
    let mut out = Outputs::new();
    out.insert("grains".into(), Artifact::Series(grains_to_series(grains)));
    out.insert("stats".into(), Artifact::Table(t));
    out.insert("summary".into(), Artifact::Table(s));
    out
}

fn grain_output_ports() -> Vec<PortSpec> {
    vec![
        PortSpec::new(
            "grains",
            ArtifactKind::Series,
            "one PhaseImage per grain (frame time = grain index; label 1 = grain; phase 1 is \
             named after the grain's source)",
        ),
        PortSpec::new(
            "stats",
            ArtifactKind::Table,
            "per grain: voxels, volume, d_eq, d_bound, length/width/thickness, elongation, \
             flatness, sphericity",
        ),
        PortSpec::new(
            "summary",
            ArtifactKind::Table,
            "D10, D50, D90 and mean (by number) of d_eq and d_bound",
        ),
    ]
}

fn preflight_grains(info: &StageInfo, n: usize, voxels_per_grain: f64) -> Preflight {
    let mut p = Preflight::from_info(info, (n as f64 * voxels_per_grain * 2.0) as u64);
    if let Some(m) = p.outputs.get_mut("grains") {
        m.count_estimate = n as u64;
    }
    p
}

fn check_voxel(key: &str, h: f64) -> Result<(), StageError> {
    if !(h.is_finite() && h > 0.0) {
        return Err(StageError::param(
            key,
            format!("must be a positive length, got {h} m"),
        ));
    }
    Ok(())
}

/// Resolves a data path: relative to the working directory, or else (for the shipped data)
/// relative to the repository root.
pub fn resolve_path(p: &str) -> PathBuf {
    let path = PathBuf::from(p);
    if path.is_absolute() || path.exists() {
        return path;
    }
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").join(p);
    if repo.exists() {
        repo
    } else {
        path
    }
}

// ---------------------------------------------------------------------------------------
// grains.from_harmonics

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HarmonicsParams {
    pub directory: String,
    pub files: Vec<String>,
    pub count: usize,
    pub voxel_size: Q<Length>,
    pub d50: Q<Length>,
    pub size: Option<SizeDistribution>,
    pub random_rotation: bool,
    pub max_degree: usize,
}

impl Default for HarmonicsParams {
    fn default() -> Self {
        HarmonicsParams {
            directory: "data/sand-grains/MA107-6-fine".into(),
            files: Vec::new(),
            count: 0,
            // Paper section 2.1: micro-CT at 4 um; GS14 sand, D50 = 140 um (section 4.3).
            voxel_size: Q::new(4e-6),
            d50: Q::new(140e-6),
            size: None,
            random_rotation: false,
            max_degree: 30,
        }
    }
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
    fn info(&self) -> StageInfo {
        StageInfo {
            id: "grains.from_harmonics",
            version: "1.0.0",
            doc: "Star-shaped grains from spherical-harmonic coefficient files (VCCTL `-anm-` \
                  format, the real sand grains of data/sand-grains/), rescaled to a target \
                  size and voxelized: the default grain source of the sand-core pipelines.",
            params: vec![
                ParamSpec { name: "directory", ty: "path", unit: "", doc: "folder of `-anm-` .dat files (relative to the working directory; the shipped data/ folder is found from anywhere)" },
                ParamSpec { name: "files", ty: "[file names]", unit: "", doc: "files to use inside `directory`; empty = every .dat file, sorted by name" },
                ParamSpec { name: "count", ty: "integer", unit: "", doc: "grains to output; 0 = one per file; more than the files cycles through them (use random_rotation)" },
                ParamSpec { name: "voxel_size", ty: "length", unit: "m", doc: "voxel edge of the masks (paper: 4 um CT)" },
                ParamSpec { name: "d50", ty: "length", unit: "m", doc: "median volume-equivalent diameter after one common rescaling (paper: GS14 sand, 140 um); ignored when `size` is set" },
                ParamSpec { name: "size", ty: "size distribution or null", unit: "m", doc: "law of the volume-equivalent diameter: grain sizes become its quantiles in the order of the natural sizes" },
                ParamSpec { name: "random_rotation", ty: "bool", unit: "", doc: "rotate each grain uniformly at random" },
                ParamSpec { name: "max_degree", ty: "integer", unit: "", doc: "truncate the expansion at this degree (files hold 30; VCCTL genaggpack uses 14)" },
            ],
            inputs: vec![],
            outputs: grain_output_ports(),
        }
    }
    fn preflight(&self, p: &Self::Params, _: &InputMetas) -> Result<Preflight, StageError> {
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
        Ok(preflight_grains(&self.info(), n, vox))
    }
    fn run(&self, p: &Self::Params, _: &Inputs, ctx: &RunContext) -> Result<Outputs, StageError> {
        let files = p.file_list()?;
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
                    random_rotation(&mut ctx.substream(k as u64))
                } else {
                    Matrix3::identity()
                };
                let shape = StarShape {
                    table: tables[i].clone(),
                    transform: rot * scale,
                };
                let (dims, origin, mask) = shape
                    .voxelize(p.voxel_size.si())
                    .map_err(StageError::failed)?;
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

fn check_nonempty(grains: &[GrainMask]) -> Result<(), StageError> {
    if let Some((k, g)) = grains.iter().enumerate().find(|(_, g)| g.voxels() == 0) {
        return Err(StageError::failed(format!(
            "grain {k} ({}) has no voxel at voxel_size {:.3e} m: use a smaller voxel_size",
            g.source, g.voxel
        )));
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// grains.synthetic

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SyntheticParams {
    pub count: usize,
    pub size: SizeDistribution,
    pub voxel_size: Q<Length>,
    pub length_to_thickness: f64,
    pub width_to_thickness: f64,
    pub aspect_spread: f64,
    pub roughness: f64,
    pub spectral_exponent: f64,
    pub min_degree: usize,
    pub max_degree: usize,
}

/// Defaults from the 30 real grains of data/sand-grains (examples/fit_synthetic.rs,
/// docs/stages/clumps.md): the point deviation of the relative radius over degrees 3..30 is
/// 0.1325; the least-squares spectral slope is 3.99, but with it the synthetic grains are
/// rougher than the real ones (sphericity 0.77 vs 0.84), so the exponent is set to 5, which
/// reproduces the real sphericity (0.83).
pub const FIT_ROUGHNESS: f64 = 0.13;
pub const FIT_SPECTRAL_EXPONENT: f64 = 5.0;

impl Default for SyntheticParams {
    fn default() -> Self {
        SyntheticParams {
            count: 50,
            // Silica foundry sand: D50 = 140 um (paper, GS14); log-normal width assumed.
            size: SizeDistribution::Lognormal {
                median: Q::new(140e-6),
                sigma: 0.25,
                min: None,
                max: None,
            },
            voxel_size: Q::new(4e-6),
            // VCCTL MA107-6 set statistics: mean L/T = 1.819 +- 0.427, W/T = 1.373 +- 0.289.
            length_to_thickness: 1.819,
            width_to_thickness: 1.373,
            aspect_spread: 0.2,
            roughness: FIT_ROUGHNESS,
            spectral_exponent: FIT_SPECTRAL_EXPONENT,
            min_degree: 3,
            max_degree: 30,
        }
    }
}

pub struct Synthetic;

/// One synthetic grain shape (reference size: unit equivalent diameter not yet imposed).
/// Returns the shape and its surface area [m^2].
pub fn synthetic_shape(
    p: &SyntheticParams,
    rng: &mut rand_chacha::ChaCha8Rng,
    d_eq: f64,
) -> (StarShape, f64) {
    use rand_distr::{Distribution, StandardNormal};
    let g = gaussian_random_field(
        rng,
        p.min_degree,
        p.max_degree,
        p.spectral_exponent,
        p.roughness,
    );
    let nt = (4 * p.max_degree).max(60);
    let mut table = g.tabulate(nt, 2 * nt);
    for v in &mut table.r {
        *v = v.exp(); // r = exp(g) keeps the radius positive
    }
    let e1: f64 = StandardNormal.sample(rng);
    let e2: f64 = StandardNormal.sample(rng);
    let lt = (p.length_to_thickness * (p.aspect_spread * e1).exp()).max(1.0);
    let wt = (p.width_to_thickness * (p.aspect_spread * e2).exp()).clamp(1.0, lt);
    let rot = random_rotation(rng);
    let stretch = Matrix3::from_diagonal(&nalgebra::Vector3::new(lt, wt, 1.0));
    let shape = StarShape {
        table,
        transform: rot * stretch,
    };
    let (v, a) = shape.volume_area();
    let s = (std::f64::consts::PI / 6.0 * d_eq.powi(3) / v).cbrt();
    (
        StarShape {
            table: shape.table,
            transform: shape.transform * s,
        },
        a * s * s,
    )
}

impl TypedStage for Synthetic {
    type Params = SyntheticParams;
    fn info(&self) -> StageInfo {
        StageInfo {
            id: "grains.synthetic",
            version: "1.0.0",
            doc: "Random star-shaped grains: radius exp(g) with g a Gaussian random field on \
                  the sphere (power-law spectrum, fitted to the real grains of \
                  data/sand-grains), stretched to random length/width/thickness ratios (VCCTL \
                  MA107-6 statistics), randomly rotated, sized by a volume-equivalent diameter \
                  law (default log-normal, D50 = 140 um).",
            params: vec![
                ParamSpec {
                    name: "count",
                    ty: "integer",
                    unit: "",
                    doc: "number of grains",
                },
                ParamSpec {
                    name: "size",
                    ty: "size distribution",
                    unit: "m",
                    doc: "law of the volume-equivalent diameter (median = D50)",
                },
                ParamSpec {
                    name: "voxel_size",
                    ty: "length",
                    unit: "m",
                    doc: "voxel edge of the masks",
                },
                ParamSpec {
                    name: "length_to_thickness",
                    ty: "number >= 1",
                    unit: "",
                    doc: "median L/T stretch (VCCTL MA107-6: 1.819)",
                },
                ParamSpec {
                    name: "width_to_thickness",
                    ty: "number >= 1",
                    unit: "",
                    doc: "median W/T stretch (VCCTL MA107-6: 1.373)",
                },
                ParamSpec {
                    name: "aspect_spread",
                    ty: "number >= 0",
                    unit: "",
                    doc: "log-normal spread of both ratios (MA107-6: about 0.2)",
                },
                ParamSpec {
                    name: "roughness",
                    ty: "number >= 0",
                    unit: "",
                    doc: "standard deviation of ln r over the sphere (angularity)",
                },
                ParamSpec {
                    name: "spectral_exponent",
                    ty: "number",
                    unit: "",
                    doc: "beta of the angular power spectrum C_n ~ n^-beta",
                },
                ParamSpec {
                    name: "min_degree",
                    ty: "integer >= 1",
                    unit: "",
                    doc:
                        "lowest random degree (2 would add random elongation on top of the stretch)",
                },
                ParamSpec {
                    name: "max_degree",
                    ty: "integer",
                    unit: "",
                    doc: "highest degree (the real grains' files stop at 30)",
                },
            ],
            inputs: vec![],
            outputs: grain_output_ports(),
        }
    }
    fn preflight(&self, p: &Self::Params, _: &InputMetas) -> Result<Preflight, StageError> {
        check_voxel("voxel_size", p.voxel_size.si())?;
        p.size
            .validate()
            .map_err(|(k, m)| StageError::param(&format!("size.{k}"), m))?;
        if p.count == 0 {
            return Err(StageError::param("count", "must be at least 1"));
        }
        if !(p.length_to_thickness >= 1.0
            && p.width_to_thickness >= 1.0
            && p.width_to_thickness <= p.length_to_thickness)
        {
            return Err(StageError::param(
                "length_to_thickness",
                "need 1 <= width_to_thickness <= length_to_thickness",
            ));
        }
        for (k, v) in [
            ("aspect_spread", p.aspect_spread),
            ("roughness", p.roughness),
        ] {
            if !(v.is_finite() && (0.0..=2.0).contains(&v)) {
                return Err(StageError::param(k, format!("must be in [0, 2], got {v}")));
            }
        }
        if !p.spectral_exponent.is_finite() {
            return Err(StageError::param("spectral_exponent", "must be finite"));
        }
        if p.min_degree == 0 || p.min_degree > p.max_degree || p.max_degree > 200 {
            return Err(StageError::param(
                "max_degree",
                "need 1 <= min_degree <= max_degree <= 200",
            ));
        }
        let vox =
            (2.0 * p.size.practical_max() * p.length_to_thickness / p.voxel_size.si()).powi(3);
        if vox > 5e7 {
            return Err(StageError::param(
                "voxel_size",
                format!("a grain would need ~{vox:.0} voxels: use a larger voxel_size"),
            ));
        }
        Ok(preflight_grains(&self.info(), p.count, vox / 8.0))
    }
    fn run(&self, p: &Self::Params, _: &Inputs, ctx: &RunContext) -> Result<Outputs, StageError> {
        let done = std::sync::atomic::AtomicU64::new(0);
        let grains: Vec<GrainMask> = (0..p.count)
            .into_par_iter()
            .map(|k| {
                let mut rng = ctx.substream(k as u64);
                let d = p.size.sample(&mut rng);
                let (shape, area) = synthetic_shape(p, &mut rng, d);
                let (dims, origin, mask) = shape
                    .voxelize(p.voxel_size.si())
                    .map_err(StageError::failed)?;
                let c = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                ctx.progress(c, p.count as u64)?;
                Ok(GrainMask {
                    dims,
                    voxel: p.voxel_size.si(),
                    origin,
                    mask,
                    source: format!("synthetic #{k}"),
                    area: Some(area),
                })
            })
            .collect::<Result<_, StageError>>()?;
        check_nonempty(&grains)?;
        Ok(grain_outputs(&grains))
    }
}

// ---------------------------------------------------------------------------------------
// grains.from_meshes

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MeshesParams {
    pub files: Vec<String>,
    pub voxel_size: Q<Length>,
    pub mesh_unit: Q<Length>,
}

impl Default for MeshesParams {
    fn default() -> Self {
        MeshesParams {
            files: Vec::new(),
            voxel_size: Q::new(4e-6),
            mesh_unit: Q::new(1e-3),
        }
    }
}

pub struct FromMeshes;

impl TypedStage for FromMeshes {
    type Params = MeshesParams;
    fn info(&self) -> StageInfo {
        StageInfo {
            id: "grains.from_meshes",
            version: "1.0.0",
            doc: "Grains from closed triangle surfaces (STL ASCII or binary, OBJ), one grain \
                  per file, voxelized by ray parity (a voxel is inside when a ray from its \
                  centre crosses the surface an odd number of times).",
            params: vec![
                ParamSpec { name: "files", ty: "[paths]", unit: "", doc: ".stl / .obj files, one closed surface per grain (relative to the working directory)" },
                ParamSpec { name: "voxel_size", ty: "length", unit: "m", doc: "voxel edge of the masks" },
                ParamSpec { name: "mesh_unit", ty: "length", unit: "m", doc: "length of one mesh coordinate unit (STL/OBJ carry none)" },
            ],
            inputs: vec![],
            outputs: grain_output_ports(),
        }
    }
    fn preflight(&self, p: &Self::Params, _: &InputMetas) -> Result<Preflight, StageError> {
        check_voxel("voxel_size", p.voxel_size.si())?;
        check_voxel("mesh_unit", p.mesh_unit.si())?;
        if p.files.is_empty() {
            return Err(StageError::param(
                "files",
                "list at least one .stl or .obj file",
            ));
        }
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
        }
        Ok(preflight_grains(&self.info(), p.files.len(), 1e5))
    }
    fn run(&self, p: &Self::Params, _: &Inputs, ctx: &RunContext) -> Result<Outputs, StageError> {
        let mut grains = Vec::new();
        for (k, f) in p.files.iter().enumerate() {
            let path = resolve_path(f);
            let mut m = Mesh::read(&path).map_err(StageError::failed)?;
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
        Ok(grain_outputs(&grains))
    }
}

// ---------------------------------------------------------------------------------------
// grains.from_labels

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LabelsParams {
    pub drop_touching: String,
    pub background: i64,
    pub min_voxels: usize,
    pub largest_component: bool,
}

impl Default for LabelsParams {
    fn default() -> Self {
        LabelsParams {
            drop_touching: "z".into(),
            background: 0,
            min_voxels: 8,
            largest_component: true,
        }
    }
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

impl TypedStage for FromLabels {
    type Params = LabelsParams;
    fn info(&self) -> StageInfo {
        StageInfo {
            id: "grains.from_labels",
            version: "1.0.0",
            doc: "One mask per grain from a segmented scan whose labels are grain ids (read it \
                  with import.raw / import.hdf5 / import.netcdf / import.vti). A PhaseImage \
                  holds at most 255 grain ids (u8 labels); connect a Field of integer values \
                  (import.* with `as: field`) for more. Grains touching the top/bottom are \
                  dropped as incomplete (paper, section 2.1).",
            params: vec![
                ParamSpec {
                    name: "drop_touching",
                    ty: "one of: z, all, none",
                    unit: "",
                    doc: "drop grains touching the z faces (paper), any face, or none",
                },
                ParamSpec {
                    name: "background",
                    ty: "integer",
                    unit: "",
                    doc: "label of the pore space",
                },
                ParamSpec {
                    name: "min_voxels",
                    ty: "integer",
                    unit: "",
                    doc: "drop grains with fewer voxels (segmentation debris)",
                },
                ParamSpec {
                    name: "largest_component",
                    ty: "bool",
                    unit: "",
                    doc: "keep only the largest 26-connected part of each label",
                },
            ],
            inputs: vec![
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
            ],
            outputs: grain_output_ports(),
        }
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
        if let Some(g) = &meta.grid {
            let s = g.spacing;
            if (s[1] / s[0] - 1.0).abs() > 1e-6 || (s[2] / s[0] - 1.0).abs() > 1e-6 {
                return Err(StageError::input(
                    "labels",
                    format!("voxels must be cubic, spacing is {s:?} m"),
                ));
            }
        }
        Ok(Preflight::from_info(&self.info(), mem))
    }
    fn run(
        &self,
        p: &Self::Params,
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
        let s = grid.spacing;
        if (s[1] / s[0] - 1.0).abs() > 1e-6 || (s[2] / s[0] - 1.0).abs() > 1e-6 {
            return Err(StageError::input(
                "labels",
                format!("voxels must be cubic, spacing is {s:?} m"),
            ));
        }
        let grains = split_labels(&labels, &grid, p).map_err(StageError::failed)?;
        if grains.is_empty() {
            return Err(StageError::failed(
                "no grain left after dropping border grains and those under min_voxels",
            ));
        }
        Ok(grain_outputs(&grains))
    }
}

/// Builds a grain from a star shape (helper for tests and the benchmark).
pub fn grain_from_shape(shape: &StarShape, h: f64, source: &str) -> Result<GrainMask, String> {
    let (dims, origin, mask) = shape.voxelize(h)?;
    Ok(GrainMask {
        dims,
        voxel: h,
        origin,
        mask,
        source: source.into(),
        area: Some(shape.volume_area().1),
    })
}

/// Synthetic grains without a pipeline (tests, benchmark): `count` grains from `seed`.
pub fn synthetic_grains(p: &SyntheticParams, seed: u64) -> Vec<GrainMask> {
    (0..p.count)
        .into_par_iter()
        .map(|k| {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(derive_seed(
                seed,
                &(k as u64).to_le_bytes(),
            ));
            let d = p.size.sample(&mut rng);
            let (shape, area) = synthetic_shape(p, &mut rng, d);
            let (dims, origin, mask) = shape.voxelize(p.voxel_size.si()).expect("voxelize");
            GrainMask {
                dims,
                voxel: p.voxel_size.si(),
                origin,
                mask,
                source: format!("synthetic #{k}"),
                area: Some(area),
            }
        })
        .collect()
}
