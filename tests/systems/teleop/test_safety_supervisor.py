"""SafetySupervisor: the control-barrier filter on a cylinder FPSM (the true clearance by hand;
the barrier is the sound FPSM clearance of systems.placement.tool_clearance, a certified lower
bound),
tested alone (FixValue on the input, the periodic update evaluated), and its core's properties."""

import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import transform
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.tool_clearance import ToolClearance
from implantplan.systems.teleop.supervisor import (
    JUMP,
    Barrier,
    SafetySupervisor,
    barrier_filter,
    clearance,
    step_pose_into,
    stepped_poses,
    supervise,
)

# A cylinder FPSM of radius 50 mm from z = 0 to 100 mm (opening at the top); the tool's rod
# (radius 6 mm) points up the cylinder (Tool x = Center z), its implant along Tool -z = Center -x.
CYL = Fpsm.cylinder(0.05, 0.0, 0.1, slices=11)
TOOL = Instrument.paper(rod_radius=0.006, implant_length=0.031)
# Tool x, y, z = Center z, -y, x
R_CT = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
DT = 0.005
BAR = Barrier(margin=0.001, alpha=20.0)


@functools.cache
def clear() -> ToolClearance:
    """The cylinder's clearance of the paper tool (its field built on first use, not at
    collection)."""
    return ToolClearance(CYL, TOOL)


def pose(x: float, z: float = 0.05) -> np.ndarray:
    return transform(R_CT, [x, 0.0, z])


def x_at(h: float) -> float:
    """The TCP's x (m) where the barrier is h (it falls as the tool nears the wall at +x)."""
    lo, hi = 0.02, 0.049
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if clear().one(pose(mid)) > h else (lo, mid)
    return 0.5 * (lo + hi)


def test_clearance_is_a_lower_bound_of_the_one_by_hand():
    """TCP at x = 42 mm: the rod (radius 6 mm, vertical) and the head sphere (radius 6 mm) are
    50 - 6 - 42 = 2 mm from the wall; the implant points to Tool -z = Center -x, 39 mm away. The
    barrier is a certified lower bound: at most 2 mm, and not far below."""
    h = clearance(CYL, pose(0.042)[None], TOOL)[0]
    assert 0.001 <= h <= 0.002
    # nearer the wall it falls, through zero at the wall
    assert clear().one(pose(0.0425)) < h and clear().one(pose(0.0445)) < 0.0
    # wholly above the opening: large (the field is capped)
    assert clearance(CYL, pose(0.0, 0.2)[None], TOOL)[0] >= 0.01


def test_a_command_away_from_the_wall_or_slow_enough_passes_untouched():
    X = pose(x_at(0.002))
    V = np.array([[0, 0, 0, -0.04, 0.0, 0.01],  # away from the wall (Center -x), and up
                  [0, 0, 0, 0.0, 0.0, -0.01],  # along the wall
                  [0, 0, 0, 0.008, 0.0, 0.0]])  # towards it, slower than alpha (h - m) = 20 mm/s
    res = supervise(clear(), np.repeat(X[None], 3, axis=0), V, BAR, DT)
    np.testing.assert_array_equal(res.V, V)
    assert not res.active.any()
    np.testing.assert_array_equal(res.scale, 1.0)


def test_a_command_towards_the_wall_is_slowed_to_the_barrier_rate():
    """h = 2 mm, margin 1 mm, alpha 20/s: h may fall at most 20 (2 - 1) = 20 mm/s. Pushing at
    40 mm/s towards the wall (Center +x) is cut to about that."""
    V = np.array([[0, 0, 0, 0.04, 0.0, 0.0]])
    res = supervise(clear(), pose(x_at(0.002))[None], V, BAR, DT)
    h, h1 = res.h[0], res.h_next[0]
    assert res.active[0] and 0.0 < res.scale[0] < 1.0
    assert h - h1 <= DT * 20.0 * (h - 0.001) + 1e-8  # the discrete barrier condition
    assert h - h1 >= 0.25 * DT * 20.0 * (h - 0.001)  # still approaching, not stopped
    assert 0.0 < res.V[0, 3] < 0.04
    assert np.abs(res.V[0, :3]).max() < 2e-3  # rad/s: the correction is a translation
    # 0.05 mm above the margin at most 20 * 0.05 = 1 mm/s towards the wall is left; the part
    # along it passes (h is a bound on a 1 mm grid: along the wall it wiggles by micrometres
    # within a cell, which exactly at the margin may stop a tangential move too); the projected
    # command's check lets h fall at most JUMP further than the rate, never below the margin
    res = supervise(clear(), pose(x_at(0.00105))[None], np.array([[0, 0, 0, 0.04, 0.0, -0.01]]),
                    BAR, DT)
    assert res.h_next[0] >= max(0.001, res.h[0] - DT * 20.0 * 0.00005 - JUMP) - 1e-8
    assert abs(res.V[0, 3]) < 2e-3 and -0.01 - 1e-12 <= res.V[0, 5] <= -0.005
    # below the margin (h = 0.5 mm) an approach is stopped, not turned into a retreat
    res = supervise(clear(), pose(x_at(0.0005))[None], np.array([[0, 0, 0, 0.04, 0.0, 0.0]]),
                    BAR, DT)
    assert -1e-4 < res.V[0, 3] < 2e-3
    assert res.h_next[0] >= res.h[0] - 1e-8


