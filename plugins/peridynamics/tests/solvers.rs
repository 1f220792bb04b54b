//! Solver behaviour: ADR and PCG agree on heterogeneous samples, floating clusters,
//! the critical time step, divergence and determinism across thread counts.

mod common;
use common::*;
use grainpipe_core::{ArtifactKind, ArtifactMeta, InputMetas, Stage};
use grainpipe_peridynamics::bond_based::{BondBased, BondBasedParams, FloatingMode, SolverKind};
use grainpipe_peridynamics::setup::{build, Grips, Identity, PhaseSpec, Role, Setup};
use grainpipe_peridynamics::solve::{relax, Dynamics, Settings, SolveError};

/// Particles (E_p = 4 E_m, Table I) in a matrix, optionally with voids.
fn sample(nx: usize, ny: usize, voids: bool) -> Vec<u8> {
    let mut labels = vec![3u8; nx * ny];
    let mut rng = Rng(7);
    for k in 0..14 {
        let (cx, cy) = (rng.next() * nx as f64, rng.next() * ny as f64);
        let r = if k % 3 == 0 { 6.0 } else { 3.0 };
        paint_disk(&mut labels, nx, cx, cy, r, if k % 3 == 0 { 1 } else { 2 });
    }
    if voids {
        for _ in 0..6 {
            let (cx, cy) = (rng.next() * nx as f64, 8.0 + rng.next() * (ny - 16) as f64);
            paint_disk(&mut labels, nx, cx, cy, 2.5, 0);
        }
    }
    labels
}

fn params(solver: SolverKind) -> BondBasedParams {
    BondBasedParams {
        solver,
        tolerance: 1e-5,
        max_iterations: 40_000,
        ..Default::default()
    }
}

/// Largest displacement difference relative to the largest displacement.
fn rel_diff(a: &[f32], b: &[f32]) -> f64 {
    let m = a.iter().map(|v| v.abs()).fold(0f32, f32::max) as f64;
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs() as f64)
        .fold(0.0, f64::max)
        / m
}

#[test]
fn adr_and_pcg_agree_on_contrast_and_voids() {
    for voids in [false, true] {
        let (nx, ny) = (36, 36);
        let img = image(nx, ny, sample(nx, ny, voids));
        let c = run(&params(SolverKind::Cg), &img);
        let a = run(&params(SolverKind::Adr), &img);
        let (ic, ia) = (
            col_i64(&c.report, "iterations"),
            col_i64(&a.report, "iterations"),
        );
        let d = rel_diff(&c.displacement, &a.displacement);
        let (ec, ea) = (
            col_f64(&c.report, "effective_modulus"),
            col_f64(&a.report, "effective_modulus"),
        );
        println!(
            "voids {voids}: CG {ic} iterations, ADR {ia}; displacement difference {d:.2e}; \
             E_eff CG {ec:.4e}, ADR {ea:.4e}"
        );
        assert!(col_f64(&c.report, "residual") < 2e-5);
        assert!(col_f64(&a.report, "residual") <= 1e-5);
        // Linearised vs nonlinear bonds at strain 1e-4 differ at O(1e-4); the rest is the
        // tolerance.
        assert!(d < 2e-3, "CG and ADR displacements differ by {d:.2e}");
        assert!((ec / ea - 1.0).abs() < 2e-3);
        // ADR with the Rayleigh quotient of the deviation from the affine field is quick on
        // small grids; the gap widens with the grid (see the benchmark).
        assert!(
            ic < ia,
            "CG ({ic}) should need fewer iterations than ADR ({ia})"
        );
        // Histories decrease to the tolerance.
        let h = c.history.f64_column("residual").unwrap();
        assert!(h.last().unwrap() < &1e-5 && h[0] > 1e-3);
    }
}

#[test]
fn floating_particle_is_detected_and_excluded_or_refused() {
    let (nx, ny) = (30, 30);
    let mut labels = vec![3u8; nx * ny];
    // A void hole wider than the horizon with a particle floating inside it.
    paint_disk(&mut labels, nx, 15.0, 15.0, 9.0, 0);
    paint_disk(&mut labels, nx, 15.0, 15.0, 3.0, 1);
    let island = labels.iter().filter(|&&l| l == 1).count() as i64;
    let img = image(nx, ny, labels);
    let r = run(&params(SolverKind::Cg), &img);
    assert_eq!(col_i64(&r.report, "floating_nodes"), island);
    assert_eq!(col_i64(&r.report, "floating_clusters"), 1);
    let note = match &r.report.column("note").unwrap().data {
        grainpipe_core::ColumnData::Str(v) => v[0].clone(),
        _ => unreachable!(),
    };
    assert!(note.contains("floating"), "{note}");
    // The island carries no stress; the ring around the hole does.
    assert_eq!(s2(&r, nx, 15, 15, 1), 0.0);
    assert!(col_f64(&r.report, "effective_modulus") > 0.0);
    // ADR on the same sample converges too (no singular hang).
    let a = run(&params(SolverKind::Adr), &img);
    assert!(col_f64(&a.report, "residual") <= 1e-5);
    let p = BondBasedParams {
        floating: FloatingMode::Fail,
        ..params(SolverKind::Cg)
    };
    let e = try_run(&p, &img).err().expect("floating must be refused");
    assert!(e.to_string().contains("floating cluster"), "{e}");
}

fn stage_preflight(params: serde_json::Value) -> Result<(), grainpipe_core::StageError> {
    let stage = grainpipe_core::stage::Typed::new(BondBased);
    let mut metas = InputMetas::new();
    metas.insert(
        "image".into(),
        ArtifactMeta::on_grid(ArtifactKind::PhaseImage, image(64, 64, vec![]).grid),
    );
    let p = stage.normalize_params(&params)?;
    stage.preflight(&p, &metas).map(|_| ())
}

