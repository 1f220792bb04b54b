//! Issue 35, importers and exporters under hostile input: small files declaring huge arrays
//! are refused by the memory check before anything is allocated (exit 2, not an abort),
//! exports never overwrite each other (implicit files and `..` paths included), a killed or
//! interrupted export leaves no temporary file behind, non-ASCII YAML does not break TIFF
//! exports, a NaN origin is an input error. Every input is generated here, small.

use std::path::Path;
use std::process::Command;

fn pipe(args: &[&str], dir: &Path) -> (i32, String, String) {
    // Spawned under the HDF5 lock: a child forked while another test holds an HDF5 file open
    // inherits its descriptor and with it the library's file lock, so a later `pipe` opening
    // that file fails with "NetCDF: HDF error" (seen once in CI).
    let child = {
        let _g = hdf5_lock();
        Command::new(env!("CARGO_BIN_EXE_pipe"))
            .args(args)
            .current_dir(dir)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .expect("pipe runs")
    };
    let out = child.wait_with_output().expect("pipe runs");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// A pipeline importing `with` (flow YAML) through `stage`, exported nowhere (every step
/// runs).
fn import_yaml(stage: &str, with: &str) -> String {
    format!("name: t\nstages:\n  - id: imp\n    use: {stage}\n    with: {with}\n")
}

// ------------------------------------------------------------------ A: declared sizes

/// The HDF5 library (under NetCDF-4 too) is not thread-safe: tests write their files one at
/// a time, and no child process is spawned while one of them is open (see `pipe`).
static HDF5: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn hdf5_lock() -> std::sync::MutexGuard<'static, ()> {
    HDF5.lock().unwrap_or_else(|e| e.into_inner())
}

/// An HDF5 file of a few KB declaring a chunked 4000^3 u16 dataset (no chunk written).
fn huge_h5(path: &Path, shape: &[usize]) {
    let _g = hdf5_lock();
    let f = hdf5_metno::File::create(path).unwrap();
    let chunk: Vec<usize> = shape.iter().map(|_| 16).collect();
    f.new_dataset::<u16>()
        .chunk(chunk)
        .shape(shape)
        .create("big")
        .unwrap();
}

/// A NetCDF-4 file of a few KB declaring a 4000^3 i16 variable `labels` (nothing written),
/// returned open. Call it under [`hdf5_lock`].
fn huge_nc(path: &Path) -> netcdf::FileMut {
    let mut f = netcdf::create(path).unwrap();
    for n in ["z", "y", "x"] {
        f.add_dimension(n, 4000).unwrap();
    }
    f.add_variable::<i16>("labels", &["z", "y", "x"]).unwrap();
    f
}

#[test]
fn a_small_hdf5_declaring_4000_cubed_is_refused_by_the_memory_check_not_read() {
    let d = tempfile::tempdir().unwrap();
    huge_h5(&d.path().join("big.h5"), &[4000, 4000, 4000]);
    assert!(std::fs::metadata(d.path().join("big.h5")).unwrap().len() < 64 << 10);
    std::fs::write(
        d.path().join("p.yaml"),
        import_yaml("import.hdf5", "{path: big.h5, dataset: big, spacing: 1 um}"),
    )
    .unwrap();
    for cmd in ["validate", "run"] {
        let (code, _, err) = pipe(&[cmd, "p.yaml", "--no-cache"][..2], d.path());
        // Before: the label check read 4000^3 values at preflight and aborted (134).
        assert_eq!(code, 2, "{cmd}: {err}");
        assert!(err.contains("of memory but"), "{cmd}: {err}");
    }
}

#[test]
fn a_small_netcdf_declaring_4000_cubed_is_refused_by_the_memory_check_not_read() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("big.nc");
    {
        let _g = hdf5_lock();
        huge_nc(&p);
    }
    assert!(std::fs::metadata(&p).unwrap().len() < 64 << 10);
    std::fs::write(
        d.path().join("p.yaml"),
        import_yaml(
            "import.netcdf",
            "{path: big.nc, variable: labels, spacing: 1 um}",
        ),
    )
    .unwrap();
    let (code, _, err) = pipe(&["validate", "p.yaml"], d.path());
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("of memory but"), "{err}");
}

/// A process that inherited an open NetCDF-4 file (here a child forked while the file was
/// being written) keeps HDF5's lock on it: the import names the likely cause and the way out,
/// and with that way out the file reaches the memory check.
#[test]
fn a_netcdf_file_locked_by_another_process_names_the_lock() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("big.nc");
    let mut holder = {
        let _g = hdf5_lock();
        let f = huge_nc(&p);
        // Forked while `f` is open: the child holds HDF5's lock on it.
        let child = Command::new("sleep").arg("60").spawn().unwrap();
        drop(f);
        child
    };
    std::fs::write(
        d.path().join("p.yaml"),
        import_yaml(
            "import.netcdf",
            "{path: big.nc, variable: labels, spacing: 1 um}",
        ),
    )
    .unwrap();
    let (code, _, err) = pipe(&["validate", "p.yaml"], d.path());
    let unlocked = Command::new(env!("CARGO_BIN_EXE_pipe"))
        .args(["validate", "p.yaml"])
        .current_dir(d.path())
        .env("HDF5_USE_FILE_LOCKING", "FALSE")
        .output()
        .unwrap();
    holder.kill().ok();
    holder.wait().ok();
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("open for writing") && err.contains("HDF5_USE_FILE_LOCKING=FALSE"),
        "{err}"
    );
    let err = String::from_utf8_lossy(&unlocked.stderr);
    assert_eq!(unlocked.status.code(), Some(2), "{err}");
    assert!(err.contains("of memory but"), "{err}");
}

