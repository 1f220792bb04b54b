//! The binder stages through YAML: grid independence against the closing baseline (the
//! point of section 2.3), and pipelines/binder.yaml on a stacked-MCM packing of real sand.

use grainpipe_core::testing::{run_pipeline, run_yaml, workspace_root};
use grainpipe_core::{PhaseImage, Registry};

fn registry() -> Registry {
    let mut r = Registry::new();
    grainpipe_formats::register(&mut r);
    grainpipe_geometry::register(&mut r);
    grainpipe_clumps::register(&mut r);
    grainpipe_mcm::register(&mut r);
    grainpipe_binder::register(&mut r);
    grainpipe_analysis::register(&mut r);
    r
}

#[test]
fn registry_is_consistent() {
    registry().check_consistency().unwrap();
}

/// Mismatch between a coarse binder image and a fine one of the same packing: per coarse
/// voxel, the share of its 8 fine children that are binder against its own 0/1, summed and
/// divided by the coarse binder voxels (0 = the fine image coarsens to the coarse one).
fn mismatch(coarse: &PhaseImage, fine: &PhaseImage) -> f64 {
    let [cx, cy, cz] = coarse.grid.dims;
    assert_eq!(fine.grid.dims, [2 * cx, 2 * cy, 2 * cz]);
    let mut err = 0.0;
    for z in 0..cz {
        for y in 0..cy {
            for x in 0..cx {
                let mut share = 0.0;
                for k in 0..8 {
                    let (i, j, l) = (2 * x + (k & 1), 2 * y + ((k >> 1) & 1), 2 * z + (k >> 2));
                    share += f64::from(u8::from(fine.labels[fine.grid.index(i, j, l)] == 2)) / 8.0;
                }
                let b = f64::from(u8::from(coarse.labels[coarse.grid.index(x, y, z)] == 2));
                err += (share - b).abs();
            }
        }
    }
    err / coarse.labels.iter().filter(|&&l| l == 2).count() as f64
}

fn rsa_yaml() -> String {
    // About 80 non-overlapping spheres of radius 6-10 um at 35 %: random gaps, so bridges
    // form only where neighbours come close.
    String::from(
        "name: grid\nseed: 7\nstages:\n  - id: pack\n    use: packing.rsa\n    with:\n      \
         size: [80 um, 80 um, 80 um]\n      radius: {kind: uniform, min: 6 um, max: 10 um}\n      \
         volume_fraction: 0.35\n",
    )
}

fn binder_count(im: &PhaseImage) -> f64 {
    im.labels.iter().filter(|&&l| l == 2).count() as f64
}

/// The point of section 2.3: the level set is defined without a grid, so the same
/// parameters give the same binder at every voxel size, where a closing on the grid moves
/// with it. Both are fitted to 3 % binder on the finest grid (0.5 um) and then run with that
/// a and that closing radius at 2, 1 and 0.5 um.
#[test]
fn level_set_binder_fraction_depends_less_on_the_grid_than_the_closing() {
    let mut yaml = rsa_yaml();
    for stage in ["levelset", "closing"] {
        yaml.push_str(&format!(
            "  - id: {stage}\n    use: binder.{stage}\n    in: {{ packing: pack.packing }}\n    \
             with: {{ voxel_size: 0.5 um, binder_fraction: 0.03 }}\n"
        ));
    }
    let fitted = run_yaml(&registry(), &yaml).unwrap();
    let a = fitted.column("levelset.report", "a")[0];
    let radius = fitted.column("closing.report", "closing_radius")[0];
    let mut yaml = rsa_yaml();
    for (i, h) in ["2 um", "1 um", "0.5 um"].iter().enumerate() {
        yaml.push_str(&format!(
            "  - id: levelset{i}\n    use: binder.levelset\n    in: {{ packing: pack.packing }}\n    \
             with: {{ voxel_size: {h}, a: {a:e} }}\n  - id: closing{i}\n    use: binder.closing\n    \
             in: {{ packing: pack.packing }}\n    with: {{ voxel_size: {h}, radius: {radius:e} }}\n"
        ));
    }
    let res = run_yaml(&registry(), &yaml).unwrap();
    let img = |id: &str| {
        res.artifact(&format!("{id}.image"))
            .as_phase_image()
            .unwrap()
    };
    let spread = |stage: &str| {
        let f: Vec<f64> = (0..3)
            .map(|i| {
                let im = img(&format!("{stage}{i}"));
                binder_count(im) / im.labels.len() as f64
            })
            .collect();
        let max = f.iter().copied().fold(f64::MIN, f64::max);
        let min = f.iter().copied().fold(f64::MAX, f64::min);
        (max - min) / f[2]
    };
    let (ls, cl) = (spread("levelset"), spread("closing"));
    eprintln!("binder fraction spread over 2, 1, 0.5 um: level set {ls:.4}, closing {cl:.4}");
    assert!(
        ls < 0.05,
        "level-set binder fraction varies by {ls:.3} across resolutions"
    );
    assert!(ls < cl, "level set {ls:.4} vs closing {cl:.4}");
    // Voxel-wise agreement after coarsening is printed for the record, not asserted: the
    // level set's thin films are sampled differently at each voxel size, so this measure
    // does not favour it at every level (docs/stages/binder.md gives the numbers).
    for i in 0..2 {
        let ls = mismatch(
            img(&format!("levelset{i}")),
            img(&format!("levelset{}", i + 1)),
        );
        let cl = mismatch(
            img(&format!("closing{i}")),
            img(&format!("closing{}", i + 1)),
        );
        eprintln!("level {i}: coarsening mismatch level set {ls:.3}, closing {cl:.3}");
    }
}

