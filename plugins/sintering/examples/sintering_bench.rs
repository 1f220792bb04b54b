//! Benchmark of `sintering.laser` on a bed of the section 5.2 size (6 x 6 x 1 bricks of
//! [1, 1, 0.12] x 30 r_mean, Weibull(15.7 um, 3.55) radii, contacts within 0.1 r_mean) and
//! the default print (five 500 um scan lines, 2 r_L apart, 1 m/s, 1 ms cooldown).
//!
//! The bed is made here by a simple deterministic deposition (no dependency on the brick
//! filling crate): each sphere is dropped vertically at the lowest of 12 random x-y
//! candidates until it touches the floor (centre at z = 0, as Method 2 puts face spheres
//! on the faces) or a placed sphere; spheres whose centre would end above 0.12 x 30 r_mean
//! are rejected, and filling stops after 30 consecutive rejections (later, only small
//! spheres still fit and the size distribution drifts away from the Weibull law).
//!
//! cargo run --release -p grainpipe-sintering --example sintering_bench [-- --png out.png]

use grainpipe_core::model::{Body, Contact, ContactGraph, Domain, Packing};
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::units::Q;
use grainpipe_core::RunContext;
use grainpipe_sintering::params::{Integrator, LaserParams};
use grainpipe_sintering::{simulate, RunResult};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Weibull};
use std::time::Instant;

const SCALE: f64 = 15.7e-6;
const SHAPE: f64 = 3.55;

/// Mean of Weibull(lambda, k): lambda Gamma(1 + 1/k) (paper eq. 2.3) = 14.14 um.
fn mean_radius() -> f64 {
    // Gamma(1 + 1/3.55) = Gamma(1.2817) = 0.90063 (Lanczos value, paper: r ~ 14.14 um).
    SCALE * 0.900_63
}

struct Cells {
    cell: f64,
    n: usize,
    items: Vec<Vec<usize>>,
}

impl Cells {
    fn new(l: f64, cell: f64) -> Cells {
        let n = (l / cell).ceil() as usize + 1;
        Cells {
            cell,
            n,
            items: vec![Vec::new(); n * n],
        }
    }
    fn key(&self, x: f64, y: f64) -> (usize, usize) {
        let c = |v: f64| ((v / self.cell).max(0.0) as usize).min(self.n - 1);
        (c(x), c(y))
    }
    fn add(&mut self, i: usize, x: f64, y: f64) {
        let (a, b) = self.key(x, y);
        self.items[a + self.n * b].push(i);
    }
    fn near(&self, x: f64, y: f64, reach: f64, mut f: impl FnMut(usize)) {
        let (a0, b0) = self.key(x - reach, y - reach);
        let (a1, b1) = self.key(x + reach, y + reach);
        for b in b0..=b1 {
            for a in a0..=a1 {
                for &i in &self.items[a + self.n * b] {
                    f(i);
                }
            }
        }
    }
}

