//! Bounded fuzzing (issue 17): mutants of real inputs — pipeline YAML, `--set` overrides,
//! `.vti` files, raw layouts and cache entries — must give errors, never panics. Each target
//! runs a fixed-seed mutation stream for a fixed time budget (about a second), so the suite
//! stays fast and a failure names a reproducible input.

use grainpipe_core::engine::{execute, plan, PlanOptions, RunOptions, SilentObserver};
use grainpipe_core::pipeline::PipelineDoc;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::time::{Duration, Instant};

const BUDGET: Duration = Duration::from_millis(1200);
const MIN_CASES: u64 = 12;

fn root() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// One mutation of `input`: bit flips, byte changes, deletions, duplications, insertions of
/// interesting tokens (huge numbers, units, YAML syntax).
fn mutate(input: &[u8], rng: &mut ChaCha8Rng) -> Vec<u8> {
    const TOKENS: &[&str] = &[
        "9223372036854775809",
        "-1",
        "0",
        "1e308",
        "nan",
        ".inf",
        "1e-300",
        "18446744073709551615",
        "4294967296",
        " um",
        " m",
        " W",
        ": ",
        "- ",
        "[",
        "]",
        "{",
        "}",
        "\n",
        "'",
        "\"",
        "&a",
        "*a",
        "!!binary",
        "~",
        "null",
        "true",
        "\t",
    ];
    let mut v = input.to_vec();
    for _ in 0..rng.random_range(1..4) {
        let n = v.len().max(1);
        let at = rng.random_range(0..n).min(v.len());
        match rng.random_range(0..6) {
            0 if !v.is_empty() => {
                let i = at.min(v.len() - 1);
                v[i] ^= 1 << rng.random_range(0..8);
            }
            1 if !v.is_empty() => {
                let i = at.min(v.len() - 1);
                v[i] = rng.random();
            }
            2 => {
                let end = (at + rng.random_range(1..16)).min(v.len());
                v.drain(at..end);
            }
            3 => {
                let end = (at + rng.random_range(1..32)).min(v.len());
                let chunk = v[at..end].to_vec();
                v.splice(at..at, chunk);
            }
            _ => {
                let t = TOKENS[rng.random_range(0..TOKENS.len())];
                v.splice(at..at, t.bytes());
            }
        }
    }
    v
}

/// Runs `case` on mutants of every seed until the budget is spent; a panic fails the test
/// with the mutant.
fn fuzz(name: &str, seeds: &[Vec<u8>], mut case: impl FnMut(&[u8])) {
    let mut rng = ChaCha8Rng::seed_from_u64(0x17);
    let start = Instant::now();
    let mut n = 0u64;
    // At least MIN_CASES whatever the load: a busy machine must not fail the test by
    // leaving no time for cases (a mutant of a real pipeline may take 0.2 s to plan).
    while start.elapsed() < BUDGET || n < MIN_CASES {
        let seed = &seeds[(n as usize) % seeds.len()];
        let m = mutate(seed, &mut rng);
        if catch_unwind(AssertUnwindSafe(|| case(&m))).is_err() {
            panic!(
                "{name}: mutant {n} panicked:\n{}",
                String::from_utf8_lossy(&m)
            );
        }
        n += 1;
    }
    assert!(n >= MIN_CASES, "{name}: only {n} cases ran");
}

fn pipelines() -> Vec<Vec<u8>> {
    let mut v: Vec<Vec<u8>> = std::fs::read_dir(root().join("pipelines"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "yaml"))
        .map(|p| std::fs::read(p).unwrap())
        .collect();
    v.sort();
    v
}

#[test]
fn yaml_mutants_plan_or_fail_cleanly() {
    let registry = grainpipe_cli::builtin_registry();
    let dir = tempfile::tempdir().unwrap();
    fuzz("yaml", &pipelines(), |m| {
        let text = String::from_utf8_lossy(m).into_owned();
        if let Ok(d) = PipelineDoc::parse(&dir.path().join("f.yaml"), text) {
            let _ = plan(
                &d,
                &registry,
                &PlanOptions {
                    targets: vec![],
                    memory_limit: Some(1 << 30),
                },
            );
        }
    });
}

#[test]
fn set_override_mutants_fail_cleanly() {
    let registry = grainpipe_cli::builtin_registry();
    let base = PipelineDoc::load(&root().join("pipelines/spheres.yaml")).unwrap();
    let seeds: Vec<Vec<u8>> = [
        "pack.volume_fraction=0.25",
        "pack.size=[100 um, 100 um, 100 um]",
        "pack.radius={kind: weibull, scale: 15 um, shape: 3}",
        "voxels.voxels_per_diameter=8",
    ]
    .iter()
    .map(|s| s.as_bytes().to_vec())
    .collect();
    fuzz("--set", &seeds, |m| {
        let mut d = base.clone();
        if d.apply_override(&String::from_utf8_lossy(m)).is_ok() {
            let _ = plan(
                &d,
                &registry,
                &PlanOptions {
                    targets: vec![],
                    memory_limit: Some(1 << 30),
                },
            );
        }
    });
}

