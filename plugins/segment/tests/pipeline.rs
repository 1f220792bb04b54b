//! The stages through the engine: a grey-value scan written as a raw file, imported as a
//! field, median-filtered, Otsu-thresholded, cleaned, cropped and downsampled, against the
//! labels known by construction; plus the registry check and parameter errors that name
//! their key.

use grainpipe_core::testing::run_yaml;
use grainpipe_core::Registry;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::Path;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_segment::register(&mut r);
    r
}

#[test]
fn registry_is_consistent() {
    registry().check_consistency().unwrap();
}

const N: usize = 16;

fn idx(x: usize, y: usize, z: usize) -> usize {
    x + N * (y + N * z)
}

/// A 16^3 scan (f32, little endian): dark matrix (20) below z = 8, bright (100) from z = 8,
/// uniform noise of +-5. In the bright half a dark 4^3 cavity (enclosed); in the dark half
/// a bright 3^3 lump (the median leaves its centre and face centres, 7 voxels) and single
/// bright "salt" voxels (the median removes them).
fn write_scan(dir: &Path) -> String {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut v = vec![0f32; N * N * N];
    for z in 0..N {
        for y in 0..N {
            for x in 0..N {
                let cavity = (6..10).contains(&x) && (6..10).contains(&y) && (10..14).contains(&z);
                let lump = (2..5).contains(&x) && (2..5).contains(&y) && (2..5).contains(&z);
                let bright = (z >= 8 && !cavity) || lump;
                let base = if bright { 100.0 } else { 20.0 };
                v[idx(x, y, z)] = base + rng.random_range(-5.0f32..5.0);
            }
        }
    }
    for (x, y, z) in [(10, 3, 1), (12, 12, 5), (0, 0, 0), (15, 8, 7)] {
        v[idx(x, y, z)] = 100.0;
    }
    let path = dir.join("scan.raw");
    let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(&path, bytes).unwrap();
    serde_json::to_string(&path.display().to_string()).unwrap()
}

fn pipeline(path: &str, clean: &str) -> String {
    format!(
        "name: t
stages:
  - id: scan
    use: import.raw
    with: {{ path: {path}, dims: [16, 16, 16], dtype: f32, spacing: 2 um, as: field, unit: '1' }}
  - id: smooth
    use: segment.filter
    in: {{ field: scan.field }}
    with: {{ method: median, radius: 1 }}
  - id: seg
    use: segment.threshold
    in: {{ field: smooth.field }}
    with: {{ method: otsu, names: [matrix, grain] }}
  - id: clean
    use: segment.clean
    in: {{ image: seg.image }}
    with: {clean}
  - id: sub
    use: segment.crop
    in: {{ image: clean.image }}
    with: {{ start: [0, 0, 4], size: [0, 0, 8] }}
  - id: coarse
    use: segment.downsample
    in: {{ image: sub.image }}
    with: {{ factor: 2 }}
"
    )
}

