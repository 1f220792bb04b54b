"""Interop test of the mesh exports (`vtu`, `vtk`, `xdmf`, `abaqus` .inp, `gmsh` .msh) against
a real run of `pipe` ($PIPE): a 9x7x5 label image with anisotropic spacing, a non-zero origin
and periodic x and z axes (made here with numpy and imported with `import.raw`), a field
imported from the same voxels, and a packing imported from a CSV of known spheres.

The references are the numpy arrays written here, never grainpipe's own output:
- meshio.read on every file: the cell type, one hexahedron per voxel of the selected
  phases, cell data `phase` equal to the labels byte for byte (uint8), points at
  origin + index * spacing, shared corners once (the point count is the number of distinct
  corners of the selected voxels), each cell's first and seventh node at its voxel's lower
  and upper corner;
- pyvista (VTK 9) on .vtu/.vtk/.xdmf agrees with meshio (points, cells, cell data);
- the Abaqus deck's element and node sets, the Gmsh physical groups (meshio, and the `gmsh`
  module when it is installed);
- packings: one vertex per sphere at the CSV's centres with its radius.
"""

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

import meshio  # noqa: E402
import pyvista as pv  # noqa: E402
import vtk  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
PIPE = str((ROOT / os.environ.get("PIPE", "target/release/pipe")).resolve())

NX, NY, NZ = 9, 7, 5
SPACING = np.array([2e-6, 3e-6, 5e-6])
ORIGIN = np.array([1e-3, -2e-4, 5e-5])
# (z, y, x) labels 0..2: every phase on every face.
Z, Y, X = np.meshgrid(np.arange(NZ), np.arange(NY), np.arange(NX), indexing="ij")
LABELS = ((X + 2 * Y + 3 * Z + (X * Y) % 2) % 3).astype(np.uint8)
SPHERES = np.array([[10.0, 20.0, 30.0, 5.0], [40.0, 25.0, 12.5, 7.5], [80.0, 80.0, 80.0, 10.0]])

PIPELINE = """name: mesh-interop
stages:
  - id: scan
    use: import.raw
    with:
      path: labels.raw
      dims: [9, 7, 5]
      dtype: u8
      spacing: [2 um, 3 um, 5 um]
      origin: [1 mm, -0.2 mm, 0.05 mm]
      periodic: [true, false, true]
  - id: heat
    use: import.raw
    with: { path: values.raw, dims: [9, 7, 5], dtype: f64, spacing: [2 um, 3 um, 5 um],
            origin: [1 mm, -0.2 mm, 0.05 mm], as: field }
  - id: beads
    use: import.packing
    with: { path: spheres.csv, unit: um, box: [100 um, 100 um, 100 um] }
  - id: ball
    use: import.raw
    with: { path: ball.raw, dims: [32, 32, 32], dtype: u8, spacing: [1 um, 1 um, 1 um],
            origin: [0.5 mm, 0 mm, 0 mm] }
  - id: lam
    use: import.raw
    with: { path: lam.raw, dims: [7, 5, 10], dtype: u8, spacing: [2 um, 3 um, 5 um] }
export:
  - { from: scan.image, to: out/all.vtu }
  - { from: scan.image, to: out/sel.vtu, with: { phases: [phase1, phase2] } }
  - { from: scan.image, to: out/b64z.vtu, with: { encoding: binary, compression: 6, phases: [2] } }
  - { from: scan.image, to: out/b64.vtu, with: { encoding: binary } }
  - { from: scan.image, to: out/rawz.vtu, with: { compression: 1 } }
  - { from: scan.image, to: out/asc.vtu, with: { encoding: ascii, phases: [phase1] } }
  - { from: scan.image, to: out/all.vtk }
  - { from: scan.image, to: out/asc.vtk, with: { encoding: ascii, phases: [phase1] } }
  - { from: scan.image, to: out/hex.xdmf, with: { phases: [phase2, phase1] } }
  - { from: scan.image, to: out/img.xdmf, with: { mesh: image } }
  - { from: scan.image, to: out/m.inp, with: { phases: [phase1, phase2] } }
  - { from: scan.image, to: out/m.msh }
  - { from: heat.field, to: out/heat.vtu }
  - { from: heat.field, to: out/heat.vtk }
  - { from: heat.field, to: out/heat.xdmf }
  - { from: beads.packing, to: out/beads.vtu }
  - { from: beads.packing, to: out/beads.vtk }
  - { from: beads.packing, to: out/beads.xdmf }
  - { from: ball.image, to: out/ball.vtu, with: { mesh: surface } }
  - { from: ball.image, to: out/ball.msh, with: { mesh: surface } }
  - { from: ball.image, to: out/ball_smooth.vtu, with: { mesh: surface, smooth: 10 } }
  - { from: ball.image, to: out/ball_dec.vtu, with: { mesh: surface, smooth: 10, decimate: 0.25 } }
  - { from: ball.image, to: out/ball_dec.msh, with: { mesh: surface, smooth: 10, decimate: 0.25 } }
  - { from: scan.image, to: out/surf.vtu, with: { mesh: surface, encoding: binary, compression: 6 } }
  - { from: scan.image, to: out/surf.msh, with: { mesh: surface } }
  - { from: lam.image, to: out/lam.vtu, with: { mesh: surface, encoding: ascii } }
  - { from: lam.image, to: out/lam_binder.msh, with: { mesh: surface, phases: [phase2] } }
"""

