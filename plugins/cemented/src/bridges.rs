//! `binder.bridges`: trapezoidal matrix bridges between neighbouring particles (Topin et al.
//! 2008, as used in sec. II.B of Heinze et al. 2020), rasterised with the particles to a
//! phase image of the central square (cube) of the sample.

use crate::common::{phases, sub, Particles, LARGE, MATRIX, SMALL, VOID};
use grainpipe_core::raster::SphereRaster;
use grainpipe_core::spatial::CellList;
use grainpipe_core::units::{Length, Q};
use grainpipe_core::{
    params, Artifact, ArtifactKind, ArtifactMeta, ComponentConvention, Field, FieldData, Grid,
    InputMetas, Inputs, Outputs, PhaseImage, PortSpec, Preflight, RunContext, StageError,
    StageInfo, Table, TypedStage, WorldSphere,
};

/// Largest image this stage writes (voxels).
pub const MAX_VOXELS: u64 = 1 << 31;

#[params]
pub struct BridgesParams {
    /// 2 for a disk sample (one voxel layer through z = 0), 3 for spheres; must match the
    /// packing (its `disk` attribute).
    #[param(default = 2)]
    pub dimension: u32,
    /// Bridge base width as a fraction of the particle radius: w_i = eta r_i (0.2 to 1.0 in
    /// the paper).
    #[param(default = 0.4)]
    pub eta: f64,
    /// Pairs whose surfaces are at most this far apart get a bridge (the paper's l); absent
    /// = three voxels, the peridynamic horizon h = 3 dx.
    pub max_gap: Option<Q<Length>>,
    /// Edge of the cropped central square (cube); absent = crop_fraction of the box edge.
    /// Give it to announce the image grid before running (peridynamics needs it).
    pub crop_size: Option<Q<Length>>,
    /// Crop edge relative to the shortest box edge, used when crop_size is absent.
    #[param(default = 0.8)]
    pub crop_fraction: f64,
    /// Centre of the crop; packing.poisson_disk centres its box on the origin and
    /// dem.compact keeps it there.
    #[param(default = [Q::new(0.0); 3])]
    pub crop_center: [Q<Length>; 3],
    /// Voxels along the crop edge (1024 in the paper); ignored when voxel_size is given.
    #[param(default = 1024)]
    pub resolution: usize,
    /// Voxel edge; overrides resolution.
    pub voxel_size: Option<Q<Length>>,
    /// Sub-samples per voxel edge; a voxel takes the phase covering most of its sub-samples
    /// (1 = voxel centres only).
    #[param(default = 3)]
    pub supersampling: u32,
}

/// A bridge: the frustum (trapezoid in 2-D) from centre `a` (half-width `ha`) to centre `b`
/// (half-width `hb`), eq. of Topin et al.: w = eta r at each base.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bridge {
    pub a: [f64; 3],
    pub b: [f64; 3],
    pub ha: f64,
    pub hb: f64,
}

impl Bridge {
    /// Whether `p` lies in the bridge: its projection on the axis falls between the two
    /// centres and its distance from the axis is below the linearly varying half-width.
    #[inline]
    pub fn contains(&self, p: [f64; 3]) -> bool {
        let u = sub(self.b, self.a);
        let len2 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2];
        let q = sub(p, self.a);
        let t = (q[0] * u[0] + q[1] * u[1] + q[2] * u[2]) / len2;
        if !(0.0..=1.0).contains(&t) {
            return false;
        }
        let perp = [0, 1, 2].map(|k| q[k] - t * u[k]);
        let w = self.ha + (self.hb - self.ha) * t;
        perp[0] * perp[0] + perp[1] * perp[1] + perp[2] * perp[2] <= w * w
    }
    /// Half the axis length plus the larger half-width: every point of the bridge lies within
    /// this distance of the axis midpoint.
    pub fn bounding_radius(&self) -> f64 {
        let d = sub(self.b, self.a);
        0.5 * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() + self.ha.max(self.hb)
    }
    pub fn midpoint(&self) -> [f64; 3] {
        [0, 1, 2].map(|k| 0.5 * (self.a[k] + self.b[k]))
    }
}

