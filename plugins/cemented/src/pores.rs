//! `analysis.pores`: single pores and single voids by flood fill, their volume statistics,
//! the matrix saturation S_m and the partial coordination numbers (Heinze et al. 2020,
//! sec. III, eqs. 8-9).

use crate::common::{sub, Particles, LARGE, MATRIX, SMALL, VOID};
use grainpipe_analysis::components::{label_components, Labeling, NONE};
use grainpipe_core::spatial::CellList;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, Grid, InputMetas, Inputs, Outputs, PhaseImage,
    PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
};
use std::f64::consts::PI;

#[params]
pub struct PoresParams {
    /// Contact horizon: two particles whose surfaces are at most this far apart are in
    /// contact (eq. 9), for the coordination numbers and for closing pores; absent = three
    /// voxels of the image (the peridynamic horizon h = 3 dx).
    pub horizon: Option<Q<Length>>,
    /// Close the gap of every contact with a one-voxel wall, so that a single pore is the
    /// space enclosed by a closed chain of contiguous particles (sec. III) even where two
    /// particles in contact do not touch on the grid.
    #[param(default = true)]
    pub close_contacts: bool,
    /// Count pores and voids that touch the image border (cut by the crop); by default they
    /// are listed but left out of the statistics.
    #[param(default = false)]
    pub include_border: bool,
    /// Bins of the volume PDFs.
    #[param(default = 30)]
    pub bins: usize,
}

/// One connected region.
#[derive(Clone, Debug, PartialEq)]
pub struct Region {
    pub voxels: u64,
    pub volume: f64,
    pub border: bool,
}

/// Mean, standard deviation (population) and coefficient of variation.
pub fn moments(v: &[f64]) -> (f64, f64, f64) {
    if v.is_empty() {
        return (0.0, 0.0, 0.0);
    }
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let s = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n).sqrt();
    (m, s, if m > 0.0 { s / m } else { 0.0 })
}

/// A histogram density on [0, max] with `bins` bins: (centres, density), sum(density * width) = 1.
pub fn pdf(v: &[f64], bins: usize) -> (Vec<f64>, Vec<f64>) {
    let max = v.iter().cloned().fold(0.0, f64::max);
    let w = if max > 0.0 { max / bins as f64 } else { 1.0 };
    let mut h = vec![0.0; bins];
    for &x in v {
        let k = ((x / w) as usize).min(bins - 1);
        h[k] += 1.0;
    }
    let n = v.len().max(1) as f64;
    (
        (0..bins).map(|k| (k as f64 + 0.5) * w).collect(),
        h.into_iter().map(|c| c / (n * w)).collect(),
    )
}

/// Contacts (i < j) with surface distance at most `horizon`, in increasing (i, j) order.
pub fn contacts(
    parts: &Particles,
    domain: &grainpipe_core::Domain,
    horizon: f64,
) -> Vec<(usize, usize, [f64; 3])> {
    let r_max = parts.radius.iter().cloned().fold(0.0, f64::max);
    let mut cells = CellList::new(
        domain.min,
        domain.size(),
        domain.periodic,
        2.0 * r_max + horizon,
    );
    for (i, c) in parts.pos.iter().enumerate() {
        cells.insert(i as u32, *c);
    }
    let mut out = Vec::new();
    let mut near = Vec::new();
    for i in 0..parts.len() {
        near.clear();
        cells.visit(
            parts.pos[i],
            parts.radius[i] + r_max + horizon,
            |j, shift| {
                let j = j as usize;
                if j != i {
                    let cj = [0, 1, 2].map(|k| parts.pos[j][k] + shift[k]);
                    let d = sub(cj, parts.pos[i]);
                    let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    if dist - parts.radius[i] - parts.radius[j] <= horizon {
                        near.push((j, cj));
                    }
                }
                true
            },
        );
        near.sort_by(|a, b| a.0.cmp(&b.0).then(a.1[0].total_cmp(&b.1[0])));
        for &(j, cj) in &near {
            if j > i {
                out.push((i, j, cj));
            }
        }
    }
    out
}