VALUES = (X * 100.0 + Y * 10.0 + Z + 0.25).astype(np.float64)
# A ball of label 1, radius 12 voxels (1 um), centred in a 32^3 box: voxel in when its
# centre is.
BALL_N, BALL_R = 32, 12.0
_c = np.arange(BALL_N) + 0.5 - BALL_N / 2
BALL = ((_c[:, None, None] ** 2 + _c[None, :, None] ** 2 + _c[None, None, :] ** 2) < BALL_R**2).astype(
    np.uint8
)
# A laminate along z (7x5x10, spacing 2, 3, 5 um): 0 below z = 3, 1 up to z = 7, 2 above.
LAM = np.zeros((10, 5, 7), np.uint8)
LAM[3:7] = 1
LAM[7:] = 2


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    cwd = tmp_path_factory.mktemp("mesh")
    LABELS.tofile(cwd / "labels.raw")
    VALUES.astype("<f8").tofile(cwd / "values.raw")
    BALL.tofile(cwd / "ball.raw")
    LAM.tofile(cwd / "lam.raw")
    with open(cwd / "spheres.csv", "w") as f:
        f.write("x,y,z,r\n")
        for s in SPHERES:
            f.write(",".join(repr(float(v)) for v in s) + "\n")
    (cwd / "mesh.yaml").write_text(PIPELINE)
    subprocess.run([PIPE, "run", "mesh.yaml", "--quiet", "--no-cache"], cwd=cwd, check=True)
    return cwd / "out"


def selected(phases):
    """Voxels of the phases in cell order (x fastest), their labels, lower corners [m] and
    the number of distinct corners they touch."""
    mask = np.isin(LABELS, phases)
    z, y, x = np.nonzero(mask)  # C order of (z, y, x): x fastest, as the cells
    lower = ORIGIN + np.stack([x, y, z], axis=1) * SPACING
    corners = set()
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                corners.update(zip((x + dx).tolist(), (y + dy).tolist(), (z + dz).tolist()))
    return LABELS[mask], lower, len(corners)


