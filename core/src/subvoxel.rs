//! Sub-voxel geometry for composite voxels (Kabel, Merkert & Schneider, CMAME 294 (2015)
//! 168-188): beside the labels, each voxel carries the volume fraction of every phase and,
//! where it holds more than one, a unit normal of the interface through it.
//!
//! It travels between stages as a [`Field`] named [`FIELD_NAME`] on the image's grid with
//! `P + 3` plain components per voxel: the fractions of the image's phases in the order of
//! `PhaseImage::phases`, then the normal (x, y, z), zero in pure voxels. A plain field so
//! that every exporter and `import.hdf5` (`as: field`) carry it unchanged.
//!
//! Normals are the direction of steepest descent of the voxel's dominant phase fraction,
//! `-grad phi_A`, with a 3x3x3 Sobel-weighted difference over the neighbours' fractions
//! (pure neighbours count 0 or 1): for a plane interface this recovers the normal to a few
//! degrees, where the first moment of a single voxel's samples is biased to the grid axes.
//! Where that gradient vanishes (a lamina thinner than a voxel, centred in it) the first
//! moment of the voxel's own samples is used.

use crate::model::{
    Artifact, ArtifactMeta, ComponentConvention, Field, FieldData, Grid, PhaseImage,
};
use crate::stage::{input, Inputs, StageError};
use crate::{params, ParamChoice};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// How a solver treats voxels cut by an interface.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum Interfaces {
    /// Each voxel is the phase of its label (staircased interfaces).
    Labels,
    /// Voxels cut by an interface are composite voxels: a laminate of their phases along
    /// the interface normal (Kabel, Merkert & Schneider 2015), from a `subvoxel` input or
    /// from coarsening a finer image.
    Composite,
}

/// How a composite voxel that holds pore is treated by the FFT solvers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ParamChoice)]
#[serde(rename_all = "snake_case")]
pub enum PoreVoxels {
    /// The laminate of the solid phases where they fill at least half of the voxel, pore
    /// otherwise (robust: the solver converges as on labels).
    Majority,
    /// The exact rank-one laminate with a traction-free (non-conducting) pore lamina: exact
    /// for plane layers, but on granular images the void laminae leave near-mechanisms and
    /// CG may stall.
    Laminate,
}

/// The interface settings shared by the image solvers (`elasticity.fft`,
/// `conductivity.fft`, `stokes.permeability`).
#[params]
pub struct InterfaceParams {
    /// `labels`: every voxel is the phase of its label. `composite`: voxels cut by an
    /// interface get the laminate property of their phases along the interface normal
    /// (sub-voxel accuracy; needs the `subvoxel` input from an image maker run with
    /// `subvoxel: true`, or coarsen 2 or 4; in elasticity.fft and conductivity.fft it needs
    /// discretization: hex8 or rotated).
    #[param(default = Interfaces::Labels)]
    pub interfaces: Interfaces,
    /// Solve on the image coarsened by this factor per axis (1, 2 or 4): each coarse voxel
    /// gets the phase fractions of its fine voxels (composite voxels for a labels-only
    /// image such as a CT scan) and the most frequent label. The dims must be multiples.
    #[param(default = 1, ty = "integer 1|2|4")]
    pub coarsen: usize,
    /// elasticity.fft and conductivity.fft with interfaces: composite: `majority` gives a
    /// voxel that holds pore the laminate of its solid phases when they fill at least half of
    /// it, else makes it pore; `laminate` uses the exact laminate with a traction-free pore
    /// lamina (exact for plane layers; on sand images CG stalled, see docs/stages/
    /// elasticity.md). stokes.permeability uses the fluid fractions and ignores it.
    #[param(default = PoreVoxels::Majority)]
    pub pore_voxels: PoreVoxels,
}