/// Partial coordination numbers (eq. 8): Z[a][b] = contacts of class-a particles with class-b
/// particles / number of class-a particles, over the particles with `counted[i]`; the
/// partners may be any particle. Index 0 = large, 1 = small. Also returns the counts n_a.
pub fn partial_coordination(
    parts: &Particles,
    pairs: &[(usize, usize, [f64; 3])],
    counted: &[bool],
) -> ([[f64; 2]; 2], [usize; 2]) {
    let k = |c: u8| usize::from(c == SMALL);
    let mut n = [0usize; 2];
    for i in 0..parts.len() {
        if counted[i] {
            n[k(parts.class[i])] += 1;
        }
    }
    let mut c = [[0usize; 2]; 2];
    for &(i, j, _) in pairs {
        if counted[i] {
            c[k(parts.class[i])][k(parts.class[j])] += 1;
        }
        if counted[j] {
            c[k(parts.class[j])][k(parts.class[i])] += 1;
        }
    }
    let z = [0, 1].map(|a| [0, 1].map(|b| c[a][b] as f64 / n[a].max(1) as f64));
    (z, n)
}

/// Marks the voxels whose centre lies within `width` of the segment between the facing
/// surface points of every contact (extended one voxel into both particles), so the flood
/// fill cannot pass between two particles in contact.
pub fn contact_walls(
    grid: &Grid,
    parts: &Particles,
    pairs: &[(usize, usize, [f64; 3])],
) -> Vec<bool> {
    let mut wall = vec![false; grid.voxel_count()];
    let dx = grid.spacing[0];
    let width = 0.75 * dx;
    for &(i, _j, cj) in pairs {
        let ci = parts.pos[i];
        let d = sub(cj, ci);
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if len == 0.0 {
            continue;
        }
        let u = d.map(|x| x / len);
        let ri = parts.radius[i];
        let rj = parts.radius[_j];
        let a = [0, 1, 2].map(|k| ci[k] + (ri - dx) * u[k]);
        let b = [0, 1, 2].map(|k| cj[k] - (rj - dx) * u[k]);
        let lo = [0, 1, 2].map(|k| a[k].min(b[k]) - width);
        let hi = [0, 1, 2].map(|k| a[k].max(b[k]) + width);
        let range = |k: usize| {
            let f = |x: f64| (x - grid.origin[k]) / grid.spacing[k] - 0.5;
            let l = f(lo[k]).ceil().max(0.0) as usize;
            let h = f(hi[k]).floor();
            if h < 0.0 {
                return l..l;
            }
            l..((h as usize) + 1).min(grid.dims[k])
        };
        let ab = sub(b, a);
        let ab2 = ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2];
        for z in range(2) {
            for y in range(1) {
                for x in range(0) {
                    let p = grid.voxel_center(x, y, z);
                    let q = sub(p, a);
                    let t = if ab2 > 0.0 {
                        ((q[0] * ab[0] + q[1] * ab[1] + q[2] * ab[2]) / ab2).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    let e = [0, 1, 2].map(|k| q[k] - t * ab[k]);
                    if e[0] * e[0] + e[1] * e[1] + e[2] * e[2] <= width * width {
                        wall[grid.index(x, y, z)] = true;
                    }
                }
            }
        }
    }
    wall
}

