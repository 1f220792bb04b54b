"""Compare analysis.local_thickness and analysis.two_point with porespy on one image.

Not part of `make test`: porespy lives in its own venv.

    python3 -m venv .venv-porespy && .venv-porespy/bin/pip install porespy
    cargo build --release -p grainpipe-cli
    .venv-porespy/bin/python validate/porespy_compare.py [--n 96] [--radius 5] [--seed 1]

The image is a Boolean model (overlapping balls, pore fraction about 0.5, seeded), written
as a raw u8 file (0 pore, 1 solid) and read by `import.raw` (a non-periodic grid). The
script prints the mean pore thickness and the thickness distributions of both (porespy's
local_thickness values are sphere radii: the diameters compared are twice them), and S2 at
short lags: grainpipe's along x, y, z (open axes, normalised by the pairs inside the image)
against porespy's two_point_correlation (radially averaged), and the closed form of the
Boolean model, exp(-rho V2(r)). Short runs only: n = 96 takes seconds.
"""

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np


def boolean(n, r, seed):
    """Pore mask of n^3 voxels: voxel centres in no ball of radius r (periodic placement)."""
    rng = np.random.default_rng(seed)
    count = int(math.log(2) * n**3 / (4 / 3 * math.pi * r**3))
    centres = rng.random((count, 3)) * n
    pore = np.ones((n, n, n), dtype=bool)  # indexed [z, y, x]
    k = int(math.ceil(r)) + 1
    offs = np.arange(-k, k + 1)
    for c in centres:
        b = np.floor(c).astype(int)
        xs, ys, zs = (b[a] + offs for a in range(3))
        dx = (xs + 0.5 - c[0]) ** 2
        dy = (ys + 0.5 - c[1]) ** 2
        dz = (zs + 0.5 - c[2]) ** 2
        inside = dz[:, None, None] + dy[None, :, None] + dx[None, None, :] <= r * r
        zz, yy, xx = np.nonzero(inside)
        pore[zs[zz] % n, ys[yy] % n, xs[xx] % n] = False
    return pore, count


def union_volume(r, s):
    v = 4 / 3 * math.pi * r**3
    lens = math.pi / 12 * (4 * r + s) * (2 * r - s) ** 2 if s < 2 * r else 0.0
    return 2 * v - lens


def read_csv(path):
    """Rows of a grainpipe CSV as dicts keyed by column name (headers are `name [unit]`)."""
    with open(path) as f:
        rows = list(csv.reader(row for row in f if not row.startswith("#")))
    names = [h.split(" [")[0] for h in rows[0]]
    return [dict(zip(names, r)) for r in rows[1:]]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=96)
    ap.add_argument("--radius", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--pipe", default=os.environ.get("PIPE", "target/release/pipe"))
    a = ap.parse_args()
    import porespy as ps

    h = 1e-6
    pore, count = boolean(a.n, a.radius, a.seed)
    phi = pore.mean()
    rho = count / a.n**3
    print(f"{a.n}^3 voxels, {count} balls of {a.radius} voxels, pore fraction {phi:.4f}")
    with tempfile.TemporaryDirectory() as d:
        raw = os.path.join(d, "image.raw")
        (~pore).astype(np.uint8).tofile(raw)  # x fastest: C order of [z, y, x]
        yaml = f"""name: porespy-compare
stages:
  - id: img
    use: import.raw
    with: {{ path: {raw}, dims: [{a.n}, {a.n}, {a.n}], spacing: 1 um }}
  - id: lt
    use: analysis.local_thickness
    in: {{ image: img.image }}
    with: {{ bins: 20 }}
  - id: s2
    use: analysis.two_point
    in: {{ image: img.image }}
    with: {{ max_lag: {4 * a.radius} um, radial: true }}
export:
  - {{ from: lt.distribution, to: {d}/lt.csv }}
  - {{ from: lt.summary, to: {d}/lt_summary.csv }}
  - {{ from: s2.s2, to: {d}/s2.csv }}
"""
        path = os.path.join(d, "compare.yaml")
        with open(path, "w") as f:
            f.write(yaml)
        pipe = os.path.abspath(a.pipe)
        subprocess.run([pipe, "run", "--no-cache", "--quiet", path], check=True, cwd=d)
        # Stage wall times from the run record (the export directory's run.json).
        with open(os.path.join(d, "run.json")) as f:
            steps = {st["step"]: st["wall_s"] for st in json.load(f)["steps"]}
        ours_mean = float(read_csv(f"{d}/lt_summary.csv")[0]["mean_thickness"]) / h
        dist = read_csv(f"{d}/lt.csv")
        s2 = read_csv(f"{d}/s2.csv")

    t0 = time.perf_counter()
    lt = ps.filters.local_thickness(pore, sizes=100)
    t_lt = time.perf_counter() - t0
    theirs = 2 * lt[pore]
    print(f"mean pore thickness: grainpipe {ours_mean:.3f} voxels, porespy (2 x radius) {theirs.mean():.3f}")
    edges = [float(r["diameter_lower"]) / h for r in dist] + [float(dist[-1]["diameter_upper"]) / h]
    hist, _ = np.histogram(theirs, bins=edges)
    print("diameter bin (voxels)   grainpipe   porespy")
    for r, c in zip(dist, hist):
        lo, hi = float(r["diameter_lower"]) / h, float(r["diameter_upper"]) / h
        print(f"{lo:6.2f} - {hi:6.2f}       {float(r['volume_fraction']):.4f}     {c / pore.sum():.4f}")

    t0 = time.perf_counter()
    tp = ps.metrics.two_point_correlation(pore)
    t_s2 = time.perf_counter() - t0
    dist_r = np.asarray(tp.distance)
    prob = np.asarray(tp.probability_scaled if hasattr(tp, "probability_scaled") else tp.probability)
    print("lag (voxels)  S2 x      S2 y      S2 z      porespy radial   closed form exp(-rho V2)")
    by_axis = {ax: {} for ax in "xyz"}
    for r in s2:
        by_axis[r["axis"]][int(r["lag_voxels"])] = float(r["s2"])
    for k in range(0, int(4 * a.radius) + 1, 2):
        radial = np.interp(k, dist_r, prob)
        closed = math.exp(-rho * union_volume(a.radius, k))
        xs = "  ".join(f"{by_axis[ax].get(k, float('nan')):.4f}" for ax in "xyz")
        print(f"{k:6d}        {xs}    {radial:.4f}           {closed:.4f}")
    print("wall time [s]       grainpipe   porespy   ratio (porespy / grainpipe)")
    # Our S2 step also computes the radial average (one 3-D FFT), as porespy does.
    for name, ours, theirs_t in (("local thickness", steps["lt"], t_lt), ("two-point S2", steps["s2"], t_s2)):
        print(f"{name:18s}  {ours:9.3f}   {theirs_t:7.3f}   {theirs_t / ours:.1f}")


if __name__ == "__main__":
    sys.exit(main())
