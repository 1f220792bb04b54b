"""Independent numpy reference for `voxelize.packing`: stamps every sphere of a grainpipe
packing (.h5, clumps expanded) into its bounding box of voxels, a voxel being solid when its
centre lies in some sphere (no supersampling), with periodic wrap.

    .venv/bin/python plugins/geometry/bench/stamp_reference.py PACKING.h5 VOXEL_M \
        [--compare IMAGE.h5] [--spheres OUT.csv]

Prints the wall time of the stamping and, with --compare, the fraction of voxels on which
an image exported by `pipe` (dataset `phase`, z y x) agrees with the reference. --spheres
writes the world spheres (x, y, z, r in metres) for other tools.
"""

import argparse
import time

import h5py
import numpy as np


def world_spheres(path):
    with h5py.File(path, "r") as f:
        pos = f["positions"][:]
        domain = f["domain"].attrs
        lo, hi = np.asarray(domain["min"]), np.asarray(domain["max"])
        periodic = np.asarray(domain["periodic"]).astype(bool)
        if "clump_index" not in f:
            return pos, f["radius"][:], lo, hi, periodic
        q = f["orientation"][:]
        ci = f["clump_index"][:]
        first = f["library/first_sphere"][:]
        off = f["library/sphere_offset"][:]
        rad = f["library/sphere_radius"][:]
    centres, radii = [], []
    for b in range(len(pos)):
        w, u = q[b, 0], q[b, 1:]
        v = off[first[ci[b]] : first[ci[b] + 1]]
        # v' = v + 2 w (u x v) + 2 u x (u x v): rotation by the unit quaternion (w, u).
        c1 = np.cross(u, v)
        c2 = np.cross(u, c1)
        centres.append(pos[b] + v + 2.0 * (w * c1 + c2))
        radii.append(rad[first[ci[b]] : first[ci[b] + 1]])
    return np.concatenate(centres), np.concatenate(radii), lo, hi, periodic


def stamp(centres, radii, lo, hi, periodic, voxel):
    dims = np.maximum(np.round((hi - lo) / voxel).astype(int), 1)
    h = (hi - lo) / dims
    img = np.zeros(dims[::-1], dtype=bool)  # z y x
    for c, r in zip(centres, radii):
        axes = []
        for a in range(3):
            i0 = int(np.floor((c[a] - r - lo[a]) / h[a] - 0.5))
            i1 = int(np.ceil((c[a] + r - lo[a]) / h[a] - 0.5))
            idx = np.arange(i0, i1 + 1)
            d = lo[a] + (idx + 0.5) * h[a] - c[a]
            if periodic[a]:
                idx = idx % dims[a]
            else:
                keep = (idx >= 0) & (idx < dims[a])
                idx, d = idx[keep], d[keep]
            axes.append((idx, d))
        (ix, dx), (iy, dy), (iz, dz) = axes
        inside = dz[:, None, None] ** 2 + dy[None, :, None] ** 2 + dx[None, None, :] ** 2 <= r * r
        img[np.ix_(iz, iy, ix)] |= inside
    return img


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("packing")
    ap.add_argument("voxel", type=float)
    ap.add_argument("--compare")
    ap.add_argument("--spheres")
    a = ap.parse_args()
    centres, radii, lo, hi, periodic = world_spheres(a.packing)
    if a.spheres:
        np.savetxt(a.spheres, np.column_stack([centres, radii]), delimiter=",",
                   header="x,y,z,r", comments="", fmt="%.17g")
    t = time.perf_counter()
    img = stamp(centres, radii, lo, hi, periodic, a.voxel)
    wall = time.perf_counter() - t
    print(f"{len(radii)} spheres, {img.shape[2]}x{img.shape[1]}x{img.shape[0]} voxels: "
          f"numpy stamping {wall:.3f} s, solid fraction {img.mean():.5f}")
    if a.compare:
        with h5py.File(a.compare, "r") as f:
            other = f["phase"][:] > 0
        print(f"agreement with {a.compare}: {(other == img).mean() * 100:.3f} % of voxels")


if __name__ == "__main__":
    main()
