"""Stage 2 placement (Eq. 14-22): frames, objectives, PSO, the grid check and the paper's
cylinder example, with the expected figures derived by hand below."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from implantplan.systems import seeds
from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.placement.planner import (
    PlacementProblem,
    feeding_lines,
    hole_frame,
    place_instrument,
    pso,
    tool_frames,
    verify_by_grid,
)
from implantplan.systems.safety import SafetySpec

MM = 1e-3
HOLE = np.array([0.0, -50.0, 50.0]) * MM
AXIS = np.array([0.0, 1.0, 0.0])
D12 = 31 * MM

# The cylinder check (paper Sec. 5.3, Fig. 19, Table 2), by hand.
#
# Eq. 16 with D_hz = (0, 1, 0): D_hx = (0, 0, 1); Eq. 17: R_ch = (x, y, z) = ((0,0,1), (1,0,0),
# (0,1,0)). Eq. 18: the Tool origin is T = t_ch + d_T D_hz = (0, d_T - 50, 50) mm. Eq. 19 at
# theta_T = 0: D = R_ch (1, 0, 0) = (0, 0, 1), straight out of the mouth; P1 = T + r D and
# P2 = T + r D - d12 D_hz = (0, d_T - 81, 50 + r) mm. A vertical line at distance |y| from the
# axis has d_safe = R - |y| at every sample, so Eq. 13 gives f = 0.5 d + 0.5 d = d, and both
# lines start at the same height, so m1 = m2 and Eq. 14/21/22 weigh them equally. Any tilt
# (theta_T != 0) moves every crossing further from the axis, so theta_T = 0 is optimal.
#
# Rod radius r = 0: d1 = 50 - |d_T - 50|, d2 = 50 - |d_T - 81| (mm).
#   On [50, 81]: d1 = 100 - d_T, d2 = d_T - 31, so d1 + d2 = 69 (constant); outside it the sum
#   is smaller (2 d_T - 31 below 50, 231 - 2 d_T above 81).
#   Eq. 14 maximizes sqrt(d1) + sqrt(d2) at fixed sum: d1 = d2 = 34.5 -> d_T = 65.5 mm,
#   F = -sqrt(34.5 mm).
#   Eq. 21 maximizes d1 + d2: flat at 69 / 2 on the whole of [50, 81].
#   Eq. 22 maximizes d1^2 + d2^2 at fixed sum: at an end of the segment. d_T = 50 gives
#   (50, 19) and d_T = 81 gives (19, 50): the SAME value 2861 mm^2. The paper's "81" is one of
#   two tied optima when r = 0 (it used r = 6 mm for Table 2, where 81 is the unique optimum).
# Rod radius r = 6 mm: line1 against the 44 mm shrunk cylinder: d1 = 44 - |d_T - 50|,
#   d2 = 50 - |d_T - 81|. On [50, 81]: d1 = 94 - d_T, d2 = d_T - 31, sum 63 (constant).
#   Eq. 14: d1 = d2 = 31.5 -> d_T = 62.5 mm, F = -sqrt(31.5 mm).
#   Eq. 21: flat at 63 / 2 on [50, 81].
#   Eq. 22: d_T = 50 -> (44, 19): 2297; d_T = 81 -> (13, 50): 2669 -> d_T = 81 mm.


@pytest.fixture(scope="module")
def cyl():
    return Fpsm.cylinder(50 * MM, 0.0, 100 * MM, 11)


def test_hole_frame_eq16_and_degenerate_axes():
    X = hole_frame(HOLE, AXIS)
    np.testing.assert_allclose(X[:3, :3], [[0, 1, 0], [0, 0, 1], [1, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(X[:3, 3], HOLE)
    # D_hz = +-Center x: Eq. 16 is 0/0; the rule picks D_hx = Center z.
    for sx in (1.0, -1.0):
        X = hole_frame(HOLE, [sx, 0, 0])
        np.testing.assert_allclose(X[:3, 0], [0, 0, 1], atol=1e-15)
        np.testing.assert_allclose(X[:3, 1], [0, -sx, 0], atol=1e-15)  # z x x
    # D_hz_y = 0 but D_hz_z != 0: the limit from D_hz_y > 0, D_hx = (0, -sign(D_hz_z), 0).
    X = hole_frame(HOLE, [0, 0, 2.0])
    np.testing.assert_allclose(X[:3, 0], [0, -1, 0], atol=1e-15)


@settings(max_examples=60, deadline=None)
@given(st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 1e-3))
def test_hole_frame_matches_eq16_and_is_a_rotation(axis):
    X = hole_frame(HOLE, axis)
    R = X[:3, :3]
    assert np.all(np.isfinite(R))
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    z = np.asarray(axis) / np.linalg.norm(axis)
    np.testing.assert_allclose(R[:, 2], z, atol=1e-12)
    assert abs(R[0, 0]) < 1e-12  # D_hx in Center's YZ plane
    if abs(z[1]) > 1e-6:  # Eq. 16 as printed
        n = np.hypot(z[1], z[2])
        np.testing.assert_allclose(
            R[1:, 0], [-z[2] / z[1] * abs(z[1]) / n, abs(z[1]) / n], atol=1e-9
        )


def test_feeding_lines_eq19_by_hand():
    X = hole_frame(HOLE, AXIS)
    lines = feeding_lines(X, [65.5 * MM], [0.0], 6 * MM, D12)
    np.testing.assert_allclose(lines.tool[0], [0, 15.5 * MM, 50 * MM], atol=1e-15)
    np.testing.assert_allclose(lines.direction[0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(lines.start1[0], [0, 15.5 * MM, 56 * MM], atol=1e-15)
    np.testing.assert_allclose(lines.start2[0], [0, -15.5 * MM, 56 * MM], atol=1e-15)
    # theta_T = 90 deg turns the rod to Hole y = Center x; the same as Tool x of Eq. 18.
    X_CT = tool_frames(X, 65.5 * MM, np.pi / 2)
    lines = feeding_lines(X, [65.5 * MM], [np.pi / 2], 0.0, D12)
    np.testing.assert_allclose(lines.direction[0], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(X_CT[:3, 0], lines.direction[0], atol=1e-15)
    np.testing.assert_allclose(X_CT[:3, 3], lines.tool[0], atol=1e-15)


@pytest.mark.parametrize(
    "rod_mm, d_T_mm, F_expected",
    [(0.0, 65.5, -np.sqrt(34.5 * MM)), (6.0, 62.5, -np.sqrt(31.5 * MM))],
)
def test_cylinder_eq14_optimum(cyl, rod_mm, d_T_mm, F_expected):
    p = place_instrument(cyl, HOLE, AXIS, rod_radius=rod_mm * MM, implant_length=D12, seed=0)
    assert p.valid and p.reason == ""
    assert p.d_T == pytest.approx(d_T_mm * MM, abs=0.01 * MM)
    assert p.theta_T == pytest.approx(0.0, abs=np.deg2rad(0.01))
    # the PSO compares F rounded to seeds.OBJECTIVE_BITS (the same path on every machine): it
    # finds the optimum to that step
    step = abs(F_expected) * 2.0 ** (1 - seeds.OBJECTIVE_BITS)
    assert p.F_safe == pytest.approx(F_expected, abs=step)
    # d1 = d2 at the optimum (both lines equally far from the walls), to 10 um: F is flat to
    # second order there, so its rounding step leaves the balance a few um
    assert p.f_safe_line1 == pytest.approx(p.f_safe_line2, abs=1e-5)
    # PSO within 0.1 mm / 0.1 deg of the exhaustive grid optimum
    assert p.grid["distance_d_T"] <= 0.1 * MM
    assert p.grid["distance_theta_T"] <= np.deg2rad(0.1)
    assert p.grid["F_pso_minus_grid"] <= step
    assert p.iterations >= 40 and p.evaluations == 30 * (p.iterations + 1)
    assert np.all(np.diff(p.history) <= 0)  # the global best never gets worse


@pytest.mark.parametrize("rod_mm, flat_F", [(0.0, -34.5 * MM), (6.0, -31.5 * MM)])
def test_cylinder_eq21_is_flat_on_50_81(cyl, rod_mm, flat_F):
    X = hole_frame(HOLE, AXIS)
    problem = PlacementProblem(cyl, X, rod_mm * MM, D12, "eq21")
    d = np.linspace(50, 81, 32) * MM
    F = problem(np.stack([d, np.zeros_like(d)], axis=1))
    np.testing.assert_allclose(F, flat_F, atol=1e-15)
    outside = problem(np.array([[49.0 * MM, 0.0], [82.0 * MM, 0.0], [65 * MM, 0.05]]))
    assert np.all(outside > flat_F + 1e-6)
    p = place_instrument(
        cyl, HOLE, AXIS, rod_radius=rod_mm * MM, implant_length=D12, objective="eq21", verify=False
    )
    assert 50 * MM - 1e-9 <= p.d_T <= 81 * MM + 1e-9
    assert p.F_safe == pytest.approx(flat_F, abs=abs(flat_F) * 2.0 ** (1 - seeds.OBJECTIVE_BITS))


def test_cylinder_eq22(cyl):
    X = hole_frame(HOLE, AXIS)
    # r = 6 mm: unique optimum at d_T = 81 mm with F = -(13^2 + 50^2) / 2 mm^2
    problem = PlacementProblem(cyl, X, 6 * MM, D12, "eq22")
    g = verify_by_grid(problem, [31 * MM, -np.pi], [131 * MM, np.pi])
    assert g["x"][0] == pytest.approx(81 * MM, abs=0.01 * MM)
    assert g["x"][1] == pytest.approx(0.0, abs=1e-3)
    assert g["F"] == pytest.approx(-(13**2 + 50**2) / 2 * MM**2, rel=1e-9)
    p = place_instrument(
        cyl,
        HOLE,
        AXIS,
        rod_radius=6 * MM,
        implant_length=D12,
        objective="eq22",
        seed=0,
        verify=False,
    )
    assert p.valid
    # r = 0: d_T = 50 and d_T = 81 tie at -(50^2 + 19^2) / 2 mm^2
    problem = PlacementProblem(cyl, X, 0.0, D12, "eq22")
    F = problem(np.array([[50 * MM, 0.0], [81 * MM, 0.0], [65.5 * MM, 0.0]]))
    np.testing.assert_allclose(F[:2], -(50**2 + 19**2) / 2 * MM**2, rtol=1e-12)
    assert F[2] > F[0]  # the Eq. 14 optimum is not an Eq. 22 optimum


def test_eq22_keeps_the_sign_of_collisions(cyl):
    # A rod turned towards the throat collides (f < 0): the signed square must not reward it.
    X = hole_frame(HOLE, AXIS)
    problem = PlacementProblem(cyl, X, 0.0, D12, "eq22")
    ev = problem.evaluate(np.array([[65.5 * MM, np.pi], [65.5 * MM, 0.0]]))
    assert ev.f_safe_line1[0] < 0 and ev.F[0] > 0 > ev.F[1]


def test_same_seed_same_result_and_bounds(cyl):
    kw = dict(rod_radius=6 * MM, implant_length=D12, verify=False)
    a = place_instrument(cyl, HOLE, AXIS, seed=3, **kw)
    b = place_instrument(cyl, HOLE, AXIS, seed=3, **kw)
    assert a.d_T == b.d_T and a.theta_T == b.theta_T
    np.testing.assert_array_equal(a.history, b.history)
    # bounds exclude the optimum: the PSO stops on the bound (d_T <= 55 mm -> 55 mm)
    c = place_instrument(cyl, HOLE, AXIS, bounds=[[31 * MM, -0.5], [55 * MM, 0.5]], **kw)
    assert c.d_T == pytest.approx(55 * MM, abs=1e-6)


def test_pso_on_a_known_function():
    # f = (x - 0.3)^2 + (y + 0.2)^2 on [-1, 1]^2; and a linear f whose minimum is a corner.
    quad = lambda x: (x[:, 0] - 0.3) ** 2 + (x[:, 1] + 0.2) ** 2  # noqa: E731
    r = pso(quad, [-1, -1], [1, 1], seed=1)
    np.testing.assert_allclose(r.x, [0.3, -0.2], atol=1e-5)
    assert r.stopped == "stall" and r.history[-1] == r.F
    lin = lambda x: x[:, 0] + x[:, 1]  # noqa: E731
    r = pso(lin, [-1, -2], [1, 1], seed=1)
    np.testing.assert_allclose(r.x, [-1, -2])
    with pytest.raises(InputError, match="bounds"):
        pso(lin, [1, 0], [0, 1])


def test_planning_failure_when_no_safe_line():
    # A 5 mm tube cannot hold a 6 mm rod: line1 is unsafe everywhere.
    tube = Fpsm.cylinder(5 * MM, 0.0, 100 * MM, 11)
    p = place_instrument(
        tube, [0, -5 * MM, 50 * MM], AXIS, rod_radius=6 * MM, implant_length=2 * MM, verify=False
    )
    assert not p.valid and "line1" in p.reason and p.f_safe_line1 <= 0


@pytest.mark.parametrize(
    "hole, axis, kw, field",
    [
        ([0, -0.05, 0.2], AXIS, {}, "hole"),  # above the slices
        ([0, -0.07, 0.05], AXIS, {}, "hole"),  # 20 mm outside the wall
        ([0, np.nan, 0.05], AXIS, {}, "hole"),
        (HOLE, [0, 0, 0], {}, "hole_axis"),
        (HOLE, AXIS, {"objective": "eq99"}, "objective"),
        (HOLE, AXIS, {"rod_radius": -1.0}, "rod_radius"),
        (HOLE, AXIS, {"bounds": [[0.1, 0], [0.05, 1]]}, "bounds"),
    ],
)
def test_bad_input(cyl, hole, axis, kw, field):
    args = dict(rod_radius=6 * MM, implant_length=D12, verify=False) | kw
    with pytest.raises(InputError) as err:
        place_instrument(cyl, hole, axis, **args)
    assert err.value.field == field


def test_placement_on_a_non_circular_model():
    # An elliptic tube (x semi-axis 40 mm, y semi-axis 25 mm): the rod should stay near the
    # centre plane y = 0 of the narrow direction; the hole is on the +x wall pointing to -x.
    n = 24
    th = 2 * np.pi * np.arange(n) / n
    r = 1.0 / np.sqrt((np.cos(th) / 0.04) ** 2 + (np.sin(th) / 0.025) ** 2)
    f = Fpsm(np.linspace(0, 0.08, 9), np.tile(r, (9, 1)))
    p = place_instrument(
        f, [0.04, 0.0, 0.03], [-1, 0, 0], rod_radius=3 * MM, implant_length=10 * MM, seed=0
    )
    assert p.valid
    assert p.grid["distance_d_T"] <= 0.1 * MM and p.grid["distance_theta_T"] <= np.deg2rad(0.1)
    # by symmetry about y = 0 (Hole y = Center -y here), the rod stays in the plane y = 0
    assert abs(p.line1["direction"][1]) < 1e-3


def test_cylinder_verification_with_the_sound_clearance(cyl):
    # At the Eq. 14 optimum with r = 6 mm (d_T = 62.5 mm, theta_T = 0) the tool origin is at
    # Center (0, 12.5, 50) mm and the rod rises along +z: the rod axis is 50 - 12.5 = 37.5 mm
    # from the wall, the implant axis (Tool z = Center +y, down to y = 12.5 - 31 = -18.5 mm)
    # 50 - 18.5 = 31.5 mm, the head (a 6 mm sphere at the origin) 37.5 mm; so the true
    # clearance over the feed is 31.5 mm. The certified value never exceeds it and, resolved
    # only up to RESOLVE, is at least RESOLVE minus the bound's slack and the region's loss
    # (lateral 0.5 mm + 1 deg x 31 mm).
    from implantplan.systems.placement.tool_clearance import RESOLVE, clearance_field

    p = place_instrument(cyl, HOLE, AXIS, rod_radius=6 * MM, implant_length=D12, seed=0,
                         verify=False)
    v = p.verification
    f = clearance_field(cyl)
    slack = f.spacing * np.sqrt(3) / 2 + f.spacing / 4 + f.cover
    loss = 0.5 * MM + np.radians(1.0) * D12
    assert RESOLVE - slack - loss <= v["clearance_certified"] <= 31.5 * MM - 0.5 * MM
    assert p.valid and v["reasons"] == []
    assert p.to_dict()["fixture_tolerance"]["lateral"] == 0.5 * MM
    # a margin above the true clearance makes the placement invalid, with the reason
    q = place_instrument(cyl, HOLE, AXIS, rod_radius=6 * MM, implant_length=D12, seed=0,
                         verify=False, safety=SafetySpec(clearance_margin=40 * MM))
    assert not q.valid and "clinical margin 40.000 mm" in q.reason
