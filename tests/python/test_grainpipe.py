"""Tests of the `grainpipe` Python package (python/): results equal, element for element, to
the files `pipe` exports for the same pipeline and seed; errors carry their locations; a
cancelled run raises KeyboardInterrupt and leaves no half-written export; a plugin stage
works; the quickstart example runs.

Needs the package installed in the interpreter (`make python`) and the `pipe` binary ($PIPE,
default target/release/pipe). The plugin test builds examples/plugin-example with cargo
($CARGO) unless $GRAINPIPE_PLUGIN_EXAMPLE names the built library.
"""

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

import grainpipe as gp  # noqa: E402
import h5py  # noqa: E402
import netCDF4  # noqa: E402
import pyvista as pv  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SPHERES = ROOT / "pipelines/spheres.yaml"
PIPE = str((ROOT / os.environ.get("PIPE", "target/release/pipe")).resolve())
# A smaller box than the shipped pipeline, so the test takes about a second.
SET = {"pack.size": "[200 um, 200 um, 200 um]"}
SEED = 7


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """`pipe run` of spheres.yaml; the directory of its exports."""
    cwd = tmp_path_factory.mktemp("pipe")
    args = [PIPE, "run", str(SPHERES), "--quiet", "--no-cache", "--seed", str(SEED)]
    for k, v in SET.items():
        args += ["--set", f"{k}={v}"]
    subprocess.run(args, cwd=cwd, check=True)
    return cwd / "out/spheres"


@pytest.fixture(scope="module")
def result():
    """The same pipeline and seed from Python, writing nothing."""
    return gp.run(SPHERES, set=SET, seed=SEED, cache=False, exports=False, progress=False)


def test_image_equals_vti_and_netcdf(exported, result):
    img = result["voxels.image"]
    assert isinstance(img, gp.Image)
    assert img.array.dtype == np.uint8
    nx, ny, nz = img.dims
    assert img.array.shape == (nz, ny, nx)
    vti = pv.read(exported / "image.vti")
    assert tuple(d - 1 for d in vti.dimensions) == img.dims
    np.testing.assert_array_equal(np.asarray(vti.spacing), img.spacing)
    np.testing.assert_array_equal(np.asarray(vti.origin), img.origin)
    (name,) = [n for n in vti.cell_data.keys() if vti.cell_data[n].size == img.array.size]
    # VTK's cell order is x fastest: the C-order ravel of (z, y, x).
    np.testing.assert_array_equal(vti.cell_data[name], img.array.ravel())
    with netCDF4.Dataset(exported / "image.nc") as nc:
        np.testing.assert_array_equal(nc.variables["phase"][:], img.array)
        np.testing.assert_array_equal(nc.variables["x"][:], img.coords()["x"])
        flags = nc.variables["phase"].getncattr("flag_values")
        assert sorted(int(f) for f in np.atleast_1d(flags)) == sorted(img.phases)
    # Provenance: the same seed and step as the exported files carry.
    assert result.provenance["voxels"]["seed"] == str(SEED)
    assert img.provenance["step"] == "voxels.image"
    assert json.loads(img.provenance["params"])["voxels_per_diameter"] == 20


def test_packing_equals_h5(exported, result):
    p = result["pack.packing"]
    assert isinstance(p, gp.Packing)
    with h5py.File(exported / "packing.h5", "r") as f:
        np.testing.assert_array_equal(f["positions"][()], p.positions)
        np.testing.assert_array_equal(f["radius"][()], p.radii)
        np.testing.assert_array_equal(f["orientation"][()], p.quaternions)
        np.testing.assert_array_equal(f["clump_index"][()], p.clump_index)
        np.testing.assert_array_equal(f["domain"].attrs["max"], p.domain["max"])
    assert p.positions.shape == (len(p), 3)
    np.testing.assert_array_equal(p.body_ids, np.arange(len(p)))
    poly = p.to_pyvista()
    assert poly.n_points == len(p)
    np.testing.assert_array_equal(poly.point_data["radius"], p.radii)
    vtp = pv.read(exported / "packing.vtp")
    np.testing.assert_array_equal(np.asarray(vtp.points), p.positions)


