"""FPSM estimator: the actuator's lines (Eq. 19) against the FPSM (Eq. 13), core and system."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform

from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import transform
from implantplan.systems.teleop.fpsm_estimator import FpsmEstimator, ToolLines, tool_safety

R, D12 = 0.006, 0.031
CYL = Fpsm.cylinder(0.05, 0.0, 0.1, slices=11)
# Tool x (the rod) along Center +z (out of the mouth), Tool z along Center +x, Tool y = -Center y
R_CT = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


def pose(origin):
    return transform(R_CT, np.asarray(origin, dtype=float))


def test_contra_angle_lines_are_eq19():
    lines = ToolLines.contra_angle(R, D12)
    np.testing.assert_allclose(lines.start_T, [[R, 0, 0], [R, 0, -D12]])
    np.testing.assert_allclose(lines.direction_T, [[1, 0, 0], [1, 0, 0]])
    np.testing.assert_allclose(lines.radius, [R, 0.0])
    with pytest.raises(InputError, match="implant_length"):
        ToolLines.contra_angle(R, 0.0)


def test_rod_on_the_axis_by_hand():
    # T at (0, 0, 44 mm): P1 = T + r x_T = (0, 0, 50 mm) on the axis, so every sample of line1
    # sits at 50 - 6 = 44 mm from the shrunk wall: f_safe = 0.5*44 + 0.5*44 = 44 mm.
    # P2 = T + r x_T - d12 z_T = (-31, 0, 50) mm: 19 mm from the wall all the way up:
    # f_safe = 19 mm; min d_safe = 19 mm; far from the 1 mm alarm margin.
    s = tool_safety(CYL, pose([0.0, 0.0, 0.044]), ToolLines.contra_angle(R, D12), method="paper")
    assert s.f_safe_line1[0] == pytest.approx(0.044, abs=1e-9)
    assert s.f_safe_line2[0] == pytest.approx(0.019, abs=1e-9)
    assert s.min_d_safe[0] == pytest.approx(0.019, abs=1e-9)
    assert not s.alarm[0]


def test_alarm_near_and_in_the_wall_batched():
    # shift the tool by +x (towards the wall on line2's side is -x): line2 at x = -31 + dx mm ...
    # move it by -dx along Center x: line2 is at 31 + dx mm from the axis, 19 - dx from the wall.
    dx = np.array([0.0, 0.0185, 0.019, 0.025])
    X = np.stack([pose([-d, 0.0, 0.044]) for d in dx])
    s = tool_safety(CYL, X, ToolLines.contra_angle(R, D12), alarm_margin=0.001, method="paper")
    np.testing.assert_allclose(s.min_d_safe, 0.019 - dx, atol=1e-9)
    assert s.alarm.tolist() == [False, True, True, True]
    assert s.f_safe_line2[3] == pytest.approx(0.5 * (0.019 - 0.025), abs=1e-9)  # collision


def test_sound_clearance_of_the_whole_tool_by_hand():
    # The same poses: the implant axis (radius 0) runs from (0, 0, 50) to (-31 + dx, 0, 50) mm
    # in the 50 mm cylinder, the rod and head (6 mm) on the axis: the tool's true clearance is
    # 19 - dx mm. The certified value never exceeds it, is resolved below RESOLVE, and the
    # alarm (1 mm) fires at 0.5 mm and in the wall.
    from implantplan.systems.placement.tool_clearance import RESOLVE, clearance_field

    dx = np.array([0.0, 0.0185, 0.019, 0.025])
    X = np.stack([pose([-d, 0.0, 0.044]) for d in dx])
    s = tool_safety(CYL, X, ToolLines.contra_angle(R, D12), alarm_margin=0.001)
    f = clearance_field(CYL)
    slack = f.spacing * np.sqrt(3) / 2 + f.spacing / 4 + f.cover
    true = 0.019 - dx
    assert np.all(s.min_d_safe[true > 0] <= true[true > 0])
    assert s.min_d_safe[0] >= RESOLVE - slack
    assert s.min_d_safe[1] >= 0.0005 - slack
    assert s.alarm.tolist() == [False, True, True, True]
    # Eq. 19's line check misses the head: a tool whose head (radius 6 mm at the origin)
    # touches the throat while both lines are clear
    Y = pose([0.0, 0.0, 0.004])  # head sphere reaches z = -2 mm, below the bottom slice
    assert tool_safety(CYL, Y, ToolLines.contra_angle(R, D12)).min_d_safe[0] < 0
    assert tool_safety(CYL, Y, ToolLines.contra_angle(R, D12), method="paper").min_d_safe[0] > 0


def test_tool_outside_the_mouth_is_safe():
    s = tool_safety(CYL, pose([0.0, 0.0, 0.2]), ToolLines.contra_angle(R, D12))
    assert np.isinf(s.f_safe_line1[0]) and not s.alarm[0]
    # the whole tool is 100 mm above the opening: certified free beyond the resolved level
    from implantplan.systems.placement.tool_clearance import RESOLVE

    assert s.min_d_safe[0] >= RESOLVE


def test_system_with_a_center_frame_offset():
    X_WC = transform(np.eye(3), [1.0, 2.0, 0.5])
    system = FpsmEstimator(CYL, X_WC, ToolLines.contra_angle(R, D12), alarm_margin=0.02,
                           method="paper")
    context = system.CreateDefaultContext()
    X_WT = X_WC @ pose([0.0, 0.0, 0.044])
    system.GetInputPort("X_WT").FixValue(context, AbstractValue.Make(RigidTransform(X_WT)))
    np.testing.assert_allclose(
        system.GetOutputPort("safety").Eval(context), [0.044, 0.019, 0.019], atol=1e-9
    )
    # the margin is 20 mm here, so 19 mm of clearance already alarms
    assert system.GetOutputPort("alarm").Eval(context)[0] == 1.0
    X_out = X_WC @ pose([0.0, 0.0, 0.3])
    system.GetInputPort("X_WT").FixValue(context, AbstractValue.Make(RigidTransform(X_out)))
    np.testing.assert_allclose(
        system.GetOutputPort("safety").Eval(context), [FpsmEstimator.FAR] * 3
    )
    assert system.GetOutputPort("alarm").Eval(context)[0] == 0.0


def test_periodic_estimator_holds_the_last_estimate():
    system = FpsmEstimator(CYL, np.eye(4), ToolLines.contra_angle(R, D12), period=0.02,
                           method="paper")
    context = system.CreateDefaultContext()
    system.GetInputPort("X_WT").FixValue(
        context, AbstractValue.Make(RigidTransform(pose([0.0, 0.0, 0.044])))
    )
    # before the first update the state says "far, no alarm"
    np.testing.assert_allclose(system.GetOutputPort("safety").Eval(context), [1e3] * 3)
    update = system.EvalUniquePeriodicDiscreteUpdate(context)
    context.SetDiscreteState(0, update.get_vector(0).get_value())
    np.testing.assert_allclose(
        system.GetOutputPort("safety").Eval(context), [0.044, 0.019, 0.019], atol=1e-9
    )
    assert system.GetOutputPort("alarm").Eval(context)[0] == 0.0
    with pytest.raises(InputError, match="period"):
        FpsmEstimator(CYL, np.eye(4), period=0.0)


def test_system_is_the_core_at_every_pose_and_refuses_a_scaled_pose():
    """The LeafSystem's one compiled call per estimate gives tool_safety's values bit for bit
    (the sound clearance of the whole tool), and a scaled "pose" is refused as the core
    refuses it (it would shrink the tool and pass as safe)."""
    lines = ToolLines.contra_angle(R, D12)
    system = FpsmEstimator(CYL, np.eye(4), lines, alarm_margin=0.01)
    context = system.CreateDefaultContext()
    port = system.GetInputPort("X_WT")
    rng = np.random.default_rng(3)
    for z in np.linspace(-0.02, 0.2, 12):
        X = pose([rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), z])
        port.FixValue(context, AbstractValue.Make(RigidTransform(X)))
        core = tool_safety(CYL, X, lines, alarm_margin=0.01)
        want = np.clip([core.f_safe_line1[0], core.f_safe_line2[0], core.min_d_safe[0],
                        float(core.alarm[0])], -FpsmEstimator.FAR, FpsmEstimator.FAR)
        np.testing.assert_array_equal(system.estimate(context), want)
    scaled = pose([0.0, 0.0, 0.044])
    scaled[:3, :3] *= 0.9
    port.FixValue(context, AbstractValue.Make(RigidTransform(scaled)))
    with pytest.raises(InputError, match="proper rotation"):
        system.estimate(context)