/// Connected regions (face connectivity: 4 in 2-D, 6 in 3-D) of the voxels with `member`,
/// where voxels in `wall` separate regions; wall voxels of the phase are then given to an
/// adjacent region so that the volumes add up to the phase volume. `border` = touches a face
/// of the image along the first `dim` axes.
pub fn regions(grid: &Grid, dim: usize, member: &[bool], wall: &[bool]) -> Vec<Region> {
    let lab: Labeling = label_components(grid.dims, [false; 3], |i| member[i] && !wall[i]);
    let mut ids = lab.ids;
    let mut vox: Vec<u64> = lab.components.iter().map(|c| c.voxels).collect();
    let mut border: Vec<bool> = lab
        .components
        .iter()
        .map(|c| (0..dim).any(|a| c.touches[a][0] || c.touches[a][1]))
        .collect();
    let [nx, ny, nz] = grid.dims;
    // Wall voxels join a neighbouring region (passes until nothing changes; walls are thin).
    loop {
        let mut changed = false;
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    let i = grid.index(x, y, z);
                    if !(member[i] && wall[i] && ids[i] == NONE) {
                        continue;
                    }
                    let mut nb = Vec::with_capacity(6);
                    if x > 0 {
                        nb.push(i - 1);
                    }
                    if x + 1 < nx {
                        nb.push(i + 1);
                    }
                    if y > 0 {
                        nb.push(i - nx);
                    }
                    if y + 1 < ny {
                        nb.push(i + nx);
                    }
                    if z > 0 {
                        nb.push(i - nx * ny);
                    }
                    if z + 1 < nz {
                        nb.push(i + nx * ny);
                    }
                    if let Some(&k) = nb.iter().find(|&&k| ids[k] != NONE) {
                        ids[i] = ids[k];
                        vox[ids[k] as usize] += 1;
                        let on_face = (x == 0 || x + 1 == nx)
                            || (y == 0 || y + 1 == ny)
                            || (dim == 3 && (z == 0 || z + 1 == nz));
                        if on_face {
                            border[ids[k] as usize] = true;
                        }
                        changed = true;
                    }
                }
            }
        }
        if !changed {
            break;
        }
    }
    // Wall voxels enclosed only by walls and particles form regions of their own.
    let rest = label_components(grid.dims, [false; 3], |i| member[i] && ids[i] == NONE);
    let vv = grid.voxel_volume() / if dim == 2 { grid.spacing[2] } else { 1.0 };
    let mut out: Vec<Region> = vox
        .iter()
        .zip(&border)
        .map(|(&v, &b)| Region {
            voxels: v,
            volume: v as f64 * vv,
            border: b,
        })
        .collect();
    out.extend(rest.components.iter().map(|c| Region {
        voxels: c.voxels,
        volume: c.voxels as f64 * vv,
        border: (0..dim).any(|a| c.touches[a][0] || c.touches[a][1]),
    }));
    out
}

pub struct Pores;

impl TypedStage for Pores {
    type Params = PoresParams;
    type Plan = ();

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "analysis.pores",
            "1.0.0",
            "Texture of a cemented granular sample (Heinze et al., Phys. Rev. E 101, 052901 \
             (2020), sec. III). A single pore is a connected region of interstitial space \
             (matrix or void, everything not particle) enclosed by a closed chain of \
             contiguous particles; a single void is a connected region of empty space \
             enclosed by matrix, or matrix and particles. Both are labelled by flood fill \
             (face connectivity) on the phase image (labels 0 pore, i.e. the paper's empty space, \
             1 large, 2 small, 3 matrix), with \
             the gaps of particles in contact (surface distance <= horizon, eq. 9) closed by \
             one-voxel walls. Reports per-region volumes (also normalised by the mean large \
             particle area pi r_L^2, or volume in 3-D), their PDFs, mean, standard deviation \
             and coefficient of variation, the phase fractions, the matrix saturation \
             S_m = rho_m / (1 - rho_p) and the partial coordination numbers Z_ll, Z_ls, Z_sl, \
             Z_ss (eq. 8) of the particles whose centre lies in the image.",
        )
        .inputs(vec![
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "labels 0 = pore (empty space), 1 = large, 2 = small, 3 = matrix",
            ),
            PortSpec::new(
                "packing",
                ArtifactKind::Packing,
                "the particles the image was made of",
            ),
        ])
        .outputs(vec![
            PortSpec::new(
                "summary",
                ArtifactKind::Table,
                "one row: counts, moments, S_m, Z",
            ),
            PortSpec::new("pores", ArtifactKind::Table, "one row per single pore"),
            PortSpec::new("voids", ArtifactKind::Table, "one row per single void"),
            PortSpec::new(
                "pdfs",
                ArtifactKind::Table,
                "PDFs of normalised pore and void volumes",
            ),
        ])
    }

    fn preflight(&self, p: &PoresParams, inputs: &InputMetas) -> Result<Preflight, StageError> {
        if let Some(h) = p.horizon {
            if !(h.si().is_finite() && h.si() >= 0.0) {
                return Err(StageError::param("horizon", "must be a length >= 0"));
            }
        }
        if p.bins == 0 || p.bins > 100_000 {
            return Err(StageError::param("bins", "must be in [1, 100000]"));
        }
        let voxels = inputs
            .get("image")
            .and_then(|m| m.grid.as_ref())
            .map(|g| g.voxel_count() as u64)
            .unwrap_or(0);
        let particles = inputs.get("packing").map(|m| m.count_estimate).unwrap_or(0);
        // Per voxel: the pore, void and contact-wall masks (3 x 1 B) and the component ids of
        // the two labelings held at once (2 x 4 B), plus their per-component tables (below a
        // byte per voxel). Per particle: the particles (33 B), the cell list (~32 B), and the
        // contacts within the horizon (a `(usize, usize, [f64; 3])` of 40 B; up to 4 per
        // particle where small disks ring a large one, in a vector that may have doubled).
        let memory = 12 * voxels + (33 + 32 + 4 * 2 * 40) * particles + (64 << 10);
        Ok(Preflight::from_info(&self.info(), memory)
            .announce(
                "summary",
                ArtifactMeta::of(ArtifactKind::Table).with_count(1, Some([1, 1])),
            )
            .announce(
                "pdfs",
                ArtifactMeta::of(ArtifactKind::Table)
                    .with_count(p.bins as u64, Some([p.bins as u64; 2])),
            ))
    }

    fn run(
        &self,
        p: &PoresParams,
        _plan: &(),
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let img = grainpipe_core::stage::input(inputs, "image", Artifact::as_phase_image)?;
        let pk = grainpipe_core::stage::input(inputs, "packing", Artifact::as_packing)?;
        let parts = Particles::from_packing(pk, "packing")?;
        if let Some(bad) = img.labels.iter().find(|&&l| l > MATRIX) {
            return Err(StageError::input(
                "image",
                format!("label {bad}: expected 0 pore, 1 large, 2 small, 3 matrix"),
            ));
        }
        let a = analyse(img, &parts, &pk.domain, p)?;
        ctx.progress(1, 1)?;
        Ok(a)
    }
}