/// A cement bridge spans a gap smaller than the particles it joins (the paper's l is the
/// horizon, three voxels). `max_gap: 1` (1 m) joined every pair of the sample: minutes of
/// search and a solid block instead of bridges. A gap wider than the largest particle's
/// diameter is refused.
fn check_gap(max_gap: f64, largest_radius: f64) -> Result<(), StageError> {
    if max_gap > 2.0 * largest_radius {
        return Err(StageError::param(
            "max_gap",
            format!(
                "{} is wider than the largest particle ({} across): a cement bridge joins \
                 near neighbours (the paper's l is the horizon, three voxels; leave max_gap out \
                 for that)",
                grainpipe_core::units::format_length(max_gap),
                grainpipe_core::units::format_length(2.0 * largest_radius)
            ),
        ));
    }
    Ok(())
}

/// Memory per particle of the stage [bytes]: the particles read from the packing (33 B), the
/// spheres of the raster (`WorldSphere`) and its bins (8 B for each of the at most 4 x 4
/// blocks a disk spans; a sphere up to 4 x 4 x 4), the cell list of the bridge search and of
/// the bridges (2 x 24 B), and the bridges: a particle bridges at most ~6 neighbours within
/// the gap (3 pairs per particle), each a `Bridge` in a vector that may have doubled.
fn per_particle_bytes() -> u64 {
    33 + std::mem::size_of::<WorldSphere>() as u64
        + 8 * 64
        + 2 * 24
        + 3 * 2 * std::mem::size_of::<Bridge>() as u64
}

/// Bridges between every pair of particles whose surface gap is at most `max_gap`
/// (sec. II.B), pairs in increasing (i, j) order. Periodic partners are taken at their
/// nearest image. `poll(done, total)` is called every 1024 particles and may stop the search
/// (an interrupt) by returning an error.
pub fn find_bridges<E>(
    parts: &Particles,
    domain: &grainpipe_core::Domain,
    eta: f64,
    max_gap: f64,
    mut poll: impl FnMut(u64, u64) -> Result<(), E>,
) -> Result<Vec<Bridge>, E> {
    let r_max = parts.radius.iter().cloned().fold(0.0, f64::max);
    let mut cells = CellList::new(
        domain.min,
        domain.size(),
        domain.periodic,
        2.0 * r_max + max_gap,
    );
    for (i, c) in parts.pos.iter().enumerate() {
        cells.insert(i as u32, *c);
    }
    let mut out = Vec::new();
    let mut near: Vec<(usize, [f64; 3])> = Vec::new();
    for i in 0..parts.len() {
        if i % 1024 == 0 {
            poll(i as u64, parts.len() as u64)?;
        }
        let (ci, ri) = (parts.pos[i], parts.radius[i]);
        near.clear();
        cells.visit(ci, ri + r_max + max_gap, |j, shift| {
            let j = j as usize;
            if j > i {
                let cj = [0, 1, 2].map(|k| parts.pos[j][k] + shift[k]);
                let d = sub(cj, ci);
                let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                if dist - ri - parts.radius[j] <= max_gap {
                    near.push((j, cj));
                }
            }
            true
        });
        near.sort_by(|x, y| x.0.cmp(&y.0).then(x.1[0].total_cmp(&y.1[0])));
        for &(j, cj) in &near {
            out.push(Bridge {
                a: ci,
                b: cj,
                ha: 0.5 * eta * ri,
                hb: 0.5 * eta * parts.radius[j],
            });
        }
    }
    Ok(out)
}

/// The plan: the image grid when it is known before running.
#[derive(Clone, Debug)]
pub struct Plan {
    pub grid: Option<Grid>,
}

/// The crop grid of edge `edge` centred on `c`, voxel `voxel`; in 2-D one layer through z = c_z.
pub fn crop_grid(dim: usize, c: [f64; 3], edge: f64, voxel: f64) -> Grid {
    let h = 0.5 * edge;
    let n = (edge / voxel).round().max(1.0);
    let dx = edge / n;
    let hz = if dim == 2 { 0.5 * dx } else { h };
    Grid::tiling(
        [c[0] - h, c[1] - h, c[2] - hz],
        [c[0] + h, c[1] + h, c[2] + hz],
        [false; 3],
        dx,
    )
}

