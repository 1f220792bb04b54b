"""Independent check of a periodic sphere packing from its CSV (first line `# box Lx Ly Lz`,
then `x,y,z,r`): the volume fraction from the radii and the box, and the smallest surface
gap over every pair and the 27 periodic images (all pairs, no neighbour list)."""
import sys

import numpy as np

path = sys.argv[1]
with open(path) as f:
    box = np.array([float(v) for v in f.readline().split()[2:5]])
d = np.loadtxt(path, delimiter=",", skiprows=2)
x, r = d[:, :3], d[:, 3]
phi = (4.0 / 3.0 * np.pi * r**3).sum() / box.prod()
gap = np.inf
shifts = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)]) * box
for a in range(len(r) - 1):
    dx = x[a + 1 :] - x[a]  # (m, 3)
    dist = np.linalg.norm(dx[:, None, :] + shifts[None, :, :], axis=2).min(axis=1)
    gap = min(gap, (dist - r[a] - r[a + 1 :]).min() / r.mean())
print(f"phi {phi:.5f}, smallest gap {gap:.2e} mean radii ({'no overlap' if gap >= -1e-12 else 'OVERLAP'})")