@settings(max_examples=200, deadline=None)
@given(
    V=arrays(float, (6,), elements=st.floats(-1.0, 1.0)),
    g=arrays(float, (6,), elements=st.floats(-1.0, 1.0)),
    h=st.floats(-0.01, 0.05),
)
def test_barrier_filter_never_amplifies_and_meets_the_constraint(V, g, h):
    out, b, active = barrier_filter(V[None], [h], g[None], margin=0.001, alpha=20.0,
                                    length_scale=0.5)
    M = np.array([0.25] * 3 + [1.0] * 3)
    assert np.sum(out[0] ** 2 * M) <= np.sum(V**2 * M) * (1 + 1e-12) + 1e-15
    assert out[0] @ g >= min(b[0], V @ g) - 1e-12
    assert b[0] <= 0.0
    if V @ g >= b[0]:
        np.testing.assert_array_equal(out[0], V)  # a command that meets it passes untouched
        assert not active[0]


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(0.02, 0.045),
    V=arrays(float, (6,), elements=st.floats(-0.1, 0.1)),
)
def test_supervised_step_keeps_the_barrier_and_never_amplifies(x, V):
    """On the cylinder, any command: one period of the filtered twist meets the discrete barrier
    condition on h itself (the projected command's check: at most ``JUMP`` further, never below
    the margin), and |V'|_M <= |V|_M."""
    res = supervise(clear(), pose(x)[None], V[None], BAR, DT)
    b = min(-20.0 * (res.h[0] - 0.001), 0.0)
    floor = res.h[0] + DT * b
    if res.h[0] >= 0.001:
        floor = min(floor, max(0.001, floor - JUMP))
        assert res.h_next[0] >= 0.001 - 1e-8  # never below the margin from above it
    assert res.h_next[0] >= floor - 1e-8
    M = np.array([BAR.length_scale**2] * 3 + [1.0] * 3)  # the metric of the projection
    assert np.sum(res.V[0] ** 2 * M) <= np.sum(V**2 * M) * (1 + 1e-12) + 1e-18
    assert 0.0 <= res.scale[0] <= 1.0 + 1e-12
    assert clear()(res.X_next)[0] == res.h_next[0]  # the barrier at the pose it steps to
    # the guarantee does not rest on the gradient: a wrong one still meets the condition
    wrong = supervise(clear(), pose(x)[None], V[None], BAR, DT, g=np.roll(V, 2)[None])
    assert wrong.h_next[0] >= floor - 1e-8
    assert np.sum(wrong.V[0] ** 2 * M) <= np.sum(V**2 * M) * (1 + 1e-12) + 1e-18


@functools.cache
def scan_bound():
    """The scan bound (capped at 5 mm) of the paper tool against a cylindrical cavity's mesh:
    radius 30 mm from z = 0 to 80 mm, open at the top (a 1 mm distance grid; built on first
    use)."""
    import trimesh

    from implantplan.systems.placement.distance_grid import build_grid
    from implantplan.systems.placement.exact_clearance import ExactCavity
    from implantplan.systems.placement.scan_clearance import CappedScanClearance, ScanClearance

    m = trimesh.creation.cylinder(radius=0.03, height=0.08, sections=96)
    m.apply_translation([0, 0, 0.04])
    keep = ~np.all(np.isclose(m.vertices[m.faces][..., 2], 0.08), axis=1)
    cavity = ExactCavity(trimesh.Trimesh(m.vertices, m.faces[keep], process=False))
    scan = ScanClearance(cavity, TOOL, grid=build_grid(cavity.mesh, spacing=1e-3))
    return CappedScanClearance(scan, 0.005)


