"""Command limits: the operator's twist before the virtual fixture (DESIGN.md section 7).

The master's command is a tool twist V = [w; v] in World (systems.teleop.master_device: the
handle's velocity under the incremental mapping). Nothing upstream bounds it: a device glitch
that jumps the handle 200 mm in one 5 ms sample is a command of 40 m/s, a driver fault a NaN. A
command of absurd size must never become a fast motion of the instrument in the mouth, so the
command goes through :class:`CommandLimiter` first (master -> limiter -> fixture -> [guard] ->
supervisor -> DiffIK):

- a **fault**: any component non-finite, or a command that would move the tool more than
  ``fault_jump`` (or turn it more than ``fault_turn``) in one control period dt, i.e.
  |v| dt > fault_jump or |w| dt > fault_turn (at the default 200 Hz one period is one master
  sample: this is the handle's jump in one sample). The command becomes zero (the desired pose
  holds: under incremental mapping the jump is dropped, not replayed later), and the fault is
  latched and logged;
- **clipped**: not a fault but faster than the limits, |v| > ``linear_speed`` or |w| >
  ``angular_speed``: V' = s V with s = min(linear_speed / |v|, angular_speed / |w|), one scale
  for the whole twist, so the screw axis (the direction of the motion) is kept;
- **clean** otherwise: V passes unchanged.

**The latch.** From a fault on, the output is zero (hold). The fault clears at the
``n_clear``-th consecutive clean sample, n_clear = ceil(clear_after / dt) (40 at the defaults:
0.2 s); that sample passes and the ones after it are limited as usual. A clipped command (fast
but not absurd) or a new fault while latched restarts the count: the fault clears only once the
operator's command has been back within the limits, without interruption, for ``clear_after``
seconds. After a step jump of the handle the hand usually goes on as before (its increments are
within the limits again), so the feed resumes 0.2 s later from where the tool was held.

:func:`classify` (one verdict per command) and :func:`limit_series` (a time series: the latch
vectorized with running maxima of indices) are the numpy core for batches; :func:`limit_step`
is the same rule for one sample on plain floats (the LeafSystem's hot path; tested against the
vectorized form).

**Between control steps.** The supervisor integrates the desired pose from the twist it is
given, X_{k+1} = (p_k + v dt, exp([w] dt) R_k), and clips that twist to the same speed limits
(systems.teleop.supervisor: the fixture's return law and the head guard's retreat included), so
every step of the desired pose is a screw motion with |v| <= linear_speed and |w| <=
angular_speed. Along it a tool point at distance <= L from the TCP travels a path of length at
most S = (linear_speed + L angular_speed) dt (:meth:`CommandLimits.step_path`). The distance of a
point to the tissue is 1-Lipschitz along its path, so at any pose between X_k and X_{k+1} every
point is within S/2 of its place at one of the two ends, and the whole tool's clearance there is
at least min(h(X_k), h(X_{k+1})) - S/2. With the defaults and the actuator's reach (the rod's
far end, L = 0.172 m) S/2 = (0.05 + 0.172 x 0.105) x 0.005 / 2 = 0.170 mm, inside the 0.2 mm the
safety studies allow below the margin. The fixture (systems.teleop.fixture_system) bounds the
same desired pose, so the commanded pose stays in its admissible region at every step, and the
arm follows it one period behind: at 50 mm/s DiffIK's joint rates are a few deg/s, far below the
AUBO-i10's 147-180 deg/s (DESIGN.md section 8), so the arm's own step between control steps is
the desired pose's.

**The limits** are :class:`systems.safety.CommandLimits`, a section of the case's safety spec
(``safety.command_limits``: the defaults and where each comes from are in its docstring); the
limiter and the supervisor take the spec's, so what the plan records is what they enforce.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.safety import CommandLimits

CLEAN, CLIPPED, FAULT = 0, 1, 2  # the verdict on one command
NO_FAULT, NON_FINITE, JUMP, TURN = 0, 1, 2, 3  # the cause of a fault
CAUSES = {NON_FINITE: "non-finite", JUMP: "jump", TURN: "turn"}

# -- the numpy core (batches) ---------------------------------------------------------------------


def _norms(V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|w| and |v| of twists (n, 6) without overflow (hypot: a 1e200 component stays finite)."""
    return (np.hypot(np.hypot(V[:, 0], V[:, 1]), V[:, 2]),
            np.hypot(np.hypot(V[:, 3], V[:, 4]), V[:, 5]))


