//! pipelines/elasticity.yaml through the engine (packing.rsa -> voxelize.packing ->
//! elasticity.fft + conductivity.fft), checked against bounds that hold for any geometry,
//! plus the registry consistency check and an inline pipeline with a parameter error.
#![allow(clippy::needless_range_loop)]

mod common;

use grainpipe_core::testing::{run_pipeline, run_yaml, workspace_root};
use grainpipe_core::Registry;
use grainpipe_fft::kernel::Iso;

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_geometry::register(&mut r);
    grainpipe_fft::register(&mut r);
    r
}

#[test]
fn registry_is_consistent() {
    registry().check_consistency().unwrap();
}

#[test]
fn elasticity_pipeline_runs_and_exports() {
    let root = workspace_root(env!("CARGO_MANIFEST_DIR"));
    let out = tempfile::tempdir().unwrap();
    let res = run_pipeline(&registry(), &root, "elasticity.yaml", &[], out.path()).unwrap();
    let img = res.artifact("voxels.image").as_phase_image().unwrap();
    let phi = img.fraction(1);
    let c = res.artifact("stiffness.stiffness").as_tensor().unwrap();
    assert_eq!(c.shape, vec![6, 6]);
    let v = |i: usize, j: usize| c.values[6 * i + j];
    // Sand spheres (66.9 GPa, 0.25) in binder (43 GPa, 0.17): the bulk and shear moduli of
    // the nearly isotropic apparent stiffness lie within the Hashin-Shtrikman bounds
    // (2 % slack for the anisotropy of one small sample), and C is symmetric.
    let (s, b) = (Iso::from_e_nu(66.9e9, 0.25), Iso::from_e_nu(43e9, 0.17));
    let hs_k = |ka: f64, ga: f64, fa: f64, kb: f64, fb: f64| {
        ka + fb / (1.0 / (kb - ka) + 3.0 * fa / (3.0 * ka + 4.0 * ga))
    };
    let (k_lo, k_hi) = (
        hs_k(b.bulk(), b.mu, 1.0 - phi, s.bulk(), phi),
        hs_k(s.bulk(), s.mu, phi, b.bulk(), 1.0 - phi),
    );
    let k = (v(0, 0) + v(1, 1) + v(2, 2) + 2.0 * (v(0, 1) + v(0, 2) + v(1, 2))) / 9.0;
    assert!(
        k > 0.98 * k_lo && k < 1.02 * k_hi,
        "K {k} not in [{k_lo}, {k_hi}]"
    );
    for i in 0..6 {
        for j in 0..6 {
            assert!(
                (v(i, j) - v(j, i)).abs() < 1e-3 * v(0, 0),
                "asymmetric C{i}{j}"
            );
        }
    }
    // The mean stress is the volume average of the phase stresses (eq. 3.4).
    let ps = res.table("stiffness.phase_stress");
    let f = ps.f64_column("fraction").unwrap();
    let sxx = ps.f64_column("s_xx").unwrap();
    let mean_xx: f64 = f.iter().zip(sxx).take(2).map(|(a, b)| a * b).sum();
    assert!((mean_xx / v(0, 0) - 1.0).abs() < 1e-9);
    let consts = res.table("stiffness.constants");
    let ex = consts.f64_column("E_x").unwrap()[0];
    assert!(ex > 43e9 && ex < 66.9e9);
    // Conductivity: between the series and parallel means, diagonal dominated.
    let kt = res
        .artifact("conductivity.conductivity")
        .as_tensor()
        .unwrap();
    let (par, ser) = (phi * 7.7 + (1.0 - phi), 1.0 / (phi / 7.7 + (1.0 - phi)));
    for i in 0..3 {
        let kii = kt.values[4 * i];
        assert!(
            kii > ser && kii < par,
            "k_{i}{i} = {kii} not in [{ser}, {par}]"
        );
    }
    for f in [
        "stiffness.csv",
        "constants.csv",
        "history.csv",
        "conductivity.csv",
        "image.vti",
    ] {
        let p = out.path().join("elasticity").join(f);
        assert!(p.is_file(), "{} missing", p.display());
    }
}

/// The error of a small pipeline (RSA spheres at 10 um voxels) whose last step is `stage`
/// with parameters `with` (a YAML flow map); panics if it runs.
/// A pipeline of RSA spheres voxelized at 10 um (phase `grain`) feeding `stage` with `with`.
fn spheres_into(stage: &str, with: &str) -> String {
    format!(
        r#"
name: t
stages:
  - id: pack
    use: packing.rsa
    with: {{ size: [100 um, 100 um, 100 um], radius: {{ kind: fixed, value: 20 um }}, volume_fraction: 0.2 }}
  - id: voxels
    use: voxelize.packing
    in: {{ packing: pack.packing }}
    with: {{ voxel_size: 10 um }}
  - id: out
    use: {stage}
    in: {{ image: voxels.image }}
    with: {with}
"#
    )
}