/// The sub-voxel output switch shared by the image makers (`binder.levelset`,
/// `voxelize.packing`).
#[params]
pub struct SubvoxelOutput {
    /// Also output the sub-voxel geometry as `subvoxel`: per voxel the volume fraction of
    /// every phase (in the image's phase order) and the interface normal, for composite
    /// voxels in the solvers (`interfaces: composite`). Costs (phases + 3) x 4 bytes per
    /// voxel and the sampling of the voxels next to an interface.
    #[param(default = false)]
    pub subvoxel: bool,
    /// Sub-samples per axis in each voxel next to an interface for the sub-voxel fractions
    /// (the fraction error is below about 1 / samples of a voxel's volume).
    #[param(default = 6, ty = "integer 2..16")]
    pub subvoxel_samples: usize,
}

impl SubvoxelOutput {
    /// Refuses a sampling outside 2..=16 per axis (16^3 = 4096 points a voxel is plenty; more
    /// is a typo that would run for hours). `(key, message)` on error.
    pub fn check(&self) -> Result<(), (String, String)> {
        if !(2..=16).contains(&self.subvoxel_samples) {
            return Err((
                "subvoxel_samples".into(),
                format!(
                    "must be between 2 and 16 sub-samples per axis, got {}",
                    self.subvoxel_samples
                ),
            ));
        }
        Ok(())
    }

    /// Bytes per voxel of the output field of an image of `phases` phases (0 when off).
    pub fn bytes_per_voxel(&self, phases: usize) -> u64 {
        if self.subvoxel {
            4 * (phases as u64 + 3)
        } else {
            0
        }
    }
}

impl InterfaceParams {
    /// Checks the settings against the solve: `subvoxel` the metadata of the `subvoxel`
    /// input when it is connected, `grid` the input image's grid. Returns the grid that is
    /// solved on.
    pub fn check(&self, subvoxel: Option<&ArtifactMeta>, grid: &Grid) -> Result<Grid, StageError> {
        if ![1, 2, 4].contains(&self.coarsen) {
            return Err(StageError::param(
                "coarsen",
                format!("must be 1, 2 or 4, got {}", self.coarsen),
            ));
        }
        if self.coarsen > 1 && subvoxel.is_some() {
            return Err(StageError::param(
                "coarsen",
                "a `subvoxel` input already gives the fractions; coarsen the image or give \
                 the subvoxel input, not both",
            ));
        }
        if self.interfaces == Interfaces::Composite && subvoxel.is_none() && self.coarsen == 1 {
            return Err(StageError::param(
                "interfaces",
                "composite voxels need sub-voxel geometry: connect the image maker's \
                 `subvoxel` output (run binder.levelset or voxelize.packing with subvoxel: \
                 true) to this step's `subvoxel` input, or set coarsen: 2 or 4 on a finer \
                 image",
            ));
        }
        if let Some(g) = subvoxel.and_then(|m| m.grid.as_ref()) {
            if g.dims != grid.dims {
                return Err(StageError::input(
                    "subvoxel",
                    format!(
                        "the sub-voxel field is on a {:?} grid and the image on {:?}: connect \
                         the `subvoxel` output of the step that made this image",
                        g.dims, grid.dims
                    ),
                ));
            }
        }
        if grid.dims.iter().any(|&d| d % self.coarsen != 0) {
            return Err(StageError::param(
                "coarsen",
                format!(
                    "the image's dims {:?} are not multiples of {}",
                    grid.dims, self.coarsen
                ),
            ));
        }
        let f = self.coarsen;
        Ok(Grid {
            dims: grid.dims.map(|d| d / f),
            spacing: grid.spacing.map(|s| s * f as f64),
            origin: grid.origin,
            periodic: grid.periodic,
        })
    }

    /// The `subvoxel` input of a solver, `None` when it is not connected.
    pub fn subvoxel_input(inputs: &Inputs) -> Result<Option<&Field>, StageError> {
        match inputs.get("subvoxel") {
            Some(_) => input(inputs, "subvoxel", Artifact::as_field).map(Some),
            None => Ok(None),
        }
    }

