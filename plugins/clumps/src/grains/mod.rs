//! Grain masks travelling between stages, their size/shape statistics, and the four
//! `grains.*` stages, one per file beside this one.
//!
//! A set of grains is a `Collection` of `PhaseImage` items named after their source: item k
//! is a small image holding grain k alone, label 1 = grain, 0 = outside, voxels cubic, the grid origin
//! at the grain's physical position. Phase 1's name carries the grain's source (file name,
//! label id or generator). See docs/stages/clumps.md for why.

mod harmonics;
mod labels;
mod meshes;
mod synthetic;

pub use harmonics::HarmonicsPlan;
pub use harmonics::{FromHarmonics, HarmonicsParams};
pub use labels::{keep_largest_component, split_labels, FromLabels, LabelsParams};
pub use meshes::{FromMeshes, MeshesParams};
pub use synthetic::{
    grain_size_limit, sampled_law, size_law_warning, synthetic_grains, synthetic_shape,
    truncate_above, Synthetic, SyntheticParams, FIT_ROUGHNESS, FIT_SPECTRAL_EXPONENT, MAX_CUT_MASS,
    MAX_GRAIN_VOXELS,
};

use crate::shape::{StarShape, VoxelizeError};
use grainpipe_core::*;
use nalgebra::{Matrix3, SymmetricEigen};
use rayon::prelude::*;
use serde::{Deserialize, Deserializer};
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

/// Wraps grains into the collection that travels between stages, one item per grain,
/// named `<k> <source>`.
pub fn grains_to_collection(grains: &[GrainMask]) -> Collection {
    Collection {
        items: grains
            .iter()
            .enumerate()
            .map(|(k, g)| {
                (
                    format!("{k:04} {}", g.source),
                    Artifact::PhaseImage(g.to_phase_image()),
                )
            })
            .collect(),
    }
}

