"""Lattice-Boltzmann peer (lbmpy) on the Zick & Homsy simple-cubic sphere images (issue 13).

Same images as `examples/arrays.rs` (volume-matched voxelization of a centred sphere, one
voxel = one lattice node, periodic cell), driven by a body force along x.

Method and why:
- D3Q19, TRT with the "magic" parameter Lambda = 3/16 (Ginzburg, Verhaeghe & d'Humieres 2008):
  with halfway bounce-back the wall then sits exactly on the voxel faces for Poiseuille flow
  whatever tau, so the wall rule matches the MAC solver's voxel surface and tau only sets the
  speed of convergence (a larger viscosity diffuses momentum faster). SRT would move the wall
  by O((tau - 1/2)^2) and bias kappa by several percent at 20 voxels per diameter.
- Halfway bounce-back (lbmpy NoSlip) on every solid node, incompressible equilibrium,
  Guo forcing; the force is small so that the Mach number is ~1e-3 (Stokes regime).
- Steady state: every `check` steps the change of the velocity field relative to its norm,
  ||u_t - u_{t-check}|| / ||u_t||, must fall below `tol`.
- Drag: the body force on the fluid is balanced by the drag of the sphere, so
  K = f n^3 / (6 pi nu a U) with U the mean velocity over the whole cell (Zick & Homsy 1982,
  Table 2 normalisation, as in examples/arrays.rs).

Usage: peer_lbm.py VOXELS_PER_DIAMETER FRACTION [FRACTION...]
Environment: LBM_TAU (default 1.0), LBM_TOL (1e-6), LBM_CHECK (100), LBM_TRACE=1 (print the
change and K at every check), OMP_NUM_THREADS.
"""

import math
import os
import resource
import sys
import time

import numpy as np

ZICK_HOMSY = {0.027: 2.008, 0.064: 2.810, 0.125: 4.292, 0.216: 7.442, 0.343: 15.4,
              0.45: 28.1, 0.5236: 42.1}


def body(n, fraction):
    """Solid mask of the volume-matched centred sphere: the same rule as `body` in
    examples/arrays.rs (the squared-distance cut whose count is nearest the target, first one
    on ties)."""
    c = n / 2.0
    p = np.arange(n) + 0.5 - c
    d2 = p[:, None, None] ** 2 + p[None, :, None] ** 2 + p[None, None, :] ** 2
    values, counts = np.unique(d2.ravel(), return_counts=True)
    ends = np.cumsum(counts)
    target = fraction * n ** 3
    best = int(np.argmin(np.abs(ends - target)))
    return d2 <= values[best]


def run(vpd, fraction, tau, tol, check):
    from lbmpy import LBMConfig, LBStencil, Method, ForceModel, Stencil
    from lbmpy.boundaries import NoSlip
    from lbmpy.lbstep import LatticeBoltzmannStep
    from lbmpy.relaxationrates import relaxation_rate_from_magic_number
    import pystencils as ps

    d_over_l = 2.0 * (3.0 * fraction / (4.0 * math.pi)) ** (1.0 / 3.0)
    n = int(round(vpd / d_over_l))
    solid = body(n, fraction)
    a = d_over_l / 2.0 * n
    nu = (tau - 0.5) / 3.0
    omega = 1.0 / tau
    omega_odd = float(relaxation_rate_from_magic_number(omega, 3.0 / 16.0))
    # Mean velocity U ~ kappa f / nu; kappa ~ n^3 / (6 pi a K) with K ~ 5-20: aim at U ~ 1e-4.
    kappa_guess = n ** 3 / (6.0 * math.pi * a * 5.0)
    force = 1e-4 * nu / kappa_guess

    t0 = time.time()
    c0 = os.times()
    config = LBMConfig(stencil=LBStencil(Stencil.D3Q19), method=Method.TRT,
                       relaxation_rates=[omega, omega_odd], compressible=False,
                       force=(force, 0.0, 0.0), force_model=ForceModel.GUO)
    step = LatticeBoltzmannStep(domain_size=(n, n, n), periodicity=(True, True, True),
                                lbm_config=config,
                                config=ps.CreateKernelConfig(cpu_openmp=True))

    def solid_at(x, y, z):
        # Cell midpoints, ghost layers included: the periodic image of the voxel.
        ix = np.floor(x).astype(int) % n
        iy = np.floor(y).astype(int) % n
        iz = np.floor(z).astype(int) % n
        return solid[ix, iy, iz]

    step.boundary_handling.set_boundary(NoSlip(), mask_callback=solid_at)
    step.run(1)
    setup_wall = time.time() - t0

    fluid = ~solid
    trace = os.environ.get("LBM_TRACE") == "1"
    t1 = time.time()
    c1 = os.times()
    u_old = None
    steps = 1
    history = []
    while True:
        step.run(check)
        steps += check
        u = np.array(step.data_handling.gather_array(step.velocity_data_name), copy=True)
        u[solid] = 0.0
        if u_old is not None:
            change = np.linalg.norm(u - u_old) / max(np.linalg.norm(u), 1e-300)
            history.append((steps, change))
            if trace:
                k_now = force * n ** 3 / (6.0 * math.pi * nu * a * (float(u[..., 0][fluid].sum()) / n ** 3))
                print(f"# step {steps} change {change:.3e} K {k_now:.6f}", file=sys.stderr, flush=True)
            if change < tol or steps > 2_000_000:
                break
        u_old = u
    wall = time.time() - t1
    c2 = os.times()
    cpu = (c2.user - c1.user) + (c2.system - c1.system)
    setup_cpu = (c1.user - c0.user) + (c1.system - c0.system)
    ux = u[..., 0]
    mean_u = float(ux[fluid].sum()) / n ** 3
    k = force * n ** 3 / (6.0 * math.pi * nu * a * mean_u)
    ref = ZICK_HOMSY.get(round(fraction, 4))
    err = 100.0 * (k / ref - 1.0) if ref else float("nan")
    mach = float(np.abs(u).max()) * math.sqrt(3.0)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    mlups = fluid.sum() * steps / wall / 1e6
    print(f"lbmpy,{fraction},{vpd},{n},{tau},{ref},{k:.4f},{err:.2f},{steps},{wall:.2f},"
          f"{cpu:.2f},{setup_wall:.2f},{setup_cpu:.2f},{rss:.0f},{mach:.2e},{mlups:.2f}",
          flush=True)


def main():
    args = sys.argv[1:]
    vpd = float(args[0]) if args else 20.0
    fractions = [float(s) for s in args[1:]] or [0.125, 0.343]
    tau = float(os.environ.get("LBM_TAU", "1.0"))
    tol = float(os.environ.get("LBM_TOL", "1e-6"))
    check = int(os.environ.get("LBM_CHECK", "100"))
    print("peer,fraction,voxels_per_diameter,n,tau,reference,computed,error_percent,steps,"
          "wall_s,cpu_s,setup_wall_s,setup_cpu_s,peak_rss_mib,max_mach,mlups", flush=True)
    for c in fractions:
        run(vpd, c, tau, tol, check)


if __name__ == "__main__":
    main()
