//! Microstructure statistics of a packing of rigid grains that are unions of spheres
//! (issue 31): near-contacts between grains, their counts per grain and the contact-normal
//! fabric tensor. Plain functions over slices (sphere centres, radii, body ids, the box and
//! its periodicity): no framework types, so they serve any packing.
//!
//! The gap between two grains is the smallest surface distance of their spheres,
//! `min over a of i, b of j of |c_a - c_b| - r_a - r_b`, over every periodic image of `j`
//! on the periodic axes; the contact normal is the unit vector between the centres of that
//! closest sphere pair. [`near_pairs`] finds every grain pair with a gap up to a cut-off
//! through a cell list over the spheres (core's `CellList`, which reports every periodic
//! image within reach, so cells thinner than a grain are handled); [`near_pairs_brute`] is
//! the O(N^2) definition over explicit images, the reference the cell list is tested against.

use grainpipe_core::spatial::CellList;
use rayon::prelude::*;
use std::collections::HashMap;

/// The spheres of a packing: world centres, radii and the body (grain) each belongs to.
#[derive(Clone, Copy, Debug)]
pub struct Spheres<'a> {
    pub centres: &'a [[f64; 3]],
    pub radii: &'a [f64],
    pub body: &'a [u32],
}

/// The box `[min, min + len)` and which of its axes are periodic.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cell {
    pub min: [f64; 3],
    pub len: [f64; 3],
    pub periodic: [bool; 3],
}

/// One grain pair within the cut-off: bodies `i < j`, their gap (negative if they overlap),
/// the unit normal from the closest sphere of `i` towards the closest sphere of `j` (the
/// image of `j` that realises the gap) and the contact point, the middle of the gap on that
/// line, wrapped into the box on its periodic axes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NearPair {
    pub i: u32,
    pub j: u32,
    pub gap: f64,
    pub normal: [f64; 3],
    pub point: [f64; 3],
}

impl Cell {
    /// `x` wrapped into the box on the periodic axes (as the cell list stores it: a value
    /// within rounding of the period that the cell list puts in cell 0 is given as `w - l`).
    fn wrap(&self, x: [f64; 3], dims: [usize; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| {
            if !self.periodic[a] {
                return x[a];
            }
            let l = self.len[a];
            let w = (x[a] - self.min[a]).rem_euclid(l);
            let w = if (w / (l / dims[a] as f64)).floor() as usize >= dims[a] {
                w - l
            } else {
                w
            };
            self.min[a] + w
        })
    }

    fn wrap_point(&self, x: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| {
            if self.periodic[a] {
                self.min[a] + (x[a] - self.min[a]).rem_euclid(self.len[a])
            } else {
                x[a]
            }
        })
    }
}

/// The closest sphere pair found so far for a grain pair: gap, normal, contact point.
type Closest = Option<(f64, [f64; 3], [f64; 3])>;

/// Keeps the closer of two candidate sphere pairs; on an exact tie the first one found.
fn closer(best: &mut Closest, gap: f64, normal: [f64; 3], point: [f64; 3]) {
    if best.is_none_or(|b| gap < b.0) {
        *best = Some((gap, normal, point));
    }
}

/// Gap, normal and contact point of sphere `a` at `pa` and sphere `b` at `pb` (an image).
fn sphere_pair(pa: [f64; 3], ra: f64, pb: [f64; 3], rb: f64) -> (f64, [f64; 3], [f64; 3]) {
    let d = [0, 1, 2].map(|k| pb[k] - pa[k]);
    let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let gap = dist - ra - rb;
    let n = if dist > 0.0 {
        d.map(|x| x / dist)
    } else {
        [1.0, 0.0, 0.0]
    };
    let s = ra + 0.5 * gap;
    (gap, n, [0, 1, 2].map(|k| pa[k] + n[k] * s))
}

