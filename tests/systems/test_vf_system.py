"""VirtualFixtureForceLaw: the admittance law around a cylinder fixture, tested alone."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform

from implantplan.systems.frames import transform
from implantplan.systems.vf_system import VirtualFixtureForceLaw
from implantplan.systems.virtual_fixture import VirtualFixture

K, B = 2000.0, 100.0  # N/m, N s/m -> return gain 20 1/s
# Fixture along Center +z through the target at the origin, cylinder of radius 6 mm up to the
# entry at 50 mm, then a 30 mm cone of 15 deg.
VF = VirtualFixture(
    origin=[0.0, 0.0, 0.0],
    direction=[0.0, 0.0, 1.0],
    entry_distance=0.05,
    cylinder_radius=0.006,
    segment_lengths=[0.03],
    half_angles=[np.deg2rad(15.0)],
)
X_WC = transform(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [0.5, 0.2, 0.8])


def make(p_C, V_W, *, enabled=True):
    X_WE = X_WC @ transform(np.eye(3), p_C)
    system = VirtualFixtureForceLaw(VF, X_WC, X_WE, stiffness=K, damping=B, enabled=enabled)
    context = system.CreateDefaultContext()
    system.GetInputPort("V_WE_command").FixValue(context, np.asarray(V_W, dtype=float))
    system.GetInputPort("X_WE_measured").FixValue(
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
    assert xd[12] == 0.0  # no violation


def test_a_point_outside_the_cylinder_is_pushed_back_by_the_stated_force():
    # 8 mm from the axis along Center x: 2 mm outside; outward normal = Center x = World y.
    # Still hand (no command): F = -k * 0.002 * n = -4 N along World y; the corrected velocity
    # is the admittance return -(k/b) * 0.002 * n = -0.04 m/s along World y.
    system, context, X_WE = make([0.008, 0.0, 0.02], np.zeros(6))
    context.SetDiscreteState(0, system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0)
                             .get_value())
    assert system.GetOutputPort("violation").Eval(context)[0] == pytest.approx(0.002, abs=1e-12)
    # the update moved the desired pose by the return velocity over one period: 0.2 mm inward
    desired = system.GetOutputPort("X_WE_desired").Eval(context).translation()
    np.testing.assert_allclose(desired - X_WE[:3, 3], [0.0, -0.04 * 0.005, 0.0], atol=1e-12)
    np.testing.assert_allclose(
        system.GetOutputPort("F_W_fixture").Eval(context), [0.0, -4.0, 0.0], atol=1e-9
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
    # on the boundary the violation is 0, so only the damping acts (force() counts d > 0 only)
    F = system.GetOutputPort("F_W_fixture").Eval(context)
    assert np.linalg.norm(F) <= 2.0 + 1e-9
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
