"""The awake patient's head motion (DESIGN.md section 7, seed 001): seeded profiles or a CSV.

The motion is a rigid displacement D(t) of the head in World, D(0) = identity: a rotation by the
rotation vector w(t) about the pivot p (a World point, by default the Center origin) followed by
a translation u(t),

    D(t) x = R(w(t)) (x - p) + p + u(t),

so the head frame (the case's Center frame, fixed in the head) is X_WHead(t) = D(t) X_WHead(0).
Profiles (all amplitudes and times drawn from ``seed``):

- ``breathing``: u = A (1 - cos 2 pi f t) / 2 along a mostly vertical unit vector, f in
  [0.2, 0.3] Hz, peak-to-peak A in [1, 2] mm;
- ``swallow``: one bump A sin^2(pi (t - t0) / 1 s) (rises A in [3, 5] mm within 0.5 s, returns
  within the next 0.5 s), t0 in [1, 3] s;
- ``startle``: a minimum-jerk step of A in [5, 10] mm and a rotation of [2, 4] deg within 0.2 s
  at t0 in [1, 3] s; the head then stays where it went;
- ``drift``: a constant velocity of [2, 5] mm/min and [0.5, 1] deg/min;
- ``turn``: the head turned about the neck (the cranial axis through the dens of C2, ``neck``:
  :func:`neck_of` the Center frame) by A in [10, 15] deg, either way, a minimum-jerk step whose
  peak rate is drawn in [30, 60] deg/s (a quick look aside), at t0 in [1, 3] s; it stays turned;
- a CSV file (``t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad``: the displacement against time, rotation
  vector about the pivot), linearly interpolated and held outside its time range.

The core (:class:`HeadMotion`) is vectorized over times; velocities are central differences of
the closed forms (1e-5 s). :class:`HeadMotionSource` is the LeafSystem over it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError
from implantplan.systems.frames import rotations

PROFILES = ("still", "breathing", "swallow", "startle", "drift", "turn")
CSV_HEADER = "t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad"
STARTLE_SECONDS = 0.2
SWALLOW_SECONDS = 1.0  # the whole bump: up within 0.5 s, back within the next 0.5 s
_FD = 1e-5  # s: central-difference step of the velocities
MIN_JERK_PEAK = 1.875  # the minimum-jerk step's peak rate, in units of its size / duration
NECK_BEHIND_CENTER = 0.04  # m: the neck's axis behind Center's origin (the back of the mouth):
# the oropharynx (about 15 mm deep) and the atlas' arch to the dens of C2 (about 25 mm)


def neck_of(X_WCenter) -> tuple[np.ndarray, np.ndarray]:
    """(a point, a unit axis) in World of the neck's turning axis for a head whose Center frame
    is ``X_WCenter``: along Center +Y (cranial), :data:`NECK_BEHIND_CENTER` behind Center's
    origin (Center -Z, away from the mouth)."""
    X = np.asarray(X_WCenter, dtype=float)
    return X[:3, 3] - NECK_BEHIND_CENTER * X[:3, 2], X[:3, 1] / np.linalg.norm(X[:3, 1])


def _min_jerk(tau):
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)


def _direction(rng, vertical: float) -> np.ndarray:
    """A random unit vector with at least ``vertical`` of it along World z."""
    v = rng.normal(size=3)
    v[2] = 0.0
    v /= max(np.linalg.norm(v), 1e-12)
    z = rng.uniform(vertical, 1.0)
    return np.array([*(np.sqrt(1.0 - z * z) * v[:2]), z * rng.choice([-1.0, 1.0])])


@dataclass
class HeadMotion:
    """A seeded head-motion profile (or a CSV recording) as a displacement of the head in World.

    Attributes:
        profile: one of ``PROFILES`` or ``"csv"``.
        seed: the seed of its random parameters.
        pivot: (3,) World point the rotation is about (m).
        params: the drawn parameters (SI), for reports.
        samples: (n, 7) [t, u (3), w (3)] of a CSV recording, else None.
    """

    profile: str
    seed: int = 0
    pivot: np.ndarray = field(default_factory=lambda: np.zeros(3))
    params: dict = field(default_factory=dict)
    samples: np.ndarray | None = None

    @classmethod
    def make(cls, profile: str, *, seed: int = 0, pivot=None, start: float = 1.0,
             window: float = 2.0, neck=None) -> HeadMotion:
        """Draw a profile's parameters from ``seed``; ``start``/``window``: the swallow's,
        startle's or turn's onset is uniform in [start, start + window] s; ``neck``: (point,
        axis) in World of the turn's axis (default: World Z through the pivot)."""
        pivot = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=float).reshape(3)
        if profile not in PROFILES:
            path = Path(profile)
            if path.suffix.lower() == ".csv" or path.is_file():
                return cls.from_csv(path, pivot=pivot)
            raise InputError(
                "--head-motion", f"expected one of {', '.join(PROFILES[1:])} or a CSV file, "
                f"got {profile!r}")
        rng = np.random.default_rng(seed)
        p: dict = {}
        if profile == "breathing":
            p = {"frequency_hz": rng.uniform(0.2, 0.3), "amplitude_m": rng.uniform(0.001, 0.002),
                 "direction": _direction(rng, 0.8)}
        elif profile == "swallow":
            p = {"onset_s": rng.uniform(start, start + window),
                 "amplitude_m": rng.uniform(0.003, 0.005), "direction": _direction(rng, 0.8)}
        elif profile == "startle":
            axis = rng.normal(size=3)
            p = {"onset_s": rng.uniform(start, start + window),
                 "amplitude_m": rng.uniform(0.005, 0.010), "direction": _direction(rng, 0.0),
                 "angle_rad": np.deg2rad(rng.uniform(2.0, 4.0)),
                 "axis": axis / np.linalg.norm(axis)}
        elif profile == "drift":
            axis = rng.normal(size=3)
            p = {"speed_m_s": rng.uniform(0.002, 0.005) / 60.0, "direction": _direction(rng, 0.0),
                 "rate_rad_s": np.deg2rad(rng.uniform(0.5, 1.0)) / 60.0,
                 "axis": axis / np.linalg.norm(axis)}
        elif profile == "turn":
            angle = np.deg2rad(rng.uniform(10.0, 15.0))
            rate = np.deg2rad(rng.uniform(30.0, 60.0))
            onset = rng.uniform(start, start + window)
            sign = float(rng.choice([-1.0, 1.0]))
            turn = cls.turn(angle=angle, peak_rate=rate, sign=sign, onset=onset, pivot=pivot,
                            neck=neck)
            return cls(profile=profile, seed=int(seed), pivot=pivot, params=turn.params)
        return cls(profile=profile, seed=int(seed), pivot=pivot, params=p)

    @classmethod
    def turn(cls, *, angle: float, peak_rate: float, sign: float, onset: float, pivot=None,
             neck=None) -> HeadMotion:
        """The ``turn`` profile with given parameters (the sweep of the head-motion study):
        ``angle`` (rad, > 0) about the neck's axis ``neck`` = (point, axis) in World (default
        World Z through the pivot), ``sign`` +1 / -1 along the axis or against it, a
        minimum-jerk step peaking at ``peak_rate`` (rad/s, > 0) from ``onset`` (s, >= 0)."""
        pivot = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=float).reshape(3)
        for name, value in (("angle", angle), ("peak_rate", peak_rate)):
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"turn.{name}", f"expected a finite value > 0, got {value}")
        if not (np.isfinite(onset) and onset >= 0):
            raise InputError("turn.onset", f"expected a finite time >= 0 s, got {onset}")
        if sign not in (-1.0, 1.0):
            raise InputError("turn.sign", f"expected +1 or -1, got {sign}")
        point, axis = (pivot, np.array([0.0, 0.0, 1.0])) if neck is None else neck
        axis = np.asarray(axis, dtype=float).reshape(3)
        p = {"onset_s": float(onset), "angle_rad": float(angle),
             "peak_rate_rad_s": float(peak_rate),
             "seconds": MIN_JERK_PEAK * float(angle) / float(peak_rate),
             "axis": float(sign) * axis / np.linalg.norm(axis),
             "neck_point": np.asarray(point, dtype=float).reshape(3)}
        return cls(profile="turn", pivot=pivot, params=p)

    @classmethod
    def from_csv(cls, path, *, pivot=None) -> HeadMotion:
        """A recorded displacement (``CSV_HEADER`` columns, SI, times increasing)."""
        path = Path(path)
        if not path.is_file():
            raise InputError("--head-motion", f"expected a profile name or a CSV file, no file "
                             f"{str(path)!r}")
        try:
            data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        except ValueError as err:
            raise InputError("--head-motion", f"{path}: expected numeric rows ({err})") from None
        if data.shape[1] != 7 or data.shape[0] < 2:
            raise InputError("--head-motion", f"{path}: expected >= 2 rows of 7 columns "
                             f"({CSV_HEADER}), got shape {data.shape}")
        if not np.all(np.isfinite(data)) or np.any(np.diff(data[:, 0]) <= 0):
            raise InputError("--head-motion", f"{path}: expected finite values and increasing t")
        pivot = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=float).reshape(3)
        return cls(profile="csv", pivot=pivot, params={"file": str(path)}, samples=data)

    def save_csv(self, path, t) -> Path:
        """Write this motion sampled at times ``t`` as a CSV recording (atomic)."""
        from implantplan.systems.files import write_text_atomic

        u, w = self.displacement(t)
        rows = np.column_stack([np.asarray(t, dtype=float), u, w])
        lines = [CSV_HEADER] + [",".join(f"{x:.9g}" for x in r) for r in rows]
        return write_text_atomic(Path(path), "\n".join(lines) + "\n")

    # -- the core ---------------------------------------------------------------------------

    def displacement(self, t) -> tuple[np.ndarray, np.ndarray]:
        """(u (n, 3) translation in m, w (n, 3) rotation vector in rad) at times ``t`` (n,)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        n = t.shape[0]
        u, w = np.zeros((n, 3)), np.zeros((n, 3))
        p = self.params
        if self.profile == "breathing":
            s = 0.5 * p["amplitude_m"] * (1.0 - np.cos(2.0 * np.pi * p["frequency_hz"] * t))
            u = s[:, None] * p["direction"]
        elif self.profile == "swallow":
            tau = np.clip((t - p["onset_s"]) / SWALLOW_SECONDS, 0.0, 1.0)
            u = (p["amplitude_m"] * np.sin(np.pi * tau) ** 2)[:, None] * p["direction"]
        elif self.profile == "startle":
            s = _min_jerk((t - p["onset_s"]) / STARTLE_SECONDS)
            u = (p["amplitude_m"] * s)[:, None] * p["direction"]
            w = (p["angle_rad"] * s)[:, None] * p["axis"]
        elif self.profile == "turn":
            s = _min_jerk((t - p["onset_s"]) / p["seconds"])
            w = (p["angle_rad"] * s)[:, None] * p["axis"]
            # about the neck, not the pivot: x -> R (x - c) + c = R (x - pivot) + pivot + u
            c = p["neck_point"] - self.pivot
            u = c - rotations(np.atleast_2d(w)) @ c
        elif self.profile == "drift":
            tt = np.maximum(t, 0.0)
            u = (p["speed_m_s"] * tt)[:, None] * p["direction"]
            w = (p["rate_rad_s"] * tt)[:, None] * p["axis"]
        elif self.profile == "csv":
            d = self.samples
            u = np.column_stack([np.interp(t, d[:, 0], d[:, 1 + i]) for i in range(3)])
            w = np.column_stack([np.interp(t, d[:, 0], d[:, 4 + i]) for i in range(3)])
            u, w = u - d[0, 1:4], w - d[0, 4:7]  # D(0) = identity: relative to the first row
        return u, w

    def speed_bounds(self) -> tuple[float, float]:
        """(rad/s, m/s) upper bounds, over all times, of the head's angular speed |omega| and
        of |du/dt|, the speed of the pivot's image p + u(t) (for bounds between sampled
        times: a head point x moves at most |omega| |x - p - u| + |du/dt|). From the closed
        forms: a minimum-jerk step of size A over T peaks at MIN_JERK_PEAK A / T, the swallow's
        A sin^2(pi tau) at pi A / T, the breathing's at pi f A; a CSV's piecewise-linear
        interpolation at its largest slope. The rotation vector's rate bounds |omega| (the
        left Jacobian of SO(3) has norm <= 1)."""
        p = self.params
        if self.profile == "breathing":
            return 0.0, float(np.pi * p["frequency_hz"] * p["amplitude_m"])
        if self.profile == "swallow":
            return 0.0, float(np.pi * p["amplitude_m"] / SWALLOW_SECONDS)
        if self.profile == "startle":
            return (float(MIN_JERK_PEAK * p["angle_rad"] / STARTLE_SECONDS),
                    float(MIN_JERK_PEAK * p["amplitude_m"] / STARTLE_SECONDS))
        if self.profile == "drift":
            return float(p["rate_rad_s"]), float(p["speed_m_s"])
        if self.profile == "turn":  # u = c - R c, c the neck point from the pivot
            w = float(p["peak_rate_rad_s"])
            return w, w * float(np.linalg.norm(p["neck_point"] - self.pivot))
        if self.profile == "csv":
            d = self.samples
            dt = np.diff(d[:, 0])[:, None]
            return (float(np.linalg.norm(np.diff(d[:, 4:7], axis=0) / dt, axis=1).max()),
                    float(np.linalg.norm(np.diff(d[:, 1:4], axis=0) / dt, axis=1).max()))
        return 0.0, 0.0  # still

    def D(self, t) -> np.ndarray:
        """(n, 4, 4) the head's displacement in World at times ``t``."""
        u, w = self.displacement(t)
        R = rotations(np.atleast_2d(w))
        X = np.repeat(np.eye(4)[None], R.shape[0], axis=0)
        X[:, :3, :3] = R
        X[:, :3, 3] = self.pivot - R @ self.pivot + u
        return X

    def velocity(self, t, point=None) -> np.ndarray:
        """(n, 6) [angular velocity; velocity of ``point`` (World, default the pivot)] of the
        head at times ``t``, by central differences of the closed forms."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        Xa, Xb = self.D(t + _FD), self.D(t - _FD)
        q = self.pivot if point is None else np.asarray(point, dtype=float).reshape(3)
        v = (Xa[:, :3, :3] @ q + Xa[:, :3, 3] - Xb[:, :3, :3] @ q - Xb[:, :3, 3]) / (2 * _FD)
        dR = (Xa[:, :3, :3] - Xb[:, :3, :3]) / (2 * _FD)
        Om = dR @ np.swapaxes(self.D(t)[:, :3, :3], 1, 2)
        omega = np.stack([Om[:, 2, 1], Om[:, 0, 2], Om[:, 1, 0]], axis=1)
        return np.concatenate([omega, v], axis=1)


class HeadMotionSource(LeafSystem):
    """The patient's head pose from a :class:`HeadMotion` (a function of time, no state).

    .. pydrake_system::

        name: HeadMotionSource
        output_ports:
        - X_WHead
        - V_WHead
        - D_W

    ``X_WHead`` (abstract RigidTransform): the head frame (the case's Center, fixed in the head)
    in World, D(t) X_WHead0. ``V_WHead`` (6): [angular velocity; velocity of the head frame's
    origin] in World. ``D_W`` (abstract RigidTransform): the displacement D(t) itself (what moves
    the head's geometry in the scene).

    The motion is a parameter of the context (``motion`` by default; :meth:`set_motion`), so
    one diagram replays runs with other head motions.

    Args:
        motion: the profile (the default context's).
        X_WHead0: (4, 4) the head frame at rest (t = 0).
    """

    def __init__(self, motion: HeadMotion, X_WHead0):
        super().__init__()
        self._motion = motion
        self._X0 = np.asarray(X_WHead0, dtype=float)
        self._param = self.DeclareAbstractParameter(AbstractValue.Make(motion))
        self._X = self.DeclareAbstractOutputPort(
            "X_WHead", lambda: AbstractValue.Make(RigidTransform()), self._calc_pose)
        self.DeclareVectorOutputPort("V_WHead", 6, self._calc_velocity)
        self.DeclareAbstractOutputPort(
            "D_W", lambda: AbstractValue.Make(RigidTransform()), self._calc_displacement)

    @property
    def motion(self) -> HeadMotion:
        """The motion of the default context."""
        return self._motion

    def set_motion(self, context, motion: HeadMotion) -> None:
        """Replay ``motion`` in ``context`` (this system's context or a diagram's root one)."""
        if not isinstance(motion, HeadMotion):
            raise InputError("head_motion", f"expected a HeadMotion, got {type(motion).__name__}")
        own = self.GetMyMutableContextFromRoot(context)
        own.get_mutable_abstract_parameter(self._param).set_value(motion)

    def motion_in(self, context) -> HeadMotion:
        """The motion ``context`` replays (this system's context or the root)."""
        return self.GetMyContextFromRoot(context).get_abstract_parameter(self._param).get_value()

    def _motion_of(self, context) -> HeadMotion:
        return context.get_abstract_parameter(self._param).get_value()

    def _calc_pose(self, context, value):
        X = self._motion_of(context).D(context.get_time())[0] @ self._X0
        value.set_value(RigidTransform(RotationMatrix(X[:3, :3]), X[:3, 3]))

    def _calc_displacement(self, context, value):
        X = self._motion_of(context).D(context.get_time())[0]
        value.set_value(RigidTransform(RotationMatrix(X[:3, :3]), X[:3, 3]))

    def _calc_velocity(self, context, output: BasicVector):
        output.SetFromVector(self._motion_of(context).velocity(context.get_time(),
                                                               self._X0[:3, 3])[0])