#[test]
fn binder_pipeline_images_stacked_sand_with_exact_fractions() {
    let root = workspace_root(env!("CARGO_MANIFEST_DIR"));
    let out = tempfile::tempdir().unwrap();
    let res = run_pipeline(&registry(), &root, "binder.yaml", &[], out.path()).unwrap();
    let packing = res.artifact("pack.packing").as_packing().unwrap();
    for step in ["binder", "closing"] {
        let im = res
            .artifact(&format!("{step}.image"))
            .as_phase_image()
            .unwrap();
        assert_eq!(im.grid.dims, [140, 140, 140]);
        let n = im.labels.len() as f64;
        // The packing's analytic clump volume (union volumes of the library), one voxel.
        let analytic = packing.solid_volume() / packing.domain.volume();
        assert!(
            (im.fraction(1) - analytic).abs() <= 1.0 / n,
            "{step}: sand {} vs analytic {analytic}",
            im.fraction(1)
        );
        assert_eq!(
            im.phases
                .iter()
                .map(|p| p.name.as_str())
                .collect::<Vec<_>>(),
            ["pore", "grain", "binder"]
        );
    }
    let ls = res.artifact("binder.image").as_phase_image().unwrap();
    assert!((ls.fraction(2) - 0.02).abs() <= 1.0 / ls.labels.len() as f64);
    // The smoothed level set is 1-Lipschitz (a soft minimum of distances), so where its
    // value at a voxel centre exceeds half the voxel diagonal every sub-sample of that voxel
    // is on the same side: solid (sand or binder) where negative, pore where positive.
    let grainpipe_core::Artifact::Field(field) = res.artifact("binder.level_set") else {
        panic!("level_set is not a field");
    };
    assert_eq!(field.grid, ls.grid);
    let half_diagonal = 0.5 * 3f64.sqrt() * ls.grid.spacing[0] * (1.0 + 1e-6);
    let mut decided = 0;
    for (i, &l) in ls.labels.iter().enumerate() {
        let v = field.data.get(i);
        if v < -half_diagonal {
            assert_ne!(l, 0, "voxel {i}: level set {v:e} < 0 but pore");
            decided += 1;
        } else if v > half_diagonal {
            assert_eq!(l, 0, "voxel {i}: level set {v:e} > 0 but solid");
            decided += 1;
        }
    }
    assert!(decided > ls.labels.len() / 2);
    for f in [
        "levelset.vti",
        "levelset.vtkhdf",
        "levelset.nc",
        "level_set.vti",
        "closing.vti",
    ] {
        assert!(
            out.path().join("binder").join(f).is_file(),
            "{f} not written"
        );
    }
}

