"""Oral meshes in: formats, units, validation, Center frame, closing cuts, procedural cavity."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from implantplan import models
from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.oral_mesh import (
    DEFAULT_CAVITY,
    boundary_loops,
    center_frame,
    close_open_cuts,
    load_default_cavity,
    load_oral_mesh,
    procedural_oral_cavity,
    repair_mesh,
    validate_mesh,
)

CUBE_QUADS_MM = """# a 10 mm cube written with quads
v 0 0 0
v 10 0 0
v 10 10 0
v 0 10 0
v 0 0 10
v 10 0 10
v 10 10 10
v 0 10 10
f 1 4 3 2
f 5 6 7 8
f 1 2 6 5
f 2 3 7 6
f 3 4 8 7
f 4 1 5 8
"""


def test_obj_with_quads_in_mm_becomes_triangles_in_metres(tmp_path):
    path = tmp_path / "cube.obj"
    path.write_text(CUBE_QUADS_MM)
    mesh = load_oral_mesh(path, units="mm")
    assert len(mesh.faces) == 12  # 6 quads -> 12 triangles
    assert mesh.area == pytest.approx(6 * 0.01**2)  # 6 faces of (10 mm)^2
    assert mesh.is_watertight
    assert np.allclose(mesh.bounds, [[0, 0, 0], [0.01, 0.01, 0.01]])
    assert mesh.metadata["implantplan"]["units_in"] == "mm"


@pytest.mark.parametrize("ext", ["stl", "ply", "off", "glb", "obj"])
def test_formats_round_trip(tmp_path, ext):
    cavity = procedural_oral_cavity(angular_resolution=16, axial_resolution=5)
    path = tmp_path / f"cavity.{ext}"
    cavity.mesh.export(path)
    mesh = load_oral_mesh(path, units="m")
    assert mesh.area == pytest.approx(cavity.mesh.area, rel=1e-6)
    assert len(mesh.faces) == len(cavity.mesh.faces)


@pytest.fixture(scope="module")
def scan_obj():
    """The bundled scan as loaded from its OBJ (mm), the reference for the other formats."""
    path = models.model_path("oral/oralCavityMesh.obj")
    return path, load_oral_mesh(path, units="mm")


@pytest.mark.parametrize(
    "file_type, units, tol",
    [
        ("stl", "mm", 1e-8),  # binary STL stores float32: ~7.6e-6 mm at 100 mm
        ("stl_ascii", "mm", 0.0),
        ("ply", "mm", 1e-8),
        ("stl", "m", 1e-8),
        ("ply", "m", 1e-8),
    ],
)
def test_scanner_formats_load_the_same_mesh_as_the_obj(tmp_path, scan_obj, file_type, units, tol):
    path_obj, ref = scan_obj
    raw = trimesh.load(path_obj, process=False, force="mesh")
    if units == "m":
        raw.apply_scale(1e-3)
    path = tmp_path / f"scan.{'stl' if file_type.startswith('stl') else file_type}"
    raw.export(path, file_type=file_type)
    mesh = load_oral_mesh(path, units=units)
    assert mesh.vertices.shape == ref.vertices.shape  # STL's 73,794 corners merged to 12,465
    assert np.abs(mesh.vertices[mesh.faces] - ref.vertices[ref.faces]).max() <= tol
    repairs = mesh.metadata["implantplan"]["repairs"]
    assert repairs["merged_vertices"] == (3 * len(ref.faces) - len(ref.vertices)
                                         if file_type.startswith("stl") else 0)
    assert repairs["flipped_faces"] == 0
    assert mesh.is_winding_consistent


def test_repair_drops_duplicate_faces_and_fixes_a_flipped_face():
    box = trimesh.creation.box()
    faces = np.vstack([box.faces, box.faces[:1]])  # one face twice
    faces[5] = faces[5][::-1]  # one face wound the other way
    out = load_repaired(box.vertices, faces)
    repairs = out.metadata["implantplan"]["repairs"]
    assert repairs["removed_duplicate_faces"] == 1
    assert repairs["flipped_faces"] == 1
    assert len(out.faces) == 12 and out.is_winding_consistent and out.is_watertight


def load_repaired(V, F):
    return repair_mesh(validate_mesh(trimesh.Trimesh(V, F, process=False)))


def test_corrupt_folder_and_unreadable_meshes_are_input_errors(tmp_path, monkeypatch):
    corrupt = tmp_path / "scan.stl"
    corrupt.write_bytes(b"solid x\n\x00\xff\xfe not a mesh" * 40)
    with pytest.raises(InputError, match="mesh: could not read .*corrupt or not a mesh"):
        load_oral_mesh(corrupt)
    with pytest.raises(InputError, match="is a folder; expected a file"):
        load_oral_mesh(tmp_path)
    locked = tmp_path / "locked.stl"
    locked.write_bytes(b"x")
    real_open = open

    def deny(path, *args, **kwargs):  # root reads any file, so deny it the way the OS would
        if str(path) == str(locked):
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr("builtins.open", deny)
    with pytest.raises(InputError, match="cannot read .*Permission denied"):
        load_oral_mesh(locked)


def test_units_must_be_known(tmp_path):
    path = tmp_path / "cube.obj"
    path.write_text(CUBE_QUADS_MM)
    with pytest.raises(InputError, match="units"):
        load_oral_mesh(path, units="cm")


def test_missing_and_empty_files_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_oral_mesh(tmp_path / "nope.stl")
    empty = tmp_path / "empty.obj"
    empty.write_text("# no geometry\n")
    with pytest.raises(InputError, match="empty|no triangle"):
        load_oral_mesh(empty)


def test_nan_vertices_are_an_input_error(tmp_path):
    mesh = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(InputError, match="NaN"):
        validate_mesh(mesh)
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n")
    with pytest.raises(InputError, match="NaN"):
        load_oral_mesh(path)


def test_zero_area_faces_are_removed_and_counted():
    V = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [0, 0, 1]]
    F = [[0, 1, 2], [0, 1, 3], [0, 1, 4], [1, 1, 2]]  # second: collinear; fourth: repeated index
    out = validate_mesh(trimesh.Trimesh(V, F, process=False))
    assert len(out.faces) == 2
    assert out.metadata["implantplan"]["removed_zero_area_faces"] == 2


def test_center_frame_and_bad_axis():
    X = center_frame([0.1, 0.0, 0.1], [-1, 0, 0], x_hint=[0, -1, 0])
    # hand: z = -x_mesh, x = -y_mesh, y = z cross x = +z_mesh
    assert np.allclose(X[:3, :3], [[0, 0, -1], [-1, 0, 0], [0, 1, 0]])
    assert np.allclose(X[:3, 3], [0.1, 0.0, 0.1])
    with pytest.raises(InputError, match="center_z"):
        center_frame([0, 0, 0], [0, 0, 0])
    with pytest.raises(InputError, match="center_origin"):
        center_frame([0, np.nan, 0], [0, 0, 1])


def test_procedural_cavity_is_watertight_seeded_and_matches_its_radius():
    a = procedural_oral_cavity(noise=0.05, seed=7)
    b = procedural_oral_cavity(noise=0.05, seed=7)
    c = procedural_oral_cavity(noise=0.05, seed=8)
    assert a.mesh.is_watertight and a.mesh.is_winding_consistent
    assert a.mesh.volume > 0  # normals out of the air space
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert not np.array_equal(a.mesh.vertices, c.mesh.vertices)
    ring = a.mesh.vertices[:-2]  # the last two are the cap centres
    theta = np.arctan2(ring[:, 1], ring[:, 0])
    assert np.allclose(np.hypot(ring[:, 0], ring[:, 1]), a.radius(theta, ring[:, 2]))


def test_procedural_cylinder_has_the_hand_volume():
    r, length, n = 0.02, 0.05, 256
    cyl = procedural_oral_cavity(
        length=length,
        half_width=r,
        dome_height=r,
        floor_depth=r,
        arch_taper=0.0,
        dome_taper=0.0,
        tongue_bulge=0.0,
        ridge_height=0.0,
        opening_ratio=1.0,
        angular_resolution=n,
        axial_resolution=3,
    )
    # regular n-gon prism: area n/2 r^2 sin(2 pi / n)
    assert cyl.mesh.volume == pytest.approx(0.5 * n * r * r * np.sin(2 * np.pi / n) * length)


def test_close_open_cuts_restores_planar_caps_exactly():
    cavity = procedural_oral_cavity(noise=0.03, seed=1, angular_resolution=48, axial_resolution=9)
    nt = 48
    open_mesh = trimesh.Trimesh(
        cavity.mesh.vertices, cavity.mesh.faces[: -2 * nt], process=False
    )  # drop both end caps
    loops = boundary_loops(open_mesh)
    assert sorted(len(loop) for loop in loops) == [nt, nt]
    closed, info = close_open_cuts(open_mesh)
    assert info["loops"] == 2 and info["cap_triangles"] == 2 * nt
    assert closed.is_watertight and closed.is_winding_consistent
    # a planar loop capped by any fan inside its plane encloses the same volume
    assert closed.volume == pytest.approx(cavity.mesh.volume, rel=1e-9)
    assert boundary_loops(closed) == []


def test_default_cavity_has_one_cut_and_closes():
    mesh, X_WC = load_default_cavity()
    assert mesh.bounds[0] == pytest.approx([0.0537753, -0.0375262, 0.0541203], abs=1e-6)
    loops = boundary_loops(mesh)
    assert [len(loop) for loop in loops] == [330]  # ATTRIBUTION.txt: one loop of 330 edges
    closed, info = close_open_cuts(mesh)
    assert closed.is_watertight
    origin = np.asarray(DEFAULT_CAVITY["center_origin_mm"]) * 1e-3
    assert np.allclose(X_WC[:3, 3], origin)
    assert closed.contains(origin[None, :])[0]
    assert not closed.contains(np.array([[0.0, 0.0, 0.0]]))[0]