@dataclass(frozen=True)
class Verdicts:
    """Per command (n, ...): ``V`` the limited twist (zero for a fault), ``status`` (CLEAN,
    CLIPPED, FAULT), ``cause`` (NO_FAULT, NON_FINITE, JUMP, TURN), ``scale`` (the clip's factor;
    0 for a fault)."""

    V: np.ndarray
    status: np.ndarray
    cause: np.ndarray
    scale: np.ndarray


def classify(V, limits: CommandLimits, dt: float) -> Verdicts:
    """The verdict on each of the commands ``V`` (n, 6) = [w; v] at the control period ``dt``
    (module docstring), each on its own (no latch)."""
    V = np.asarray(V, dtype=float).reshape(-1, 6)
    dt = limits.check_period(dt)
    finite = np.all(np.isfinite(V), axis=1)
    Vf = np.where(finite[:, None], V, 0.0)
    nw, nv = _norms(Vf)
    cause = np.full(V.shape[0], NO_FAULT)
    cause[nw * dt > limits.fault_turn] = TURN
    cause[nv * dt > limits.fault_jump] = JUMP
    cause[~finite] = NON_FINITE
    fault = cause != NO_FAULT
    with np.errstate(divide="ignore"):
        scale = np.minimum(1.0, np.minimum(limits.linear_speed / nv, limits.angular_speed / nw))
    scale[fault] = 0.0
    status = np.where(fault, FAULT, np.where(scale < 1.0, CLIPPED, CLEAN))
    return Verdicts(V=Vf * scale[:, None], status=status, cause=cause, scale=scale)


def held_after_faults(status, n_clear: int) -> np.ndarray:
    """(n,) bool: the samples a time series of verdicts ``status`` (n,) holds, starting
    unlatched (module docstring: from a fault to the sample before the ``n_clear``-th
    consecutive clean one). With r[k] the run of clean samples ending at k, the latch of the
    last fault f <= k has cleared iff some j in (f, k] has r[j] >= n_clear; running maxima of
    indices give f, r and the last such j for every k at once."""
    status = np.asarray(status).reshape(-1)
    idx = np.arange(status.size)
    clean = status == CLEAN
    run = idx - np.maximum.accumulate(np.where(~clean, idx, -1))
    last_fault = np.maximum.accumulate(np.where(status == FAULT, idx, -1))
    last_ready = np.maximum.accumulate(np.where(run >= n_clear, idx, -1))
    return (last_fault >= 0) & (last_ready < last_fault)


@dataclass(frozen=True)
class Limited:
    """A time series through the limiter (n, ...): the output twist, the verdicts, and
    ``held`` (the latch held the sample: its output is zero)."""

    V: np.ndarray
    status: np.ndarray
    cause: np.ndarray
    held: np.ndarray

    @property
    def fault_samples(self) -> np.ndarray:
        """Indices of the samples that were faults."""
        return np.flatnonzero(self.status == FAULT)

    @property
    def fault_events(self) -> np.ndarray:
        """Indices of the faults that set the latch (a fault while not held before)."""
        before = np.concatenate([[False], self.held[:-1]])
        return np.flatnonzero((self.status == FAULT) & ~before)


def limit_series(V, limits: CommandLimits, dt: float) -> Limited:
    """The commands ``V`` (n, 6) of consecutive control periods ``dt`` through the limiter,
    starting unlatched: :func:`classify`, then the latch (:func:`held_after_faults`)."""
    verdicts = classify(V, limits, dt)
    held = held_after_faults(verdicts.status, limits.clear_samples(dt))
    return Limited(V=np.where(held[:, None], 0.0, verdicts.V), status=verdicts.status,
                   cause=verdicts.cause, held=held)


def limit_step(V, latched: bool, run: int, limits: CommandLimits, dt: float, n_clear: int):
    """One sample of :func:`limit_series` on plain floats, from the latch state (``latched``,
    ``run``: clean samples counted since the last non-clean one). ``dt`` is taken as checked
    (:meth:`CommandLimits.check_period`). Returns (the output twist (6,) as a list, status,
    cause, latched after, run after)."""
    w0, w1, w2, v0, v1, v2 = V.tolist() if isinstance(V, np.ndarray) else map(float, V)
    # the sum is finite when every component is (the exact test only when it is not: finite
    # components of ~1e308 may overflow it)
    if not math.isfinite(w0 + w1 + w2 + v0 + v1 + v2) and not all(
            map(math.isfinite, (w0, w1, w2, v0, v1, v2))):
        return [0.0] * 6, FAULT, NON_FINITE, True, 0
    nv, nw = math.hypot(v0, v1, v2), math.hypot(w0, w1, w2)
    if nv * dt > limits.fault_jump:
        return [0.0] * 6, FAULT, JUMP, True, 0
    if nw * dt > limits.fault_turn:
        return [0.0] * 6, FAULT, TURN, True, 0
    s = 1.0
    if nv > limits.linear_speed:
        s = limits.linear_speed / nv
    if nw > limits.angular_speed:
        s = min(s, limits.angular_speed / nw)
    if s < 1.0:
        out = [0.0] * 6 if latched else [s * w0, s * w1, s * w2, s * v0, s * v1, s * v2]
        return out, CLIPPED, NO_FAULT, latched, 0
    run += 1
    if latched and run >= n_clear:
        latched = False
    return ([0.0] * 6 if latched else [w0, w1, w2, v0, v1, v2]), CLEAN, NO_FAULT, latched, run


