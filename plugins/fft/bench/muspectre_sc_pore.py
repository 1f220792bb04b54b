"""Peer side of plugins/fft/bench/peer.sh: the simple-cubic spherical pore of porosity 0.2
(E = 1, nu = 0.3, unit cell) solved with muSpectre (PyPI 0.27.0), small strain.

    python muspectre_sc_pore.py <n> [cases] [tolerance]

Prints one CSV row per load case, the same columns as examples/fft_study.rs:
n,discretization,precision,tolerance,porosity,case,status,iterations,seconds,c11,c12,c44

Discretisation: muSpectre's linear finite elements (each voxel split into six linear
tetrahedra, muFFT.Stencils3D.linear_finite_elements, six quadrature points per voxel). Its
Fourier-derivative default (Moulinec-Suquet) refuses even grids ("Only an odd number of grid
points is supported by this stencil"); the tetrahedra, a conforming finite-element scheme, are
the counterpart of our staggered / hex8 schemes.
"""
import sys
import time

import numpy as np
import muSpectre as msp
from muSpectre import linear_finite_elements as lfe


def sphere_pore(n):
    """Same voxel rule as fft_study.rs: voxel centre within r of the cell centre."""
    r = (0.2 * 3.0 / (4.0 * np.pi)) ** (1.0 / 3.0) * n
    c = np.arange(n) + 0.5 - n / 2.0
    x, y, z = np.meshgrid(c, c, c, indexing="ij")
    return x * x + y * y + z * z < r * r  # indexed [x, y, z]


def main():
    n = int(sys.argv[1])
    cases = sys.argv[2].split(",") if len(sys.argv) > 2 else ["xx", "yz"]
    tol = float(sys.argv[3]) if len(sys.argv) > 3 else 1e-5
    pore = sphere_pore(n)
    porosity = pore.mean()
    stencil, weights = lfe.gradient_3d
    for case in cases:
        t0 = time.perf_counter()
        cell = msp.Cell([n, n, n], [1.0, 1.0, 1.0], msp.Formulation.small_strain,
                        stencil, weights=weights)
        solid = msp.material.MaterialLinearElastic1_3d.make(cell, "solid", 1.0, 0.3)
        # A pore of exactly zero stiffness, as in ours: no artificial soft phase.
        void = msp.material.MaterialLinearElastic1_3d.make(cell, "pore", 0.0, 0.3)
        # muSpectre's pixel index runs with x fastest (column-major), hence order="F".
        for i, is_pore in enumerate(pore.ravel(order="F")):
            (void if is_pore else solid).add_pixel(i)
        cell.initialise()
        eps = np.zeros((3, 3))
        if case == "xx":
            eps[0, 0] = 1.0
        elif case == "yz":
            # engineering shear gamma_yz = 1, so sigma_yz is C44 (a shear modulus)
            eps[1, 2] = eps[2, 1] = 0.5
        else:
            raise SystemExit(f"load case {case}: only xx and yz")
        krylov = msp.solvers.KrylovSolverCG(cell, tol, 10000, msp.Verbosity.Silent)
        # Linear problem: one Newton step; the Newton / equilibrium tolerances only stop it.
        res = msp.solvers.newton_cg(cell, eps, krylov, 1e-8, 1e-8, msp.Verbosity.Silent)
        secs = time.perf_counter() - t0
        # The stress at every quadrature point (equal weights): the cell average is eq. (3.4).
        sig = np.asarray(res.stress).reshape(3, 3, -1, order="F").mean(axis=2)
        iters = krylov.counter
        head = f"{n},muspectre-fe6tet,double,{tol:e},{porosity:.6f},{case}"
        status = "ok" if res.success else "failed: " + str(res.message).replace(",", ";")
        if case == "xx":
            print(f"{head},{status},{iters},{secs:.3f},{sig[0,0]:.8e},{sig[1,1]:.8e},", flush=True)
        else:
            print(f"{head},{status},{iters},{secs:.3f},,,{sig[1,2]:.8e}", flush=True)
        del cell, solid, void, krylov, res


if __name__ == "__main__":
    main()
