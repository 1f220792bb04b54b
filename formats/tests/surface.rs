//! Interface surfaces of phase images (`mesh: surface` on the `vtu` and `gmsh` exports):
//! a voxelized sphere against 4/3 pi r^3 and 4 pi r^2, watertightness and the Euler
//! characteristic of a sphere, the tags and positions of laminate interfaces, the closure
//! of every phase's boundary in a random three-phase image, Taubin smoothing, and the files
//! read back by small parsers. meshio and gmsh read the same files in
//! tests/interop/test_mesh.py.

use grainpipe_core::registry::ExportOptions;
use grainpipe_core::serde_json::json;
use grainpipe_core::*;
use grainpipe_formats::mesh::surface::{
    area_and_volume, decimate, interfaces, taubin_smooth, InterfaceMesh,
};
use grainpipe_formats::mesh::{GmshExporter, VtuExporter};
use std::collections::HashMap;
use std::f64::consts::PI;

const H: f64 = 2e-6;
const ORIGIN: [f64; 3] = [1e-3, -2e-4, 5e-5];

/// A ball of label 1 (radius `r` voxels, centred in an `n`^3 box) in label 0: voxel v is in
/// the ball when its centre is.
fn ball(n: usize, r: f64) -> Vec<u8> {
    let c = n as f64 / 2.0;
    let mut l = Vec::with_capacity(n * n * n);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let d2: f64 = [x, y, z]
                    .iter()
                    .map(|&i| (i as f64 + 0.5 - c).powi(2))
                    .sum();
                l.push(u8::from(d2 < r * r));
            }
        }
    }
    l
}

fn index_of(m: &InterfaceMesh, pair: [i32; 2]) -> usize {
    m.pairs
        .iter()
        .position(|p| *p == pair)
        .expect("interface present")
}

type EdgeCounts = HashMap<(u32, u32), usize>;

/// Undirected edge -> number of triangles, and directed edge -> count.
fn edge_counts(tris: &[[u32; 3]]) -> (EdgeCounts, EdgeCounts) {
    let mut und = HashMap::new();
    let mut dir = HashMap::new();
    for t in tris {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            *und.entry((a.min(b), a.max(b))).or_insert(0) += 1;
            *dir.entry((a, b)).or_insert(0) += 1;
        }
    }
    (und, dir)
}

/// The enclosed volume and area of a voxelized sphere. Reference: 4/3 pi r^3 and 4 pi r^2.
/// Tolerances from the voxel size h: the vertices are midpoints between a centre inside and
/// one outside the ball, so the surface follows the sphere with a mean signed offset well
/// below h/8; the volume is within a shell of h/8, |V - V0| <= 4 pi r^2 h / 8 (3/8 h/r
/// relative: 4.7 % at r = 8 h, 1.9 % at r = 20 h; measured 1.0 %, 0.6 %, 0.05 % at r = 8,
/// 12, 20 h). The area of a midpoint marching-tetrahedra surface of binary voxels carries a
/// resolution-independent bias (its facets take few lattice orientations; the voxel-face
/// staircase's is exactly 3/2): measured +26 to +30 % at r = 8-20 h, asserted within
/// [+20 %, +32 %] and below the staircase's +50 %.
#[test]
fn sphere_volume_and_area_match_the_ball_and_the_surface_is_a_closed_sphere() {
    for r in [8.0, 12.0, 20.0] {
        let n = (2.0 * r) as usize + 8;
        let l = ball(n, r);
        let m = interfaces([n; 3], ORIGIN, [H; 3], &l, |_, _| true).unwrap();
        // Interfaces: exterior|0 (the box) and 0|1 (the sphere), no other.
        assert_eq!(m.pairs, vec![[-1, 0], [0, 1]]);
        let k = index_of(&m, [0, 1]);
        let tris = m.interface_triangles(k);
        let (a, v) = area_and_volume(&m, tris);
        let rr = r * H;
        let (a0, v0) = (4.0 * PI * rr * rr, 4.0 / 3.0 * PI * rr.powi(3));
        assert!((v - v0).abs() <= a0 * H / 8.0, "r = {r}: V/V0 = {}", v / v0);
        let bias = a / a0 - 1.0;
        assert!((0.20..=0.32).contains(&bias), "r = {r}: A/A0 - 1 = {bias}");
        // Watertight: every edge in exactly two triangles, once in each direction (the
        // orientation is consistent), and Euler characteristic V - E + F = 2 (a sphere).
        let (und, dir) = edge_counts(tris);
        assert!(und.values().all(|&c| c == 2));
        assert!(dir.values().all(|&c| c == 1));
        let mut verts: Vec<u32> = tris.iter().flatten().copied().collect();
        verts.sort_unstable();
        verts.dedup();
        let chi = verts.len() as i64 - und.len() as i64 + tris.len() as i64;
        assert_eq!(chi, 2, "r = {r}");
        // The box: closed too, its faces on the voxel faces of the image (the outward normal
        // points into the exterior), its 12 edges chamfered by at most half a voxel (a
        // prism of cross-section h^2/8 along each).
        let box_tris = m.interface_triangles(index_of(&m, [-1, 0]));
        let (und, _) = edge_counts(box_tris);
        assert!(und.values().all(|&c| c == 2));
        let (_, vbox) = area_and_volume(&m, box_tris);
        let side = n as f64 * H;
        assert!(vbox <= side.powi(3) * (1.0 + 1e-12), "{vbox}");
        assert!(side.powi(3) - vbox <= 12.0 * side * H * H / 8.0, "{vbox}");
    }
}