def clip_twist(V, limits: CommandLimits) -> np.ndarray:
    """A twist (6,) scaled down to the speed limits (direction kept), zero if not finite: the
    supervisor's bound on every step it integrates (module docstring, between control steps)."""
    V = np.asarray(V, dtype=float)
    w0, w1, w2, v0, v1, v2 = V.tolist()
    if not math.isfinite(w0 + w1 + w2 + v0 + v1 + v2) and not all(
            map(math.isfinite, (w0, w1, w2, v0, v1, v2))):
        return np.zeros(6)
    nv, nw = math.hypot(v0, v1, v2), math.hypot(w0, w1, w2)
    s = 1.0
    if nv > limits.linear_speed:
        s = limits.linear_speed / nv
    if nw > limits.angular_speed:
        s = min(s, limits.angular_speed / nw)
    return V if s == 1.0 else V * s


# -- the LeafSystem ---------------------------------------------------------------------------

STATUS_SIZE = 6  # [status, cause, held, fault samples, fault events, time of the sample]
_STATUS_OF_STATE = np.array([4, 5, 0, 2, 3, 6])  # the status output's entries of the state


class CommandLimiter(LeafSystem):
    """Clips the operator's twist to the speed limits; a non-finite or absurd command, or a jump
    of the handle, is a fault: held at zero, latched and logged (module docstring).

    .. pydrake_system::

        name: CommandLimiter
        input_ports:
        - V_WE_command
        output_ports:
        - V_WE_limited
        - command_status

    ``V_WE_command`` (6): the master's twist [w; v] in World. ``V_WE_limited`` (6): the limited
    twist for the current input and the latch as it stands (the same rule the periodic update
    then records). ``command_status`` (6): the last recorded sample: [status (0 clean, 1 clipped,
    2 fault), cause (0 none, 1 non-finite, 2 jump, 3 turn), held (1 while the latch holds the
    output), fault samples so far, fault events so far (faults that set the latch), the sample's
    time (s; -1 before the first)].

    Args:
        limits: the limits (CommandLimits() if None).
        period: the control period (s): the update's period and the dt of the fault test.
    """

    def __init__(self, limits: CommandLimits | None = None, *, period: float = 0.005):
        super().__init__()
        self.limits = limits or CommandLimits()
        self._dt = self.limits.check_period(period)
        self._n_clear = self.limits.clear_samples(self._dt)
        self._V = self.DeclareVectorInputPort("V_WE_command", 6)
        # state: [latched, run, fault samples, fault events, status, cause, time]
        self.DeclareDiscreteState(np.array([0.0, 0.0, 0.0, 0.0, CLEAN, NO_FAULT, -1.0]))
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)
        self.DeclareVectorOutputPort("V_WE_limited", 6, self._calc_limited)
        self.DeclareVectorOutputPort("command_status", STATUS_SIZE, self._calc_status,
                                     prerequisites_of_calc={self.xd_ticket()})

    @property
    def period(self) -> float:
        return self._dt

    def _calc_limited(self, context, output: BasicVector):
        x = context.get_discrete_state(0).get_value()
        output.set_value(limit_step(self._V.Eval(context), x[0] > 0.5, int(x[1]), self.limits,
                                    self._dt, self._n_clear)[0])

    def _update(self, context, discrete_state):
        x0, x1, x2, x3 = context.get_discrete_state(0).get_value()[:4].tolist()
        _, status, cause, latched, run = limit_step(self._V.Eval(context), x0 > 0.5, int(x1),
                                                    self.limits, self._dt, self._n_clear)
        fault = status == FAULT
        discrete_state.set_value(0, [
            1.0 if latched else 0.0, float(min(run, self._n_clear)), x2 + fault,
            x3 + (fault and x0 < 0.5), float(status), float(cause), context.get_time()])

    def _calc_status(self, context, output: BasicVector):
        output.set_value(context.get_discrete_state(0).get_value()[_STATUS_OF_STATE])
