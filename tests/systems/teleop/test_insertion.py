"""The insertion core (systems.teleop.insertion): the planned implant, its deviation, the
insertion fixture and the phase switch, against hand-derived values."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from implantplan.systems.errors import InputError
from implantplan.systems.frames import rot_x, rotations, transform
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.fixture import VirtualFixture
from implantplan.systems.teleop.insertion import (
    R_INSERT,
    InsertionPhase,
    append_stroke,
    implant_deviation,
    implant_points,
    insertion_fixture,
    planned_insertion,
)
from implantplan.systems.teleop.master_device import MasterMotion

R, D12, L = 0.006, 0.031, 0.010


def paper():
    return Instrument.paper(rod_radius=R, implant_length=D12)


def target(d_T=0.04):
    """A feeding target: Hole at (0.01, -0.02, 0.03) with z along +y of Center, theta_T 0.3."""
    z = np.array([0.0, 1.0, 0.0])
    x = np.array([0.0, 0.0, 1.0])
    R_CH = np.column_stack([x, np.cross(z, x), z])
    c, s = np.cos(0.3), np.sin(0.3)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    X_CH = transform(R_CH, [0.01, -0.02, 0.03])
    return X_CH, X_CH @ transform(Rz, [0.0, 0.0, d_T])


def test_implant_points_of_the_paper_tool_and_the_actuator():
    top, apex = implant_points(paper())
    np.testing.assert_allclose(top, [R, 0, 0])
    np.testing.assert_allclose(apex, [R, 0, -D12])
    top, apex = implant_points(Instrument.actuator())
    assert top[2] > apex[2]
    np.testing.assert_allclose(apex[2], -D12, atol=1e-9)  # the implant ends d12 below the TCP


def test_planned_implant_sits_on_the_hole_plane():
    X_CH, X_CT = target(0.04)
    plan = planned_insertion(X_CT, 0.04, paper(), L)
    # the tip travels from d_T - d12 above the hole's plane to L below it
    assert plan.depth == pytest.approx(0.04 - D12 + L)
    # platform on the hole's plane, apex L below it, the axis the hole's z
    np.testing.assert_allclose((plan.platform - X_CH[:3, 3]) @ X_CH[:3, 2], 0.0, atol=1e-15)
    np.testing.assert_allclose((plan.apex - X_CH[:3, 3]) @ X_CH[:3, 2], -L, atol=1e-15)
    np.testing.assert_allclose(plan.axis, X_CH[:3, 2], atol=1e-15)
    # the paper's implant line is r off the hole's axis (Eq. 19's line2); the actuator's is on it
    off = plan.platform - X_CH[:3, 3]
    assert np.linalg.norm(off - (off @ X_CH[:3, 2]) * X_CH[:3, 2]) == pytest.approx(R)
    act = planned_insertion(X_CT, 0.04, Instrument.actuator(), L)
    np.testing.assert_allclose(act.platform, X_CH[:3, 3], atol=1e-12)  # on the site
    with pytest.raises(InputError, match="d_T"):
        planned_insertion(X_CT, D12 - L, paper(), L)
    with pytest.raises(InputError, match="placed_implant_length"):
        planned_insertion(X_CT, 0.04, paper(), 0.05)


def test_deviation_of_known_placements():
    _, X_CT = target()
    plan = planned_insertion(X_CT, 0.04, paper(), L)
    X = plan.X_CT_final
    d = implant_deviation(X, plan)
    assert d["entry"] == 0 and d["apex"] == 0 and d["angle"] == 0
    assert d["depth_reached"] == pytest.approx(plan.depth)
    # 1 mm off along Center x: entry = apex = 1 mm, no angle
    shifted = transform(np.eye(3), [0.001, 0, 0]) @ X
    d = implant_deviation(shifted, plan)
    assert d["entry"] == pytest.approx(0.001) and d["apex"] == pytest.approx(0.001)
    assert d["angle"] == pytest.approx(0.0, abs=1e-15)
    # turned by a about an axis through the platform perpendicular to the implant: the entry
    # stays, the apex moves 2 d12 sin(a/2), the angle is a
    a = np.deg2rad(2.0)
    p = plan.platform
    Rt = rot_x(a) if abs(plan.axis[0]) < 0.5 else rotations(np.array([[0, a, 0]]))[0]
    turn = transform(Rt, p - Rt @ p)
    d = implant_deviation(turn @ X, plan)
    assert d["entry"] == pytest.approx(0.0, abs=1e-15)
    assert d["apex"] == pytest.approx(2 * L * np.sin(a / 2), rel=1e-12)
    assert d["angle"] == pytest.approx(a, rel=1e-12)
    # half way: the depth reached is half the depth
    half = X_CT @ transform(np.eye(3), [0, 0, -plan.depth / 2])
    assert implant_deviation(half, plan)["depth_reached"] == pytest.approx(plan.depth / 2)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-0.05, 0.05), min_size=3, max_size=3),
       st.lists(st.floats(-0.01, 0.01), min_size=3, max_size=3))
def test_deviation_is_frame_free(w, t):
    """The deviations do not depend on the frame they are computed in (Center vs the scan)."""
    _, X_CT = target()
    plan = planned_insertion(X_CT, 0.04, paper(), L)
    X = transform(rotations(np.array([w]))[0], t) @ plan.X_CT_final
    G = transform(rotations(np.array([[0.3, -1.0, 2.0]]))[0], [0.1, 0.2, -0.3])
    moved = planned_insertion(G @ X_CT, 0.04, paper(), L)
    a, b = implant_deviation(X, plan), implant_deviation(G @ X, moved)
    for k in ("entry", "apex", "angle"):
        assert a[k] == pytest.approx(b[k], abs=1e-12)


def test_insertion_fixture_passes_the_stroke_and_stops_at_the_depth():
    _, X_CT = target()
    plan = planned_insertion(X_CT, 0.04, paper(), L)
    feed = VirtualFixture(origin=X_CT[:3, 3], direction=X_CT[:3, 0], entry_distance=0.03,
                          cylinder_radius=R, segment_lengths=(0.03, 0.05),
                          half_angles=np.deg2rad([15.0, 30.0]), R_ref=X_CT[:3, :3])
    vf = insertion_fixture(feed, plan)
    R_fix = X_CT[:3, :3] @ R_INSERT  # the tool as the insertion fixture sees it
    down = np.r_[0, 0, 0, -0.01 * X_CT[:3, 2]]
    # at the target and half way: the stroke along the implant axis passes unchanged
    for s in (0.0, plan.depth / 2):
        p = X_CT[:3, 3] - s * X_CT[:3, 2]
        law = vf.correct_twist(p, R_fix, down, dt=0.005)
        np.testing.assert_allclose(law.V[0], down, atol=1e-12)
    # the feed's fixture would not let it go down (it leaves line1)
    p_half = X_CT[:3, 3] - 0.01 * X_CT[:3, 2]
    assert feed.correct_twist(p_half, X_CT[:3, :3], np.zeros(6)).violation[0] > 0.009
    # at the depth stop the stroke is stopped; a lateral push at the tolerance is stopped
    law = vf.correct_twist(plan.X_CT_final[:3, 3], R_fix, down, dt=0.005)
    assert abs(law.V[0, 3:] @ X_CT[:3, 2]) < 1e-9
    side = X_CT[:3, 0]
    p_edge = X_CT[:3, 3] - plan.depth / 2 * X_CT[:3, 2] + vf.lateral_tolerance * side
    law = vf.correct_twist(p_edge, R_fix, np.r_[0, 0, 0, 0.01 * side], dt=0.005)
    assert law.V[0, 3:] @ side < 1e-9


def test_insertion_phase_switches_at_its_start():
    sys = InsertionPhase()
    ctx = sys.CreateDefaultContext()
    a, b = np.arange(6.0), -np.arange(6.0)
    sys.GetInputPort("V_WE_feed").FixValue(ctx, a)
    sys.GetInputPort("V_WE_insertion").FixValue(ctx, b)
    np.testing.assert_array_equal(sys.GetOutputPort("V_WE_corrected").Eval(ctx), a)  # never
    sys.set_start(ctx, 1.5)
    ctx.SetTime(1.49)
    np.testing.assert_array_equal(sys.GetOutputPort("V_WE_corrected").Eval(ctx), a)
    assert sys.GetOutputPort("barrier_release").Eval(ctx)[0] == 0.0
    ctx.SetTime(1.5)
    np.testing.assert_array_equal(sys.GetOutputPort("V_WE_corrected").Eval(ctx), b)
    assert sys.GetOutputPort("barrier_release").Eval(ctx)[0] == 1.0


def test_append_stroke_holds_then_continues_from_the_end():
    a = MasterMotion(dt=0.01, p_M=np.array([[0, 0, 0], [1, 0, 0.0]]))
    b = MasterMotion(dt=0.01, p_M=np.array([[5, 5, 5], [5, 5, 4.0]]))
    m = append_stroke(a, b, hold=0.02)
    np.testing.assert_allclose(m.p_M, [[0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0],
                                       [1, 0, -1]])
    with pytest.raises(InputError, match="dt"):
        append_stroke(a, MasterMotion(dt=0.02, p_M=b.p_M))