/// Taubin smoothing (10 iterations) of the r = 12 h and 20 h spheres: the volume changes by
/// less than 0.5 % while the area error falls from 26-28 % to below 8 %; the box and the
/// number of points and triangles do not change.
#[test]
fn taubin_smoothing_keeps_the_volume_and_removes_the_area_bias() {
    for r in [12.0, 20.0] {
        let n = (2.0 * r) as usize + 8;
        let m = interfaces([n; 3], ORIGIN, [H; 3], &ball(n, r), |_, _| true).unwrap();
        let k = index_of(&m, [0, 1]);
        let (a, v) = area_and_volume(&m, m.interface_triangles(k));
        let mut s = m.clone();
        taubin_smooth(&mut s, 10);
        let (a1, v1) = area_and_volume(&s, s.interface_triangles(k));
        let a0 = 4.0 * PI * (r * H).powi(2);
        assert!(
            (v1 / v - 1.0).abs() < 5e-3,
            "r = {r}: dV/V = {}",
            v1 / v - 1.0
        );
        assert!((a1 / a0 - 1.0).abs() < 0.08, "r = {r}: A/A0 = {}", a1 / a0);
        assert!((a1 / a0 - 1.0).abs() < 0.5 * (a / a0 - 1.0).abs());
        let b = index_of(&m, [-1, 0]);
        assert_eq!(
            area_and_volume(&s, s.interface_triangles(b)),
            area_and_volume(&m, m.interface_triangles(b))
        );
        assert_eq!(
            (s.points.len(), s.triangles),
            (m.points.len(), m.triangles.clone())
        );
    }
}

