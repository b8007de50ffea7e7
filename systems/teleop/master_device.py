"""Master device: the operator's commanded tool motion (scripted, recorded, mapped) + LeafSystem.

Seed 001 ("Experimental validation") feeds the actuator into the mouth under master-slave control
with a virtual fixture, ten times per layout ("10 sub-groups"), and says the master-slave strategy
changes single runs but not the statistics. We stand in for the person with a seeded *scripted
operator* whose randomness is the three things a hand does on a haptic stylus:

- **jitter**: a slow lateral drift (smoothed Gaussian noise, correlation ~0.3 s) plus a small
  physiological tremor (~9 Hz sine with random phase), both faded in and out with a window so the
  script starts at the start and ends at the target;
- **pauses**: the operator stops a few times (Poisson count, random lengths) along the way;
- **overshoot**: the stroke passes the target by a few millimetres along the feed direction and
  comes back.

The nominal stroke is a minimum-jerk profile s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 from the start
to the (overshoot) point and back. The path is generated in the slave's (World) frame and turned
into master-handle positions by the inverse of the mapping, so the same script can be replayed
under a different scale.

**Incremental mapping** (one of the strategies seed 001 lists): the slave's tool moves by the
master handle's increments, scaled and rotated into World: dp_W = scale * R_WM dp_M; as a
velocity command, v_W = scale * R_WM pdot_M. Rotations are mapped unscaled: the handle's
angular velocity w_M (in M) commands the tool's w_W = R_WM w_M (rotation scale 1, as in surgical
teleoperation where the motion scale applies to translation and the tool turns as the hand
does). The scripted operator holds the stylus orientation (w = 0: the feed is a translation
along the fixture's axis); live and recorded motions may turn it (the fixture bounds the tool's
orientation to beta of the planned one, systems.placement.fixture).

The handle's orientation part is kept as ``r_M`` (n, 3): the running integral of its angular
velocity in M, r_M[k] = sum_{j<k} w_M[j] dt (rad; r_M[0] = 0 for a recording that starts at
rest), so w_M[k] = (r_M[k+1] - r_M[k]) / dt, exactly as the velocity is the difference of the
positions. It equals the rotation vector of the handle's orientation relative to the start when
the handle turns about one fixed axis of M; in general it is the integral, not a rotation vector
(the replay needs the angular velocity, which the integral gives back exactly).

Recorded motions are CSV files with a header ``t_s,x_m,y_m,z_m`` (master handle positions, M
frame, uniform sampling) and optionally the three columns ``rx_rad,ry_rad,rz_rad`` (``r_M``);
a 4-column file is a motion without rotation.

The :class:`MasterDevice` LeafSystem replays a :class:`MasterMotion` as a zero-order hold: its
output at time t is the sample at floor(t / dt) (zero velocity after the end). A
:class:`GlitchedMotion` is a motion whose device reports other twists at a few samples (a driver
or link fault: NaN, inf or absurd values, which a MasterMotion's positions cannot hold); it
replays the same way, for testing the command limits (systems.teleop.command_limits). The
motion is an abstract *parameter* of the system's context (:meth:`MasterDevice.set_motion`), not
of the system: one diagram serves every run of a case, each run setting its motion in a fresh
context.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems import validate
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_text_atomic


@dataclass(frozen=True)
class MasterMotion:
    """Master handle positions (and optionally its turning) sampled uniformly.

    Attributes:
        dt: sample period (s).
        p_M: (n, 3) handle positions in the master device frame M (m), sample k at t = k dt.
        r_M: (n, 3) the integral of the handle's angular velocity in M (rad; module docstring),
            or None: the handle does not turn (w = 0).
    """

    dt: float
    p_M: np.ndarray
    r_M: np.ndarray | None = None

    def __post_init__(self):
        dt = float(self.dt)
        if not np.isfinite(dt) or dt <= 0:
            raise InputError("dt", f"expected a sample period > 0 s, got {self.dt}")
        p = np.asarray(self.p_M, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2:
            raise InputError("p_M", f"expected (n >= 2, 3) positions, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise InputError("p_M", "expected finite positions (m)")
        object.__setattr__(self, "dt", dt)
        object.__setattr__(self, "p_M", p)
        if self.r_M is not None:
            r = np.asarray(self.r_M, dtype=float)
            if r.shape != p.shape:
                raise InputError("r_M", f"expected one (3,) angle integral per position "
                                 f"{p.shape}, got shape {r.shape}")
            if not np.all(np.isfinite(r)):
                raise InputError("r_M", "expected finite angles (rad)")
            object.__setattr__(self, "r_M", r)

    @property
    def duration(self) -> float:
        """Time of the last sample (s)."""
        return (self.p_M.shape[0] - 1) * self.dt

    @property
    def t(self) -> np.ndarray:
        return np.arange(self.p_M.shape[0]) * self.dt

    def velocity_M(self) -> np.ndarray:
        """(n, 3) handle velocity (m/s): forward differences, held over each sample interval;
        the last sample's velocity is zero (the hand stops)."""
        v = np.zeros_like(self.p_M)
        v[:-1] = np.diff(self.p_M, axis=0) / self.dt
        return v

    def angular_velocity_M(self) -> np.ndarray:
        """(n, 3) handle angular velocity in M (rad/s), the differences of ``r_M`` held like
        :meth:`velocity_M` (zero without ``r_M``)."""
        w = np.zeros_like(self.p_M)
        if self.r_M is not None:
            w[:-1] = np.diff(self.r_M, axis=0) / self.dt
        return w


