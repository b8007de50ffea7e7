"""The awake patient's guard next to the safety supervisor (DESIGN.md section 7).

Two things the tracked head changes for the supervisor:

1. **Margin.** The arm follows the *tracked* head: between the true and the tracked head there
   is the camera's lag (latency plus one camera period plus one control period, at the head's
   speed) and its noise. The supervisor's margin grows by
   ``extra = speed x (latency + camera period + control period) + tracker error bound``, with
   speed = |v| + reach |w| of the tracked head (an upper bound of the speed of any point of the
   tool's reach).
2. **Stop and back out.** When tracking is lost, or the tracked head moves faster than the arm
   can follow (``follow_speed``), the guard latches *retreat*: it drops the operator's command
   and sends the tool back out along the fixture's axis D (out of the mouth) at
   ``retreat_speed`` until the *measured* tool (in the tracked head frame) has moved
   ``retreat_distance`` along D from where it was at the trigger, then holds. The supervisor
   still filters that twist (near a wall, with the margin grown by a fast head, it may hold
   the tool for a while): the guard keeps asking until the distance is really backed out,
   rather than counting what it asked for. The latch lasts until the run ends (the surgeon
   restarts the feed).

:func:`guard_step` is the core (one step, plain floats); :class:`HeadGuard` the LeafSystem.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError


@dataclass(frozen=True)
class GuardSettings:
    """The guard's settings (SI units).

    Attributes:
        follow_speed: tracked head speed (m/s) beyond which the arm is not asked to follow.
        retreat_speed: back-out speed along the fixture's axis (m/s).
        retreat_distance: how far to back out (m).
        reach: lever (m) for the angular part of the head's speed.
    """

    follow_speed: float = 0.03
    retreat_speed: float = 0.02
    retreat_distance: float = 0.01
    reach: float = 0.1

    def __post_init__(self):
        for name in ("follow_speed", "retreat_speed", "retreat_distance", "reach"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"guard.{name}", f"expected a finite value > 0, got {v}")


def head_speed(V_head: np.ndarray, reach: float) -> np.ndarray:
    """(n,) |v| + reach |w| of head twists (n, 6) [w; v] (m/s)."""
    V = np.atleast_2d(np.asarray(V_head, dtype=float))
    return np.linalg.norm(V[:, 3:], axis=1) + reach * np.linalg.norm(V[:, :3], axis=1)


def guard_step(state: np.ndarray, V_cmd: np.ndarray, speed: float, lost: bool, t: float,
               settings: GuardSettings, axis_W: np.ndarray, dt: float, p_tool: np.ndarray):
    """One guard update. ``state`` (7) = [mode (0 feed, 1 retreat), backed out (m, measured
    along ``axis_W`` from the trigger), trigger time (s, -1 none), trigger cause (0 none, 1 lost
    tracking, 2 head too fast), the tool's position at the trigger (3)]; ``p_tool`` (3): the
    measured tool position now (tracked head frame).

    Returns (new state, the twist to pass on (6,))."""
    st = np.array(state, dtype=float).reshape(7)
    p = np.asarray(p_tool, dtype=float).reshape(3)
    if st[0] < 0.5 and (lost or speed > settings.follow_speed):
        st[0], st[2], st[3] = 1.0, t, 1.0 if lost else 2.0
        st[4:7] = p
    if st[0] < 0.5:
        return st, np.asarray(V_cmd, dtype=float)
    st[1] = max(st[1], float((p - st[4:7]) @ axis_W))
    V = np.zeros(6)
    if st[1] < settings.retreat_distance:  # on at full speed: the tool's lag overshoots the
        V[3:] = axis_W * settings.retreat_speed  # distance by a period or two (<= 0.2 mm)
    return st, V


class HeadGuard(LeafSystem):
    """Margin growth and the stop-and-back-out mode of the tracked head.

    .. pydrake_system::

        name: HeadGuard
        input_ports:
        - V_WE_corrected
        - V_WHead_estimated
        - lost
        - X_WE
        output_ports:
        - V_WE_guarded
        - margin_extra
        - mode

    ``V_WE_corrected`` (6): the fixture's twist [w; v] (head-fixed World). ``V_WHead_estimated``
    (6) and ``lost`` (1): the tracker's. ``X_WE`` (abstract RigidTransform): the measured tool
    pose in the tracked head frame (the back-out is measured on it). ``V_WE_guarded`` (6): the
    twist for the supervisor (the input while feeding; the back-out twist in retreat).
    ``margin_extra`` (1, m): what the supervisor adds to its margin (module notes).
    ``mode`` (4): [mode (0 feed, 1 retreat), backed out (m, measured), trigger time (s, -1
    before), cause (1 lost tracking, 2 head too fast)].

    Args:
        axis_W: (3,) the fixture's axis D out of the mouth, in (head-fixed) World.
        lag: latency + camera period + control period (s).
        error_bound: the tracker's error bound (m).
        settings: :class:`GuardSettings`.
        period: update period (s), the supervisor's.
    """

    def __init__(self, axis_W, *, lag: float, error_bound: float,
                 settings: GuardSettings | None = None, period: float = 0.005):
        super().__init__()
        a = np.asarray(axis_W, dtype=float).reshape(3)
        self._axis = a / np.linalg.norm(a)
        self._lag, self._err = float(lag), float(error_bound)
        self._s = settings or GuardSettings()
        self._dt = float(period)
        self._V = self.DeclareVectorInputPort("V_WE_corrected", 6)
        self._Vh = self.DeclareVectorInputPort("V_WHead_estimated", 6)
        self._lost = self.DeclareVectorInputPort("lost", 1)
        self._X = self.DeclareAbstractInputPort("X_WE", AbstractValue.Make(RigidTransform()))
        # [mode, backed out, trigger time, cause, the twist passed on (6), margin extra,
        #  the tool's position at the trigger (3)]
        self.DeclareDiscreteState(np.array([0.0, 0.0, -1.0, 0.0, *np.zeros(6), self._err,
                                            *np.zeros(3)]))
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)
        self.DeclareVectorOutputPort("V_WE_guarded", 6, self._calc_V,
                                     prerequisites_of_calc={self.xd_ticket()})
        self.DeclareVectorOutputPort("margin_extra", 1, self._calc_margin,
                                     prerequisites_of_calc={self.xd_ticket()})
        self.DeclareVectorOutputPort("mode", 4, self._calc_mode,
                                     prerequisites_of_calc={self.xd_ticket()})

    def margin_extra(self, speed: float) -> float:
        return speed * self._lag + self._err

    def _update(self, context, discrete_state):
        x = context.get_discrete_state(0).get_value()
        speed = float(head_speed(self._Vh.Eval(context), self._s.reach)[0])
        lost = self._lost.Eval(context)[0] > 0.5
        state = np.concatenate([x[:4], x[11:14]])
        st, V = guard_step(state, self._V.Eval(context), speed, lost, context.get_time(),
                           self._s, self._axis, self._dt, self._X.Eval(context).translation())
        discrete_state.get_mutable_vector(0).SetFromVector(
            np.concatenate([st[:4], V, [self.margin_extra(speed)], st[4:7]]))

    def _calc_V(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(0).get_value()[4:10])

    def _calc_margin(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(0).get_value()[10:11])

    def _calc_mode(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(0).get_value()[:4])