/// Decimation (meshoptimizer, half-voxel error bound) of the smoothed r = 20 h sphere to a
/// quarter of its triangles: at most 0.25 of the triangles (+1 %) remain, the sphere is
/// still closed and welded (every edge in two triangles, once per direction, Euler
/// characteristic 2), its volume within the half-voxel shell of the undecimated one
/// (|dV| <= A h / 2) and in fact within 1 %, and unused points are dropped. On the
/// three-phase laminate with a ball, the junction lines (points on two interfaces) are kept.
#[test]
fn decimation_keeps_a_closed_sphere_and_the_junctions() {
    let (n, r) = (48usize, 20.0);
    let mut m = interfaces([n; 3], ORIGIN, [H; 3], &ball(n, r), |_, _| true).unwrap();
    taubin_smooth(&mut m, 10);
    let k = index_of(&m, [0, 1]);
    let before = m.interface_triangles(k).len();
    let (a, v) = area_and_volume(&m, m.interface_triangles(k));
    decimate(&mut m, 0.25, [H; 3]);
    let tris = m.interface_triangles(k);
    assert!(
        (tris.len() as f64) <= 0.2525 * before as f64,
        "{} of {before}",
        tris.len()
    );
    let (und, dir) = edge_counts(tris);
    assert!(und.values().all(|&c| c == 2));
    assert!(dir.values().all(|&c| c == 1));
    let mut verts: Vec<u32> = m.triangles.iter().flatten().copied().collect();
    verts.sort_unstable();
    verts.dedup();
    assert_eq!(verts.len(), m.points.len(), "every point used");
    let sphere_verts = {
        let mut s: Vec<u32> = tris.iter().flatten().copied().collect();
        s.sort_unstable();
        s.dedup();
        s.len() as i64
    };
    assert_eq!(sphere_verts - und.len() as i64 + tris.len() as i64, 2);
    let (a1, v1) = area_and_volume(&m, tris);
    println!(
        "decimated {before} -> {} triangles, dV/V = {:.2e}, A/A0 - 1 = {:.4} (before {:.4})",
        tris.len(),
        v1 / v - 1.0,
        a1 / (4.0 * PI * (r * H).powi(2)) - 1.0,
        a / (4.0 * PI * (r * H).powi(2)) - 1.0
    );
    assert!((v1 - v).abs() <= a * H / 2.0);
    assert!((v1 / v - 1.0).abs() < 0.01, "{}", v1 / v - 1.0);

    // Junctions: a ball of 1 cut by a plane into 1 and 2, in 0. The points where three
    // labels meet (pore|grain|binder) are on the three interfaces before and after.
    let mut l = ball(24, 9.0);
    for (i, x) in l.iter_mut().enumerate() {
        if *x == 1 && i / (24 * 24) >= 12 {
            *x = 2;
        }
    }
    let m0 = interfaces([24; 3], ORIGIN, [H; 3], &l, |_, _| true).unwrap();
    let junction = |m: &InterfaceMesh| {
        let mut on: HashMap<[u64; 3], u8> = HashMap::new();
        for (t, &k) in m.triangles.iter().zip(&m.interface) {
            if m.pairs[k as usize][0] < 0 {
                continue;
            }
            for &v in t {
                *on.entry(m.points[v as usize].map(f64::to_bits))
                    .or_insert(0) |= 1 << k;
            }
        }
        let mut j: Vec<[u64; 3]> = on
            .into_iter()
            .filter(|(_, mask)| mask.count_ones() == 3)
            .map(|(p, _)| p)
            .collect();
        j.sort_unstable();
        j
    };
    let mut m1 = m0.clone();
    decimate(&mut m1, 0.2, [H; 3]);
    assert!(m1.triangles.len() < m0.triangles.len() / 2);
    assert!(!junction(&m0).is_empty());
    assert_eq!(junction(&m1), junction(&m0));
}

