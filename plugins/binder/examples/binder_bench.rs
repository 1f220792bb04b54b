//! Benchmark of binder.levelset against the closing baseline on the paper's setting
//! (Donval et al. 2025, section 2.3 and 3.1): a two-layer stacked-MCM packing of real sand
//! clumps, (560 um)^2 x 560 um at 50 %, 2 % binder, imaged at 8, 4, 2 and 1 um.
//!
//! cargo run --release -p grainpipe-binder --example binder_bench -- [finest_um, 1] [closing_finest_um, 2]
//!
//! Part 1, cost: each stage fitted to 2 % (exact fractions) at each voxel size: wall time,
//! a or closing radius, sand and binder fractions reached.
//! Part 2, grid dependence: the a and the closing radius fitted on the finest grid both
//! stages run at are then kept fixed at every coarser voxel size; the binder fraction's
//! deviation from the finest grid and the coarsening mismatch (share of binder voxels that
//! do not agree with the next finer image coarsened 2x) measure how much the binder moves
//! with the grid. Writes out/bench/binder.csv (chart: plugins/binder/bench/chart.py).

use grainpipe_core::engine::run_quietly;
use grainpipe_core::pipeline::PipelineDoc;
use grainpipe_core::testing::run_yaml;
use grainpipe_core::{PhaseImage, Registry};
use std::io::Write;
use std::path::Path;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_clumps::register(&mut r);
    grainpipe_mcm::register(&mut r);
    grainpipe_binder::register(&mut r);
    grainpipe_analysis::register(&mut r);
    r
}

fn mismatch(coarse: &PhaseImage, fine: &PhaseImage) -> f64 {
    let [cx, cy, cz] = coarse.grid.dims;
    let mut err = 0.0;
    for z in 0..cz {
        for y in 0..cy {
            for x in 0..cx {
                let mut share = 0.0;
                for k in 0..8 {
                    let (i, j, l) = (2 * x + (k & 1), 2 * y + ((k >> 1) & 1), 2 * z + (k >> 2));
                    share += f64::from(u8::from(fine.labels[fine.grid.index(i, j, l)] == 2)) / 8.0;
                }
                let b = f64::from(u8::from(coarse.labels[coarse.grid.index(x, y, z)] == 2));
                err += (share - b).abs();
            }
        }
    }
    err / coarse.labels.iter().filter(|&&l| l == 2).count().max(1) as f64
}

