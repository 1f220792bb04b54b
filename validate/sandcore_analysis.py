#!/usr/bin/env python3
"""Tables of the sand-core validation (docs/VALIDATION.md) from `pipe sweep` directories.

Usage: sandcore_analysis.py SWEEP_DIR [SWEEP_DIR ...] > table.md

Reads every run's result.json (so it also works on a sweep that is still running) and the
manifest sweep.json, groups the runs by parameter point and prints, as Markdown:
  - per point: the orthotropic moduli E_x, E_y, E_z, the anisotropy
    dE = E_z / mean(E_x, E_y) - 1 (elasticity.fft `anisotropy_z`), the permeabilities and
    dk = kappa_zz / mean(kappa_xx, kappa_yy) - 1 (stokes.permeability `anisotropy_z`), the
    packing's microstructure statistics; means with Student-t 90 % confidence intervals, the
    realizations that would make the interval of dE and dk 4 points wide, and the t-test of
    the mean against 0 and against the paper's smallest claim;
  - paired points (same realization = same seed at every point of a sweep): the per-
    realization difference or ratio between a point and the first point of the sweep;
  - per point: least-squares regressions of dE and dk on the fabric measures, per
    realization (slope, Pearson r, p-value).
Needs numpy and scipy (validate/requirements.txt).
"""

import json
import math
import pathlib
import sys

import numpy as np
from scipy import stats

# The paper's numbers (Donval et al. 2025): Table 7 means give E_z 9 % below the in-plane
# mean (section 4.2: E_x / E_z = 1.16-1.17, i.e. 12-17 %); section 4.4: kappa_zz 8.7-11.5 %
# below the in-plane permeabilities; spheres +53 % in-plane, +68 % along z.
PAPER_DE = -0.09
PAPER_DK = -0.087


def short(override):
    """`key=[a,b,...,z]` with a long list as `key=[a ... z] (n)` (labels of grain subsets)."""
    key, _, value = override.partition("=")
    if value.startswith("[") and len(value) > 60:
        items = value.strip("[]").split(",")
        return f"{key}=[{items[0]} ... {items[-1]}] ({len(items)})"
    return override


def load(sweep_dir):
    """Runs of a sweep as dicts: point label, realization, status and collected values."""
    root = pathlib.Path(sweep_dir)
    manifest = json.loads((root / "sweep.json").read_text())
    runs = []
    for run in manifest["runs"]:
        result_path = root / "runs" / run["id"] / "result.json"
        if not result_path.exists():
            continue
        result = json.loads(result_path.read_text())
        values = {
            v["name"]: (math.nan if v["value"] is None else float(v["value"]))
            for v in result.get("values", [])
        }
        label = ", ".join(short(o) for o in run["overrides"]) or "base"
        runs.append(
            {
                "sweep": root.name,
                "point": f"{root.name}: {label}",
                "realization": run["realization"],
                "status": result["status"],
                "error": result.get("error", ""),
                "wall": result.get("wall_time", math.nan),
                "values": values,
            }
        )
    return manifest, runs


def derived(v):
    """The quantities of one run (NaN where the run did not collect them)."""
    g = lambda k: v.get(k, math.nan)  # noqa: E731
    layers = [k for k in v if k.startswith("pack.report.near_contacts_per_grain[")]
    near = np.nanmean([v[k] for k in layers]) if layers else math.nan
    interface = [
        v[k]
        for k in v
        if k.startswith("pack.report.interface_anisotropy_z[") and not math.isnan(v[k])
    ]
    tries = [v[k] for k in v if k.startswith("pack.report.tries[")]
    released = [v[k] for k in v if k.startswith("pack.report.released[")]
    orient = [v[k] for k in v if k.startswith("pack.report.orientation_zz[")]
    kx, ky, kz = (g(f"flow.report.kappa[{i}]") for i in range(3))
    return {
        "E_x [GPa]": g("stiffness.constants.E_x[1]") / 1e9,
        "E_y [GPa]": g("stiffness.constants.E_y[1]") / 1e9,
        "E_z [GPa]": g("stiffness.constants.E_z[1]") / 1e9,
        "dE [%]": 100 * g("stiffness.constants.anisotropy_z[1]"),
        "kappa_xx [1e-11 m^2]": kx * 1e11,
        "kappa_yy [1e-11 m^2]": ky * 1e11,
        "kappa_zz [1e-11 m^2]": kz * 1e11,
        "dk [%]": 100 * g("flow.report.anisotropy_z[0]"),
        "near-contacts per grain": near,
        "contact fabric N_zz": g("pack.contact_fabric[8]"),
        "interface fabric 3 N_zz - 1": np.mean(interface) if interface else math.nan,
        "long axes <n_z n_z>": np.mean(orient) if orient else math.nan,
        "layers placed afresh": sum(t > 1 for t in tries) if tries else math.nan,
        "layers with released grains": sum(r > 0 for r in released) if released else math.nan,
    }


def ci90(x):
    """Mean, half-width of the Student-t 90 % interval, standard deviation, n."""
    x = np.asarray([a for a in x if not math.isnan(a)])
    n = len(x)
    if n == 0:
        return math.nan, math.nan, math.nan, 0
    if n == 1:
        return x[0], math.nan, math.nan, 1
    sd = x.std(ddof=1)
    return x.mean(), stats.t.ppf(0.95, n - 1) * sd / math.sqrt(n), sd, n


def needed(sd, width=4.0):
    """Realizations for a 90 % interval `width` points wide (Student t, by iteration)."""
    if not (sd > 0):
        return math.nan
    n = 2
    while n < 100000 and 2 * stats.t.ppf(0.95, n - 1) * sd / math.sqrt(n) > width:
        n += 1
    return n


