"""The command limits: clip and fault by hand-derived values, the latch, the vectorized series
against the LeafSystem's one-sample rule, the swept-motion bound on an exact geometry."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from implantplan.systems.errors import InputError
from implantplan.systems.teleop import command_limits as C
from implantplan.systems.teleop.command_limits import CommandLimiter, CommandLimits

DT = 0.005
# the round values these tests compute by hand: 50 mm/s, 0.1 rad/s; faults above 5 mm or 0.05 rad
# per period; 0.2 s (the defaults differ only in the angles: 6 deg/s, 3 deg)
LIM = CommandLimits(linear_speed=0.05, angular_speed=0.1, fault_jump=0.005, fault_turn=0.05,
                    clear_after=0.2)


def twist(w=(0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0)):
    return np.concatenate([w, v]).astype(float)


def test_a_fast_command_is_scaled_to_the_limit_with_its_direction():
    # 100 mm/s along x: twice the limit -> half of it, 50 mm/s along x
    # 3-4-0 at 500 mm/s with 0.2 rad/s about z: the linear part wants 0.1, the angular 0.5
    V = np.array([twist(v=(0.1, 0, 0)), twist(w=(0, 0, 0.2), v=(0.3, 0.4, 0.0)),
                  twist(w=(0.08, 0, 0), v=(0.0, 0.03, 0.0))])
    out = C.classify(V, LIM, DT)
    np.testing.assert_array_equal(out.status, [C.CLIPPED, C.CLIPPED, C.CLEAN])
    np.testing.assert_allclose(out.scale, [0.5, 0.1, 1.0])
    np.testing.assert_allclose(out.V[0], twist(v=(0.05, 0, 0)))
    np.testing.assert_allclose(out.V[1], twist(w=(0, 0, 0.02), v=(0.03, 0.04, 0.0)))
    np.testing.assert_array_equal(out.V[2], V[2])  # within the limits: untouched


def test_a_rotation_too_fast_is_clipped_by_the_angular_limit():
    # 0.2 rad/s and 10 mm/s: the angular part binds (0.1 / 0.2 = 0.5)
    out = C.classify(twist(w=(0.2, 0, 0), v=(0.01, 0, 0)), LIM, DT)
    assert out.status[0] == C.CLIPPED and out.scale[0] == pytest.approx(0.5)
    np.testing.assert_allclose(out.V[0], twist(w=(0.1, 0, 0), v=(0.005, 0, 0)))


def test_faults_by_hand():
    V = np.array([
        twist(v=(0.99, 0, 0)),  # 4.95 mm in one period: clipped, not a fault
        twist(v=(0.0, 1.01, 0)),  # 5.05 mm: a jump
        twist(v=(40.0, 0, 0)),  # a 200 mm jump of the handle in one 5 ms sample
        twist(v=(1e9, 0, 0)),
        twist(v=(1e200, 1e200, 0)),  # finite components: a jump (no overflow to "non-finite")
        twist(w=(9.9, 0, 0)),  # 0.0495 rad in one period: clipped
        twist(w=(0, 0, 10.1)),  # 0.0505 rad: a turn
        twist(v=(np.nan, 0, 0)),
        twist(w=(0, -np.inf, 0)),
        twist(w=(1e9, 0, 0), v=(np.inf, 0, 0)),
    ])
    out = C.classify(V, LIM, DT)
    np.testing.assert_array_equal(
        out.status, [C.CLIPPED] + [C.FAULT] * 4 + [C.CLIPPED] + [C.FAULT] * 4)
    np.testing.assert_array_equal(
        out.cause, [0, C.JUMP, C.JUMP, C.JUMP, C.JUMP, 0, C.TURN, C.NON_FINITE, C.NON_FINITE,
                    C.NON_FINITE])
    np.testing.assert_array_equal(out.V[out.status == C.FAULT], 0.0)
    np.testing.assert_allclose(out.V[0], twist(v=(0.05, 0, 0)))


def test_the_latch_holds_until_40_clean_samples():
    # n_clear = ceil(0.2 s / 5 ms) = 40; a fault at sample 3; the 40th clean sample after it
    # (sample 43) passes
    assert LIM.clear_samples(DT) == 40
    V = np.tile(twist(v=(0.01, 0, 0)), (60, 1))
    V[3] = twist(v=(40.0, 0, 0))
    out = C.limit_series(V, LIM, DT)
    held = np.zeros(60, dtype=bool)
    held[3:43] = True
    np.testing.assert_array_equal(out.held, held)
    np.testing.assert_array_equal(out.V[3:43], 0.0)
    np.testing.assert_array_equal(out.V[43:], V[43:])
    np.testing.assert_array_equal(out.fault_samples, [3])
    np.testing.assert_array_equal(out.fault_events, [3])


def test_a_fast_command_while_latched_restarts_the_count():
    # fault at 0; clean 1..10; clipped at 11 (too fast: not back within the limits); clean from
    # 12: the fault clears at 12 + 39 = 51
    V = np.tile(twist(v=(0.01, 0, 0)), (70, 1))
    V[0] = twist(v=(np.nan, 0, 0))
    V[11] = twist(v=(0.2, 0, 0))
    out = C.limit_series(V, LIM, DT)
    assert out.held[:51].all() and not out.held[51:].any()
    # a new fault while latched: one event, two fault samples
    V[20] = twist(v=(10.0, 0, 0))
    out = C.limit_series(V, LIM, DT)
    assert out.held[:60].all() and not out.held[60:].any()
    np.testing.assert_array_equal(out.fault_samples, [0, 20])
    np.testing.assert_array_equal(out.fault_events, [0])
    # after the clear a fast command is clipped again, not held
    V[65] = twist(v=(0.2, 0, 0))
    out = C.limit_series(V, LIM, DT)
    np.testing.assert_allclose(out.V[65], twist(v=(0.05, 0, 0)))


_small = st.floats(min_value=-0.02, max_value=0.02)
_any = st.sampled_from([0.0, 0.01, -0.03, 0.07, 0.5, 2.0, 40.0, 1e9, np.nan, np.inf, -np.inf])
# mostly calm commands (clean), with fast (clipped) and absurd (fault) ones among them
_row = st.one_of(st.tuples(*[_small] * 6), st.tuples(*[_small] * 6), st.tuples(*[_small] * 6),
                 st.tuples(*[_any] * 6))


@settings(max_examples=80, deadline=None)
@given(st.lists(_row, min_size=1, max_size=120), st.integers(min_value=1, max_value=6))
def test_the_one_sample_rule_is_the_vectorized_series(rows, n_clear):
    V = np.array(rows, dtype=float)
    lim = CommandLimits(clear_after=n_clear * DT)
    assert lim.clear_samples(DT) == n_clear
    series = C.limit_series(V, lim, DT)
    latched, run = False, 0
    for k in range(V.shape[0]):
        out, status, cause, latched, run = C.limit_step(V[k], latched, run, lim, DT, n_clear)
        assert status == series.status[k] and cause == series.cause[k]
        assert latched == series.held[k]
        np.testing.assert_allclose(out, series.V[k], rtol=1e-12, atol=0.0)


def test_limits_are_validated_and_read_from_the_case_form():
    with pytest.raises(InputError, match="command_limits.linear_speed"):
        CommandLimits(linear_speed=0.0)
    with pytest.raises(InputError, match="command_limits.clear_after"):
        CommandLimits(clear_after=float("nan"))
    with pytest.raises(InputError, match="fault thresholds"):
        CommandLimits(linear_speed=2.0).check_period(DT)  # 10 mm per period > the 5 mm fault
    lim = CommandLimits.from_dict({"linear_speed_mm_s": 20, "fault_turn_deg": 4.0})
    assert lim.linear_speed == pytest.approx(0.02)
    assert lim.fault_turn == pytest.approx(math.radians(4.0))
    assert lim.angular_speed == CommandLimits().angular_speed  # the one default
    assert CommandLimits.from_dict(lim.to_dict()) == lim
    with pytest.raises(InputError, match="safety.command_limits.speed_mm_s"):
        CommandLimits.from_dict({"speed_mm_s": 20}, "safety.command_limits")
    with pytest.raises(InputError, match="fault_jump_mm"):
        CommandLimits.from_dict({"fault_jump_mm": -1})


def test_the_step_path_by_hand():
    lim = LIM
    # (50 mm/s + 0.172 m x 0.1 rad/s) x 5 ms = 0.336 mm: half of it, 0.168 mm, is what the tool
    # between two steps may lose against its ends
    assert lim.step_path(0.172, DT) == pytest.approx(0.000336)
    # and a point at the reach travels that far when the turn carries it along v: the rod's end
    # (0.172, 0, 0) turning about z at 0.1 rad/s moves along +y, as v = 50 mm/s does
    V = twist(w=(0, 0, 0.1), v=(0, 0.05, 0))
    s = np.linspace(0.0, 1.0, 2001)
    x = np.stack([0.172 * np.cos(0.1 * s * DT), 0.172 * np.sin(0.1 * s * DT) + 0.05 * s * DT],
                 axis=1)
    path = np.linalg.norm(np.diff(x, axis=0), axis=1).sum()
    assert np.allclose(C.clip_twist(V, lim), V)
    assert path == pytest.approx(lim.step_path(0.172, DT), rel=1e-6)


def _capsule_plane_clearance(X, a, b, r):
    """Exact clearance of capsules (segments a-b in the tool frame, radii r) above the plane
    z = 0 of World: the lowest end point's height minus the radius."""
    z = (np.einsum("ij,cj->ci", X[:3, :3], a)[:, 2], np.einsum("ij,cj->ci", X[:3, :3], b)[:, 2])
    return float((np.minimum(z[0], z[1]) + X[2, 3] - r).min())


