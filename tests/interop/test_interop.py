"""Interop test: files written by grainpipe-formats open in pyvista (VTK), h5py and netCDF4
with the right shape, spacing, origin, values and phase fractions.

The files come from `cargo run --release -p grainpipe-formats --example write_samples -- DIR`
(cargo from $CARGO if set), run from the workspace root; `manifest.json` beside them holds
the numbers computed in Rust from the artifacts themselves. Field values follow the formula
value(x, y, z, k) = x + 100 y + 10000 z + 0.25 k, so a swapped axis cannot pass.
"""

import json
import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

import h5py  # noqa: E402
import pandas as pd  # noqa: E402
import netCDF4  # noqa: E402
import pyvista as pv  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]

# Doubles are stored in binary (HDF5, NetCDF, VTK binary arrays): exact. Grid geometry in VTK
# XML is text written as the shortest round-trip decimal, which VTK parses back to the same
# double; 1e-12 relative only guards against a parser that rounds in the last bit.
RTOL = 1e-12


@pytest.fixture(scope="session")
def samples(tmp_path_factory):
    out = tmp_path_factory.mktemp("samples")
    cargo = os.environ.get("CARGO", "cargo")
    cmd = [cargo, "run", "--release", "-q", "-p", "grainpipe-formats", "--example",
           "write_samples", "--", str(out)]
    subprocess.run(cmd, cwd=ROOT, check=True)
    manifest = json.loads((out / "manifest.json").read_text())
    return out, manifest


def grid(m):
    g = m["grid"]
    return g["dims"], np.array(g["spacing"]), np.array(g["origin"])


def expected_field(m):
    nx, ny, nz = m["grid"]["dims"]
    z, y, x, k = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), np.arange(3),
                             indexing="ij")
    return x + 100.0 * y + 10000.0 * z + 0.25 * k  # shape (nz, ny, nx, 3)


def check_fractions(labels, m):
    labels = np.asarray(labels).ravel()
    for pid, frac in m["phase"]["fractions"].items():
        # counts of voxels are integers: the fraction must match exactly
        assert np.count_nonzero(labels == int(pid)) / labels.size == frac
    assert labels.sum() == m["phase"]["labels_sum"]
    # the slab z < 2 is exactly a quarter of an 8-layer image
    assert np.count_nonzero(labels == 2) / labels.size == m["phase"]["slab_fraction_analytic"]


def check_image_geometry(mesh, m):
    dims, spacing, origin = grid(m)
    assert tuple(mesh.dimensions) == tuple(d + 1 for d in dims)  # points = cells + 1
    assert mesh.n_cells == int(np.prod(dims))
    np.testing.assert_allclose(mesh.spacing, spacing, rtol=RTOL)
    np.testing.assert_allclose(mesh.origin, origin, rtol=RTOL)


def cells_zyx(mesh, name, m, ncomp=1):
    nx, ny, nz = m["grid"]["dims"]
    a = np.asarray(mesh.cell_data[name])
    return a.reshape((nz, ny, nx, ncomp) if ncomp > 1 else (nz, ny, nx))


# --------------------------------------------------------------------------- pyvista


@pytest.mark.parametrize("ext", ["vti", "vtkhdf"])
def test_pyvista_phase_image(samples, ext):
    d, m = samples
    mesh = pv.read(d / f"phase.{ext}")
    check_image_geometry(mesh, m)
    labels = cells_zyx(mesh, "phase", m)
    assert labels.dtype == np.uint8
    check_fractions(labels, m)
    # slab along z, not along x or y
    assert (labels[:2] == 2).all() and not (labels[2:] == 2).any()
    if ext == "vti":
        names = list(mesh.field_data["phase_names"])
        assert names == [p["name"] for p in m["phase"]["phases"]]
        assert list(mesh.field_data["phase_ids"]) == [p["id"] for p in m["phase"]["phases"]]
        assert str(mesh.field_data["seed"][0]) == m["provenance"]["seed"]


@pytest.mark.parametrize("ext", ["vti", "vtkhdf"])
def test_pyvista_field(samples, ext):
    d, m = samples
    mesh = pv.read(d / f"field.{ext}")
    check_image_geometry(mesh, m)
    np.testing.assert_array_equal(cells_zyx(mesh, "velocity", m, 3), expected_field(m))
    if ext == "vti":
        assert str(mesh.field_data["unit"][0]) == "m/s"


def test_pyvista_packing(samples):
    d, m = samples
    p = m["packing"]
    mesh = pv.read(d / "packing.vtp")
    assert mesh.n_points == p["n_points"]
    assert mesh.n_verts == p["n_points"]
    # clump spheres are rotated into place in Rust; positions are stored as doubles
    np.testing.assert_allclose(mesh.points, np.array(p["centers"]), rtol=0, atol=1e-18)
    np.testing.assert_array_equal(mesh.point_data["radius"], p["radius"])
    np.testing.assert_array_equal(mesh.point_data["body_id"], p["body_id"])
    np.testing.assert_array_equal(mesh.point_data["layer"], p["layer"])
    np.testing.assert_array_equal(mesh.point_data["peak_temperature"], p["peak_temperature"])