impl BridgesParams {
    fn voxel_for(&self, edge: f64) -> f64 {
        match self.voxel_size {
            Some(v) => v.si(),
            None => edge / self.resolution as f64,
        }
    }

    fn check(&self) -> Result<usize, StageError> {
        let dim = match self.dimension {
            2 => 2,
            3 => 3,
            d => {
                return Err(StageError::param(
                    "dimension",
                    format!("{d}: must be 2 or 3"),
                ))
            }
        };
        if !(self.eta > 0.0 && self.eta <= 2.0) {
            return Err(StageError::param(
                "eta",
                "must be in (0, 2] (a base wider than the particle diameter is not a bridge)",
            ));
        }
        if let Some(g) = self.max_gap {
            if !(g.si().is_finite() && g.si() >= 0.0) {
                return Err(StageError::param("max_gap", "must be a length >= 0"));
            }
        }
        if let Some(c) = self.crop_size {
            if !(c.si().is_finite() && c.si() > 0.0) {
                return Err(StageError::param("crop_size", "must be a positive length"));
            }
        }
        if !(self.crop_fraction > 0.0 && self.crop_fraction <= 1.0) {
            return Err(StageError::param("crop_fraction", "must be in (0, 1]"));
        }
        if self.resolution < 8 {
            return Err(StageError::param("resolution", "must be at least 8"));
        }
        if let Some(v) = self.voxel_size {
            if !(v.si().is_finite() && v.si() > 0.0) {
                return Err(StageError::param("voxel_size", "must be a positive length"));
            }
        }
        if self.supersampling == 0 || self.supersampling > 8 {
            return Err(StageError::param("supersampling", "must be in [1, 8]"));
        }
        Ok(dim)
    }

    fn check_grid(&self, g: &Grid) -> Result<(), StageError> {
        let n = g.voxel_count() as u64;
        if n > MAX_VOXELS {
            let key = if self.voxel_size.is_some() {
                "voxel_size"
            } else {
                "resolution"
            };
            return Err(StageError::param(
                key,
                format!("the image would have {n} voxels, more than {MAX_VOXELS}"),
            ));
        }
        Ok(())
    }
}

pub struct Bridges;