/// Every pair of grains whose gap is at most `cutoff` (see the module doc), sorted by (i, j).
/// Uses a cell list over the spheres with cells of at least `2 r_max + cutoff`; each sphere
/// of body `i` looks at every sphere image within `r_a + r_max + cutoff` and keeps, per
/// partner body `j > i`, the closest pair. Parallel over bodies, deterministic.
pub fn near_pairs(s: Spheres, cell: Cell, cutoff: f64) -> Vec<NearPair> {
    let n = s.centres.len();
    assert!(
        s.radii.len() == n && s.body.len() == n,
        "one radius and body per sphere"
    );
    if n == 0 {
        return Vec::new();
    }
    let rmax = s.radii.iter().cloned().fold(0.0, f64::max);
    let mut cells = CellList::new(cell.min, cell.len, cell.periodic, 2.0 * rmax + cutoff);
    let dims = cells.dims();
    let wrapped: Vec<[f64; 3]> = s.centres.iter().map(|c| cell.wrap(*c, dims)).collect();
    for (k, w) in wrapped.iter().enumerate() {
        cells.insert(k as u32, *w);
    }
    let nb = s.body.iter().map(|&b| b as usize + 1).max().unwrap_or(0);
    let mut of_body: Vec<Vec<u32>> = vec![Vec::new(); nb];
    for (k, &b) in s.body.iter().enumerate() {
        of_body[b as usize].push(k as u32);
    }
    let per_body: Vec<Vec<NearPair>> = (0..nb)
        .into_par_iter()
        .map(|i| {
            let mut best: HashMap<u32, Closest> = HashMap::new();
            for &a in &of_body[i] {
                let (pa, ra) = (wrapped[a as usize], s.radii[a as usize]);
                cells.visit(pa, ra + rmax + cutoff, |b, img| {
                    let j = s.body[b as usize];
                    if j as usize <= i {
                        return true;
                    }
                    let w = wrapped[b as usize];
                    let pb = [w[0] + img[0], w[1] + img[1], w[2] + img[2]];
                    let (gap, nrm, pt) = sphere_pair(pa, ra, pb, s.radii[b as usize]);
                    if gap <= cutoff {
                        closer(best.entry(j).or_insert(None), gap, nrm, pt);
                    }
                    true
                });
            }
            let mut v: Vec<NearPair> = best
                .into_iter()
                .filter_map(|(j, b)| {
                    b.map(|(gap, normal, point)| NearPair {
                        i: i as u32,
                        j,
                        gap,
                        normal,
                        point: cell.wrap_point(point),
                    })
                })
                .collect();
            v.sort_by_key(|p| p.j);
            v
        })
        .collect();
    per_body.into_iter().flatten().collect()
}

/// The definition, O(N^2) in spheres: every sphere pair of different bodies, every periodic
/// image within `+-k` periods where `k` covers twice the largest radius plus the cut-off.
/// Only for tests and small packings.
pub fn near_pairs_brute(s: Spheres, cell: Cell, cutoff: f64) -> Vec<NearPair> {
    let n = s.centres.len();
    let rmax = s.radii.iter().cloned().fold(0.0, f64::max);
    let reach = 2.0 * rmax + cutoff;
    let k: [i64; 3] = [0, 1, 2].map(|a| {
        if cell.periodic[a] {
            (reach / cell.len[a]).ceil() as i64 + 1
        } else {
            0
        }
    });
    let mut best: HashMap<(u32, u32), Closest> = HashMap::new();
    for a in 0..n {
        for b in 0..n {
            let (i, j) = (s.body[a], s.body[b]);
            if i >= j {
                continue;
            }
            for ix in -k[0]..=k[0] {
                for iy in -k[1]..=k[1] {
                    for iz in -k[2]..=k[2] {
                        let sh = [
                            ix as f64 * cell.len[0],
                            iy as f64 * cell.len[1],
                            iz as f64 * cell.len[2],
                        ];
                        let pb = [0, 1, 2].map(|q| s.centres[b][q] + sh[q]);
                        let (gap, nrm, pt) = sphere_pair(s.centres[a], s.radii[a], pb, s.radii[b]);
                        if gap <= cutoff {
                            closer(best.entry((i, j)).or_insert(None), gap, nrm, pt);
                        }
                    }
                }
            }
        }
    }
    let mut v: Vec<NearPair> = best
        .into_iter()
        .filter_map(|((i, j), b)| {
            b.map(|(gap, normal, point)| NearPair {
                i,
                j,
                gap,
                normal,
                point: cell.wrap_point(point),
            })
        })
        .collect();
    v.sort_by_key(|p| (p.i, p.j));
    v
}

/// Number of near-contacts of each of `bodies` grains among `pairs` with a gap <= `within`.
pub fn counts(pairs: &[NearPair], bodies: usize, within: f64) -> Vec<u32> {
    let mut c = vec![0u32; bodies];
    for p in pairs.iter().filter(|p| p.gap <= within) {
        c[p.i as usize] += 1;
        c[p.j as usize] += 1;
    }
    c
}

/// Histogram of counts: entry k = how many of `counts` equal k (k = 0..=max).
pub fn histogram(counts: impl IntoIterator<Item = u32>) -> Vec<u64> {
    let mut h: Vec<u64> = Vec::new();
    for c in counts {
        let c = c as usize;
        if h.len() <= c {
            h.resize(c + 1, 0);
        }
        h[c] += 1;
    }
    h
}

/// The second-order fabric tensor N = <n n> (row-major 3x3) of the given unit normals, the
/// mean of n_i n_j over them; `None` without any normal. Trace 1; I/3 for isotropic normals.
pub fn fabric<'a>(normals: impl IntoIterator<Item = &'a [f64; 3]>) -> Option<[f64; 9]> {
    let mut t = [0.0; 9];
    let mut k = 0usize;
    for n in normals {
        for a in 0..3 {
            for b in 0..3 {
                t[3 * a + b] += n[a] * n[b];
            }
        }
        k += 1;
    }
    (k > 0).then(|| t.map(|x| x / k as f64))
}

/// The anisotropy of a fabric tensor along z: 3 N_zz - 1. 0 for isotropic normals, -1 when
/// every normal lies in the x-y plane, 2 when every normal is along z.
pub fn anisotropy_z(n: &[f64; 9]) -> f64 {
    3.0 * n[8] - 1.0
}

