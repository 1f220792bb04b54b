# %% [markdown]
# # grainpipe quickstart (notebook-style script)
#
# Builds a sphere packing, voxelises it, then plots a slice of the voxel image and the
# particle size distribution with matplotlib. Run it as a script
# (`python examples/python/quickstart.py [OUTDIR]`, PNGs written to OUTDIR, default
# `out/python`) or cell by cell in Jupyter (the `# %%` markers).

# %%
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files, not windows: the script also runs in tests and on servers
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import grainpipe as gp  # noqa: E402

out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("out/python")
out.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# A pipeline built in Python: the same structure as a YAML file. Lengths carry units.

# %%
pipeline = {
    "name": "quickstart",
    "seed": 1,
    "stages": [
        {
            "id": "pack",
            "use": "packing.rsa",
            "with": {
                "size": ["300 um", "300 um", "300 um"],
                "radius": {"kind": "uniform", "min": "15 um", "max": "30 um"},
                "volume_fraction": 0.3,
            },
        },
        {
            "id": "voxels",
            "use": "voxelize.packing",
            "in": {"packing": "pack.packing"},
            "with": {"voxels_per_diameter": 12},
        },
    ],
}
plan = gp.validate(pipeline, exports=False)
print(f"estimated memory: {plan['memory_bytes'] / 2**20:.1f} MiB")
r = gp.run(pipeline, cache=False, progress=False)

# %% [markdown]
# The packing: numpy arrays, SI units (metres).

# %%
packing = r["pack.packing"]
print(f"{len(packing)} spheres, solid fraction {packing.volume_fraction():.3f}")

# %% [markdown]
# The voxel image: `array` has the shape (z, y, x), so `array[k]` is the slice at height k.

# %%
img = r["voxels.image"]
nz = img.array.shape[0]
k = nz // 2
nx, ny, _ = img.dims
extent_um = [
    img.origin[0] * 1e6,
    (img.origin[0] + nx * img.spacing[0]) * 1e6,
    img.origin[1] * 1e6,
    (img.origin[1] + ny * img.spacing[1]) * 1e6,
]
fig, ax = plt.subplots(figsize=(5, 5))
ax.imshow(img.array[k], origin="lower", extent=extent_um, cmap="gray_r", interpolation="nearest")
z_um = (img.origin[2] + (k + 0.5) * img.spacing[2]) * 1e6
ax.set(xlabel="x [um]", ylabel="y [um]", title=f"slice z = {z_um:.0f} um, porosity {img.fraction(0):.3f}")
fig.savefig(out / "slice.png", dpi=100)

# %% [markdown]
# The size distribution of the spheres.

# %%
fig, ax = plt.subplots(figsize=(5, 4))
ax.hist(2e6 * packing.radii, bins=20, color="tab:blue", edgecolor="white")
ax.set(xlabel="diameter [um]", ylabel="count", title="particle sizes")
fig.savefig(out / "sizes.png", dpi=100)
print(f"mean diameter {2e6 * np.mean(packing.radii):.1f} um; figures in {out}")