@settings(max_examples=200, deadline=None)
@given(st.integers(min_value=0, max_value=2**32 - 1))
def test_the_tool_between_two_limited_steps_keeps_its_ends_clearance_less_half_a_path(seed):
    """Exact geometry (capsules above a plane): any pose between X and X stepped by a twist at
    the limits keeps min(ends) - S / 2."""
    rng = np.random.default_rng(seed)
    a = np.array([[0.006, 0, 0], [0, 0, 0], [0.006, 0, 0]])
    b = np.array([[0.166, 0, 0], [0, 0, 0], [0.006, 0, -0.031]])
    r = np.array([0.006, 0.008, 0.002])
    reach = float(np.max(np.maximum(np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)) + r))
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    X = np.eye(4)
    X[:3, :3], X[2, 3] = R, 0.2
    V = rng.standard_normal(6)
    V = C.clip_twist(V * 10.0, LIM)  # at the limits (one of them binds)
    S = LIM.step_path(reach, DT)

    def at(s):
        Y = X.copy()
        Y[:3, 3] += V[3:] * s * DT
        angle = np.linalg.norm(V[:3]) * s * DT
        k = V[:3] / np.linalg.norm(V[:3])
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        Y[:3, :3] = (np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K) @ R
        return _capsule_plane_clearance(Y, a, b, r)

    ends = min(at(0.0), at(1.0))
    between = min(at(s) for s in np.linspace(0.0, 1.0, 33))
    assert between >= ends - 0.5 * S - 1e-15


