"""Table 2 layout from the runs of resolution.sh: apparent E_x ... G_xy [GPa], the relative
error of the best orthotropic approximation [%], the largest relative difference of the six
moduli to the finest resolution of the same cell [%], and wall / CPU / RSS of the run.

    python resolution_table.py            (reads plugins/fft/bench/resolution.csv)
"""
import csv
import os

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))
KEYS = ["E_x [Pa]", "E_y [Pa]", "E_z [Pa]", "G_yz [Pa]", "G_zx [Pa]", "G_xy [Pa]"]


def constants(path):
    with open(os.path.join(ROOT, path)) as f:
        rows = {r["approximation"]: r for r in csv.DictReader(f)}
    moduli = [float(rows["apparent"][k]) / 1e9 for k in KEYS]
    return moduli, 100.0 * float(rows["orthotropic"]["relative_error [1]"])


def main():
    with open(os.path.join(HERE, "resolution.csv")) as f:
        runs = list(csv.DictReader(f))
    data = []
    for r in runs:
        path = r["constants_file"]
        if not os.path.exists(os.path.join(ROOT, path)):
            continue
        m, orth = constants(path)
        data.append((r, m, orth))
    finest = {}
    for r, m, _ in data:
        v = float(r["voxel_um"])
        if r["layer_size"] not in finest or v < finest[r["layer_size"]][0]:
            finest[r["layer_size"]] = (v, m)
    print("| cell | voxel | E_x | E_y | E_z | G_yz | G_zx | G_xy | orthotropy error | max diff. to finest | wall / CPU / peak RSS | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r, m, orth in data:
        fm = finest[r["layer_size"]][1]
        diff = max(abs(a / b - 1.0) for a, b in zip(m, fm)) * 100.0
        print(f"| 2 x 280 um on ({r['layer_size']})^2 | {r['voxel_um']} um | "
              + " | ".join(f"{x:.2f}" for x in m)
              + f" | {orth:.1f} % | {diff:.1f} % | {float(r['wall_s']):.0f} s / {float(r['cpu_s']):.0f} s / "
              f"{float(r['peak_rss_mb']):.0f} MB | {r['load_before']} |")


if __name__ == "__main__":
    main()
