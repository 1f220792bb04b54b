//! `voxelize.packing`: spheres and clumps -> a phase image, with sub-voxel supersampling.

use grainpipe_core::resolution::{AutoVoxel, VoxelSize, UNRESOLVED};
use grainpipe_core::subvoxel::{self, SubvoxelOutput};
use grainpipe_core::{
    input, params, Artifact, ArtifactKind, ArtifactMeta, Grid, InputMetas, Inputs, Outputs, Phase,
    PhaseImage, PortSpec, Preflight, RunContext, StageError, StageInfo, Table, TypedStage,
    WorldSphere,
};
use rayon::prelude::*;

#[params]
pub struct VoxelizeParams {
    /// Voxel edge (adjusted so voxels tile the box); 0 = use voxels_per_diameter. Give it to
    /// have the grid known before running (downstream memory estimates need it). `auto`:
    /// the runner picks the coarsest voxel whose estimated error on auto_quantities meets
    /// target_error (cheap levels at auto_levels voxels per diameter, Richardson
    /// extrapolation; docs/sweeps.md).
    #[param(default = VoxelSize::default())]
    pub voxel_size: VoxelSize,
    /// Voxels across the mean volume-equivalent body diameter when voxel_size is 0.
    #[param(default = 10.0)]
    pub voxels_per_diameter: f64,
    /// Sub-samples per axis in voxels cut by a surface.
    #[param(default = 4, ty = "integer 1..16")]
    pub supersampling: u32,
    /// Name of the solid phase (label 1); `grain` in the phase vocabulary.
    #[param(default = grainpipe_core::phases::GRAIN.into())]
    pub phase_name: String,
    #[param(flatten)]
    pub subvoxel: SubvoxelOutput,
    #[param(flatten)]
    pub auto: AutoVoxel,
}

pub struct Voxelize;

/// The sub-voxel geometry of a two-phase sphere image: voxels next to an interface sampled
/// at `samples^3` points against the spheres that reach them (solid inside any sphere).
fn subvoxel_geometry(
    image: &PhaseImage,
    spheres: &[WorldSphere],
    samples: usize,
    ctx: &RunContext,
) -> Result<grainpipe_core::Field, StageError> {
    use grainpipe_core::raster::{min_distance, SphereRaster};
    let grid = &image.grid;
    let half_diagonal = 0.5 * grid.spacing.iter().map(|s| s * s).sum::<f64>().sqrt();
    let raster = SphereRaster::new(grid, spheres, 2.0 * half_diagonal)
        .map_err(|e| StageError::failed(e.to_string()))?;
    let which = subvoxel::interface_candidates(grid, &image.labels);
    let [nx, ny, _] = grid.dims;
    let mut slots = vec![0u8; grid.voxel_count()];
    let per_slab = raster.scan(
        &mut slots,
        Vec::new,
        |acc: &mut Vec<subvoxel::VoxelSamples>, cands, [x, y, z], c, _| {
            let v = x + nx * (y + ny * z);
            if which[v] {
                let s = subvoxel::sample_voxel(c, grid.spacing, samples, 2, |q| {
                    usize::from(min_distance(cands, q, 0.0, 0.0) < 0.0)
                });
                acc.push((v, s));
            }
        },
        |done, total| ctx.progress(done, total),
    )?;
    let sv = subvoxel::from_samples(image, per_slab.into_iter().flatten().collect())
        .map_err(StageError::failed)?;
    ctx.info(&format!(
        "sub-voxel geometry: {} mixed voxels ({:.1} %)",
        sv.mixed_count(),
        100.0 * sv.mixed_count() as f64 / image.labels.len().max(1) as f64
    ));
    Ok(sv.to_field(grid))
}

/// Upper bound on voxels, so a typo in voxel_size is refused instead of swapping.
const MAX_VOXELS: f64 = 4e9;

