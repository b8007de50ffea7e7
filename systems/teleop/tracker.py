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

**Prediction (latency compensation).** The arm follows ``X_WHead_predicted``: the least-squares
line through the newest ``predict_samples`` good samples, evaluated at the newest sample and
carried to the present over the sample's age (latency plus up to one camera period) by the
line's slope, shortened by a dead zone of four standard deviations of the slope's noise
(:meth:`TrackerParams.gates`; 34 mm/s and 0.6 rad/s at 60 Hz with two samples), while the
``VELOCITY_WINDOW`` fit calls the head still (inside its own dead zones, 4 standard deviations
of its slope: 5.7 mm/s and 0.1 rad/s at 60 Hz): a still, breathing or drifting head (<= 2 mm/s)
stays there (its noise crosses those 4-sigma gates at about 0.2% of the samples, and then
only just), so the prediction adds no noise to it. Never across a dropout: on lost
tracking, or with the newest good sample older than latency + two periods, the output is the
held estimate.

**Moving head.** The two-sample dead zone lags a moving head by its width: a startle's
rotation (2-4 deg in 0.2 s, at most 0.66 rad/s) hardly leaves its 0.6 rad/s and the
translation is carried 34 mm/s short: in the seeded startles of analyses.studies.head_motion
the tool trailed the true mouth by millimetres and the clearance was lost to that lag, not to
a late stop of the feed (docs/measurements.md, the awake patient). When the fit says
the head moves, the slope is that of the newest ``max(MOVING_SAMPLES, predict_samples)``
samples (three: about half the noise of two), its own dead zones scaled by 1 - the share the
fit says the head moves by (:func:`_kept`: 0 at the fit's dead zone, 1 at twice it; rotation
and translation each), so a head at twice the fit's dead zones is carried at its full rate
(a swallow, up to 16 mm/s, partly; the startles' clearance with and without it:
docs/measurements.md). The moving head's slope, unshortened, carries a new sample's noise
over the sample's age: a correction can then turn the predicted head faster than the arm's
joints can follow in one control step; the tracked head frame the arm holds the tool in steps
towards this prediction no faster than they can (systems.teleop.tracked_frame), so the arm
never lags its command there.

**Why 60 Hz and 20 ms by default.** The following error during a startle is the head's motion
over the lag the prediction cannot remove. Over 50 seeded startles at the default case's site 36
(analyses.studies.head_motion, FCL against the moving scan) a 40 Hz, 30 ms camera without
prediction put the tool in tissue, and each step towards 60 Hz, 20 ms with the 2-sample
prediction kept more clearance (docs/measurements.md, the awake patient: the camera table).
The issue's range is 30-60 Hz and 20-50 ms; the default is its fast end, and
``analyze head-motion --tracker-rate-hz --tracker-latency-ms --prediction-samples`` measures
another camera against the same exact reference.

