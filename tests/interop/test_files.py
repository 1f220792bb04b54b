"""Interop test of the files users open, against real runs of `pipe` ($PIPE):

- HDF5 / VTKHDF / NetCDF are chunked and deflated by default, `compression: 0` turns it off;
  pyvista (VTK), h5py and netCDF4 read the compressed files back to the same values;
- `.h5` packings carry `units` on every dataset, the seed as uint64, integer attributes as
  integers and say what they are (`grainpipe_kind`);
- every CSV the shipped pipelines write parses with a plain `pandas.read_csv(path)` (header
  `name [unit]`, numbers as numbers, no comment rows) and matches the sidecar, the .json and
  the .h5 of the same table;
- `.vtp` packings carry `clump_index` and `layer`, and the `periodic` option wraps or clips.

Runs spheres (smaller box), mcm and powderbed always; the remaining shipped pipelines (each
a minute or more on 2 cores) only with INTEROP_ALL_PIPELINES=1.
"""

import json
import os
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

import h5py  # noqa: E402
import netCDF4  # noqa: E402
import pandas as pd  # noqa: E402
import pyvista as pv  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
PIPE = str((ROOT / os.environ.get("PIPE", "target/release/pipe")).resolve())

FAST = ["spheres", "mcm", "powderbed", "clumps", "elasticity"]
SLOW = ["permeability", "binder", "sandcore-quick", "sandcore-spheres", "cemented2d", "sandcore"]
PIPELINES = FAST + (SLOW if os.environ.get("INTEROP_ALL_PIPELINES") == "1" else [])

HEADER = re.compile(r"^[^\[\]#]+ \[[^\[\]]+\]$")


def run(cwd, pipeline, *extra):
    subprocess.run([PIPE, "run", str(pipeline), "--quiet", "--no-cache", *extra],
                   cwd=cwd, check=True)


@pytest.fixture(scope="module")
def compression(tmp_path_factory):
    """The spheres image (120^3 voxels) exported with and without compression."""
    cwd = tmp_path_factory.mktemp("compression")
    text = (ROOT / "pipelines/spheres.yaml").read_text()
    text = text[: text.index("export:")] + """export:
  - { from: voxels.image, to: out/on.vtkhdf }
  - { from: voxels.image, to: out/off.vtkhdf, with: { compression: 0 } }
  - { from: voxels.image, to: out/on.h5 }
  - { from: voxels.image, to: out/off.h5, with: { compression: 0 } }
  - { from: voxels.image, to: out/on.nc, with: { compression: 9 } }
  - { from: voxels.image, to: out/off.nc, with: { compression: 0 } }
  - { from: voxels.image, to: out/ref.vti }
  - { from: pack.packing, to: out/packing.h5 }
  - { from: pack.report, to: out/rsa.csv }
  - { from: pack.report, to: out/rsa.json }
  - { from: pack.report, to: out/rsa.h5 }
"""
    (cwd / "p.yaml").write_text(text)
    run(cwd, cwd / "p.yaml", "--set", "pack.size=[300 um, 300 um, 300 um]")
    return cwd / "out"


