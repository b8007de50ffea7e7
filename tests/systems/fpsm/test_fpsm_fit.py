"""Stage 1 FPSM fit: wall casting with pre-assignment, the exact and paper methods, diagnostics,
open meshes, the real oral mesh and soundness of d_safe against exact containment."""

from __future__ import annotations

import re

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.fit import (
    axis_extent,
    cast_walls,
    first_hits,
    fit_fpsm,
    fit_slice_exact,
    fit_slices_paper,
    ray_engine,
)
from implantplan.systems.fpsm.model import TWO_PI, Fpsm, area, basis_matrix
from implantplan.systems.fpsm.oral_mesh import (
    close_open_cuts,
    load_default_cavity,
    procedural_oral_cavity,
)
from implantplan.systems.frames import apply, invert, rpy_to_rotation, transform

R_CYL, L_CYL, N_SIDES = 0.02, 0.06, 256


def cylinder_cavity():
    return procedural_oral_cavity(
        length=L_CYL,
        half_width=R_CYL,
        dome_height=R_CYL,
        floor_depth=R_CYL,
        arch_taper=0.0,
        dome_taper=0.0,
        tongue_bulge=0.0,
        ridge_height=0.0,
        opening_ratio=1.0,
        angular_resolution=N_SIDES,
        axial_resolution=4,
    )


def centre_pose(z):
    return transform(np.eye(3), [0.0, 0.0, z])


@pytest.fixture(scope="module")
def cavity():
    return procedural_oral_cavity(noise=0.03, seed=5, angular_resolution=96, axial_resolution=48)


@pytest.fixture(scope="module")
def real():
    mesh, X_WC = load_default_cavity()
    return mesh, X_WC, close_open_cuts(mesh)[0]


def test_cylinder_fit_is_radius_minus_margin():
    cyl = cylinder_cavity()
    margin = 0.001
    f = fit_fpsm(
        cyl.mesh, centre_pose(L_CYL / 2), slices=5, control_points=12, samples=96, margin=margin
    )
    assert isinstance(f, Fpsm)
    # walls of the inscribed 256-gon lie between r cos(pi/256) and r: the fit sits below r - margin
    # by at most the sag r (1 - cos(pi/256)) = 1.5 um
    sag = R_CYL * (1 - np.cos(np.pi / N_SIDES))
    assert np.all(f.rho <= R_CYL - margin + 1e-12)
    assert np.all(f.rho >= R_CYL - margin - sag - 1e-9)
    # default z range: axis from -L/2 to L/2, inset by half a slice spacing (h = L / 5)
    h = L_CYL / 5
    assert np.allclose(f.slice_z, np.linspace(-L_CYL / 2 + h / 2, L_CYL / 2 - h / 2, 5))
    assert f.diagnostics["axis_extent_m"] == pytest.approx([-L_CYL / 2, L_CYL / 2], abs=1e-9)
    assert f.diagnostics["penetrating_samples"] == [0] * 5
    assert f.diagnostics["dense_penetration_rate_total"] == 0.0
    # coverage against the own polygon: ((r - margin) / r)^2 up to the sag
    assert np.allclose(f.diagnostics["coverage"], ((R_CYL - margin) / R_CYL) ** 2, atol=2e-3)


def test_pre_assignment_gives_the_same_walls_as_the_whole_mesh(cavity):
    X = centre_pose(0.0)
    slice_z = np.linspace(0.01, 0.07, 4)
    angles = np.arange(40) * TWO_PI / 40
    levels, R, info = cast_walls(cavity.mesh, X, slice_z, angles, per_gap=3, pre_assign=True)
    assert info["pre_assigned"]
    assert len(levels) == 3 * 3 + 1
    assert max(info["triangles_per_slab"]) < info["triangles_total"] / 3
    o = np.repeat(np.stack([np.zeros_like(levels)] * 2 + [levels], 1), angles.size, axis=0)
    d = np.tile(
        np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], 1), (len(levels), 1)
    )
    full = first_hits(cavity.mesh.ray, o, d).reshape(R.shape)
    assert np.allclose(R, full, atol=1e-9)