pub fn collection_to_grains(c: &Collection) -> Result<Vec<GrainMask>, String> {
    c.items
        .iter()
        .map(|(name, item)| match item {
            Artifact::PhaseImage(img) => {
                GrainMask::from_phase_image(img).map_err(|e| format!("grain `{name}`: {e}"))
            }
            other => Err(format!(
                "grain `{name}` is a {}, expected a PhaseImage",
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
        // Inside-outside neighbour pairs per direction class (axis, face and cube diagonal).
        let mut crossings = [0usize; 3];
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
                    for (dx, dy, dz, class) in NEIGHBOURS_26 {
                        if !at(xi + dx, yi + dy, zi + dz) {
                            crossings[class] += 1;
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
        let area = g.area.unwrap_or_else(|| crofton_area(crossings, h));
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

/// The 26 neighbour offsets with their class: 0 axis, 1 face diagonal, 2 cube diagonal.
const NEIGHBOURS_26: [(i64, i64, i64, usize); 26] = {
    let mut out = [(0, 0, 0, 0); 26];
    let mut k = 0;
    let mut i = 0;
    while i < 27 {
        let (dx, dy, dz) = (i as i64 % 3 - 1, (i as i64 / 3) % 3 - 1, i as i64 / 9 - 1);
        let n = (dx * dx + dy * dy + dz * dz) as usize;
        if n > 0 {
            out[k] = (dx, dy, dz, n - 1);
            k += 1;
        }
        i += 1;
    }
    out
};

/// Crofton weights of the 26 lattice directions (Legland, Kieu & Devaux 2007, Image Anal.
/// Stereol. 26: the solid angle of each direction's Voronoi cell on the unit sphere, as a
/// fraction of 4 pi) for the axis, face-diagonal and cube-diagonal classes; 6 c0 + 12 c1 +
/// 8 c2 = 1.
const CROFTON_WEIGHTS: [f64; 3] = [
    0.045_777_891_204_76,
    0.036_980_627_876_08,
    0.035_195_639_782_32,
];

/// Surface area of a voxel set from its inside-outside neighbour pairs per direction class:
/// the Cauchy-Crofton formula S = 4 sum_d c_d N_d h^3 / |d| (N_d pairs along direction d;
/// the lines along d through voxel centres have density 1 / (h^3 / |d|) per unit area, each
/// pair is one line crossing, and the mean of |n.u| over directions is 1/2). Unlike the
/// voxel-face count (3/2 of a smooth surface on average, anywhere from 1 to sqrt(3)) it is
/// unbiased for every orientation distribution that the 26 directions resolve.
pub fn crofton_area(crossings: [usize; 3], h: f64) -> f64 {
    let len = [1.0, std::f64::consts::SQRT_2, 3f64.sqrt()];
    4.0 * h
        * h
        * (0..3)
            .map(|c| CROFTON_WEIGHTS[c] * crossings[c] as f64 / len[c])
            .sum::<f64>()
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

/// One grain as it leaves a `grains.*` stage: its source, its image and its statistics.
/// Stages build these one grain at a time so a grain's bool mask is dropped as soon as its
/// image exists.
pub struct GrainItem {
    pub source: String,
    pub image: PhaseImage,
    pub stats: GrainStats,
}

impl GrainMask {
    /// The output item of this grain (statistics first, then the mask becomes the labels).
    pub fn into_item(self) -> GrainItem {
        let stats = GrainStats::of(&self);
        let image = self.to_phase_image();
        GrainItem {
            source: self.source,
            image,
            stats,
        }
    }
}

/// Per-grain table and the D10/D50/D90 summary.
pub fn stats_tables(grains: &[GrainMask]) -> (Table, Table) {
    let st: Vec<GrainStats> = grains.par_iter().map(GrainStats::of).collect();
    let sources: Vec<String> = grains.iter().map(|g| g.source.clone()).collect();
    tables_of(&st, sources)
}

fn tables_of(st: &[GrainStats], sources: Vec<String>) -> (Table, Table) {
    let col = |f: &dyn Fn(&GrainStats) -> f64| st.iter().map(f).collect::<Vec<f64>>();
    let table = Table::new("grains")
        .with_i64("grain", "", (0..st.len() as i64).collect())
        .with_str("source", sources)
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

fn grain_outputs(grains: Vec<GrainMask>) -> Outputs {
    item_outputs(grains.into_par_iter().map(GrainMask::into_item).collect())
}

fn item_outputs(items: Vec<GrainItem>) -> Outputs {
    let st: Vec<GrainStats> = items.iter().map(|g| g.stats.clone()).collect();
    let sources: Vec<String> = items.iter().map(|g| g.source.clone()).collect();
    let (t, s) = tables_of(&st, sources);
    let collection = Collection {
        items: items
            .into_iter()
            .enumerate()
            .map(|(k, g)| {
                (
                    format!("{k:04} {}", g.source),
                    Artifact::PhaseImage(g.image),
                )
            })
            .collect(),
    };
    let mut out = Outputs::new();
    out.insert("grains".into(), Artifact::Collection(collection));
    out.insert("stats".into(), Artifact::Table(t));
    out.insert("summary".into(), Artifact::Table(s));
    out
}

fn grain_output_ports() -> Vec<PortSpec> {
    vec![
        PortSpec::new(
            "grains",
            ArtifactKind::Collection,
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

/// What a `grains.*` preflight announces: `count` grains (and stats rows) when the parameters
/// fix it, else an estimate; the four-row summary; the typical grain diameter when known.
fn preflight_grains(
    info: &StageInfo,
    count: Option<usize>,
    voxels_per_grain: f64,
    diameter: Option<f64>,
) -> Preflight {
    let n = count.unwrap_or(0) as u64;
    let bounds = count.map(|c| [c as u64; 2]);
    let mut grains = ArtifactMeta::of(ArtifactKind::Collection).with_count(n, bounds);
    if let Some(d) = diameter {
        grains = grains.with_length_scale(d);
    }
    Preflight::from_info(info, (n as f64 * voxels_per_grain * 2.0) as u64)
        .announce("grains", grains)
        .announce(
            "stats",
            ArtifactMeta::of(ArtifactKind::Table).with_count(n, bounds),
        )
        .announce(
            "summary",
            ArtifactMeta::of(ArtifactKind::Table).with_count(4, Some([4, 4])),
        )
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
    match repo.canonicalize() {
        Ok(r) => r,
        Err(_) => path,
    }
}

/// [`resolve_path`] as text: the value a path parameter holds once normalized, so the file
/// the engine hashes for the cache key is the one the stage reads.
pub fn resolved(p: &str) -> String {
    resolve_path(p).display().to_string()
}

/// Deserializes a path parameter resolved by [`resolve_path`].
fn de_resolved<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    Ok(resolved(&String::deserialize(d)?))
}

/// Deserializes a list of path parameters, each resolved by [`resolve_path`].
fn de_resolved_list<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<String>, D::Error> {
    Ok(Vec::<String>::deserialize(d)?
        .iter()
        .map(|p| resolved(p))
        .collect())
}

fn check_nonempty_items(items: &[GrainItem]) -> Result<(), StageError> {
    if let Some((k, g)) = items.iter().enumerate().find(|(_, g)| g.stats.voxels == 0) {
        return Err(StageError::failed(format!(
            "grain {k} ({}) has no voxel at voxel_size {:.3e} m: use a smaller voxel_size",
            g.source, g.image.grid.spacing[0]
        )));
    }
    Ok(())
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

/// Builds a grain from a star shape (helper for tests and the benchmark).
pub fn grain_from_shape(
    shape: &StarShape,
    h: f64,
    source: &str,
) -> Result<GrainMask, VoxelizeError> {
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