/// The norm of the deviator D = N - I/3 scaled to sqrt(3/2 D:D): 0 for isotropic normals,
/// 1 when every normal is along one axis, 1/2 for normals spread evenly in a plane.
pub fn deviator_norm(n: &[f64; 9]) -> f64 {
    let mut dd = 0.0;
    for a in 0..3 {
        for b in 0..3 {
            let d = n[3 * a + b] - if a == b { 1.0 / 3.0 } else { 0.0 };
            dd += d * d;
        }
    }
    (1.5 * dd).sqrt()
}

/// The statistics of one layer of a stacked packing (of the whole packing for one layer).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LayerStats {
    pub grains: usize,
    /// Mean over the layer's grains of their near-contacts (partners in any layer).
    pub near_per_grain: f64,
    /// Grains of the layer with 0, 1, 2, ... near-contacts.
    pub near_histogram: Vec<u64>,
    /// As `near_per_grain` within the bridge distance.
    pub bridges_per_grain: f64,
    pub bridge_histogram: Vec<u64>,
    /// Near-contacts between two grains of the layer, and their fabric.
    pub contacts: usize,
    pub fabric: Option<[f64; 9]>,
    /// Near-contacts between grains of different layers whose contact point is nearest the
    /// plane at the layer's bottom (z = z_min + layer T; with a periodic z the top plane is
    /// the bottom of layer 0), and their fabric.
    pub interface_contacts: usize,
    pub interface_fabric: Option<[f64; 9]>,
}

/// How bodies are layered: `layer[b]` is body b's layer, `layers` layers `thickness` thick
/// from `z_min`, the stack periodic in z or not.
#[derive(Clone, Copy, Debug)]
pub struct Layering<'a> {
    pub layer: &'a [u32],
    pub layers: usize,
    pub z_min: f64,
    pub thickness: f64,
    pub periodic_z: bool,
}

/// Per-layer statistics from the near pairs: near-contacts are pairs with a gap <=
/// `contact`, bridges those with a gap <= `bridge`.
pub fn layer_stats(pairs: &[NearPair], ly: Layering, contact: f64, bridge: f64) -> Vec<LayerStats> {
    let Layering {
        layer,
        layers,
        z_min,
        thickness,
        periodic_z,
    } = ly;
    let near = counts(pairs, layer.len(), contact);
    let bridges = counts(pairs, layer.len(), bridge);
    let mut out: Vec<LayerStats> = (0..layers)
        .map(|l| {
            let members: Vec<usize> = (0..layer.len())
                .filter(|&b| layer[b] as usize == l)
                .collect();
            let mean = |c: &[u32]| {
                members.iter().map(|&b| c[b] as f64).sum::<f64>() / members.len().max(1) as f64
            };
            LayerStats {
                grains: members.len(),
                near_per_grain: mean(&near),
                near_histogram: histogram(members.iter().map(|&b| near[b])),
                bridges_per_grain: mean(&bridges),
                bridge_histogram: histogram(members.iter().map(|&b| bridges[b])),
                ..LayerStats::default()
            }
        })
        .collect();
    let mut within: Vec<Vec<[f64; 3]>> = vec![Vec::new(); layers];
    let mut across: Vec<Vec<[f64; 3]>> = vec![Vec::new(); layers];
    for p in pairs.iter().filter(|p| p.gap <= contact) {
        let (li, lj) = (layer[p.i as usize] as usize, layer[p.j as usize] as usize);
        if li == lj {
            within[li].push(p.normal);
        } else {
            let k = ((p.point[2] - z_min) / thickness).round() as i64;
            let k = if periodic_z {
                k.rem_euclid(layers as i64)
            } else {
                k.clamp(0, layers as i64 - 1)
            };
            across[k as usize].push(p.normal);
        }
    }
    for (l, o) in out.iter_mut().enumerate() {
        o.contacts = within[l].len();
        o.fabric = fabric(&within[l]);
        o.interface_contacts = across[l].len();
        o.interface_fabric = fabric(&across[l]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn anisotropy_measures_of_the_limiting_fabrics() {
        let iso = [
            1.0 / 3.0,
            0.0,
            0.0,
            0.0,
            1.0 / 3.0,
            0.0,
            0.0,
            0.0,
            1.0 / 3.0,
        ];
        let z = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        let plane = [0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0];
        assert!(anisotropy_z(&iso).abs() < 1e-15 && deviator_norm(&iso) < 1e-15);
        assert_eq!(anisotropy_z(&z), 2.0);
        assert!((deviator_norm(&z) - 1.0).abs() < 1e-15);
        assert_eq!(anisotropy_z(&plane), -1.0);
        assert!((deviator_norm(&plane) - 0.5).abs() < 1e-15);
    }

    #[test]
    fn histogram_counts_each_value() {
        assert_eq!(histogram([0, 2, 2, 5]), vec![1, 0, 2, 0, 0, 1]);
        assert!(histogram([]).is_empty());
    }
}