#[test]
fn filter_threshold_clean_gives_the_constructed_labels() {
    let d = tempfile::tempdir().unwrap();
    let path = write_scan(d.path());
    let res = run_yaml(
        &registry(),
        &pipeline(
            &path,
            "{ min_size: 80 um^3, fill_holes: [0], relabel: [[1, 2]] }",
        ),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    // Otsu's threshold lies between the two noisy levels (15..25 and 95..105 before the
    // median; every threshold in the empty gap between them scores the same and the first,
    // just above the darker values, is taken).
    let upper = res.column("seg.classes", "upper");
    assert!(upper[0] > 15.0 && upper[0] < 95.0, "threshold {}", upper[0]);
    let smooth = res.artifact("smooth.field").as_field().unwrap();
    let t = upper[0];
    let (dark_max, bright_min) = (0..N * N * N).fold((f64::MIN, f64::MAX), |(a, b), i| {
        let v = smooth.data.get(i);
        if v < 60.0 {
            (a.max(v), b)
        } else {
            (a, b.min(v))
        }
    });
    assert!(
        dark_max < t && t <= bright_min,
        "{dark_max} < {t} <= {bright_min}"
    );
    // Before cleaning: the median left the cavity without its corners and edges (32 of 64
    // voxels) and the lump as its centre and face centres (7 voxels).
    let seg = res.artifact("seg.image").as_phase_image().unwrap();
    assert_eq!(seg.labels[idx(7, 7, 11)], 0, "cavity");
    assert_eq!(seg.labels[idx(3, 3, 3)], 1, "lump centre");
    assert_eq!(
        seg.labels.iter().filter(|&&l| l == 1).count(),
        8 * 256 - 32 + 7
    );
    // After cleaning: exactly the two halves, the grain relabelled 2.
    let clean = res.artifact("clean.image").as_phase_image().unwrap();
    let want: Vec<u8> = (0..N * N * N)
        .map(|i| if i / (N * N) >= 8 { 2 } else { 0 })
        .collect();
    assert_eq!(clean.labels, want);
    let names: Vec<(u8, &str)> = clean
        .phases
        .iter()
        .map(|p| (p.id, p.name.as_str()))
        .collect();
    assert_eq!(names, vec![(0, "matrix"), (2, "grain")]);
    assert_eq!(res.column("clean.summary", "components"), vec![1.0, 1.0]);
    assert_eq!(res.column("clean.summary", "voxels"), vec![7.0, 32.0]);
    // Crop z 4..12: origin 8 um up, z no longer periodic (it was not); 16 x 16 x 8.
    let sub = res.artifact("sub.image").as_phase_image().unwrap();
    assert_eq!(sub.grid.dims, [16, 16, 8]);
    assert!((sub.grid.origin[2] - 8e-6).abs() < 1e-18);
    // Downsample by 2: 8 x 8 x 4 of 4 um; the lower two planes matrix, the upper two grain.
    let coarse = res.artifact("coarse.image").as_phase_image().unwrap();
    assert_eq!(coarse.grid.dims, [8, 8, 4]);
    assert!((coarse.grid.spacing[0] - 4e-6).abs() < 1e-18);
    let want: Vec<u8> = (0..256).map(|i| if i / 64 >= 2 { 2 } else { 0 }).collect();
    assert_eq!(coarse.labels, want);
}

#[test]
fn parameter_errors_name_their_key() {
    let d = tempfile::tempdir().unwrap();
    let path = write_scan(d.path());
    let cases = [
        (
            pipeline(&path, "{ relabel: [[1, 2], [1, 3]] }"),
            "relabel",
            "mapped twice",
        ),
        (
            pipeline(&path, "{}").replace("size: [0, 0, 8]", "size: [0, 0, 14]"),
            "size",
            "at most 12 fit",
        ),
        (
            pipeline(&path, "{}").replace("factor: 2", "factor: 3"),
            "factor",
            "crop to 15 voxels",
        ),
        (
            pipeline(&path, "{}").replace("method: otsu,", "method: manual,"),
            "thresholds",
            "needs at least one threshold",
        ),
        (
            pipeline(&path, "{}").replace("method: otsu,", "method: otsu, classes: 3,"),
            "classes",
            "multi_otsu",
        ),
        (
            pipeline(&path, "{}").replace("names: [matrix, grain]", "names: [a, b, c]"),
            "names",
            "3 names for 2 classes",
        ),
    ];
    for (yaml, key, words) in cases {
        let Err(e) = run_yaml(&registry(), &yaml) else {
            panic!("`{key}` case ran");
        };
        let text = format!("{e}");
        let related: Vec<String> = e.related.iter().map(|r| r.to_string()).collect();
        let all = format!("{text} {}", related.join(" "));
        assert!(
            all.contains(&format!("`{key}`")) && all.contains(words),
            "expected `{key}` and `{words}` in: {all}"
        );
    }
}

#[test]
fn multi_otsu_and_gaussian_through_the_engine() {
    // Three levels along x (10, 50, 90) without noise: a Gaussian of sigma 0.5 voxel blurs
    // only the planes next to the steps; multi-Otsu puts one threshold in each step.
    let d = tempfile::tempdir().unwrap();
    let mut v = vec![0f64; N * N * N];
    for (i, x) in v.iter_mut().enumerate() {
        *x = [10.0, 50.0, 90.0][(i % N) * 3 / N];
    }
    let path = d.path().join("levels.raw");
    std::fs::write(
        &path,
        v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>(),
    )
    .unwrap();
    let path = serde_json::to_string(&path.display().to_string()).unwrap();
    let yaml = format!(
        "name: t
stages:
  - id: scan
    use: import.raw
    with: {{ path: {path}, dims: [16, 16, 16], dtype: f64, spacing: 1 um, as: field }}
  - id: smooth
    use: segment.filter
    in: {{ field: scan.field }}
    with: {{ method: gaussian, sigma: '0.5 um' }}
  - id: seg
    use: segment.threshold
    in: {{ field: smooth.field }}
    with: {{ method: multi_otsu, classes: 3 }}
"
    );
    let res = run_yaml(&registry(), &yaml).unwrap_or_else(|e| panic!("{e}"));
    // sigma = 0.5 um on 1 um voxels: weights exp(-2 k^2) for k = -2..=2 (truncated at
    // ceil(4 x 0.5)), normalised. At x = 5 (10, next to 50 at x = 6, 7) the value is
    // 10 + 40 (w1 + w2).
    let w: Vec<f64> = (-2i32..=2).map(|k| (-2.0 * (k * k) as f64).exp()).collect();
    let s: f64 = w.iter().sum();
    let smooth = res.artifact("smooth.field").as_field().unwrap();
    let want = 10.0 + 40.0 * (w[3] + w[4]) / s;
    assert!((smooth.data.get(idx(5, 3, 3)) - want).abs() < 1e-12);
    let im = res.artifact("seg.image").as_phase_image().unwrap();
    // Columns x: 0..6 -> 10, 6..11 -> 50, 11..16 -> 90 ((x * 3) / 16).
    for (i, &l) in im.labels.iter().enumerate() {
        let want = ((i % N) * 3 / N) as u8;
        assert_eq!(l, want, "voxel {i}");
    }
    let names: Vec<&str> = im.phases.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, vec!["pore", "binder", "grain"]);
    let upper = res.column("seg.classes", "upper");
    assert!(upper[0] > 10.0 && upper[0] < 50.0 && upper[1] > 50.0 && upper[1] < 90.0);
}

