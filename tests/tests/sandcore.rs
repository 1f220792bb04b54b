//! pipelines/sandcore-quick.yaml end to end (the sand-core chain at 8 um): every stage runs
//! from the YAML, the fractions are exact, and the effective properties lie inside bounds
//! that hold for any microstructure with these phases.

use grainpipe_core::Artifact;
use grainpipe_tests::run_pipeline;

fn tensor(a: &Artifact) -> &grainpipe_core::Tensor {
    match a {
        Artifact::Tensor(t) => t,
        other => panic!("not a tensor: {:?}", other.kind()),
    }
}

#[test]
fn quick_sand_core_chain_gives_bounded_properties() {
    let dir = tempfile::tempdir().unwrap();
    let r = run_pipeline("sandcore-quick.yaml", &[], dir.path()).unwrap();
    let image = r.outputs["binder"]["image"].as_phase_image().unwrap();
    let n = image.labels.len() as f64;
    assert!((image.fraction(1) - 0.5).abs() <= 1.0 / n);
    assert!((image.fraction(2) - 0.02).abs() <= 1.0 / n);
    let (phi_s, phi_b) = (image.fraction(1), image.fraction(2));

    // Stiffness: symmetric, and every directional modulus below the Voigt bound of the
    // phases (Table 1: sand 66.9 GPa, binder 43 GPa, pores 0).
    let c = tensor(&r.outputs["stiffness"]["stiffness"]);
    assert_eq!(c.shape, [6, 6]);
    for i in 0..6 {
        for j in 0..6 {
            let (a, b) = (c.values[6 * i + j], c.values[6 * j + i]);
            assert!((a - b).abs() <= 1e-3 * c.values[0], "C{i}{j} {a} vs {b}");
        }
    }
    let voigt_e = phi_s * 66.9e9 + phi_b * 43e9;
    for axis in ["E_x", "E_y", "E_z"] {
        let e = r.column("stiffness.constants", axis)[0];
        assert!(
            e > 0.0 && e < voigt_e,
            "{axis} = {e:e}, Voigt bound {voigt_e:e}"
        );
    }

    // Conductivity: symmetric, between 0 (pores insulate) and the Voigt mean.
    let k = tensor(&r.outputs["conductivity"]["conductivity"]);
    let voigt_k = phi_s * 7.7 + phi_b * 0.3;
    for i in 0..3 {
        assert!(k.values[4 * i] > 0.0 && k.values[4 * i] < voigt_k);
    }

    // Permeability: positive on the diagonal, symmetric to a few per cent, and in the range
    // of the paper's Table 3 (2.1-2.8e-11 m^2 at 1-8 um, gap 8 um) within a factor of 5.
    let kappa = tensor(&r.outputs["flow"]["permeability"]);
    for i in 0..3 {
        let d = kappa.values[4 * i];
        assert!(d > 0.4e-11 && d < 14e-11, "kappa_{i}{i} = {d:e}");
    }
    for (i, j) in [(0, 1), (0, 2), (1, 2)] {
        let (a, b) = (kappa.values[3 * i + j], kappa.values[3 * j + i]);
        assert!(
            (a - b).abs() <= 0.05 * kappa.values[0],
            "kappa_{i}{j} {a:e} vs {b:e}"
        );
    }
    for f in [
        "image.vti",
        "constants.csv",
        "permeability.json",
        "velocity.vti",
    ] {
        assert!(dir.path().join("sandcore-quick").join(f).is_file(), "{f}");
    }
}