/// The parameter that set the voxel: `voxel_size` when given, else `voxels_per_diameter`.
fn voxel_key(p: &VoxelizeParams) -> &'static str {
    if p.voxel_size.si() > 0.0 {
        "voxel_size"
    } else {
        "voxels_per_diameter"
    }
}

fn voxel_size(p: &VoxelizeParams, mean_diameter: f64) -> f64 {
    if p.voxel_size.si() > 0.0 {
        p.voxel_size.si()
    } else {
        mean_diameter / p.voxels_per_diameter
    }
}

impl TypedStage for Voxelize {
    type Params = VoxelizeParams;
    /// The voxel size, when preflight could fix it.
    type Plan = Option<f64>;

    fn info(&self) -> StageInfo {
        StageInfo::new(
            "voxelize.packing",
            "1.1.0",
            "Voxelizes a packing of spheres or clumps into a two-phase image (0 = pore, 1 = \
             grain, named by phase_name). A voxel entirely inside a sphere is solid, one entirely outside every \
             sphere is pore, and a voxel cut by a surface is sampled at supersampling^3 points \
             against the union of the spheres that reach it and is solid when at least half \
             of its points are. Periodic axes wrap. The report compares the image's solid \
             fraction and the sub-voxel coverage with the analytic volume fraction of the \
             packing.",
        )
        .inputs(vec![PortSpec::new(
            "packing",
            ArtifactKind::Packing,
            "spheres or clumps to voxelize",
        )])
        .outputs(vec![
            PortSpec::new(
                "image",
                ArtifactKind::PhaseImage,
                "0 = pore, 1 = grain (phase_name)",
            ),
            PortSpec::new(
                "report",
                ArtifactKind::Table,
                "analytic, image and coverage volume fractions",
            ),
            PortSpec::new(
                "subvoxel",
                ArtifactKind::Field,
                "with subvoxel: true, per voxel the pore and solid fractions and the interface \
                 normal (5 components), sampled against the spheres, for interfaces: composite \
                 in the solvers",
            ),
        ])
    }

