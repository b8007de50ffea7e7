"""Master device core (scripted operator, incremental mapping, CSV) and the MasterDevice system."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from implantplan.systems.errors import InputError
from implantplan.systems.frames import rot_z
from implantplan.systems.teleop.master_device import (
    IncrementalMapping,
    MasterDevice,
    MasterMotion,
    Operator,
    feeding_runs,
    load_csv,
    save_csv,
    scripted_feed,
)

START = np.array([0.10, -0.02, 0.30])
TARGET = np.array([0.10, -0.02, 0.25])  # a 50 mm feed along -z


def test_incremental_mapping_by_hand():
    # R_WM = 90 deg about z: master x -> world y; scale 0.5
    m = IncrementalMapping(scale=0.5, R_WM=rot_z(np.pi / 2))
    np.testing.assert_allclose(m.to_world([1.0, 0.0, 0.0]), [0.0, 0.5, 0.0], atol=1e-15)
    np.testing.assert_allclose(m.to_world([0.0, 2.0, 0.0]), [-1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(m.to_master(m.to_world([0.3, -0.2, 0.7])), [0.3, -0.2, 0.7])
    with pytest.raises(InputError, match="scale"):
        IncrementalMapping(scale=0.0)
    with pytest.raises(InputError, match="R_WM"):
        IncrementalMapping(R_WM=np.diag([1.0, 1.0, -1.0]))


def test_scripted_feed_starts_still_ends_on_target_and_overshoots():
    op = Operator(overshoot=(0.002, 0.002))
    motion = scripted_feed(START, TARGET, seed=3, operator=op)
    d_W = IncrementalMapping().to_world(motion.p_M - motion.p_M[0])
    np.testing.assert_allclose(d_W[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(START + d_W[-1], TARGET, atol=1e-12)
    axial = d_W @ np.array([0.0, 0.0, -1.0])  # progress along the feed
    assert axial.max() == pytest.approx(0.050 + 0.002, abs=1e-6)  # the 2 mm overshoot
    # the jitter is lateral: bounded and zero at the ends
    lateral = np.linalg.norm(d_W[:, :2], axis=1)
    assert 0 < lateral.max() < 0.003
    assert lateral[-1] < 1e-12
    # the hand is still for the settle time at the end
    np.testing.assert_allclose(motion.velocity_M()[-int(0.4 / motion.dt):], 0.0, atol=1e-12)


def test_scripted_feed_is_seeded():
    a = scripted_feed(START, TARGET, seed=11)
    b = scripted_feed(START, TARGET, seed=11)
    c = scripted_feed(START, TARGET, seed=12)
    assert np.array_equal(a.p_M, b.p_M)
    assert a.p_M.shape != c.p_M.shape or not np.array_equal(a.p_M, c.p_M)


def test_pauses_stop_the_hand():
    op = Operator(pauses_per_feed=30.0, pause_seconds=(0.5, 0.5), drift=0.0, tremor=0.0)
    calm = Operator(pauses_per_feed=0.0, drift=0.0, tremor=0.0, overshoot=(0.0, 0.0))
    paused = scripted_feed(START, TARGET, seed=1, operator=op)
    plain = scripted_feed(START, TARGET, seed=1, operator=calm)
    # 50 mm at 10 mm/s is a 5 s stroke; pauses of 0.5 s each add up on top of it
    assert plain.duration == pytest.approx(5.0 + 0.5, abs=0.01)
    assert paused.duration > plain.duration + 5.0
    still = np.linalg.norm(paused.velocity_M(), axis=1) < 1e-9
    assert still.sum() * paused.dt > 5.0


def test_feeding_runs_are_independent_and_prefix_stable():
    ten = feeding_runs(START, TARGET, runs=10, seed=5)
    three = feeding_runs(START, TARGET, runs=3, seed=5)
    assert len(ten) == 10
    for a, b in zip(three, ten[:3], strict=True):
        assert np.array_equal(a.p_M, b.p_M)
    assert len({m.p_M.shape[0] for m in ten}) > 1  # pauses differ between runs
    with pytest.raises(InputError, match="runs"):
        feeding_runs(START, TARGET, runs=0)


@settings(max_examples=20, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=30), st.floats(1e-3, 0.1))
def test_csv_round_trip(values, dt):
    n = len(values) // 3
    motion = MasterMotion(dt=dt, p_M=np.array(values[: 3 * n]).reshape(n, 3))
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = save_csv(Path(tmp) / "m.csv", motion)
        back = load_csv(path)
    assert back.dt == pytest.approx(dt, rel=1e-9)
    assert np.array_equal(back.p_M, motion.p_M)


def test_csv_errors_name_the_problem(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_csv(tmp_path / "none.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,y,z\n0,0,0,0\n")
    with pytest.raises(InputError, match="header"):
        load_csv(bad)
    bad.write_text("t_s,x_m,y_m,z_m\n0,0,0,0\n0.1,0,0,0\n0.3,0,0,0\n")
    with pytest.raises(InputError, match="uniformly"):
        load_csv(bad)


def test_master_device_system_outputs_the_mapped_samples():
    p_M = np.array([[0.0, 0.0, 0.0], [0.001, 0.0, 0.0], [0.001, 0.002, 0.0], [0.001, 0.002, 0.0]])
    motion = MasterMotion(dt=0.01, p_M=p_M)
    system = MasterDevice(motion, IncrementalMapping(scale=2.0, R_WM=rot_z(np.pi / 2)))
    context = system.CreateDefaultContext()
    V = system.GetOutputPort("V_WE_command")
    off = system.GetOutputPort("p_WE_offset")
    context.SetTime(0.005)  # sample 0: master moves +1 mm in x over 10 ms -> 0.1 m/s
    # world: scale 2, x -> y: v_W = (0, 0.2, 0)
    np.testing.assert_allclose(V.Eval(context), [0, 0, 0, 0.0, 0.2, 0.0], atol=1e-12)
    np.testing.assert_allclose(off.Eval(context), 0.0, atol=1e-15)
    context.SetTime(0.015)  # sample 1: master +2 mm in y -> world -x at 0.4 m/s
    np.testing.assert_allclose(V.Eval(context), [0, 0, 0, -0.4, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(off.Eval(context), [0.0, 0.002, 0.0], atol=1e-15)
    context.SetTime(10.0)  # after the end: still
    np.testing.assert_allclose(V.Eval(context), 0.0, atol=1e-15)
    np.testing.assert_allclose(off.Eval(context), [-0.004, 0.002, 0.0], atol=1e-15)
    np.testing.assert_allclose(system.GetOutputPort("p_M").Eval(context), p_M[-1])


def test_master_device_motion_is_a_context_parameter():
    """One system, two contexts, two motions: each context replays its own (hand-derived
    velocities: 1 mm per 10 ms = 0.1 m/s, 3 mm per 20 ms = 0.15 m/s), the default one the hand at
    rest when built without a motion; a non-motion is an input error naming the field."""
    system = MasterDevice()
    V = system.GetOutputPort("V_WE_command")
    a, b = system.CreateDefaultContext(), system.CreateDefaultContext()
    np.testing.assert_allclose(V.Eval(a), 0.0)
    system.set_motion(a, MasterMotion(dt=0.01, p_M=[[0, 0, 0], [0.001, 0, 0]]))
    system.set_motion(b, MasterMotion(dt=0.02, p_M=[[0, 0, 0], [0, 0, 0.003]]))
    for c in (a, b):
        c.SetTime(0.005)
    np.testing.assert_allclose(V.Eval(a), [0, 0, 0, 0.1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(V.Eval(b), [0, 0, 0, 0, 0, 0.15], atol=1e-12)
    assert system.motion_in(b).dt == 0.02 and system.motion.dt == 1.0
    with pytest.raises(InputError, match="motion"):
        system.set_motion(a, np.zeros((3, 3)))


def test_operator_finishes_by_eye_after_the_script():
    from pydrake.common.value import AbstractValue
    from pydrake.math import RigidTransform

    motion = MasterMotion(dt=0.01, p_M=np.zeros((3, 3)))
    target = np.array([0.1, 0.2, 0.3])
    system = MasterDevice(motion, target_W=target, finish_gain=2.0, finish_speed=0.005)
    context = system.CreateDefaultContext()
    port = system.GetInputPort("X_WE_measured")
    V = system.GetOutputPort("V_WE_command")
    # 1 mm short along x: v = 2 * 0.001 = 2 mm/s towards the target (below the 5 mm/s cap)
    port.FixValue(context, AbstractValue.Make(RigidTransform(target - [0.001, 0.0, 0.0])))
    context.SetTime(0.01)  # during the script: the script's (zero) velocity
    np.testing.assert_allclose(V.Eval(context), 0.0)
    context.SetTime(1.0)
    np.testing.assert_allclose(V.Eval(context), [0, 0, 0, 0.002, 0.0, 0.0], atol=1e-15)
    # 10 mm away: capped at 5 mm/s
    port.FixValue(context, AbstractValue.Make(RigidTransform(target - [0.0, 0.01, 0.0])))
    np.testing.assert_allclose(V.Eval(context), [0, 0, 0, 0.0, 0.005, 0.0], atol=1e-15)


@settings(max_examples=20, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=12, max_size=60), st.floats(1e-3, 0.1))
def test_csv_round_trip_with_rotation(values, dt):
    n = len(values) // 6
    data = np.array(values[: 6 * n]).reshape(n, 6)
    motion = MasterMotion(dt=dt, p_M=data[:, :3], r_M=data[:, 3:])
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = save_csv(Path(tmp) / "m.csv", motion)
        assert path.read_text().startswith("t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad\n")
        back = load_csv(path)
    assert back.dt == pytest.approx(dt, rel=1e-9)
    assert np.array_equal(back.p_M, motion.p_M)
    assert np.array_equal(back.r_M, motion.r_M)


def test_old_four_column_files_load_and_replay_unchanged(tmp_path):
    """A file written before the rotation columns: it loads without an orientation part, is
    written back byte for byte, and MasterDevice replays it with zero angular velocity (the
    same translation as before)."""
    text = "t_s,x_m,y_m,z_m\n0.0,0.0,0.0,0.0\n0.01,0.001,0.0,0.0\n0.02,0.001,0.002,0.0\n"
    old = tmp_path / "old.csv"
    old.write_text(text)
    motion = load_csv(old)
    assert motion.r_M is None
    np.testing.assert_allclose(motion.angular_velocity_M(), 0.0)
    assert save_csv(tmp_path / "again.csv", motion).read_text() == text
    system = MasterDevice(motion, IncrementalMapping(scale=2.0, R_WM=rot_z(np.pi / 2)))
    context = system.CreateDefaultContext()
    context.SetTime(0.015)
    np.testing.assert_allclose(system.GetOutputPort("V_WE_command").Eval(context),
                               [0, 0, 0, -0.4, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(system.GetOutputPort("r_M").Eval(context), 0.0)


def test_master_device_turns_unscaled_through_R_WM():
    """w_W = R_WM w_M, not scaled by the motion scale: 0.01 rad per 10 ms about M's x is
    1 rad/s about World y under a 90 deg turn about z (hand-derived)."""
    p_M = np.zeros((3, 3))
    r_M = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.01, 0.0, 0.02]])
    motion = MasterMotion(dt=0.01, p_M=p_M, r_M=r_M)
    np.testing.assert_allclose(motion.angular_velocity_M(), [[1, 0, 0], [0, 0, 2], [0, 0, 0]])
    system = MasterDevice(motion, IncrementalMapping(scale=2.0, R_WM=rot_z(np.pi / 2)))
    context = system.CreateDefaultContext()
    V = system.GetOutputPort("V_WE_command")
    context.SetTime(0.005)
    np.testing.assert_allclose(V.Eval(context), [0.0, 1.0, 0.0, 0, 0, 0], atol=1e-12)
    context.SetTime(0.015)
    np.testing.assert_allclose(V.Eval(context), [0.0, 0.0, 2.0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(system.GetOutputPort("r_M").Eval(context), r_M[1])
    context.SetTime(1.0)
    np.testing.assert_allclose(V.Eval(context), 0.0)


def test_rotation_columns_errors_name_the_problem(tmp_path):
    with pytest.raises(InputError, match="r_M"):
        MasterMotion(dt=0.01, p_M=np.zeros((3, 3)), r_M=np.zeros((2, 3)))
    with pytest.raises(InputError, match="r_M"):
        MasterMotion(dt=0.01, p_M=np.zeros((2, 3)), r_M=[[0, 0, 0], [np.nan, 0, 0]])
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,x_m,y_m,z_m,rx_rad\n0,0,0,0,0\n0.1,0,0,0,0\n")
    with pytest.raises(InputError, match="header"):
        load_csv(bad)
    bad.write_text("t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad\n0,0,0,0,0,0,0\n0.1,0,0,0\n")
    with pytest.raises(InputError, match="7 columns"):
        load_csv(bad)


def test_scripted_operator_does_not_turn():
    motion = scripted_feed(START, TARGET, seed=2)
    assert motion.r_M is None
    system = MasterDevice(motion)
    context = system.CreateDefaultContext()
    V = system.GetOutputPort("V_WE_command")
    for t in np.linspace(0.0, motion.duration, 50):
        context.SetTime(t)
        assert np.all(V.Eval(context)[:3] == 0.0)