fn make_bed(seed: u64) -> (Packing, ContactGraph) {
    let rm = mean_radius();
    let l = 6.0 * 30.0 * rm;
    let h = 0.12 * 30.0 * rm;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let weibull = Weibull::new(SCALE, SHAPE).expect("valid Weibull");
    let mut cells = Cells::new(l, 4.0 * rm);
    let mut pos: Vec<[f64; 3]> = Vec::new();
    let mut rad: Vec<f64> = Vec::new();
    let mut rmax: f64 = 0.0;
    let mut fails = 0;
    while fails < 30 {
        let r: f64 = weibull.sample(&mut rng);
        let mut best: Option<[f64; 3]> = None;
        for _ in 0..12 {
            let x = rng.random::<f64>() * l;
            let y = rng.random::<f64>() * l;
            let mut z: f64 = 0.0;
            cells.near(x, y, r + rmax, |j| {
                let d2 = (pos[j][0] - x).powi(2) + (pos[j][1] - y).powi(2);
                let s = r + rad[j];
                if d2 < s * s {
                    z = z.max(pos[j][2] + (s * s - d2).sqrt());
                }
            });
            if best.is_none_or(|b| z < b[2]) {
                best = Some([x, y, z]);
            }
        }
        let b = best.expect("12 candidates");
        if b[2] > h {
            fails += 1;
            continue;
        }
        fails = 0;
        cells.add(pos.len(), b[0], b[1]);
        pos.push(b);
        rad.push(r);
        rmax = rmax.max(r);
    }
    let mut pk = Packing::new(Domain::boxed(
        [0.0, 0.0, -rmax],
        [l, l, h + rmax],
        [false; 3],
    ));
    for (p, r) in pos.iter().zip(&rad) {
        pk.bodies.push(Body::sphere(*p, *r));
    }
    // Contacts: surface gap within the paper's contact parameter 0.1 x r_mean.
    let tol = 0.1 * rm;
    let mut g = ContactGraph::default();
    for i in 0..pos.len() {
        cells.near(pos[i][0], pos[i][1], rad[i] + rmax + tol, |j| {
            if j > i {
                let d = (0..3)
                    .map(|a| (pos[i][a] - pos[j][a]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                let gap = d - rad[i] - rad[j];
                if gap < tol {
                    g.contacts.push(Contact { i, j, gap });
                }
            }
        });
    }
    g.contacts.sort_by_key(|c| (c.i, c.j));
    g.positions = pos;
    (pk, g)
}

fn timed(p: &LaserParams, pk: &Packing, g: &ContactGraph, reps: usize) -> (f64, RunResult) {
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..reps {
        let t0 = Instant::now();
        let r = simulate(p, pk, g, &RunContext::new(42, &SilentReporter)).expect("run");
        best = best.min(t0.elapsed().as_secs_f64());
        out = Some(r);
    }
    (best, out.expect("reps >= 1"))
}

fn temps(r: &RunResult) -> &[f64] {
    &r.packing.attributes["temperature"].values
}

/// (max |T - T_ref| over particles, relative to the reference's peak rise; bonds).
fn accuracy(r: &RunResult, reference: &RunResult) -> (f64, usize) {
    let tr = temps(reference);
    let rise = tr.iter().map(|t| t - 300.0).fold(0.0, f64::max);
    let dev = temps(r)
        .iter()
        .zip(tr)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    (dev / rise, r.bonds.bonds.len())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let png = args
        .iter()
        .position(|a| a == "--png")
        .and_then(|k| args.get(k + 1).cloned());
    let threads = rayon::current_num_threads();
    if args.iter().any(|a| a == "--default-only") {
        // Profiling aid: the default print once.
        let (pk, g) = make_bed(42);
        let (secs, r) = timed(&LaserParams::default(), &pk, &g, 1);
        println!("default print: {} steps in {secs:.3} s", r.steps);
        return;
    }
    if let Some(k) = args.iter().position(|a| a == "--implicit-only") {
        // Profiling aid: one implicit run at the given dt [s].
        let dt: f64 = args[k + 1].parse().expect("dt in s");
        let (pk, g) = make_bed(42);
        let p = LaserParams {
            integrator: Integrator::Implicit,
            dt: Some(Q::new(dt)),
            snapshot_interval: Q::new(0.0),
            history_interval: Q::new(0.0),
            ..Default::default()
        };
        let (secs, r) = timed(&p, &pk, &g, 1);
        let its = match &r.history.column("cg_iterations").unwrap().data {
            grainpipe_core::model::ColumnData::I64(v) => v.iter().sum::<i64>(),
            _ => 0,
        };
        println!(
            "implicit dt {dt:e}: {} steps, {its} CG iterations in {secs:.3} s",
            r.steps
        );
        return;
    }
    let t0 = Instant::now();
    let (pk, g) = make_bed(42);
    let n = pk.bodies.len();
    let coord = 2.0 * g.contacts.len() as f64 / n as f64;
    let mean_r = pk
        .bodies
        .iter()
        .map(|b| match b.shape {
            grainpipe_core::model::BodyShape::Sphere { radius } => radius,
            _ => 0.0,
        })
        .sum::<f64>()
        / n as f64;
    println!(
        "bed: {n} particles (mean radius {:.2} um, Weibull mean 14.14 um), {} contacts (mean \
         coordination {coord:.2}), volume fraction {:.3} of the centre slab, built in {:.2} s",
        mean_r * 1e6,
        g.contacts.len(),
        pk.solid_volume()
            / (pk.domain.size()[0] * pk.domain.size()[1] * 0.12 * 30.0 * mean_radius()),
        t0.elapsed().as_secs_f64()
    );
    println!("rayon threads: {threads}");

    let base = LaserParams {
        snapshot_interval: Q::new(250e-6),
        ..Default::default()
    };
    let (secs, def) = timed(&base, &pk, &g, 3);
    let h = &def.history;
    let limit = h.f64_column("stability_limit").unwrap()[0];
    let laser = *h.f64_column("laser_energy").unwrap().last().unwrap();
    let resid = *h.f64_column("energy_residual").unwrap().last().unwrap();
    let peak = def.packing.attributes["peak_temperature"]
        .values
        .iter()
        .cloned()
        .fold(0.0, f64::max);
    let bonded_particles = def.packing.attributes["bond_count"]
        .values
        .iter()
        .filter(|&&b| b > 0.0)
        .count();
    println!(
        "default print (explicit, auto dt): {} absorbers, stability limit {:.3e} s, {} steps, \
         {:.3} s best of 3, {:.3e} particle-steps/s; {} bonds, {} bonded particles, peak {:.0} K, \
         laser energy {:.4e} J, energy residual {:.2e} J ({:.1e} relative), {} snapshots",
        def.absorbers.len(),
        limit,
        def.steps,
        secs,
        n as f64 * def.steps as f64 / secs,
        def.bonds.bonds.len(),
        bonded_particles,
        peak,
        laser,
        resid,
        resid / laser,
        def.snapshots.frames.len()
    );
    if let Some(path) = png {
        use grainpipe_core::Exporter;
        grainpipe_sintering::BondGraphPng
            .write_defaults(
                &grainpipe_core::Artifact::ContactGraph(def.bonds.clone()),
                std::path::Path::new(&path),
                &Default::default(),
            )
            .expect("png");
        println!("wrote {path}");
    }

    // Cost vs accuracy against the paper's scheme at its own limit: one global explicit
    // step of 0.9 x min_i m_i C_p / (sum_j k_ij + k_b) for every particle.
    let quiet = LaserParams {
        snapshot_interval: Q::new(0.0),
        ..Default::default()
    };
    let (rs, reference) = timed(
        &LaserParams {
            multirate: false,
            ..quiet.clone()
        },
        &pk,
        &g,
        1,
    );
    println!(
        "reference: explicit, global dt = 0.9 x limit, {} steps, {rs:.2} s, {:.3e} \
         particle-steps/s, {} bonds",
        reference.steps,
        n as f64 * reference.steps as f64 / rs,
        reference.bonds.bonds.len()
    );
    println!(
        "| integrator | dt [s] | steps | sub-cycled particles | CG iterations/step | time [s] | max abs(T - T_ref) / peak rise | bonds |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    let mut rows: Vec<(String, LaserParams)> =
        vec![("explicit multirate (default)".into(), quiet.clone())];
    for dt in [5e-6, 2e-6, 1e-6] {
        rows.push((
            "explicit multirate".into(),
            LaserParams {
                dt: Some(Q::new(dt)),
                ..quiet.clone()
            },
        ));
    }
    for dt in [10e-6, 5e-6, 2e-6, 1e-6] {
        rows.push((
            "implicit".to_string(),
            LaserParams {
                integrator: Integrator::Implicit,
                dt: Some(Q::new(dt)),
                ..quiet.clone()
            },
        ));
    }
    for (name, p) in rows {
        let (secs, r) = timed(&p, &pk, &g, 3);
        let dt = r.history.f64_column("dt").unwrap()[1];
        let stiff = match &r.history.column("subcycled_particles").unwrap().data {
            grainpipe_core::model::ColumnData::I64(v) => v.iter().copied().max().unwrap_or(0),
            _ => 0,
        };
        let cg = match &r.history.column("cg_iterations").unwrap().data {
            grainpipe_core::model::ColumnData::I64(v) => {
                v.iter().skip(1).sum::<i64>() as f64 / (v.len() - 1).max(1) as f64
            }
            _ => 0.0,
        };
        let (acc, bonds) = accuracy(&r, &reference);
        println!(
            "| {name} | {dt:.3e} | {} | {stiff} | {cg:.1} | {secs:.3} | {acc:.2e} | {bonds} |",
            r.steps
        );
    }
}
