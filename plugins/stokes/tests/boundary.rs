//! Boundaries for images that are not periodic (`boundary:`): the permeameter (`walls`)
//! against closed forms (the MAC slit solution exactly, the square duct series at second
//! order, Hagen-Poiseuille in a round channel), its mass balance, and `mirror` against the
//! explicitly mirrored periodic image; preflight refuses a scan without a choice.

use grainpipe_core::boundary::{mirror_image, Boundary, BoundaryParams};
use grainpipe_core::stage::TypedStage;
use grainpipe_core::testing::WarningLog;
use grainpipe_core::{
    Artifact, ArtifactKind, ArtifactMeta, Grid, InputMetas, Inputs, Phase, PhaseImage, RunContext,
    StageError, Table, Tensor,
};
use grainpipe_stokes::permeability::{Axis, PermeabilityParams, PermeabilityStage};
use std::sync::Arc;

const H: f64 = 2e-6;

fn image(dims: [usize; 3], periodic: [bool; 3], fluid: impl Fn([usize; 3]) -> bool) -> PhaseImage {
    let mut labels = vec![];
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                labels.push(u8::from(!fluid([x, y, z])));
            }
        }
    }
    PhaseImage {
        grid: Grid {
            dims,
            spacing: [H; 3],
            origin: [0.0; 3],
            periodic,
        },
        labels,
        phases: vec![
            Phase {
                id: 0,
                name: "pore".into(),
            },
            Phase {
                id: 1,
                name: "solid".into(),
            },
        ],
    }
}

fn params(boundary: Option<Boundary>, directions: Vec<Axis>) -> PermeabilityParams {
    PermeabilityParams {
        directions,
        tolerance: 1e-7,
        boundary: BoundaryParams { boundary },
        ..Default::default()
    }
}

/// Preflight and run of the stage on `img`: the tensor, the report and the warnings.
fn run(
    img: &PhaseImage,
    p: &PermeabilityParams,
) -> Result<(Tensor, Table, Vec<String>), StageError> {
    let mut metas = InputMetas::new();
    metas.insert(
        "image".into(),
        ArtifactMeta::on_grid(ArtifactKind::PhaseImage, img.grid.clone()),
    );
    let pf = PermeabilityStage.preflight(p, &metas)?;
    let mut inputs = Inputs::new();
    inputs.insert("image".into(), Arc::new(Artifact::PhaseImage(img.clone())));
    let log = WarningLog::default();
    let ctx = RunContext::new(1, &log);
    let out = PermeabilityStage.run(p, &pf.plan, &inputs, &ctx)?;
    let Artifact::Tensor(k) = &out["permeability"] else {
        panic!()
    };
    let Artifact::Table(t) = &out["report"] else {
        panic!()
    };
    Ok((k.clone(), t.clone(), log.warnings()))
}

fn col(t: &Table, name: &str) -> Vec<f64> {
    t.f64_column(name)
        .unwrap_or_else(|| panic!("no column {name}"))
        .to_vec()
}

#[test]
fn a_scan_without_a_boundary_is_refused_at_preflight_naming_the_choices() {
    let img = image([6, 6, 6], [false; 3], |c| c[0] > 1);
    let mut metas = InputMetas::new();
    metas.insert(
        "image".into(),
        ArtifactMeta::on_grid(ArtifactKind::PhaseImage, img.grid.clone()),
    );
    match PermeabilityStage.preflight(&params(None, vec![Axis::X]), &metas) {
        Err(StageError::InvalidParam { key, message }) => {
            assert_eq!(key, "boundary");
            for choice in ["`mirror`", "`walls`", "`periodic`"] {
                assert!(message.contains(choice), "{message}");
            }
        }
        other => panic!("expected a boundary error, got {:?}", other.map(|_| ())),
    }
    // Forced periodic runs, with the glued faces warned.
    let (_, _, warnings) = run(&img, &params(Some(Boundary::Periodic), vec![Axis::X])).unwrap();
    assert!(warnings.iter().any(|w| w.contains("glued")), "{warnings:?}");
}