def test_pyvista_contact_graph(samples):
    d, m = samples
    g = m["graph"]
    mesh = pv.read(d / "graph.vtp")
    assert mesh.n_points == g["n_points"]
    lines = np.asarray(mesh.lines).reshape(-1, 3)
    assert (lines[:, 0] == 2).all()
    np.testing.assert_array_equal(lines[:, 1:], g["lines"])
    gap = np.asarray(mesh.cell_data["gap"])
    np.testing.assert_array_equal(gap[:2], g["gap"][:2])
    assert math.isnan(gap[2])  # bond without contact: no gap known
    np.testing.assert_array_equal(mesh.cell_data["bonded"], g["bonded"])
    np.testing.assert_array_equal(mesh.field_data["faces_zmin"], g["faces"]["zmin"])


def test_pyvista_series(samples):
    d, m = samples
    s = m["series"]
    reader = pv.get_reader(d / "series.pvd")
    np.testing.assert_allclose(reader.time_values, s["times"], rtol=RTOL)
    blocks = reader.read()
    x0 = None
    for k, t in enumerate(s["times"]):
        reader.set_active_time_value(t)
        mesh = reader.read()[0]
        assert mesh.n_points == s["n_points"]
        if x0 is None:
            x0 = np.asarray(mesh.points[:, 0]).copy()
        np.testing.assert_allclose(mesh.points[:, 0] - x0, k * s["x_shift_per_frame"],
                                   rtol=0, atol=1e-15)
    assert len(blocks) == 1


# --------------------------------------------------------------------------- h5py


def test_h5py_phase_image(samples):
    d, m = samples
    dims, spacing, origin = grid(m)
    with h5py.File(d / "phase.h5", "r") as f:
        assert f.attrs["grainpipe_kind"] == "PhaseImage"
        # Seeds are u64 attributes: numbers in h5py, the exact 64-bit value.
        assert f.attrs["seed"] == int(m["provenance"]["seed"])
        assert f.attrs["seed"].dtype == np.uint64
        ds = f["phase"]
        assert ds.shape == tuple(reversed(dims))
        np.testing.assert_array_equal(ds.attrs["spacing"], spacing)
        np.testing.assert_array_equal(ds.attrs["origin"], origin)
        assert [n for n in ds.attrs["phase_names"]] == [p["name"] for p in m["phase"]["phases"]]
        check_fractions(ds[()], m)


def test_h5py_field(samples):
    d, m = samples
    with h5py.File(d / "field.h5", "r") as f:
        ds = f[f.attrs["dataset"]]
        assert ds.attrs["units"] == "m/s"
        np.testing.assert_array_equal(ds[()], expected_field(m))


def test_h5py_vtkhdf_layout(samples):
    d, m = samples
    dims, spacing, origin = grid(m)
    with h5py.File(d / "phase.vtkhdf", "r") as f:
        g = f["VTKHDF"]
        assert g.attrs["Type"] == b"ImageData"
        assert list(g.attrs["Version"]) == [2, 0]
        assert list(g.attrs["WholeExtent"]) == [0, dims[0], 0, dims[1], 0, dims[2]]
        np.testing.assert_array_equal(g.attrs["Spacing"], spacing)
        assert g["CellData/phase"].shape == tuple(reversed(dims))


def test_h5py_packing(samples):
    d, m = samples
    p = m["packing"]
    with h5py.File(d / "packing.h5", "r") as f:
        assert f["positions"].shape == (p["n_bodies"], 3)
        assert f["orientation"].shape == (p["n_bodies"], 4)
        assert list(f["clump_index"][()]) == [-1, -1, 0]
        assert f["library/sphere_radius"].shape == (2,)
        t = f["attributes/peak_temperature"]
        assert t.attrs["units"] == "K"
        assert f["positions"].attrs["units"] == "m" and f["radius"].attrs["units"] == "m"
        np.testing.assert_array_equal(t[()], [300.0, 450.5, 1200.25])
        np.testing.assert_array_equal(f["domain"].attrs["max"], [1e-3] * 3)


