"""Force-sweep throughput of the peer `peripy` (OpenCL, pocl on the CPU) on the grid of
pd_bench: an n x n regular grid, horizon 3 dx (28 neighbours), homogeneous, explicit
Euler steps (peripy has no quasi-static solver). Usage: python peer_sweep.py N STEPS"""
import sys
import tempfile
import time

import meshio
import numpy as np
from peripy import Model
from peripy.integrators import EulerCL

n = int(sys.argv[1]) if len(sys.argv) > 1 else 256
steps = int(sys.argv[2]) if len(sys.argv) > 2 else 20
dx = 1.0 / n
xs = (np.arange(n) + 0.5) * dx
X, Y = np.meshgrid(xs, xs, indexing="xy")
points = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], axis=1)
mesh = tempfile.NamedTemporaryFile(suffix=".vtk", delete=False).name
# peripy reads 2-D meshes as triangles: two per grid square (volumes are given below).
i = np.arange(n - 1)
a = (i[None, :] + n * i[:, None]).ravel()
tri = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
e = np.arange(n - 1)
lines = np.concatenate([np.stack([e, e + 1], 1), np.stack([n * (n - 1) + e, n * (n - 1) + e + 1], 1)])
meshio.write_points_cells(mesh, points, [("triangle", tri), ("line", lines)])
# h = 3 dx with the same tiny tolerance as the Rust stencil (keeps (3, 0): 28 neighbours).
horizon = 3.0 * dx * (1.0 + 1e-6)
# 2-D plane-stress micromodulus c = 6E / (pi h^3 (1 - nu)) (issue 16), E = 1, nu = 1/3.
c = 6.0 / (np.pi * horizon**3 * (2.0 / 3.0))


def boundary(x):
    # bottom row clamped, top row displaced in +y (uniaxial tension as in pd_bench)
    if x[1] < dx:
        return [0, 0, None]
    if x[1] > 1.0 - dx:
        return [None, 1, None]
    return [None, None, None]


t = time.time()
model = Model(mesh, integrator=EulerCL(dt=1e-9), horizon=horizon,
              critical_stretch=1.0, bond_stiffness=c, dimensions=2,
              volume=np.full(n * n, dx * dx), is_displacement_boundary=boundary)
setup = time.time() - t
nbonds = int(model.n_neigh.sum()) if hasattr(model, "n_neigh") else -1
print(f"peripy n={n}: set-up (neighbour search, connectivity) {setup:.1f} s, "
      f"{nbonds} bond ends, max neighbours {model.max_neighbours}")
model.simulate(steps=2, displacement_bc_magnitudes=np.full(2, 1e-7))
t = time.time()
model.simulate(steps=steps, displacement_bc_magnitudes=np.full(steps, 1e-7))
s = (time.time() - t) / steps
print(f"peripy n={n}: {1e3 * s:.1f} ms per explicit step, "
      f"{n * n * 28 / s:.3e} bond updates/s (n^2 x 28)")