def test_walls_match_the_analytic_radius_at_mesh_vertex_angles(cavity):
    # at a vertex ring height and a vertex angle the wall is a mesh vertex: distance = R(theta, z)
    nt, nz = 96, 48
    z_ring = np.linspace(0, cavity.length, nz)[[10, 20, 30]]
    angles = np.arange(nt) * TWO_PI / nt
    levels, R, _ = cast_walls(cavity.mesh, centre_pose(0.0), z_ring, angles, per_gap=1)
    expected = cavity.radius(angles[None, :], levels[:, None])
    assert np.allclose(R, expected, atol=1e-7)


def test_numpy_engine_agrees_with_the_default_engine(cavity):
    rng = np.random.default_rng(0)
    o = np.column_stack([np.zeros(30), np.zeros(30), rng.uniform(0.01, 0.07, 30)])
    a = rng.uniform(0, TWO_PI, 30)
    d = np.column_stack([np.cos(a), np.sin(a), np.zeros(30)])
    fast = first_hits(ray_engine(cavity.mesh, "auto"), o, d)
    slow = first_hits(ray_engine(cavity.mesh, "numpy"), o, d)
    assert np.allclose(fast, slow, atol=1e-8)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(3, 12),
    factor=st.integers(1, 6),
    seed=st.integers(0, 2**31 - 1),
)
def test_exact_never_penetrates_at_the_samples(n, factor, seed):
    rng = np.random.default_rng(seed)
    z = n * factor
    wall = rng.uniform(0.5, 30.0, z)
    B = basis_matrix(np.arange(z) * TWO_PI / z, n)
    rho, _ = fit_slice_exact(B, wall)
    assert np.all(B @ rho <= wall)  # exact, no tolerance
    # at least as large as the largest inscribed circle, which is feasible
    assert area(rho) >= np.pi * wall.min() ** 2 * (1 - 1e-9)


def test_exact_on_an_ellipse_covers_almost_all_of_it():
    a, b, z = 30.0, 18.0, 240
    phi = np.arange(z) * TWO_PI / z
    wall = 1.0 / np.sqrt((np.cos(phi) / a) ** 2 + (np.sin(phi) / b) ** 2)
    B = basis_matrix(phi, 16)
    rho, _ = fit_slice_exact(B, wall)
    assert np.all(B @ rho <= wall)
    assert area(rho) / (np.pi * a * b) > 0.97  # hand: the ellipse area is pi a b


def test_paper_descent_on_a_circle_approaches_the_wall_and_never_worsens():
    z, n, c = 150, 15, 20.0  # mm
    wall = np.full((1, z), c)
    wall[0, :10] = 15.0  # a dent: the start circle is radius 15
    B = basis_matrix(np.arange(z) * TWO_PI / z, n)
    rho, info = fit_slices_paper(B, wall)
    start_F = -np.pi * 15.0**2
    assert info["F_aim_mm2"][0] <= start_F
    assert area(rho[0]) > np.pi * 15.0**2 * 1.3  # grew well beyond the start circle
    assert info["iterations"][0] <= 1000


def test_exact_beats_paper_on_area_with_no_sample_penetration(cavity):
    X = centre_pose(0.0)
    kw = dict(slices=6, control_points=12, samples=90, z_range=(0.01, 0.07), check_factor=2)
    exact = fit_fpsm(cavity.mesh, X, method="exact", **kw)
    paper = fit_fpsm(cavity.mesh, X, method="paper", **kw)
    assert exact.diagnostics["penetrating_samples"] == [0] * 6
    assert np.all(area(exact.rho) >= area(paper.rho) * (1 - 1e-3))
    assert paper.settings["paper"]["lambda_pene"] == 30000.0
    assert np.all(np.asarray(exact.diagnostics["coverage"]) > 0.7)