#[test]
fn a_300_byte_dump_claiming_10_to_the_12_atoms_is_an_error_with_its_line() {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(
        d.path().join("d.dump"),
        "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n1000000000000\nITEM: BOX BOUNDS pp pp pp\n\
         0 1\n0 1\n0 1\nITEM: ATOMS id x y z radius\n1 0.5 0.5 0.5 0.1\n2 0.2 0.2 0.2 0.1\n",
    )
    .unwrap();
    std::fs::write(
        d.path().join("p.yaml"),
        import_yaml("import.packing", "{path: d.dump}"),
    )
    .unwrap();
    let (code, _, err) = pipe(&["validate", "p.yaml"], d.path());
    // Before: Vec::with_capacity(10^12) aborted.
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("d.dump:12: frame 0 announces 1000000000000 atoms but lists 2"),
        "{err}"
    );
}

#[test]
fn a_labels_check_streams_through_slabs_and_names_the_voxel() {
    // 300 x 100 x 100 u16 (6 MB): three slabs of the streamed scan; the bad label in the
    // last one.
    let d = tempfile::tempdir().unwrap();
    let (nz, ny, nx) = (300usize, 100usize, 100usize);
    let mut v = vec![1u16; nz * ny * nx];
    v[(290 * ny + 7) * nx + 3] = 300;
    let g = hdf5_lock();
    let f = hdf5_metno::File::create(d.path().join("l.h5")).unwrap();
    f.new_dataset::<u16>()
        .shape([nz, ny, nx])
        .create("l")
        .unwrap()
        .write_raw(&v)
        .unwrap();
    drop(f);
    drop(g);
    std::fs::write(
        d.path().join("p.yaml"),
        import_yaml("import.hdf5", "{path: l.h5, dataset: l, spacing: 1 um}"),
    )
    .unwrap();
    let (code, _, err) = pipe(&["validate", "p.yaml"], d.path());
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("voxel (x=3, y=7, z=290) holds 300") && err.contains("values span 1 .. 300"),
        "{err}"
    );
}

// ------------------------------------------------------------------ D: bad errors

#[test]
fn a_nan_origin_in_the_file_is_an_input_error_at_the_origin_key() {
    let d = tempfile::tempdir().unwrap();
    let g = hdf5_lock();
    let f = hdf5_metno::File::create(d.path().join("n.h5")).unwrap();
    let ds = f.new_dataset::<u8>().shape([2, 2, 2]).create("l").unwrap();
    ds.write_raw(&[1u8; 8]).unwrap();
    ds.new_attr::<f64>()
        .shape([3])
        .create("origin")
        .unwrap()
        .write_raw(&[f64::NAN, 0.0, 0.0])
        .unwrap();
    drop(ds);
    drop(f);
    drop(g);
    std::fs::write(
        d.path().join("p.yaml"),
        import_yaml("import.hdf5", "{path: n.h5, dataset: l, spacing: 1 um}"),
    )
    .unwrap();
    for cmd in ["validate", "run"] {
        let (code, _, err) = pipe(&[cmd, "p.yaml"], d.path());
        // Before: exit 1, "the data does not match the header read before running
        // (changed since?)".
        assert_eq!(code, 2, "{cmd}: {err}");
        assert!(
            err.contains("p.yaml:4") && err.contains("origin") && err.contains("NaN"),
            "{cmd}: {err}"
        );
        assert!(!err.contains("changed since"), "{cmd}: {err}");
    }
}

/// A small image: packing.rsa voxelized.
const IMAGE: &str = "name: t\nseed: 1\nstages:\n  - id: pack\n    use: packing.rsa\n    with: \
                     { size: [100 um, 100 um, 100 um], radius: { kind: fixed, value: 20 um }, \
                     volume_fraction: 0.2 }\n  - id: vox\n    use: voxelize.packing\n    in: { \
                     packing: pack.packing }\n    with: { voxel_size: 5 um }\n";

