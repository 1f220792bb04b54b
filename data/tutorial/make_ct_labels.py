#!/usr/bin/env python3
"""Writes the segmented "CT scan" of docs/tutorials/ct-to-packing.md.

    python3 data/tutorial/make_ct_labels.py [OUT_DIR]     # default: data/tutorial

A 64 x 64 x 48 voxel label image (10 um voxels) of irregular grains, label 0 = pore and
k = 1..N one grain each, as a segmentation tool would hand it over: `ct_labels.tif` (one
uint8 page per z slice, page k = slice z = k) and the same bytes as `ct_labels_64x64x48_u8.raw`
(x fastest, then y, then z). `ct_labels.json` records the grain count and voxel counts, which
the tutorial checks against what grainpipe reads back.

Grains are ellipsoids with random axes and orientations whose radius is modulated by a few
random low-order harmonics (rounded sand-like shapes), placed one by one at random positions
without touching an earlier grain. Only numpy is needed; the seed fixes every byte.
"""

import json
import struct
import sys
from pathlib import Path

import numpy as np

NX, NY, NZ = 64, 64, 48
VOXEL_UM = 10.0
SEED = 2026


def random_rotation(rng):
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def grain_mask(rng, zz, yy, xx, centre, r_eq):
    axes = r_eq * np.array([1.25, 1.0, 0.8]) * rng.uniform(0.9, 1.1, 3)
    rot = random_rotation(rng)
    d = np.stack([xx - centre[0], yy - centre[1], zz - centre[2]], axis=-1) @ rot
    rho = np.sqrt(((d / axes) ** 2).sum(-1))
    # Radius modulation by low-order harmonics of the direction (bumps, not spikes).
    n = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
    bump = np.zeros(rho.shape)
    for _ in range(4):
        k = rng.normal(size=3)
        bump += 0.06 * np.cos(2.0 * (n @ (k / np.linalg.norm(k))) + rng.uniform(0, 2 * np.pi))
    return rho <= 1.0 + bump


def tiff_stack(pages: np.ndarray) -> bytes:
    """Baseline little-endian multi-page grayscale TIFF, uncompressed, one strip per page:
    the header, every page's pixels, then the chain of page directories."""
    nz, ny, nx = pages.shape
    data = pages.tobytes()
    ntags = 10
    ifd_size = 2 + 12 * ntags + 4
    first_ifd = 8 + len(data) + len(data) % 2
    out = bytearray(b"II*\x00" + struct.pack("<I", first_ifd) + data)
    out += b"\x00" * (len(data) % 2)
    for z in range(nz):
        tags = [
            (256, 3, nx), (257, 3, ny), (258, 3, 8), (259, 3, 1), (262, 3, 1),
            (273, 4, 8 + z * nx * ny), (277, 3, 1), (278, 3, ny), (279, 4, nx * ny), (339, 3, 1),
        ]
        assert len(tags) == ntags
        out += struct.pack("<H", ntags)
        for tag, typ, value in tags:
            packed = struct.pack("<HH", value, 0) if typ == 3 else struct.pack("<I", value)
            out += struct.pack("<HHI", tag, typ, 1) + packed
        out += struct.pack("<I", first_ifd + (z + 1) * ifd_size if z + 1 < nz else 0)
    return bytes(out)


def main():
    out_dir = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent
    rng = np.random.default_rng(SEED)
    zz, yy, xx = np.meshgrid(np.arange(NZ) + 0.5, np.arange(NY) + 0.5, np.arange(NX) + 0.5,
                             indexing="ij")
    labels = np.zeros((NZ, NY, NX), np.uint8)
    # A one-voxel shell around every grain keeps grains apart, as a watershed leaves them.
    grown = np.zeros_like(labels, bool)
    label = 0
    for _ in range(4000):
        if label == 60:
            break
        r_eq = rng.uniform(5.0, 8.0)
        centre = rng.uniform([0, 0, 0], [NX, NY, NZ])
        # Only the grain's bounding box is evaluated (largest reach: 1.25 * 1.1 * 1.24 r_eq).
        reach = 1.75 * r_eq
        lo = np.maximum(np.floor(centre - reach).astype(int), 0)
        hi = np.minimum(np.ceil(centre + reach).astype(int), [NX, NY, NZ])
        box = np.s_[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
        mask = np.zeros(labels.shape, bool)
        mask[box] = grain_mask(rng, zz[box], yy[box], xx[box], centre, r_eq)
        if mask.sum() < 100 or (mask & grown).any():
            continue
        label += 1
        labels[mask] = label
        shell = mask.copy()
        for axis in range(3):
            shell |= np.roll(mask, 1, axis) | np.roll(mask, -1, axis)
        grown |= shell
    counts = np.bincount(labels.ravel(), minlength=label + 1)
    touching_z = sorted((set(np.unique(labels[0])) | set(np.unique(labels[-1]))) - {0})
    (out_dir / "ct_labels.tif").write_bytes(tiff_stack(labels))
    (out_dir / "ct_labels_64x64x48_u8.raw").write_bytes(labels.tobytes())
    meta = {
        "dims_xyz": [NX, NY, NZ],
        "voxel_size_um": VOXEL_UM,
        "grains": int(label),
        "grains_touching_z_faces": len(touching_z),
        "voxels_per_label": [int(c) for c in counts],
        "seed": SEED,
    }
    (out_dir / "ct_labels.json").write_text(json.dumps(meta, indent=1) + "\n")
    print(f"{label} grains, {len(touching_z)} touch the z faces, "
          f"solid fraction {1 - counts[0] / labels.size:.3f}")


if __name__ == "__main__":
    main()