def test_the_limiter_alone():
    system = CommandLimiter(LIM, period=DT)
    context = system.CreateDefaultContext()
    port = system.GetInputPort("V_WE_command")
    out = system.GetOutputPort("V_WE_limited")
    status = system.GetOutputPort("command_status")
    port.FixValue(context, twist(v=(0.0, 0.1, 0.0)))
    np.testing.assert_allclose(out.Eval(context), twist(v=(0.0, 0.05, 0.0)))
    np.testing.assert_array_equal(status.Eval(context), [C.CLEAN, 0, 0, 0, 0, -1.0])
    # a NaN: held at zero, recorded by the update
    port.FixValue(context, twist(v=(np.nan, 0.0, 0.0)))
    np.testing.assert_array_equal(out.Eval(context), 0.0)
    context.SetTime(1.0)
    context.SetDiscreteState(0, system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0)
                             .get_value())
    np.testing.assert_array_equal(status.Eval(context), [C.FAULT, C.NON_FINITE, 1, 1, 1, 1.0])
    # a calm command is held while latched ...
    port.FixValue(context, twist(v=(0.0, 0.0, 0.01)))
    for _ in range(39):
        np.testing.assert_array_equal(out.Eval(context), 0.0)
        context.SetDiscreteState(0, system.EvalUniquePeriodicDiscreteUpdate(context)
                                 .get_vector(0).get_value())
    # ... and the 40th clean sample passes
    np.testing.assert_allclose(out.Eval(context), twist(v=(0.0, 0.0, 0.01)))
    context.SetDiscreteState(0, system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0)
                             .get_value())
    assert status.Eval(context)[2] == 0.0  # no longer held
    assert status.Eval(context)[3] == 1 and status.Eval(context)[4] == 1
