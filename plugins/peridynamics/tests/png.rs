//! The `pdf-png` exporter: the stress PDFs of `analysis.stress_stats` as a decodable,
//! non-blank PNG of the stated size, chosen over the sintering plugin's `png` for a Table.

mod common;
use common::*;
use grainpipe_core::registry::ExportOptions;
use grainpipe_core::{
    Artifact, ArtifactKind, ComponentConvention, Exporter, Field, FieldData, Provenance, Registry,
    Table,
};
use grainpipe_peridynamics::pdf_png::{curves, PdfPng, HEIGHT, WIDTH};
use grainpipe_peridynamics::stress_stats::{analyse, StressStatsParams};
use std::path::Path;

/// The `pdf` table of two phases: "large" with exponential x (tail exponent 1), "matrix"
/// uniform on [0, 2]; built the way the stage builds it.
fn pdf_table() -> Table {
    let (nx, ny) = (200, 200);
    let labels: Vec<u8> = (0..nx * ny)
        .map(|i| if i % nx < 100 { 1 } else { 3 })
        .collect();
    let img = image(nx, ny, labels);
    let mut rng = Rng(7);
    let data: Vec<f32> = img
        .labels
        .iter()
        .flat_map(|&l| {
            let u = rng.next();
            let s = if l == 1 {
                -(1.0 - u).ln() * 1e6
            } else {
                2.0 * u * 1e6
            };
            [0.0, s as f32, 0.0]
        })
        .collect();
    let field = Field::new(
        img.grid.clone(),
        "stress",
        "Pa",
        ComponentConvention::Voigt,
        FieldData::F32(data),
    )
    .unwrap();
    let p = StressStatsParams {
        tail_from: 1.0,
        ..Default::default()
    };
    let (stats, centres) = analyse(&p, &field, &img).unwrap();
    let mut t = Table::new("stress_pdf").with_f64("x", "1", centres);
    for s in &stats {
        t = t.with_f64(&format!("pdf_{}", s.name), "1", s.pdf.clone());
    }
    for s in &stats {
        t = t.with_f64(&format!("fit_{}", s.name), "1", s.fit_pdf.clone());
    }
    t
}

fn prov() -> Provenance {
    let mut p = Provenance::default();
    p.entries.insert("seed".into(), "7".into());
    p.entries.insert("pipeline".into(), "name: σ-test\n".into());
    p
}

/// Decodes a PNG: (width, height, RGB bytes, text chunk keywords).
fn decode(path: &Path) -> (u32, u32, Vec<u8>, Vec<String>) {
    let dec = png::Decoder::new(std::fs::File::open(path).unwrap());
    let mut reader = dec.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgb);
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    buf.truncate(info.buffer_size());
    let keys = reader
        .info()
        .utf8_text
        .iter()
        .map(|t| t.keyword.clone())
        .collect();
    (info.width, info.height, buf, keys)
}

fn count_colour(rgb: &[u8], c: [u8; 3]) -> usize {
    rgb.chunks_exact(3).filter(|p| *p == c).count()
}

#[test]
fn pdf_png_decodes_with_the_stated_size_and_shows_every_phase() {
    let t = pdf_table();
    let (x, cs) = curves(&t).unwrap();
    assert_eq!(cs.len(), 2);
    // The legend's s is the stage's fitted exponent (exponential: s = 1 within sampling).
    let s = cs[0].exponent(&x).unwrap();
    assert!((s - 1.0).abs() < 0.1, "s = {s}");
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pdf.png");
    let a = Artifact::Table(t);
    PdfPng.write_defaults(&a, &path, &prov()).unwrap();
    let (w, h, rgb, keys) = decode(&path);
    assert_eq!((w, h), (WIDTH, HEIGHT));
    assert_eq!(rgb.len(), (w * h * 3) as usize);
    let white = count_colour(&rgb, [255, 255, 255]);
    let drawn = (w * h) as usize - white;
    assert!(
        drawn > (w * h) as usize / 50,
        "only {drawn} of {} pixels drawn",
        w * h
    );
    // The markers in each phase's colour (large blue, matrix green).
    let blue = count_colour(&rgb, [31, 119, 180]);
    let green = count_colour(&rgb, [44, 160, 44]);
    assert!(blue > 200 && green > 200, "blue {blue}, green {green}");
    assert!(keys.iter().any(|k| k == "pipeline"), "{keys:?}");
    // Options set the size; no temporary file is left beside the output.
    let mut o: ExportOptions = PdfPng.default_options();
    o.insert("width".into(), serde_json::json!(640));
    o.insert("height".into(), serde_json::json!(400));
    let small = dir.path().join("small.png");
    PdfPng.write(&a, &small, &prov(), &o).unwrap();
    let (w, h, _, _) = decode(&small);
    assert_eq!((w, h), (640, 400));
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
}

#[test]
fn pdf_png_refuses_other_tables_and_bad_sizes_without_leaving_a_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("x.png");
    let other = Artifact::Table(Table::new("dem").with_f64("packing_fraction", "1", vec![0.8]));
    let e = PdfPng.write_defaults(&other, &path, &prov()).unwrap_err();
    assert!(e.contains("pdf_<phase>") && e.contains("`dem`"), "{e}");
    let mut o = PdfPng.default_options();
    o.insert("width".into(), serde_json::json!(50));
    let (key, msg) = PdfPng.check_options(&o).unwrap_err();
    assert_eq!(key, "width");
    assert!(msg.contains("200 to 8000"), "{msg}");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

/// With the sintering plugin's `png` (a ContactGraph view) registered first, a Table to
/// `.png` still reaches `pdf-png`, and a ContactGraph still reaches `png`.
#[test]
fn png_extension_is_resolved_by_artifact_kind() {
    let mut r = Registry::new();
    grainpipe_sintering::register(&mut r);
    grainpipe_peridynamics::register(&mut r);
    r.check_consistency().unwrap();
    let p = Path::new("out/stress_pdf.png");
    let name = |k| r.exporter_for(None, p, k).map(|e| e.name());
    assert_eq!(name(ArtifactKind::Table), Some("pdf-png"));
    assert_eq!(name(ArtifactKind::ContactGraph), Some("png"));
}
