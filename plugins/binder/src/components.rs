//! Counting the binder bridges: face-connected (6-neighbour) components of one label,
//! joined across periodic faces. Only the voxels of that label are indexed (a sorted list
//! searched by bisection), so the memory is a few bytes per binder voxel, not per voxel.

use grainpipe_core::Grid;

fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let p = parent[i as usize];
        parent[i as usize] = parent[p as usize];
        i = p;
    }
    i
}

/// Number of connected components of the voxels carrying `label`.
pub fn count_components(grid: &Grid, labels: &[u8], label: u8) -> usize {
    let members: Vec<usize> = labels
        .iter()
        .enumerate()
        .filter(|(_, &l)| l == label)
        .map(|(i, _)| i)
        .collect();
    let mut parent: Vec<u32> = (0..members.len() as u32).collect();
    let [nx, ny, nz] = grid.dims;
    let dims = [nx, ny, nz];
    let stride = [1, nx, nx * ny];
    for (m, &i) in members.iter().enumerate() {
        let c = [i % nx, (i / nx) % ny, i / (nx * ny)];
        // The +1 neighbour along each axis covers every face once.
        for a in 0..3 {
            let j = if c[a] + 1 < dims[a] {
                i + stride[a]
            } else if grid.periodic[a] && dims[a] > 1 {
                i - c[a] * stride[a]
            } else {
                continue;
            };
            if labels[j] != label {
                continue;
            }
            let n = members.binary_search(&j).expect("a member voxel") as u32;
            let (ra, rb) = (find(&mut parent, m as u32), find(&mut parent, n));
            if ra != rb {
                parent[ra.max(rb) as usize] = ra.min(rb);
            }
        }
    }
    (0..members.len() as u32)
        .filter(|&m| find(&mut parent, m) == m)
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_blobs_and_joins_across_periodic_faces() {
        let grid = |periodic| Grid {
            dims: [6, 4, 3],
            spacing: [1.0; 3],
            origin: [0.0; 3],
            periodic: [periodic; 3],
        };
        let mut l = vec![0u8; 72];
        let at = |x: usize, y: usize, z: usize| x + 6 * (y + 4 * z);
        l[at(0, 1, 1)] = 2;
        l[at(5, 1, 1)] = 2; // the periodic neighbour of the first along x
        l[at(2, 2, 0)] = 2;
        l[at(2, 3, 0)] = 2; // face neighbour
        l[at(3, 0, 2)] = 2; // diagonal to nothing
        assert_eq!(count_components(&grid(false), &l, 2), 4);
        assert_eq!(count_components(&grid(true), &l, 2), 3);
    }
}