#[test]
fn tiff_exports_work_when_the_yaml_holds_non_ascii_text() {
    let d = tempfile::tempdir().unwrap();
    let yaml = format!(
        "# voxels of 5 µm — ∅ 40 µm spheres\n{IMAGE}export:\n  - {{ from: vox.image, to: \
         out/a.tif }}\n  - {{ from: vox.image, to: out/b.tif, with: {{ stack: directory }} }}\n"
    );
    std::fs::write(d.path().join("p.yaml"), &yaml).unwrap();
    let (code, _, err) = pipe(&["run", "p.yaml", "--quiet", "--no-cache"], d.path());
    // Before: exit 1, every TIFF export failed on the provenance's "µm".
    assert_eq!(code, 0, "{err}");
    assert!(d.path().join("out/a.tif").is_file());
    assert!(d.path().join("out/b/b_0000.tif").is_file());
    // Read back: the image and its calibration.
    std::fs::write(
        d.path().join("q.yaml"),
        import_yaml("import.tiff", "{path: out/a.tif}"),
    )
    .unwrap();
    let (code, _, err) = pipe(&["run", "q.yaml", "--quiet", "--no-cache"], d.path());
    assert_eq!(code, 0, "{err}");
}

// ------------------------------------------------------------------ C: exports

fn refused(yaml: &str, needles: &[&str]) {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(d.path().join("p.yaml"), yaml).unwrap();
    let (code, _, err) = pipe(&["validate", "p.yaml"], d.path());
    assert_eq!(code, 2, "{yaml}\n{err}");
    for n in needles {
        assert!(err.contains(n), "no `{n}` in\n{err}");
    }
}

#[test]
fn exports_writing_one_file_implicitly_or_through_dot_dot_are_refused() {
    // A `..` path: the same file.
    refused(
        &format!(
            "{IMAGE}export:\n  - {{ from: vox.image, to: out/A.vti }}\n  - {{ from: vox.image, \
             to: out/sub/../A.vti }}\n"
        ),
        &[
            "p.yaml:13",
            "out/sub/../A.vti",
            "already the target of the export at line 12",
        ],
    );
    // The `.raw` a `.mhd` writes beside it, and a `.raw` export.
    refused(
        &format!(
            "{IMAGE}export:\n  - {{ from: vox.image, to: out/a.mhd }}\n  - {{ from: vox.image, \
             to: out/a.raw, format: raw }}\n"
        ),
        &["p.yaml:13", "out/a.raw"],
    );
    // A `.csv.json` sidecar and a JSON export of that name.
    refused(
        &format!(
            "{IMAGE}export:\n  - {{ from: vox.report, to: out/r.csv }}\n  - {{ from: \
             vox.report, to: out/r.csv.json }}\n"
        ),
        &["p.yaml:13", "r.csv.json"],
    );
    // A file inside the directory a TIFF directory stack replaces.
    refused(
        &format!(
            "{IMAGE}export:\n  - {{ from: vox.image, to: out/ct.tif, with: {{ stack: directory \
             }} }}\n  - {{ from: vox.image, to: out/ct/extra.vti }}\n"
        ),
        &["p.yaml:13", "directory replaced as a whole"],
    );
}

#[test]
fn mhd_pair_is_replaced_payload_first_and_stale_leftovers_go() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    std::fs::create_dir_all(&out).unwrap();
    // What killed exports left: a fresh payload never named by a header, a temporary file of
    // a dead writer (pid 0 is never alive), a temporary directory of a TIFF stack.
    std::fs::write(out.join("a.grainpipe-1234abcd.raw"), b"old").unwrap();
    std::fs::write(out.join(".a.mhd.0.17.grainpipe-tmp"), b"half").unwrap();
    std::fs::create_dir_all(out.join(".ct.0.18.grainpipe-tmp")).unwrap();
    std::fs::write(out.join(".ct.0.18.grainpipe-tmp/ct_0000.tif"), b"x").unwrap();
    std::fs::write(
        d.path().join("p.yaml"),
        format!(
            "{IMAGE}export:\n  - {{ from: vox.image, to: out/a.mhd }}\n  - {{ from: vox.image, \
             to: out/ct.tif, with: {{ stack: directory }} }}\n"
        ),
    )
    .unwrap();
    let (code, _, err) = pipe(&["run", "p.yaml", "--quiet", "--no-cache"], d.path());
    assert_eq!(code, 0, "{err}");
    let header = std::fs::read_to_string(out.join("a.mhd")).unwrap();
    assert!(header.contains("ElementDataFile = a.raw\n"), "{header}");
    assert_eq!(
        std::fs::metadata(out.join("a.raw")).unwrap().len(),
        20 * 20 * 20
    );
    let mut left: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n != "run.json" && n != "report-data")
        .collect();
    left.sort();
    assert_eq!(left, ["a.mhd", "a.raw", "ct"], "leftovers");
}

// ------------------------------------------------------------------ B: export memory

#[test]
fn validate_counts_the_memory_of_exports() {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(
        d.path().join("p.yaml"),
        format!("{IMAGE}export:\n  - {{ from: vox.image, to: out/a.stl }}\n"),
    )
    .unwrap();
    let (code, out, err) = pipe(&["validate", "p.yaml"], d.path());
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("-> out/a.stl (stl) ~"), "{out}");
}
