//! Times the voxelizer on spheres from a CSV (`x,y,z,r` in metres after one header line),
//! without the pipeline around it:
//!
//! ```text
//! cargo run --release -p grainpipe-geometry --example voxelize_csv -- \
//!     SPHERES.csv BOX_M VOXEL_M SUPERSAMPLING [THREADS] [OUT.raw]
//! ```
//!
//! The cell is the periodic cube [0, BOX_M)^3; OUT.raw receives the labels (u8, x fastest).

use grainpipe_core::stage::SilentReporter;
use grainpipe_core::{Grid, RunContext, WorldSphere};
use grainpipe_geometry::voxelize::voxelize;
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 5 {
        return Err(
            "usage: voxelize_csv SPHERES.csv BOX_M VOXEL_M SUPERSAMPLING [THREADS] [OUT.raw]"
                .into(),
        );
    }
    let text = std::fs::read_to_string(&args[1])?;
    let mut spheres = Vec::new();
    for (i, line) in text.lines().enumerate().skip(1) {
        let v: Vec<f64> = line
            .split(',')
            .map(|t| t.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| format!("{}:{}: {e}", args[1], i + 1))?;
        spheres.push(WorldSphere {
            center: [v[0], v[1], v[2]],
            radius: v[3],
            body: i,
        });
    }
    let size: f64 = args[2].parse()?;
    let voxel: f64 = args[3].parse()?;
    let ss: usize = args[4].parse()?;
    let threads: usize = args.get(5).map(|t| t.parse()).transpose()?.unwrap_or(0);
    let grid = Grid::tiling([0.0; 3], [size; 3], [true; 3], voxel);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let ctx = RunContext::new(0, &SilentReporter);
    let start = Instant::now();
    let (labels, coverage) = pool.install(|| voxelize(&grid, &spheres, [true; 3], ss, &ctx))?;
    let wall = start.elapsed().as_secs_f64();
    let solid = labels.iter().filter(|&&l| l == 1).count() as f64 / labels.len() as f64;
    println!(
        "{} spheres, {:?} voxels, supersampling {ss}, {} threads: {wall:.3} s, solid {solid:.5}, coverage {coverage:.5}",
        spheres.len(),
        grid.dims,
        pool.current_num_threads()
    );
    if let Some(out) = args.get(6) {
        grainpipe_core::fsutil::atomic_write_bytes(std::path::Path::new(out), &labels)?;
    }
    Ok(())
}
