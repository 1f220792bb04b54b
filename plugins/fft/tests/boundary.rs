//! `boundary:` of the FFT solvers on images that are not periodic (a scan, a cut sample):
//! `mirror` against the explicitly mirrored periodic image and against the laminate means,
//! fields on the input's grid, and the preflight refusal without a choice.

mod common;
use common::*;
use grainpipe_core::boundary::{mirror_image, Boundary, BoundaryParams};
use grainpipe_core::stage::TypedStage;
use grainpipe_core::testing::WarningLog;
use grainpipe_core::units::Q;
use grainpipe_core::{
    Artifact, ArtifactKind, ArtifactMeta, InputMetas, Inputs, Outputs, PhaseImage, RunContext,
    StageError,
};
use grainpipe_fft::common::Discretization;
use grainpipe_fft::conductivity::{ConductivityFft, ConductivityParams};
use grainpipe_fft::elasticity::{ElasticityFft, ElasticityParams, LoadCase};
use std::sync::Arc;

fn metas(img: &PhaseImage) -> InputMetas {
    let mut m = InputMetas::new();
    m.insert(
        "image".into(),
        ArtifactMeta::on_grid(ArtifactKind::PhaseImage, img.grid.clone()),
    );
    m
}

fn run<S: TypedStage>(
    stage: &S,
    p: &S::Params,
    img: &PhaseImage,
) -> Result<(Outputs, Vec<String>), StageError> {
    let pf = stage.preflight(p, &metas(img))?;
    let mut inputs = Inputs::new();
    inputs.insert("image".into(), Arc::new(Artifact::PhaseImage(img.clone())));
    let log = WarningLog::default();
    let ctx = RunContext::new(1, &log);
    let out = stage.run(p, &pf.plan, &inputs, &ctx)?;
    Ok((out, log.warnings()))
}

fn tensor(out: &Outputs, port: &str) -> Vec<f64> {
    match &out[port] {
        Artifact::Tensor(t) => t.values.clone(),
        other => panic!("{port} is a {}", other.kind()),
    }
}

fn not_periodic(mut img: PhaseImage, periodic: [bool; 3]) -> PhaseImage {
    img.grid.periodic = periodic;
    img
}

fn conductivity_params(boundary: Option<Boundary>) -> ConductivityParams {
    ConductivityParams {
        conductivities: [("1", 7.7), ("2", 1.0), ("3", 0.2)]
            .iter()
            .map(|&(l, v)| (l.to_string(), Q::new(v)))
            .collect(),
        tolerance: 1e-9,
        boundary: BoundaryParams { boundary },
        ..Default::default()
    }
}

/// Layers normal to z whose sequence is not periodic (3 layers of 3, 2, 4 voxels: the first
/// and last differ, so gluing the faces only joins two layers into one). Mirrored, it is a
/// laminate of the same fractions: the conductivity is the arithmetic mean in the plane and
/// the harmonic mean across, exactly.
#[test]
fn a_mirrored_laminate_gives_the_series_and_parallel_means() {
    let img = not_periodic(
        image([4, 4, 9], 1e-6, |_, _, z| match z {
            0..=2 => 1,
            3..=4 => 2,
            _ => 3,
        }),
        [true, true, false],
    );
    let (out, warnings) = run(
        &ConductivityFft,
        &conductivity_params(Some(Boundary::Mirror)),
        &img,
    )
    .unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    let k = tensor(&out, "conductivity");
    let f = [3.0 / 9.0, 2.0 / 9.0, 4.0 / 9.0];
    let kv = [7.7, 1.0, 0.2];
    let parallel: f64 = (0..3).map(|i| f[i] * kv[i]).sum();
    let series = 1.0 / (0..3).map(|i| f[i] / kv[i]).sum::<f64>();
    assert!(
        (k[0] / parallel - 1.0).abs() < 1e-8,
        "{} vs {parallel}",
        k[0]
    );
    assert!((k[8] / series - 1.0).abs() < 1e-8, "{} vs {series}", k[8]);
    assert!(k[2].abs() < 1e-9 * parallel, "no coupling: {k:?}");
}