def read_csv(path):
    # Provenance may precede the header as `# key: value` comment lines.
    with open(path) as f:
        rows = list(csv.reader(line for line in f if not line.startswith("#")))
    return rows[0], rows[1:]


def test_tables_equal_csv(exported, result):
    for port, name in [("pack.report", "rsa.csv"), ("voxels.report", "voxelize.csv")]:
        t = result[port]
        assert isinstance(t, gp.Table)
        header, rows = read_csv(exported / name)
        assert len(header) == len(t)
        for k, (col, values) in enumerate(t.columns.items()):
            unit = t.units[col]
            assert header[k] == (f"{col} [{unit}]" if unit else col)
            got = [float(r[k]) for r in rows]
            # The CSV holds the shortest round-trip decimal of each double: exact.
            np.testing.assert_array_equal(np.asarray(values, dtype=float), got)


def test_image_fraction_matches_analytic(result):
    img, p = result["voxels.image"], result["pack.packing"]
    box = np.prod(np.asarray(p.domain["max"]) - np.asarray(p.domain["min"]))
    analytic = (4.0 / 3.0 * math.pi * np.sum(p.radii**3)) / box
    solid = 1.0 - img.fraction(0)
    assert abs(solid - analytic) < 0.01, (solid, analytic)
    g = img.to_pyvista()
    assert g.n_cells == img.array.size


def test_zero_copy_and_layout(result):
    a = result["voxels.image"].array
    # numpy owns nothing: the memory is the Vec the stage produced.
    assert not a.flags["OWNDATA"]
    assert a.flags["C_CONTIGUOUS"]
    assert result["voxels.image"].array is a


def test_dict_pipeline_and_validate():
    doc = {
        "name": "from-python",
        "seed": 3,
        "stages": [
            {"id": "pack", "use": "packing.rsa",
             "with": {"size": ["150 um", "150 um", "150 um"],
                      "radius": {"kind": "fixed", "value": "25 um"}, "volume_fraction": 0.2}},
            {"id": "voxels", "use": "voxelize.packing", "in": {"packing": "pack.packing"},
             "with": {"voxels_per_diameter": 10}},
        ],
    }
    plan = gp.validate(doc, exports=False)
    assert [s["id"] for s in plan["steps"]] == ["pack", "voxels"]
    grid = plan["steps"][1]["outputs"]["image"]["grid"]
    assert plan["memory_bytes"] > 0
    r = gp.run(doc, cache=False, progress=False)
    img = r["voxels.image"]
    assert list(img.dims) == grid["dims"]
    np.testing.assert_allclose(img.spacing, grid["spacing"], rtol=0, atol=0)
    # The same pipeline as YAML text gives the same voxels.
    text = json.dumps(doc)
    r2 = gp.run(text + "\n", cache=False, progress=False)
    np.testing.assert_array_equal(r2["voxels.image"].array, img.array)


def test_numpy_scalars_and_one_target_string():
    """Issue 35: numpy scalars were refused as parameter values (json cannot write them) and a
    string `targets` was split into characters."""
    set_np = dict(SET, **{"pack.volume_fraction": np.float32(0.25),
                          "voxels.voxels_per_diameter": np.int64(12)})
    set_py = dict(SET, **{"pack.volume_fraction": float(np.float32(0.25)),
                          "voxels.voxels_per_diameter": 12})
    a = gp.run(SPHERES, set=set_np, seed=np.int64(SEED), cache=False, exports=False,
               progress=False)
    b = gp.run(SPHERES, set=set_py, seed=SEED, cache=False, exports=False, progress=False)
    np.testing.assert_array_equal(a["voxels.image"].array, b["voxels.image"].array)
    plan = gp.validate(SPHERES, set=set_np, targets="pack", exports=False)
    assert [s["id"] for s in plan["steps"]] == ["pack"]
    with pytest.raises(TypeError, match="step ids"):
        gp.validate(SPHERES, targets=[1], exports=False)


