#!/usr/bin/env python3
"""Writes the DEM result of docs/tutorials/dem-to-tiff.md: `dem_bed.liggghts`, a LIGGGHTS
`dump custom` text file with two frames of a sphere bed (1 x 1 x 0.5 mm box, periodic in x
and y, walls in z; radii 40-60 um, lengths in metres, atoms in processor order as LAMMPS
writes them), and `two_spheres.csv`, the smallest CSV packing (x, y, z, r in um).

    python3 data/tutorial/make_dem_dump.py [OUT_DIR]     # default: data/tutorial

The bed (frame 1, timestep 50000) is random sequential addition of non-overlapping spheres in
the box; frame 0 is the same bed 1.5x looser along z in a taller box, before it settled: a
stand-in for a DEM run, small enough to commit. Only numpy is needed; the seed fixes every byte.
"""

import sys
from pathlib import Path

import numpy as np

SEED = 11
BOX = np.array([1.0e-3, 1.0e-3, 0.5e-3])
COUNT = 300


def main():
    out_dir = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent
    rng = np.random.default_rng(SEED)
    pos, rad = [], []
    while len(pos) < COUNT:
        r = rng.uniform(40e-6, 60e-6)
        # Walls in z: the sphere stays inside; x and y wrap, so overlaps are checked periodically.
        p = rng.uniform([0, 0, r], [BOX[0], BOX[1], BOX[2] - r])
        if pos:
            d = np.array(pos) - p
            d[:, :2] -= BOX[:2] * np.round(d[:, :2] / BOX[:2])
            if (np.linalg.norm(d, axis=1) < np.array(rad) + r).any():
                continue
        pos.append(p)
        rad.append(r)
    pos, rad = np.array(pos), np.array(rad)
    # Frame 0 is the bed before it settled: the same spheres spread 1.5x higher above the
    # floor in a 1.5x taller box (stretching along z only ever widens gaps).
    loose = pos.copy()
    loose[:, 2] = rad + 1.5 * (pos[:, 2] - rad)
    order = rng.permutation(COUNT)  # processor order, not id order
    lines = []
    for step, frame, top in ((0, loose, 1.5 * BOX[2]), (50000, pos, BOX[2])):
        lines += ["ITEM: TIMESTEP", str(step), "ITEM: NUMBER OF ATOMS", str(COUNT),
                  "ITEM: BOX BOUNDS pp pp ff"]
        lines += [f"{0.0:.6e} {b:.6e}" for b in (BOX[0], BOX[1], top)]
        lines.append("ITEM: ATOMS id type x y z vx vy vz radius")
        for i in order:
            x, y, z = frame[i]
            lines.append(f"{i + 1} 1 {x:.9e} {y:.9e} {z:.9e} 0 0 0 {rad[i]:.9e}")
    (out_dir / "dem_bed.liggghts").write_text("\n".join(lines) + "\n")
    (out_dir / "two_spheres.csv").write_text(
        "x [um],y [um],z [um],r [um]\n50,50,50,40\n150,50,50,40\n")
    print(f"{COUNT} spheres, solid fraction {np.sum(4 / 3 * np.pi * rad**3) / BOX.prod():.3f}")


if __name__ == "__main__":
    main()