/// Plane Poiseuille flow between walls the permeameter adds: the MAC solution with ghost
/// walls is the parabola shifted by 1/8, so kappa / h^2 = H^2 / 12 + 1/6 exactly (H the gap
/// in voxels; channels.rs derives it). With a non-periodic flow axis the pressure drop is
/// read from the buffers, with a periodic one it is the body force's: both give it.
#[test]
fn slit_between_the_walls_gives_the_discrete_poiseuille_solution() {
    let gap = 12;
    for periodic_x in [false, true] {
        // periodic along y: walls only across z
        let img = image([5, 4, gap], [periodic_x, true, false], |_| true);
        let (k, t, warnings) = run(&img, &params(Some(Boundary::Walls), vec![Axis::X])).unwrap();
        let exact = (gap * gap) as f64 / 12.0 + 1.0 / 6.0;
        let kappa = k.values[0] / (H * H);
        assert!(
            (kappa / exact - 1.0).abs() < 1e-5,
            "periodic x {periodic_x}: {kappa} vs {exact}"
        );
        // The permeameter measures only the flow along its axis.
        assert!(k.values[1].is_nan() && k.values[3].is_nan());
        assert!(
            col(&t, "mass_balance")[0] < 1e-6,
            "{:?}",
            col(&t, "mass_balance")
        );
        assert!(warnings.is_empty(), "{warnings:?}");
        // Darcy: Q = kappa A dP / (mu L) through the sample's cross-section.
        let q = col(&t, "flow_rate")[0];
        let area = (4 * gap) as f64 * H * H;
        let want = k.values[0] * area * 100.0 / (1.8e-5 * 5.0 * H);
        assert!((q / want - 1.0).abs() < 1e-12, "{q} vs {want}");
    }
}

/// Mean velocity over a square duct of side a for f = mu = 1 (Boussinesq series; White,
/// Viscous Fluid Flow, eq. 3-48): k / a^2 = 0.0351442537.
const SQUARE_DUCT: f64 = 0.035_144_253_7;

#[test]
fn square_duct_in_the_permeameter_matches_the_series_at_second_order() {
    let err: Vec<f64> = [8usize, 16]
        .iter()
        .map(|&n| {
            let img = image([3, n, n], [false; 3], |_| true);
            let (k, _, _) = run(&img, &params(Some(Boundary::Walls), vec![Axis::X])).unwrap();
            k.values[0] / (n as f64 * H).powi(2) / SQUARE_DUCT - 1.0
        })
        .collect();
    // The same discrete duct as channels.rs: 5.9 % and 1.5 % above the series.
    assert!(err[1].abs() < 0.02, "{err:?}");
    let order = (err[0] / err[1]).log2();
    assert!((1.9..2.1).contains(&order), "order {order} from {err:?}");
}