**Smoothing** (``smooth``, off by default). Even at its full rate (*Moving head*), a head
turning at 30-60 deg/s (0.5-1 rad/s) is corrected by every new sample (the slope's noise and
the turn's acceleration over the samples' age: up to 2.2-2.5 mm per control step at points
4-14 cm ahead of the neck, tracker alone, 15 deg at 60 deg/s, tests/systems/teleop/test_tracker.py),
which the arm has to make in one control step (before the moving-head rule, with the turn cut
by the two-sample dead zone's 0.6 rad/s: 3.9-4.6 mm). With ``smooth``:

- the ``VELOCITY_WINDOW``-sample fit (its own dead zones, 4 standard deviations of its slope:
  0.1 rad/s and 5.7 mm/s at 60 Hz, against 0.6 rad/s and 34 mm/s of the two-sample slope)
  says how much the head moves: a share rising linearly from 0 at its dead zone to 1 at twice
  it, for the rotation and the translation each. Within the dead zone the prediction is the
  default one; beyond it, the slope of the newest ``SMOOTH_SAMPLES`` samples times that share
  (unshortened at full share: a turn is predicted at its rate, not 0.6 rad/s below it);
- each new sample's correction (the previous samples' prediction at the moment the new one
  became available, against the new one's) is blended in linearly over one camera period, so
  the predicted pose is continuous in time (a new sample's noise, too, enters over a period).

Computed from the ring alone (no extra state). Measured (analyses.studies.head_turn, and
tests/systems/teleop/test_tracker.py on the tracker alone): see docs/measurements.md.

Core: :func:`camera_samples` (vectorized over ticks), :func:`predict_pose`. LeafSystem:
:class:`Tracker`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError
from implantplan.systems.frames import invert, rotation_vector, rotations

RING = 12  # samples kept: more than latency * rate + VELOCITY_WINDOW for every setting
VELOCITY_WINDOW = 6  # good samples in the velocity fit (0.1-0.2 s at 30-60 Hz)
SMOOTH_SAMPLES = 3  # good samples of the moving head's slope under ``smooth``
MOVING_SAMPLES = 3  # good samples (at least) of the moving head's slope by default


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
        predict_samples: good samples of the latency-compensating prediction (module notes);
            0 turns it off (the arm follows the delayed estimate).
        smooth: the prediction for a fast head (module notes, *Smoothing*): off by default
            (it loses clearance in a startle: docs/measurements.md, the awake patient).
    """

    rate: float = 60.0
    latency: float = 0.02
    noise_position: float = 0.0001
    noise_angle: float = float(np.deg2rad(0.1))
    dropouts: tuple = ()
    seed: int = 0
    reach: float = 0.1
    predict_samples: int = 2
    smooth: bool = False

    def __post_init__(self):
        if not (np.isfinite(self.rate) and 30.0 <= self.rate <= 60.0):
            raise InputError("tracker.rate", f"expected 30-60 Hz, got {self.rate}")
        if not (np.isfinite(self.latency) and 0.0 <= self.latency <= 0.1):
            raise InputError("tracker.latency", f"expected 0-100 ms, got {self.latency} s")
        for name in ("noise_position", "noise_angle", "reach"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"tracker.{name}", f"expected a finite value >= 0, got {v}")
        if not (isinstance(self.predict_samples, int | np.integer)
                and (self.predict_samples == 0 or 2 <= self.predict_samples <= RING // 2)):
            raise InputError("tracker.predict_samples", f"expected 0 (no prediction) or an "
                             f"integer 2-{RING // 2}, got {self.predict_samples!r}")
        if not isinstance(self.smooth, bool | np.bool_):
            raise InputError("tracker.smooth", f"expected true or false, got {self.smooth!r}")
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

    def gates(self, samples: int | None = None) -> tuple[float, float]:
        """(m/s, rad/s) the prediction's dead zones: 4 standard deviations of the noise of a
        ``predict_samples``-sample slope (or a ``samples``-sample one) at the camera's rate (a
        still head's fitted slope stays inside them, so the prediction adds no noise to a still
        head)."""
        k = max(self.predict_samples if samples is None else samples, 2)
        tt = (np.arange(k) - 0.5 * (k - 1)) / self.rate
        spread = float(np.sqrt(tt @ tt))
        return 4.0 * self.noise_position / spread, 4.0 * self.noise_angle / spread

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
    return _slopes(rows)[2]


def _slopes(rows: np.ndarray):
    """Least-squares lines through samples ``rows`` (n, 14) [t, good, p, R], n >= 2: (t_mean,
    Y_mean (6,), slope (6,)) of Y = [rotation vector from the newest sample (World); p]."""
    t = rows[:, 0]
    R = rows[:, 5:14].reshape(-1, 3, 3)
    dR = R @ R[-1].T  # rotation of each sample from the newest, in World
    w = 0.5 * np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0],
                        dR[:, 1, 0] - dR[:, 0, 1]], axis=1)
    Y = np.concatenate([w, rows[:, 2:5]], axis=1)
    tm, Ym = t.mean(), Y.mean(axis=0)
    tc = t - tm
    return tm, Ym, tc @ (Y - Ym) / (tc @ tc)


def _shrink(v: np.ndarray, gate: float) -> np.ndarray:
    """v shortened by ``gate`` (zero inside it): the soft threshold of a noisy slope."""
    n = float(np.linalg.norm(v))
    return v * max(0.0, 1.0 - gate / n) if n > 0 else v


def _kept(v: np.ndarray, gate: float) -> float:
    """How much a slope ``v`` says the head moves: 0 inside its dead zone ``gate``, rising
    linearly to 1 at twice the gate (a noise-free camera's zero gate: 1 for any motion)."""
    n = float(np.linalg.norm(v))
    if gate <= 0.0:
        return 1.0 if n > 0.0 else 0.0
    return float(np.clip(n / gate - 1.0, 0.0, 1.0))


def predict_pose(rows: np.ndarray, t: float, gates: tuple[float, float], *,
                 line=None) -> np.ndarray:
    """(4, 4) the head pose at time ``t`` extrapolated from the good samples ``rows`` (n >= 2,
    oldest first): the least-squares line through them evaluated at the newest sample's time,
    carried to ``t`` by the slope shortened by ``gates`` (m/s, rad/s; :func:`_shrink`).
    ``line``: ``_slopes(rows)`` if already known."""
    tm, Ym, S = _slopes(rows) if line is None else line
    t_new = rows[-1, 0]
    Y = Ym + S * (t_new - tm)
    Y[:3] += _shrink(S[:3], gates[1]) * (t - t_new)
    Y[3:] += _shrink(S[3:], gates[0]) * (t - t_new)
    X = np.eye(4)
    X[:3, :3] = rotations(Y[None, :3])[0] @ rows[-1, 5:14].reshape(3, 3)
    X[:3, 3] = Y[3:]
    return X


def camera_noise(params: TrackerParams, ticks, seed: int | None = None) -> np.ndarray:
    """(n, 6) [rotation vector (rad); translation (m)] noise of camera ticks ``ticks`` (n,):
    a pure function of (seed, tick), so every run with the same seed sees the same noise
    (``seed``: instead of ``params.seed``)."""
    ticks = np.atleast_1d(np.asarray(ticks, dtype=np.int64))
    seed = params.seed if seed is None else seed
    out = np.empty((ticks.shape[0], 6))
    for i, k in enumerate(ticks):
        z = np.random.default_rng([seed, int(k)]).standard_normal(6)
        out[i, :3] = params.noise_angle * z[:3]
        out[i, 3:] = params.noise_position * z[3:]
    return out


def camera_samples(params: TrackerParams, X_true: np.ndarray, ticks,
                   seed: int | None = None) -> np.ndarray:
    """(n, 4, 4) noisy measurements of the true poses ``X_true`` (n, 4, 4) at ``ticks``: the
    noise rotation applied about the pose's origin, then the noise translation (``seed``:
    instead of ``params.seed``)."""
    X = np.array(X_true, dtype=float, copy=True).reshape(-1, 4, 4)
    nz = camera_noise(params, ticks, seed)
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
        - X_WHead_predicted
        - V_WHead_estimated
        - lost

    ``X_WHead`` (abstract RigidTransform): the true head pose. ``X_WHead_estimated`` (abstract
    RigidTransform): the newest good sample taken at least ``latency`` ago (the initial pose
    before the first one). ``X_WHead_predicted`` (abstract RigidTransform): that estimate
    carried to the present (:meth:`predicted`; module notes). ``V_WHead_estimated`` (6):
    [angular velocity; velocity] of the head, the slope over the newest ``VELOCITY_WINDOW`` good
    available samples (zero before that many). ``lost`` (1): 1.0 when the
    newest available sample is missing (marker occluded), else 0.0.

    State: a ring of the last ``RING`` samples [time, good, p (3), R (9)], written at the
    camera's rate, and the newest good available sample (held through long dropouts).

    The noise's seed is a parameter of the context (``params.seed`` by default;
    :meth:`set_seed`), so one diagram replays runs with other noise.
    """

    def __init__(self, params: TrackerParams, X_WHead0):
        super().__init__()
        self._p = params
        self._gates = params.gates()
        self._moving_gates = params.gates(VELOCITY_WINDOW)
        self._memo = None  # (key, entry, the available rows' bytes) of the last _rows call
        X0 = np.asarray(X_WHead0, dtype=float)
        self._X0 = X0
        row = np.concatenate([[-np.inf, 1.0], X0[:3, 3], X0[:3, :3].ravel()])
        # [ring (RING x 14), next slot, held: the newest good available sample (14)]
        self.DeclareDiscreteState(np.concatenate([np.tile(row, RING), [0.0], row]))
        self.DeclarePeriodicDiscreteUpdateEvent(params.period, 0.0, self._update)
        self._seed = self.DeclareAbstractParameter(AbstractValue.Make(int(params.seed)))
        self._X_in = self.DeclareAbstractInputPort("X_WHead",
                                                   AbstractValue.Make(RigidTransform()))
        self.DeclareAbstractOutputPort("X_WHead_estimated",
                                       lambda: AbstractValue.Make(RigidTransform()),
                                       self._calc_pose, prerequisites_of_calc={
                                           self.xd_ticket(), self.time_ticket()})
        self.DeclareAbstractOutputPort("X_WHead_predicted",
                                       lambda: AbstractValue.Make(RigidTransform()),
                                       self._calc_predicted, prerequisites_of_calc={
                                           self.xd_ticket(), self.time_ticket()})
        self.DeclareVectorOutputPort("V_WHead_estimated", 6, self._calc_velocity,
                                     prerequisites_of_calc={self.xd_ticket(),
                                                            self.time_ticket()})
        self.DeclareVectorOutputPort("lost", 1, self._calc_lost, prerequisites_of_calc={
            self.xd_ticket(), self.time_ticket()})

    @property
    def params(self) -> TrackerParams:
        """The camera's settings (the seed: the default context's)."""
        return self._p

    def set_seed(self, context, seed: int) -> None:
        """Draw the noise from ``seed`` in ``context`` (this system's context or a diagram's
        root one)."""
        if not isinstance(seed, int | np.integer):
            raise InputError("tracker.seed", f"expected an integer, got {seed!r}")
        own = self.GetMyMutableContextFromRoot(context)
        own.get_mutable_abstract_parameter(self._seed).set_value(int(seed))

    def seed_in(self, context) -> int:
        """The noise's seed in ``context`` (this system's or the root)."""
        return self.GetMyContextFromRoot(context).get_abstract_parameter(self._seed).get_value()

    def _update(self, context, discrete_state):
        x = context.get_discrete_state(0).get_value().copy()
        t = context.get_time()
        good = self._good(context)
        if good.shape[0]:  # held through dropouts longer than the ring
            x[-14:] = good[-1]
        tick = int(round(t * self._p.rate))
        X = self._X_in.Eval(context).GetAsMatrix4()
        Xm = camera_samples(self._p, X[None], [tick],
                            context.get_abstract_parameter(self._seed).get_value())[0]
        slot = int(x[14 * RING]) % RING
        good = 0.0 if self._p.missing(t)[0] else 1.0
        x[14 * slot:14 * slot + 14] = np.concatenate([[t, good], Xm[:3, 3], Xm[:3, :3].ravel()])
        x[14 * RING] = (slot + 1) % RING
        discrete_state.get_mutable_vector(0).SetFromVector(x)

    def _rows(self, context) -> dict:
        """The available samples (taken >= latency ago, oldest first), the good ones among them
        and what is fitted to them, memoized on (state, which samples are available): every
        output port asks at every control step, the answer changes only at camera ticks."""
        x = context.get_discrete_state(0).get_value()
        times = x[:14 * RING:14]
        avail = times <= context.get_time() - self._p.latency + 1e-9
        key = (x.tobytes(), avail.tobytes())
        if self._memo is not None and self._memo[0] == key:
            return self._memo[1]
        ring = x[:14 * RING].reshape(RING, 14)
        order = np.argsort(times, kind="stable")
        rows = ring[order][avail[order]]
        # a sample taken but not yet available changes the state, not the answer: the fits
        # are kept while the available samples are the same
        rows_key = rows.tobytes()
        if self._memo is not None and self._memo[2] == rows_key:
            entry = self._memo[1]
        else:
            entry = {"available": rows, "good": rows[rows[:, 1] > 0.5]}
        self._memo = (key, entry, rows_key)
        return entry

    def _available(self, context) -> np.ndarray:
        """Rows of the available samples (taken >= latency ago), oldest first."""
        return self._rows(context)["available"]

    def _good(self, context) -> np.ndarray:
        return self._rows(context)["good"]

    def estimate(self, context) -> np.ndarray:
        """(4, 4) the current estimate of the head pose."""
        good = self._good(context)
        row = good[-1] if good.shape[0] else context.get_discrete_state(0).get_value()[-14:]
        X = np.eye(4)
        X[:3, 3], X[:3, :3] = row[2:5], row[5:14].reshape(3, 3)
        return X

    def predicted(self, context) -> np.ndarray:
        """(4, 4) the head pose now, extrapolated over the samples' age (:func:`predict_pose`
        on the newest ``predict_samples`` good samples); the estimate itself without prediction,
        with fewer good samples, on lost tracking, or when the newest good sample is older than
        latency + two camera periods (a dropout: never extrapolate across a gap)."""
        k = self._p.predict_samples
        entry = self._rows(context)
        good = entry["good"]
        good = good[np.isfinite(good[:, 0])]
        t = context.get_time()
        if (k < 2 or good.shape[0] < k or self._lost_now(context)
                or t - good[-1, 0] > self._p.latency + 2.0 * self._p.period + 1e-9):
            return self.estimate(context)
        if not self._p.smooth:
            if "line" not in entry:
                entry["line"] = self._default_line(good)
            rows, line, gates = entry["line"]
            return predict_pose(rows, t, gates, line=line)
        if "smooth" not in entry:
            entry["smooth"] = self._smooth_line(good)
        rows, line, gates = entry["smooth"]
        X = predict_pose(rows, t, gates, line=line)
        # the correction of the newest sample, blended in over one camera period
        t_a = good[-1, 0] + self._p.latency  # when the newest sample became available
        f = 1.0 - (t - t_a) * self._p.rate
        if f <= 0.0 or good.shape[0] < k + 1 or good[-1, 0] - good[-2, 0] > 1.5 * self._p.period:
            return X
        if "correction" not in entry:
            old = self._smooth_predict(good[:-1], t_a)
            new = predict_pose(rows, t_a, gates, line=line)
            C = old @ invert(new)
            entry["correction"] = (rotation_vector(C[:3, :3]), C[:3, 3])
        w, u = entry["correction"]
        C = np.eye(4)
        C[:3, :3], C[:3, 3] = rotations((f * w)[None])[0], f * u
        return C @ X

    def _default_line(self, good: np.ndarray):
        """(rows, line, gates) of the default prediction from the good samples ``good``
        (oldest first; module notes, *Moving head*): the ``predict_samples`` slope shortened by
        its dead zones while the ``VELOCITY_WINDOW`` fit calls the head still; for a moving
        head the slope of the newest ``max(MOVING_SAMPLES, predict_samples)`` samples, its own
        dead zones scaled by 1 - the share the fit says the head moves by (rotation and
        translation each)."""
        k = self._p.predict_samples
        still = good[-k:], _slopes(good[-k:]), self._gates
        if good.shape[0] < VELOCITY_WINDOW:
            return still
        v = _slopes(good[-VELOCITY_WINDOW:])[2]
        gp, gw = self._moving_gates
        share = np.array([_kept(v[:3], gw), _kept(v[3:], gp)])
        if not share.any():
            return still
        rows = good[-max(MOVING_SAMPLES, k):]
        gp, gw = self._p.gates(rows.shape[0])
        return rows, _slopes(rows), (gp * (1.0 - share[1]), gw * (1.0 - share[0]))

    def _smooth_predict(self, good: np.ndarray, t: float) -> np.ndarray:
        """The prediction under ``smooth`` from the good samples ``good`` (oldest first) at
        ``t``: the default (shortened ``predict_samples`` slope) for a head the
        ``VELOCITY_WINDOW`` fit calls still, the ``SMOOTH_SAMPLES`` slope times the share it
        moves by for a moving one (module notes)."""
        rows, line, gates = self._smooth_line(good)
        return predict_pose(rows, t, gates, line=line)

    def _smooth_line(self, good: np.ndarray):
        """(rows, line, gates) of :meth:`_smooth_predict`'s prediction from ``good``: what
        :func:`predict_pose` evaluates at any time (the same between camera samples)."""
        k = self._p.predict_samples
        if good.shape[0] < max(VELOCITY_WINDOW, SMOOTH_SAMPLES):
            return good[-k:], _slopes(good[-k:]), self._gates
        v = _slopes(good[-VELOCITY_WINDOW:])[2]
        gp, gw = self._moving_gates
        share = np.array([_kept(v[:3], gw), _kept(v[3:], gp)])
        if not share.any():
            return good[-k:], _slopes(good[-k:]), self._gates
        line = _slopes(good[-SMOOTH_SAMPLES:])
        S = line[2].copy()
        S[:3] *= share[0]
        S[3:] *= share[1]
        return good[-SMOOTH_SAMPLES:], (line[0], line[1], S), (0.0, 0.0)

    def _calc_predicted(self, context, value):
        X = self.predicted(context)
        value.set_value(RigidTransform(RotationMatrix.ProjectToRotationMatrix(X[:3, :3]),
                                       X[:3, 3]))

    def _calc_pose(self, context, value):
        X = self.estimate(context)
        value.set_value(RigidTransform(RotationMatrix.ProjectToRotationMatrix(X[:3, :3]),
                                       X[:3, 3]))

    def _calc_velocity(self, context, output: BasicVector):
        entry = self._rows(context)
        if "velocity" not in entry:
            good = entry["good"]
            entry["velocity"] = velocity_fit(good[np.isfinite(good[:, 0])][-VELOCITY_WINDOW:])
        output.SetFromVector(entry["velocity"])

    def _lost_now(self, context) -> bool:
        rows = self._available(context)
        rows = rows[np.isfinite(rows[:, 0])]
        return bool(rows.shape[0] > 0 and rows[-1, 1] < 0.5)

    def _calc_lost(self, context, output: BasicVector):
        output.SetFromVector([1.0 if self._lost_now(context) else 0.0])
