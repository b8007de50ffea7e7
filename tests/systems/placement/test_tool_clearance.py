"""Sound tool clearance on the FPSM (systems.placement.tool_clearance): hand-derived cylinder
values and
soundness against the exact distance on random rods."""

import numpy as np
import pytest

from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.tool_clearance import (
    RESOLVE,
    ToolClearance,
    build_field,
    clearance_field,
    curve_bounds,
    feed_clearance,
    is_rigid_pose,
    rigid_poses,
    rod_clearance,
    rod_safe,
    tool_clearance,
)

RHO = 0.05  # cylinder radius (m), z from 0 to 0.1, opening at z = 0.1


@pytest.fixture(scope="module")
def cylinder():
    return Fpsm.cylinder(RHO, 0.0, 0.1, 11)


def _exact_cylinder(p0, d, r, length=0.3, n=3001):
    """Exact signed clearance of capsules (start p0, unit d, length) in the open-topped
    cylinder (the start point is the lowest when d_z >= 0), by dense sampling of the axis (the
    axis distance to the boundary is piecewise smooth; sampling at 0.1 mm over-estimates the
    minimum by at most 0.05 mm)."""
    s = np.linspace(0, length, n)
    P = p0[:, None, :] + s[None, :, None] * d[:, None, :]
    rr = np.hypot(P[..., 0], P[..., 1])
    below = P[..., 2] <= 0.1
    dist = np.where(below, np.minimum(RHO - rr, P[..., 2]),
                    np.hypot(P[..., 2] - 0.1, np.maximum(RHO - rr, 0.0)))
    return dist.min(axis=1) - r


def test_curve_bounds_exact_on_a_circle():
    m, d = curve_bounds(np.full((2, 8), 0.03))
    assert np.allclose(m, 0.03) and np.allclose(d, 0.0, atol=1e-15)


def test_on_axis_rod_in_cylinder_is_rho_minus_r_up_to_the_resolved_level(cylinder):
    # A vertical rod on the axis of a circular cylinder: its true clearance is rho - r = 44 mm
    # (the wall is 50 mm away, the rod leaves through the opening). The sound value never
    # exceeds it and, being resolved only up to RESOLVE, is at least RESOLVE minus the bound's
    # slack (grid interpolation <= g sqrt(3)/2, march <= step/2, sampling cover).
    c = rod_clearance(cylinder, [0, 0, 0.05], [0, 0, 1.0], 0.006)[0]
    f = clearance_field(cylinder)
    slack = f.spacing * np.sqrt(3) / 2 + f.spacing / 4 + f.cover
    assert c <= RHO - 0.006
    assert c >= RESOLVE - slack
    # near the wall (clearance below RESOLVE) it is resolved: 50 - 41 - 6 = 3 mm
    c = rod_clearance(cylinder, [0.041, 0, 0.05], [0.041, 0, 1.0], 0.006)[0]
    assert 0.003 - slack <= c <= 0.003


def test_sound_never_exceeds_exact_on_random_rods(cylinder):
    rng = np.random.default_rng(7)
    n = 3000
    p0 = np.column_stack([rng.uniform(-0.045, 0.045, n), rng.uniform(-0.045, 0.045, n),
                          rng.uniform(0.005, 0.095, n)])
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.6
    d /= np.linalg.norm(d, axis=1)[:, None]
    r = rng.uniform(0.002, 0.008, n)
    c = rod_clearance(cylinder, p0, p0 + 0.3 * d, r)
    exact = _exact_cylinder(p0, d, r)
    # the contract: a positive value certifies at least that much clearance (the exact
    # reference samples the axis at 0.1 mm: it over-estimates by <= 0.05 mm); negative values
    # are only "not certified"
    assert np.sum((c > 0) & (c > exact + 5e-5)) == 0
    assert np.sum((c > 0) & (exact < 0)) == 0
    free = exact > 0
    assert free.sum() > 500
    # conservative but not useless: most rods free by 1.5 mm are certified free
    assert np.mean(c[exact > 0.0015] > 0) > 0.9


