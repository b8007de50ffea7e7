"""VirtualFixtureForceLaw: the admittance law around a cylinder fixture, tested alone."""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform

from implantplan.systems.frames import rot_x, rot_y, transform
from implantplan.systems.placement.fixture import VirtualFixture
from implantplan.systems.teleop.fixture_system import VirtualFixtureForceLaw

K, B = 2000.0, 100.0  # N/m, N s/m -> return gain 20 1/s
# Fixture along Center +z through the target at the origin, an axis region of radius 6 mm (a
# wide lateral tolerance, so the numbers are easy) up to the entry at 50 mm, then a 30 mm cone
# of 15 deg.
VF = VirtualFixture(
    origin=[0.0, 0.0, 0.0],
    direction=[0.0, 0.0, 1.0],
    entry_distance=0.05,
    cylinder_radius=0.006,
    segment_lengths=[0.03],
    half_angles=[np.deg2rad(15.0)],
    lateral_tolerance=0.006,
)
X_WC = transform(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [0.5, 0.2, 0.8])
R_CT = rot_y(-np.pi / 2)  # the tool's x axis (the rod, out of the mouth) along Center +z


def make(p_C, V_W, *, enabled=True, vf=VF, R=R_CT, integrate=True):
    X_WE = X_WC @ transform(R, p_C)
    system = VirtualFixtureForceLaw(vf, X_WC, X_WE, stiffness=K, damping=B, enabled=enabled,
                                    integrate=integrate)
    context = system.CreateDefaultContext()
    system.GetInputPort("V_WE_command").FixValue(context, np.asarray(V_W, dtype=float))
    system.GetInputPort("X_WE").FixValue(
        context, AbstractValue.Make(RigidTransform(X_WE))
    )
    return system, context, X_WE


def test_motion_along_the_axis_passes_unchanged():
    # Center z is World z here; feed inward at 10 mm/s from 20 mm above the target
    V = [0.0, 0.0, 0.0, 0.0, 0.0, -0.01]
    system, context, X_WE = make([0.0, 0.0, 0.02], V)
    np.testing.assert_allclose(system.GetOutputPort("V_WE_corrected").Eval(context), V)
    np.testing.assert_allclose(system.GetOutputPort("F_W_fixture").Eval(context), 0.0)
    # one period integrates the desired pose by v dt = 50 um
    xd = system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0).get_value()
    np.testing.assert_allclose(xd[:3], X_WE[:3, 3] + [0.0, 0.0, -0.01 * 0.005], atol=1e-15)
    np.testing.assert_allclose(xd[3:12].reshape(3, 3), X_WE[:3, :3], atol=1e-15)
    assert xd[12] == 0.0 and xd[13] == 0.0  # no violation


def test_a_point_outside_the_cylinder_is_pushed_back_by_the_stated_force():
    # Rod parallel to the axis, 8 mm off along Center x: the TCP is 2 mm outside (outward
    # normal n = Center x = World y), and so is the rod where it crosses the entry plane (its
    # lateral offset counts there, same normal). Still hand (no command): the corrected
    # velocity is the admittance return -(k/b) * 0.002 * n = -0.04 m/s along World y; the force
    # adds both springs: F = -2 k 0.002 n = -8 N along World y.
    system, context, X_WE = make([0.008, 0.0, 0.02], np.zeros(6))
    context.SetDiscreteState(0, system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0)
                             .get_value())
    assert system.GetOutputPort("violation").Eval(context)[0] == pytest.approx(0.002, abs=1e-12)
    # the update moved the desired pose by the return velocity over one period: 0.2 mm inward
    desired = system.GetOutputPort("X_WE_desired").Eval(context).translation()
    np.testing.assert_allclose(desired - X_WE[:3, 3], [0.0, -0.04 * 0.005, 0.0], atol=1e-12)
    np.testing.assert_allclose(
        system.GetOutputPort("F_W_fixture").Eval(context),
        [0.0, -8.0, 0.0], atol=1e-9
    )
    np.testing.assert_allclose(
        system.GetOutputPort("V_WE_corrected").Eval(context), [0, 0, 0, 0.0, -0.04, 0.0], atol=1e-9
    )


