//! The cache follows the content of the files a pipeline reads: editing an input between two
//! runs re-runs the steps that read it (and those downstream), never serving a stale result,
//! while an untouched input is served from the cache.

use grainpipe_core::engine::{execute, plan, PlanOptions, RunOptions, SilentObserver};
use grainpipe_core::pipeline::PipelineDoc;
use std::path::Path;

fn run(yaml: &str, cache: &Path) -> grainpipe_core::engine::RunResult {
    let doc = PipelineDoc::parse(Path::new("cache.yaml"), yaml.to_string()).unwrap();
    let registry = grainpipe_cli::builtin_registry();
    let p = plan(&doc, &registry, &PlanOptions::default()).unwrap();
    let opts = RunOptions {
        cache_dir: Some(cache.to_path_buf()),
    };
    execute(&doc, &p, &opts, &mut SilentObserver).unwrap()
}

#[test]
fn editing_an_imported_file_invalidates_the_cache() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let raw = dir.path().join("labels.raw");
    // 4 x 4 x 4 labels, a quarter of them solid.
    let quarter: Vec<u8> = (0..64).map(|i| u8::from(i % 4 == 0)).collect();
    std::fs::write(&raw, &quarter).unwrap();
    let yaml = format!(
        "name: cache\nstages:\n  - id: img\n    use: import.raw\n    with: {{path: {:?}, dims: [4, 4, 4], spacing: 1 um}}\n",
        raw.display().to_string()
    );
    let fraction = |r: &grainpipe_core::engine::RunResult| {
        r.artifact("img.image")
            .as_phase_image()
            .unwrap()
            .fraction(1)
    };
    let first = run(&yaml, &cache);
    assert!(!first.stats["img"].from_cache);
    assert_eq!(fraction(&first), 0.25);
    let again = run(&yaml, &cache);
    assert!(again.stats["img"].from_cache);
    assert_eq!(fraction(&again), 0.25);
    // Same path, same size, half the voxels solid now.
    let half: Vec<u8> = (0..64).map(|i| u8::from(i % 2 == 0)).collect();
    std::fs::write(&raw, &half).unwrap();
    let edited = run(&yaml, &cache);
    assert!(
        !edited.stats["img"].from_cache,
        "a stale cache entry was served"
    );
    assert_eq!(fraction(&edited), 0.5);
}
