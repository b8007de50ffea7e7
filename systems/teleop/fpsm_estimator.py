"""Surrogate collision estimator of the implanting actuator against the FPSM, and its LeafSystem.

Seed 000 (Sec. 4, Eq. 19) models the contra-angle actuator at the feeding target by two lines in
the Tool frame {T} (x along the rod, z along the implant axis, origin at the head):

- line1, the handle rod of radius r: from P1 = [r, 0, 0] along +x, checked against the FPSM
  shrunk by r (Eq. 12);
- line2, the path swept by the implant tip: from P2 = [r, 0, -d12] along +x, checked against the
  unshrunk FPSM.

Both are rays leaving the mouth (the FPSM's +Z end); :meth:`systems.fpsm.model.Fpsm.line_safety`
gives f_safe (Eq. 13) and the smallest safe distance of each. During the simulated feed the same
two lines ride on the *measured* tool pose, so the estimator says, every step, how safe the
actuator is where it actually is:

    min_d_safe = the certified clearance of the whole tool body (rod, head, implant) against the
                 FPSM (systems.placement.tool_clearance), or with method="paper" the
                 paper's
                 min(d_safe_min(line1), d_safe_min(line2)),
    alarm = min_d_safe <= alarm_margin.

With ``alarm_margin`` > 0 the alarm fires before contact (d_safe = 0) for any motion slower than
alarm_margin per update period. Where the paper evaluates the lines only at the planned target,
we evaluate them at every pose of the run (that is the estimator's job in the diagram).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem, ValueProducer

from implantplan.systems.actuator import IMPLANT_LENGTH, ROD_RADIUS
from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm, line_kernel
from implantplan.systems.frames import apply, invert
from implantplan.systems.instrument import Instrument
from implantplan.systems.jit import numba
from implantplan.systems.placement.scan_clearance import capped_at
from implantplan.systems.placement.tool_clearance import (
    ToolClearance,
    clearance_field,
    fpsm_at,
    is_rigid_pose,
    rigid_poses,
)
from implantplan.systems.safety import DEFAULT as SAFETY


@dataclass(frozen=True)
class ToolLines:
    """The actuator's lines in the tool frame T (Eq. 19).

    Attributes:
        start_T: (2, 3) start points of line1 and line2 in T (m).
        direction_T: (2, 3) unit directions in T.
        radius: (2,) radius each line is checked with (line1: rod radius r; line2: 0), m.
    """

    start_T: np.ndarray
    direction_T: np.ndarray
    radius: np.ndarray
    tool: Instrument | None = None  # the whole body, for the sound clearance
    X_AT: np.ndarray | None = None  # pose of seed 000's Tool frame in the lines' frame

    @classmethod
    def contra_angle(cls, rod_radius: float = ROD_RADIUS,
                     implant_length: float = IMPLANT_LENGTH,
                     tool: Instrument | None = None) -> ToolLines:
        """Eq. 19 in the Tool frame (:meth:`Instrument.lines_T`): P1 = [r, 0, 0],
        P2 = [r, 0, -d12], both along +x; ``tool`` is the body the sound clearance checks
        (default: :class:`Instrument` of that rod radius and implant length)."""
        r, d12 = float(rod_radius), float(implant_length)
        if not np.isfinite(r) or r < 0:
            raise InputError("rod_radius", f"expected a radius >= 0 m, got {rod_radius}")
        if not np.isfinite(d12) or d12 <= 0:
            raise InputError("implant_length", f"expected a length > 0 m, got {implant_length}")
        tool = tool or Instrument.paper(rod_radius=r, implant_length=d12)
        starts, u = Instrument.paper(rod_radius=r, implant_length=d12).lines_T()
        return cls(
            start_T=starts,
            direction_T=np.stack([u, u]),
            radius=np.array([r, 0.0]),
            tool=tool,
            X_AT=np.eye(4),
        )

    def expressed_in(self, X_AT) -> ToolLines:
        """The same lines expressed in a frame A, given the pose ``X_AT`` of T in A (e.g. the
        plant's TCP frame, whose axes differ from seed 000's Tool frame)."""
        X = np.asarray(X_AT, dtype=float)
        prior = np.eye(4) if self.X_AT is None else self.X_AT
        return ToolLines(
            start_T=apply(X, self.start_T),
            direction_T=self.direction_T @ X[:3, :3].T,
            radius=self.radius.copy(),
            tool=self.tool,
            X_AT=X @ prior,
        )


@dataclass(frozen=True)
class ToolSafety:
    """Safety of the actuator at K tool poses; every field has shape (K,).

    Attributes:
        f_safe_line1, f_safe_line2: Eq. 13 for the rod and the implant path (+inf: the line is
            wholly outside the mouth).
        min_d_safe: with ``method="sound"`` (default) the certified clearance of the whole
            tool body (:func:`systems.placement.tool_clearance.tool_clearance`, m); with
            ``"paper"`` the
            smallest safe distance over both lines (Eq. 12-13), m.
        alarm: min_d_safe <= alarm_margin.
    """

    f_safe_line1: np.ndarray
    f_safe_line2: np.ndarray
    min_d_safe: np.ndarray
    alarm: np.ndarray


@numba.njit(cache=True)
def _lines_at_poses(X, start_T, dir_T, radius, rho, slice_z, shrink, max_radius, lam_avg,
                    lam_min, f, d):
    """The tool's n lines (starts and unit directions in T as columns, (3, n)) at K poses X
    (K, 4, 4) through the line kernel of systems.fpsm.model: f_safe and d_safe_min, (K, n) each."""
    K, n = X.shape[0], radius.size
    m = K * n
    start = np.empty((m, 3))
    u = np.empty((m, 3))
    rad = np.empty(m)
    for k in range(K):
        for i in range(n):
            row = k * n + i
            rad[row] = radius[i]
            for a in range(3):
                sa = X[k, a, 3]
                ua = 0.0
                for b in range(3):
                    sa += X[k, a, b] * start_T[b, i]
                    ua += X[k, a, b] * dir_T[b, i]
                start[row, a] = sa
                u[row, a] = ua
    line_kernel(start, u, np.full(m, np.inf), rad, rho, slice_z, shrink, max_radius, lam_avg,
                 lam_min, f.reshape(m), d.reshape(m), np.empty(m), np.empty(m, dtype=np.int64))


class LinesAtPoses:
    """The tool's lines against one model, prepared once (the compiled kernel's arguments):
    ``(X (K, 4, 4)) -> (f_safe, d_safe_min)``, each (K, n_lines)."""

    def __init__(self, fpsm: Fpsm, lines: ToolLines, *, lambda_avg: float = 0.5,
                 lambda_min: float = 0.5):
        self._start_T = np.ascontiguousarray(lines.start_T.T)
        u = lines.direction_T / np.linalg.norm(lines.direction_T, axis=1, keepdims=True)
        self._dir_T = np.ascontiguousarray(u.T)
        self._radius = np.ascontiguousarray(lines.radius, dtype=float)
        self._args = (np.ascontiguousarray(fpsm.rho), np.ascontiguousarray(fpsm.slice_z),
                      float(fpsm.settings.get("shrink_m", 0.0)), fpsm.max_radius,
                      float(lambda_avg), float(lambda_min))
        # the compiled kernel's arguments in one tuple (the estimator's one call per update)
        self.kernel_args = (self._start_T, self._dir_T, self._radius, *self._args)

    def __call__(self, X_CenterT: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        X = np.ascontiguousarray(X_CenterT, dtype=float).reshape(-1, 4, 4)
        f = np.empty((X.shape[0], self._radius.size))
        d = np.empty_like(f)
        _lines_at_poses(X, self._start_T, self._dir_T, self._radius, *self._args, f, d)
        return f, d


def tool_safety(
    fpsm: Fpsm,
    X_CenterT,
    lines: ToolLines,
    *,
    alarm_margin: float = SAFETY.alarm_margin,
    lambda_avg: float = 0.5,
    lambda_min: float = 0.5,
    method: str = "sound",
) -> ToolSafety:
    """Safety of the actuator at poses ``X_CenterT`` (K, 4, 4) or (4, 4) in Center of the frame
    the lines are given in.

    f_safe of each line by Eq. 13, both lines of all poses in one compiled call
    (:class:`LinesAtPoses`); the clearance ``min_d_safe`` that the alarm watches is, by default
    (``method="sound"``), the certified clearance of the whole tool body (rod, head,
    implant), or the paper's smallest line sample (``"paper"``, Eq. 12).
    """
    if method not in ("sound", "paper"):
        raise InputError("method", f"expected 'sound' or 'paper', got {method!r}")
    X = np.asarray(X_CenterT, dtype=float)
    if X.shape[-2:] != (4, 4):
        raise InputError("X_CenterT", f"expected (K, 4, 4) poses, got {X.shape}")
    if not np.isfinite(alarm_margin):
        raise InputError("alarm_margin", "expected a finite distance (m)")
    X = X.reshape(-1, 4, 4)
    f, d = LinesAtPoses(fpsm, lines, lambda_avg=lambda_avg, lambda_min=lambda_min)(X)
    d_min = np.minimum(d[:, 0], d[:, 1])
    if method == "sound":
        d_min = _sound(fpsm, lines)(X)
    return ToolSafety(
        f_safe_line1=f[:, 0], f_safe_line2=f[:, 1], min_d_safe=d_min, alarm=d_min <= alarm_margin
    )


_CLEARANCES: dict = {}


def _sound_clearance(fpsm: Fpsm, lines: ToolLines, clearance=None):
    """(the prepared whole-tool clearance, X_AT) for lines given in frame A (``clearance``: a
    prepared one of the lines' tool; None: the FPSM's)."""
    tool = lines.tool or Instrument.paper(rod_radius=float(lines.radius[0]))
    X_AT = np.eye(4) if lines.X_AT is None else np.asarray(lines.X_AT, dtype=float)
    if clearance is None:
        clearance = _clearance(fpsm, tool)
    elif clearance.instrument != tool:
        raise InputError("clearance", f"bounds the instrument {clearance.instrument.name!r}, "
                         f"not the estimator's {tool.name!r}")
    return clearance, X_AT


def _sound(fpsm: Fpsm, lines: ToolLines, clearance=None):
    """X_CenterA (K, 4, 4) -> (K,) certified whole-tool clearance, for lines given in frame A
    (``clearance``: a prepared one of the lines' tool; None: the FPSM's)."""
    clearance, X_AT = _sound_clearance(fpsm, lines, clearance)
    return lambda X: np.atleast_1d(clearance(np.asarray(X, dtype=float) @ X_AT))


def _clearance(fpsm: Fpsm, tool: Instrument) -> ToolClearance:
    key = (id(fpsm), tool)
    hit = _CLEARANCES.get(key)
    if hit is None or hit.fpsm is not fpsm or hit.field is not clearance_field(fpsm):
        hit = _CLEARANCES[key] = ToolClearance(fpsm, tool)
    return hit


@numba.njit(inline="always")
def _estimate(h_at, h_args, X_CT, X_CA, margin, far, lines_args, out) -> bool:
    """One estimate in one call: the lines at the pose X_CT (4, 4) of their frame in Center
    (:class:`LinesAtPoses`), the whole tool's clearance ``h_at(h_args, X_CA)`` at its Tool pose
    X_CA (4, 4), the alarm, each clipped to +-``far`` (as ``np.clip``), into ``out`` (4). False
    (``out`` not written): X_CA is not a rigid pose
    (:func:`systems.placement.tool_clearance.is_rigid_pose`); the caller raises its error."""
    start_T, dir_T, radius, rho, slice_z, shrink, max_radius, lam_avg, lam_min = lines_args
    f = np.empty((1, radius.size))
    d = np.empty((1, radius.size))
    _lines_at_poses(X_CT.reshape((1, 4, 4)), start_T, dir_T, radius, rho, slice_z, shrink,
                    max_radius, lam_avg, lam_min, f, d)
    if not is_rigid_pose(X_CA):
        return False
    d_min = h_at(h_args, X_CA)
    out[0], out[1], out[2] = f[0, 0], f[0, 1], d_min
    out[3] = 1.0 if d_min <= margin else 0.0
    for i in range(4):  # NaN stays NaN
        if out[i] > far:
            out[i] = far
        elif out[i] < -far:
            out[i] = -far
    return True


@numba.njit(cache=True)
def _estimate_fpsm(h_args, X_CT, X_CA, margin, far, lines_args, out) -> bool:
    """:func:`_estimate` with the FPSM bound (an entry point with its hook fixed: numba caches
    it on disk, as the supervisor's)."""
    return _estimate(fpsm_at, h_args, X_CT, X_CA, margin, far, lines_args, out)


@numba.njit(cache=True)
def _estimate_scan(h_args, X_CT, X_CA, margin, far, lines_args, out) -> bool:
    """:func:`_estimate` with the capped scan bound."""
    return _estimate(capped_at, h_args, X_CT, X_CA, margin, far, lines_args, out)


_ESTIMATES = {fpsm_at: _estimate_fpsm, capped_at: _estimate_scan}


class FpsmEstimator(LeafSystem):
    """Rod safety of the actuator against the FPSM at the measured tool pose, every period.

    .. pydrake_system::

        name: FpsmEstimator
        input_ports:
        - X_WT
        output_ports:
        - safety
        - alarm

    ``X_WT`` (abstract RigidTransform): the measured pose of the frame the lines are given in
    (seed 000's {Tool} by default; see :meth:`ToolLines.expressed_in`) in World. ``safety`` (3):
    [f_safe_line1, f_safe_line2, min_d_safe] (m; a line wholly outside the mouth reports 1.0e3
    instead of +inf so loggers stay finite). ``alarm`` (1): 1.0 when min_d_safe <=
    alarm_margin, else 0.0.

    With ``period=None`` the outputs are computed from the input on demand (direct
    feedthrough). With a ``period`` (s) the estimate is a discrete state refreshed every period
    and the outputs read it: the sensible rate for the diagram (each estimate is one compiled
    call: the two lines, the rigid-pose check and the whole tool's clearance), and the alarm
    still fires before contact for any tool speed below alarm_margin / period (1 mm / 20 ms =
    50 mm/s at the defaults).

    ``clearance``: the prepared whole-instrument clearance ``min_d_safe`` takes (of the lines'
    tool; the plan's scan bound capped above the alarm margin,
    :class:`systems.placement.scan_clearance.CappedScanClearance`, so values above the cap read
    as the cap); None: the FPSM's (:class:`ToolClearance`).
    """

    FAR = 1.0e3  # stand-in for +inf on the output ports (m)

    def __init__(
        self,
        fpsm: Fpsm,
        X_WCenter,
        lines: ToolLines | None = None,
        *,
        alarm_margin: float = SAFETY.alarm_margin,
        period: float | None = None,
        method: str = "sound",
        clearance=None,
    ):
        super().__init__()
        self._fpsm = fpsm
        self._X_CenterW = invert(np.asarray(X_WCenter, dtype=float))
        self._lines = lines or ToolLines.contra_angle()
        self._at_poses = LinesAtPoses(fpsm, self._lines)
        self._margin = float(alarm_margin)
        if method not in ("sound", "paper"):
            raise InputError("method", f"expected 'sound' or 'paper', got {method!r}")
        self._method = method
        self._sound = None
        if method == "sound":  # one compiled call per estimate: lines, rigid check, clearance
            sound, self._X_AT = _sound_clearance(fpsm, self._lines, clearance)
            kernel = _ESTIMATES.get(getattr(sound, "at", None))
            if kernel is None:
                raise InputError("clearance", "expected a ToolClearance or a CappedScanClearance "
                                 f"(a compiled hook the estimator knows), got "
                                 f"{type(sound).__name__}")
            self._sound = (kernel, sound.at_args)
        self._X = self.DeclareAbstractInputPort("X_WT", AbstractValue.Make(RigidTransform()))
        if period is None:
            cache = self.DeclareCacheEntry(
                description="tool_safety",
                value_producer=ValueProducer(
                    allocate=AbstractValue.Make(np.zeros(4)).Clone, calc=self._calc_cache
                ),
                prerequisites_of_calc={self.input_port_ticket(self._X.get_index())},
            )
            self._estimate = lambda context: cache.Eval(context)
            ticket = cache.ticket()
        else:
            if not np.isfinite(period) or period <= 0:
                raise InputError("period", f"expected a period > 0 s, got {period}")
            state = self.DeclareDiscreteState(np.array([self.FAR, self.FAR, self.FAR, 0.0]))
            self.DeclarePeriodicDiscreteUpdateEvent(float(period), 0.0, self._update)
            self._estimate = lambda context: context.get_discrete_state(state).get_value()
            ticket = self.xd_ticket()
        self._safety = self.DeclareVectorOutputPort(
            "safety", 3, self._calc_safety, prerequisites_of_calc={ticket}
        )
        self._alarm = self.DeclareVectorOutputPort(
            "alarm", 1, self._calc_alarm, prerequisites_of_calc={ticket}
        )

    @property
    def alarm_margin(self) -> float:
        """The alarm threshold on min d_safe (m) this estimator raises its alarm at."""
        return self._margin

    def estimate(self, context) -> np.ndarray:
        """[f_safe_line1, f_safe_line2, min_d_safe, alarm] for the input in ``context``."""
        X_CT = self._X_CenterW @ self._X.Eval(context).GetAsMatrix4()
        if self._sound is None:  # the paper's smaller line distance
            f, d = self._at_poses(X_CT)
            d_min = min(d[0, 0], d[0, 1])
            out = np.array([f[0, 0], f[0, 1], d_min, float(d_min <= self._margin)])
            return np.clip(out, -self.FAR, self.FAR)
        kernel, h_args = self._sound
        X_CA = X_CT @ self._X_AT  # the Tool pose the clearance takes
        out = np.empty(4)
        if not kernel(h_args, X_CT, X_CA, self._margin, self.FAR, self._at_poses.kernel_args,
                      out):
            rigid_poses(X_CA)  # raises: not a rigid pose
            raise RuntimeError("is_rigid_pose and rigid_poses disagree")  # pragma: no cover
        return out

    def _update(self, context, discrete_state):
        discrete_state.set_value(0, self.estimate(context))

    def _calc_cache(self, context, value):
        value.set_value(self.estimate(context))

    def _calc_safety(self, context, output: BasicVector):
        output.set_value(self._estimate(context)[:3])

    def _calc_alarm(self, context, output: BasicVector):
        output.set_value(self._estimate(context)[3:])
