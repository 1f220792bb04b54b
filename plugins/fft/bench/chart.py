"""Error against time of the four discretizations (and muSpectre) on the simple-cubic
spherical pore, from errtime.csv (sweep.sh) and peer.csv (peer.sh).

    python chart.py [--out docs/stages/elasticity_error_vs_time.png]

Reference (the continuum cell of porosity exactly 0.2): the voxel porosity of the image
oscillates around 0.2 (+0.0046 at 32^3, +0.0005 at 64^3, -0.0001 at 128^3), so every result
is first moved to porosity 0.2 with the Mori-Tanaka sensitivity d ln C / d phi (a <= 1.3 %
shift at 32^3, <= 0.15 % from 64^3 on); the corrected staggered and hex8 values on the two
finest grids n, 2n of each scheme are then Richardson-extrapolated to first order (the order
of the staircase error of a voxelized interface; the observed order from three grids is
printed as a check, it is erratic because the staircase error is not smooth in n); the
reference is the mean of the two schemes' extrapolations and their difference is its stated
uncertainty. Errors are of the raw (uncorrected) values: the porosity error of the
image is part of the error of a run at that resolution, for us and for the peer alike.

The x axis is CPU time (user + system, /usr/bin/time -v) of the process that solved both
load cases: the 2 cores were shared with other jobs (load average 9-14), which inflated the
wall clock 2-5x; wall times are printed beside.
"""
import argparse
import csv
import math
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def rows(name):
    path = os.path.join(HERE, name)
    if not os.path.exists(path):
        return []
    with open(path) as f:
        return list(csv.DictReader(f))


def value(r):
    return float(r["c11"] if r["case"] == "xx" else r["c44"])


def mt_dlnc_dphi(case, e=1.0, nu=0.3, phi=0.2):
    """d ln C / d phi of the Mori-Tanaka estimate for spherical pores (C11 or C44)."""
    k, g = e / (3 * (1 - 2 * nu)), e / (2 * (1 + nu))

    def c(f):
        kk = k * (1 - f) / (1 + f * 3 * k / (4 * g))
        z = g * (9 * k + 8 * g) / (6 * (k + 2 * g))
        gg = g * (1 - f) / (1 + f * g / z)
        return kk + 4 * gg / 3 if case == "xx" else gg

    h = 1e-6
    return (math.log(c(phi + h)) - math.log(c(phi - h))) / (2 * h)


def corrected(r):
    """The value of row r moved to porosity 0.2 (first order, Mori-Tanaka sensitivity)."""
    return value(r) * (1.0 - mt_dlnc_dphi(r["case"]) * (float(r["porosity"]) - 0.2))


def richardson(pts):
    """pts: [(n, value)] on n, 2n (and 4n) -> (first-order extrapolation from the two finest,
    observed order from three grids or nan)."""
    pts = sorted(pts)
    (n2, b), (n3, c) = pts[-2:]
    assert n3 == 2 * n2, pts
    p = float("nan")
    if len(pts) >= 3:
        a = pts[-3][1]
        d1, d2 = a - b, b - c
        if d2 != 0 and d1 * d2 > 0:
            p = math.log2(d1 / d2)
    return 2.0 * c - b, p


def reference(data):
    ref = {}
    for case in ("xx", "yz"):
        ests = []
        for d in ("staggered", "hex8"):
            pts = {
                int(r["n"]): corrected(r)
                for r in data
                if r["solver"] == "ours" and r["discretization"] == d and r["case"] == case
                and r["status"] == "ok"
            }
            levels = sorted(pts)[-3:]
            if len(levels) >= 2:
                v, p = richardson([(k, pts[k]) for k in levels])
                ests.append(v)
                print(f"reference {case} from {d} {levels}: {v:.6f} (observed order {p:.2f}); "
                      f"corrected values " + ", ".join(f"{pts[k]:.6f}" for k in levels))
        if ests:
            ref[case] = (sum(ests) / len(ests), max(ests) - min(ests))
            print(f"reference {case}: {ref[case][0]:.6f} +- {ref[case][1]:.1e} (spread of the two)")
    return ref


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="docs/stages/elasticity_error_vs_time.png")
    a = ap.parse_args()
    # Ours from the sweep, the peer from peer.csv (whose "ours" rows repeat the sweep's sizes).
    data = rows("errtime.csv") + [r for r in rows("peer.csv") if r["solver"] != "ours"]
    for r in rows("peer.csv"):
        r["source"] = "peer.csv"
    ref = reference(data)
    # Error and time per (solver, discretization, n): the two load cases of one process.
    groups = {}
    for r in data:
        key = (r["solver"], r["discretization"], int(r["n"]))
        groups.setdefault(key, []).append(r)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), sharey=False)
    style = {
        "staggered": ("C0", "o"),
        "hex8": ("C1", "s"),
        "rotated": ("C2", "^"),
        "spectral": ("C3", "x"),
        "muspectre-fe6tet": ("k", "D"),
    }
    print("solver,discretization,n,case,value,rel_error,cpu_s_process,wall_s_process")
    failed = {}
    for ax, case, label in ((axes[0], "xx", "C11"), (axes[1], "yz", "C44")):
        if case not in ref:
            continue
        lines = {}
        for (solver, disc, n), rs in sorted(groups.items()):
            for r in rs:
                if r["case"] != case or n > 128:
                    continue
                t = float(r["cpu_s"])
                if r["status"] != "ok":
                    print(f"{solver},{disc},{n},{case},failed,,{t},{r['wall_s']}")
                    failed.setdefault(disc, set()).add(n)
                    continue
                err = abs(value(r) / ref[case][0] - 1.0)
                print(f"{solver},{disc},{n},{case},{value(r):.6f},{err:.3e},{t},{r['wall_s']}")
                name = disc if solver == "ours" else "muSpectre 0.27 (linear FE, 6 tets)"
                lines.setdefault((disc, name), []).append((t, err, n))
        for (disc, name), pts in lines.items():
            pts.sort(key=lambda p: p[2])
            c, m = style.get(disc, ("gray", "."))
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], color=c, marker=m, label=name)
            for t, e, n in pts:
                ax.annotate(f"{n}", (t, e), textcoords="offset points", xytext=(4, 4), fontsize=7)
        ax.set_xlabel("CPU time of the run, xx + yz [s] (2 cores)")
        ax.set_ylabel(f"relative error of {label}")
        ax.set_title(f"SC spherical pore, porosity 0.2: {label} (load {case})")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    for disc, ns in failed.items():
        sizes = ", ".join(f"{n}$^3$" for n in sorted(ns))
        axes[1].text(0.02, 0.02, f"{disc} (Moulinec-Suquet): no converged result at {sizes}\n"
                     "(stagnation / 1000 iterations on the pore); not run at 128$^3$",
                     transform=axes[1].transAxes, fontsize=7, color="C3")
    fig.suptitle(
        "Error vs CPU time, tolerance 1e-5; reference: Richardson extrapolation of staggered and "
        "hex8 (porosity-corrected) on the two finest grids", fontsize=9)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