#[test]
fn sizes_in_voxels_or_units_survive_normalisation() {
    // The canonical parameters (what the cache key hashes and preflight reads back) keep a
    // length or volume apart from a number of voxels.
    let r = registry();
    let filter = &r.stage("segment.filter").unwrap().stage;
    let n = filter
        .normalize_params(&serde_json::json!({"sigma": "0.5 um"}))
        .unwrap();
    assert_eq!(n["sigma"], serde_json::json!("5e-7 m"));
    assert_eq!(filter.normalize_params(&n).unwrap(), n);
    let n = filter
        .normalize_params(&serde_json::json!({"sigma": 2}))
        .unwrap();
    assert_eq!(n["sigma"], serde_json::json!(2.0));
    let clean = &r.stage("segment.clean").unwrap().stage;
    let n = clean
        .normalize_params(&serde_json::json!({"min_size": "1000 um^3"}))
        .unwrap();
    let text = n["min_size"].as_str().unwrap();
    let si: f64 = text.strip_suffix(" m^3").unwrap().parse().unwrap();
    assert!((si / 1e-15 - 1.0).abs() < 1e-15, "{text}");
    assert_eq!(clean.normalize_params(&n).unwrap(), n);
    let e = clean
        .normalize_params(&serde_json::json!({"min_size": "3 um"}))
        .unwrap_err();
    assert!(e.to_string().contains("min_size"), "{e}");
}