    /// The image to solve and its sub-voxel geometry (`None` for labels): the input image
    /// coarsened when asked, with the `subvoxel` field when given.
    pub fn prepare<'a>(
        &self,
        image: &'a PhaseImage,
        field: Option<&Field>,
    ) -> Result<(std::borrow::Cow<'a, PhaseImage>, Option<Subvoxel>), String> {
        use std::borrow::Cow;
        if self.coarsen > 1 {
            let (coarse, sv) = coarsen(image, self.coarsen)?;
            let sv = (self.interfaces == Interfaces::Composite).then_some(sv);
            return Ok((Cow::Owned(coarse), sv));
        }
        match (self.interfaces, field) {
            (Interfaces::Composite, Some(f)) => {
                Ok((Cow::Borrowed(image), Some(Subvoxel::from_field(f, image)?)))
            }
            (Interfaces::Composite, None) => {
                Err("interfaces: composite needs the `subvoxel` input or coarsen: 2|4".into())
            }
            (Interfaces::Labels, _) => Ok((Cow::Borrowed(image), None)),
        }
    }
}

/// Name of the sub-voxel field.
pub const FIELD_NAME: &str = "subvoxel";

/// A voxel whose largest phase fraction is below `1 - MIXED_BELOW` is mixed.
pub const MIXED_BELOW: f32 = 1e-6;

/// Per-voxel phase fractions and interface normals of an image.
#[derive(Clone, Debug, PartialEq)]
pub struct Subvoxel {
    /// Number of phases `P` (the image's phase table).
    pub phases: usize,
    /// `P` fractions per voxel, phase order of the image's phase table.
    pub fractions: Vec<f32>,
    /// Unit normal per voxel, zero in pure voxels (and in mixed voxels without one).
    pub normals: Vec<[f32; 3]>,
}

impl Subvoxel {
    /// All voxels pure, as the labels say (`index_of_label` maps a label to its phase index).
    pub fn from_labels(image: &PhaseImage) -> Result<Subvoxel, String> {
        let index = phase_index(image)?;
        let p = image.phases.len();
        let mut fractions = vec![0.0f32; p * image.labels.len()];
        for (v, &l) in image.labels.iter().enumerate() {
            fractions[v * p + index[l as usize]] = 1.0;
        }
        Ok(Subvoxel {
            phases: p,
            fractions,
            normals: vec![[0.0; 3]; image.labels.len()],
        })
    }

    /// Fractions of voxel `v`.
    pub fn of(&self, v: usize) -> &[f32] {
        &self.fractions[v * self.phases..(v + 1) * self.phases]
    }

    /// Whether voxel `v` holds more than one phase.
    pub fn is_mixed(&self, v: usize) -> bool {
        self.of(v).iter().all(|&f| f < 1.0 - MIXED_BELOW)
    }

    /// Number of mixed voxels.
    pub fn mixed_count(&self) -> usize {
        (0..self.normals.len())
            .filter(|&v| self.is_mixed(v))
            .count()
    }

    /// The field that carries this description between stages.
    pub fn to_field(&self, grid: &Grid) -> Field {
        let c = self.phases + 3;
        let mut data = vec![0.0f32; c * self.normals.len()];
        data.par_chunks_mut(c).enumerate().for_each(|(v, d)| {
            d[..self.phases].copy_from_slice(self.of(v));
            d[self.phases..].copy_from_slice(&self.normals[v]);
        });
        Field::new(
            grid.clone(),
            FIELD_NAME,
            "1",
            ComponentConvention::Plain,
            FieldData::F32(data),
        )
        .expect("P + 3 components per voxel fill the grid")
    }