fn refusal(stage: &str, with: &str) -> String {
    match run_yaml(&registry(), &spheres_into(stage, with)) {
        Ok(_) => panic!("{stage} with {with} ran; it should be refused"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn a_bad_tolerance_is_a_parameter_error() {
    let err = refusal("elasticity.fft", "{ tolerance: 2 }");
    assert!(err.contains("tolerance"), "{err}");
}

/// A material with a wrong set of keys is refused before anything runs, with a message
/// naming the keys given and the two accepted forms.
#[test]
fn a_material_with_mixed_keys_names_them() {
    for (material, expect) in [
        ("{ E: 66.9 GPa, nu: 0.25, K: 3 GPa }", "got {E, nu, K}"),
        ("{ E: 66.9 GPa }", "got {E}"),
        ("{ G: 3 GPa }", "got {G}"),
        ("{ E: 66.9 GPa, Nu: 0.25 }", "unknown field `Nu`"),
    ] {
        let err = refusal(
            "elasticity.fft",
            &format!("{{ materials: {{ grain: {material} }} }}"),
        );
        assert!(err.contains(expect), "{material}: {err}");
        if !expect.starts_with("unknown") {
            assert!(err.contains("{E, nu} or {K, G}"), "{material}: {err}");
        }
    }
}

/// Moduli far outside any material are refused at preflight with a hint at the unit; and
/// values that overflow double precision in the solver (a conductivity of 1e307 W/(m K))
/// fail with the cause instead of "converging" in 0 iterations to infinite moduli.
#[test]
fn moduli_out_of_range_fail_loudly() {
    let err = refusal(
        "elasticity.fft",
        "{ materials: { grain: { E: 1e308 Pa, nu: 0.25 } } }",
    );
    assert!(err.contains("check the unit"), "{err}");
    let err = refusal(
        "conductivity.fft",
        "{ conductivities: { grain: 1e307 W/(m K) } }",
    );
    assert!(err.contains("out of floating-point range"), "{err}");
}

/// Issue 36: a phase name the image will not have (`grian` for `grain`) passed `pipe validate`
/// and failed at run time after the upstream steps. voxelize.packing announces its phases
/// (`pore`, `grain`), so preflight names the phase without an entry and the likely typo.
#[test]
fn a_misspelt_phase_is_refused_at_preflight_with_a_suggestion() {
    for (stage, with, key) in [
        (
            "elasticity.fft",
            "{ materials: { grian: { E: 66.9 GPa, nu: 0.25 } } }",
            "materials",
        ),
        (
            "conductivity.fft",
            "{ conductivities: { grian: 1.4 W/(m K) } }",
            "conductivities",
        ),
    ] {
        let yaml = spheres_into(stage, with);
        let reg = registry();
        let doc = grainpipe_core::pipeline::PipelineDoc::parse("t.yaml".as_ref(), yaml).unwrap();
        let Err(e) = grainpipe_core::engine::plan(&doc, &reg, &Default::default()) else {
            panic!("{stage}: planned")
        };
        let e = e.to_string();
        assert!(
            e.contains(key)
                && e.contains("phase `grain` (label 1)")
                && e.contains("did you mean `grain` for `grian`?"),
            "{stage}: {e}"
        );
    }
}

/// Issue 35: every modulus the solver uses is guarded, not only the given ones. nu = -0.999999
/// made G = 3.3e16 Pa (past the 1e15 guard on E) and an indefinite, non-symmetric "stiffness";
/// E = 5e-324 underflowed to a void and was reported as "no solid voxel". (The floor is
/// 1e-20 Pa, not 1 Pa: scale-free tests use moduli of order 1.)
#[test]
fn derived_and_vanishing_moduli_are_refused_at_preflight() {
    for (material, expect) in [
        (
            "{ E: 66.9 GPa, nu: -0.999999 }",
            "shear modulus G = 3.345e16 Pa is above 1e15 Pa",
        ),
        ("{ E: 66.9 GPa, nu: 0.4999999999 }", "bulk modulus K"),
        (
            "{ E: 5e-324 Pa, nu: 0.25 }",
            "E = 4.941e-324 Pa is below 1e-20 Pa",
        ),
        (
            "{ K: 1e14 Pa, G: 1e-25 Pa }",
            "G = 1.000e-25 Pa is below 1e-20 Pa",
        ),
    ] {
        let err = refusal(
            "elasticity.fft",
            &format!("{{ materials: {{ grain: {material} }} }}"),
        );
        assert!(err.contains(expect), "{material}: {err}");
    }
}

/// The result check behind the solver: a matrix that is not a stiffness fails instead of being
/// reported. References: an isotropic stiffness passes; its transpose-perturbed copy (the 1.3
/// asymmetry of the reported case) and an indefinite symmetric one fail.
#[test]
fn a_stiffness_that_is_not_one_fails() {
    use grainpipe_fft::elasticity::{check_stiffness, LoadCase};
    let all = [
        LoadCase::Xx,
        LoadCase::Yy,
        LoadCase::Zz,
        LoadCase::Yz,
        LoadCase::Xz,
        LoadCase::Xy,
    ];
    let (l, m) = (26.76e9, 26.76e9);
    let mut c = [[0.0; 6]; 6];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = l;
        }
        c[i][i] = l + 2.0 * m;
        c[i + 3][i + 3] = m;
    }
    check_stiffness(&c, &all).unwrap();
    let mut skew = c;
    skew[0][1] += 1.3 * 1.5 * l;
    let e = check_stiffness(&skew, &all).unwrap_err().to_string();
    assert!(e.contains("not symmetric"), "{e}");
    let mut indefinite = c;
    for i in 0..3 {
        for j in 0..3 {
            indefinite[i][j] = if i == j { l } else { 2.0 * l };
        }
    }
    let e = check_stiffness(&indefinite, &all).unwrap_err().to_string();
    assert!(e.contains("not positive definite"), "{e}");
    let mut negative = c;
    negative[2][2] = -1.0;
    let e = check_stiffness(&negative, &[LoadCase::Zz])
        .unwrap_err()
        .to_string();
    assert!(e.contains("load case zz"), "{e}");
}

/// The composite-voxel chain from YAML: voxelize.packing with `subvoxel: true` exports its
/// sub-voxel geometry to HDF5; a second pipeline imports image and geometry (import.hdf5,
/// `as: field`) and solves with `interfaces: composite`. The stiffness equals the one solved
/// in the first pipeline from the in-memory field (to 1e-12: the file keeps every value), and
/// the sub-voxel solid fraction equals the packing's analytic volume fraction (to 0.5 %;
/// measured 1e-4, the labels 2.8 % off). The spheres sit in a matrix (the `pore` label given
/// a material): with void around them the isolated grains carry nothing.
#[test]
fn composite_voxels_run_from_yaml_and_survive_hdf5() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().display();
    let first = format!(
        r#"
name: composite
seed: 3
stages:
  - id: pack
    use: packing.rsa
    with:
      size: [100 um, 100 um, 100 um]
      radius: {{ kind: fixed, value: 17 um }}
      volume_fraction: 0.3
  - id: voxels
    use: voxelize.packing
    in: {{ packing: pack.packing }}
    with: {{ voxel_size: 6.25 um, subvoxel: true }}
  - id: stiffness
    use: elasticity.fft
    in: {{ image: voxels.image, subvoxel: voxels.subvoxel }}
    with:
      materials: {{ grain: {{ E: 66.9 GPa, nu: 0.25 }}, pore: {{ E: 43 GPa, nu: 0.17 }} }}
      discretization: hex8
      interfaces: composite
      load_cases: [xx, yz]
export:
  - {{ from: voxels.image, to: {d}/image.h5 }}
  - {{ from: voxels.subvoxel, to: {d}/subvoxel.h5 }}
  - {{ from: stiffness.stiffness, to: {d}/c1.json }}
"#
    );
    let res = run_yaml(&registry(), &first).unwrap();
    let sv = res.artifact("voxels.subvoxel").as_field().unwrap();
    assert_eq!(sv.components, 5);
    let n = sv.grid.voxel_count();
    let solid: f64 = (0..n).map(|v| sv.data.get(5 * v + 1)).sum::<f64>() / n as f64;
    let img = res.artifact("voxels.image").as_phase_image().unwrap();
    let analytic = res.column("voxels.report", "analytic_fraction")[0];
    eprintln!(
        "solid: sub-voxel {solid:.5}, labels {:.5}, analytic {analytic:.5}",
        img.fraction(1)
    );
    assert!((solid / analytic - 1.0).abs() < 0.005);
    let c1 = res
        .artifact("stiffness.stiffness")
        .as_tensor()
        .unwrap()
        .values
        .clone();
    let second = format!(
        r#"
name: composite-reread
seed: 3
stages:
  - id: image
    use: import.hdf5
    with: {{ path: {d}/image.h5, dataset: phase }}
  - id: geometry
    use: import.hdf5
    with: {{ path: {d}/subvoxel.h5, dataset: subvoxel, as: field }}
  - id: stiffness
    use: elasticity.fft
    in: {{ image: image.image, subvoxel: geometry.field }}
    with:
      materials: {{ grain: {{ E: 66.9 GPa, nu: 0.25 }}, pore: {{ E: 43 GPa, nu: 0.17 }} }}
      discretization: hex8
      interfaces: composite
      load_cases: [xx, yz]
export:
  - {{ from: stiffness.stiffness, to: {d}/c2.json }}
"#
    );
    let res2 = run_yaml(&registry(), &second).unwrap();
    let c2 = &res2
        .artifact("stiffness.stiffness")
        .as_tensor()
        .unwrap()
        .values;
    for (a, b) in c1.iter().zip(c2) {
        assert!((a - b).abs() <= 1e-12 * c1[0].abs(), "{a} vs {b}");
    }
}