def test_describe_is_pipe_describe():
    d = gp.describe("packing.rsa")
    out = subprocess.run([PIPE, "describe", "--json", "packing.rsa"], check=True,
                         capture_output=True, text=True).stdout
    assert d == json.loads(out)
    names = [p["name"] for p in d["params"]]
    assert "volume_fraction" in names
    assert [o["name"] for o in d["outputs"]][:1] == ["packing"]
    assert "packing.rsa" in gp.stages()
    with pytest.raises(gp.PipelineError) as e:
        gp.describe("packing.rsaa")
    assert e.value.suggestion == "packing.rsa" or "packing.rsa" in str(e.value.suggestion)


def test_pipeline_error_carries_location(tmp_path):
    bad = SPHERES.read_text().replace("volume_fraction: 0.30", "volume_fractoin: 0.30")
    path = tmp_path / "bad.yaml"
    path.write_text(bad)
    with pytest.raises(gp.PipelineError) as e:
        gp.validate(path)
    err = e.value
    assert err.file == str(path)
    line = next(i for i, l in enumerate(bad.splitlines(), 1) if "volume_fractoin" in l)
    assert err.line == line
    assert err.column == bad.splitlines()[line - 1].index("volume_fractoin") + 1
    assert err.key == "volume_fractoin"
    assert "volume_fraction" in err.suggestion
    assert f"{path}:{line}:" in str(err)
    # An unknown stage in a pipeline given as text: the pseudo path and the suggestion.
    text = "name: t\nstages:\n  - id: pack\n    use: packing.rsaa\n"
    with pytest.raises(gp.PipelineError) as e:
        gp.run(text, cache=False, progress=False)
    assert (e.value.file, e.value.line, e.value.key) == ("<python>", 4, "packing.rsaa")
    assert "packing.rsa" in e.value.suggestion
    # A bad override names --set.
    with pytest.raises(gp.PipelineError) as e:
        gp.validate(SPHERES, set={"nosuchstep.x": 1})
    assert "nosuchstep" in str(e.value)


def test_stage_error_is_raised():
    # 0.38 passes the input check (below the 0.383 jamming limit) but RSA in so small a box
    # jams first: the stage fails at run time and says how far it got.
    with pytest.raises(gp.StageError) as e:
        gp.run(SPHERES, set={**SET, "pack.volume_fraction": 0.38}, seed=SEED, cache=False,
               exports=False, targets=["pack"], progress=False)
    assert e.value.line == 8 and e.value.key == "packing.rsa"
    assert "volume fraction reached 0.3" in e.value.message
    assert not isinstance(e.value, gp.PipelineError)


def test_progress_events(tmp_path):
    events = []
    gp.run(SPHERES, set=SET, seed=SEED, cache=False, exports=False, progress=events.append)
    kinds = [e["event"] for e in events]
    assert kinds.count("start") == 2 and kinds.count("finish") == 2
    starts = [e for e in events if e["event"] == "start"]
    assert [s["step"] for s in starts] == ["pack", "voxels"]
    assert all(s["count"] == 2 for s in starts)


def test_cache_is_shared_with_pipe(tmp_path):
    cache = tmp_path / "cache"
    a = gp.run(SPHERES, set=SET, seed=SEED, cache=cache, exports=False, progress=False)
    b = gp.run(SPHERES, set=SET, seed=SEED, cache=cache, exports=False, progress=False)
    assert not a.stats["pack"]["from_cache"]
    assert b.stats["pack"]["from_cache"] and b.stats["voxels"]["from_cache"]
    np.testing.assert_array_equal(a["voxels.image"].array, b["voxels.image"].array)


