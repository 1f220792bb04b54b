//! Imports that cannot succeed fail before running with where and why: a value that is not
//! a phase label named by its (x, y, z), a misspelled HDF5 dataset with the file's datasets.

use grainpipe_core::{InputMetas, Registry, StageError};
use serde_json::json;

fn preflight_error(stage: &str, with: serde_json::Value) -> (String, String) {
    let mut reg = Registry::new();
    grainpipe_formats::register(&mut reg);
    let st = reg.stage(stage).unwrap().stage.clone();
    let params = st.normalize_params(&with).unwrap();
    match st.preflight(&params, &InputMetas::new()) {
        Err(StageError::InvalidParam { key, message }) => (key, message),
        Err(other) => panic!("{stage}: expected a parameter error, got {other:?}"),
        Ok(_) => panic!("{stage}: preflight accepted it"),
    }
}

/// 4 x 3 x 3 uint16 labels 0..=2 with one 300 at (x=3, y=1, z=2) (linear index
/// 3 + 4*1 + 12*2 = 31).
fn labels_u16() -> Vec<u16> {
    let mut v: Vec<u16> = (0..36).map(|i| (i % 3) as u16).collect();
    v[31] = 300;
    v
}

#[test]
fn raw_u16_label_out_of_range_is_named_by_x_y_z_in_preflight() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("l.raw");
    let bytes: Vec<u8> = labels_u16().iter().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(&p, bytes).unwrap();
    let with = json!({"path": p, "dims": [4, 3, 3], "dtype": "u16", "spacing": "1 um"});
    let (key, msg) = preflight_error("import.raw", with.clone());
    assert_eq!(key, "as");
    assert!(msg.contains("(x=3, y=1, z=2) holds 300"), "{msg}");
    assert!(
        msg.contains("0 .. 300") && msg.contains("as: field"),
        "{msg}"
    );
    // The same file as a field passes.
    let mut reg = Registry::new();
    grainpipe_formats::register(&mut reg);
    let st = reg.stage("import.raw").unwrap().stage.clone();
    let mut f = with;
    f["as"] = json!("field");
    assert!(st
        .preflight(&st.normalize_params(&f).unwrap(), &InputMetas::new())
        .is_ok());
}

#[test]
fn hdf5_label_range_and_misspelled_dataset_fail_in_preflight() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("l.h5");
    {
        let f = hdf5_metno::File::create(&p).unwrap();
        let ds = f
            .new_dataset::<u16>()
            .shape([3, 3, 4])
            .create("labels")
            .unwrap();
        ds.write_raw(&labels_u16()).unwrap();
        let g = f.create_group("meta").unwrap();
        g.new_dataset::<f32>()
            .shape([2])
            .create("porosity")
            .unwrap();
    }
    let (key, msg) = preflight_error(
        "import.hdf5",
        json!({"path": p, "dataset": "labels", "spacing": "1 um"}),
    );
    assert_eq!(key, "as");
    assert!(msg.contains("(x=3, y=1, z=2) holds 300"), "{msg}");
    let (key, msg) = preflight_error(
        "import.hdf5",
        json!({"path": p, "dataset": "lables", "spacing": "1 um"}),
    );
    assert_eq!(key, "dataset");
    assert!(
        msg.contains("`labels`, `meta/porosity`") && msg.contains("did you mean `labels`?"),
        "{msg}"
    );
}