def test_compressed_files_are_smaller_and_read_back_equal(compression):
    out = compression
    ref = np.asarray(pv.read(out / "ref.vti").cell_data["phase"])
    n = ref.size  # one byte per voxel uncompressed
    for ext in ["vtkhdf", "h5", "nc"]:
        on, off = (out / f"on.{ext}").stat().st_size, (out / f"off.{ext}").stat().st_size
        assert off >= n, (ext, off, n)
        # A two-phase image of spheres: deflate must win at least a factor 5.
        assert on * 5 <= off, (ext, on, off)
    # pyvista/VTK reads the chunked, deflated VTKHDF to the same labels and grid.
    for name in ["on.vtkhdf", "off.vtkhdf"]:
        img = pv.read(out / name)
        np.testing.assert_array_equal(np.asarray(img.cell_data["phase"]), ref)
    with h5py.File(out / "on.vtkhdf", "r") as f:
        ds = f["VTKHDF/CellData/phase"]
        assert ds.compression == "gzip" and ds.compression_opts == 4 and ds.chunks is not None
    with h5py.File(out / "off.vtkhdf", "r") as f:
        assert f["VTKHDF/CellData/phase"].chunks is None
    with h5py.File(out / "on.h5", "r") as f:
        assert f["phase"].compression == "gzip"
        np.testing.assert_array_equal(f["phase"][()].ravel(), ref)
    with netCDF4.Dataset(out / "on.nc") as nc:
        v = nc.variables["phase"]
        assert v.filters()["zlib"] and v.filters()["complevel"] == 9
        np.testing.assert_array_equal(np.asarray(v[:]).ravel(), ref)
    with netCDF4.Dataset(out / "off.nc") as nc:
        assert not nc.variables["phase"].filters()["zlib"]


def test_h5_packing_units_seed_and_kind(compression):
    with h5py.File(compression / "packing.h5", "r") as f:
        assert f.attrs["grainpipe_kind"] == "Packing"
        assert f.attrs["seed"] == 42 and f.attrs["seed"].dtype == np.uint64
        assert f.attrs["stage_seed"].dtype == np.uint64
        units = {}

        def collect(name, obj):  # returns None: visititems stops at a non-None return
            if isinstance(obj, h5py.Dataset):
                units[name] = obj.attrs.get("units")

        f.visititems(collect)
        assert units["positions"] == "m" and units["radius"] == "m"
        assert units["orientation"] == "1" and units["layer"] == "1"
        assert units["domain/excluded_spheres"] == "m"
        missing = [k for k, u in units.items() if u is None]
        assert not missing, missing


def numeric_columns(df):
    return [c for c in df.columns if pd.api.types.is_numeric_dtype(df[c])]


def test_one_table_in_csv_json_and_h5_holds_the_same_values(compression):
    out = compression
    df = pd.read_csv(out / "rsa.csv")
    side = json.loads((out / "rsa.csv.json").read_text())
    js = json.loads((out / "rsa.json").read_text())
    assert side["provenance"]["seed"] == "42" and side["name"] == js["name"]
    with h5py.File(out / "rsa.h5", "r") as f:
        g = f["table"]
        for col, c in zip(df.columns, js["columns"]):
            assert col == f"{c['name']} [{c['unit'] or '1'}]"
            # the CSV holds the shortest round-trip decimal of each double: exact
            assert df[col].tolist() == c["values"]
            key = [k for k in g if g[k].attrs["name"] == c["name"]][0]
            assert g[key][()].tolist() == c["values"]
            assert g[key].attrs["units"] == (c["unit"] or "1")


@pytest.fixture(scope="module", params=PIPELINES)
def shipped(request, tmp_path_factory):
    cwd = tmp_path_factory.mktemp(request.param)
    pipeline = ROOT / "pipelines" / f"{request.param}.yaml"
    extra = ["--set", "pack.size=[200 um, 200 um, 200 um]"] if request.param == "spheres" else []
    run(cwd, pipeline, *extra)
    return request.param, cwd / "out"