#[test]
fn time_step_above_critical_is_refused_at_preflight() {
    stage_preflight(serde_json::json!({"solver": "explicit", "time_step": "0.1 ns"}))
        .expect("0.1 ns is below the critical step at 1 um voxels");
    let e = stage_preflight(serde_json::json!({"solver": "explicit", "time_step": "1 us"}))
        .unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("time_step") && msg.contains("critical"),
        "{msg}"
    );
    // Other bad parameters name their key.
    let e = stage_preflight(serde_json::json!({"strain": 0.0})).unwrap_err();
    assert!(e.to_string().contains("strain"), "{e}");
    let e = stage_preflight(serde_json::json!({"breaking": true})).unwrap_err();
    assert!(e.to_string().contains("breaking"), "{e}");
    let e = stage_preflight(serde_json::json!({"memory_limit_gib": 1e-6})).unwrap_err();
    assert!(e.to_string().contains("GiB"), "{e}");
}

fn plate_lattice(nx: usize, ny: usize) -> grainpipe_peridynamics::setup::Built {
    let mut phases = [PhaseSpec::VOID; 256];
    phases[3] = PhaseSpec {
        role: Role::Matrix,
        e: 1e9,
        gc: 10.0,
    };
    let setup = Setup {
        horizon: 3.0,
        interface: PhaseSpec {
            role: Role::Matrix,
            e: 1e9,
            gc: 10.0,
        },
        identity: Identity::Components,
        breaking: false,
        axis: 1,
        grips: Grips::Clamped,
        grip_layers: 1,
        strain: 1e-3,
        fail_on_floating: false,
        stiffness_scale: 1.0,
    };
    build([nx, ny, 1], &vec![3u8; nx * ny], &phases, 1e-6, &setup).unwrap()
}

/// Explicit dynamics above the critical step (bypassing the stage's refusal): the energy
/// check stops the run with an error and no NaN; below it the same run converges.
#[test]
fn divergence_is_detected() {
    let b = plate_lattice(20, 20);
    let lat = &b.lattice;
    let smax = lat.spring_sums().into_iter().fold(0f32, f32::max) as f64;
    let crit = (2.0 / smax).sqrt();
    let kmax = lat.kself.iter().cloned().fold(0f32, f32::max) as f64;
    let s = Settings {
        tolerance: 1e-5,
        max_iterations: 20_000,
        stagnation_window: 5000,
    };
    let mut u = b.u0.clone();
    // The per-node bound is conservative (about half the true limit): 3x is unstable.
    let d = Dynamics {
        dt: 3.0 * crit,
        damping: 0.1,
        kmax,
    };
    let e = relax(lat, &mut u, &s, Some(d), None, &mut |_, _| true).unwrap_err();
    match e {
        SolveError::Diverged {
            iteration, energy, ..
        } => {
            assert!(energy.is_finite() && iteration < 2000, "{e}")
        }
        other => panic!("expected divergence, got {other}"),
    }
    let mut u = b.u0.clone();
    let d = Dynamics {
        dt: 0.8 * crit,
        damping: 0.5,
        kmax,
    };
    let st = relax(lat, &mut u, &s, Some(d), None, &mut |_, _| true).expect("stable step");
    assert!(st.residual <= 1e-5);
    assert!(u.c.iter().flatten().all(|v| v.is_finite()));
}

/// Work limits: a solve that cannot reach the tolerance in max_iterations fails, naming
/// the residual reached.
#[test]
fn iteration_limit_fails_loudly() {
    let (nx, ny) = (30, 30);
    let img = image(nx, ny, sample(nx, ny, false));
    let p = BondBasedParams {
        max_iterations: 5,
        ..params(SolverKind::Adr)
    };
    let e = try_run(&p, &img)
        .err()
        .expect("5 ADR iterations cannot converge");
    let msg = e.to_string();
    assert!(
        msg.contains("not converged after 5 iterations") && msg.contains("residual"),
        "{msg}"
    );
}

#[test]
fn same_numbers_for_any_thread_count() {
    let (nx, ny) = (40, 32);
    let img = image(nx, ny, sample(nx, ny, true));
    let go = |threads: usize, solver| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| run(&params(solver), &img))
    };
    for solver in [SolverKind::Cg, SolverKind::Adr] {
        let a = go(1, solver);
        let b = go(3, solver);
        assert_eq!(a.displacement, b.displacement);
        assert_eq!(a.stress, b.stress);
        assert_eq!(a.report, b.report);
    }
}

/// Critical-stretch breaking: at a strain far above s_c bonds break and the run still ends
/// (converged or failing loudly, never NaN); at a tiny strain none break.
#[test]
fn bonds_break_beyond_the_critical_stretch() {
    let (nx, ny) = (24, 24);
    let img = image(nx, ny, vec![3; nx * ny]);
    let p = BondBasedParams {
        solver: SolverKind::Adr,
        breaking: true,
        strain: 1e-4,
        ..params(SolverKind::Adr)
    };
    let r = run(&p, &img);
    assert_eq!(col_i64(&r.report, "broken_bonds"), 0);
    // s_c = sqrt(4 pi G / (9 E h)) = sqrt(4 pi 10 / (9e9 * 3e-6)) = 0.039 for the matrix.
    let p = BondBasedParams {
        strain: 0.05,
        max_iterations: 3000,
        ..p
    };
    match try_run(&p, &img) {
        Ok(r) => assert!(col_i64(&r.report, "broken_bonds") > 0),
        Err(e) => assert!(e.to_string().contains("solver"), "{e}"),
    }
}