def test_a_command_leaving_the_cylinder_is_stopped_at_the_wall():
    # On the wall (6 mm out along Center x), commanding 20 mm/s outward (World +y) and 10 mm/s
    # inward along the axis: the outward part is removed, the axial part passes; the force
    # is the damping on the outward velocity b * 0.02 = 2 N, inward.
    V = [0.0, 0.0, 0.0, 0.0, 0.02, -0.01]
    system, context, _ = make([0.006, 0.0, 0.02], V)
    np.testing.assert_allclose(
        system.GetOutputPort("V_WE_corrected").Eval(context), [0, 0, 0, 0, 0, -0.01], atol=1e-12
    )
    # on the boundary the violation is 0, so at most the damping acts at the TCP and at the rod's
    # crossing of the entry plane (both on the wall): 2 N each
    F = system.GetOutputPort("F_W_fixture").Eval(context)
    assert np.linalg.norm(F) <= 4.0 + 1e-9
    # inside, 1 mm from the wall: the outward motion is limited to 1 mm per period
    system, context, _ = make([0.005, 0.0, 0.02], [0, 0, 0, 0, 1.0, 0.0])
    v = system.GetOutputPort("V_WE_corrected").Eval(context)
    assert v[4] == pytest.approx(0.001 / 0.005, rel=1e-9)


def test_disabled_fixture_passes_everything():
    V = [0.0, 0.0, 0.1, 0.0, 0.02, 0.0]
    system, context, X_WE = make([0.008, 0.0, 0.02], V, enabled=False)
    np.testing.assert_allclose(system.GetOutputPort("V_WE_corrected").Eval(context), V)
    xd = system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0).get_value()
    # rotation about World z by 0.1 rad/s * 5 ms
    a = 0.1 * 0.005
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    np.testing.assert_allclose(xd[3:12].reshape(3, 3), Rz @ X_WE[:3, :3], atol=1e-15)
    desired = system.GetOutputPort("X_WE_desired").Eval(context)
    np.testing.assert_allclose(desired.GetAsMatrix4(), X_WE, atol=1e-15)


def test_update_near_the_wall_uses_the_full_law():
    # 1 mm inside the wall, commanding 1 m/s outward: the update limits the step to 1 mm
    system, context, X_WE = make([0.005, 0.0, 0.02], [0, 0, 0, 0, 1.0, 0.0])
    xd = system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0).get_value()
    np.testing.assert_allclose(xd[:3] - X_WE[:3, 3], [0.0, 0.001, 0.0], atol=1e-12)


# -- the body: the rod axis and the orientation ------------------------------------------------

# the same fixture with delta 0.5 mm, beta 0.5 deg (tool radius 6 mm) and the planned orientation
BODY = dataclasses.replace(VF, lateral_tolerance=0.0005, angle_tolerance=np.deg2rad(0.5),
                           R_ref=R_CT)


def test_the_rod_axis_is_bounded_not_only_the_tcp():
    """The old law let the TCP sit anywhere within the rod radius (6 mm) of line1; the body
    fixture allows delta = 0.5 mm. A TCP 2 mm off line1 (parallel to it) is 1.5 mm out."""
    system, context, _ = make([0.002, 0.0, 0.02], np.zeros(6), vf=BODY, integrate=False)
    assert system.GetOutputPort("violation").Eval(context)[0] == pytest.approx(0.0015, abs=1e-12)
    # returned at k/b * 1.5 mm = 30 mm/s towards the axis (Center -x = World -y)
    np.testing.assert_allclose(system.GetOutputPort("V_WE_corrected").Eval(context),
                               [0, 0, 0, 0, -0.03, 0], atol=1e-12)
    assert system.HasAnyDirectFeedthrough()  # without integrate: a pure function of its inputs