impl TypedStage for Bridges {
    type Params = BridgesParams;
    type Plan = Plan;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "binder.bridges",
            "1.2.0",
            "Cementing matrix as trapezoidal bridges (Topin et al., J. Cereal Sci. 47, 347 \
             (2008); Heinze et al., Phys. Rev. E 101, 052901 (2020), sec. II.B and Fig. 2a): \
             every pair of particles whose surfaces are at most max_gap apart is joined by the \
             trapezoid (frustum in 3-D) spanning their centres with base widths eta r_i and \
             eta r_j; the part outside the particles is matrix. The central square (cube) of \
             edge crop_size is rasterised to a phase image with labels 0 pore, 1 large, \
             2 small, 3 matrix (the phase names); each voxel takes the phase covering most of its \
             supersampling^d sub-samples. Particle tests use the shared sphere raster. Needs \
             the `class` attribute of packing.poisson_disk.",
        )
        .inputs(vec![PortSpec::new(
            "packing",
            ArtifactKind::Packing,
            "the compacted disks or spheres with their class",
        )])
        .outputs(vec![
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "0 = pore, 1 = large, 2 = small, 3 = matrix",
            ),
            PortSpec::new(
                "report",
                ArtifactKind::Table,
                "bridges, voxel and sub-sample phase fractions, the grid",
            ),
            PortSpec::new(
                "particles",
                ArtifactKind::Field,
                "particle identity on the image grid: 1 + the packing index of the particle \
                 covering most of a particle voxel's sub-samples, 0 elsewhere (exact in f32 up \
                 to 2^24 particles); peridynamics.bond_based uses it to tell touching \
                 particles apart (Table I)",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &BridgesParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<Plan>, StageError> {
        let dim = p.check()?;
        let centre = p.crop_center.map(|q| q.si());
        let up = inputs.get("packing");
        let edge = match (p.crop_size, up.and_then(|m| m.domain_box)) {
            (Some(c), _) => Some(c.si()),
            (None, Some((lo, hi))) => Some(
                p.crop_fraction
                    * (0..dim)
                        .map(|a| hi[a] - lo[a])
                        .fold(f64::INFINITY, f64::min),
            ),
            (None, None) => None,
        };
        // Before the packing exists its particle sizes are unknown, but a gap wider than half
        // the box is no bridge of any particle in it (the run checks the particles).
        if let (Some(g), Some((lo, hi))) = (p.max_gap, up.and_then(|m| m.domain_box)) {
            let half_box = 0.5
                * (0..dim)
                    .map(|a| hi[a] - lo[a])
                    .fold(f64::INFINITY, f64::min);
            if g.si() > half_box {
                return Err(StageError::param(
                    "max_gap",
                    format!(
                        "{} is wider than half the packing box ({}): a cement bridge joins \
                         near neighbours (leave max_gap out for the paper's three voxels)",
                        grainpipe_core::units::format_length(g.si()),
                        grainpipe_core::units::format_length(half_box)
                    ),
                ));
            }
        }
        if let (Some(e), Some((lo, hi))) = (edge, up.and_then(|m| m.domain_box)) {
            for a in 0..dim {
                if centre[a] - 0.5 * e < lo[a] - 1e-12 * e
                    || centre[a] + 0.5 * e > hi[a] + 1e-12 * e
                {
                    return Err(StageError::param(
                        "crop_size",
                        format!("the crop of edge {e:.4e} m leaves the packing box along axis {a}"),
                    ));
                }
            }
        }
        let grid = edge.map(|e| crop_grid(dim, centre, e, p.voxel_for(e)));
        // Per voxel: the raster's (label, particle id) pairs (8 B), the labels (1 B) and ids
        // (4 B) split off them, then the f32 `particles` field (4 B) while the ids live:
        // at most 14 B.
        let bytes = match &grid {
            Some(g) => {
                p.check_grid(g)?;
                14 * g.voxel_count() as u64
            }
            None => 14 * (p.resolution as u64).pow(dim as u32),
        } + per_particle_bytes() * up.map(|m| m.count_estimate).unwrap_or(0)
            + (64 << 10);
        // The phase table is fixed: announced so downstream `materials` keys are checked.
        let image = match &grid {
            Some(g) => ArtifactMeta::on_grid(ArtifactKind::PhaseImage, g.clone()),
            None => ArtifactMeta::of(ArtifactKind::PhaseImage),
        }
        .with_phases(phases());
        let particles = match &grid {
            Some(g) => ArtifactMeta::on_grid(ArtifactKind::Field, g.clone()),
            None => ArtifactMeta::of(ArtifactKind::Field),
        };
        Ok(Preflight::from_info(&self.info(), bytes)
            .announce("image", image)
            .announce("particles", particles)
            .announce(
                "report",
                ArtifactMeta::of(ArtifactKind::Table).with_count(1, Some([1, 1])),
            )
            .with_plan(Plan { grid }))
    }

    fn run(
        &self,
        p: &BridgesParams,
        plan: &Plan,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let pk = grainpipe_core::stage::input(inputs, "packing", Artifact::as_packing)?;
        let parts = Particles::from_packing(pk, "packing")?;
        let dim = p.dimension as usize;
        if parts.dim != dim {
            return Err(StageError::param(
                "dimension",
                format!("is {dim} but the packing holds a {}-D sample", parts.dim),
            ));
        }
        let centre = p.crop_center.map(|q| q.si());
        let grid = match &plan.grid {
            Some(g) => g.clone(),
            None => {
                let s = pk.domain.size();
                let e = p.crop_fraction * (0..dim).map(|a| s[a]).fold(f64::INFINITY, f64::min);
                let g = crop_grid(dim, centre, e, p.voxel_for(e));
                p.check_grid(&g)?;
                g
            }
        };
        let ext = grid.extent();
        for a in 0..dim {
            let lo = grid.origin[a];
            let hi = lo + ext[a];
            let tol = 1e-9 * ext[a];
            if lo < pk.domain.min[a] - tol || hi > pk.domain.max[a] + tol {
                return Err(StageError::param(
                    "crop_size",
                    format!(
                        "the crop [{lo:.4e}, {hi:.4e}] m leaves the packing box [{:.4e}, {:.4e}] \
                         m along axis {a}; crop less or centre the crop (crop_center)",
                        pk.domain.min[a], pk.domain.max[a]
                    ),
                ));
            }
        }
        let dx = grid.spacing[0];
        let max_gap = p.max_gap.map(|g| g.si()).unwrap_or(3.0 * dx);
        check_gap(max_gap, parts.radius.iter().cloned().fold(0.0, f64::max))?;
        let bridges = find_bridges(&parts, &pk.domain, p.eta, max_gap, |_, _| {
            ctx.check_cancelled()
        })?;
        let (labels, ids, counts) =
            rasterize(&parts, &bridges, &grid, p.supersampling as usize, ctx)?;
        let nvox = labels.len() as f64;
        let frac = |l: u8| labels.iter().filter(|&&x| x == l).count() as f64 / nvox;
        let sub_total: u64 = counts.iter().sum();
        let sfrac = |l: u8| counts[l as usize] as f64 / sub_total as f64;
        let report = Table::new("bridges")
            .with_i64("bridges", "", vec![bridges.len() as i64])
            .with_f64("eta", "", vec![p.eta])
            .with_f64("max_gap", "m", vec![max_gap])
            .with_i64("nx", "", vec![grid.dims[0] as i64])
            .with_i64("ny", "", vec![grid.dims[1] as i64])
            .with_i64("nz", "", vec![grid.dims[2] as i64])
            .with_f64("voxel_size", "m", vec![dx])
            .with_f64("rho_large", "", vec![frac(LARGE)])
            .with_f64("rho_small", "", vec![frac(SMALL)])
            .with_f64("rho_matrix", "", vec![frac(MATRIX)])
            .with_f64("rho_void", "", vec![frac(VOID)])
            .with_f64("theta_image", "", vec![frac(LARGE) / frac(SMALL)])
            .with_f64("coverage_large", "", vec![sfrac(LARGE)])
            .with_f64("coverage_small", "", vec![sfrac(SMALL)])
            .with_f64("coverage_matrix", "", vec![sfrac(MATRIX)])
            .with_f64("coverage_void", "", vec![sfrac(VOID)]);
        let particles = Field::new(
            grid.clone(),
            "particle",
            "",
            ComponentConvention::Plain,
            FieldData::F32(ids.iter().map(|&i| i as f32).collect()),
        )
        .map_err(StageError::failed)?;
        let mut out = Outputs::new();
        out.insert(
            "image".into(),
            Artifact::PhaseImage(PhaseImage {
                grid,
                labels,
                phases: phases(),
            }),
        );
        out.insert("particles".into(), Artifact::Field(particles));
        out.insert("report".into(), Artifact::Table(report));
        Ok(out)
    }
}

/// Labels every voxel of `grid`: the phase (large, small, matrix, void) covering most of its
/// `s^d` sub-samples (ties to the lower label, i.e. void < large < small < matrix); also
/// returns each voxel's particle identity (1 + the index of the particle of the voxel's
/// phase covering most of its sub-samples, ties to the lower index; 0 for void and matrix)
/// and the sub-sample counts per label. Deterministic: the raster scans fixed slabs.
#[allow(clippy::type_complexity)]
pub fn rasterize(
    parts: &Particles,
    bridges: &[Bridge],
    grid: &Grid,
    s: usize,
    ctx: &RunContext,
) -> Result<(Vec<u8>, Vec<u32>, [u64; 4]), StageError> {
    let dim = parts.dim;
    let spheres: Vec<WorldSphere> = parts
        .pos
        .iter()
        .zip(&parts.radius)
        .enumerate()
        .map(|(i, (c, r))| WorldSphere {
            center: *c,
            radius: *r,
            body: i,
        })
        .collect();
    let half_diag = 0.5
        * (0..dim)
            .map(|a| grid.spacing[a].powi(2))
            .sum::<f64>()
            .sqrt();
    let raster = SphereRaster::new(grid, &spheres, half_diag)
        .map_err(|e| StageError::failed(e.to_string()))?;
    // Bridges binned by their midpoints; a query reaches the largest bounding radius.
    let reach = bridges
        .iter()
        .map(Bridge::bounding_radius)
        .fold(0.0, f64::max)
        + half_diag;
    let ext = grid.extent();
    let mut cells = CellList::new(
        [0, 1, 2].map(|a| grid.origin[a] - reach),
        [0, 1, 2].map(|a| ext[a] + 2.0 * reach),
        [false; 3],
        reach.max(grid.spacing[0]),
    );
    for (k, b) in bridges.iter().enumerate() {
        cells.insert(k as u32, b.midpoint());
    }
    // Sub-sample offsets inside a voxel (cell-centred), in-plane only for 2-D samples.
    let offs: Vec<[f64; 3]> = {
        let o = |k: usize, a: usize| ((k as f64 + 0.5) / s as f64 - 0.5) * grid.spacing[a];
        let nz = if dim == 2 { 1 } else { s };
        let mut v = Vec::with_capacity(s * s * nz);
        for kz in 0..nz {
            for ky in 0..s {
                for kx in 0..s {
                    let z = if dim == 2 { 0.0 } else { o(kz, 2) };
                    v.push([o(kx, 0), o(ky, 1), z]);
                }
            }
        }
        v
    };
    let mut voxels = vec![(VOID, 0u32); grid.voxel_count()];
    let class = &parts.class;
    let accs = raster.scan(
        &mut voxels,
        || ([0u64; 4], Vec::<u32>::new(), Vec::<(u32, u32)>::new()),
        |acc, cands, _v, centre, out| {
            let (counts, near, bodies) = acc;
            bodies.clear();
            // Bridges that can reach this voxel.
            near.clear();
            cells.visit(centre, reach, |k, _| {
                let b = &bridges[k as usize];
                let m = b.midpoint();
                let d = sub(centre, m);
                let lim = b.bounding_radius() + half_diag;
                if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= lim * lim {
                    near.push(k);
                }
                true
            });
            let mut c = [0u32; 4];
            for o in &offs {
                let q = [0, 1, 2].map(|a| centre[a] + o[a]);
                let mut label = VOID;
                for cd in cands {
                    if cd.lower_bound > 0.0 {
                        break;
                    }
                    if cd.distance(q) < 0.0 {
                        label = class[cd.body as usize];
                        let body = cd.body;
                        match bodies.iter_mut().find(|(b, _)| *b == body) {
                            Some((_, n)) => *n += 1,
                            None => bodies.push((body, 1)),
                        }
                        break;
                    }
                }
                if label == VOID && near.iter().any(|&k| bridges[k as usize].contains(q)) {
                    label = MATRIX;
                }
                c[label as usize] += 1;
            }
            let mut best = 0usize;
            for l in 1..4 {
                if c[l] > c[best] {
                    best = l;
                }
            }
            // The particle of the winning phase with the most sub-samples (lowest index on
            // ties, so the id does not depend on the candidates' order).
            let id = bodies
                .iter()
                .filter(|(b, _)| class[*b as usize] as usize == best)
                .max_by(|x, y| x.1.cmp(&y.1).then(y.0.cmp(&x.0)))
                .map_or(0, |(b, _)| b + 1);
            *out = (best as u8, id);
            for l in 0..4 {
                counts[l] += c[l] as u64;
            }
        },
        |done, total| ctx.progress(done, total),
    )?;
    let mut counts = [0u64; 4];
    for (c, _, _) in accs {
        for l in 0..4 {
            counts[l] += c[l];
        }
    }
    let (labels, ids) = voxels.into_iter().unzip();
    Ok((labels, ids, counts))
}