struct Row {
    stage: &'static str,
    mode: &'static str,
    h_um: f64,
    wall: f64,
    parameter: f64,
    sand: f64,
    binder: f64,
    fraction_deviation: f64,
    mismatch: f64,
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let finest: f64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(1.0);
    let closing_finest: f64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(2.0);
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    std::env::set_current_dir(&root).unwrap();
    let out = root.join("out/bench");
    std::fs::create_dir_all(&out).unwrap();
    // The packing of pipelines/binder.yaml, written once to HDF5 and imported by every run.
    let packing_file = out.join("binder_packing.h5");
    if !packing_file.is_file() {
        let mut doc = PipelineDoc::load(&root.join("pipelines/binder.yaml")).unwrap();
        doc.exports.clear();
        doc.apply_override("binder.voxel_size=8 um").unwrap();
        doc.apply_override("closing.voxel_size=8 um").unwrap();
        let res = run_quietly(&doc, &registry()).unwrap();
        let packing = &res.outputs["pack"]["packing"];
        grainpipe_formats::hdf5_plain::write_h5(packing, &packing_file, &Default::default())
            .unwrap();
    }
    let levels: Vec<f64> = [8.0, 4.0, 2.0, 1.0]
        .into_iter()
        .filter(|h| *h >= finest)
        .collect();
    let head = format!(
        "name: bench\nseed: 1\nstages:\n  - id: pack\n    use: import.packing\n    with: {{ path: {} }}\n",
        packing_file.display()
    );
    let stage_yaml = |id: &str, stage: &str, h: f64, with: &str| {
        format!(
            "  - id: {id}\n    use: binder.{stage}\n    in: {{ packing: pack.packing }}\n    \
             with: {{ voxel_size: {h} um, {with} }}\n"
        )
    };
    let mut rows: Vec<Row> = Vec::new();
    // Part 1: fitted to 2 % at each level, one run per stage and level.
    let mut fitted: Vec<(&'static str, f64, f64)> = Vec::new();
    for &h in &levels {
        for (stage, mode, with, column) in [
            ("levelset", "fitted", "binder_fraction: 0.02", "a"),
            (
                "levelset",
                "fitted_grains",
                "binder_fraction: 0.02, smooth_over: grains",
                "a",
            ),
            (
                "closing",
                "fitted",
                "binder_fraction: 0.02",
                "closing_radius",
            ),
        ] {
            if stage == "closing" && h < closing_finest {
                continue;
            }
            let yaml = head.clone() + &stage_yaml("b", stage, h, with);
            let res = run_yaml(&registry(), &yaml).unwrap();
            let wall = res.stats["b"].wall.as_secs_f64();
            let im = res.artifact("b.image").as_phase_image().unwrap();
            let p = res.column("b.report", column)[0];
            println!(
                "{stage:>8} {mode:>13} h {h} um: {wall:7.2} s, {column} = {p:.3e} m, sand {:.5}, binder {:.5}",
                im.fraction(1),
                im.fraction(2)
            );
            fitted.push((mode_key(stage, mode), h, p));
            rows.push(Row {
                stage,
                mode,
                h_um: h,
                wall,
                parameter: p,
                sand: im.fraction(1),
                binder: im.fraction(2),
                fraction_deviation: f64::NAN,
                mismatch: f64::NAN,
            });
        }
    }
    // Part 2: the finest fit kept fixed across levels.
    for (stage, mode, key, finest_h) in [
        ("levelset", "fixed", "a", finest),
        ("levelset", "fixed_grains", "a", finest),
        ("closing", "fixed", "radius", closing_finest),
    ] {
        let fit_mode = if mode == "fixed_grains" {
            "fitted_grains"
        } else {
            "fitted"
        };
        let value = fitted
            .iter()
            .find(|f| f.0 == mode_key(stage, fit_mode) && f.1 == finest_h)
            .map(|f| f.2)
            .unwrap();
        let extra = if mode == "fixed_grains" {
            ", smooth_over: grains"
        } else {
            ""
        };
        let mut images: Vec<(f64, PhaseImage)> = Vec::new();
        for &h in levels.iter().filter(|&&h| h >= finest_h) {
            let yaml =
                head.clone() + &stage_yaml("b", stage, h, &format!("{key}: {value:e}{extra}"));
            let res = run_yaml(&registry(), &yaml).unwrap();
            let wall = res.stats["b"].wall.as_secs_f64();
            let im = res.artifact("b.image").as_phase_image().unwrap().clone();
            rows.push(Row {
                stage,
                mode,
                h_um: h,
                wall,
                parameter: value,
                sand: im.fraction(1),
                binder: im.fraction(2),
                fraction_deviation: f64::NAN,
                mismatch: f64::NAN,
            });
            images.push((h, im));
        }
        let reference = images.last().unwrap().1.fraction(2);
        for i in 0..images.len() {
            let dev = images[i].1.fraction(2) / reference - 1.0;
            let mm = if i + 1 < images.len() {
                mismatch(&images[i].1, &images[i + 1].1)
            } else {
                0.0
            };
            let row = rows
                .iter_mut()
                .rev()
                .find(|r| r.stage == stage && r.mode == mode && r.h_um == images[i].0)
                .unwrap();
            row.fraction_deviation = dev;
            row.mismatch = mm;
            println!(
                "{stage:>8} {mode:>13} h {} um: binder {:.5} ({:+.2} % vs finest), coarsening mismatch {mm:.3}",
                images[i].0,
                images[i].1.fraction(2),
                100.0 * dev
            );
        }
    }
    let mut f = std::fs::File::create(out.join("binder.csv")).unwrap();
    writeln!(
        f,
        "stage,mode,voxel_um,wall_s,parameter_m,sand_fraction,binder_fraction,binder_fraction_deviation,coarsening_mismatch"
    )
    .unwrap();
    for r in &rows {
        writeln!(
            f,
            "{},{},{},{:.3},{:.6e},{:.6},{:.6},{:.6},{:.6}",
            r.stage,
            r.mode,
            r.h_um,
            r.wall,
            r.parameter,
            r.sand,
            r.binder,
            r.fraction_deviation,
            r.mismatch
        )
        .unwrap();
    }
    println!("wrote {}", out.join("binder.csv").display());
}

fn mode_key(stage: &str, mode: &str) -> &'static str {
    match (stage, mode) {
        ("levelset", "fitted") => "levelset",
        ("levelset", "fitted_grains") => "levelset_grains",
        _ => "closing",
    }
}