def test_h5py_graph_table_tensor_series(samples):
    d, m = samples
    with h5py.File(d / "graph.h5", "r") as f:
        np.testing.assert_array_equal(f["pairs"][()], [[0, 1], [1, 2]])
        np.testing.assert_array_equal(f["gaps"][()], m["graph"]["gap"][:2])
        np.testing.assert_array_equal(f["bonds"][()], [[0, 1], [2, 3]])
        np.testing.assert_array_equal(f["faces/xmax"][()], [3])
    t = m["table"]
    with h5py.File(d / "table.h5", "r") as f:
        g = f["table"]
        assert g.attrs["name"] == t["name"]
        for c in t["columns"]:
            ds = g[c["name"]]
            if c["name"] != "note":  # text has no unit; dimensionless is "1"
                assert ds.attrs["units"] == (c["unit"] or "1")
        np.testing.assert_array_equal(g["time"][()], t["time"])
        np.testing.assert_array_equal(g["step"][()], t["step"])
        assert [s.decode() for s in g["note"][()]] == t["note"]
    with h5py.File(d / "tensor.h5", "r") as f:
        ds = f["tensor"]
        assert ds.shape == (6, 6)
        assert ds.attrs["convention"] == "Mandel"
        np.testing.assert_array_equal(ds[()].ravel(), m["tensor"]["values"])
    with h5py.File(d / "series.h5", "r") as f:
        times = [f["frames"][k].attrs["time"] for k in sorted(f["frames"])]
        np.testing.assert_array_equal(times, m["series"]["times"])


# --------------------------------------------------------------------------- netCDF4


def check_nc_coords(ds, m):
    dims, spacing, origin = grid(m)
    for a, name in enumerate("xyz"):
        c = ds.variables[name]
        assert c.units == "m"
        centres = origin[a] + (np.arange(dims[a]) + 0.5) * spacing[a]
        np.testing.assert_allclose(c[:], centres, rtol=RTOL)


def test_netcdf_phase_image(samples):
    d, m = samples
    with netCDF4.Dataset(d / "phase.nc") as ds:
        v = ds.variables["phase"]
        assert v.dimensions == ("z", "y", "x")
        assert v.long_name == "phase label"
        check_nc_coords(ds, m)
        assert list(v.flag_values) == [p["id"] for p in m["phase"]["phases"]]
        assert v.flag_meanings.split() == ["pore", "grain", "base_plate"]
        assert ds.seed == int(m["provenance"]["seed"])  # NC_UINT64
        check_fractions(np.asarray(v[:]), m)


def test_netcdf_field(samples):
    d, m = samples
    with netCDF4.Dataset(d / "field.nc") as ds:
        v = ds.variables["velocity"]
        assert v.dimensions == ("z", "y", "x", "component")
        assert v.units == "m/s"
        check_nc_coords(ds, m)
        np.testing.assert_array_equal(np.asarray(v[:]), expected_field(m))


# --------------------------------------------------------------------------- CSV / JSON


def test_csv_and_json(samples):
    d, m = samples
    t = m["table"]
    # A plain read_csv: the first row is the header, numbers are numbers.
    df = pd.read_csv(d / "table.csv")
    assert list(df.columns) == ["time [s]", "step [1]", "neck radius [m]", "note"]
    assert df["time [s]"].tolist() == t["time"]
    assert df["step [1]"].dtype == np.int64 and df["step [1]"].tolist() == t["step"]
    assert df["neck radius [m]"].tolist() == t["neck radius"]
    assert df["note"].fillna("").tolist() == t["note"]
    side = json.loads((d / "table.csv.json").read_text())
    assert [c["name"] for c in side["columns"]] == [c["name"] for c in t["columns"]]
    assert side["provenance"]["seed"] == m["provenance"]["seed"]
    j = json.loads((d / "table.json").read_text())
    assert [c["name"] for c in j["columns"]] == [c["name"] for c in t["columns"]]
    assert j["columns"][2]["values"] == t["neck radius"]
    tensor = pd.read_csv(d / "tensor.csv")
    assert list(tensor.columns) == [f"{c} [Pa]" for c in ("xx", "yy", "zz", "yz", "xz", "xy")]
    np.testing.assert_array_equal(tensor.to_numpy().ravel(), m["tensor"]["values"])
    tside = json.loads((d / "tensor.csv.json").read_text())
    assert tside["convention"] == "Mandel" and tside["unit"] == "Pa" and tside["shape"] == [6, 6]
    tj = json.loads((d / "tensor.json").read_text())
    np.testing.assert_array_equal(np.array(tj["values"]).ravel(), m["tensor"]["values"])
    g = pd.read_csv(d / "graph.csv")
    assert list(g.columns)[:4] == ["i [1]", "j [1]", "gap [m]", "bonded [1]"]
    assert g[["i [1]", "j [1]"]].to_numpy().tolist() == m["graph"]["lines"]
    assert np.isnan(g["gap [m]"][2]) and g["bonded [1]"].tolist() == m["graph"]["bonded"]
    gj = json.loads((d / "graph.json").read_text())
    assert gj["faces"]["zmin"] == m["graph"]["faces"]["zmin"]