def test_cancelled_run_raises_keyboard_interrupt(tmp_path):
    out = tmp_path / "run"
    seen = []

    def interrupt(event):
        seen.append(event)
        # Ctrl-C while voxelize runs: the packing's exports are complete by then.
        if event["event"] == "start" and event["step"] == "voxels":
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        gp.run(SPHERES, set={"pack.size": "[400 um, 400 um, 400 um]",
                             "voxels.voxels_per_diameter": 40},
               seed=SEED, cache=False, out=out, progress=interrupt)
    written = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    # Nothing half-written: no temporary files, and every file present opens completely.
    assert all(not Path(w).name.startswith(".") and "tmp" not in w for w in written), written
    for w in written:
        if w.endswith(".h5"):
            with h5py.File(out / w, "r") as f:
                assert f["positions"].shape[1] == 3
        elif w.endswith(".vtp"):
            assert pv.read(out / w).n_points > 0
    # The image the interrupted step would have produced was not exported.
    assert not any(w.startswith("spheres/image") for w in written), written


def plugin_library():
    lib = os.environ.get("GRAINPIPE_PLUGIN_EXAMPLE")
    if lib:
        return Path(lib)
    cargo = os.environ.get("CARGO", "cargo")
    subprocess.run([cargo, "build", "--release", "-q", "-p", "grainpipe-plugin-example"],
                   cwd=ROOT, check=True)
    target = Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target"))
    return target / "release/libgrainpipe_plugin_example.so"


def test_plugin_stage_from_python():
    lib = plugin_library()
    text = """name: plugin
seed: 9
stages:
  - id: pack
    use: packing.rsa
    with: { size: [200 um, 200 um, 200 um], volume_fraction: 0.25 }
  - id: voxels
    use: voxelize.packing
    in: { packing: pack.packing }
    with: { voxels_per_diameter: 6 }
  - id: profile
    use: example.porosity_profile
    in: { image: voxels.image }
    with: { axis: y }
"""
    assert "example.porosity_profile" in gp.stages(plugin_dirs=[lib])
    r = gp.run(text, cache=False, progress=False, plugin_dirs=[lib])
    prof = r["profile.profile"]
    img = r["voxels.image"]
    porosity = [c for c in prof.columns if "poros" in c][0]
    expected = (img.array == 0).mean(axis=(0, 2))  # per y slice of (z, y, x)
    np.testing.assert_allclose(prof[porosity], expected, rtol=0, atol=1e-15)
    # Without the library the stage is unknown: an input error, nothing ran.
    with pytest.raises(gp.PipelineError):
        gp.validate(text)


def test_quickstart_example_runs(tmp_path):
    env = dict(os.environ, MPLBACKEND="Agg")
    subprocess.run([sys.executable, str(ROOT / "examples/python/quickstart.py"), str(tmp_path)],
                   cwd=ROOT, check=True, env=env)
    for name in ("slice.png", "sizes.png"):
        png = tmp_path / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sigint_cancels_at_next_checkpoint(tmp_path):
    """A real Ctrl-C (SIGINT to this process) while a stage runs: KeyboardInterrupt, soon."""
    import signal
    import time

    # The signal is sent once the voxelization has started (its first event), not after a
    # fixed delay: on a loaded machine a timer may fire before or after the stage runs.
    sent = []

    def ctrl_c_during_voxels(event):
        if event.get("step") == "voxels" and not sent:
            sent.append(time.monotonic())
            os.kill(os.getpid(), signal.SIGINT)

    # A process started in the background by a non-interactive shell inherits SIGINT ignored,
    # and Python then installs no KeyboardInterrupt handler: install it for this test.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    started = time.monotonic()
    try:
        with pytest.raises(KeyboardInterrupt):
            # About 370 million voxels: far longer than it takes to notice the signal.
            gp.run(SPHERES, set={"pack.size": "[600 um, 600 um, 600 um]",
                                 "voxels.voxels_per_diameter": 60},
                   seed=SEED, cache=tmp_path / "cache", out=tmp_path / "run",
                   progress=ctrl_c_during_voxels)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert sent, "the voxels step never started"
    assert time.monotonic() - started < 30
    # Nothing of the interrupted step: no export, no cache entry for it.
    assert not list((tmp_path / "run").rglob("image*"))


