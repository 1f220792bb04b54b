"""Error against CPU time of composite voxels and labels (hex8) from composite_errtime.csv
(`cargo run --release -p grainpipe-fft --example composite_errtime`): the Hashin coated
sphere's bulk modulus and the Rayleigh array's conductivity, each against its exact value.

    python composite_chart.py [--out docs/stages/composite_error_vs_time.png]
"""
import argparse
import csv
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

here = os.path.dirname(os.path.abspath(__file__))
ap = argparse.ArgumentParser()
ap.add_argument("--csv", default=os.path.join(here, "composite_errtime.csv"))
ap.add_argument("--out", default=os.path.join(here, "../../../docs/stages/composite_error_vs_time.png"))
args = ap.parse_args()

rows = list(csv.DictReader(open(args.csv)))
titles = {
    "coated_sphere_bulk": "Hashin coated sphere, bulk modulus",
    "rayleigh_conductivity": "Rayleigh SC spheres (k = 10), conductivity",
}
fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
for ax, case in zip(axes, titles):
    for mode, style in [("labels", "o-"), ("composite", "s-")]:
        pts = [r for r in rows if r["case"] == case and r["interfaces"] == mode]
        # CPU time below the 10 ms tick resolution is shown at 10 ms.
        t = [max(float(r["cpu_s"]), 0.01) for r in pts]
        e = [100 * float(r["error"]) for r in pts]
        ax.loglog(t, e, style, label=mode)
        for r, x, y in zip(pts, t, e):
            ax.annotate(f"{r['n']}$^3$", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_title(titles[case], fontsize=10)
    ax.set_xlabel("CPU time of the solve [s] (2 cores, shared)")
    ax.set_ylabel("error against the exact value [%]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
fig.suptitle("hex8: composite voxels vs labels (grainpipe-fft)", fontsize=11)
fig.tight_layout()
fig.savefig(args.out, dpi=110)
print("wrote", os.path.abspath(args.out))