    fn preflight(
        &self,
        p: &VoxelizeParams,
        inputs: &InputMetas,
    ) -> Result<Preflight<Option<f64>>, StageError> {
        if p.voxel_size.is_auto() {
            return Err(StageError::param("voxel_size", UNRESOLVED));
        }
        if p.voxel_size.si() < 0.0 || !p.voxel_size.si().is_finite() {
            return Err(StageError::param(
                "voxel_size",
                "must be a positive length, or 0",
            ));
        }
        if p.voxel_size.si() == 0.0
            && (p.voxels_per_diameter.is_nan() || p.voxels_per_diameter < 1.0)
        {
            return Err(StageError::param(
                "voxels_per_diameter",
                "must be at least 1",
            ));
        }
        if !(1..=16).contains(&p.supersampling) {
            return Err(StageError::param(
                "supersampling",
                "must be between 1 and 16",
            ));
        }
        p.subvoxel
            .check()
            .map_err(|(k, m)| StageError::param(&k, m))?;
        let meta = inputs.get("packing");
        let mut out = ArtifactMeta::of(ArtifactKind::PhaseImage);
        let mut memory = 0;
        let mut voxel = None;
        if let Some((lo, hi)) = meta.and_then(|m| m.domain_box) {
            let scale = meta.and_then(|m| m.mean_diameter.or(m.length_scale));
            if p.voxel_size.si() > 0.0 || scale.is_some() {
                let v = voxel_size(p, scale.unwrap_or(0.0));
                Grid::check_tiling(lo, hi, v).map_err(|m| StageError::param(voxel_key(p), m))?;
                let n: f64 = (0..3)
                    .map(|a| ((hi[a] - lo[a]) / v).round().max(1.0))
                    .product();
                if n > MAX_VOXELS {
                    return Err(StageError::param(
                        "voxel_size",
                        format!("{n:.3e} voxels: more than {MAX_VOXELS:.0e}; use a larger voxel"),
                    ));
                }
                // The label array (1 B per voxel, moved into the image) and the sub-voxel
                // field; per worker thread one plane of sample slots (4 B per voxel) and of
                // sub-sample masks (8 B per 64 samples, every voxel of a plane cut at worst);
                // per sphere its bounds (48 B) and up to 8 periodic images (80 B) listed in
                // the slabs (of 8 planes) they span, two on average.
                let plane: f64 = (0..2)
                    .map(|a| ((hi[a] - lo[a]) / v).round().max(1.0))
                    .product();
                let samples = (p.supersampling * p.supersampling * p.supersampling) as u64;
                let threads = rayon::current_num_threads() as u64;
                let spheres = meta.map(|m| m.count_estimate).unwrap_or(0);
                memory = n as u64 * (1 + p.subvoxel.bytes_per_voxel(2))
                    + threads * plane as u64 * (4 + 8 * samples.div_ceil(64))
                    + spheres * (48 + 8 * 2 * 80)
                    + (64 << 10);
                // The grid is known when the voxel size is: given, or derived from a mean
                // diameter the packing fixes exactly (a length scale is only an estimate of the
                // diameter the run measures). The run then uses this voxel size.
                let exact = p.voxel_size.si() > 0.0 || meta.and_then(|m| m.mean_diameter).is_some();
                match meta.and_then(|m| m.periodic) {
                    Some(periodic) if exact => {
                        out = ArtifactMeta::on_grid(
                            ArtifactKind::PhaseImage,
                            Grid::tiling(lo, hi, periodic, v),
                        );
                        out.phases = Some(phase_table(&p.phase_name));
                        voxel = Some(v);
                    }
                    _ => out.count_estimate = n as u64,
                }
            }
        }
        let mut pf = Preflight::from_info(&self.info(), memory)
            .announce("image", out.clone())
            .announce(
                "report",
                ArtifactMeta::of(ArtifactKind::Table).with_count(1, Some([1, 1])),
            );
        if p.subvoxel.subvoxel {
            let mut field = out;
            field.kind = ArtifactKind::Field;
            field.phases = None;
            pf = pf.announce("subvoxel", field);
        } else {
            pf.outputs.retain(|k, _| k != "subvoxel");
        }
        Ok(pf.with_plan(voxel))
    }

    fn run(
        &self,
        p: &VoxelizeParams,
        planned_voxel: &Option<f64>,
        inputs: &Inputs,
        ctx: &RunContext,
    ) -> Result<Outputs, StageError> {
        let packing = input(inputs, "packing", Artifact::as_packing)?;
        if packing.bodies.is_empty() {
            return Err(StageError::input("packing", "the packing has no bodies"));
        }
        let d = &packing.domain;
        let v = planned_voxel.unwrap_or_else(|| voxel_size(p, packing.mean_diameter()));
        Grid::check_tiling(d.min, d.max, v).map_err(|m| StageError::param(voxel_key(p), m))?;
        let n: f64 = (0..3)
            .map(|a| ((d.max[a] - d.min[a]) / v).round().max(1.0))
            .product();
        if n > MAX_VOXELS {
            return Err(StageError::param(
                "voxel_size",
                format!("{n:.3e} voxels: use a larger voxel"),
            ));
        }
        let grid = Grid::tiling(d.min, d.max, d.periodic, v);
        let spheres = packing.world_spheres();
        let (labels, coverage) =
            voxelize(&grid, &spheres, d.periodic, p.supersampling as usize, ctx)?;
        let image = PhaseImage {
            grid: grid.clone(),
            labels,
            phases: phase_table(&p.phase_name),
        };
        let analytic = packing.volume_fraction();
        let img = image.fraction(1);
        ctx.info(&format!(
            "{}x{}x{} voxels of {:.3e} m: solid fraction {img:.5} (coverage {coverage:.5}) vs analytic {analytic:.5}",
            grid.dims[0], grid.dims[1], grid.dims[2], grid.spacing[0]
        ));
        let report = Table::new("voxelize")
            .with_f64("analytic_fraction", "1", vec![analytic])
            .with_f64("image_fraction", "1", vec![img])
            .with_f64("coverage_fraction", "1", vec![coverage])
            .with_f64("relative_error", "1", vec![(img - analytic) / analytic])
            .with_f64("voxel_size", "m", vec![grid.spacing[0]])
            .with_i64("voxels", "1", vec![grid.voxel_count() as i64]);
        let subvoxel_field = if p.subvoxel.subvoxel {
            Some(subvoxel_geometry(
                &image,
                &spheres,
                p.subvoxel.subvoxel_samples,
                ctx,
            )?)
        } else {
            None
        };
        let mut out = Outputs::new();
        out.insert("image".into(), Artifact::PhaseImage(image));
        out.insert("report".into(), Artifact::Table(report));
        if let Some(f) = subvoxel_field {
            out.insert("subvoxel".into(), Artifact::Field(f));
        }
        Ok(out)
    }
}