    /// Reads the field back, checked against the image it describes: same grid dims,
    /// `P + 3` components, finite fractions in [0, 1] summing to 1 (to 1e-3), normals of
    /// unit length or zero.
    pub fn from_field(field: &Field, image: &PhaseImage) -> Result<Subvoxel, String> {
        let p = image.phases.len();
        if field.grid.dims != image.grid.dims {
            return Err(format!(
                "the sub-voxel field is on a {:?} grid, the image on {:?}",
                field.grid.dims, image.grid.dims
            ));
        }
        if field.components != p + 3 {
            return Err(format!(
                "the sub-voxel field has {} components per voxel; an image of {p} phases \
                 needs {} (the {p} phase fractions in the image's phase order, then the \
                 normal x, y, z)",
                field.components,
                p + 3
            ));
        }
        let n = image.labels.len();
        let mut fractions = vec![0.0f32; p * n];
        let mut normals = vec![[0.0f32; 3]; n];
        for v in 0..n {
            let base = v * (p + 3);
            let mut sum = 0.0;
            for k in 0..p {
                let f = field.data.get(base + k);
                if !(f.is_finite() && (-1e-6..=1.0 + 1e-6).contains(&f)) {
                    return Err(format!(
                        "voxel {v}: phase fraction {f} of phase `{}` is not in [0, 1]",
                        image.phases[k].name
                    ));
                }
                fractions[v * p + k] = f.clamp(0.0, 1.0) as f32;
                sum += f;
            }
            if (sum - 1.0).abs() > 1e-3 {
                return Err(format!(
                    "voxel {v}: the phase fractions sum to {sum}, not 1"
                ));
            }
            let nv = [0, 1, 2].map(|a| field.data.get(base + p + a));
            let len = nv.iter().map(|x| x * x).sum::<f64>().sqrt();
            if !len.is_finite() || (len > 1e-6 && (len - 1.0).abs() > 1e-3) {
                return Err(format!(
                    "voxel {v}: the normal {nv:?} is neither zero nor of unit length"
                ));
            }
            normals[v] = nv.map(|x| x as f32);
        }
        Ok(Subvoxel {
            phases: p,
            fractions,
            normals,
        })
    }
}

/// `index[label]` = position of the label in the image's phase table; errors on a label
/// the table does not name.
pub fn phase_index(image: &PhaseImage) -> Result<[usize; 256], String> {
    let mut index = [usize::MAX; 256];
    for (k, ph) in image.phases.iter().enumerate() {
        index[ph.id as usize] = k;
    }
    let mut seen = [false; 256];
    for &l in &image.labels {
        seen[l as usize] = true;
    }
    for l in 0..256 {
        if seen[l] && index[l] == usize::MAX {
            return Err(format!("label {l} is not in the image's phase table"));
        }
    }
    Ok(index)
}

/// Neighbour index along one axis: wraps on periodic axes, clamps otherwise.
#[inline]
fn step(i: usize, d: isize, n: usize, periodic: bool) -> usize {
    let j = i as isize + d;
    if periodic {
        j.rem_euclid(n as isize) as usize
    } else {
        j.clamp(0, n as isize - 1) as usize
    }
}

/// Voxels next to (26-neighbourhood) a voxel of another label, or holding one: the only
/// ones an interface can cross when the labels are the phase at the voxel centres and no
/// feature is thinner than a voxel.
pub fn interface_candidates(grid: &Grid, labels: &[u8]) -> Vec<bool> {
    let [nx, ny, nz] = grid.dims;
    let per = grid.periodic;
    let mut out = vec![false; labels.len()];
    out.par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(z, plane)| {
            for y in 0..ny {
                for x in 0..nx {
                    let l = labels[grid.index(x, y, z)];
                    let mut differs = false;
                    'n: for dz in -1..=1 {
                        let zz = step(z, dz, nz, per[2]);
                        for dy in -1..=1 {
                            let yy = step(y, dy, ny, per[1]);
                            for dx in -1..=1 {
                                let xx = step(x, dx, nx, per[0]);
                                if labels[grid.index(xx, yy, zz)] != l {
                                    differs = true;
                                    break 'n;
                                }
                            }
                        }
                    }
                    plane[x + nx * y] = differs;
                }
            }
        });
    out
}

