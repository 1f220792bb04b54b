//! Issue 35: Ctrl-C during an export stops the writer and removes its temporary file (one
//! test in its own binary: the interrupt flag is process-wide).

use grainpipe_core::*;
use grainpipe_formats::stl::StlExporter;

#[test]
fn an_interrupted_export_leaves_neither_target_nor_temporary_file() {
    let n = 8usize;
    let img = Artifact::PhaseImage(PhaseImage {
        grid: Grid {
            dims: [n, n, n],
            spacing: [1e-6; 3],
            origin: [0.0; 3],
            periodic: [false; 3],
        },
        labels: (0..n * n * n).map(|i| (i % 2) as u8).collect(),
        phases: vec![],
    });
    let d = tempfile::tempdir().unwrap();
    // Left by a killed writer (pid 0 is never alive): cleaned by this export of that target.
    let stale = d.path().join(".a.stl.0.99.grainpipe-tmp");
    std::fs::write(&stale, b"half").unwrap();
    grainpipe_core::fsutil::request_interrupt();
    let p = d.path().join("a.stl");
    let e = StlExporter
        .write_defaults(&img, &p, &Provenance::default())
        .unwrap_err();
    assert!(e.contains("interrupted"), "{e}");
    let left: Vec<_> = std::fs::read_dir(d.path()).unwrap().collect();
    assert!(left.is_empty(), "{left:?}");
    // The raw exporter too (its payload is written in blocks).
    let e = grainpipe_formats::raw::RawExporter
        .write_defaults(&img, &d.path().join("a.mhd"), &Provenance::default())
        .unwrap_err();
    assert!(e.contains("interrupted"), "{e}");
    assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 0);
}
