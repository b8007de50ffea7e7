"""The virtual-fixture force law as a Drake LeafSystem (thin adapter over
systems.placement.fixture).

Admittance law (seed 000 Sec. 2.2, its ref. [12]; the maths in systems.placement.fixture). The
master commands a tool twist V_cmd = [w; v]; with the tool pose it is given (the TCP and the
tool's axes, in the fixture's Center frame) the fixture bounds the tool *body*:

1. the TCP and, while the TCP is inside the mouth, the rod axis at the entry plane stay within
   the lateral tolerance delta of line1 (the cones funnel towards it outside the mouth), and the
   orientation within beta of the planned Tool frame: outward rates are limited to what reaches
   the boundary within one period;
2. a tool outside is pulled back with the admittance of a spring-damper: a force
   F = -(k * violation + b * max(v.n, 0)) n acting through an admittance 1/b gives the return
   rate -(k / b) * violation (position and orientation alike; ``return_gain = k / b``).

One compiled call (:func:`systems.placement.fixture.body_law_world`) per evaluation gives the
corrected twist, the violations and the force. With ``integrate`` (the default, for using the
fixture alone) the corrected twist is integrated at the fixture's period into the desired tool
pose that drives differential IK (incremental mapping: the command moves the *desired* pose).

Which pose the law constrains is its input ``X_WE``. In the teleop diagram (diagrams.teleop) the
SafetySupervisor integrates the desired pose (it filters the corrected twist first) and the
fixture is given that desired pose, the pose the command moves: the law then keeps the
*commanded* pose in the admissible region one period ahead at every step. Constraining the
measured pose instead, which lags the desired one by one or two periods, lets the desired pose
run outside by the lag (and a fast command along the funnel's wall carries it far ahead of the
arm): on the default case the fixture's violation reached 0.64-0.73 mm under a 2 mm tremor and
0.94 mm under a 5 mm lateral twitch that way, 0 with the commanded pose.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.eigen_geometry import AngleAxis
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError
from implantplan.systems.frames import invert
from implantplan.systems.placement import fixture as vfc
from implantplan.systems.placement.fixture import VirtualFixture


def step_pose(p: np.ndarray, R: np.ndarray, V: np.ndarray, dt: float):
    """One explicit step of a pose under the spatial velocity V = [w; v] (w about the frame's
    origin, v of the origin): p + v dt, exp([w] dt) R (Drake's AngleAxis rotation)."""
    p = p + V[3:] * dt
    w = np.asarray(V[:3], dtype=float)
    scale = float(np.abs(w).max())
    if scale > 0.0:  # the axis normalized after scaling: a denormal twist's square underflows
        u = w / scale
        norm = float(np.linalg.norm(u))
        R = RotationMatrix(AngleAxis(scale * norm * dt, u / norm)).matrix() @ R
    return p, R


class VirtualFixtureForceLaw(LeafSystem):
    """Corrects the operator's tool twist with the virtual fixture (it bounds the tool body).

    .. pydrake_system::

        name: VirtualFixtureForceLaw
        input_ports:
        - V_WE_command
        - X_WE
        output_ports:
        - V_WE_corrected
        - violation
        - angle_violation
        - F_W_fixture
        - X_WE_desired

    ``V_WE_command`` (6): commanded spatial velocity of the tool E, [w; v] in World.
    ``X_WE`` (abstract RigidTransform): the tool pose the law constrains, in World (its origin is
    the TCP; the fixture's Tool axes are E's rotated by ``R_ET``): the commanded (desired) pose
    in the teleop diagram (module docstring). ``V_WE_corrected`` (6): the
    corrected twist, [w; v] in World. ``violation`` (1): how far the tool axis is outside the
    fixture (m, >= 0). ``angle_violation`` (1): the orientation error beyond the tolerance
    (rad, >= 0). ``F_W_fixture`` (3): the fixture's restoring force (N) in World.
    ``X_WE_desired`` (abstract RigidTransform, only with ``integrate``): the integrated desired
    pose (discrete state, period ``period``); the violations then come from the state, as
    at the last update.

    Args:
        vf: the fixture (in the Center frame).
        X_WCenter: (4, 4) pose of the Center frame in World.
        X_WE_initial: (4, 4) initial desired pose (with ``integrate``; identity if None).
        R_ET: (3, 3) the fixture's Tool axes in the measured frame E (x along the rod, out of
            the mouth); identity if None.
        period: control period (s).
        stiffness: k (N/m); damping: b (N s/m); the return gain is k / b (1/s).
        enabled: False passes the command unchanged (for experiments without the fixture).
        integrate: declare the desired-pose state and its ``X_WE_desired`` output.
    """

    def __init__(
        self,
        vf: VirtualFixture,
        X_WCenter,
        X_WE_initial=None,
        *,
        R_ET=None,
        period: float = 0.005,
        stiffness: float = 2000.0,
        damping: float = 100.0,
        enabled: bool = True,
        integrate: bool = True,
    ):
        super().__init__()
        if not np.isfinite(period) or period <= 0:
            raise InputError("period", f"expected a period > 0 s, got {period}")
        if not (np.isfinite(stiffness) and stiffness > 0 and np.isfinite(damping) and damping > 0):
            raise InputError("stiffness/damping", "expected positive stiffness and damping")
        self._vf = vf
        self._X_CW = np.ascontiguousarray(invert(np.asarray(X_WCenter, dtype=float)))
        self._R_ET = np.ascontiguousarray(np.eye(3) if R_ET is None else R_ET, dtype=float)
        self._period = float(period)
        self._k, self._b = float(stiffness), float(damping)
        self._enabled = bool(enabled)
        self._args = vf.kernel_args() + (self._period, self._k / self._b, self._k, self._b, 1e-9)

        self._V_cmd = self.DeclareVectorInputPort("V_WE_command", 6)
        self._X_meas = self.DeclareAbstractInputPort(
            "X_WE", AbstractValue.Make(RigidTransform())
        )
        ticket = self.all_input_ports_ticket()
        self._integrate = bool(integrate)
        if self._integrate:
            X0 = np.eye(4) if X_WE_initial is None else np.asarray(X_WE_initial, dtype=float)
            # state: [p_WE desired (3), R_WE desired row-major (9), violation, angle violation]
            self.DeclareDiscreteState(np.concatenate([X0[:3, 3], X0[:3, :3].ravel(), [0, 0]]))
            self.DeclarePeriodicDiscreteUpdateEvent(self._period, 0.0, self._update)
            ticket = self.xd_ticket()
        # each output evaluates the law itself (one compiled call): in the diagram only the
        # corrected twist is read, once per step
        self._V_out = self.DeclareVectorOutputPort(
            "V_WE_corrected", 6, self._calc_corrected,
            prerequisites_of_calc={self.all_input_ports_ticket()},
        )
        self._violation = self.DeclareVectorOutputPort(
            "violation", 1, self._calc_violation, prerequisites_of_calc={ticket}
        )
        self._angle = self.DeclareVectorOutputPort(
            "angle_violation", 1, self._calc_angle, prerequisites_of_calc={ticket}
        )
        self._force = self.DeclareVectorOutputPort(
            "F_W_fixture", 3, self._calc_force,
            prerequisites_of_calc={self.all_input_ports_ticket()}
        )
        if self._integrate:
            self._X_des = self.DeclareAbstractOutputPort(
                "X_WE_desired",
                lambda: AbstractValue.Make(RigidTransform()),
                self._calc_desired,
                prerequisites_of_calc={self.xd_ticket()},
            )

    # -- the law ------------------------------------------------------------------------------

    @property
    def fixture(self) -> VirtualFixture:
        """The virtual fixture (its admissible region) this force law enforces."""
        return self._vf

    def law(self, context) -> np.ndarray:
        """(12) for the inputs in ``context``: corrected [w; v] in World, position violation
        (m), angle violation (rad), F in World (N), angle error (rad)."""
        V = self._V_cmd.Eval(context)
        out = np.empty(12)
        vfc.body_law_world(self._X_meas.Eval(context).GetAsMatrix4(), V, self._X_CW, self._R_ET,
                           *self._args, out)
        if not self._enabled:
            out[:6] = V
        return out

    def corrected(self, context) -> np.ndarray:
        """[w; v] corrected command in World for the inputs in ``context``."""
        return self.law(context)[:6]

    def _update(self, context, discrete_state):
        x = context.get_discrete_state(0).get_value()
        law = self.law(context)
        p, R = step_pose(x[:3], x[3:12].reshape(3, 3), law[:6], self._period)
        discrete_state.get_mutable_vector(0).SetFromVector(
            np.concatenate([p, R.ravel(), law[6:8]])
        )

    # -- outputs ------------------------------------------------------------------------------

    def _calc_desired(self, context, value):
        x = context.get_discrete_state(0).get_value()
        value.set_value(RigidTransform(RotationMatrix(x[3:12].reshape(3, 3)), x[:3]))

    def _calc_corrected(self, context, output: BasicVector):
        if not self._enabled:  # the law's corrected twist is then the command itself
            output.set_value(self._V_cmd.Eval(context))
            return
        output.set_value(self.law(context)[:6])

    def _violations(self, context) -> np.ndarray:
        if self._integrate:
            return context.get_discrete_state(0).get_value()[12:14]
        return self.law(context)[6:8]

    def _calc_violation(self, context, output: BasicVector):
        output.SetAtIndex(0, self._violations(context)[0])

    def _calc_angle(self, context, output: BasicVector):
        output.SetAtIndex(0, self._violations(context)[1])

    def _calc_force(self, context, output: BasicVector):
        output.SetFromVector(self.law(context)[8:11])

    def set_desired_pose(self, context, X_WE) -> None:
        """Reset the desired pose (e.g. to the tool's pose at the start of a run)."""
        X = np.asarray(X_WE, dtype=float)
        context.SetDiscreteState(0, np.concatenate([X[:3, 3], X[:3, :3].ravel(), [0.0, 0.0]]))
