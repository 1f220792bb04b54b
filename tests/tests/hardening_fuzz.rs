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

// ------------------------------------------------------------------ issue 35

/// Declared size fields of the importers: HDF5 datasets (chunked, nothing written) and
/// NetCDF-less raw layouts of any shape, VTI size and compression headers of any value, and
/// dumps of any atom count, against small files: an error or a read of the right size, never
/// an allocation of what a header claims (which aborts the test process).
#[test]
fn declared_sizes_and_compression_headers_are_bounded_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(35);
    let start = Instant::now();
    let mut n = 0;
    // HDF5: shapes up to 2^40 per axis, read through the header, the label scan and the
    // full reader.
    while start.elapsed() < BUDGET / 2 || n < MIN_CASES {
        let p = dir.path().join(format!("h{n}.h5"));
        let rank = rng.random_range(2..5usize);
        let shape: Vec<usize> = (0..rank)
            .map(|_| match rng.random_range(0..3) {
                0 => 1usize << rng.random_range(0..40),
                1 => rng.random_range(1..300),
                _ => rng.random_range(1..4),
            })
            .collect();
        let made = (|| -> hdf5_metno::Result<()> {
            let f = hdf5_metno::File::create(&p)?;
            let chunk: Vec<usize> = shape.iter().map(|&s| s.min(8)).collect();
            f.new_dataset::<u16>()
                .chunk(chunk)
                .shape(&shape[..])
                .create("d")?;
            Ok(())
        })();
        n += 1;
        if made.is_err() {
            continue;
        }
        let declared: Option<u64> = shape.iter().try_fold(2u64, |a, &s| a.checked_mul(s as u64));
        let r = catch_unwind(AssertUnwindSafe(|| {
            // A read is only attempted where the test machine could hold it.
            if declared.is_some_and(|b| b <= 64 << 20) {
                let v = grainpipe_formats::read_hdf5_dataset(&p, "d").unwrap();
                assert_eq!(Some(v.data.len() as u64 * 2), declared);
            } else if declared.is_none_or(|b| b > grainpipe_formats::volume::memory_budget()) {
                let e = grainpipe_formats::read_hdf5_dataset(&p, "d").unwrap_err();
                assert!(e.contains("declares"), "{shape:?}: {e}");
            }
            let registry = grainpipe_cli::builtin_registry();
            let yaml = format!(
                "name: f\nstages:\n  - id: i\n    use: import.hdf5\n    with: {{path: '{}', \
                 dataset: d, spacing: 1 um}}\n",
                p.display()
            );
            let d = PipelineDoc::parse(&dir.path().join("f.yaml"), yaml).unwrap();
            let _ = plan(
                &d,
                &registry,
                &PlanOptions {
                    targets: vec![],
                    memory_limit: Some(1 << 30),
                },
            );
        }));
        assert!(r.is_ok(), "hdf5 shape {shape:?} panicked");
        let _ = std::fs::remove_file(&p);
    }
    // VTI: a zlib-compressed array of a small extent whose compression header states random
    // block counts and sizes (zlib bombs: a claimed size far above the extent's).
    let img = grainpipe_core::Artifact::PhaseImage(grainpipe_core::PhaseImage {
        grid: grainpipe_core::Grid {
            dims: [4, 3, 2],
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
        labels: vec![0; 24],
        phases: vec![],
    });
    let good = dir.path().join("g.vti");
    grainpipe_formats::write_vti(&img, &good, &Default::default()).unwrap();
    let text = std::fs::read_to_string(&good).unwrap();
    use base64::Engine;
    let b64 = base64::engine::general_purpose::STANDARD;
    // Zeros compress 1000:1: a body that honestly inflates to `big` bytes.
    let big = 1usize << 24;
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
    std::io::Write::write_all(&mut z, &vec![0u8; big]).unwrap();
    let bomb = z.finish().unwrap();
    let m = dir.path().join("m.vti");
    let start = Instant::now();
    let mut k = 0;
    while start.elapsed() < BUDGET / 2 || k < MIN_CASES {
        k += 1;
        let header: Vec<u64> = match rng.random_range(0..3) {
            0 => vec![1, big as u64, big as u64, bomb.len() as u64],
            1 => vec![1, rng.random::<u32>() as u64, 0, bomb.len() as u64],
            _ => vec![
                rng.random_range(1..4),
                1u64 << rng.random_range(0..40),
                rng.random_range(0..1 << 20),
                bomb.len() as u64,
            ],
        };
        let hbytes: Vec<u8> = header.iter().flat_map(|h| h.to_le_bytes()).collect();
        let payload = format!("{}{}", b64.encode(&hbytes), b64.encode(&bomb));
        // Replace the phase array's payload (the one after `Name="phase"`).
        let at = text.find("Name=\"phase\"").expect("phase array");
        let open = at + text[at..].find('>').unwrap() + 1;
        let close = open + text[open..].find('<').unwrap();
        let mutated = format!("{}{}{}", &text[..open], payload, &text[close..])
            .replace("header_type=\"UInt32\"", "header_type=\"UInt64\"");
        std::fs::write(&m, mutated).unwrap();
        let r = catch_unwind(AssertUnwindSafe(|| grainpipe_formats::read_vti(&m, None)));
        match r {
            Ok(Ok(v)) => assert_eq!(v.data.len(), 24, "header {header:?}"),
            Ok(Err(_)) => {}
            Err(_) => panic!("vti compression header {header:?} panicked"),
        }
    }
    // Dumps: atom counts up to 2^64 - 1 against two listed atoms.
    let registry = grainpipe_cli::builtin_registry();
    for count in ["3", "1000000000000", "18446744073709551615", "4294967297"] {
        let dump = dir.path().join("d.dump");
        std::fs::write(
            &dump,
            format!(
                "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n{count}\nITEM: BOX BOUNDS pp pp pp\n\
                 0 1\n0 1\n0 1\nITEM: ATOMS id x y z radius\n1 0.5 0.5 0.5 0.1\n2 0.2 0.2 0.2 0.1\n"
            ),
        )
        .unwrap();
        let yaml = format!(
            "name: f\nstages:\n  - id: i\n    use: import.packing\n    with: {{path: '{}'}}\n",
            dump.display()
        );
        let d = PipelineDoc::parse(&dir.path().join("f.yaml"), yaml).unwrap();
        let e = plan(&d, &registry, &PlanOptions::default())
            .err()
            .unwrap_or_else(|| panic!("{count} atoms accepted"));
        assert!(e.to_string().contains("but lists 2"), "{e}");
    }
}

