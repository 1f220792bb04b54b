"""Result classes around the plain data the native module returns.

Conventions (docs/python.md): SI units (metres, seconds, pascals...); voxel arrays have the
shape (z, y, x) in C order, plus a trailing component axis for multi-component fields, which
is grainpipe's own memory layout (x fastest), so numpy shares the memory the run produced:
no copy is made. `spacing`, `origin` and `dims` are given in (x, y, z) order, as in the YAML
and the VTK files. The optional libraries (xarray, pandas, pyvista) are imported only inside
the methods that need them.
"""

from __future__ import annotations

import re
from typing import Any, Iterator, Mapping, Optional

import numpy as np


def _nc_name(s: str) -> str:
    """The variable / flag name our NetCDF writer uses for `s` (formats/src/netcdf_io.rs)."""
    out = "".join(c if (c.isascii() and c.isalnum()) or c in "_.@+-" else "_" for c in s)
    if not re.match(r"[A-Za-z_]", out[:1]):
        out = "_" + out
    return out


#: Provenance entries our NetCDF and HDF5 writers store as integers (formats/src/h5util.rs).
_INTEGER_PROVENANCE = ("seed", "stage_seed")


class Artifact:
    """One output of a step. `kind` is the artifact kind (PhaseImage, Field, Packing, ...);
    `provenance` the entries grainpipe writes into exported files."""

    kind: str

    def __init__(self, data: dict, provenance: Optional[dict] = None):
        self._data = data
        self.kind = data["kind"]
        self.provenance = dict(provenance or {})

    def __repr__(self) -> str:
        return f"<grainpipe.{type(self).__name__} {self.kind}>"


class _Volume(Artifact):
    """Common to images and fields: a regular grid of voxels."""

    @property
    def array(self) -> np.ndarray:
        """The voxel values, shape (z, y, x) or (z, y, x, components); no copy."""
        return self._data["array"]

    @property
    def dims(self) -> tuple:
        """Voxel counts (nx, ny, nz)."""
        return tuple(self._data["dims"])

    @property
    def spacing(self) -> tuple:
        """Voxel edge lengths (dx, dy, dz) [m]."""
        return tuple(self._data["spacing"])

    @property
    def origin(self) -> tuple:
        """The grid's lower corner (not the first voxel centre) (x, y, z) [m]."""
        return tuple(self._data["origin"])

    @property
    def periodic(self) -> tuple:
        return tuple(self._data["periodic"])

    def coords(self) -> dict:
        """Voxel-centre coordinates per axis [m] ({"x": ..., "y": ..., "z": ...})."""
        return {
            a: self.origin[k] + (np.arange(self.dims[k]) + 0.5) * self.spacing[k]
            for k, a in enumerate("xyz")
        }

    def _name(self) -> str:
        raise NotImplementedError

    def _var_attrs(self) -> dict:
        raise NotImplementedError

    def to_xarray(self):
        """An xarray.DataArray with dims (z, y, x[, component]), coordinates of voxel centres
        in metres, and the CF attributes our NetCDF export writes (units, long_name, axis;
        flag_values / flag_meanings for phases; Conventions, spacing, origin and the
        provenance in the attributes)."""
        import xarray as xr

        c = self.coords()
        coords = {
            a: xr.Variable(
                (a,),
                c[a],
                attrs={"units": "m", "long_name": f"{a} coordinate of voxel centres", "axis": a.upper()},
            )
            for a in "zyx"
        }
        dims = ["z", "y", "x"]
        if self.array.ndim == 4:
            dims.append("component")
        attrs = self._var_attrs()
        attrs.update(
            {
                "Conventions": "CF-1.8",
                "title": f"grainpipe {self._name()}",
                "spacing": list(self.spacing),
                "origin": list(self.origin),
                "periodic": [int(p) for p in self.periodic],
            }
        )
        for k, v in self.provenance.items():
            # As the NetCDF writer: seeds as uint64 numbers (exact for 64-bit seeds).
            if k in _INTEGER_PROVENANCE and v.isdigit():
                v = np.uint64(int(v))
            attrs[_nc_name(k)] = v
        return xr.DataArray(self.array, dims=dims, coords=coords, name=_nc_name(self._name()), attrs=attrs)

    def to_pyvista(self):
        """A pyvista.ImageData whose cells are the voxels (cell data named as in our .vti)."""
        import pyvista as pv

        nx, ny, nz = self.dims
        g = pv.ImageData(dimensions=(nx + 1, ny + 1, nz + 1), spacing=self.spacing, origin=self.origin)
        a = self.array
        # C order of (z, y, x) is x fastest: VTK's cell order.
        values = a.reshape(nx * ny * nz, -1) if a.ndim == 4 else a.reshape(-1)
        g.cell_data[self._name()] = values
        return g


