"""The virtual-fixture force law as a Drake LeafSystem (thin adapter over systems.virtual_fixture).

Admittance law (seed 000 Sec. 2.2, its ref. [12]). The master commands a tool velocity v_cmd;
with the measured tool point p (the TCP, in the fixture's Center frame) the fixture

1. passes motion along the axis and inside the allowed region, and limits the outward normal
   component to what reaches the boundary within one period (``VirtualFixture.correct_velocity``
   with ``dt``);
2. pulls a point that is outside back with the admittance of a spring-damper: a force
   F = -(k * violation + b * max(v.n, 0)) n acting through an admittance 1/b gives the return
   velocity -(k / b) * violation * n (``return_gain = k / b``).

The corrected velocity is integrated at the fixture's period into the desired tool pose that
drives differential IK (incremental mapping: the command moves the *desired* pose, the measured
pose feeds the fixture). The force F (evaluated with the commanded velocity) is also an output:
it is what a haptic master would render to the operator.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError
from implantplan.systems.frames import invert
from implantplan.systems.virtual_fixture import VirtualFixture


def _rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """exp([w]x) by Rodrigues' formula."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


class VirtualFixtureForceLaw(LeafSystem):
    """Corrects the operator's tool velocity with the virtual fixture; integrates the desired pose.

    .. pydrake_system::

        name: VirtualFixtureForceLaw
        input_ports:
        - V_WE_command
        - X_WE_measured
        output_ports:
        - X_WE_desired
        - V_WE_corrected
        - violation
        - F_W_fixture

    ``V_WE_command`` (6): commanded spatial velocity of the tool E, [w; v] in World.
    ``X_WE_measured`` (abstract RigidTransform): measured tool pose in World (its origin is the
    fixture's tool point). ``X_WE_desired`` (abstract RigidTransform): the integrated desired
    pose (discrete state, period ``period``), for differential IK. ``V_WE_corrected`` (6): the
    corrected velocity, [w; v] in World. ``violation`` (1): how far the measured tool point was
    outside the fixture at the last update (m, >= 0; kept in the state so the update's one
    distance query serves the logger too). ``F_W_fixture`` (3): the fixture's restoring force
    (N) in World.

    Args:
        vf: the fixture (in the Center frame).
        X_WCenter: (4, 4) pose of the Center frame in World.
        X_WE_initial: (4, 4) initial desired pose (set it to the tool's initial pose).
        period: update period (s).
        stiffness: k (N/m); damping: b (N s/m); the return gain is k / b (1/s).
        enabled: False passes the command unchanged (for experiments without the fixture).
    """

    def __init__(
        self,
        vf: VirtualFixture,
        X_WCenter,
        X_WE_initial,
        *,
        period: float = 0.005,
        stiffness: float = 2000.0,
        damping: float = 100.0,
        enabled: bool = True,
    ):
        super().__init__()
        if not np.isfinite(period) or period <= 0:
            raise InputError("period", f"expected a period > 0 s, got {period}")
        if not (np.isfinite(stiffness) and stiffness > 0 and np.isfinite(damping) and damping > 0):
            raise InputError("stiffness/damping", "expected positive stiffness and damping")
        self._vf = vf
        X_WC = np.asarray(X_WCenter, dtype=float)
        self._R_WC = X_WC[:3, :3].copy()
        self._X_CW = invert(X_WC)
        self._period = float(period)
        self._k, self._b = float(stiffness), float(damping)
        self._enabled = bool(enabled)
        X0 = np.asarray(X_WE_initial, dtype=float)

        self._V_cmd = self.DeclareVectorInputPort("V_WE_command", 6)
        self._X_meas = self.DeclareAbstractInputPort(
            "X_WE_measured", AbstractValue.Make(RigidTransform())
        )
        # state: [p_WE desired (3), R_WE desired row-major (9), violation at the update (1)]
        self._state = self.DeclareDiscreteState(
            np.concatenate([X0[:3, 3], X0[:3, :3].ravel(), [0.0]])
        )
        self.DeclarePeriodicDiscreteUpdateEvent(self._period, 0.0, self._update)
        self._X_des = self.DeclareAbstractOutputPort(
            "X_WE_desired",
            lambda: AbstractValue.Make(RigidTransform()),
            self._calc_desired,
            prerequisites_of_calc={self.xd_ticket()},
        )
        self._V_out = self.DeclareVectorOutputPort("V_WE_corrected", 6, self._calc_corrected)
        self._violation = self.DeclareVectorOutputPort(
            "violation", 1, self._calc_violation, prerequisites_of_calc={self.xd_ticket()}
        )
        self._force = self.DeclareVectorOutputPort("F_W_fixture", 3, self._calc_force)

    # -- the law (one tool point) -------------------------------------------------------------

    def _tool_point_C(self, context) -> np.ndarray:
        p_W = self._X_meas.Eval(context).translation()
        return self._X_CW[:3, :3] @ p_W + self._X_CW[:3, 3]

    def corrected(self, context) -> np.ndarray:
        """[w; v] corrected command in World for the inputs in ``context``."""
        V = np.array(self._V_cmd.Eval(context), dtype=float)
        if not self._enabled:
            return V
        v_C = self._R_WC.T @ V[3:]
        v_C = self._vf.correct_velocity(
            self._tool_point_C(context), v_C, dt=self._period, return_gain=self._k / self._b
        )
        return np.concatenate([V[:3], self._R_WC @ v_C])

    def _update(self, context, discrete_state):
        x = context.get_discrete_state(0).get_value()
        V = np.array(self._V_cmd.Eval(context), dtype=float)
        p_C = self._tool_point_C(context)
        d = float(self._vf.distance(p_C))
        violation = max(d, 0.0)
        v_C = self._R_WC.T @ V[3:]
        # A point that cannot reach the boundary within this period passes unchanged
        # (correct_velocity would return v_C exactly); only near the wall call the full law.
        if self._enabled and d > -float(np.linalg.norm(v_C)) * self._period - 1e-9:
            v_C = self._vf.correct_velocity(
                p_C, v_C, dt=self._period, return_gain=self._k / self._b
            )
            V = np.concatenate([V[:3], self._R_WC @ v_C])
        p = x[:3] + V[3:] * self._period
        R = _rotation_from_vector(V[:3] * self._period) @ x[3:12].reshape(3, 3)
        discrete_state.get_mutable_vector(0).SetFromVector(
            np.concatenate([p, R.ravel(), [violation]])
        )

    # -- outputs ------------------------------------------------------------------------------

    def _calc_desired(self, context, value):
        x = context.get_discrete_state(0).get_value()
        R = RotationMatrix(x[3:12].reshape(3, 3))
        value.set_value(RigidTransform(R, x[:3]))

    def _calc_corrected(self, context, output: BasicVector):
        output.SetFromVector(self.corrected(context))

    def _calc_violation(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(0).get_value()[12:])

    def _calc_force(self, context, output: BasicVector):
        V = np.array(self._V_cmd.Eval(context), dtype=float)
        F_C = self._vf.force(
            self._tool_point_C(context), self._R_WC.T @ V[3:], stiffness=self._k, damping=self._b
        )
        output.SetFromVector(self._R_WC @ F_C)

    def set_desired_pose(self, context, X_WE) -> None:
        """Reset the desired pose (e.g. to the tool's pose at the start of a run)."""
        X = np.asarray(X_WE, dtype=float)
        context.SetDiscreteState(0, np.concatenate([X[:3, 3], X[:3, :3].ravel(), [0.0]]))
