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
use grainpipe_sintering::simulate;
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


fn cases() -> Vec<(&'static str, LaserParams)> {
    use grainpipe_sintering::params::{BeamProfile, PathKind, TopSurface};
    let base = LaserParams { cooldown: Q::new(2e-4), ..Default::default() };
    std::fs::write("/tmp/bs_out/path.csv", "x,y,on\n800,800,1\n1300,800,1\n1300,900,0\n800,900,1\n800,1000,1\n").unwrap();
    vec![
        ("default", base.clone()),
        ("exact", LaserParams { cooldown: Q::new(5e-4), ..base.clone() }), ("short", LaserParams { passes: 1, raster_length: Q::new(200e-6), cooldown: Q::new(0.0), snapshot_interval: Q::new(50e-6), ..base.clone() }),
        ("implicit", LaserParams { integrator: Integrator::Implicit, ..base.clone() }),
        ("userdt_mr", LaserParams { dt: Some(Q::new(2e-6)), ..base.clone() }),
        
        ("shadow_gauss", LaserParams { top_surface: TopSurface::Depth, shadowing: true, beam_profile: BeamProfile::Gaussian, ..base.clone() }),
        ("all_shadow", LaserParams { top_surface: TopSurface::All, shadowing: true, ..base.clone() }),
        ("melting", LaserParams { melting: true, power: Q::new(200.0), ..base.clone() }),
        ("csv", LaserParams { path: PathKind::Csv, path_csv: "/tmp/bs_out/path.csv".into(), path_csv_unit: Q::new(1e-6), ..base.clone() }),
        ("hist0", LaserParams { history_interval: Q::new(0.0), snapshot_interval: Q::new(0.0), passes: 1, ..base.clone() }),
    ]
}

fn main() {
    let dir = std::env::args().nth(1).expect("out dir");
    let (pk, g) = make_bed(1);
    eprintln!("bed: {} bodies, {} contacts", pk.bodies.len(), g.contacts.len());
    for (name, p) in cases() {
        let t0 = Instant::now();
        let r = simulate(&p, &pk, &g, &RunContext::new(42, &SilentReporter)).expect(name);
        let dt = t0.elapsed().as_secs_f64();
        let json = serde_json::to_string(&(&r.bonds, &r.packing, &r.snapshots, &r.history, r.steps, &r.absorbers)).unwrap();
        std::fs::write(format!("{dir}/sinter_{name}.json"), json).unwrap();
        let mut metas = grainpipe_core::InputMetas::new();
        metas.insert("packing".into(), grainpipe_core::ArtifactMeta::of(grainpipe_core::ArtifactKind::Packing));
        metas.insert("contacts".into(), grainpipe_core::ArtifactMeta::of(grainpipe_core::ArtifactKind::ContactGraph));
        use grainpipe_core::TypedStage;
        let pf = grainpipe_sintering::LaserSintering.preflight(&p, &metas).unwrap();
        pf.outputs["snapshots"].check(&grainpipe_core::Artifact::Series(r.snapshots.clone())).unwrap();
        eprintln!("bounds {:?} history est {}", pf.outputs["snapshots"].count_bounds, pf.outputs["history"].count_estimate);
        eprintln!("{name}: {} steps, {} frames, {:.2}s", r.steps, r.snapshots.frames.len(), dt);
    }
}