/// A three-layer laminate along z: pore (0) for z < 3, grain (1) for 3 <= z < 7, binder (2)
/// above. Reference: the planes z = origin + 3 h (pore|grain) and z = origin + 7 h
/// (grain|binder). Away from the box walls (the cubes of voxel centres fully inside, x and y
/// in [h/2, (n - 1/2) h] from the origin) each plane is exactly (nx - 1)(ny - 1) cubes of 8
/// triangles, area (nx - 1)(ny - 1) h^2, normals -z (out of the higher label, above, into
/// the lower); there is no pore|binder interface.
#[test]
fn laminate_interfaces_lie_on_their_planes_with_their_phase_pairs() {
    let (nx, ny, nz) = (7usize, 5usize, 10usize);
    let sp = [2e-6, 3e-6, 5e-6];
    let mut l = Vec::new();
    for z in 0..nz {
        for _ in 0..ny * nx {
            l.push(if z < 3 {
                0
            } else if z < 7 {
                1
            } else {
                2
            });
        }
    }
    let m = interfaces([nx, ny, nz], ORIGIN, sp, &l, |_, _| true).unwrap();
    assert_eq!(m.pairs, vec![[-1, 0], [-1, 1], [-1, 2], [0, 1], [1, 2]]);
    let inner = |p: [f64; 3]| {
        (0..2).all(|a| {
            let u = (p[a] - ORIGIN[a]) / sp[a];
            u > 0.5 - 1e-9 && u < [nx, ny][a] as f64 - 0.5 + 1e-9
        })
    };
    for (pair, plane) in [([0, 1], 3.0), ([1, 2], 7.0)] {
        let zp = ORIGIN[2] + plane * sp[2];
        let tris = m.interface_triangles(index_of(&m, pair));
        let on: Vec<[u32; 3]> = tris
            .iter()
            .copied()
            .filter(|&t| m.corners(t).iter().all(|&p| inner(p)))
            .collect();
        assert_eq!(on.len(), 8 * (nx - 1) * (ny - 1), "{pair:?}");
        let mut area = 0.0;
        for &t in &on {
            let c = m.corners(t);
            assert!(
                c.iter().all(|p| (p[2] - zp).abs() <= 1e-12),
                "{pair:?} {c:?}"
            );
            let n = [0, 1].map(|k| [0, 1, 2].map(|a| c[k + 1][a] - c[0][a]));
            let nz_ = n[0][0] * n[1][1] - n[0][1] * n[1][0];
            assert!(
                nz_ < 0.0,
                "normal out of the higher label (above) into the lower"
            );
            area -= 0.5 * nz_;
        }
        let expect = ((nx - 1) * (ny - 1)) as f64 * sp[0] * sp[1];
        assert!((area - expect).abs() <= 1e-9 * expect);
        // The rest are within one voxel of the walls, between the layers' centres.
        for &t in tris {
            for p in m.corners(t) {
                assert!((p[2] - zp).abs() <= sp[2] / 2.0 + 1e-12);
            }
        }
    }
}

/// A random three-phase image: every phase's boundary (the triangles of its interfaces,
/// oriented out of it) is closed: each directed edge is matched by its reverse, and the
/// signed volumes of the phases add up to the volume inside the exterior interface.
#[test]
fn every_phase_boundary_closes_in_a_random_three_phase_image() {
    let dims = [9, 8, 7];
    let mut state = 12345u64;
    let l: Vec<u8> = (0..dims.iter().product::<usize>())
        .map(|_| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) % 3) as u8
        })
        .collect();
    let m = interfaces(dims, ORIGIN, [H; 3], &l, |_, _| true).unwrap();
    assert_eq!(m.pairs.len(), 6);
    let mut total = 0.0;
    for p in 0..3i32 {
        let mut tris = Vec::new();
        for (k, pair) in m.pairs.iter().enumerate() {
            for &t in m.interface_triangles(k) {
                if pair[1] == p {
                    tris.push(t);
                } else if pair[0] == p {
                    tris.push([t[0], t[2], t[1]]);
                }
            }
        }
        let (_, dir) = edge_counts(&tris);
        for (&(a, b), &c) in &dir {
            assert_eq!(dir.get(&(b, a)), Some(&c), "phase {p}: edge {a}-{b}");
        }
        let (_, v) = area_and_volume(&m, &tris);
        assert!(v > 0.0);
        total += v;
    }
    let mut outer = Vec::new();
    for (k, pair) in m.pairs.iter().enumerate() {
        if pair[0] == -1 {
            outer.extend_from_slice(m.interface_triangles(k));
        }
    }
    let (_, vout) = area_and_volume(&m, &outer);
    assert!((total - vout).abs() <= 1e-9 * vout, "{total} {vout}");
}

fn image(labels: Vec<u8>, dims: [usize; 3]) -> Artifact {
    Artifact::PhaseImage(PhaseImage {
        grid: Grid {
            dims,
            spacing: [H; 3],
            origin: ORIGIN,
            periodic: [false; 3],
        },
        labels,
        phases: ["pore", "grain", "binder"]
            .iter()
            .enumerate()
            .map(|(i, n)| Phase {
                id: i as u8,
                name: n.to_string(),
            })
            .collect(),
    })
}

fn options(e: &dyn Exporter, extra: serde_json::Value) -> ExportOptions {
    let mut o = e.default_options();
    for (k, v) in extra.as_object().unwrap() {
        o.insert(k.clone(), v.clone());
    }
    o
}