@dataclass(frozen=True)
class IncrementalMapping:
    """Slave increments = ``scale`` * R_WM * master increments.

    Attributes:
        scale: motion scale (slave m per master m), > 0.
        R_WM: (3, 3) orientation of the master device frame in World.
    """

    scale: float = 1.0
    R_WM: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self):
        scale = float(self.scale)
        if not np.isfinite(scale) or scale <= 0:
            raise InputError("scale", f"expected a motion scale > 0, got {self.scale}")
        R = validate.rotation(self.R_WM, "R_WM")
        object.__setattr__(self, "scale", scale)
        object.__setattr__(self, "R_WM", R)

    def to_world(self, d_M) -> np.ndarray:
        """Master increments or velocities (..., 3) -> slave ones in World."""
        return self.scale * np.asarray(d_M, dtype=float) @ self.R_WM.T

    def to_master(self, d_W) -> np.ndarray:
        """Inverse of :meth:`to_world`."""
        return np.asarray(d_W, dtype=float) @ self.R_WM / self.scale

    def angular_to_world(self, w_M) -> np.ndarray:
        """Master angular velocities or angle increments (..., 3) -> the tool's in World,
        w_W = R_WM w_M (rotations are not scaled)."""
        return np.asarray(w_M, dtype=float) @ self.R_WM.T


@dataclass(frozen=True)
class Operator:
    """The scripted operator's habits (SI units). Defaults: a calm feed at 10 mm/s.

    Attributes:
        speed: mean speed of the stroke (m/s).
        drift: RMS lateral drift of the hand (m).
        tremor: amplitude of the ~9 Hz tremor (m).
        pauses_per_feed: mean number of pauses (Poisson).
        pause_seconds: (min, max) length of one pause (s).
        overshoot: (min, max) distance past the target along the feed (m).
    """

    speed: float = 0.010
    drift: float = 0.0003
    tremor: float = 0.00005
    pauses_per_feed: float = 1.5
    pause_seconds: tuple[float, float] = (0.2, 0.8)
    overshoot: tuple[float, float] = (0.0005, 0.002)

    def __post_init__(self):
        if not np.isfinite(self.speed) or self.speed <= 0:
            raise InputError("speed", f"expected a speed > 0 m/s, got {self.speed}")
        for name in ("drift", "tremor", "pauses_per_feed"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise InputError(name, f"expected a finite value >= 0, got {value}")
        for name in ("pause_seconds", "overshoot"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi)) or lo < 0 or hi < lo:
                raise InputError(name, f"expected (min, max) with 0 <= min <= max, got {(lo, hi)}")