/// The whole analysis (the stage's run without the framework).
pub fn analyse(
    img: &PhaseImage,
    parts: &Particles,
    domain: &grainpipe_core::Domain,
    p: &PoresParams,
) -> Result<Outputs, StageError> {
    let g = &img.grid;
    let dim = if g.dims[2] == 1 { 2 } else { 3 };
    if dim != parts.dim {
        return Err(StageError::input(
            "image",
            format!("a {dim}-D image of a {}-D packing", parts.dim),
        ));
    }
    let horizon = p.horizon.map(|h| h.si()).unwrap_or(3.0 * g.spacing[0]);
    let pairs = contacts(parts, domain, horizon);
    let wall = if p.close_contacts {
        contact_walls(g, parts, &pairs)
    } else {
        vec![false; g.voxel_count()]
    };
    let pore_member: Vec<bool> = img
        .labels
        .iter()
        .map(|&l| l == VOID || l == MATRIX)
        .collect();
    let void_member: Vec<bool> = img.labels.iter().map(|&l| l == VOID).collect();
    let pores = regions(g, dim, &pore_member, &wall);
    let voids = regions(g, dim, &void_member, &wall);
    // Normalisation by the mean large-particle measure pi r_L^2 (sec. III), 4/3 pi r_L^3 in 3-D.
    let large: Vec<f64> = (0..parts.len())
        .filter(|&i| parts.class[i] == LARGE)
        .map(|i| parts.radius[i])
        .collect();
    let r_l = if large.is_empty() {
        0.0
    } else {
        large.iter().sum::<f64>() / large.len() as f64
    };
    let unit_volume = if dim == 2 {
        PI * r_l * r_l
    } else {
        4.0 / 3.0 * PI * r_l.powi(3)
    };
    let norm = |v: f64| {
        if unit_volume > 0.0 {
            v / unit_volume
        } else {
            0.0
        }
    };
    let counted = |rs: &[Region]| -> Vec<f64> {
        rs.iter()
            .filter(|r| p.include_border || !r.border)
            .map(|r| norm(r.volume))
            .collect()
    };
    let pv = counted(&pores);
    let vv = counted(&voids);
    let (pm, ps, pcv) = moments(&pv);
    let (vm, vs, vcv) = moments(&vv);
    let n = img.labels.len() as f64;
    let frac = |l: u8| img.labels.iter().filter(|&&x| x == l).count() as f64 / n;
    let rho_p = frac(LARGE) + frac(SMALL);
    let rho_m = frac(MATRIX);
    let s_m = if rho_p < 1.0 {
        rho_m / (1.0 - rho_p)
    } else {
        0.0
    };
    // Particles whose centre lies in the image (the cropped sample) are counted.
    let ext = g.extent();
    let counted_p: Vec<bool> = parts
        .pos
        .iter()
        .map(|c| (0..dim).all(|a| c[a] >= g.origin[a] && c[a] < g.origin[a] + ext[a]))
        .collect();
    let (z, nc) = partial_coordination(parts, &pairs, &counted_p);
    let z_l = z[0][0] + z[0][1];
    let z_s = z[1][0] + z[1][1];
    let unit = if dim == 2 { "m^2" } else { "m^3" };
    let summary = Table::new("pores_summary")
        .with_i64("n_pores", "", vec![pv.len() as i64])
        .with_i64(
            "n_pores_border",
            "",
            vec![pores.iter().filter(|r| r.border).count() as i64],
        )
        .with_f64("pore_mean", "", vec![pm])
        .with_f64("pore_std", "", vec![ps])
        .with_f64("pore_cv", "", vec![pcv])
        .with_i64("n_voids", "", vec![vv.len() as i64])
        .with_i64(
            "n_voids_border",
            "",
            vec![voids.iter().filter(|r| r.border).count() as i64],
        )
        .with_f64("void_mean", "", vec![vm])
        .with_f64("void_std", "", vec![vs])
        .with_f64("void_cv", "", vec![vcv])
        .with_f64("unit_volume", unit, vec![unit_volume])
        .with_f64("rho_particles", "", vec![rho_p])
        .with_f64("rho_large", "", vec![frac(LARGE)])
        .with_f64("rho_small", "", vec![frac(SMALL)])
        .with_f64("rho_matrix", "", vec![rho_m])
        .with_f64("rho_void", "", vec![frac(VOID)])
        .with_f64("s_m", "", vec![s_m])
        .with_f64("horizon", "m", vec![horizon])
        .with_i64("n_large", "", vec![nc[0] as i64])
        .with_i64("n_small", "", vec![nc[1] as i64])
        .with_f64("z_ll", "", vec![z[0][0]])
        .with_f64("z_ls", "", vec![z[0][1]])
        .with_f64("z_sl", "", vec![z[1][0]])
        .with_f64("z_ss", "", vec![z[1][1]])
        .with_f64("z_l", "", vec![z_l])
        .with_f64("z_s", "", vec![z_s])
        .with_f64("z", "", vec![0.5 * (z_l + z_s)]);
    let table = |name: &str, rs: &[Region]| {
        Table::new(name)
            .with_i64("id", "", (0..rs.len() as i64).collect())
            .with_i64("voxels", "", rs.iter().map(|r| r.voxels as i64).collect())
            .with_f64("volume", unit, rs.iter().map(|r| r.volume).collect())
            .with_f64(
                "normalized_volume",
                "",
                rs.iter().map(|r| norm(r.volume)).collect(),
            )
            .with_i64("border", "", rs.iter().map(|r| r.border as i64).collect())
    };
    let (pc, pd) = pdf(&pv, p.bins);
    let (vc, vd) = pdf(&vv, p.bins);
    let pdfs = Table::new("pores_pdfs")
        .with_f64("pore_volume", "", pc)
        .with_f64("pore_pdf", "", pd)
        .with_f64("void_volume", "", vc)
        .with_f64("void_pdf", "", vd);
    let mut out = Outputs::new();
    out.insert("summary".into(), Artifact::Table(summary));
    out.insert("pores".into(), Artifact::Table(table("pores", &pores)));
    out.insert("voids".into(), Artifact::Table(table("voids", &voids)));
    out.insert("pdfs".into(), Artifact::Table(pdfs));
    Ok(out)
}
