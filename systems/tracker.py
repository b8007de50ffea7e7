"""The stereo camera that tracks the marker on the patient's head (seed 001; DESIGN.md sec. 7).

The camera samples the true head pose at its own rate (30-60 Hz); each sample carries seeded
Gaussian noise (``noise_position`` per axis, ``noise_angle`` per axis of a small rotation) and
becomes available ``latency`` after it was taken. During a dropout window (the marker
occluded) the samples are missing: the estimate holds the last good one and the lost-tracking
flag is raised as soon as the newest *available* sample is a missing one.

The head velocity estimate is the least-squares slope over the newest ``VELOCITY_WINDOW``
available good samples (positions, and rotation vectors relative to the newest sample): a
finite difference of two samples would carry sqrt(2) noise * rate (several mm/s at 40 Hz); the
fit cuts that about 3x for half the window's lag. The tracker's error bound, for the
supervisor's margin, is :meth:`TrackerParams.error_bound`: four standard deviations of the
position noise plus the lever ``reach`` times four of the angle noise.

Core: :func:`camera_samples` (vectorized over ticks). LeafSystem: :class:`Tracker`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError
from implantplan.systems.exact_clearance import _rotations as rotations

RING = 12  # samples kept: more than latency * rate + VELOCITY_WINDOW for every setting
VELOCITY_WINDOW = 6  # good samples in the velocity fit (0.1-0.2 s at 30-60 Hz)


@dataclass(frozen=True)
class TrackerParams:
    """The camera's settings (SI units).

    Attributes:
        rate: sampling rate (Hz), 30-60.
        latency: time from a sample to its availability (s), 20-50 ms.
        noise_position: standard deviation of the position noise per axis (m).
        noise_angle: standard deviation of the rotation noise per axis (rad).
        dropouts: ((t_start, t_end), ...) windows with the marker occluded (s).
        seed: the noise's seed.
        reach: lever (m) from the head frame's origin to the tool, for the error bound.
    """

    rate: float = 40.0
    latency: float = 0.03
    noise_position: float = 0.0001
    noise_angle: float = float(np.deg2rad(0.1))
    dropouts: tuple = ()
    seed: int = 0
    reach: float = 0.1

    def __post_init__(self):
        if not (np.isfinite(self.rate) and 30.0 <= self.rate <= 60.0):
            raise InputError("tracker.rate", f"expected 30-60 Hz, got {self.rate}")
        if not (np.isfinite(self.latency) and 0.0 <= self.latency <= 0.1):
            raise InputError("tracker.latency", f"expected 0-100 ms, got {self.latency} s")
        for name in ("noise_position", "noise_angle", "reach"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"tracker.{name}", f"expected a finite value >= 0, got {v}")
        for w in self.dropouts:
            if len(w) != 2 or not (np.all(np.isfinite(w)) and w[1] > w[0]):
                raise InputError("tracker.dropouts", f"expected (start, end) with end > start, "
                                 f"got {w}")

    @property
    def period(self) -> float:
        return 1.0 / self.rate

    def error_bound(self) -> float:
        """Bound (m) of the estimate's noise at the tool: 4 sigma (per axis) of position plus
        reach x 4 sigma of angle (a 3-D normal's norm exceeds 4 sigma with probability 0.1%)."""
        return 4.0 * (self.noise_position + self.reach * self.noise_angle)

    def missing(self, t) -> np.ndarray:
        """(n,) True where a sample taken at ``t`` falls in a dropout window."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        out = np.zeros(t.shape, dtype=bool)
        for a, b in self.dropouts:
            out |= (t >= a) & (t < b)
        return out


def velocity_fit(rows: np.ndarray) -> np.ndarray:
    """(6,) [w; v] least-squares slope of samples ``rows`` (n, 14) [t, good, p, R]; zero for
    fewer than ``VELOCITY_WINDOW`` (a slope of two or three noisy samples reads tens of mm/s of
    noise as head speed)."""
    if rows.shape[0] < VELOCITY_WINDOW:
        return np.zeros(6)
    t = rows[:, 0] - rows[-1, 0]
    R = rows[:, 5:14].reshape(-1, 3, 3)
    dR = R @ R[-1].T  # rotation of each sample from the newest, in World
    w = 0.5 * np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0],
                        dR[:, 1, 0] - dR[:, 0, 1]], axis=1)
    Y = np.concatenate([w, rows[:, 2:5]], axis=1)
    tc = t - t.mean()
    return tc @ (Y - Y.mean(axis=0)) / (tc @ tc)


def camera_noise(params: TrackerParams, ticks) -> np.ndarray:
    """(n, 6) [rotation vector (rad); translation (m)] noise of camera ticks ``ticks`` (n,):
    a pure function of (seed, tick), so every run with the same seed sees the same noise."""
    ticks = np.atleast_1d(np.asarray(ticks, dtype=np.int64))
    out = np.empty((ticks.shape[0], 6))
    for i, k in enumerate(ticks):
        z = np.random.default_rng([params.seed, int(k)]).standard_normal(6)
        out[i, :3] = params.noise_angle * z[:3]
        out[i, 3:] = params.noise_position * z[3:]
    return out


def camera_samples(params: TrackerParams, X_true: np.ndarray, ticks) -> np.ndarray:
    """(n, 4, 4) noisy measurements of the true poses ``X_true`` (n, 4, 4) at ``ticks``: the
    noise rotation applied about the pose's origin, then the noise translation."""
    X = np.array(X_true, dtype=float, copy=True).reshape(-1, 4, 4)
    nz = camera_noise(params, ticks)
    X[:, :3, :3] = rotations(nz[:, :3]) @ X[:, :3, :3]
    X[:, :3, 3] += nz[:, 3:]
    return X


class Tracker(LeafSystem):
    """The camera's estimate of the head pose, with latency, noise and dropouts.

    .. pydrake_system::

        name: Tracker
        input_ports:
        - X_WHead
        output_ports:
        - X_WHead_estimated
        - V_WHead_estimated
        - lost

    ``X_WHead`` (abstract RigidTransform): the true head pose. ``X_WHead_estimated`` (abstract
    RigidTransform): the newest good sample taken at least ``latency`` ago (the initial pose
    before the first one). ``V_WHead_estimated`` (6): [angular velocity; velocity] of the head
    from the two newest good available samples (zero before two). ``lost`` (1): 1.0 when the
    newest available sample is missing (marker occluded), else 0.0.

    State: a ring of the last ``RING`` samples [time, good, p (3), R (9)], written at the
    camera's rate, and the newest good available sample (held through long dropouts).
    """

    def __init__(self, params: TrackerParams, X_WHead0):
        super().__init__()
        self._p = params
        X0 = np.asarray(X_WHead0, dtype=float)
        self._X0 = X0
        row = np.concatenate([[-np.inf, 1.0], X0[:3, 3], X0[:3, :3].ravel()])
        # [ring (RING x 14), next slot, held: the newest good available sample (14)]
        self.DeclareDiscreteState(np.concatenate([np.tile(row, RING), [0.0], row]))
        self.DeclarePeriodicDiscreteUpdateEvent(params.period, 0.0, self._update)
        self._X_in = self.DeclareAbstractInputPort("X_WHead",
                                                   AbstractValue.Make(RigidTransform()))
        self.DeclareAbstractOutputPort("X_WHead_estimated",
                                       lambda: AbstractValue.Make(RigidTransform()),
                                       self._calc_pose, prerequisites_of_calc={
                                           self.xd_ticket(), self.time_ticket()})
        self.DeclareVectorOutputPort("V_WHead_estimated", 6, self._calc_velocity,
                                     prerequisites_of_calc={self.xd_ticket(),
                                                            self.time_ticket()})
        self.DeclareVectorOutputPort("lost", 1, self._calc_lost, prerequisites_of_calc={
            self.xd_ticket(), self.time_ticket()})

    @property
    def params(self) -> TrackerParams:
        return self._p

    def _update(self, context, discrete_state):
        x = context.get_discrete_state(0).get_value().copy()
        t = context.get_time()
        good = self._good(context)
        if good.shape[0]:  # held through dropouts longer than the ring
            x[-14:] = good[-1]
        tick = int(round(t * self._p.rate))
        X = self._X_in.Eval(context).GetAsMatrix4()
        Xm = camera_samples(self._p, X[None], [tick])[0]
        slot = int(x[14 * RING]) % RING
        good = 0.0 if self._p.missing(t)[0] else 1.0
        x[14 * slot:14 * slot + 14] = np.concatenate([[t, good], Xm[:3, 3], Xm[:3, :3].ravel()])
        x[14 * RING] = (slot + 1) % RING
        discrete_state.get_mutable_vector(0).SetFromVector(x)

    def _available(self, context) -> np.ndarray:
        """Rows of the available samples (taken >= latency ago), oldest first."""
        x = context.get_discrete_state(0).get_value()
        ring = x[:14 * RING].reshape(RING, 14)
        ring = ring[np.argsort(ring[:, 0], kind="stable")]
        return ring[ring[:, 0] <= context.get_time() - self._p.latency + 1e-9]

    def _good(self, context) -> np.ndarray:
        rows = self._available(context)
        return rows[rows[:, 1] > 0.5]

    def estimate(self, context) -> np.ndarray:
        """(4, 4) the current estimate of the head pose."""
        good = self._good(context)
        row = good[-1] if good.shape[0] else context.get_discrete_state(0).get_value()[-14:]
        X = np.eye(4)
        X[:3, 3], X[:3, :3] = row[2:5], row[5:14].reshape(3, 3)
        return X

    def _calc_pose(self, context, value):
        X = self.estimate(context)
        value.set_value(RigidTransform(RotationMatrix.ProjectToRotationMatrix(X[:3, :3]),
                                       X[:3, 3]))

    def _calc_velocity(self, context, output: BasicVector):
        good = self._good(context)
        output.SetFromVector(velocity_fit(good[np.isfinite(good[:, 0])][-VELOCITY_WINDOW:]))

    def _calc_lost(self, context, output: BasicVector):
        rows = self._available(context)
        rows = rows[np.isfinite(rows[:, 0])]
        lost = rows.shape[0] > 0 and rows[-1, 1] < 0.5
        output.SetFromVector([1.0 if lost else 0.0])