def test_fit_is_deterministic_and_frame_invariant(cavity):
    kw = dict(slices=4, control_points=10, samples=60, z_range=(0.01, 0.07), check_factor=0)
    base = fit_fpsm(cavity.mesh, centre_pose(0.0), **kw)
    again = fit_fpsm(cavity.mesh, centre_pose(0.0), **kw)
    assert np.array_equal(base.rho, again.rho)
    # move the mesh by a rigid transform and give the moved Center frame: same model
    X_WM = transform(rpy_to_rotation([0.3, -0.7, 1.1]), [0.1, -0.2, 0.05])
    moved = cavity.mesh.copy()
    moved.apply_transform(X_WM)
    other = fit_fpsm(moved, X_WM @ centre_pose(0.0), **kw)
    assert np.allclose(other.rho, base.rho, atol=1e-7)


def test_open_mesh_stops_unless_capped_or_closed(cavity):
    faces = cavity.mesh.faces
    centres = cavity.mesh.triangles_center
    hole = (centres[:, 1] < -0.005) & (np.abs(centres[:, 0]) < 0.004)  # a slot in the floor
    hole &= (centres[:, 2] > 0.02) & (centres[:, 2] < 0.06)
    open_mesh = trimesh.Trimesh(cavity.mesh.vertices, faces[~hole], process=False)
    kw = dict(slices=5, control_points=10, samples=72, z_range=(0.01, 0.07), check_factor=2)
    with pytest.raises(InputError, match="meet no wall") as err:
        fit_fpsm(open_mesh, centre_pose(0.0), **kw)
    # slices at z = 10, 25, 40, 55, 70 mm: the slot (z 20..60 mm) opens slices 1-3, around
    # 270 deg (straight down) +- atan(4 mm / ~15 mm) ~ 15 deg
    message = str(err.value)
    assert "slice 0" not in message and "slice 4" not in message
    for j in (1, 2, 3):
        assert re.search(rf"slice {j}: 2[4-6]\d-2[8-9]\d deg", message), message
    assert "--cap-radius-mm" in message and "--close-open-cuts" in message
    capped = fit_fpsm(open_mesh, centre_pose(0.0), cap_radius=0.01, **kw)
    assert capped.diagnostics["rays_without_wall"] > 0
    assert capped.diagnostics["dense_rays_without_wall"] > 0
    closed = fit_fpsm(open_mesh, centre_pose(0.0), close_open_cuts=True, **kw)
    assert closed.diagnostics["rays_without_wall"] == 0
    assert closed.diagnostics["closed_open_cuts"]["loops"] == 1


def test_bad_input_is_named():
    cyl = cylinder_cavity()
    X = centre_pose(L_CYL / 2)
    kw = dict(slices=4, control_points=8, samples=40)
    with pytest.raises(InputError, match="slices"):
        fit_fpsm(cyl.mesh, X, slices=1, control_points=8, samples=40)
    with pytest.raises(InputError, match="samples"):
        fit_fpsm(cyl.mesh, X, slices=4, control_points=8, samples=5)
    with pytest.raises(InputError, match="method"):
        fit_fpsm(cyl.mesh, X, method="magic", **kw)
    with pytest.raises(InputError, match="margin"):
        fit_fpsm(cyl.mesh, X, margin=-1e-3, **kw)
    with pytest.raises(InputError, match="z_range"):
        fit_fpsm(cyl.mesh, X, z_range=(0.01, -0.01), **kw)
    with pytest.raises(InputError, match="center_origin"):
        fit_fpsm(cyl.mesh, X, margin=0.05, **kw)  # margin wider than the cavity
    with pytest.raises(InputError, match="z_range"):  # origin outside: the axis escapes
        fit_fpsm(cyl.mesh, centre_pose(0.2), **kw)
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int), process=False)
    with pytest.raises(InputError, match="empty"):
        fit_fpsm(empty, X, **kw)


