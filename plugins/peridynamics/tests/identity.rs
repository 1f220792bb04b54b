//! Particle identity from the image maker (issue 34, item 1): two touching particles of one
//! phase are one region for `components`, two for `packing`, and the bonds between them
//! follow the interface rule of Table I. The bond census is checked against a brute-force
//! classification of every node pair within the horizon.

mod common;

use common::*;
use grainpipe_core::stage::SilentReporter;
use grainpipe_core::RunContext;
use grainpipe_peridynamics::bond_based::{
    resolve_phases, solve_image_with, BondBasedParams, ParticleIdentity, RunResult,
};
use std::sync::Arc;

const NX: usize = 16;
const NY: usize = 16;

/// All voxels "large" (label 1); particle 1 left of x = SPLIT, particle 2 from it on.
const SPLIT: usize = 7;

fn ids() -> Arc<[u32]> {
    (0..NX * NY)
        .map(|v| if v % NX < SPLIT { 1 } else { 2 })
        .collect()
}

fn solve(p: &BondBasedParams, ids: Option<Arc<[u32]>>) -> Result<RunResult, String> {
    let img = image(NX, NY, vec![1; NX * NY]);
    let phases = resolve_phases(&p.materials, &img).map_err(|e| e.to_string())?;
    let ctx = RunContext::new(1, &SilentReporter);
    solve_image_with(p, p.horizon, &img, ids, &phases, &ctx).map_err(|e| e.to_string())
}

/// Brute force: (bonds within the horizon in all, bonds joining the two particles).
fn census(h: f64) -> (i64, i64) {
    let (mut all, mut across) = (0, 0);
    for a in 0..NX * NY {
        for b in a + 1..NX * NY {
            let (dx, dy) = (
                (a % NX) as f64 - (b % NX) as f64,
                (a / NX) as f64 - (b / NX) as f64,
            );
            if (dx * dx + dy * dy).sqrt() <= h + 1e-9 {
                all += 1;
                across += i64::from((a % NX < SPLIT) != (b % NX < SPLIT));
            }
        }
    }
    (all, across)
}

#[test]
fn touching_particles_of_one_phase_bond_by_the_interface_rule_with_packing_identity() {
    let p = BondBasedParams::default();
    let (all, across) = census(p.horizon);
    assert!(across > 0 && across < all);

    // The labels alone: one particle, every bond a particle bond.
    let merged = solve(&p, None).unwrap();
    assert_eq!(col_i64(&merged.report, "particles"), 1);
    assert_eq!(col_i64(&merged.report, "particle_bonds"), all);
    assert_eq!(col_i64(&merged.report, "interface_bonds"), 0);

    // The packing's ids (the default `auto` uses them when given): the bonds across the
    // contact are interface bonds.
    let apart = solve(&p, Some(ids())).unwrap();
    assert_eq!(col_i64(&apart.report, "particles"), 2);
    assert_eq!(col_i64(&apart.report, "interface_bonds"), across);
    assert_eq!(col_i64(&apart.report, "particle_bonds"), all - across);
    assert_eq!(col_i64(&apart.report, "matrix_bonds"), 0);

    // Table I's interface (E_i = E_m = E_p / 4) softens a sample loaded across the contact
    // (tension along x crosses it; the plain `components` stiffness is the upper bound).
    let mut px = BondBasedParams {
        axis: grainpipe_peridynamics::bond_based::Axis::X,
        ..BondBasedParams::default()
    };
    let ex_merged = col_f64(&solve(&px, None).unwrap().report, "effective_modulus");
    let ex_apart = col_f64(
        &solve(&px, Some(ids())).unwrap().report,
        "effective_modulus",
    );
    assert!(
        ex_apart < 0.97 * ex_merged,
        "{ex_apart} vs {ex_merged}: the softer interface must show"
    );
    // With the interface as stiff as the particles the identity changes no bond constant:
    // the same modulus to round-off.
    px.interface.e = px.materials["large"].e;
    let same_merged = col_f64(&solve(&px, None).unwrap().report, "effective_modulus");
    let same_apart = col_f64(
        &solve(&px, Some(ids())).unwrap().report,
        "effective_modulus",
    );
    assert!(
        ((same_apart - same_merged) / same_merged).abs() < 1e-5,
        "{same_apart} vs {same_merged}"
    );

    // `components` ignores given ids; `packing` without them is refused.
    let p_components = BondBasedParams {
        particle_identity: ParticleIdentity::Components,
        ..BondBasedParams::default()
    };
    let r = solve(&p_components, Some(ids())).unwrap();
    assert_eq!(col_i64(&r.report, "interface_bonds"), 0);
    let p_packing = BondBasedParams {
        particle_identity: ParticleIdentity::Packing,
        ..BondBasedParams::default()
    };
    let e = solve(&p_packing, None).err().expect("refused");
    assert!(e.contains("particles"), "{e}");
}

/// A particle voxel without an id, or ids of another size, are errors naming the input.
#[test]
fn particle_ids_that_do_not_fit_the_image_are_refused() {
    let p = BondBasedParams::default();
    let mut holes: Vec<u32> = ids().to_vec();
    holes[NX + 3] = 0;
    let e = solve(&p, Some(holes.into())).err().expect("refused");
    assert!(
        e.contains("voxel (3, 1, 0)") && e.contains("no particle id"),
        "{e}"
    );
    let short: Arc<[u32]> = vec![1u32; 10].into();
    let e = solve(&p, Some(short)).err().expect("refused");
    assert!(e.contains("10 values for 256 voxels"), "{e}");
}