/// Sub-voxel description of an image made by a geometry that can be evaluated anywhere:
/// `phase_at(point)` gives the phase index (in `image.phases` order) at a point [m]. Every
/// voxel in [`interface_candidates`] is sampled at `samples^3` points (cell centres of a
/// regular sub-grid); the others keep their label. Normals as in the module doc.
pub fn sample<F>(image: &PhaseImage, samples: usize, phase_at: F) -> Result<Subvoxel, String>
where
    F: Fn([f64; 3]) -> usize + Sync,
{
    let grid = &image.grid;
    let cand = interface_candidates(grid, &image.labels);
    let [nx, ny, _] = grid.dims;
    let sampled: Vec<VoxelSamples> = (0..image.labels.len())
        .into_par_iter()
        .filter(|&v| cand[v])
        .map(|v| {
            let c = grid.voxel_center(v % nx, (v / nx) % ny, v / (nx * ny));
            (
                v,
                sample_voxel(c, grid.spacing, samples, image.phases.len(), &phase_at),
            )
        })
        .collect();
    from_samples(image, sampled)
}

/// What sampling one voxel gives: its index and, per phase, the share of sub-samples and
/// their first moment relative to the voxel centre [m].
pub type VoxelSamples = (usize, (Vec<f32>, Vec<[f64; 3]>));

/// Samples one voxel (centre `c`, edges `h`) at `samples^3` points: per phase (`phases` of
/// them) the share of points and their first moment about the centre.
pub fn sample_voxel(
    c: [f64; 3],
    h: [f64; 3],
    samples: usize,
    phases: usize,
    mut phase_at: impl FnMut([f64; 3]) -> usize,
) -> (Vec<f32>, Vec<[f64; 3]>) {
    let s = samples.max(1);
    if phases == 0 {
        return (vec![], vec![]);
    }
    let mut count = vec![0u32; phases];
    let mut moment = vec![[0.0f64; 3]; phases];
    for k in 0..s * s * s {
        let sub = [k % s, (k / s) % s, k / (s * s)];
        let off: [f64; 3] =
            std::array::from_fn(|a| ((sub[a] as f64 + 0.5) / s as f64 - 0.5) * h[a]);
        let ph = phase_at([c[0] + off[0], c[1] + off[1], c[2] + off[2]]).min(phases - 1);
        count[ph] += 1;
        for a in 0..3 {
            moment[ph][a] += off[a];
        }
    }
    let total = (s * s * s) as f32;
    (count.iter().map(|&c| c as f32 / total).collect(), moment)
}

/// The sub-voxel description from the samples of some voxels (the others keep their
/// label), normals as in the module doc. `sampled` in any order.
pub fn from_samples(
    image: &PhaseImage,
    mut sampled: Vec<VoxelSamples>,
) -> Result<Subvoxel, String> {
    let mut sv = Subvoxel::from_labels(image)?;
    let p = sv.phases;
    sampled.sort_by_key(|s| s.0);
    for (v, (f, _)) in &sampled {
        sv.fractions[v * p..(v + 1) * p].copy_from_slice(f);
    }
    set_normals(&image.grid, &mut sv, |v| {
        sampled
            .binary_search_by_key(&v, |s| s.0)
            .ok()
            .map(|i| sampled[i].1 .1.clone())
    });
    Ok(sv)
}