@pytest.mark.parametrize("threshold", [0.0, 0.001, -0.002])
def test_verdict_path_gives_the_signed_bounds_verdict(cylinder, threshold):
    """rod_safe stops a capsule's march once it is certain to fail: the verdict is still exactly
    rod_clearance > threshold, on random rods that pass and fail."""
    rng = np.random.default_rng(11)
    n = 4000
    p0 = np.column_stack([rng.uniform(-0.045, 0.045, n), rng.uniform(-0.045, 0.045, n),
                          rng.uniform(0.005, 0.095, n)])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    p1 = p0 + rng.uniform(0.0, 0.3, n)[:, None] * d
    r = rng.uniform(0.0, 0.008, n)
    c = rod_clearance(cylinder, p0, p1, r)
    safe = rod_safe(cylinder, p0, p1, r, clearance=threshold)
    np.testing.assert_array_equal(safe, c > threshold)
    assert 0 < safe.sum() < n
    # the cylinder by hand: an axial rod 40 mm off the axis, radius 6 mm, is 50 - 40 - 6 = 4 mm
    # free (the bound is within a grid cell of it and never above it)
    rod = ([0.04, 0, 0.05], [0.04, 0, 0.5], 0.006)
    assert rod_safe(cylinder, *rod, clearance=0.002)[0]
    assert not rod_safe(cylinder, *rod, clearance=0.0041)[0]


def test_a_start_just_outside_the_wall_is_never_certified(cylinder):
    """The squared-distance bound is one of the unsigned distance (module notes), so whether a
    start is in F is decided separately: a rod starting in tissue, 0.01-1.5 mm beyond the wall
    (inside the grid box, in cells with corner nodes inside the cylinder), is not free, whatever
    its radius and direction; the same points moved 5 mm inside are."""
    rng = np.random.default_rng(5)
    n = 2000
    th = rng.uniform(0, 2 * np.pi, n)
    rr = RHO + rng.uniform(1e-5, 1.5e-3, n)
    p0 = np.column_stack([rr * np.cos(th), rr * np.sin(th), rng.uniform(0.01, 0.09, n)])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    p1 = p0 + rng.uniform(0.0, 0.01, n)[:, None] * d
    assert np.all(rod_clearance(cylinder, p0, p1, 0.0) <= 0)
    assert not rod_safe(cylinder, p0, p1, 0.0).any()
    inside = p0 * np.array([0.9, 0.9, 1.0])  # 5 mm and more inside the wall
    assert np.mean(rod_clearance(cylinder, inside, inside, 0.0) > 0) > 0.99


def test_leaving_through_the_side_or_throat_is_a_collision(cylinder):
    side = rod_clearance(cylinder, [0, 0, 0.05], [0.2, 0, 0.05], 0.001)
    throat = rod_clearance(cylinder, [0, 0, 0.05], [0, 0, -0.05], 0.001)
    opening = rod_clearance(cylinder, [0, 0, 0.05], [0, 0, 0.5], 0.001)
    assert side[0] < 0 and throat[0] < 0 and opening[0] > 0


def test_paper_method_is_eq12(cylinder):
    # on a circle Eq. 12 is exact at the samples: rho - r - |xy| for a vertical line
    c = rod_clearance(cylinder, [0.01, 0, 0.05], [0.01, 0, 1.0], 0.006, method="paper")
    assert c[0] == pytest.approx(0.05 - 0.006 - 0.01)


def test_tool_clearance_batch_single_and_fast_path_agree(cylinder):
    tool = Instrument.paper(rod_radius=0.004, implant_length=0.02)
    X = np.tile(np.eye(4), (5, 1, 1))
    X[:, :3, :3] = [[0, 0, -1], [0, 1, 0], [1, 0, 0]]  # Tool x = Center z (out of the mouth)
    X[:, 0, 3] = np.linspace(-0.02, 0.02, 5)
    X[:, 2, 3] = 0.06
    c = tool_clearance(cylinder, X, tool)
    fast = ToolClearance(cylinder, tool)
    assert np.array_equal(c, fast(X))
    assert fast.one(X[2]) == c[2]
    # the implant hangs 20 mm sideways (Tool -z = Center +x): the pose at x = +20 mm is nearer
    assert c[4] < c[0]
    # the rod stays 4 mm thick on the axis line x = -20 mm: the rod's own clearance there
    rod = rod_clearance(cylinder, X[0, :3, 3] + [0, 0, 0.004], X[0, :3, 3] + [0, 0, 0.2], 0.004)
    assert c[0] <= rod[0]