class Image(_Volume):
    """A segmented volume (PhaseImage): one uint8 phase label per voxel."""

    @property
    def phases(self) -> dict:
        """Phase names by label ({0: "pore", 1: "grain", ...})."""
        return dict(self._data["phases"])

    def fraction(self, label: int) -> float:
        """Volume fraction of voxels with `label`."""
        return float(np.count_nonzero(self.array == label)) / self.array.size

    def _name(self) -> str:
        return "phase"

    def _var_attrs(self) -> dict:
        ph = self.phases
        attrs: dict[str, Any] = {"long_name": "phase label", "units": "1"}
        if ph:
            attrs["flag_values"] = np.array(list(ph.keys()), dtype=np.uint8)
            attrs["flag_meanings"] = " ".join(_nc_name(n) for n in ph.values())
            attrs["phase_names"] = list(ph.values())
        return attrs


class Field(_Volume):
    """Per-voxel values of one quantity (float32 or float64), with unit and convention."""

    @property
    def name(self) -> str:
        return self._data["name"]

    @property
    def unit(self) -> str:
        return self._data["unit"]

    @property
    def components(self) -> int:
        return self._data["components"]

    @property
    def convention(self) -> str:
        """plain, vector, voigt, mandel or tensor (what the components mean)."""
        return self._data["convention"]

    @property
    def component_names(self) -> list:
        return list(self._data["component_names"])

    def _name(self) -> str:
        return self.name

    def _var_attrs(self) -> dict:
        attrs = {
            "long_name": self.name,
            "units": self.unit or "1",
            "component_convention": self.convention,
        }
        if self.components > 1:
            attrs["component_names"] = " ".join(self.component_names)
        return attrs


class Packing(Artifact):
    """Bodies in a domain: numpy arrays of one row per body."""

    positions: np.ndarray
    radii: np.ndarray

    def __init__(self, data: dict, provenance: Optional[dict] = None):
        super().__init__(data, provenance)
        #: Centroids (n, 3) [m].
        self.positions = data["positions"]
        #: Sphere radius, or a clump's bounding radius (n,) [m].
        self.radii = data["radii"]
        #: 0..n-1, the body index contacts and attributes refer to.
        self.body_ids = data["body_ids"]
        #: Orientation quaternions (w, x, y, z), body frame -> world frame (n, 4).
        self.quaternions = data["quaternions"]
        #: Clump library index per body, -1 for a sphere (n,).
        self.clump_index = data["clump_index"]
        self.layer = data["layer"]
        self.frozen = data["frozen"]
        #: Every sphere in world coordinates (one row per sphere of every clump).
        self.sphere_centers = data["sphere_centers"]
        self.sphere_radii = data["sphere_radii"]
        self.sphere_body = data["sphere_body"]
        #: {"min", "max", "periodic", "excluded_spheres"} [m].
        self.domain = data["domain"]
        #: Per-body values: {name: {"unit": str, "values": ndarray}}.
        self.attributes = data["attributes"]
        self.library = data["library"]

    def __len__(self) -> int:
        return len(self.radii)

    def volume_fraction(self) -> float:
        """Solid volume over domain volume for sphere packings (clumps: bounding spheres)."""
        lo, hi = np.asarray(self.domain["min"]), np.asarray(self.domain["max"])
        return float((4.0 / 3.0 * np.pi * self.radii**3).sum() / np.prod(hi - lo))

    def to_pyvista(self, spheres: bool = False):
        """A pyvista.PolyData of the body centres with point data `radius`, `body_id` and the
        attributes (glyph with ``poly.glyph(scale="radius", geom=pv.Sphere(radius=1))``).
        With ``spheres=True``, one point per sphere of every clump instead."""
        import pyvista as pv

        if spheres:
            poly = pv.PolyData(np.ascontiguousarray(self.sphere_centers))
            poly.point_data["radius"] = self.sphere_radii
            poly.point_data["body_id"] = self.sphere_body
            return poly
        poly = pv.PolyData(np.ascontiguousarray(self.positions))
        poly.point_data["radius"] = self.radii
        poly.point_data["body_id"] = self.body_ids
        poly.point_data["orientation"] = self.quaternions
        for name, a in self.attributes.items():
            poly.point_data[name] = a["values"]
        return poly


class ClumpLibrary(Artifact):
    """Clump shapes: `clumps` is a list of dicts (spheres (k, 4) as x, y, z, r in the body
    frame [m], volume, bounding_radius, principal_inertia, principal_axes, source)."""

    def __init__(self, data: dict, provenance: Optional[dict] = None):
        super().__init__(data, provenance)
        self.clumps = data["library"]["clumps"]
        self.source = data["library"]["source"]

    def __len__(self) -> int:
        return len(self.clumps)


class ContactGraph(Artifact):
    """Contacts (pairs of body indices, gaps [m], negative for overlap), bonds, the bodies on
    each domain face, the body positions and, for spheres, their radii [m] (`radius`, None for
    other bodies)."""

    def __init__(self, data: dict, provenance: Optional[dict] = None):
        super().__init__(data, provenance)
        self.radius = data.get("radius")
        self.contacts = data["contacts"]
        self.gaps = data["gaps"]
        self.bonds = data["bonds"]
        self.bond_attributes = data["bond_attributes"]
        self.faces = data["faces"]
        self.positions = data["positions"]

    def to_pyvista(self):
        """A pyvista.PolyData with a line per contact between body centres (cell data `gap`;
        point data `radius` for spheres, for glyphing)."""
        import pyvista as pv

        n = len(self.contacts)
        lines = np.column_stack([np.full(n, 2), self.contacts]).astype(np.int64).ravel()
        poly = pv.PolyData(np.ascontiguousarray(self.positions), lines=lines)
        poly.cell_data["gap"] = self.gaps
        if self.radius is not None:
            poly.point_data["radius"] = self.radius
        return poly