def check_hex(points, conn, labels, phases):
    want_labels, lower, ncorners = selected(phases)
    assert conn.shape == (len(want_labels), 8)
    assert len(points) == ncorners  # shared corners are one point
    # Points at origin + index * spacing.
    idx = (points - ORIGIN) / SPACING
    np.testing.assert_allclose(idx, np.round(idx), atol=1e-9)
    np.testing.assert_allclose(points[conn[:, 0]], lower, rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(points[conn[:, 6]], lower + SPACING, rtol=1e-14, atol=1e-18)
    if labels is not None:
        assert labels.dtype == np.uint8
        assert labels.tobytes() == want_labels.tobytes()


def vtk_read(path):
    """pyvista's dataset of a file; .xdmf through VTK's vtkXdmfReader directly (pyvista's
    XdmfReader wrapper needs time steps, which these files do not have)."""
    if str(path).endswith(".xdmf"):
        r = vtk.vtkXdmfReader()
        r.SetFileName(str(path))
        r.Update()
        g = pv.wrap(r.GetOutputDataObject(0))
    else:
        g = pv.read(path)
    return g[0] if isinstance(g, pv.MultiBlock) else g


def check_blocks(m, phases):
    """FE decks: one cell block per phase (in `phases` order), each holding the voxels of
    its phase in voxel order."""
    assert [c.type for c in m.cells] == ["hexahedron"] * len(phases)
    for block, p in zip(m.cells, phases):
        check_hex_points_only(m.points, block.data, [p])
    _, _, ncorners = selected(phases)
    assert len(m.points) == ncorners


def check_hex_points_only(points, conn, phases):
    _, lower, _ = selected(phases)
    assert conn.shape == (len(lower), 8)
    np.testing.assert_allclose(points[conn[:, 0]], lower, rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(points[conn[:, 6]], lower + SPACING, rtol=1e-14, atol=1e-18)


def meshio_hex(path, phases, label_key="phase"):
    m = meshio.read(path)
    assert [c.type for c in m.cells] == ["hexahedron"]
    labels = m.cell_data[label_key][0].ravel() if label_key else None
    check_hex(m.points, m.cells[0].data, labels, phases)
    return m


@pytest.mark.parametrize(
    "name,phases",
    [
        ("all.vtu", [0, 1, 2]),
        ("sel.vtu", [1, 2]),
        ("b64z.vtu", [2]),
        ("b64.vtu", [0, 1, 2]),
        ("rawz.vtu", [0, 1, 2]),
        ("asc.vtu", [1]),
        ("all.vtk", [0, 1, 2]),
        ("asc.vtk", [1]),
        ("hex.xdmf", [1, 2]),
    ],
)
def test_meshio_and_pyvista_read_the_voxel_mesh(out, name, phases):
    m = meshio_hex(out / name, phases)
    g = vtk_read(out / name)
    assert g.n_cells == len(m.cells[0].data)
    np.testing.assert_array_equal(np.asarray(g.points, dtype=float), m.points)
    vtk_labels = np.asarray(g.cell_data["phase"]).ravel()
    assert vtk_labels.dtype == np.uint8
    assert vtk_labels.tobytes() == m.cell_data["phase"][0].tobytes()
    assert set(np.asarray(g.celltypes).tolist()) == {pv.CellType.HEXAHEDRON}
    np.testing.assert_array_equal(g.cells.reshape(-1, 9)[:, 1:], m.cells[0].data)
    if name.endswith(".vtu"):
        # The phase table as numeric field data (meshio reads no string arrays).
        assert {k: int(np.ravel(v)[0]) for k, v in m.field_data.items() if k.startswith("phase.")} == {
            f"phase.{'pore' if p == 0 else f'phase{p}'}": p for p in phases
        }
        assert list(np.ravel(m.field_data["periodic"])) == [1, 0, 1]


def test_xdmf_image_is_a_corect_mesh_that_vtk_reads(out):
    g = vtk_read(out / "img.xdmf")
    assert tuple(g.dimensions) == (NX + 1, NY + 1, NZ + 1)
    np.testing.assert_allclose(g.origin, ORIGIN, rtol=1e-14)
    np.testing.assert_allclose(g.spacing, SPACING, rtol=1e-14)
    assert np.asarray(g.cell_data["phase"]).tobytes() == LABELS.tobytes()
    # meshio 5 reads XDMF geometry of type XY/XYZ only: the image layout is for ParaView/VTK.
    # (meshio 5.3 reports it by SystemExit from its format guesser.)
    with pytest.raises((Exception, SystemExit)):
        meshio.read(out / "img.xdmf")


def test_field_as_cell_data(out):
    for name in ["heat.vtu", "heat.vtk", "heat.xdmf"]:
        m = meshio_hex(out / name, [0, 1, 2], label_key=None)
        (key,) = m.cell_data  # the field, named by import.raw
        v = m.cell_data[key][0].ravel()
        assert v.dtype.kind == "f" and v.dtype.itemsize == 8  # legacy .vtk: big-endian
        np.testing.assert_array_equal(v, VALUES.ravel())
        g = vtk_read(out / name)
        np.testing.assert_array_equal(np.asarray(g.cell_data[key]).ravel(), v)


def test_packing_as_vertices(out):
    for name in ["beads.vtu", "beads.vtk", "beads.xdmf"]:
        m = meshio.read(out / name)
        assert [c.type for c in m.cells] == ["vertex"]
        np.testing.assert_array_equal(m.cells[0].data.ravel(), np.arange(len(SPHERES)))
        np.testing.assert_allclose(m.points, SPHERES[:, :3] * 1e-6, rtol=1e-14)
        np.testing.assert_allclose(np.ravel(m.point_data["radius"]), SPHERES[:, 3] * 1e-6, rtol=1e-14)
        np.testing.assert_array_equal(np.ravel(m.point_data["body_id"]), np.arange(len(SPHERES)))
        g = vtk_read(out / name)
        np.testing.assert_array_equal(np.asarray(g.points, dtype=float), m.points)
        np.testing.assert_array_equal(np.asarray(g.point_data["radius"]), np.ravel(m.point_data["radius"]))


def test_abaqus_deck_in_meshio(out):
    m = meshio.read(out / "m.inp")
    check_blocks(m, [1, 2])
    # Element sets per phase, in the order of `phases`.
    for name, label in [("phase1", 1), ("phase2", 2)]:
        ids = np.concatenate(m.cell_sets[name])
        assert len(ids) == int((LABELS == label).sum())
    np.testing.assert_array_equal(m.cell_sets["phase1"][0], np.arange(int((LABELS == 1).sum())))
    np.testing.assert_array_equal(m.cell_sets["phase2"][1], np.arange(int((LABELS == 2).sum())))
    # Face node sets: all points on each face plane of the box.
    upper = ORIGIN + SPACING * [NX, NY, NZ]
    for axis, (lo, hi) in enumerate([("XMIN", "XMAX"), ("YMIN", "YMAX"), ("ZMIN", "ZMAX")]):
        for name, at in [(lo, ORIGIN[axis]), (hi, upper[axis])]:
            on = np.nonzero(np.isclose(m.points[:, axis], at, rtol=0, atol=1e-3 * SPACING[axis]))[0]
            np.testing.assert_array_equal(np.sort(m.point_sets[name]), on)
    # Periodic pairs on x and z: the i-th nodes differ by the box length along the axis.
    for axis, a in [(0, "X"), (2, "Z")]:
        lo, hi = m.point_sets[f"PERIODIC_{a}_LO"], m.point_sets[f"PERIODIC_{a}_HI"]
        assert len(lo) == len(hi) > 0
        d = m.points[hi] - m.points[lo]
        np.testing.assert_allclose(d[:, axis], SPACING[axis] * [NX, NY, NZ][axis], rtol=1e-12)
        np.testing.assert_allclose(np.delete(d, axis, axis=1), 0, atol=1e-18)
    assert "PERIODIC_Y_LO" not in m.point_sets


def test_gmsh_file_in_meshio_and_gmsh(out):
    m = meshio.read(out / "m.msh")
    check_blocks(m, [0, 1, 2])
    # Physical tag = label + 1, named after the phase.
    assert {k: list(v) for k, v in m.field_data.items()} == {
        "pore": [1, 3], "phase1": [2, 3], "phase2": [3, 3]
    }
    for block, label in zip(m.cell_data["gmsh:physical"], [0, 1, 2]):
        assert (block == label + 1).all() and len(block) == int((LABELS == label).sum())
    try:
        import gmsh
    except ImportError as e:  # pragma: no cover - gmsh wheels exist for the CI platforms
        pytest.skip(f"the gmsh module is not installed from PyPI here: {e}")
    gmsh.initialize(["-v", "0"])
    try:
        gmsh.open(str(out / "m.msh"))
        groups = gmsh.model.getPhysicalGroups(3)
        assert sorted(groups) == [(3, 1), (3, 2), (3, 3)]
        for dim, tag in groups:
            assert gmsh.model.getPhysicalName(dim, tag) == {1: "pore", 2: "phase1", 3: "phase2"}[tag]
            (entity,) = gmsh.model.getEntitiesForPhysicalGroup(dim, tag)
            types, elems, _ = gmsh.model.mesh.getElements(dim, entity)
            assert list(types) == [5]  # 8-node hexahedron
            assert len(elems[0]) == int((LABELS == tag - 1).sum())
        tags, coords, _ = gmsh.model.mesh.getNodes()
        assert len(tags) == (NX + 1) * (NY + 1) * (NZ + 1)
    finally:
        gmsh.finalize()


# --- interface surfaces (`mesh: surface`) ---------------------------------------------------


def surface_of(path):
    """meshio triangles of a surface .vtu: points, triangles, interface ids, (a, b) per
    triangle, and the interface table {name: (id, a, b)}."""
    m = meshio.read(path)
    assert [c.type for c in m.cells] == ["triangle"]
    tri = m.cells[0].data
    cd = {k: np.ravel(v[0]) for k, v in m.cell_data.items()}
    table = {k[len("interface."):]: tuple(int(x) for x in np.ravel(v)) for k, v in m.field_data.items()
             if k.startswith("interface.")}
    return m.points, tri, cd["interface"], np.stack([cd["phase_a"], cd["phase_b"]], 1), table


def area_volume(points, tri):
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    return area, vol


def directed_edges(tri):
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    return e


def test_surface_of_a_ball_in_meshio_and_pyvista(out):
    """The ball's pore|phase1 interface: enclosed volume within 4 pi r^2 h / 8 of 4/3 pi r^3
    (the surface's mean offset from the sphere is below h/8), area 20-32 % above 4 pi r^2
    (marching tetrahedra's bias on binary voxels); closed: every directed edge once and its
    reverse once, Euler characteristic 2. Smoothed (10 Taubin iterations): volume within
    0.5 %, area within 8 %."""
    points, tri, iface, pairs, table = surface_of(out / "ball.vtu")
    assert table == {"exterior|pore": (1, -1, 0), "pore|phase1": (2, 0, 1)}
    for name, (k, a, b) in table.items():
        assert ((pairs[iface == k]) == [a, b]).all()
    sph = tri[iface == 2]
    h, r = 1e-6, BALL_R * 1e-6
    area, vol = area_volume(points - [0.5e-3, 0, 0], sph)
    assert abs(vol - 4 / 3 * np.pi * r**3) <= 4 * np.pi * r**2 * h / 8
    assert 0.20 <= area / (4 * np.pi * r**2) - 1 <= 0.32
    e = directed_edges(sph)
    fwd = {tuple(x) for x in e}
    assert len(fwd) == len(e) and {(b, a) for a, b in fwd} == fwd
    nv = len(np.unique(sph))
    assert nv - len(e) // 2 + len(sph) == 2
    # Points welded: no two equal.
    assert len(np.unique(points, axis=0)) == len(points)
    # pyvista (VTK 9) reads the same triangles.
    g = pv.read(out / "ball.vtu")
    assert g.n_cells == len(tri) and (g.celltypes == 5).all()
    assert np.array_equal(g.cell_data["interface"], iface)
    p2, t2, i2, _, _ = surface_of(out / "ball_smooth.vtu")
    a2, v2 = area_volume(p2 - [0.5e-3, 0, 0], t2[i2 == 2])
    assert abs(v2 / vol - 1) < 5e-3 and abs(a2 / (4 * np.pi * r**2) - 1) < 0.08


@pytest.mark.parametrize("name", ["ball", "surf", "ball_dec"])
def test_surface_msh_matches_the_vtu_in_meshio_and_gmsh(out, name):
    """The .msh holds the .vtu's triangles: per physical group (= interface id, named
    `<a>|<b>`) the same count; the element data phase_a/phase_b equal the .vtu's."""
    points, tri, iface, pairs, table = surface_of(out / f"{name}.vtu")
    m = meshio.read(out / f"{name}.msh")
    assert {k: list(v) for k, v in m.field_data.items()} == {n: [k, 2] for n, (k, _, _) in table.items()}
    assert all(c.type == "triangle" for c in m.cells)
    ids = np.concatenate(m.cell_data["gmsh:physical"])
    assert np.array_equal(ids, iface)
    assert np.array_equal(np.concatenate(m.cell_data["phase_a"]).astype(int), pairs[:, 0])
    assert np.array_equal(np.concatenate(m.cell_data["phase_b"]).astype(int), pairs[:, 1])
    assert len(m.points) == len(points)
    try:
        import gmsh
    except ImportError as e:  # pragma: no cover
        pytest.skip(f"the gmsh module is not installed from PyPI here: {e}")
    gmsh.initialize(["-v", "0"])
    try:
        gmsh.open(str(out / f"{name}.msh"))
        groups = gmsh.model.getPhysicalGroups(2)
        assert sorted(groups) == [(2, k) for k, _, _ in sorted(table.values())]
        names = {k: n for n, (k, _, _) in table.items()}
        for dim, tag in groups:
            assert gmsh.model.getPhysicalName(dim, tag) == names[tag]
            (entity,) = gmsh.model.getEntitiesForPhysicalGroup(dim, tag)
            types, elems, _ = gmsh.model.mesh.getElements(dim, entity)
            assert list(types) == [2] and len(elems[0]) == int((iface == tag).sum())
    finally:
        gmsh.finalize()


def test_three_phase_surface_closes_around_every_phase(out):
    """The 9x7x5 three-phase image: all six pairs (with the exterior) present, and each
    phase's boundary, oriented out of it (the normal points out of b into a), is closed:
    every directed edge matched by its reverse."""
    points, tri, iface, pairs, table = surface_of(out / "surf.vtu")
    assert sorted(table) == sorted(["exterior|pore", "exterior|phase1", "exterior|phase2",
                                    "pore|phase1", "pore|phase2", "phase1|phase2"])
    for p in [0, 1, 2]:
        t = np.concatenate([tri[pairs[:, 1] == p], tri[pairs[:, 0] == p][:, [0, 2, 1]]])
        e = directed_edges(t)
        fwd, cnt = np.unique(e, axis=0, return_counts=True)
        rev, cnt_r = np.unique(e[:, ::-1], axis=0, return_counts=True)
        assert np.array_equal(fwd, rev) and np.array_equal(cnt, cnt_r)


def test_laminate_interfaces_on_their_planes(out):
    """The laminate: away from the side walls, pore|phase1 is 8 (nx-1)(ny-1) triangles on
    z = 3 dz and phase1|phase2 as many on z = 7 dz, normals -z (out of the higher label into
    the lower); `phases: [phase2]` keeps the interfaces touching phase2 only."""
    points, tri, iface, pairs, table = surface_of(out / "lam.vtu")
    sp = np.array([2e-6, 3e-6, 5e-6])
    for name, zk in [("pore|phase1", 3), ("phase1|phase2", 7)]:
        k, a, b = table[name]
        t = tri[iface == k]
        c = points[t]
        u = c[:, :, :2] / sp[:2]
        inner = ((u > 0.5 - 1e-9) & (u < np.array([7, 5]) - 0.5 + 1e-9)).all(axis=(1, 2))
        assert inner.sum() == 8 * 6 * 4
        assert np.allclose(c[inner][:, :, 2], zk * sp[2], rtol=0, atol=1e-15)
        n = np.cross(c[inner][:, 1] - c[inner][:, 0], c[inner][:, 2] - c[inner][:, 0])
        assert (n[:, 2] < 0).all()
        assert np.isclose(0.5 * np.abs(n[:, 2]).sum(), 6 * 4 * sp[0] * sp[1], rtol=1e-9)
    assert "pore|phase2" not in table
    m = meshio.read(out / "lam_binder.msh")
    assert sorted(m.field_data) == ["exterior|phase2", "phase1|phase2"]


def test_decimated_ball_is_a_closed_quarter(out):
    """`decimate: 0.25` after `smooth: 10`: the sphere keeps a quarter of the smoothed
    sphere's triangles (+1 %), stays closed (each directed edge once, its reverse once, Euler
    characteristic 2) and welded (every point used, none repeated), its volume within 1 %
    of the smoothed one."""
    p1, t1, i1, _, _ = surface_of(out / "ball_smooth.vtu")
    p2, t2, i2, _, table = surface_of(out / "ball_dec.vtu")
    assert table["pore|phase1"][0] == 2
    s1, s2 = t1[i1 == 2], t2[i2 == 2]
    assert len(s2) <= 0.2525 * len(s1)
    e = directed_edges(s2)
    fwd = {tuple(x) for x in e}
    assert len(fwd) == len(e) and {(b, a) for a, b in fwd} == fwd
    assert len(np.unique(s2)) - len(e) // 2 + len(s2) == 2
    assert len(np.unique(t2)) == len(p2) and len(np.unique(p2, axis=0)) == len(p2)
    _, v1 = area_volume(p1 - [0.5e-3, 0, 0], s1)
    _, v2 = area_volume(p2 - [0.5e-3, 0, 0], s2)
    assert abs(v2 / v1 - 1) < 0.01