/// A sub-voxel sampling that would run for hours is refused before any work.
#[test]
fn absurd_subvoxel_sampling_is_refused() {
    let yaml = r#"
name: t
seed: 1
stages:
  - id: pack
    use: packing.rsa
    with:
      size: [100 um, 100 um, 100 um]
      radius: { kind: fixed, value: 17 um }
      volume_fraction: 0.3
  - id: voxels
    use: voxelize.packing
    in: { packing: pack.packing }
    with: { voxel_size: 10 um, subvoxel: true, subvoxel_samples: 1000 }
"#;
    let err = run_yaml(&registry(), yaml)
        .err()
        .expect("refused")
        .to_string();
    assert!(
        err.contains("subvoxel_samples") && err.contains("1000"),
        "{err}"
    );
}

/// The three normal load cases give the orthotropic row's E and Poisson ratios of the six
/// (the same normal columns of C_app, inverted as a block), its shear moduli NaN, and the
/// anisotropy column is E_z / mean(E_x, E_y) - 1 of the same row (issue 31: half the time
/// for an ensemble's anisotropy).
#[test]
fn three_normal_load_cases_give_the_orthotropic_moduli_of_six() {
    let yaml = r#"
name: normal-cases
seed: 11
stages:
  - id: pack
    use: packing.rsa
    with:
      size: [100 um, 100 um, 100 um]
      radius: { kind: fixed, value: 17 um }
      volume_fraction: 0.3
  - id: voxels
    use: voxelize.packing
    in: { packing: pack.packing }
    with: { voxel_size: 6.25 um }
  - id: six
    use: elasticity.fft
    in: { image: voxels.image }
    with:
      materials: { grain: { E: 66.9 GPa, nu: 0.25 }, pore: { E: 43 GPa, nu: 0.17 } }
      tolerance: 1.0e-8
  - id: three
    use: elasticity.fft
    in: { image: voxels.image }
    with:
      materials: { grain: { E: 66.9 GPa, nu: 0.25 }, pore: { E: 43 GPa, nu: 0.17 } }
      tolerance: 1.0e-8
      load_cases: [xx, yy, zz]
"#;
    let res = run_yaml(&registry(), yaml).unwrap();
    let (six, three) = (res.table("six.constants"), res.table("three.constants"));
    let row = 1; // orthotropic
    for name in [
        "E_x", "E_y", "E_z", "nu_xy", "nu_xz", "nu_yz", "nu_yx", "nu_zx", "nu_zy",
    ] {
        let (a, b) = (
            six.f64_column(name).unwrap()[row],
            three.f64_column(name).unwrap()[row],
        );
        assert!((a / b - 1.0).abs() < 1e-12, "{name}: {a} vs {b}");
    }
    for name in ["G_yz", "G_zx", "G_xy", "relative_error"] {
        assert!(three.f64_column(name).unwrap()[row].is_nan(), "{name}");
    }
    // Only the orthotropic row is defined with three cases.
    assert!(three.f64_column("E_x").unwrap()[0].is_nan());
    for t in [six, three] {
        let e = |n: &str| t.f64_column(n).unwrap()[row];
        let want = e("E_z") / (0.5 * (e("E_x") + e("E_y"))) - 1.0;
        let got = t.f64_column("anisotropy_z").unwrap()[row];
        assert!((got - want).abs() < 1e-15, "{got} vs {want}");
    }
}