def test_a_tilted_rod_is_caught_at_the_entry_plane():
    """TCP on line1 at 20 mm, rod tilted by 0.4 deg (within beta) about Center y: the axis meets
    the entry plane (s = 50 mm) 30 mm * tan(0.4 deg) = 0.209 mm off: inside. At 1.5 deg tilt
    (beyond beta = 0.5 deg) it is 0.785 mm off: 0.285 mm out, and the orientation is 1 deg out.
    """
    for tilt_deg, off in ((0.4, 0.0), (1.5, 0.03 * np.tan(np.deg2rad(1.5)) - 0.0005)):
        R = rot_y(np.deg2rad(tilt_deg)) @ R_CT  # tilts the rod towards Center +x
        system, context, _ = make([0.0, 0.0, 0.02], np.zeros(6), vf=BODY, R=R, integrate=False)
        assert system.GetOutputPort("violation").Eval(context)[0] == pytest.approx(off, abs=1e-9)
        beyond = max(np.deg2rad(tilt_deg) - BODY.angle_tolerance, 0.0)
        assert system.GetOutputPort("angle_violation").Eval(context)[0] == pytest.approx(
            beyond, abs=1e-9)
    # the tilt beyond beta is turned back at k/b * 1 deg about -Center y (World +x here)
    w = system.GetOutputPort("V_WE_corrected").Eval(context)[:3]
    np.testing.assert_allclose(w, [20.0 * np.deg2rad(1.0), 0, 0], atol=1e-9)


def test_roll_about_the_rod_counts_against_the_angle_tolerance():
    R = rot_x(np.deg2rad(2.0))  # roll about the tool x axis (the rod), in Tool coordinates
    system, context, _ = make([0.0, 0.0, 0.02], np.zeros(6), vf=BODY, R=R_CT @ R,
                              integrate=False)
    assert system.GetOutputPort("violation").Eval(context)[0] == 0.0  # the axis is on line1
    assert system.GetOutputPort("angle_violation").Eval(context)[0] == pytest.approx(
        np.deg2rad(1.5), abs=1e-9)


def test_a_sideways_push_inside_the_mouth_stops_at_delta():
    """On the axis, 0.5 mm off (at the tolerance), pushing outward at 40 mm/s and feeding at
    10 mm/s: the outward part goes, the feed passes; 0.2 mm inside, the push is cut to 0.2 mm
    per period (40 mm/s)."""
    V = [0, 0, 0, 0, 0.04, -0.01]  # World +y = Center +x, outward
    system, context, _ = make([0.0005, 0.0, 0.02], V, vf=BODY, integrate=False)
    np.testing.assert_allclose(system.GetOutputPort("V_WE_corrected").Eval(context),
                               [0, 0, 0, 0, 0, -0.01], atol=1e-12)
    system, context, _ = make([0.0003, 0.0, 0.02], [0, 0, 0, 0, 0.1, 0], vf=BODY,
                              integrate=False)
    v = system.GetOutputPort("V_WE_corrected").Eval(context)
    assert v[4] == pytest.approx(0.0002 / 0.005, rel=1e-9)


def test_core_batch_matches_the_system_and_a_rotation_command_is_limited():
    """correct_twist (the batched core) on the same poses as the LeafSystem, and a command that
    spins the rod about the TCP (moving its entry point sideways) is limited like a push."""
    rng = np.random.default_rng(3)
    p = rng.uniform(-0.002, 0.002, (50, 3)) + [0, 0, 0.02]
    R = np.array([rot_y(a) @ rot_x(b) @ R_CT for a, b in rng.uniform(-0.03, 0.03, (50, 2))])
    V = rng.uniform(-0.05, 0.05, (50, 6))
    law = BODY.correct_twist(p, R, V, dt=0.005, return_gain=K / B, stiffness=K, damping=B)
    for i in range(0, 50, 7):
        V_W = np.concatenate([X_WC[:3, :3] @ V[i, :3], X_WC[:3, :3] @ V[i, 3:]])
        system, context, _ = make(p[i], V_W, vf=BODY, R=R[i], integrate=False)
        out = system.GetOutputPort("V_WE_corrected").Eval(context)
        np.testing.assert_allclose(out[:3], X_WC[:3, :3] @ law.V[i, :3], atol=1e-12)
        np.testing.assert_allclose(out[3:], X_WC[:3, :3] @ law.V[i, 3:], atol=1e-12)
        assert system.GetOutputPort("violation").Eval(context)[0] == pytest.approx(
            law.violation[i], abs=1e-15)
    # on line1, spinning about Center y at 1 rad/s moves the entry point (30 mm up) at 30 mm/s
    # along Center x: 0.5 mm away is 0.1 m/s per period; the law keeps the spin (within beta)
    # and moves the TCP back so that the entry point goes no faster than allowed
    law = BODY.correct_twist([0, 0, 0.02], R_CT, [0, 1.0, 0, 0, 0, 0], dt=0.005)
    w, v = law.V[0, :3], law.V[0, 3:]
    v_entry = v + np.cross(w, [0, 0, 0.03])
    assert v_entry[0] <= 0.0005 / 0.005 + 1e-12
    # the orientation alone may change by at most beta in one period
    assert np.linalg.norm(w) * 0.005 <= BODY.angle_tolerance + 1e-12