def _min_jerk(tau: np.ndarray) -> np.ndarray:
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


def scripted_feed(
    start_W,
    target_W,
    *,
    seed: int | np.random.Generator = 0,
    operator: Operator | None = None,
    mapping: IncrementalMapping | None = None,
    dt: float = 0.005,
    settle: float = 0.5,
) -> MasterMotion:
    """One scripted feed from ``start_W`` to ``target_W`` (tool positions in World, m).

    The slave path is p_W(t) = start + s(t) * (target - start) + overshoot bump + jitter, where
    s is a minimum-jerk stroke to 1 + overshoot/L and back to 1, stopped by the pauses; the jitter
    is perpendicular to the feed direction and windowed to zero at both ends. ``settle`` seconds of
    stillness close the script. Same seed, same motion, bit for bit.

    Returns:
        The master handle motion (M frame) that produces this slave path under ``mapping``.
    """
    op = operator or Operator()
    mapping = mapping or IncrementalMapping()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    p0 = np.asarray(start_W, dtype=float).reshape(3)
    p1 = np.asarray(target_W, dtype=float).reshape(3)
    if not (np.all(np.isfinite(p0)) and np.all(np.isfinite(p1))):
        raise InputError("start_W/target_W", "expected finite positions (m)")
    feed = p1 - p0
    L = float(np.linalg.norm(feed))
    if L < 1e-6:
        raise InputError("target_W", "expected a target at least 1 um away from the start")
    if not np.isfinite(dt) or dt <= 0:
        raise InputError("dt", f"expected a sample period > 0 s, got {dt}")
    u = feed / L

    over = rng.uniform(*op.overshoot)
    t_in = (L + over) / op.speed
    t_back = max(over / op.speed * 2.0, 0.2) if over > 0 else 0.0
    n_pause = int(rng.poisson(op.pauses_per_feed))
    pause_at = np.sort(rng.uniform(0.1, 0.9, n_pause)) * t_in  # during the stroke in
    pause_len = rng.uniform(*op.pause_seconds, n_pause)
    t_motion = t_in + t_back
    total = t_motion + pause_len.sum() + settle
    t = np.arange(int(np.ceil(total / dt)) + 1) * dt

    # Motion clock: wall time minus the pauses taken so far (vectorized over samples).
    starts = pause_at + np.concatenate([[0.0], np.cumsum(pause_len)[:-1]])  # in wall time
    paused = np.clip(t[:, None] - starts[None, :], 0.0, pause_len[None, :]).sum(axis=1)
    tm = np.clip(t - paused, 0.0, t_motion)
    s_over = 1.0 + over / L
    s = np.where(
        tm <= t_in,
        s_over * _min_jerk(tm / t_in),
        s_over - (s_over - 1.0) * _min_jerk((tm - t_in) / max(t_back, 1e-12)),
    )

    # Lateral jitter: smoothed noise (drift) + tremor, both perpendicular to the feed.
    x_hint = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = x_hint - (x_hint @ u) * u
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    n = t.size
    corr = max(int(round(0.3 / dt)), 1)
    kernel = np.exp(-0.5 * (np.arange(-3 * corr, 3 * corr + 1) / corr) ** 2)
    noise = rng.standard_normal((n + kernel.size - 1, 2))
    drift = np.stack([np.convolve(noise[:, i], kernel, mode="valid") for i in range(2)], axis=1)
    drift *= op.drift / max(np.sqrt(np.mean(drift**2)), 1e-12)
    phase = rng.uniform(0.0, 2.0 * np.pi, 2)
    freq = rng.uniform(8.0, 10.0)
    tremor = op.tremor * np.sin(2.0 * np.pi * freq * t[:, None] + phase[None, :])
    window = np.sin(np.pi * np.clip(tm / t_motion, 0.0, 1.0)) ** 2
    lateral = (drift + tremor) * window[:, None]

    p_W = p0 + s[:, None] * feed + lateral[:, :1] * e1 + lateral[:, 1:] * e2
    p_M = mapping.to_master(p_W - p0)
    return MasterMotion(dt=dt, p_M=p_M)