/// z-planes per slab. A slab is a contiguous piece of the image that one thread owns, so
/// writes never race and every voxel's label is a function of the spheres alone, whatever the
/// thread count.
const SLAB: usize = 8;

/// Periodic images per axis a sphere may span before the cell is refused as far too small.
const MAX_IMAGES: i64 = 127;

/// One periodic image of a sphere and the voxels its reach covers.
#[derive(Clone, Copy)]
struct Image {
    center: [f64; 3],
    sphere: usize,
    /// Inclusive voxel ranges per axis, clipped to the grid.
    lo: [usize; 3],
    hi: [usize; 3],
}

/// Per sphere, the tests "signed distance <= -h", "<= h" and "<= 0" (h = half the voxel
/// diagonal) as bounds on the squared distance: the signed distance is
/// `sqrt(d2) - r`, monotone in `d2` in floating point too, so each test holds exactly up to
/// the largest `d2` that passes it. The image is then the same, bit for bit, as testing
/// `sqrt(d2) - r` per point, without a square root per point.
#[derive(Clone, Copy)]
struct Bounds {
    full: Option<f64>,
    touch: Option<f64>,
    inside: Option<f64>,
}

/// The largest `t >= 0` with `pred(t)` for a `pred` that holds up to a point and not beyond
/// (`pred(upper)` false); `None` when `pred(0)` is false. Non-negative doubles order like
/// their bit patterns, so this bisects the bits.
fn last_true(upper: f64, pred: impl Fn(f64) -> bool) -> Option<f64> {
    if !pred(0.0) {
        return None;
    }
    let (mut lo, mut hi) = (0u64, upper.to_bits());
    debug_assert!(!pred(upper));
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if pred(f64::from_bits(mid)) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some(f64::from_bits(lo))
}

fn bounds(r: f64, half_diag: f64) -> Bounds {
    let upper = 4.0 * (r + half_diag).powi(2) + f64::MIN_POSITIVE;
    Bounds {
        full: last_true(upper, |t| t.sqrt() - r <= -half_diag),
        touch: last_true(upper, |t| t.sqrt() - r <= half_diag),
        inside: last_true(upper, |t| t.sqrt() - r <= 0.0),
    }
}