/// An irregular two-phase image with pores on every face, not periodic along x and z:
/// `mirror` gives the stiffness and conductivity of its explicitly mirrored periodic image,
/// the fields on the input's grid and the phase fractions of the input.
#[test]
fn mirror_equals_the_explicitly_mirrored_periodic_image() {
    let img = not_periodic(
        image([9, 6, 7], 1e-6, |x, y, z| {
            let [x, y, z] = [x, y, z].map(|v| v as f64);
            let pore = (x - 1.0).powi(2) + (y - 2.0).powi(2) + (z - 6.0).powi(2) < 6.0
                || (x - 8.0).powi(2) + (z - 0.5).powi(2) < 4.0;
            if pore {
                0
            } else if (x + 2.0 * y + z) as usize % 5 == 0 {
                2
            } else {
                1
            }
        }),
        [false, true, false],
    );
    let explicit = mirror_image(&img, [true, false, true]);
    assert_eq!(explicit.grid.dims, [18, 6, 14]);
    let ep = |boundary| ElasticityParams {
        materials: materials(&[(1, 66.9e9, 0.25), (2, 43e9, 0.17)]),
        tolerance: 1e-8,
        discretization: Discretization::Staggered,
        load_cases: vec![LoadCase::Xx, LoadCase::Zz, LoadCase::Xz],
        fields: true,
        boundary: BoundaryParams { boundary },
        ..Default::default()
    };
    let (mirrored, _) = run(&ElasticityFft, &ep(Some(Boundary::Mirror)), &img).unwrap();
    let (reference, _) = run(&ElasticityFft, &ep(None), &explicit).unwrap();
    let (a, b) = (
        tensor(&mirrored, "stiffness"),
        tensor(&reference, "stiffness"),
    );
    for (x, y) in a.iter().zip(&b) {
        assert!((x - y).abs() <= 1e-9 * 66.9e9, "{x} vs {y}");
    }
    // Mirror symmetry: the xx column has no xz (shear) stress.
    assert!(a[4 * 6].abs() < 1e-6 * a[0], "{a:?}");
    // fields on the input's grid: the first octant of the mirrored cell's
    let Artifact::Collection(strain) = &mirrored["strain"] else {
        panic!()
    };
    let Artifact::Collection(strain_ref) = &reference["strain"] else {
        panic!()
    };
    let (Artifact::Field(f), Artifact::Field(g)) = (&strain.items[0].1, &strain_ref.items[0].1)
    else {
        panic!()
    };
    assert_eq!(f.grid.dims, img.grid.dims);
    let (fv, gv) = (&f.data, &g.data);
    let [nx, ny, _] = img.grid.dims;
    for z in 0..7 {
        for y in 0..ny {
            for x in 0..nx {
                for c in 0..6 {
                    let i = 6 * (x + nx * (y + ny * z)) + c;
                    let j = 6 * (x + 18 * (y + ny * z)) + c;
                    assert!((fv.get(i) - gv.get(j)).abs() < 1e-9, "({x}, {y}, {z}) {c}");
                }
            }
        }
    }
    // phase fractions are the input's
    let Artifact::Table(ps) = &mirrored["phase_stress"] else {
        panic!()
    };
    let fractions = ps.f64_column("fraction").unwrap();
    let pore_free: f64 =
        img.labels.iter().filter(|&&l| l == 1).count() as f64 / img.labels.len() as f64;
    assert!(
        fractions.iter().any(|&f| (f - pore_free).abs() < 1e-12),
        "{fractions:?} vs {pore_free}"
    );

    // conductivity too
    let (mc, _) = run(
        &ConductivityFft,
        &conductivity_params(Some(Boundary::Mirror)),
        &img,
    )
    .unwrap();
    let (rc, _) = run(&ConductivityFft, &conductivity_params(None), &explicit).unwrap();
    for (x, y) in tensor(&mc, "conductivity")
        .iter()
        .zip(&tensor(&rc, "conductivity"))
    {
        assert!((x - y).abs() <= 1e-9 * 7.7, "{x} vs {y}");
    }
}

#[test]
fn a_scan_without_a_boundary_is_refused_naming_the_choices() {
    let img = not_periodic(image([4, 4, 4], 1e-6, |x, _, _| (x > 0) as u8), [false; 3]);
    let ep = |boundary| ElasticityParams {
        materials: materials(&[(1, 66.9e9, 0.25)]),
        boundary: BoundaryParams { boundary },
        ..Default::default()
    };
    for (b, want) in [
        (None, "`mirror`"),
        (Some(Boundary::Walls), "stokes.permeability"),
    ] {
        match ElasticityFft.preflight(&ep(b), &metas(&img)) {
            Err(StageError::InvalidParam { key, message }) => {
                assert_eq!(key, "boundary");
                assert!(
                    message.contains(want) && !message.contains("`walls` (no-slip"),
                    "{message}"
                );
            }
            other => panic!("expected a boundary error, got {:?}", other.map(|_| ())),
        }
    }
    let e = match ConductivityFft.preflight(&conductivity_params(None), &metas(&img)) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("a scan without a boundary must be refused"),
    };
    assert!(e.to_string().contains("x, y, z"), "{e}");
    // forced periodic: warned
    let (_, warnings) = run(&ElasticityFft, &ep(Some(Boundary::Periodic)), &img).unwrap();
    assert!(warnings.iter().any(|w| w.contains("glued")), "{warnings:?}");
    // the mirror's memory: the solver state of 8 times the voxels (the per-plane and
    // fixed terms of the estimate do not scale with the voxels)
    let p1 = ElasticityFft
        .preflight(&ep(Some(Boundary::Mirror)), &metas(&img))
        .unwrap();
    let periodic = not_periodic(img.clone(), [true; 3]);
    let p0 = ElasticityFft
        .preflight(&ep(None), &metas(&periodic))
        .unwrap();
    let n = img.labels.len() as u64;
    let state = |voxels| grainpipe_fft::elasticity::memory(&ep(None), voxels);
    assert!(
        p1.memory_bytes - p0.memory_bytes >= state(8 * n) - state(n),
        "{} vs {}",
        p1.memory_bytes,
        p0.memory_bytes
    );
}
