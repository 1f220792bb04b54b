//! Failure messages say what happened (issue 34, item 3): CG at the f32 floor is not called
//! a stagnation "within" a window it never reached, and "use solver: cg" is advice for the
//! dynamic solvers only.

mod common;
use common::*;
use grainpipe_peridynamics::bond_based::{BondBasedParams, SolverKind};

fn plate() -> grainpipe_core::PhaseImage {
    image(24, 30, vec![3; 24 * 30])
}

fn error(p: BondBasedParams) -> String {
    match try_run(&p, &plate()) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("expected a failure"),
    }
}

fn base() -> BondBasedParams {
    BondBasedParams {
        materials: materials(&[("matrix", matrix_material(2e9))]),
        ..Default::default()
    }
}

#[test]
fn cg_below_the_f32_floor_says_round_off_and_what_tolerance_is_reachable() {
    let e = error(BondBasedParams {
        tolerance: 1e-9,
        ..base()
    });
    assert!(
        e.contains("round-off floor") && e.contains("loosen tolerance"),
        "{e}"
    );
    assert!(!e.contains("within"), "{e}");
    // the suggested tolerance is reachable
    let reachable: f64 = e
        .rsplit("about ")
        .next()
        .and_then(|t| t.split_whitespace().next())
        .and_then(|t| t.parse().ok())
        .unwrap_or_else(|| panic!("no tolerance in {e}"));
    try_run(
        &BondBasedParams {
            tolerance: reachable,
            ..base()
        },
        &plate(),
    )
    .unwrap_or_else(|e| panic!("suggested tolerance {reachable}: {e}"));
}

#[test]
fn use_cg_is_advised_to_the_dynamic_solvers_only() {
    let cg = error(BondBasedParams {
        max_iterations: 2,
        ..base()
    });
    assert!(
        cg.contains("not converged") && !cg.contains("use solver: cg"),
        "{cg}"
    );
    let adr = error(BondBasedParams {
        solver: SolverKind::Adr,
        max_iterations: 5,
        ..base()
    });
    assert!(
        adr.contains("not converged") && adr.contains("use solver: cg"),
        "{adr}"
    );
}

/// Degenerate horizons (issue 34, item 3): below sqrt(2) voxel edges no bond is diagonal and
/// the lattice has no shear stiffness (it used to "converge" to nonsense); a horizon of 2 is
/// run with the anisotropy it has. The Zener ratio 2 C12 / (C11 - C12) against hand sums of
/// the stencil: h = 1.5 in 2-D has 4 axial bonds (|xi| = 1) and 4 diagonal ones (sqrt 2),
/// C11 = sum x^4 / |xi|^3 = 2 + 4 / 2^1.5 and C12 = sum x^2 y^2 / |xi|^3 = 4 / 2^1.5.
#[test]
fn horizons_without_shear_stiffness_are_refused_and_anisotropy_is_measured() {
    use grainpipe_core::stage::TypedStage;
    use grainpipe_core::{ArtifactKind, ArtifactMeta, InputMetas};
    use grainpipe_peridynamics::bond_based::{lattice_zener_ratio, BondBased};
    let preflight_error = |p: BondBasedParams| {
        let mut metas = InputMetas::new();
        metas.insert(
            "image".into(),
            ArtifactMeta::on_grid(ArtifactKind::PhaseImage, plate().grid),
        );
        match BondBased.preflight(&p, &metas) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("expected a preflight error"),
        }
    };
    let e = preflight_error(BondBasedParams {
        horizon: 1.2,
        ..base()
    });
    assert!(
        e.contains("no shear stiffness") && e.contains("horizon"),
        "{e}"
    );
    let d = 2f64.powf(1.5);
    let (c11, c12) = (2.0 + 4.0 / d, 4.0 / d);
    assert!((lattice_zener_ratio(1.5, false) - 2.0 * c12 / (c11 - c12)).abs() < 1e-12);
    assert_eq!(lattice_zener_ratio(1.2, true), 0.0);
    assert!((lattice_zener_ratio(3.0, false) - 0.934).abs() < 1e-3);
    // E: 1e300 Pa is a unit slip, refused before any work
    let big = preflight_error(BondBasedParams {
        materials: materials(&[("matrix", matrix_material(1e300))]),
        ..base()
    });
    assert!(big.contains("check the unit"), "{big}");
}

/// Issue 35: `time_step: 1e-300` was answered with "diverging ... reduce time_step". A step
/// far below the critical one is refused on its key, saying why.
#[test]
fn a_vanishing_explicit_step_is_refused_on_its_key() {
    let e = error(BondBasedParams {
        solver: SolverKind::Explicit,
        time_step: Some(grainpipe_core::units::Q::new(1e-300)),
        ..base()
    });
    assert!(
        e.contains("time_step") && e.contains("below 0.001 x the critical explicit step"),
        "{e}"
    );
    assert!(!e.contains("reduce time_step"), "{e}");
}