def _same_attr(got, want):
    """An attribute value as xarray holds it against the one netCDF4 reads from the file:
    strings equal, numbers (scalars or arrays) equal element for element."""
    if isinstance(want, str):
        return got == want
    want = np.atleast_1d(np.asarray(want))
    got = np.atleast_1d(np.asarray(got))
    if want.dtype.kind in "OUS":
        return [str(x) for x in got] == [str(x) for x in want]
    return got.shape == want.shape and np.array_equal(got, want)


def test_to_xarray_equals_netcdf_export(exported, result):
    import xarray as xr

    img = result["voxels.image"]
    da = img.to_xarray()
    assert isinstance(da, xr.DataArray)
    with netCDF4.Dataset(exported / "image.nc") as nc:
        var = nc.variables["phase"]
        assert da.name == "phase"
        assert da.dims == var.dimensions
        np.testing.assert_array_equal(da.values, var[:])
        # Coordinates: voxel centres in metres, exactly the file's, with the same attributes.
        for a in "xyz":
            c = nc.variables[a]
            np.testing.assert_array_equal(da.coords[a].values, c[:])
            assert dict(da.coords[a].attrs) == {k: c.getncattr(k) for k in c.ncattrs()}
        # The variable's CF attributes and the file's global ones (grid and provenance),
        # except the timings, which describe a run rather than the result.
        want = {k: nc.getncattr(k) for k in nc.ncattrs()}
        want.update({k: var.getncattr(k) for k in var.ncattrs()})
        want.pop("stage_timings_s")
        assert set(da.attrs) == set(want), set(da.attrs) ^ set(want)
        for k, v in want.items():
            if k == "pipeline_yaml":
                # The Python run writes no files, so its effective pipeline has no
                # `export:` list; everything that determines the numbers must agree.
                import yaml

                got_doc, want_doc = yaml.safe_load(da.attrs[k]), yaml.safe_load(v)
                got_doc.pop("export", None)
                want_doc.pop("export", None)
                assert got_doc == want_doc, (got_doc, want_doc)
                continue
            assert _same_attr(da.attrs[k], v), (k, da.attrs[k], v)
        # CF: flag_values have the variable's type.
        assert np.asarray(da.attrs["flag_values"]).dtype == var.dtype
        # Seeds are numbers in the file (uint64), exact.
        assert da.attrs["seed"] == SEED and np.asarray(da.attrs["seed"]).dtype == np.uint64
    # The provenance is a plain dict of strings, the entries the exported files carry.
    assert isinstance(img.provenance, dict)
    assert all(isinstance(v, str) for v in img.provenance.values())
    assert da.coords["x"].values[0] == img.origin[0] + 0.5 * img.spacing[0]


def test_to_pandas_equals_exported_csv(exported, result):
    import pandas as pd

    for port, name in [("pack.report", "rsa.csv"), ("voxels.report", "voxelize.csv")]:
        t = result[port]
        df = t.to_pandas()
        assert isinstance(df, pd.DataFrame)
        assert df.attrs["units"] == t.units
        # Provenance lines, wherever the writer puts them, are `#` comments; round_trip
        # parses each decimal to the double it was printed from.
        csv = pd.read_csv(exported / name, comment="#", float_precision="round_trip")
        assert len(csv) == len(df) > 0
        assert len(csv.columns) == len(df.columns)
        for col, header in zip(df.columns, csv.columns):
            unit = t.units[col]
            assert header == (f"{col} [{unit}]" if unit else col)
            got, want = df[col].to_numpy(), csv[header].to_numpy()
            if want.dtype.kind == "f" or got.dtype.kind == "f":
                np.testing.assert_array_equal(got.astype(float), want.astype(float))
            else:
                assert [str(x) for x in got] == [str(x) for x in want], col


