#!/usr/bin/env python3
"""Writes the grey-value "CT scan" of docs/tutorials/ct-to-properties.md.

    pipe run pipelines/tutorial-ct-truth.yaml        # the true three-phase image, 140^3 at 4 um
    python3 data/tutorial/make_ct_grey.py [TRUTH_RAW] [OUT_DIR]
        # defaults: out/tutorial-ct-truth/truth.raw, data/tutorial

What a scanner does to the true image, crudely: each phase gets its grey value (X-ray
attenuation: pore < binder < quartz sand), the image is blurred by the point-spread function
(a Gaussian of sigma 0.7 voxel, 2.8 um) and gets Gaussian noise (sd 1500 grey values, a
signal-to-noise ratio of about 9 between neighbouring phases), and a window of 72^3 voxels (288 um, two grain diameters)
is cut out of the interior, so the scan is not periodic and grains and binder bridges are cut
by its faces. Written, x fastest then y then z:
- `ct_grey_72x72x72_u16.raw`: the scan, uint16 little-endian;
- `ct_grey_truth_72x72x72_u8.raw`: the window's true labels (0 pore, 1 grain, 2 binder);
- `ct_grey.json`: the window, the grey values and the true phase fractions.
Only numpy is needed; the seed fixes every byte.
"""

import json
import sys
from pathlib import Path

import numpy as np

FULL = 140  # the truth image, voxels per axis
WINDOW = 72
START = 34  # the window's first voxel on every axis
GREY = {0: 8000.0, 1: 36000.0, 2: 22000.0}  # pore, grain, binder
SIGMA = 0.7  # voxels
NOISE = 1500.0
SEED = 33


def gaussian_blur(v, sigma):
    """Separable Gaussian, kernel cut at 4 sigma and normalised; the truth is periodic, so
    its axes wrap."""
    r = int(np.ceil(4 * sigma))
    x = np.arange(-r, r + 1)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    k /= k.sum()
    for axis in range(3):
        v = sum(w * np.roll(v, s, axis=axis) for s, w in zip(x, k))
    return v


def main():
    truth_path = Path(sys.argv[1] if len(sys.argv) > 1 else "out/tutorial-ct-truth/truth.raw")
    out = Path(sys.argv[2] if len(sys.argv) > 2 else "data/tutorial")
    # x fastest: numpy shape (z, y, x)
    labels = np.fromfile(truth_path, dtype=np.uint8).reshape(FULL, FULL, FULL)
    grey = np.zeros(labels.shape)
    for label, g in GREY.items():
        grey[labels == label] = g
    grey = gaussian_blur(grey, SIGMA)
    grey += np.random.default_rng(SEED).normal(0.0, NOISE, grey.shape)
    w = slice(START, START + WINDOW)
    scan = np.clip(np.rint(grey[w, w, w]), 0, 65535).astype("<u2")
    window = labels[w, w, w]
    out.mkdir(parents=True, exist_ok=True)
    scan.tofile(out / f"ct_grey_{WINDOW}x{WINDOW}x{WINDOW}_u16.raw")
    window.tofile(out / f"ct_grey_truth_{WINDOW}x{WINDOW}x{WINDOW}_u8.raw")
    names = {0: "pore", 1: "grain", 2: "binder"}
    info = {
        "window_start_voxels": [START] * 3,
        "window_voxels": [WINDOW] * 3,
        "voxel_size_um": 4.0,
        "grey": {names[k]: v for k, v in GREY.items()},
        "blur_sigma_voxels": SIGMA,
        "noise_sd": NOISE,
        "seed": SEED,
        "fractions": {names[k]: float((window == k).mean()) for k in names},
    }
    (out / "ct_grey.json").write_text(json.dumps(info, indent=2) + "\n")
    print(json.dumps(info["fractions"]))


if __name__ == "__main__":
    main()