def test_a_step_of_the_scan_bound_does_not_freeze_the_tool_above_the_margin():
    """The scan bound is not continuous in the pose (its branch and bound's tree changes where a
    piece crosses its split test): towards this cavity's wall it drops by micrometres within
    1 um of travel. A tool on the upper side of such a step, 0.05 mm above the margin, may fall
    dt alpha (h - margin) = 5 um a step under the strict condition: every move towards the
    wall, however short, falls by the step, and the strict check stopped the tool for good
    (feeds frozen for a second at site 46's narrow section, the margin grown by a
    moving head). It moves on now, slower than commanded, never below the margin."""
    sc = scan_bound()
    x = np.arange(0.018, 0.0235, 1e-6)  # the TCP towards the wall at +x, 2.7-3.9 mm from it
    X = np.repeat(pose(0.0, 0.05)[None], x.size, axis=0)
    X[:, 0, 3] = x
    h = sc(X)
    k = int(np.argmax(h[:-1] - h[1:]))
    step = h[k] - h[k + 1]
    assert DT * 20.0 * 0.05e-3 < step < JUMP  # more than the rate allows, within the jump
    bar = Barrier(margin=h[k] - 0.05e-3, alpha=20.0)
    V = np.array([[0, 0, 0, 0.02, 0.0, 0.0]])  # 20 mm/s towards the wall
    res = supervise(sc, X[k][None], V, bar, DT)
    assert res.active[0] and 0.0 < res.scale[0] < 1.0
    assert res.X_next[0, 0, 3] > x[k]  # it moved towards the wall (across the step)
    assert res.h_next[0] >= bar.margin - 1e-8  # not below the margin
    assert res.h_next[0] >= h[k] - DT * 20.0 * 0.05e-3 - JUMP - 1e-8
    # where h is continuous the strict condition holds as before (one micrometre back)
    res = supervise(sc, X[k - 200][None], V, Barrier(margin=h[k - 200] - 0.05e-3, alpha=20.0),
                    DT)
    assert res.h_next[0] >= h[k - 200] - DT * 20.0 * 0.05e-3 - 1e-8 and res.scale[0] > 0.0


@settings(max_examples=60, deadline=None)
@given(V=arrays(float, (6,), elements=st.floats(-2.0, 2.0)), dt=st.floats(1e-4, 0.05))
def test_compiled_step_is_drakes_angle_axis_step(V, dt):
    """The slow path's compiled pose step (Rodrigues) against the Drake AngleAxis step of
    :func:`stepped_poses`: the same pose to rounding, for any twist."""
    X = pose(0.03)
    X[:3, :3] = X[:3, :3] @ transform(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0],
                                                [0.0, 1.0, 0.0]]), [0, 0, 0])[:3, :3]
    out = np.empty((4, 4))
    step_pose_into(X, V, dt, out)
    np.testing.assert_allclose(out, stepped_poses(X[None], V[None], dt)[0], atol=1e-14)


def test_the_system_alone_filters_and_integrates():
    X_WC = transform(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                     [0.5, 0.2, 0.8])
    R_ET = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # any fixed rotation
    x0 = x_at(0.002)
    X_WE = X_WC @ pose(x0) @ transform(R_ET.T, np.zeros(3))
    system = SafetySupervisor(CYL, X_WC, X_WE, TOOL, R_ET=R_ET, barrier=BAR, period=DT)
    context = system.CreateDefaultContext()
    np.testing.assert_allclose(system.GetOutputPort("X_WE_desired").Eval(context).GetAsMatrix4(),
                               X_WE, atol=1e-15)
    assert system.GetOutputPort("barrier").Eval(context)[0] == pytest.approx(0.002, abs=1e-9)
    # towards the wall: Center +x = World +y
    system.GetInputPort("V_WE_corrected").FixValue(context, [0, 0, 0, 0, 0.04, 0])
    xd = system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0).get_value().copy()
    step = xd[:3] - pose(x0)[:3, 3]  # the state keeps the Tool pose in Center
    assert 0.0 < step[0] < 0.04 * DT
    h, scale, active = xd[18:21]
    assert h == pytest.approx(clear().one(pose(x0 + step[0])), abs=1e-9)
    assert h >= 0.002 - DT * 20.0 * 0.001 - 1e-8 and 0 < scale < 1 and active == 1.0
    context.SetDiscreteState(0, xd)
    np.testing.assert_allclose(system.GetOutputPort("barrier").Eval(context), [h, scale, 1.0])
    np.testing.assert_allclose(system.GetOutputPort("V_WE_filtered").Eval(context), xd[12:18])
    np.testing.assert_allclose(
        system.GetOutputPort("X_WE_desired").Eval(context).translation(),
        X_WE[:3, 3] + X_WC[:3, :3] @ step, atol=1e-15)
    # away from the wall: untouched, integrated exactly
    system.GetInputPort("V_WE_corrected").FixValue(context, [0, 0, 0, 0, -0.04, 0.01])
    xd2 = system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0).get_value()
    np.testing.assert_allclose(xd2[:3] - xd[:3], [-0.04 * DT, 0, 0.01 * DT], atol=1e-15)
    np.testing.assert_array_equal(xd2[12:18], [0, 0, 0, 0, -0.04, 0.01])
    assert xd2[20] == 0.0
    # disabled: the command is integrated unfiltered
    off = SafetySupervisor(CYL, X_WC, X_WE, TOOL, R_ET=R_ET, barrier=BAR, period=DT,
                           enabled=False)
    c2 = off.CreateDefaultContext()
    off.GetInputPort("V_WE_corrected").FixValue(c2, [0, 0, 0, 0, 0.04, 0])
    xd3 = off.EvalUniquePeriodicDiscreteUpdate(c2).get_vector(0).get_value()
    np.testing.assert_allclose(xd3[:3] - pose(x0)[:3, 3], [0.04 * DT, 0, 0], atol=1e-15)