def feeding_runs(
    start_W, target_W, *, runs: int = 10, seed: int = 0, operator=None, mapping=None, dt=0.005
) -> list[MasterMotion]:
    """The paper's sub-groups: ``runs`` scripted feeds with independent operator randomness.

    Run i uses the i-th child of ``np.random.SeedSequence(seed)``, so run i is the same whatever
    ``runs`` is.
    """
    if int(runs) != runs or runs < 1:
        raise InputError("runs", f"expected an integer >= 1, got {runs}")
    children = np.random.SeedSequence(seed).spawn(int(runs))
    return [
        scripted_feed(
            start_W,
            target_W,
            seed=np.random.default_rng(c),
            operator=operator,
            mapping=mapping,
            dt=dt,
        )
        for c in children
    ]


@dataclass(frozen=True)
class GlitchedMotion:
    """A master motion whose device reports the twists ``V_W`` instead of the motion's own at the
    samples ``samples`` (a fault of the device or its link; any values, non-finite included).

    Attributes:
        motion: the hand's motion.
        samples: (m,) sample indices (0 <= k < n) the glitches replace.
        V_W: (m, 6) the reported twists [w; v], in World (after the mapping: what the master
            system outputs on those samples).
    """

    motion: MasterMotion
    samples: np.ndarray
    V_W: np.ndarray

    def __post_init__(self):
        if not isinstance(self.motion, MasterMotion):
            raise InputError("motion", f"expected a MasterMotion, got {type(self.motion).__name__}")
        k = np.asarray(self.samples).reshape(-1)
        n = self.motion.p_M.shape[0]
        if k.dtype.kind not in "iu" or np.any((k < 0) | (k >= n)):
            raise InputError("samples", f"expected sample indices in [0, {n})")
        V = np.asarray(self.V_W, dtype=float).reshape(-1, 6)
        if V.shape[0] != k.size:
            raise InputError("V_W", f"expected one twist (6,) per sample ({k.size}), "
                             f"got shape {np.shape(self.V_W)}")
        object.__setattr__(self, "samples", k.astype(int))
        object.__setattr__(self, "V_W", V)

    @property
    def dt(self) -> float:
        return self.motion.dt

    @property
    def p_M(self) -> np.ndarray:
        """The hand's positions (the motion's; the glitches are in the reported twists)."""
        return self.motion.p_M

    @property
    def duration(self) -> float:
        return self.motion.duration

    @property
    def t(self) -> np.ndarray:
        return self.motion.t


CSV_COLUMNS = ("t_s", "x_m", "y_m", "z_m")
CSV_ROTATION_COLUMNS = ("rx_rad", "ry_rad", "rz_rad")


def save_csv(path, motion: MasterMotion) -> Path:
    """Write a motion as CSV, atomically: ``t_s,x_m,y_m,z_m``, and ``rx_rad,ry_rad,rz_rad``
    (``r_M``) when the motion has an orientation part."""
    columns = [motion.t[:, None], motion.p_M]
    header = list(CSV_COLUMNS)
    if motion.r_M is not None:
        columns.append(motion.r_M)
        header += CSV_ROTATION_COLUMNS
    lines = [",".join(header)]
    lines += [",".join(repr(v) for v in row) for row in np.hstack(columns).tolist()]
    return write_text_atomic(path, "\n".join(lines) + "\n")