/// A round channel through a solid sample, flow along z from buffer to buffer. The
/// permeameter's resistance is the channel's plus the entrance and exit losses (a sudden
/// contraction from the reservoir; Sampson's orifice flow, Dagan et al. 1982, is the limit of
/// an infinite reservoir), so L / kappa(L) is linear in L with the slope of the developed
/// flow: two lengths give the channel's own kappa, which equals the periodic channel's (the
/// same discrete cross-section, independently solved without buffers) and Hagen-Poiseuille,
/// kappa = pi R^4 / (8 A), within the staircase error of the voxelised circle. The flow rates
/// at the inlet and outlet faces agree to the solver tolerance.
#[test]
fn round_channel_resistance_is_hagen_poiseuille_plus_entrance_losses() {
    let (n, r) = (16usize, 6.0f64);
    let c = n as f64 / 2.0;
    let tube = |len: usize, periodic_z: bool| {
        let img = image([n, n, len], [false, false, periodic_z], |p| {
            (p[0] as f64 + 0.5 - c).powi(2) + (p[1] as f64 + 0.5 - c).powi(2) < r * r
        });
        let (k, t, _) = run(&img, &params(Some(Boundary::Walls), vec![Axis::Z])).unwrap();
        (k.values[8] / (H * H), col(&t, "mass_balance")[0])
    };
    let (developed, _) = tube(4, true);
    let (l1, l2) = (16.0, 40.0);
    let (k1, imbalance1) = tube(l1 as usize, false);
    let (k2, imbalance2) = tube(l2 as usize, false);
    assert!(
        imbalance1 < 1e-6 && imbalance2 < 1e-6,
        "{imbalance1} {imbalance2}"
    );
    // entrance losses lower the apparent permeability of the short sample most
    assert!(k1 < k2 && k2 < developed, "{k1} {k2} {developed}");
    let slope = (l2 - l1) / (l2 / k2 - l1 / k1);
    // measured: 2e-7
    assert!(
        (slope / developed - 1.0).abs() < 1e-4,
        "{slope} vs {developed}"
    );
    let hagen_poiseuille = std::f64::consts::PI * r.powi(4) / (8.0 * (n * n) as f64);
    assert!(
        // measured: -3.5 % at R = 6 voxels
        (developed / hagen_poiseuille - 1.0).abs() < 0.05,
        "{developed} vs {hagen_poiseuille}"
    );
}

/// `mirror` solves the image reflected across its non-periodic axes: the same tensor as the
/// explicitly mirrored image given as periodic, with the pores touching the faces.
#[test]
fn mirror_equals_the_explicitly_mirrored_periodic_image() {
    let img = image([10, 8, 6], [false, true, false], |p| {
        let [x, y, z] = p.map(|v| v as f64);
        (x - 1.0).powi(2) + (y - 3.0).powi(2) + (z - 2.0).powi(2) < 10.0
            || (x - 8.0).powi(2) + (z - 5.0).powi(2) < 5.0
            || (y - 6.0).abs() < 1.0
    });
    let dirs = vec![Axis::X, Axis::Y, Axis::Z];
    let (mirrored, _, _) = run(&img, &params(Some(Boundary::Mirror), dirs.clone())).unwrap();
    let explicit = mirror_image(&img, [true, false, true]);
    assert_eq!(explicit.grid.dims, [20, 8, 12]);
    let (reference, _, _) = run(&explicit, &params(None, dirs)).unwrap();
    for (a, b) in mirrored.values.iter().zip(&reference.values) {
        assert!((a - b).abs() <= 1e-9 * b.abs().max(1e-20), "{a} vs {b}");
    }
    assert!(mirrored.values[0] > 0.0 && mirrored.values[8] > 0.0);
}

/// The permeameter on sub-voxel walls (`interfaces: composite`, here the fractions of a
/// coarsened all-fluid sample, so the walls it adds sit on voxel faces): the sub-voxel wall
/// rule and its profile quadrature are exact for plane Poiseuille flow (subvoxel.rs), so the
/// slit gives the continuum H^2 / 12 instead of the label walls' H^2 / 12 + 1/6.
#[test]
fn walls_with_composite_fractions_give_the_continuum_slit() {
    let gap = 8;
    let fine = image([8, 4, 2 * gap], [false, true, false], |_| true);
    let mut p = params(Some(Boundary::Walls), vec![Axis::X]);
    p.interface.interfaces = grainpipe_core::subvoxel::Interfaces::Composite;
    p.interface.coarsen = 2;
    let (k, t, _) = run(&fine, &p).unwrap();
    let h = 2.0 * H;
    let kappa = k.values[0] / (h * h);
    let continuum = (gap * gap) as f64 / 12.0;
    // measured: +5e-4
    assert!(
        (kappa / continuum - 1.0).abs() < 1e-3,
        "{kappa} vs {continuum}"
    );
    assert!(col(&t, "mass_balance")[0] < 1e-6);
}