def fmt(m, h, digits=2):
    if math.isnan(m):
        return "-"
    if math.isnan(h):
        return f"{m:.{digits}f}"
    return f"{m:.{digits}f} +- {h:.{digits}f}"


def main(dirs):
    points = {}
    order = []
    walls = []
    for d in dirs:
        _, runs = load(d)
        for r in runs:
            if r["point"] not in points:
                points[r["point"]] = []
                order.append(r["point"])
            points[r["point"]].append(r)
            walls.append(r["wall"])
    print(f"Runs with a result: {sum(len(p) for p in points.values())}; "
          f"wall time per run {np.nanmin(walls):.0f}-{np.nanmax(walls):.0f} s "
          f"(mean {np.nanmean(walls):.0f} s).\n")
    rows = {}
    for p in order:
        ok = [r for r in points[p] if r["status"] == "ok"]
        rows[p] = {r["realization"]: derived(r["values"]) for r in ok}
        failed = [r for r in points[p] if r["status"] != "ok"]
        if failed:
            print(f"- {p}: {len(failed)} failed run(s): "
                  + "; ".join(sorted({r['error'][:160] for r in failed})))
    print()
    quantities = list(next(iter(next(iter(rows.values())).values())).keys())
    print("| quantity | " + " | ".join(order) + " |")
    print("|---" * (len(order) + 1) + "|")
    for q in quantities:
        cells = []
        for p in order:
            m, h, _, n = ci90([d[q] for d in rows[p].values()])
            digits = 0 if q.startswith("layers") else 2
            if q.startswith("layers"):
                cells.append("-" if n == 0 else f"{int(np.nansum([d[q] for d in rows[p].values()]))} of {2 * n}")
            else:
                cells.append(fmt(m, h, digits) + ("" if n == 0 else f" (n={n})"))
        print(f"| {q} | " + " | ".join(cells) + " |")
    print()
    print("Mean +- half-width of the Student-t 90 % confidence interval over realizations.\n")
    for q, paper in (("dE [%]", PAPER_DE), ("dk [%]", PAPER_DK)):
        for p in order:
            x = [d[q] for d in rows[p].values() if not math.isnan(d[q])]
            if len(x) < 2:
                continue
            m, h, sd, n = ci90(x)
            t0 = stats.ttest_1samp(x, 0.0)
            tp = stats.ttest_1samp(x, 100 * paper)
            print(f"- {q} at {p}: mean {m:.2f}, 90 % CI [{m - h:.2f}, {m + h:.2f}], sd {sd:.2f}, "
                  f"n = {n}; against 0: p = {t0.pvalue:.3g}; against the paper's "
                  f"{100 * paper:.1f} %: p = {tp.pvalue:.3g}; a 4-point-wide interval needs "
                  f"n = {needed(sd)}")
    print()
    # Pairs: every point against the first of its sweep, realization by realization.
    first = {}
    for p in order:
        sweep = p.split(":")[0]
        first.setdefault(sweep, p)
    for p in order:
        base = first[p.split(":")[0]]
        if p == base:
            continue
        common = sorted(set(rows[p]) & set(rows[base]))
        if len(common) < 2:
            continue
        print(f"Paired by realization, {p} against {base} (n = {len(common)}):\n")
        for q in ("kappa_xx [1e-11 m^2]", "kappa_yy [1e-11 m^2]", "kappa_zz [1e-11 m^2]",
                  "E_x [GPa]", "E_z [GPa]"):
            ratio = [100 * (rows[p][r][q] / rows[base][r][q] - 1) for r in common]
            m, h, _, n = ci90(ratio)
            print(f"- {q}: {fmt(m, h)} % (ratio - 1)")
        kin = [100 * ((rows[p][r]["kappa_xx [1e-11 m^2]"] + rows[p][r]["kappa_yy [1e-11 m^2]"])
                      / (rows[base][r]["kappa_xx [1e-11 m^2]"] + rows[base][r]["kappa_yy [1e-11 m^2]"]) - 1)
               for r in common]
        m, h, _, _ = ci90(kin)
        print(f"- in-plane kappa (mean of xx, yy): {fmt(m, h)} % (ratio - 1)")
        for q in ("dE [%]", "dk [%]"):
            diff = [rows[p][r][q] - rows[base][r][q] for r in common]
            m, h, _, _ = ci90(diff)
            print(f"- {q}: difference {fmt(m, h)} points")
        print()
    # Regressions of the anisotropies on the fabric, per realization.
    fabric = ("near-contacts per grain", "contact fabric N_zz", "interface fabric 3 N_zz - 1",
              "long axes <n_z n_z>")
    print("Per-realization regressions (least squares): slope, Pearson r, p-value.\n")
    print("| point | response | " + " | ".join(fabric) + " |")
    print("|---|---|" + "---|" * len(fabric))
    for p in order:
        for q in ("dE [%]", "dk [%]"):
            cells = []
            for f in fabric:
                pairs = [(d[f], d[q]) for d in rows[p].values()
                         if not (math.isnan(d[f]) or math.isnan(d[q]))]
                if len(pairs) < 5 or np.std([a for a, _ in pairs]) == 0:
                    cells.append("-")
                    continue
                fit = stats.linregress([a for a, _ in pairs], [b for _, b in pairs])
                cells.append(f"{fit.slope:.3g}, r = {fit.rvalue:.2f}, p = {fit.pvalue:.2g}")
            print(f"| {p} | {q} | " + " | ".join(cells) + " |")
    print()


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