/// The `.msh` file of a grain ball with a binder cap: physical groups named by the pairs,
/// one element block per interface with the same triangle counts as the mesh, element data
/// equal to the pairs; `phases: [binder]` keeps the interfaces touching binder only.
#[test]
fn gmsh_surface_has_a_physical_group_per_interface() {
    let n = 20;
    let mut l = ball(n, 7.0);
    for (v, x) in l.iter_mut().enumerate() {
        if *x == 1 && v / (n * n) >= 12 {
            *x = 2;
        }
    }
    let a = image(l.clone(), [n; 3]);
    let m = interfaces([n; 3], ORIGIN, [H; 3], &l, |_, _| true).unwrap();
    assert_eq!(m.pairs, vec![[-1, 0], [0, 1], [0, 2], [1, 2]]);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("s.msh");
    GmshExporter
        .write(
            &a,
            &p,
            &Provenance::default(),
            &options(&GmshExporter, json!({"mesh": "surface"})),
        )
        .unwrap();
    let text = std::fs::read_to_string(&p).unwrap();
    let sec = |name: &str| -> Vec<&str> {
        let start = text.find(&format!("${name}\n")).unwrap() + name.len() + 2;
        let end = text[start..].find(&format!("$End{name}")).unwrap();
        text[start..start + end].lines().collect()
    };
    assert_eq!(
        sec("PhysicalNames"),
        vec![
            "4",
            "2 1 \"exterior|pore\"",
            "2 2 \"pore|grain\"",
            "2 3 \"pore|binder\"",
            "2 4 \"grain|binder\""
        ]
    );
    let el = sec("Elements");
    let mut counts = Vec::new();
    let mut i = 1;
    while i < el.len() {
        let h: Vec<usize> = el[i].split(' ').map(|x| x.parse().unwrap()).collect();
        assert_eq!((h[0], h[2]), (2, 2));
        counts.push(h[3]);
        i += 1 + h[3];
    }
    assert_eq!(counts, m.counts());
    let nodes: usize = sec("Nodes")[0].split(' ').nth(1).unwrap().parse().unwrap();
    assert_eq!(nodes, m.points.len());
    // phase_b of element e is the pair's b.
    let data: Vec<&str> = text
        .split("$ElementData\n")
        .nth(2)
        .unwrap()
        .lines()
        .collect();
    assert_eq!(data[1], "\"phase_b\"");
    let first_of_last = m.triangles.len() - m.counts()[3] + 1;
    assert_eq!(data[8 + first_of_last - 1], format!("{first_of_last} 2"));
    // Only the interfaces touching binder.
    GmshExporter
        .write(
            &a,
            &p,
            &Provenance::default(),
            &options(
                &GmshExporter,
                json!({"mesh": "surface", "phases": ["binder"]}),
            ),
        )
        .unwrap();
    let text = std::fs::read_to_string(&p).unwrap();
    assert!(text.contains("2 1 \"pore|binder\"\n2 2 \"grain|binder\"\n"));
}

/// Options: `smooth` without `mesh: surface` and `surface` of a packing are refused naming
/// the option; preflight counts the surface's memory.
#[test]
fn surface_options_are_checked() {
    let e = VtuExporter;
    let bad = options(&e, json!({"smooth": 5}));
    assert_eq!(e.check_options(&bad).unwrap_err().0, "smooth");
    let bad = options(&e, json!({"mesh": "surfaces"}));
    assert_eq!(e.check_options(&bad).unwrap_err().0, "mesh");
    let o = options(&e, json!({"mesh": "surface", "smooth": 10}));
    assert!(e.check_options(&o).is_ok());
    let meta = ArtifactMeta::of(ArtifactKind::Packing);
    assert_eq!(e.preflight(&meta, &o).unwrap_err().0, "mesh");
    let mut meta = ArtifactMeta::of(ArtifactKind::PhaseImage);
    meta.grid = Some(Grid {
        dims: [140; 3],
        spacing: [H; 3],
        origin: [0.0; 3],
        periodic: [false; 3],
    });
    let mem = e.preflight(&meta, &o).unwrap();
    assert_eq!(
        mem,
        (16 << 20) + grainpipe_formats::mesh::surface_memory([140; 3], true, false)
    );
}