/// Coarsens a fine label image by `factor` per axis: each coarse voxel gets the fractions of
/// its `factor^3` fine voxels, the label of the most frequent (ties: the lower phase index),
/// and a normal as in the module doc. The way to give labels-only images (CT scans) composite
/// voxels. Dims must be multiples of `factor`.
pub fn coarsen(image: &PhaseImage, factor: usize) -> Result<(PhaseImage, Subvoxel), String> {
    let f = factor.max(1);
    let g = &image.grid;
    if g.dims.iter().any(|&d| d % f != 0) {
        return Err(format!(
            "the image's dims {:?} are not multiples of coarsen = {f}",
            g.dims
        ));
    }
    let index = phase_index(image)?;
    let p = image.phases.len();
    let cg = Grid {
        dims: g.dims.map(|d| d / f),
        spacing: g.spacing.map(|s| s * f as f64),
        origin: g.origin,
        periodic: g.periodic,
    };
    let [cx, cy, cz] = cg.dims;
    let nc = cx * cy * cz;
    // The fine voxel indices of coarse voxel v, and the offset of each from its centre.
    let block = |v: usize| {
        let (x, y, z) = (v % cx, (v / cx) % cy, v / (cx * cy));
        (0..f * f * f).map(move |k| {
            let (i, j, l) = (k % f, (k / f) % f, k / (f * f));
            let off: [f64; 3] =
                std::array::from_fn(|a| ([i, j, l][a] as f64 + 0.5) / f as f64 - 0.5);
            (g.index(x * f + i, y * f + j, z * f + l), off)
        })
    };
    // Flat outputs (1 + 4 P bytes per coarse voxel), written per voxel in parallel.
    let mut labels = vec![0u8; nc];
    let mut fractions = vec![0.0f32; nc * p];
    labels
        .par_iter_mut()
        .zip(fractions.par_chunks_mut(p))
        .enumerate()
        .for_each(|(v, (label, frac))| {
            let mut count = vec![0u32; p];
            for (fine, _) in block(v) {
                count[index[image.labels[fine] as usize]] += 1;
            }
            let best = (0..p)
                .max_by_key(|&k| (count[k], std::cmp::Reverse(k)))
                .unwrap_or(0);
            *label = image.phases[best].id;
            let total = (f * f * f) as f32;
            for (o, &c) in frac.iter_mut().zip(&count) {
                *o = c as f32 / total;
            }
        });
    let mut sv = Subvoxel {
        phases: p,
        fractions,
        normals: vec![[0.0; 3]; nc],
    };
    // First moments only where the fraction gradient vanishes (rare), from the fine voxels.
    set_normals(&cg, &mut sv, |v| {
        let mut moment = vec![[0.0f64; 3]; p];
        for (fine, off) in block(v) {
            let ph = index[image.labels[fine] as usize];
            for a in 0..3 {
                moment[ph][a] += off[a] * cg.spacing[a];
            }
        }
        Some(moment)
    });
    Ok((
        PhaseImage {
            grid: cg,
            labels,
            phases: image.phases.clone(),
        },
        sv,
    ))
}