def test_real_mesh_needs_cuts_closed_and_then_fits_soundly(real):
    mesh, X_WC, closed = real
    kw = dict(slices=15, control_points=15, samples=150)
    with pytest.raises(InputError, match="meet no wall"):
        fit_fpsm(mesh, X_WC, z_range=(0.005, 0.08), check_factor=0, **kw)
    with pytest.raises(InputError, match="axis leaves the mesh"):
        fit_fpsm(mesh, X_WC, check_factor=0, **kw)  # open at the back too
    f = fit_fpsm(mesh, X_WC, close_open_cuts=True, check_factor=2, **kw)
    d = f.diagnostics
    assert d["penetrating_samples"] == [0] * 15
    assert d["rays_without_wall"] == 0
    assert d["dense_penetration_rate_total"] < 0.01
    assert np.all(np.asarray(d["coverage"]) > 0.3)
    # soundness: points with d_safe > 0.5 mm lie inside the closed mesh (exact containment)
    rng = np.random.default_rng(1)
    n = 20000
    z = rng.uniform(f.slice_z[0], f.slice_z[-1], n)
    r = 1.2 * f.rho.max() * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, TWO_PI, n)
    p_C = np.column_stack([r * np.cos(a), r * np.sin(a), z])
    safe = f.d_safe(p_C) > 0.5e-3
    assert safe.sum() > 2000
    assert np.all(closed.contains(apply(X_WC, p_C[safe])))
    # and points well outside the model's wall are not all free (the check can fail)
    assert not np.all(closed.contains(apply(X_WC, p_C[f.d_safe(p_C) < -5e-3])))


def test_axis_extent_of_the_default_case(real):
    _, X_WC, closed = real
    z_in, z_out = axis_extent(closed, X_WC)
    # hand: the lips' wall on the line y = 0, z = 100 mm is at x ~ 54.6 mm (section plot), and
    # the closing cap at x ~ 140.3 mm; Center z = 140 mm - x
    assert z_out == pytest.approx(0.140 - 0.0546, abs=1e-3)
    assert z_in == pytest.approx(0.140 - 0.1403, abs=1e-3)
    assert np.allclose(invert(X_WC) @ X_WC, np.eye(4))


def test_real_mesh_with_a_cap_radius_records_the_capped_rays(real):
    mesh, X_WC, _ = real
    f = fit_fpsm(
        mesh,
        X_WC,
        slices=8,
        control_points=12,
        samples=120,
        z_range=(0.005, 0.08),
        cap_radius=0.03,
        check_factor=1,
    )
    d = f.diagnostics
    assert d["rays_without_wall"] > 0 and d["dense_rays_without_wall"] > 0
    assert d["penetrating_samples"] == [0] * 8
    # the capped rays point down through the open floor: the curve there is at most the cap
    down = f.radius_at(-np.pi / 2, f.slice_z)
    assert np.all(down <= 0.03 + 1e-12)
    assert f.settings["cap_radius_m"] == 0.03


@pytest.mark.parametrize("method", ["exact", "paper"])
def test_soundness_on_100000_points_paper_scale(real, method):
    mesh, X_WC, closed = real
    f = fit_fpsm(
        mesh,
        X_WC,
        slices=15,
        control_points=15,
        samples=150,
        close_open_cuts=True,
        method=method,
        check_factor=8,
    )
    rng = np.random.default_rng(2)
    kept = []
    total = 0
    while total < 100_000:
        n = 400_000
        z = rng.uniform(f.slice_z[0], f.slice_z[-1], n)
        r = 1.1 * f.rho.max() * np.sqrt(rng.uniform(0, 1, n))
        a = rng.uniform(0, TWO_PI, n)
        p = np.column_stack([r * np.cos(a), r * np.sin(a), z])
        ds = f.d_safe(p)
        kept.append((p[ds > 0], ds[ds > 0]))
        total += int(np.count_nonzero(ds > 0))
    p = np.concatenate([k[0] for k in kept])[:100_000]
    ds = np.concatenate([k[1] for k in kept])[:100_000]
    outside = ~closed.contains(apply(X_WC, p))
    assert np.count_nonzero(outside & (ds > 0.5e-3)) == 0  # the target
    assert outside.mean() < 1e-3  # measured 0 of 100,000 for both methods