def test_every_csv_parses_with_a_plain_read_csv(shipped):
    name, out = shipped
    csvs = sorted(out.rglob("*.csv"))
    assert csvs, f"{name} wrote no CSV"
    for path in csvs:
        df = pd.read_csv(path)
        assert len(df.columns) > 0 and len(df) > 0, path
        side = json.loads((path.parent / (path.name + ".json")).read_text())
        assert side["provenance"]["pipeline_name"] == name
        for col in df.columns:
            assert not col.startswith("#") and not col.startswith("Unnamed"), (path, col)
        for col in numeric_columns(df):
            assert HEADER.match(col), (path, col)  # `name [unit]`
        text = [c for c in df.columns if c not in numeric_columns(df)]
        for col in text:
            # text columns have a bare name and hold text, not numbers that failed to parse
            vals = df[col].dropna().astype(str)
            assert not vals.str.fullmatch(r"-?[0-9.]+(e-?[0-9]+)?").all() or vals.empty, (path, col)
        if side["kind"] in ("Table", "ContactGraph"):
            assert [c["header"] for c in side["columns"]] == list(df.columns), path
        else:  # a tensor: the matrix rows
            assert df.size == int(np.prod(side["shape"])), path
            sibling = path.with_suffix(".json")
            if sibling.exists():
                js = json.loads(sibling.read_text())
                np.testing.assert_array_equal(df.to_numpy().ravel(),
                                              np.array(js["values"], dtype=float).ravel())


def test_vtp_packings_carry_clump_index_and_layer(shipped):
    name, out = shipped
    h5s = {p.stem: p for p in out.rglob("*.h5")}
    for vtp in sorted(out.rglob("*.vtp")):
        if vtp.stem not in h5s:
            continue
        with h5py.File(h5s[vtp.stem], "r") as f:
            if f.attrs["grainpipe_kind"] != "Packing":
                continue
            clump, layer = f["clump_index"][()], f["layer"][()]
        poly = pv.read(vtp)
        body = np.asarray(poly.point_data["body_id"])
        np.testing.assert_array_equal(np.asarray(poly.point_data["layer"]), layer[body])
        if (clump >= 0).any():
            np.testing.assert_array_equal(np.asarray(poly.point_data["clump_index"]), clump[body])


def test_periodic_wrap_and_clip(tmp_path):
    """The stacked MCM packing of mcm.yaml (periodic in x, y, z), smaller, written three ways."""
    text = (ROOT / "pipelines/mcm.yaml").read_text()
    text = text[: text.index("export:")] + """export:
  - { from: stacked.packing, to: out/as_is.vtp }
  - { from: stacked.packing, to: out/wrap.vtp, with: { periodic: wrap } }
  - { from: stacked.packing, to: out/clip.vtp, with: { periodic: clip } }
  - { from: stacked.packing, to: out/stacked.h5 }
"""
    text = text.replace("directory: data/", f"directory: {ROOT}/data/")
    (tmp_path / "p.yaml").write_text(text)
    run(tmp_path, tmp_path / "p.yaml", "--target", "stacked", "--set", "stacked.layers=1")
    out = tmp_path / "out"
    with h5py.File(out / "stacked.h5", "r") as f:
        lo, hi = f["domain"].attrs["min"], f["domain"].attrs["max"]
        clump = f["clump_index"][()]
    as_is, wrap, clip = (pv.read(out / f"{m}.vtp") for m in ["as_is", "wrap", "clip"])
    pts = np.asarray(as_is.points, dtype=float)
    outside = ((pts < lo) | (pts >= hi)).any(axis=1)
    assert outside.any(), "no sphere sticks out: the test would prove nothing"
    # wrap: same spheres, same radii, every centre in the box, moved by whole box lengths
    assert wrap.n_points == as_is.n_points
    w = np.asarray(wrap.points, dtype=float)
    tol = 1e-6 * (hi - lo)  # points are float32 in the file
    assert ((w >= lo - tol) & (w < hi + tol)).all()
    shift = (w - pts) / (hi - lo)
    np.testing.assert_allclose(shift, np.round(shift), atol=1e-5)
    np.testing.assert_array_equal(wrap.point_data["radius"], as_is.point_data["radius"])
    # clip: exactly the spheres whose centre is inside
    assert clip.n_points == int((~outside).sum())
    np.testing.assert_array_equal(np.asarray(clip.point_data["radius"]),
                                  np.asarray(as_is.point_data["radius"])[~outside])
    body = np.asarray(as_is.point_data["body_id"])
    np.testing.assert_array_equal(np.asarray(as_is.point_data["clump_index"]), clump[body])