@settings(max_examples=60, deadline=None)
@given(
    offset=arrays(float, (2,), elements=st.floats(-0.003, 0.003)),
    tilt=arrays(float, (2,), elements=st.floats(-0.02, 0.02)),
    depth=st.floats(0.0, 0.07),
    V=arrays(float, (6,), elements=st.floats(-0.2, 0.2)),
)
def test_one_period_of_the_corrected_twist_never_leaves_more_than_it_started(offset, tilt,
                                                                            depth, V):
    """Property: stepping the corrected twist for one period (first-order rotation, as the law
    predicts it), a body inside the fixture stays inside and one outside gets no further out,
    within 10 um, for commands up to 20x the feed speed and in any direction, poses up to 2.5 mm
    and 1.1 deg out. (The return towards the fixture is checked by hand above.)"""
    R = rot_y(tilt[0]) @ rot_x(tilt[1]) @ R_CT
    p = np.array([offset[0], offset[1], depth])
    dt, g = 0.005, K / B
    law = BODY.correct_twist(p, R, V, dt=dt, return_gain=g)
    w, v = law.V[0, :3], law.V[0, 3:]
    p1 = p + v * dt
    R1 = (np.eye(3) + dt * np.cross(np.eye(3), w)) @ R
    before, after = BODY.body_violation(transform(R, p)), BODY.body_violation(transform(R1, p1))
    assert after[0][0] <= before[0][0] + 1e-5


def test_a_tool_held_at_the_wall_pushing_out_feels_the_damping():
    # The law keeps the commanded pose inside, so a tool held at the fixture's limit sits on the
    # wall only to rounding (here 1 pm inside): pushing out at 20 mm/s it feels b * 0.02 = 2 N
    # at the TCP and 2 N at the rod's crossing of the entry plane (both on the wall), inward;
    # 1 mm inside, nothing.
    V = [0.0, 0.0, 0.0, 0.0, 0.02, 0.0]
    system, context, _ = make([0.006 - 1e-12, 0.0, 0.02], V)
    np.testing.assert_allclose(system.GetOutputPort("F_W_fixture").Eval(context),
                               [0.0, -4.0, 0.0], atol=1e-9)
    system, context, _ = make([0.005, 0.0, 0.02], V)
    np.testing.assert_allclose(system.GetOutputPort("F_W_fixture").Eval(context), 0.0)
    # held there and pushing for 20 periods: it stays on the wall and keeps feeling 4 N
    system, context, _ = make([0.005, 0.0, 0.02], V)
    for _ in range(20):
        context.SetDiscreteState(0, system.EvalUniquePeriodicDiscreteUpdate(context)
                                 .get_vector(0).get_value())
        system.GetInputPort("X_WE").FixValue(context, AbstractValue.Make(
            system.GetOutputPort("X_WE_desired").Eval(context)))
    assert system.GetOutputPort("violation").Eval(context)[0] < 1e-12
    np.testing.assert_allclose(system.GetOutputPort("F_W_fixture").Eval(context),
                               [0.0, -4.0, 0.0], atol=1e-9)