#[test]
fn vti_and_raw_mutants_read_or_fail_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let img = grainpipe_core::Artifact::PhaseImage(grainpipe_core::PhaseImage {
        grid: grainpipe_core::Grid {
            dims: [6, 5, 4],
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
        labels: (0..120).map(|i| (i % 3) as u8).collect(),
        phases: vec![],
    });
    let vti = dir.path().join("seed.vti");
    grainpipe_formats::write_vti(&img, &vti, &Default::default()).unwrap();
    let seeds = vec![std::fs::read(&vti).unwrap()];
    let path = dir.path().join("m.vti");
    fuzz("vti", &seeds, |m| {
        std::fs::write(&path, m).unwrap();
        if let Ok(v) = grainpipe_formats::read_vti(&path, None) {
            let _ = v.into_phase_image();
        }
    });
    // Raw layouts: any dims, dtype and header against a small file.
    let raw = dir.path().join("r.raw");
    std::fs::write(&raw, [0u8; 24]).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let start = Instant::now();
    while start.elapsed() < BUDGET / 4 {
        let dim = |rng: &mut ChaCha8Rng| match rng.random_range(0..4) {
            0 => rng.random::<u64>() as usize,
            1 => 1usize << rng.random_range(0..64),
            _ => rng.random_range(0..30),
        };
        let layout = grainpipe_formats::RawLayout {
            dims: [dim(&mut rng), dim(&mut rng), dim(&mut rng)],
            dtype: [
                grainpipe_formats::RawDtype::U8,
                grainpipe_formats::RawDtype::U16,
                grainpipe_formats::RawDtype::F64,
            ][rng.random_range(0..3)],
            endian: grainpipe_formats::Endian::Little,
            header_bytes: if rng.random() {
                rng.random()
            } else {
                rng.random_range(0..8)
            },
        };
        let r = catch_unwind(|| grainpipe_formats::read_raw(&raw, &layout, [1e-6; 3], [0.0; 3]));
        let v = r.unwrap_or_else(|_| panic!("raw layout {layout:?} panicked"));
        if let Ok(v) = v {
            assert_eq!(
                Some(v.data.len()),
                grainpipe_core::checked_product(&layout.dims)
            );
        }
    }
}

#[test]
fn cache_entry_mutants_are_recomputed_never_trusted() {
    let dir = tempfile::tempdir().unwrap();
    let yaml = "name: f\nseed: 1\nstages:\n  - id: pack\n    use: packing.rsa\n    with: { size: [120 um, 120 um, 120 um], volume_fraction: 0.1 }\n";
    let d = PipelineDoc::parse(&dir.path().join("f.yaml"), yaml.into()).unwrap();
    let registry = grainpipe_cli::builtin_registry();
    let p = plan(&d, &registry, &PlanOptions::default()).unwrap();
    let cache = dir.path().join("cache");
    let opts = RunOptions {
        cache_dir: Some(cache.clone()),
    };
    let reference = execute(&d, &p, &opts, &mut SilentObserver).unwrap();
    let entry = cache.join(format!("{}.bin", p.steps[0].as_ref().unwrap().cache_key));
    let good = std::fs::read(&entry).unwrap();
    fuzz("cache", &[good], |m| {
        std::fs::write(&entry, m).unwrap();
        let r = execute(&d, &p, &opts, &mut SilentObserver).expect("recomputed");
        // Served or recomputed, the result is the reference.
        assert_eq!(
            r.outputs["pack"]["packing"],
            reference.outputs["pack"]["packing"]
        );
    });
}

#[test]
fn plugin_artifact_metadata_mutants_are_validated() {
    // What a plugin states about an output (grid dims, component counts) against the arrays
    // it filled: random, often huge, dims must be refused by validation, never wrap.
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let start = Instant::now();
    while start.elapsed() < BUDGET / 4 {
        let d = |rng: &mut ChaCha8Rng| match rng.random_range(0..3) {
            0 => 1usize << rng.random_range(0..64),
            1 => rng.random::<u64>() as usize,
            _ => rng.random_range(0..5),
        };
        let grid = grainpipe_core::Grid {
            dims: [d(&mut rng), d(&mut rng), d(&mut rng)],
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        };
        let n = rng.random_range(0..70);
        let labels = vec![0u8; n];
        let a = grainpipe_core::Artifact::PhaseImage(grainpipe_core::PhaseImage {
            grid: grid.clone(),
            labels,
            phases: vec![],
        });
        let ok = catch_unwind(AssertUnwindSafe(|| a.validate().is_ok()))
            .unwrap_or_else(|_| panic!("validate panicked on {grid:?}"));
        assert_eq!(
            ok,
            grid.checked_voxel_count() == Some(n) && n > 0,
            "{grid:?} with {n}"
        );
    }
}