class Table(Artifact, Mapping):
    """Named columns of equal length, each with a unit: a read-only dict of numpy arrays
    (string columns are lists)."""

    def __init__(self, data: dict, provenance: Optional[dict] = None):
        super().__init__(data, provenance)
        self.name = data["name"]
        self.columns = {name: values for name, _, values in data["columns"]}
        #: Unit of each column ("" for none).
        self.units = {name: unit for name, unit, _ in data["columns"]}

    def __getitem__(self, key: str):
        return self.columns[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.columns)

    def __len__(self) -> int:
        return len(self.columns)

    def __repr__(self) -> str:
        return f"<grainpipe.Table {self.name!r} columns={list(self.columns)}>"

    def to_pandas(self):
        """A pandas.DataFrame; the units are in ``df.attrs["units"]``."""
        import pandas as pd

        df = pd.DataFrame({k: v for k, v in self.columns.items()})
        df.attrs["units"] = dict(self.units)
        df.attrs["name"] = self.name
        return df


class Tensor(Artifact):
    """A small dense tensor: `array` with its `convention` (plain, voigt or mandel)."""

    def __init__(self, data: dict, provenance: Optional[dict] = None):
        super().__init__(data, provenance)
        self.name = data["name"]
        self.unit = data["unit"]
        #: plain (full components), voigt (6x6, order 11 22 33 23 13 12, no factors) or
        #: mandel (the same order, shear rows and columns scaled by sqrt 2).
        self.convention = data["convention"]
        self.array = data["array"]

    def __array__(self, dtype=None, copy=None):
        return np.asarray(self.array, dtype=dtype)


class Series(Artifact):
    """A time series: `frames` is a list of (time [s], artifact)."""

    def __init__(self, data: dict, provenance: Optional[dict] = None):
        super().__init__(data, provenance)
        self.frames = [(t, wrap(a, provenance)) for t, a in data["frames"]]

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def times(self) -> np.ndarray:
        return np.array([t for t, _ in self.frames])


class Collection(Artifact, Mapping):
    """Named artifacts that belong together (grains, realizations, load cases), in order."""

    def __init__(self, data: dict, provenance: Optional[dict] = None):
        super().__init__(data, provenance)
        self.items_list = [(n, wrap(a, provenance)) for n, a in data["items"]]
        self._by_name = dict(self.items_list)

    def __getitem__(self, key: str):
        return self._by_name[key]

    def __iter__(self) -> Iterator[str]:
        return (n for n, _ in self.items_list)

    def __len__(self) -> int:
        return len(self.items_list)

    def __repr__(self) -> str:
        return f"<grainpipe.Collection of {len(self)}>"


_CLASSES = {
    "PhaseImage": Image,
    "Field": Field,
    "Packing": Packing,
    "ClumpLibrary": ClumpLibrary,
    "ContactGraph": ContactGraph,
    "Table": Table,
    "Tensor": Tensor,
    "Series": Series,
    "Collection": Collection,
}


def wrap(data: dict, provenance: Optional[dict] = None) -> Artifact:
    return _CLASSES[data["kind"]](data, provenance)


class Result(Mapping):
    """The outputs of a run, by ``"step.port"`` (``r["voxels.image"]``). ``r["step"]`` is the
    step's only output, or a dict of its ports. Also: `provenance` (by step), `stats` (wall
    time and cache use by step), `written` (exported files), `seed`."""

    def __init__(self, raw: dict):
        self.provenance: dict = raw["provenance"]
        self.stats: dict = raw["stats"]
        self.written: list = raw["written"]
        self.seed: int = raw["seed"]
        self.file: str = raw["file"]
        self._outputs: dict = {}
        for step, ports in raw["outputs"].items():
            for port, data in ports.items():
                prov = dict(self.provenance.get(step, {}))
                prov["step"] = f"{step}.{port}"
                self._outputs[f"{step}.{port}"] = wrap(data, prov)

    def __getitem__(self, key: str) -> Any:
        if key in self._outputs:
            return self._outputs[key]
        ports = {k.split(".", 1)[1]: v for k, v in self._outputs.items() if k.split(".", 1)[0] == key}
        if len(ports) == 1:
            return next(iter(ports.values()))
        if ports:
            return ports
        raise KeyError(f"{key!r}: no such output; the run gave {', '.join(self._outputs) or 'none'}")

    def __iter__(self) -> Iterator[str]:
        return iter(self._outputs)

    def __len__(self) -> int:
        return len(self._outputs)

    def __repr__(self) -> str:
        return f"<grainpipe.Result {list(self._outputs)}>"