/// The periodic images of `s` whose reach (radius + `reach`) covers voxel centres, with
/// their voxel ranges: per axis, unwrapped voxel indices `i = j + k n` see the sphere's image
/// at `centre - k L` from cell voxel `j`.
fn images(
    grid: &Grid,
    s: &WorldSphere,
    index: usize,
    reach: f64,
    out: &mut Vec<Image>,
) -> Result<(), StageError> {
    let extent = grid.extent();
    let mut per_axis: [Vec<(f64, usize, usize)>; 3] = Default::default();
    for a in 0..3 {
        let (o, h, n) = (grid.origin[a], grid.spacing[a], grid.dims[a] as i64);
        let c = if grid.periodic[a] {
            o + (s.center[a] - o).rem_euclid(extent[a])
        } else {
            s.center[a]
        };
        let r = s.radius + reach;
        // One voxel of slack either side: the exact test is done per voxel.
        let lo = ((c - r - o) / h - 0.5).floor() as i64 - 1;
        let hi = ((c + r - o) / h - 0.5).ceil() as i64 + 1;
        let (kmin, kmax) = if grid.periodic[a] {
            (lo.div_euclid(n), hi.div_euclid(n))
        } else {
            (0, 0)
        };
        if kmax - kmin > 2 * MAX_IMAGES {
            return Err(StageError::failed(format!(
                "sphere {index} (radius {:.3e} m) reaches over more than {MAX_IMAGES} periodic \
                 images of the cell along axis {a}: the packing's domain is far too small for it",
                s.radius
            )));
        }
        for k in kmin..=kmax {
            let (vlo, vhi) = ((lo - k * n).max(0), (hi - k * n).min(n - 1));
            if vlo <= vhi {
                per_axis[a].push((c - k as f64 * extent[a], vlo as usize, vhi as usize));
            }
        }
    }
    for &(cz, zlo, zhi) in &per_axis[2] {
        for &(cy, ylo, yhi) in &per_axis[1] {
            for &(cx, xlo, xhi) in &per_axis[0] {
                out.push(Image {
                    center: [cx, cy, cz],
                    sphere: index,
                    lo: [xlo, ylo, zlo],
                    hi: [xhi, yhi, zhi],
                });
            }
        }
    }
    Ok(())
}

/// Voxel states while stamping; the largest wins.
const EMPTY: u8 = 0;
/// Some sphere surface passes within half a voxel diagonal of the centre.
const CUT: u8 = 1;
/// The centre is deeper than half a voxel diagonal inside some sphere.
const FULL: u8 = 2;

/// The voxels of row (y, z) of `im` (within its x range) whose squared distance to the
/// centre, `(dx^2 + dy^2) + dz^2` as the per-point tests sum it, is at most `limit`. Along a
/// row that sum falls and then rises (every step of it is monotone in `x`), so they form one
/// run: its ends are found from the chord and then checked exactly, one voxel at a time.
#[inline]
fn run(grid: &Grid, im: &Image, (dy2, dz2): (f64, f64), limit: f64) -> Option<(usize, usize)> {
    // fl((dx2 + dy2) + dz2) >= fl(dy2 + dz2): rows beyond the limit are skipped whole.
    let rest = dy2 + dz2;
    if rest > limit {
        return None;
    }
    let (o, h, c) = (grid.origin[0], grid.spacing[0], im.center[0]);
    let d2 = |x: i64| {
        let dx = o + (x as f64 + 0.5) * h - c;
        (dx * dx + dy2) + dz2
    };
    let (lo, hi) = (im.lo[0] as i64, im.hi[0] as i64);
    let w = (limit - rest).sqrt();
    let mut a = (((c - w - o) / h - 0.5).floor() as i64).clamp(lo, hi);
    while a > lo && d2(a - 1) <= limit {
        a -= 1;
    }
    while a <= hi && d2(a) > limit {
        a += 1;
    }
    if a > hi {
        return None;
    }
    let mut b = (((c + w - o) / h - 0.5).ceil() as i64).clamp(a, hi);
    while b < hi && d2(b + 1) <= limit {
        b += 1;
    }
    while b > a && d2(b) > limit {
        b -= 1;
    }
    Some((a as usize, b as usize))
}

/// An inclusive run of voxel indices along a row.
type Run = (usize, usize);

/// The cut part of a row: the voxels within `touch` but not within `full` (one run either
/// side of the full run, or the whole touch run when nothing is full).
#[inline]
fn cut_runs(grid: &Grid, im: &Image, d: (f64, f64), b: &Bounds) -> Option<(Run, Option<Run>)> {
    let outer = run(grid, im, d, b.touch?)?;
    Some((outer, b.full.and_then(|f| run(grid, im, d, f))))
}