/// The normal of every mixed voxel: `-grad phi_A` of its dominant phase A by the 3x3x3
/// Sobel difference over the neighbours' fractions, else (vanishing gradient) from the
/// first moments `moment_of(v)[phase]` of the voxel's own samples: the direction from the
/// dominant phase's centroid away from it, or towards the second phase's centroid.
fn set_normals<M>(grid: &Grid, sv: &mut Subvoxel, moment_of: M)
where
    M: Fn(usize) -> Option<Vec<[f64; 3]>> + Sync,
{
    let [nx, ny, nz] = grid.dims;
    let per = grid.periodic;
    let p = sv.phases;
    let h = grid.spacing;
    let frac = &sv.fractions;
    let normals: Vec<[f32; 3]> = (0..nx * ny * nz)
        .into_par_iter()
        .map(|v| {
            let f = &frac[v * p..(v + 1) * p];
            if !f.iter().all(|&x| x < 1.0 - MIXED_BELOW) {
                return [0.0; 3];
            }
            let a = (0..p)
                .max_by(|&i, &j| f[i].total_cmp(&f[j]).then(j.cmp(&i)))
                .unwrap_or(0);
            let (x, y, z) = (v % nx, (v / nx) % ny, v / (nx * ny));
            let w = [1.0, 2.0, 1.0];
            let mut g = [0.0f64; 3];
            for dz in -1isize..=1 {
                let zz = step(z, dz, nz, per[2]);
                for dy in -1isize..=1 {
                    let yy = step(y, dy, ny, per[1]);
                    for dx in -1isize..=1 {
                        let xx = step(x, dx, nx, per[0]);
                        let phi = frac[(xx + nx * (yy + ny * zz)) * p + a] as f64;
                        let d = [dx, dy, dz];
                        for ax in 0..3 {
                            if d[ax] == 0 {
                                continue;
                            }
                            let (b, c) = ((ax + 1) % 3, (ax + 2) % 3);
                            let weight = w[(d[b] + 1) as usize] * w[(d[c] + 1) as usize];
                            g[ax] += d[ax] as f64 * weight * phi / h[ax];
                        }
                    }
                }
            }
            let mut n = g.map(|c| -c);
            let len = n.iter().map(|c| c * c).sum::<f64>().sqrt();
            let scale = 1.0 / h.iter().cloned().fold(f64::INFINITY, f64::min);
            if len <= 1e-6 * scale {
                n = [0.0; 3];
                if let Some(m) = moment_of(v) {
                    // Away from the dominant phase's centroid, else towards the second's.
                    let second = (0..p)
                        .filter(|&k| k != a)
                        .max_by(|&i, &j| f[i].total_cmp(&f[j]))
                        .unwrap_or(a);
                    let ma = m[a].map(|c| -c);
                    let la = ma.iter().map(|c| c * c).sum::<f64>().sqrt();
                    let mb = m[second];
                    let lb = mb.iter().map(|c| c * c).sum::<f64>().sqrt();
                    n = if la >= lb { ma } else { mb };
                }
            }
            let len = n.iter().map(|c| c * c).sum::<f64>().sqrt();
            if len > 0.0 && len.is_finite() {
                n.map(|c| (c / len) as f32)
            } else {
                [0.0; 3]
            }
        })
        .collect();
    sv.normals = normals;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Phase;

    fn image(dims: [usize; 3], h: f64, labels: Vec<u8>) -> PhaseImage {
        PhaseImage {
            grid: Grid {
                dims,
                spacing: [h; 3],
                origin: [0.0; 3],
                periodic: [true; 3],
            },
            labels,
            phases: vec![
                Phase {
                    id: 0,
                    name: "pore".into(),
                },
                Phase {
                    id: 1,
                    name: "grain".into(),
                },
            ],
        }
    }

    /// A plane `n . x = d` through a periodic box: the sampled fractions of every voxel
    /// against the exact volume fraction of the voxel below the plane (computed by a fine
    /// brute-force count), and the normals against `n` within 5 degrees.
    #[test]
    fn plane_fractions_and_normals() {
        let nrm = {
            let v = [1.0f64, 2.0, 3.0];
            let l = (14.0f64).sqrt();
            v.map(|c| c / l)
        };
        let dims = [12, 12, 12];
        let h = 1.0;
        let d = 9.6;
        // Solid where n . x < d (not periodic-consistent across the box, so mark the box
        // as not periodic).
        let below = |p: [f64; 3]| nrm[0] * p[0] + nrm[1] * p[1] + nrm[2] * p[2] < d;
        let mut img = image(dims, h, vec![0; 1728]);
        img.grid.periodic = [false; 3];
        for z in 0..12 {
            for y in 0..12 {
                for x in 0..12 {
                    let c = img.grid.voxel_center(x, y, z);
                    img.labels[img.grid.index(x, y, z)] = below(c) as u8;
                }
            }
        }
        let sv = sample(&img, 8, |p| below(p) as usize).unwrap();
        let mut mixed = 0;
        for z in 1..11 {
            for y in 1..11 {
                for x in 1..11 {
                    let v = img.grid.index(x, y, z);
                    // brute force fraction at 40^3 points
                    let c = img.grid.voxel_center(x, y, z);
                    let m = 40;
                    let mut cnt = 0;
                    for k in 0..m {
                        for j in 0..m {
                            for i in 0..m {
                                let o = [i, j, k].map(|t| (t as f64 + 0.5) / m as f64 - 0.5);
                                if below([c[0] + o[0], c[1] + o[1], c[2] + o[2]]) {
                                    cnt += 1;
                                }
                            }
                        }
                    }
                    let exact = cnt as f64 / (m * m * m) as f64;
                    let got = sv.of(v)[1] as f64;
                    assert!((got - exact).abs() < 0.04, "voxel {v}: {got} vs {exact}");
                    if sv.is_mixed(v) && exact > 0.05 && exact < 0.95 {
                        mixed += 1;
                        let n = sv.normals[v];
                        // normal points away from the dominant phase; compare up to sign
                        let cos =
                            (n[0] as f64 * nrm[0] + n[1] as f64 * nrm[1] + n[2] as f64 * nrm[2])
                                .abs();
                        assert!(cos > (5f64).to_radians().cos(), "voxel {v}: cos {cos}");
                    }
                }
            }
        }
        assert!(mixed > 50, "{mixed} mixed voxels tested");
    }

    /// Coarsening keeps the phase volumes exactly and round-trips through the field.
    #[test]
    fn coarsen_conserves_volume_and_round_trips() {
        let dims = [16, 16, 16];
        let mut labels = vec![0u8; 4096];
        for z in 0..16 {
            for y in 0..16 {
                for x in 0..16 {
                    let r2 = [x, y, z]
                        .map(|t| t as f64 + 0.5 - 8.0)
                        .iter()
                        .map(|c| c * c)
                        .sum::<f64>();
                    labels[x + 16 * (y + 16 * z)] = (r2 < 36.0) as u8;
                }
            }
        }
        let img = image(dims, 1e-6, labels);
        let (coarse, sv) = coarsen(&img, 4).unwrap();
        assert_eq!(coarse.grid.dims, [4, 4, 4]);
        assert_eq!(coarse.grid.spacing, [4e-6; 3]);
        let fine_solid = img.labels.iter().filter(|&&l| l == 1).count() as f64;
        let coarse_solid: f64 = (0..64).map(|v| sv.of(v)[1] as f64 * 64.0).sum();
        assert!((fine_solid - coarse_solid).abs() < 1e-3);
        // normals of mixed voxels point outward from the sphere (away from solid)
        for v in 0..64 {
            if sv.is_mixed(v) && sv.of(v)[1] > 0.5 {
                let c = coarse.grid.voxel_center(v % 4, (v / 4) % 4, v / 16);
                let r = c.map(|t| t - 8e-6);
                let dot: f64 = (0..3).map(|a| r[a] * sv.normals[v][a] as f64).sum();
                assert!(dot > 0.0, "voxel {v}");
            }
        }
        let back = Subvoxel::from_field(&sv.to_field(&coarse.grid), &coarse).unwrap();
        assert_eq!(back, sv);
        assert!(coarsen(&img, 3).is_err());
    }

    #[test]
    fn bad_fields_are_refused() {
        let img = image([2, 1, 1], 1.0, vec![0, 1]);
        let sv = Subvoxel::from_labels(&img).unwrap();
        let mut f = sv.to_field(&img.grid);
        assert!(Subvoxel::from_field(&f, &img).is_ok());
        if let FieldData::F32(d) = &mut f.data {
            d[0] = 0.7; // fractions of voxel 0 now sum to 0.7
        }
        let e = Subvoxel::from_field(&f, &img).unwrap_err();
        assert!(e.contains("sum to"), "{e}");
        if let FieldData::F32(d) = &mut f.data {
            d[0] = 1.0;
            d[2] = 0.5; // normal of length 0.5
        }
        let e = Subvoxel::from_field(&f, &img).unwrap_err();
        assert!(e.contains("unit length"), "{e}");
    }
}
