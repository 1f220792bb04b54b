"""Interop test: the TIFF stacks, raw + MetaImage volumes and DEM text files written by
`pipe run` open in tifffile and numpy with the same voxels and geometry.

Run: PIPE=$PWD/target/release/pipe .venv/bin/python -m pytest -q tests/interop/test_formats_out.py
"""

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import tifffile

ROOT = Path(__file__).resolve().parents[2]
PIPE = os.environ.get("PIPE", str(ROOT / "target" / "release" / "pipe"))

# (nz, ny, nx) labels with every axis distinct, imported from raw and exported again.
NX, NY, NZ = 7, 5, 3
SPACING = (1.5e-6, 2.5e-6, 4e-6)


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    d = tmp_path_factory.mktemp("formats_out")
    z, y, x = np.meshgrid(np.arange(NZ), np.arange(NY), np.arange(NX), indexing="ij")
    labels = ((x + 2 * y + 3 * z) % 4).astype(np.uint8)
    labels.tofile(d / "in.raw")
    (d / "p.yaml").write_text(
        f"""name: interop
stages:
  - id: r
    use: import.raw
    with: {{path: {d / 'in.raw'}, dims: [{NX}, {NY}, {NZ}],
            spacing: [1.5 um, 2.5 um, 4 um], origin: [1 mm, 0, 0]}}
export:
  - {{ from: r.image, to: {d / 'img.tif'} }}
  - {{ from: r.image, to: {d / 'slices.tif'}, with: {{ stack: directory }} }}
  - {{ from: r.image, to: {d / 'img.mhd'} }}
"""
    )
    subprocess.run([PIPE, "run", str(d / "p.yaml")], check=True, cwd=d)
    return d, labels


def test_multipage_tiff_in_tifffile(out):
    d, labels = out
    with tifffile.TiffFile(d / "img.tif") as t:
        assert t.is_imagej
        ij = t.imagej_metadata
        data = t.asarray()
        page = t.pages[0]
        xres = page.tags["XResolution"].value
        yres = page.tags["YResolution"].value
    assert data.dtype == np.uint8 and data.shape == (NZ, NY, NX)
    np.testing.assert_array_equal(data, labels)
    assert ij["unit"] == "micron"
    # ImageJ spacing: z step in um; resolutions in pixels per um (rational, 1e-9 exact).
    assert abs(ij["spacing"] - 4.0) < 1e-12
    assert abs(xres[0] / xres[1] - 1 / 1.5) < 1e-9
    assert abs(yres[0] / yres[1] - 1 / 2.5) < 1e-9


def test_directory_stack_in_tifffile(out):
    d, labels = out
    files = sorted((d / "slices").glob("slices_*.tif"))
    assert [f.name for f in files] == [f"slices_{k:04d}.tif" for k in range(NZ)]
    data = np.stack([tifffile.imread(f) for f in files])
    np.testing.assert_array_equal(data, labels)


def test_mhd_header_and_raw(out):
    d, labels = out
    header = dict(
        line.split(" = ", 1) for line in (d / "img.mhd").read_text().splitlines() if " = " in line
    )
    assert header["DimSize"] == f"{NX} {NY} {NZ}"
    assert header["ElementType"] == "MET_UCHAR"
    spacing_mm = [float(s) for s in header["ElementSpacing"].split()]
    np.testing.assert_allclose(np.array(spacing_mm) * 1e-3, SPACING, rtol=1e-12)
    offset_mm = [float(s) for s in header["Offset"].split()]
    np.testing.assert_allclose(
        np.array(offset_mm) * 1e-3, np.array([1e-3, 0, 0]) + 0.5 * np.array(SPACING), rtol=1e-12
    )
    data = np.fromfile(d / header["ElementDataFile"], dtype=np.uint8).reshape(NZ, NY, NX)
    np.testing.assert_array_equal(data, labels)