def test_released_the_barrier_is_computed_only_when_asked():
    """While released (the insertion) the update integrates without the barrier and leaves h
    out of the state; the barrier port computes it at the desired pose when asked, and the
    first update after the release computes it before filtering: the barrier then holds from
    the pose the release left, as it did when every released update stored h."""
    X_WC = transform(np.eye(3), [0.5, 0.2, 0.8])
    X_WE = X_WC @ pose(x_at(0.004))
    system = SafetySupervisor(CYL, X_WC, X_WE, TOOL, barrier=BAR, period=DT,
                              release_input=True)
    context = system.CreateDefaultContext()
    system.GetInputPort("barrier_release").FixValue(context, [1.0])
    system.GetInputPort("V_WE_corrected").FixValue(context, [0, 0, 0, 0.04, 0, 0])  # at the wall
    for _ in range(20):  # 4 mm towards the wall: to 0.1 mm of it, unfiltered
        context.SetDiscreteState(0, system.EvalUniquePeriodicDiscreteUpdate(context)
                                 .get_vector(0).get_value().copy())
    x = context.get_discrete_state(0).get_value()
    assert np.isnan(x[18])
    X_CT = np.eye(4)
    X_CT[:3, :3], X_CT[:3, 3] = x[3:12].reshape(3, 3), x[:3]
    h = system.GetOutputPort("barrier").Eval(context)[0]
    assert h == clear().one(X_CT) and h < BAR.margin
    system.GetInputPort("barrier_release").FixValue(context, [0.0])
    xd = system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0).get_value()
    # below the margin: no further approach (the discrete condition from the h computed)
    assert xd[20] == 1.0 and xd[18] >= h - 1e-8 and np.isfinite(xd[18])


def test_every_integrated_step_keeps_the_command_limits():
    """Whatever reaches it (the fixture's return, the guard's retreat, a supervisor used alone),
    the supervisor integrates at most the limits' speed, direction kept, and holds on a
    non-finite twist; on or off."""
    from implantplan.systems.teleop.command_limits import CommandLimits

    X_WE = pose(0.0)  # X_WC = I, R_ET = I: the state's Tool pose is X_WE
    for enabled in (True, False):
        system = SafetySupervisor(CYL, np.eye(4), X_WE, TOOL, barrier=BAR, period=DT,
                                  enabled=enabled, limits=CommandLimits(linear_speed=0.02))
        context = system.CreateDefaultContext()
        port = system.GetInputPort("V_WE_corrected")
        port.FixValue(context, [0, 0, 0, -0.3, 0.0, -0.4])  # 0.5 m/s away from the wall
        xd = system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0).get_value()
        np.testing.assert_allclose(xd[:3] - X_WE[:3, 3], [-0.012 * DT, 0, -0.016 * DT],
                                   atol=1e-15)
        port.FixValue(context, [0, 0, 0, np.nan, 0.0, 0.0])
        xd = system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0).get_value()
        np.testing.assert_array_equal(xd[:3], X_WE[:3, 3])
    # the core does the same with ``limits``
    out = supervise(clear(), pose(0.0)[None], np.array([[0, 0, 0, -0.3, 0, -0.4]]), BAR, DT,
                    limits=CommandLimits(linear_speed=0.02))
    np.testing.assert_allclose(out.V[0], [0, 0, 0, -0.012, 0, -0.016], atol=1e-15)


def test_bad_settings():
    with pytest.raises(InputError, match="barrier.alpha"):
        Barrier(alpha=0.0)
    with pytest.raises(InputError, match="period"):
        SafetySupervisor(CYL, np.eye(4), np.eye(4), TOOL, period=0.0)