def test_feed_clearance_bounds_every_depth_and_offset(cylinder):
    tool = Instrument.paper(rod_radius=0.004, implant_length=0.02)
    X = np.eye(4)
    X[:3, :3] = [[0, 0, -1], [0, 1, 0], [1, 0, 0]]
    X[:3, 3] = [0.0, 0.0, 0.03]
    base = feed_clearance(cylinder, X, tool)[0]
    assert base <= tool_clearance(cylinder, X, tool)[0]
    wider = feed_clearance(cylinder, X, tool, lateral=0.0005, angle=np.radians(1))[0]
    assert base - 0.0005 - np.radians(1) * 0.02 - 1e-12 <= wider <= base - 0.0005 + 1e-12


def test_input_errors(cylinder):
    with pytest.raises(InputError, match="radius"):
        rod_clearance(cylinder, [0, 0, 0], [0, 0, 1], -1.0)
    with pytest.raises(InputError, match="method"):
        rod_clearance(cylinder, [0, 0, 0], [0, 0, 1], 0.0, method="x")
    with pytest.raises(InputError, match="instrument.rod_radius"):
        Instrument.paper(rod_radius=-1)
    with pytest.raises(InputError, match="X_CTool"):
        tool_clearance(cylinder, np.eye(3))


def test_repeated_envelopes_are_computed_once_with_the_same_field():
    """Layers with equal envelopes (equal slices) share one distance computation; the field
    equals, to rounding, the field of the same model with those slices made distinct by 1e-14
    (every layer computed)."""
    rng = np.random.default_rng(4)
    z = np.linspace(0.0, 0.05, 8)
    rho = rng.uniform(0.02, 0.04, (8, 12))
    rho[1:4] = rho[0]  # a straight tube over the bottom three slabs, then a varying cavity
    apart = rho.copy()
    apart[1:4] *= 1.0 + 1e-14 * np.arange(1, 4)[:, None]
    a, b = build_field(Fpsm(z, rho)), build_field(Fpsm(z, apart))
    assert a.values.shape == b.values.shape and a.cover == pytest.approx(b.cover, rel=1e-12)
    np.testing.assert_allclose(a.values, b.values, rtol=0, atol=1e-12)
    assert np.ptp(a.values) > 0.01  # a field with structure, not a constant


def test_the_compiled_rigid_test_is_rigid_poses():
    """is_rigid_pose (the control loops' check) accepts exactly the poses rigid_poses accepts:
    rotations perturbed around the tolerance, scaled, sheared, reflected, with a bad last row,
    far away or non-finite."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(11)
    poses = []
    for k in range(400):
        X = np.eye(4)
        X[:3, :3] = Rotation.random(random_state=k).as_matrix()
        X[:3, 3] = rng.normal(scale=0.05, size=3)
        kind = k % 8
        if kind == 1:  # around the tolerance of the rotation
            X[:3, :3] += rng.normal(scale=10.0 ** rng.uniform(-8, -5), size=(3, 3))
        elif kind == 2:
            X[:3, :3] *= rng.choice([0.9, 1.0 + 2e-7, 1.0 - 5e-7, 1.0 + 5e-6])
        elif kind == 3:
            X[:3, 0] *= -1.0  # a reflection
        elif kind == 4:
            X[3, rng.integers(4)] += rng.choice([1e-7, 2e-6, -1e-3])
        elif kind == 5:
            X[rng.integers(3), 3] = rng.choice([999.0, 1000.0, 1000.5, -2e3])
        elif kind == 6:
            X[rng.integers(4), rng.integers(4)] = rng.choice([np.nan, np.inf, -np.inf])
        poses.append(X)
    accepted = 0
    for X in poses:
        try:
            rigid_poses(X)
            want = True
        except InputError:
            want = False
        assert is_rigid_pose(np.ascontiguousarray(X)) == want, X
        accepted += want
    assert 0 < accepted < len(poses)  # both answers occur
