//! Runs every example of the sphere-filling paper and prints a Markdown table side by side
//! with the paper's Tables 1-3 (Matlab 2021a, 2 Xeon workstation).
//!
//! `cargo run --release -p grainpipe-bricks --example bricks_bench`
//! Optional argument: number of rayon threads (default 2).

use grainpipe_bricks::{
    BrickParams, Curved, CurvedParams, Method1, Method1Params, Method2, Method2Params,
};
use grainpipe_core::distributions::SizeDistribution;
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::units::Q;
use grainpipe_core::{Outputs, RunContext, StageError, TypedStage};
use std::time::Instant;

fn gamma() -> SizeDistribution {
    // Paper eq. (3.8): theta = 7 um, k = 2.
    SizeDistribution::Gamma {
        shape: 2.0,
        scale: Q::new(7e-6),
        min: None,
        max: None,
    }
}

fn col(o: &Outputs, name: &str) -> f64 {
    let t = o["report"].as_table().unwrap();
    match &t.column(name).unwrap().data {
        grainpipe_core::ColumnData::F64(v) => v[0],
        grainpipe_core::ColumnData::I64(v) => v[0] as f64,
        _ => f64::NAN,
    }
}

/// Preflight (which builds the unit brick) and run, as the engine does.
fn go<T: TypedStage>(stage: &T, p: &T::Params, ctx: &RunContext) -> Result<Outputs, StageError> {
    let plan = stage.preflight(p, &Default::default())?.plan;
    stage.run(p, &plan, &Default::default(), ctx)
}

type Runner = Box<dyn Fn(&RunContext) -> Result<Outputs, StageError> + Sync>;

struct Case {
    name: &'static str,
    paper: &'static str,
    run: Runner,
}

fn m1(fg: f64, bg: f64, cp: f64, sides: [f64; 3], std: f64, n: [usize; 3]) -> Method1Params {
    Method1Params {
        common: BrickParams {
            face_goal: fg,
            body_goal: bg,
            contact_parameter: cp,
            brick_sides: sides,
            std_length: std,
            ..BrickParams::method1_defaults()
        },
        brick_numbers: n,
    }
}

fn m2(
    radius: SizeDistribution,
    cp: f64,
    sides: [f64; 3],
    std: f64,
    n: [usize; 3],
) -> Method2Params {
    Method2Params {
        common: BrickParams {
            radius,
            contact_parameter: cp,
            brick_sides: sides,
            std_length: std,
            ..BrickParams::method2_defaults()
        },
        brick_numbers: n,
    }
}