def test_packing_to_pyvista_is_ready_to_glyph(result):
    p = result["pack.packing"]
    poly = p.to_pyvista()
    assert poly.n_points == len(p)
    np.testing.assert_array_equal(np.asarray(poly.points), p.positions)
    np.testing.assert_array_equal(poly.point_data["radius"], p.radii)
    # Glyphing by radius: a unit sphere scaled by each radius spans the packing's bounds.
    glyphs = poly.glyph(scale="radius", geom=pv.Sphere(radius=1.0), orient=False)
    lo = (p.positions - p.radii[:, None]).min(axis=0)
    hi = (p.positions + p.radii[:, None]).max(axis=0)
    b = np.asarray(glyphs.bounds).reshape(3, 2)
    # Sphere facets lie inside the true sphere: at most 1 % of a radius short.
    tol = 0.01 * p.radii.max()
    assert np.all(np.abs(b[:, 0] - lo) < tol) and np.all(np.abs(b[:, 1] - hi) < tol), (b, lo, hi)
    one = p.to_pyvista(spheres=True)
    # Spheres: one body each, so the per-sphere view has the same points.
    assert one.n_points == len(p.sphere_radii) == len(p)


def test_tqdm_progress_runs(result, capsys):
    import tqdm  # noqa: F401  (the default display when it is installed)

    r = gp.run(SPHERES, set=SET, seed=SEED, cache=False, exports=False)
    err = capsys.readouterr().err
    assert "[1/2] pack (packing.rsa)" in err and "[2/2] voxels (voxelize.packing)" in err, err
    np.testing.assert_array_equal(r["voxels.image"].array, result["voxels.image"].array)


def test_tqdm_bar_never_moves_back(capsys):
    show = gp._progress_callback(None)
    show({"event": "start", "step": "s", "stage": "x", "index": 0, "count": 1})
    show({"event": "progress", "step": "s", "done": 700, "total": 1000})
    show({"event": "progress", "step": "s", "done": 100, "total": 1000})
    # A new total keeps the shown fraction: 1 of 4 after 70 % shows 3 of 4.
    show({"event": "progress", "step": "s", "done": 1, "total": 4})
    show({"event": "finish", "step": "s", "wall_s": 0.1, "from_cache": False})
    err = capsys.readouterr().err
    assert " 70%" in err and " 75%" in err, err
    assert " 10%" not in err and " 25%" not in err, err


def _human_bytes(b):
    """`pipe`'s rendering of a byte count (core engine::human_bytes)."""
    units = ["B", "KiB", "MiB", "GiB", "TiB"]
    v, u = float(b), 0
    while v >= 1024 and u + 1 < len(units):
        v /= 1024
        u += 1
    return f"{b} B" if u == 0 else f"{v:.1f} {units[u]}"


def test_validate_returns_the_plan_pipe_validate_prints():
    plan = gp.validate(SPHERES, set=SET, seed=SEED)
    args = [PIPE, "validate", str(SPHERES), "--seed", str(SEED)]
    for k, v in SET.items():
        args += ["--set", f"{k}={v}"]
    text = subprocess.run(args, check=True, capture_output=True, text=True).stdout
    assert f"estimated memory: {_human_bytes(plan['memory_bytes'])}" in text, text
    for s in plan["steps"]:
        assert f"{s['id']:16} {s['stage']:22} ~{_human_bytes(s['memory_bytes'])}" in text, text
    grid = plan["steps"][1]["outputs"]["image"]["grid"]
    assert "grid {}x{}x{} of".format(*grid["dims"]) in text
    # 200 um at 25 um radius and 20 voxels per diameter: 2.5 um voxels, 80 per edge.
    assert grid["dims"] == [80, 80, 80]
    np.testing.assert_allclose(grid["spacing"], [2.5e-6] * 3, rtol=1e-12)
    assert [e["path"] for e in plan["exports"]] == [
        line.split("-> ")[1].split(" (")[0] for line in text.splitlines() if "-> " in line
    ]
