"""Charts of the binder benchmark (out/bench/binder.csv, written by
`cargo run --release -p grainpipe-binder --example binder_bench`) as docs/stages/binder_grid.png.

Run: plugins/binder/bench/chart.sh (makes its own venv with matplotlib; not part of make test).
"""
import csv
import sys
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

src = sys.argv[1] if len(sys.argv) > 1 else "out/bench/binder.csv"
dst = sys.argv[2] if len(sys.argv) > 2 else "docs/stages/binder_grid.png"
rows = list(csv.DictReader(open(src)))
label = {
    ("levelset", "fixed"): "level set, over spheres",
    ("levelset", "fixed_grains"): "level set, over grains",
    ("closing", "fixed"): "closing (baseline)",
    ("levelset", "fitted"): "level set, over spheres",
    ("levelset", "fitted_grains"): "level set, over grains",
    ("closing", "fitted"): "closing (baseline)",
}
fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
series = defaultdict(list)
for r in rows:
    if r["mode"].startswith("fixed") and float(r["binder_fraction_deviation"]) != 0.0:
        series[(r["stage"], r["mode"])].append(
            (float(r["wall_s"]), abs(float(r["binder_fraction_deviation"])) * 100, r["voxel_um"])
        )
for key, pts in series.items():
    pts.sort()
    ax1.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=label[key])
    for t, e, h in pts:
        ax1.annotate(f"{h} um", (t, e), textcoords="offset points", xytext=(4, 4), fontsize=8)
ax1.set_xscale("log")
ax1.set_xlabel("wall time of one run [s] (2 cores)")
ax1.set_ylabel("binder fraction error vs finest grid [%]")
ax1.set_title("Same a / closing radius at every voxel size")
ax1.legend(fontsize=8)
fits = defaultdict(list)
for r in rows:
    if r["mode"].startswith("fitted"):
        fits[(r["stage"], r["mode"])].append((float(r["voxel_um"]), float(r["parameter_m"]) * 1e6))
for key, pts in fits.items():
    pts.sort()
    ax2.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=label[key])
ax2.set_xscale("log", base=2)
ax2.set_xlabel("voxel size [um]")
ax2.set_ylabel("fitted a or closing radius [um] for 2 % binder")
ax2.set_title("Fitted parameter against resolution")
ax2.legend(fontsize=8)
fig.tight_layout()
fig.savefig(dst, dpi=110)
print("wrote", dst)