/// Labels every voxel; returns the labels and the mean sub-voxel coverage.
///
/// Each sphere (each periodic image of it) is stamped into the voxels of its bounding box:
/// a voxel whose centre is deeper than half a voxel diagonal inside a sphere is solid, one
/// further than that from every surface keeps its state, and the rest are cut. Only cut
/// voxels are supersampled: each sphere that reaches one sets the sub-samples it contains,
/// and the voxel is solid when at least half of its sub-samples are set. Slabs of z-planes
/// run in parallel, each stamping the spheres that cross it.
pub fn voxelize(
    grid: &Grid,
    spheres: &[WorldSphere],
    periodic: [bool; 3],
    supersampling: usize,
    ctx: &RunContext,
) -> Result<(Vec<u8>, f64), StageError> {
    let grid = Grid {
        periodic,
        ..grid.clone()
    };
    let half_diag = 0.5 * grid.spacing.iter().map(|s| s * s).sum::<f64>().sqrt();
    let s = supersampling.max(1);
    let samples = s * s * s;
    let words = samples.div_ceil(64);
    // A voxel whose sub-samples are all set already needs no more spheres.
    let last_word = match samples % 64 {
        0 => !0u64,
        rest => (1u64 << rest) - 1,
    };
    let bounds: Vec<Bounds> = spheres
        .iter()
        .map(|sp| bounds(sp.radius, half_diag))
        .collect();
    let [nx, ny, nz] = grid.dims;
    let slabs = nz.div_ceil(SLAB);
    let mut per_slab: Vec<Vec<Image>> = (0..slabs).map(|_| Vec::new()).collect();
    let mut scratch = Vec::new();
    for (i, sp) in spheres.iter().enumerate() {
        if bounds[i].touch.is_none() {
            continue;
        }
        scratch.clear();
        images(&grid, sp, i, half_diag, &mut scratch)?;
        for im in scratch.drain(..) {
            let (a, b) = (im.lo[2] / SLAB, im.hi[2] / SLAB);
            for slab in &mut per_slab[a..b] {
                slab.push(im);
            }
            per_slab[b].push(im);
        }
    }
    // Sub-sample offsets from the voxel centre, per axis (x fastest in the sample index).
    let offset: [Vec<f64>; 3] = std::array::from_fn(|a| {
        (0..s)
            .map(|k| ((k as f64 + 0.5) / s as f64 - 0.5) * grid.spacing[a])
            .collect()
    });
    let plane = nx * ny;
    let done = std::sync::atomic::AtomicU64::new(0);
    let mut labels = vec![EMPTY; grid.voxel_count()];
    let inside: Vec<u64> = labels
        .par_chunks_mut(plane * SLAB)
        .zip(per_slab.par_iter())
        .enumerate()
        .map(|(slab, (state, ims))| -> Result<u64, StageError> {
            let z0 = slab * SLAB;
            let centre = |a: usize, i: usize| grid.origin[a] + (i as f64 + 0.5) * grid.spacing[a];
            // Pass 1: classify centres.
            for im in ims {
                let b = &bounds[im.sphere];
                for z in im.lo[2].max(z0)..=im.hi[2].min(z0 + SLAB - 1) {
                    let dz = centre(2, z) - im.center[2];
                    for y in im.lo[1]..=im.hi[1] {
                        let dy = centre(1, y) - im.center[1];
                        let base = (z - z0) * plane + y * nx;
                        let Some((outer, inner)) = cut_runs(&grid, im, (dy * dy, dz * dz), b)
                        else {
                            continue;
                        };
                        let mark =
                            |cells: &mut [u8]| cells.iter_mut().for_each(|c| *c = (*c).max(CUT));
                        match inner {
                            Some((c0, c1)) => {
                                mark(&mut state[base + outer.0..base + c0]);
                                state[base + c0..=base + c1].fill(FULL);
                                mark(&mut state[base + c1 + 1..=base + outer.1]);
                            }
                            None => mark(&mut state[base + outer.0..=base + outer.1]),
                        }
                    }
                }
            }
            // Pass 2, plane by plane (bounds the sub-sample masks to one plane): every sphere
            // that reaches a cut voxel sets the sub-samples it contains.
            let mut slot = vec![u32::MAX; plane];
            let mut masks: Vec<u64> = Vec::new();
            let mut count = 0u64;
            let planes = state.len() / plane;
            let (mut qx2, mut qy2, mut qz2) = (vec![0.0; s], vec![0.0; s], vec![0.0; s]);
            for zl in 0..planes {
                let z = z0 + zl;
                let cells = &mut state[zl * plane..(zl + 1) * plane];
                let mut cut = 0usize;
                for (i, c) in cells.iter().enumerate() {
                    slot[i] = if *c == CUT {
                        cut += 1;
                        (cut - 1) as u32
                    } else {
                        u32::MAX
                    };
                }
                masks.clear();
                masks.resize(cut * words, 0);
                if cut > 0 {
                    for im in ims {
                        if z < im.lo[2] || z > im.hi[2] {
                            continue;
                        }
                        let b = &bounds[im.sphere];
                        let Some(inside) = b.inside else { continue };
                        let cz = centre(2, z);
                        let dz = cz - im.center[2];
                        for (k, q) in qz2.iter_mut().enumerate() {
                            let d = cz + offset[2][k] - im.center[2];
                            *q = d * d;
                        }
                        for y in im.lo[1]..=im.hi[1] {
                            let cy = centre(1, y);
                            let dy = cy - im.center[1];
                            let Some((outer, inner)) = cut_runs(&grid, im, (dy * dy, dz * dz), b)
                            else {
                                continue;
                            };
                            for (j, q) in qy2.iter_mut().enumerate() {
                                let d = cy + offset[1][j] - im.center[1];
                                *q = d * d;
                            }
                            // The full run is solid already: no sub-samples to set there.
                            let (c0, c1) = inner.map_or((outer.1 + 1, outer.1), |r| r);
                            for x in (outer.0..c0).chain(c1 + 1..=outer.1) {
                                let sl = slot[y * nx + x];
                                if sl == u32::MAX {
                                    continue;
                                }
                                let m = &mut masks[sl as usize * words..(sl as usize + 1) * words];
                                if m[..words - 1].iter().all(|&w| w == !0)
                                    && m[words - 1] == last_word
                                {
                                    continue;
                                }
                                let cx = centre(0, x);
                                for (i, q) in qx2.iter_mut().enumerate() {
                                    let d = cx + offset[0][i] - im.center[0];
                                    *q = d * d;
                                }
                                let mut bit = 0usize;
                                for &z2 in &qz2 {
                                    for &y2 in &qy2 {
                                        for &x2 in &qx2 {
                                            if (x2 + y2) + z2 <= inside {
                                                m[bit / 64] |= 1 << (bit % 64);
                                            }
                                            bit += 1;
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
                for (i, c) in cells.iter_mut().enumerate() {
                    *c = match *c {
                        FULL => {
                            count += samples as u64;
                            1
                        }
                        CUT => {
                            let sl = slot[i] as usize;
                            let set: u64 = masks[sl * words..(sl + 1) * words]
                                .iter()
                                .map(|w| w.count_ones() as u64)
                                .sum();
                            count += set;
                            u8::from(2 * set >= samples as u64)
                        }
                        _ => 0,
                    };
                }
            }
            let finished = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            ctx.progress(finished, slabs as u64)?;
            Ok(count)
        })
        .collect::<Result<_, _>>()?;
    let total: u64 = inside.iter().sum();
    Ok((
        labels,
        total as f64 / (samples as f64 * grid.voxel_count() as f64),
    ))
}

/// The phase table of a voxelized packing: pore (0) and the solid (1).
fn phase_table(solid: &str) -> Vec<Phase> {
    grainpipe_core::phases::pore_and(&[solid])
}