def load_csv(path, *, field: str = "csv") -> MasterMotion:
    """Read a recorded motion (``t_s,x_m,y_m,z_m[,rx_rad,ry_rad,rz_rad]``, uniform sampling;
    a 4-column file has no orientation part)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(field, f"file {str(path)!r} does not exist")
    with path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    header = [c.strip() for c in rows[0]] if rows else []
    if header not in (list(CSV_COLUMNS), list(CSV_COLUMNS + CSV_ROTATION_COLUMNS)):
        raise InputError(field, f"{path}: expected the header t_s,x_m,y_m,z_m "
                         "(optionally followed by rx_rad,ry_rad,rz_rad)")
    body = [r for r in rows[1:] if r]
    short = [i + 2 for i, r in enumerate(body) if len(r) != len(header)]
    if short:
        raise InputError(field, f"{path}: expected {len(header)} columns in every row "
                         f"(line {short[0]})")
    try:
        data = np.array([[float(c) for c in r] for r in body], dtype=float)
    except ValueError:
        raise InputError(field, f"{path}: expected numbers in every row") from None
    if data.ndim != 2 or data.shape[0] < 2:
        raise InputError(field, f"{path}: expected at least 2 rows of {len(header)} columns")
    dts = np.diff(data[:, 0])
    if np.any(dts <= 0) or not np.allclose(dts, dts[0], rtol=1e-6, atol=1e-9):
        raise InputError(field, f"{path}: expected uniformly increasing t_s")
    return MasterMotion(dt=float(dts[0]), p_M=data[:, 1:4],
                        r_M=data[:, 4:7] if data.shape[1] == 7 else None)


@dataclass(frozen=True)
class _Playback:
    """A motion and its slave-side tables under one mapping (the context parameter's value)."""

    motion: MasterMotion
    v_W: np.ndarray  # (n, 3) commanded velocity per sample
    d_W: np.ndarray  # (n, 3) commanded displacement from the start per sample
    w_W: np.ndarray  # (n, 3) commanded angular velocity per sample
    V_W: np.ndarray = field(init=False, repr=False)  # (n, 6) [w_W, v_W]: the output per sample

    def __post_init__(self):
        object.__setattr__(self, "V_W", np.hstack([self.w_W, self.v_W]))

    @classmethod
    def of(cls, motion: MasterMotion | GlitchedMotion, mapping: IncrementalMapping) -> _Playback:
        glitch = motion if isinstance(motion, GlitchedMotion) else None
        motion = motion.motion if glitch is not None else motion
        if not isinstance(motion, MasterMotion):
            raise InputError("motion", f"expected a MasterMotion, got {type(motion).__name__}")
        v_W = mapping.to_world(motion.velocity_M())
        w_W = mapping.angular_to_world(motion.angular_velocity_M())
        if glitch is not None:
            w_W[glitch.samples], v_W[glitch.samples] = glitch.V_W[:, :3], glitch.V_W[:, 3:]
        return cls(motion, v_W, mapping.to_world(motion.p_M - motion.p_M[0]), w_W)


STILL = MasterMotion(dt=1.0, p_M=np.zeros((2, 3)))  # the hand at rest: the default motion


class MasterDevice(LeafSystem):
    """Replays a master handle motion as the operator's commanded tool motion.

    .. pydrake_system::

        name: MasterDevice
        output_ports:
        - V_WE_command
        - p_WE_offset
        - p_M
        - r_M

    ``V_WE_command`` (6): commanded spatial velocity of the tool, [w; v] in World (w = R_WM
    w_M, zero for a motion without ``r_M``; v = scale R_WM pdot_M). ``p_WE_offset`` (3): the
    commanded tool displacement from the start, scale R_WM (p_M(t) - p_M(0)). ``p_M`` (3): the
    handle position; ``r_M`` (3): its angle integral (zero without one). All are zero-order
    holds of the samples (the value at floor(t/dt)).

    The motion is a context parameter: ``motion`` (default: the hand at rest) goes into the
    default context, :meth:`set_motion` replaces it in a given context, so one diagram replays
    any number of runs.

    After the motion ends the hand is still (zero command) unless ``target_W`` is given: then the
    system has the optional input ``X_WE_measured`` (abstract RigidTransform) and the operator
    *finishes by eye*: v = finish_gain (target_W - p_WE), its norm capped at ``finish_speed``
    (a person watching the tool closes the last millimetres that incremental mapping and the
    fixture's stop at the target leave open; the script alone is open loop).

    .. pydrake_system::

        name: MasterDevice (finishing)
        input_ports:
        - X_WE_measured
        output_ports:
        - V_WE_command
        - p_WE_offset
        - p_M
        - r_M

    While finishing the hand does not turn (w = 0).
    """

    def __init__(
        self,
        motion: MasterMotion | None = None,
        mapping: IncrementalMapping | None = None,
        *,
        target_W=None,
        finish_gain: float = 2.0,
        finish_speed: float = 0.005,
    ):
        super().__init__()
        self._mapping = mapping or IncrementalMapping()
        self._default = _Playback.of(STILL if motion is None else motion, self._mapping)
        self._play = self.DeclareAbstractParameter(AbstractValue.Make(self._default))
        self._target = None
        if target_W is not None:
            target = np.asarray(target_W, dtype=float).reshape(-1)
            if target.shape != (3,) or not np.all(np.isfinite(target)):
                raise InputError("target_W", "expected 3 finite coordinates (m)")
            if not (finish_gain > 0 and finish_speed > 0):
                raise InputError("finish_gain/finish_speed", "expected positive values")
            self._target = target
            self._gain, self._speed = float(finish_gain), float(finish_speed)
            self._X_meas = self.DeclareAbstractInputPort(
                "X_WE_measured", AbstractValue.Make(RigidTransform())
            )
        self._V = self.DeclareVectorOutputPort("V_WE_command", 6, self._calc_velocity)
        self._offset = self.DeclareVectorOutputPort("p_WE_offset", 3, self._calc_offset)
        self._p = self.DeclareVectorOutputPort("p_M", 3, self._calc_handle)
        self._r = self.DeclareVectorOutputPort("r_M", 3, self._calc_turn)

    @property
    def motion(self) -> MasterMotion:
        """The motion of the default context."""
        return self._default.motion

    @property
    def duration(self) -> float:
        """Duration of the default context's motion (s)."""
        return self._default.motion.duration

    def set_motion(self, context, motion: MasterMotion | GlitchedMotion) -> None:
        """Replay ``motion`` in ``context`` (this system's context or a diagram's root one)."""
        own = self.GetMyMutableContextFromRoot(context)
        own.get_mutable_abstract_parameter(self._play).set_value(
            _Playback.of(motion, self._mapping))

    def motion_in(self, context) -> MasterMotion:
        """The motion ``context`` replays."""
        return self._playback(self.GetMyContextFromRoot(context)).motion

    def _playback(self, context) -> _Playback:
        return context.get_abstract_parameter(self._play).get_value()

    def _index(self, context, play: _Playback) -> int:
        k = int(np.floor(context.get_time() / play.motion.dt + 1e-9))
        return min(max(k, 0), play.motion.p_M.shape[0] - 1)

    def _calc_velocity(self, context, output: BasicVector):
        play = context.get_abstract_parameter(self._play).get_value()
        t = context.get_time()
        motion = play.motion
        if self._target is not None and t > motion.duration:
            out = np.zeros(6)
            v = self._gain * (self._target - self._X_meas.Eval(context).translation())
            norm = float(np.linalg.norm(v))
            out[3:] = v if norm <= self._speed else v * (self._speed / norm)
            output.set_value(out)
        else:  # _index, inline (w zero for a motion without r_M and no glitch)
            k = min(max(math.floor(t / motion.dt + 1e-9), 0), play.V_W.shape[0] - 1)
            output.set_value(play.V_W[k])

    def _calc_offset(self, context, output: BasicVector):
        play = self._playback(context)
        output.SetFromVector(play.d_W[self._index(context, play)])

    def _calc_handle(self, context, output: BasicVector):
        play = self._playback(context)
        output.SetFromVector(play.motion.p_M[self._index(context, play)])


    def _calc_turn(self, context, output: BasicVector):
        play = self._playback(context)
        r = play.motion.r_M
        output.SetFromVector(np.zeros(3) if r is None else r[self._index(context, play)])