/// Two touching spheres of radius 10 um read from a CSV in um through import.packing: the
/// bridge sits at the contact, mirror symmetric about the contact plane. (The radii and a
/// are kept as given: a rank selection splits mirror pairs whose thresholds differ by
/// rounding, which the fraction tests cover.)
#[test]
fn touching_pair_from_csv_gets_a_symmetric_bridge() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("pair.csv");
    std::fs::write(
        &csv,
        "x [um],y [um],z [um],r [um]\n22,20,20,10\n42,20,20,10\n",
    )
    .unwrap();
    let yaml = format!(
        "name: pair\nseed: 1\nstages:\n  - id: pair\n    use: import.packing\n    with: \
         {{ path: {}, box: [64 um, 40 um, 40 um] }}\n  - id: b\n    use: binder.levelset\n    \
         in: {{ packing: pair.packing }}\n    with: {{ voxel_size: 1 um, a: 1.5 um, exact_fractions: false }}\n",
        csv.display()
    );
    let res = run_yaml(&registry(), &yaml).unwrap();
    let im = res.artifact("b.image").as_phase_image().unwrap();
    let g = &im.grid;
    assert_eq!(g.dims, [64, 40, 40]);
    assert!(binder_count(im) > 100.0, "no bridge");
    let [nx, ny, nz] = g.dims;
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let l = im.labels[g.index(x, y, z)];
                assert_eq!(
                    l,
                    im.labels[g.index(nx - 1 - x, y, z)],
                    "mirror at {x} {y} {z}"
                );
                if l == 2 {
                    // Within a few voxels of the contact plane.
                    let dx = (x as f64 + 0.5 - 32.0).abs();
                    assert!(dx < 6.0, "binder {dx} um from the contact plane");
                }
            }
        }
    }
}

/// Issue 35: a voxel larger than the box made a one-voxel image (solid fraction 0 against an
/// analytic 0.31, and a "stiffness" equal to the binder's). Each image maker refuses it at
/// preflight on the key that set the voxel, with the box and the voxel in the message.
#[test]
fn a_voxel_larger_than_the_box_is_refused_at_preflight() {
    for (stage, with) in [
        ("voxelize.packing", "voxel_size: 1 mm"),
        ("binder.levelset", "voxel_size: 1 mm, a: 5 um"),
        ("binder.closing", "voxel_size: 1 mm, radius: 5 um"),
    ] {
        let yaml = format!(
            "name: t\nseed: 1\nstages:\n  - id: pack\n    use: packing.rsa\n    with:\n      \
             size: [400 um, 400 um, 400 um]\n      radius: {{ kind: fixed, value: 25 um }}\n      \
             volume_fraction: 0.3\n  - id: img\n    use: {stage}\n    in: {{ packing: pack.packing }}\n    \
             with: {{ {with} }}\n"
        );
        let Err(e) = run_yaml(&registry(), &yaml) else {
            panic!("{stage}: a one-voxel image was accepted")
        };
        assert_eq!(e.exit_code(), 2, "{stage}: {e}");
        assert!(
            e.message
                .contains("the voxel (1 mm) is larger than the box along x (400 um)"),
            "{stage}: {e}"
        );
        // Reported at the `with:` line that sets voxel_size (line 13).
        assert_eq!(e.loc.map(|l| l.line), Some(13), "{stage}: {e}");
    }
}

/// Issue 35: binder.closing delivered 0.45 % binder for a 30 % target without a word. On
/// dilute spheres (5 %) a closing fills little; a 30 % target now fails, naming the fraction
/// the most a closing fills; a reachable one (5 % on spheres at 30 %) runs.
#[test]
fn binder_closing_fails_loudly_on_a_fraction_it_cannot_reach() {
    let yaml = |density: f64, fraction: f64| {
        format!(
            "name: t\nseed: 1\nstages:\n  - id: pack\n    use: packing.rsa\n    with:\n      \
             size: [200 um, 200 um, 200 um]\n      radius: {{ kind: fixed, value: 25 um }}\n      \
             volume_fraction: {density}\n  - id: img\n    use: binder.closing\n    in: {{ packing: pack.packing }}\n    \
             with: {{ voxel_size: 5 um, binder_fraction: {fraction} }}\n"
        )
    };
    let Err(e) = run_yaml(&registry(), &yaml(0.05, 0.3)) else {
        panic!("a 30 % closing binder was accepted")
    };
    assert_ne!(e.exit_code(), 0);
    assert!(e.message.contains("out of reach of a closing"), "{e}");
    assert!(
        e.message.contains("fills 0.0"),
        "names the most it fills: {e}"
    );
    // A reachable target runs (the steps of the closed fraction are a warning, not a failure).
    let res = run_yaml(&registry(), &yaml(0.3, 0.05)).unwrap();
    let image = res.artifact("img.image").as_phase_image().unwrap();
    assert!(image.fraction(2) > 0.0);
}
