//! grainpipe-report: HTML reports of runs and sweeps.
//!
//! - `pipe run` records each run in its run directory (`--out DIR`, else the common parent of
//!   the exports): `run.json` ([`record::RunRecord`]) and `report-data/` (small PNG slices
//!   and renderings, tensors, tables: [`data::ReportData`]), drawn from the in-memory results
//!   so the report never re-reads gigabyte fields; with `--report` it also writes
//!   `report.html`.
//! - `pipe report DIR` renders `DIR/report.html` from those (a run directory) or from
//!   `DIR/sweep.csv` (a sweep directory).
//! - The `html` export format writes one page for any single artifact.
//!
//! Every page is one self-contained file: PNGs as data URIs, charts as inline SVG, no script
//! or style from the network. See docs/report.md.

pub mod data;
pub mod export;
pub mod html;
pub mod numbers;
pub mod page;
pub mod plots;
pub mod raster;
pub mod record;
pub mod sweep;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

pub use record::{default_run_dir, write_run_dir, RunEnd, StepRecord, WarningRecord};

/// `pipe report`.
#[derive(clap::Args, Debug)]
pub struct ReportArgs {
    /// A run directory (with run.json, written by `pipe run`) or a sweep directory (with
    /// sweep.csv, written by `pipe sweep`).
    pub dir: PathBuf,
    /// Where to write the page (default: DIR/report.html).
    #[arg(long, short)]
    pub output: Option<PathBuf>,
}

/// Adds the `html` export format.
pub fn register(r: &mut grainpipe_core::Registry) {
    r.add_exporter(export::HtmlExporter);
}

/// Renders the report of a run or sweep directory; returns the page's path.
pub fn render_dir(dir: &Path, output: Option<&Path>) -> Result<PathBuf, String> {
    let html = if dir.join(record::RUN_FILE).is_file() {
        let (rec, data, mut pics) = record::read_run_dir(dir)?;
        // The PNG exports, found where they were written (relative to the directory `pipe run`
        // ran in, else to the run directory, else in it by name).
        for e in rec.exports.iter().filter(|e| e.written) {
            let p = Path::new(&e.path);
            let found = [
                p.to_path_buf(),
                dir.join(p),
                dir.join(p.file_name().unwrap_or_default()),
            ]
            .into_iter()
            .find_map(|c| std::fs::read(c).ok());
            if let Some(b) = found.filter(|_| e.path.to_ascii_lowercase().ends_with(".png")) {
                pics.insert(page::export_key(&e.path), b);
            }
        }
        page::run_page(&rec, &data, &pics)
    } else if dir.join("sweep.csv").is_file() {
        let s = sweep::Sweep::read(dir)?;
        sweep::sweep_page(dir, &s)
    } else {
        return Err(format!(
            "{} has neither run.json (a run directory: `pipe run FILE --out DIR`) nor sweep.csv \
             (a sweep directory: `pipe sweep`)",
            dir.display()
        ));
    };
    let out = output
        .map(Path::to_path_buf)
        .unwrap_or_else(|| dir.join(record::REPORT_FILE));
    grainpipe_core::fsutil::atomic_write_bytes(&out, html.as_bytes())?;
    Ok(out)
}

pub fn report_command(args: ReportArgs, _registry: &grainpipe_core::Registry) -> ExitCode {
    match render_dir(&args.dir, args.output.as_deref()) {
        Ok(p) => {
            println!("wrote {}", p.display());
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