/// Exporters' path collisions: random sets of export targets from an alphabet of spellings
/// of the same files (`./`, `sub/..`, a `.mhd` and its `.raw`, a `.csv` and its
/// `.csv.json`, a TIFF directory stack and a file in its directory) are planned exactly when
/// no two exports write one file, as an independent model of what each writes says.
#[test]
fn export_path_collisions_are_refused_exactly() {
    let registry = grainpipe_cli::builtin_registry();
    let dir = tempfile::tempdir().unwrap();
    // (from, to, with, files written relative to the pipeline's directory; a trailing `/`
    // marks a directory replaced as a whole)
    let targets: &[(&str, &str, &str, &[&str])] = &[
        ("vox.image", "out/a.vti", "", &["out/a.vti"]),
        ("vox.image", "out/./a.vti", "", &["out/a.vti"]),
        ("vox.image", "out/sub/../a.vti", "", &["out/a.vti"]),
        ("vox.image", "out/a.mhd", "", &["out/a.mhd", "out/a.raw"]),
        ("vox.image", "out/a.raw", "", &["out/a.raw", "out/a.mhd"]),
        ("vox.image", "out/b.mhd", "", &["out/b.mhd", "out/b.raw"]),
        (
            "vox.report",
            "out/t.csv",
            "",
            &["out/t.csv", "out/t.csv.json"],
        ),
        ("vox.report", "out/t.csv.json", "", &["out/t.csv.json"]),
        ("vox.report", "out/u.json", "", &["out/u.json"]),
        (
            "vox.image",
            "out/ct.tif",
            "{stack: directory}",
            &["out/ct/"],
        ),
        ("vox.image", "out/ct.tif", "", &["out/ct.tif"]),
        (
            "vox.image",
            "out/ct/ct_0000.tif",
            "",
            &["out/ct/ct_0000.tif"],
        ),
        ("vox.image", "out/ct/../a.stl", "", &["out/a.stl"]),
        ("vox.image", "out/a.stl", "", &["out/a.stl"]),
    ];
    let clash = |a: &[&str], b: &[&str]| {
        a.iter().any(|x| {
            b.iter().any(|y| {
                x == y
                    || (y.ends_with('/') && x.starts_with(y))
                    || (x.ends_with('/') && y.starts_with(x))
            })
        })
    };
    let mut rng = ChaCha8Rng::seed_from_u64(36);
    let start = Instant::now();
    let mut n = 0;
    while start.elapsed() < BUDGET || n < 4 * MIN_CASES {
        n += 1;
        let k = rng.random_range(1..5);
        let pick: Vec<usize> = (0..k).map(|_| rng.random_range(0..targets.len())).collect();
        let mut yaml = String::from(
            "name: f\nseed: 1\nstages:\n  - id: pack\n    use: packing.rsa\n    with: { size: \
             [60 um, 60 um, 60 um], radius: { kind: fixed, value: 15 um }, volume_fraction: \
             0.1 }\n  - id: vox\n    use: voxelize.packing\n    in: { packing: pack.packing }\n    \
             with: { voxel_size: 10 um }\nexport:\n",
        );
        for &i in &pick {
            let (from, to, with, _) = targets[i];
            let with = if with.is_empty() {
                String::new()
            } else {
                format!(", with: {with}")
            };
            yaml.push_str(&format!("  - {{ from: {from}, to: {to}{with} }}\n"));
        }
        let expect_ok =
            (0..pick.len()).all(|a| (0..a).all(|b| !clash(targets[pick[a]].3, targets[pick[b]].3)));
        let d = PipelineDoc::parse(&dir.path().join("f.yaml"), yaml.clone()).unwrap();
        // Paths are relative to the working directory: the tempdir's `out` never exists, so
        // the comparison is the lexical one plus the working directory.
        let r = plan(&d, &registry, &PlanOptions::default());
        assert_eq!(
            r.is_ok(),
            expect_ok,
            "{yaml}\n{}",
            r.err().map(|e| e.to_string()).unwrap_or_default()
        );
    }
}
