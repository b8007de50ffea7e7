"""The conical virtual fixture: geometry, signed distance, admittance force, velocity filter.
Expected values by hand in the comments."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.placement.fixture import VirtualFixture
from implantplan.systems.placement.planner import place_instrument

T15, T30 = np.tan(np.deg2rad(15)), np.tan(np.deg2rad(30))


@pytest.fixture(scope="module")
def vf():
    # Axis +z through the origin; an axis region of radius 6 mm (a wide lateral tolerance, to
    # test the geometry) up to the entry at 50 mm; a 30 mm cone of 15 deg, then a 50 mm cone of
    # 30 deg; beyond, the last radius continues.
    return VirtualFixture(
        origin=[0, 0, 0],
        direction=[0, 0, 2],
        entry_distance=0.05,
        cylinder_radius=0.006,
        segment_lengths=[0.03, 0.05],
        half_angles=np.deg2rad([15, 30]),
        lateral_tolerance=0.006,
    )


def test_profile_by_hand(vf):
    s, r = vf.profile()
    np.testing.assert_allclose(s, [0, 0.05, 0.08, 0.13])
    np.testing.assert_allclose(
        r, [0.006, 0.006, 0.006 + 0.03 * T15, 0.006 + 0.03 * T15 + 0.05 * T30]
    )
    assert vf.radius_at(0.2) == pytest.approx(r[-1])
    assert np.isnan(vf.radius_at(-0.01))


def test_signed_distance_by_hand(vf):
    R1 = 0.006 + 0.015 * T15  # cone radius at s = 65 mm
    pts = np.array(
        [
            [0, 0, 0.02],  # on the axis: 6 mm inside (the cap is 20 mm away)
            [0.008, 0, 0.02],  # 2 mm outside the cylinder
            [0, 0, -0.003],  # 3 mm past the target (the cap)
            [0, 0.0, 0.001],  # 1 mm above the cap, on the axis: 1 mm inside
            [0, R1 + 0.001, 0.065],  # 1 mm radially outside the first cone: 1 mm * cos 15
            [0.0, 0.05, 0.3],  # beyond the last cone: outside the final radius
        ]
    )
    R_end = 0.006 + 0.03 * T15 + 0.05 * T30
    np.testing.assert_allclose(
        vf.distance(pts),
        [-0.006, 0.002, 0.003, -0.001, 0.001 * np.cos(np.deg2rad(15)), 0.05 - R_end],
        atol=1e-12,
    )
    np.testing.assert_allclose(vf.violation(pts[:3]), [0, 0.002, 0.003], atol=1e-12)
    n = vf.normal(pts[[1, 2, 4]])
    np.testing.assert_allclose(n[0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(n[1], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(
        n[2], [0, np.cos(np.deg2rad(15)), -np.sin(np.deg2rad(15))], atol=1e-9
    )


def test_force_law_by_hand(vf):
    k, b = 1000.0, 50.0
    # 2 mm outside the cylinder at rest: k * 0.002 = 2 N along the inward normal (-x)
    F = vf.force([[0.008, 0, 0.02]], [[0, 0, 0]], stiffness=k, damping=b)
    np.testing.assert_allclose(F, [[-2.0, 0, 0]], atol=1e-12)
    # moving outward at 10 mm/s adds b * 0.01 = 0.5 N; moving inward adds nothing
    F = vf.force([[0.008, 0, 0.02]] * 2, [[0.01, 0, 0], [-0.01, 0, 0.3]], stiffness=k, damping=b)
    np.testing.assert_allclose(F, [[-2.5, 0, 0], [-2.0, 0, 0]], atol=1e-12)
    # inside: no force whatever the velocity
    F = vf.force([[0.001, 0, 0.02]], [[1.0, 0, 0]], stiffness=k, damping=b)
    np.testing.assert_array_equal(F, [[0, 0, 0]])
    # 3 mm past the target: pushed back out along +z with 3 N
    np.testing.assert_allclose(vf.force([0, 0, -0.003], [0, 0, 0], stiffness=k), [0, 0, 3.0])


def test_velocity_filter(vf):
    # feeding straight along the axis passes unchanged (inside, and on the axis)
    v = vf.correct_velocity([[0, 0, 0.02], [0.003, 0, 0.07]], [[0, 0, -0.01], [0, 0, 0.02]])
    np.testing.assert_array_equal(v, [[0, 0, -0.01], [0, 0, 0.02]])
    # on the cylinder wall: the outward part of the command is removed, the rest passes
    v = vf.correct_velocity([0.006, 0, 0.02], [0.01, 0.002, -0.01])
    np.testing.assert_allclose(v, [0, 0.002, -0.01], atol=1e-15)
    # 2 mm outside at rest: return velocity -gain * 0.002 * n = -0.02 m/s along x (gain 10/s)
    v = vf.correct_velocity([0.008, 0, 0.02], [0, 0, 0], return_gain=10.0)
    np.testing.assert_allclose(v, [-0.02, 0, 0], atol=1e-15)
    # with a step dt, the outward speed is limited to reaching the wall in one step:
    # 1 mm to go in 1 ms -> at most 1 m/s outward
    v = vf.correct_velocity([0.005, 0, 0.02], [2.0, 0, 0.1], dt=1e-3)
    np.testing.assert_allclose(v, [1.0, 0, 0.1], atol=1e-12)
    # at the target, the command to go deeper is removed, backing out passes
    v = vf.correct_velocity([[0, 0, 0], [0, 0, 0]], [[0, 0, -0.01], [0, 0, 0.01]])
    np.testing.assert_allclose(v, [[0, 0, 0], [0, 0, 0.01]], atol=1e-15)


@settings(max_examples=40, deadline=None)
@given(
    p=arrays(float, (20, 3), elements=st.floats(-0.08, 0.2)),
    q=arrays(float, (20, 3), elements=st.floats(-0.08, 0.2)),
)
def test_distance_is_a_signed_distance(vf, p, q):
    # 1-Lipschitz, and its sign agrees with the region's definition (s >= 0, rho <= R(s))
    dp, dq = vf.distance(p), vf.distance(q)
    assert np.all(np.abs(dp - dq) <= np.linalg.norm(p - q, axis=1) + 1e-12)
    rho = np.hypot(p[:, 0], p[:, 1])
    R = vf.radius_at(np.maximum(p[:, 2], 0.0))
    inside = (p[:, 2] >= 0) & (rho <= R)
    clear = np.abs(dp) > 1e-12
    assert np.all((dp[clear] < 0) == inside[clear])
    # stepping a little along the outward normal increases the distance by that much
    n = vf.normal(p)
    step = 1e-6
    np.testing.assert_allclose(vf.distance(p + step * n)[clear], dp[clear] + step, atol=1e-9)


def test_from_placement_and_round_trip():
    cyl = Fpsm.cylinder(0.05, 0.0, 0.1, 11)
    p = place_instrument(
        cyl, [0, -0.05, 0.05], [0, 1, 0], rod_radius=0.006, implant_length=0.031, verify=False
    )
    vf = p.vf
    # the axis is line1 through the Tool origin (0, 12.5, 50) mm, straight up; the mouth
    # opening is at z = 100 mm, so the entry is 50 mm along the axis. The PSO compares F rounded
    # (seeds.rounded) and F is flat to second order at theta_T = 0: the axis to 1e-4 rad
    np.testing.assert_allclose(vf.origin, [0, 0.0125, 0.05], atol=1e-6)
    np.testing.assert_allclose(vf.direction, [0, 0, 1], atol=1e-4)
    assert vf.entry_distance == pytest.approx(0.05, abs=1e-6)
    assert vf.cylinder_radius == 0.006
    np.testing.assert_allclose(vf.entry_point, [0, 0.0125, 0.1], atol=1e-5)
    back = VirtualFixture.from_dict(vf.to_dict())
    pts = np.random.default_rng(0).uniform(-0.05, 0.15, (100, 3))
    np.testing.assert_array_equal(back.distance(pts), vf.distance(pts))


@pytest.mark.parametrize(
    "kw, field",
    [
        ({"segment_lengths": [0.0]}, "vf.segment_lengths"),
        ({"half_angles": [np.pi / 2]}, "vf.half_angles"),
        ({"direction": [0, 0, 0]}, "vf.direction"),
        ({"cylinder_radius": -1.0}, "vf.cylinder_radius"),
    ],
)
def test_bad_fixture(kw, field):
    args = (
        dict(
            origin=[0, 0, 0],
            direction=[0, 0, 1],
            entry_distance=0.05,
            cylinder_radius=0.006,
            segment_lengths=[0.03],
            half_angles=[0.2],
        )
        | kw
    )
    with pytest.raises(InputError) as err:
        VirtualFixture(**args)
    assert err.value.field == field


def test_bad_points(vf):
    with pytest.raises(InputError, match="points"):
        vf.distance([[np.nan, 0, 0]])