fn main() {
    let threads: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(2);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let cube = [1.0, 1.0, 1.0];
    let cases: Vec<Case> = vec![
        Case {
            name: "1A M1 Weibull 15r eps=0.1",
            paper: "T = 6 min, N = 450",
            run: Box::new(move |c| go(&Method1, &m1(0.8, 0.55, 0.1, cube, 15.0, [2, 2, 1]), c)),
        },
        Case {
            name: "1A M1 Weibull 15r eps=0.2",
            paper: "T = 2 min, N = 412",
            run: Box::new(move |c| go(&Method1, &m1(0.8, 0.55, 0.2, cube, 15.0, [2, 2, 1]), c)),
        },
        Case {
            name: "1B M1 Weibull 30r eps=0.1",
            paper: "T = 187 min, N = 3075",
            run: Box::new(move |c| go(&Method1, &m1(0.8, 0.55, 0.1, cube, 30.0, [2, 2, 1]), c)),
        },
        Case {
            name: "1B M1 Weibull 30r eps=0.2",
            paper: "T = 40 min, N = 2867",
            run: Box::new(move |c| go(&Method1, &m1(0.8, 0.55, 0.2, cube, 30.0, [2, 2, 1]), c)),
        },
        Case {
            name: "1C M1 [1.2,1.7,1]x15r, 4x4x2",
            paper: "T ~ 10 min",
            run: Box::new(move |c| {
                go(
                    &Method1,
                    &m1(0.8, 0.55, 0.2, [1.2, 1.7, 1.0], 15.0, [4, 4, 2]),
                    c,
                )
            }),
        },
        Case {
            name: "1C M1 [1.2,1.7,1]x30r, 2x2x1",
            paper: "T ~ 160 min",
            run: Box::new(move |c| {
                go(
                    &Method1,
                    &m1(0.8, 0.55, 0.2, [1.2, 1.7, 1.0], 30.0, [2, 2, 1]),
                    c,
                )
            }),
        },
        Case {
            name: "2 M2 Gamma 15r eps=0.1",
            paper: "T = 7 s, N = 160",
            run: Box::new(move |c| go(&Method2, &m2(gamma(), 0.1, cube, 15.0, [2, 2, 1]), c)),
        },
        Case {
            name: "2 M2 Gamma 15r eps=0.2",
            paper: "T = 11 s, N = 178",
            run: Box::new(move |c| go(&Method2, &m2(gamma(), 0.2, cube, 15.0, [2, 2, 1]), c)),
        },
        Case {
            name: "2 M2 Gamma 30r eps=0.1",
            paper: "T = 14 min, N = 1757",
            run: Box::new(move |c| go(&Method2, &m2(gamma(), 0.1, cube, 30.0, [2, 2, 1]), c)),
        },
        Case {
            name: "2 M2 Gamma 30r eps=0.2",
            paper: "T = 15 min, N = 1771",
            run: Box::new(move |c| go(&Method2, &m2(gamma(), 0.2, cube, 30.0, [2, 2, 1]), c)),
        },
        Case {
            name: "T3 M2 Weibull 15r eps=0.1",
            paper: "T = 4 min, N = 591",
            run: Box::new(move |c| {
                go(
                    &Method2,
                    &m2(SizeDistribution::default(), 0.1, cube, 15.0, [2, 2, 1]),
                    c,
                )
            }),
        },
        Case {
            name: "T3 M2 Weibull 15r eps=0.2",
            paper: "T = 4 min, N = 594",
            run: Box::new(move |c| {
                go(
                    &Method2,
                    &m2(SizeDistribution::default(), 0.2, cube, 15.0, [2, 2, 1]),
                    c,
                )
            }),
        },
        Case {
            name: "T3 M2 Weibull 30r eps=0.1",
            paper: "T = 32 min, N = 3332",
            run: Box::new(move |c| {
                go(
                    &Method2,
                    &m2(SizeDistribution::default(), 0.1, cube, 30.0, [2, 2, 1]),
                    c,
                )
            }),
        },
        Case {
            name: "T3 M2 Weibull 30r eps=0.2",
            paper: "T = 38 min, N = 3606",
            run: Box::new(move |c| {
                go(
                    &Method2,
                    &m2(SizeDistribution::default(), 0.2, cube, 30.0, [2, 2, 1]),
                    c,
                )
            }),
        },
        Case {
            name: "3A curved cube 30r, R=0.5,0.5",
            paper: "T = 49 min",
            run: Box::new(move |c| go(&Curved, &CurvedParams::default(), c)),
        },
        Case {
            name: "3B curved [1.3,1,1]x30r, R=0.2,0.4",
            paper: "T = 41 min",
            run: Box::new(move |c| {
                let p = CurvedParams {
                    common: BrickParams {
                        brick_sides: [1.3, 1.0, 1.0],
                        contact_parameter: 0.2,
                        ..BrickParams::curved_defaults()
                    },
                    hemisphere_radii: [0.2, 0.4],
                    ..Default::default()
                };
                go(&Curved, &p, c)
            }),
        },
        Case {
            name: "5.2 powder bed M2 [1,1,0.12]x30r, 6x6x1",
            paper: "T ~ 5 min",
            run: Box::new(move |c| {
                go(
                    &Method2,
                    &m2(
                        SizeDistribution::default(),
                        0.1,
                        [1.0, 1.0, 0.12],
                        30.0,
                        [6, 6, 1],
                    ),
                    c,
                )
            }),
        },
    ];
    println!("rayon threads: {threads}\n");
    println!("| example | paper (Matlab) | time [s] | N unit brick | N total | body fraction | min face fraction | goals reached | draws | rejected | KS (crit. 0.05) | contacts |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for case in &cases {
        let rep = SilentReporter;
        let ctx = RunContext::new(42, &rep);
        let t0 = Instant::now();
        let out = pool.install(|| (case.run)(&ctx));
        let dt = t0.elapsed().as_secs_f64();
        match out {
            Ok(o) => {
                println!(
                "| {} | {} | {:.3} | {} | {} | {:.3} | {:.3} | {} | {} | {} | {:.3} ({:.3}) | {} |",
                case.name,
                case.paper,
                dt,
                col(&o, "spheres_unit_brick"),
                col(&o, "spheres_total"),
                col(&o, "body_fraction"),
                col(&o, "face_fraction_min"),
                if col(&o, "goals_reached") > 0.5 { "yes" } else { "no (saturated)" },
                col(&o, "draws"),
                col(&o, "rejected_draws"),
                col(&o, "ks_distance"),
                col(&o, "ks_critical_0_05"),
                col(&o, "contacts"),
            )
            }
            Err(e) => println!(
                "| {} | {} | {:.3} | failed: {e} |",
                case.name, case.paper, dt
            ),
        }
    }
}
