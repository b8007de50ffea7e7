"""Adversarial operator motions: what a careless or startled hand does on the master.

The scripted operator of systems.teleop.master_device is calm (10 mm/s, sub-millimetre jitter).
These
are the commands the safety layer (fixture + supervisor + estimator) must survive, as master
handle motions (:class:`~implantplan.systems.teleop.master_device.MasterMotion`, identity mapping by
default), each seeded:

- ``bursts``: the calm feed plus 2-5 bursts of 0.1-0.3 s at 2-5x the feed speed in random
  directions (the displacement stays: incremental mapping);
- ``cheek_left`` / ``cheek_right``: feed in to a random depth, then push towards a cheek
  (Center +x, the patient's left, or -x) at 40 mm/s for 1-1.5 s;
- ``jaw``: the same push into the lower jaw (Center -y);
- ``drift``: the calm feed with a slow sideways drift of 1-3 mm/s in a random lateral direction,
  all the way (10-30 mm by the end);
- ``random_walk``: the calm feed plus a seeded random walk of the hand's velocity (Ornstein-
  Uhlenbeck, RMS ~15 mm/s, capped at 50 mm/s) for the whole feed;
- ``tremor``: the calm feed with a 2 mm (amplitude) tremor at 8-10 Hz across it (~110 mm/s at
  its peak: the command limits clip it, the fixture must hold it within 0.5 mm);
- ``pulse``: the calm feed with 1-3 twitches across it: the hand goes 2-5 mm sideways in 20-50 ms
  and comes back as fast;
- ``jump``: a device glitch: at a random time in the mouth (40-90% of the stroke) the handle's
  reported position jumps by 50-1000 mm (log-uniform) in one sample along one of the
  :func:`jump_directions` and stays there (the feed goes on from the new position);
  ``spike``: the same jump for one sample only (out and back);
- ``speed_1e9``, ``turn_1e9``, ``nan``, ``inf``: a device reporting an absurd twist for 1-5
  samples mid-feed (:class:`~implantplan.systems.teleop.master_device.GlitchedMotion`): 1e9 m/s
  along a random direction, 1e9 rad/s about one, NaN or +-inf in one component.

The jumps and the absurd twists are what the command limits (systems.teleop.command_limits) must
turn into faults: held, latched and logged, never a motion. :func:`handle_jump` makes one jump
of a given size and direction (the studies sweep them all: :data:`JUMP_SIZES` x
:func:`jump_directions`).

Directions come from the case: ``u_in`` (into the mouth along the rod), Center x (the patient's
left) and Center y (up), given in World.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from implantplan.systems.errors import InputError
from implantplan.systems.teleop.master_device import (
    GlitchedMotion,
    MasterMotion,
    Operator,
    scripted_feed,
)

MOTION_KINDS = ("bursts", "cheek_left", "cheek_right", "jaw", "drift", "random_walk", "tremor",
                "pulse")
JUMP_KINDS = ("jump", "spike")
ABSURD_KINDS = ("speed_1e9", "turn_1e9", "nan", "inf")
KINDS = MOTION_KINDS + JUMP_KINDS + ABSURD_KINDS
PUSH_SPEED = 0.040  # m/s, the push towards a cheek and into the jaw
TREMOR = 0.002  # m, the tremor kind's amplitude
JUMP_SIZES = (0.05, 0.1, 0.2, 0.5, 1.0)  # m, the handle jumps the studies sweep
ABSURD = 1e9  # m/s or rad/s


@dataclass(frozen=True)
class Directions:
    """World directions of a case (unit vectors).

    Attributes:
        u_in: into the mouth along the planned rod (minus Tool x).
        left: the patient's left (Center +x).
        up: towards the upper jaw (Center +y).
    """

    u_in: np.ndarray
    left: np.ndarray
    up: np.ndarray

    @classmethod
    def of_case(cls, X_WTarget, X_WCenter) -> Directions:
        X_T, X_C = np.asarray(X_WTarget, dtype=float), np.asarray(X_WCenter, dtype=float)
        return cls(u_in=-X_T[:3, 0], left=X_C[:3, 0], up=X_C[:3, 1])


def jump_directions(dirs: Directions) -> tuple[np.ndarray, list[str]]:
    """(14, 3) unit directions in World and their names: Center's six axis directions (+-x the
    patient's left/right, +-y up/down, +-z out of/into the mouth) and the eight diagonals
    (+-x +-y +-z) / sqrt(3)."""
    out_ = np.cross(dirs.left, dirs.up)  # Center z: out of the mouth
    E = np.stack([dirs.left, dirs.up, out_])
    signs, names = [], []
    for i, axis in enumerate("xyz"):
        for sign in (1, -1):
            e = np.zeros(3)
            e[i] = sign
            signs.append(e)
            names.append(f"{'+-'[sign < 0]}{axis}")
    for sx in (1, -1):
        for sy in (1, -1):
            for sz in (1, -1):
                signs.append(np.array([sx, sy, sz]) / np.sqrt(3.0))
                names.append("".join(f"{'+-'[sg < 0]}{a}"
                                     for sg, a in zip((sx, sy, sz), "xyz", strict=True)))
    return np.array(signs) @ E, names


def _motion(d_W: np.ndarray, dt: float) -> MasterMotion:
    """A slave displacement path (n, 3) from the start as a master motion (identity mapping)."""
    return MasterMotion(dt=dt, p_M=d_W - d_W[0])


def _feed(start, target, rng, dt, operator=None) -> np.ndarray:
    """The calm scripted feed as a displacement path (n, 3) from the start."""
    m = scripted_feed(start, target, seed=rng, operator=operator, dt=dt)
    return m.p_M - m.p_M[0]


def bursts(start, target, rng, dt=0.005, *, feed_speed=0.010) -> MasterMotion:
    d = _feed(start, target, rng, dt, Operator(speed=feed_speed))
    v = np.diff(d, axis=0, prepend=d[:1]) / dt
    n = d.shape[0]
    for _ in range(int(rng.integers(2, 6))):
        k0 = int(rng.integers(0, max(n - 1, 1)))
        k1 = min(n, k0 + int(round(rng.uniform(0.1, 0.3) / dt)))
        u = rng.standard_normal(3)
        v[k0:k1] += rng.uniform(2.0, 5.0) * feed_speed * u / np.linalg.norm(u)
    return _motion(np.cumsum(v, axis=0) * dt, dt)


def push(start, target, rng, direction, dt=0.005, *, speed=PUSH_SPEED) -> MasterMotion:
    """Feed in to a random depth (40-100% of the way) at the calm speed, then push along
    ``direction`` (World, unit) at ``speed`` for 1-1.5 s, then hold still for 0.5 s."""
    target = np.asarray(target, dtype=float)
    start = np.asarray(start, dtype=float)
    depth = rng.uniform(0.4, 1.0)
    d_in = _feed(start, start + depth * (target - start), rng, dt)
    T = rng.uniform(1.0, 1.5)
    s = np.arange(1, int(round(T / dt)) + 1) * dt * speed
    d_push = d_in[-1] + s[:, None] * np.asarray(direction, dtype=float)
    hold = np.repeat(d_push[-1:], int(round(0.5 / dt)), axis=0)
    return _motion(np.concatenate([d_in, d_push, hold]), dt)


def drift(start, target, rng, dirs: Directions, dt=0.005) -> MasterMotion:
    d = _feed(start, target, rng, dt)
    a = rng.uniform(0.0, 2.0 * np.pi)
    lateral = np.cos(a) * dirs.left + np.sin(a) * dirs.up
    t = np.arange(d.shape[0]) * dt
    return _motion(d + rng.uniform(0.001, 0.003) * t[:, None] * lateral, dt)


def random_walk(start, target, rng, dt=0.005, *, rms=0.015, cap=0.050, tau=0.3) -> MasterMotion:
    d = _feed(start, target, rng, dt)
    n = d.shape[0]
    a = np.exp(-dt / tau)
    kick = rms * np.sqrt(1.0 - a * a) * rng.standard_normal((n, 3))
    v = np.zeros((n, 3))
    for k in range(1, n):  # Ornstein-Uhlenbeck velocity, sequential by nature
        v[k] = a * v[k - 1] + kick[k]
    speed = np.linalg.norm(v, axis=1, keepdims=True)
    v *= np.minimum(1.0, cap / np.maximum(speed, 1e-12))
    return _motion(d + np.cumsum(v, axis=0) * dt, dt)


def tremor(start, target, rng, dt=0.005, *, amplitude=TREMOR) -> MasterMotion:
    return MasterMotion(dt=dt, p_M=_feed(start, target, rng, dt, Operator(tremor=amplitude)))


def pulse(start, target, rng, dirs: Directions, dt=0.005) -> MasterMotion:
    """The calm feed with 1-3 twitches across it: 2-5 mm out in 20-50 ms and back as fast."""
    d = _feed(start, target, rng, dt)
    n = d.shape[0]
    for _ in range(int(rng.integers(1, 4))):
        a = rng.uniform(0.0, 2.0 * np.pi)
        lateral = np.cos(a) * dirs.left + np.sin(a) * dirs.up
        m = max(int(round(rng.uniform(0.02, 0.05) / dt)), 1)
        k0 = int(rng.integers(int(0.2 * n), max(int(0.8 * n) - 2 * m, int(0.2 * n) + 1)))
        bump = np.concatenate([np.arange(1, m + 1), np.arange(m - 1, -1, -1)]) / m
        d[k0:k0 + bump.size] += rng.uniform(0.002, 0.005) * bump[:, None] * lateral
    return _motion(d, dt)


def _stroke_sample(m: MasterMotion, rng) -> int:
    """A sample at 40-90% of a scripted feed's stroke (its last 0.5 s are the settle)."""
    n_stroke = max(m.p_M.shape[0] - int(round(0.5 / m.dt)), 2)
    return int(rng.integers(int(0.4 * n_stroke), max(int(0.9 * n_stroke), int(0.4 * n_stroke) + 1)))


def handle_jump(start, target, rng, direction, size, dt=0.005, *, back=False) -> MasterMotion:
    """The calm feed with a one-sample jump of the handle's reported position by ``size`` (m)
    along ``direction`` (World, unit) at 40-90% of the stroke; it stays (``back=False``: the
    rest of the feed goes on from there) or comes back at the next sample (``back``)."""
    d = _feed(start, target, rng, dt)
    m = MasterMotion(dt=dt, p_M=d)
    k = _stroke_sample(m, rng)
    offset = float(size) * np.asarray(direction, dtype=float)
    if back:
        d[k] += offset
    else:
        d[k:] += offset
    return MasterMotion(dt=dt, p_M=d)


def absurd_command(start, target, rng, kind: str, dt=0.005) -> GlitchedMotion:
    """The calm feed with the device reporting an absurd twist (``kind`` in
    :data:`ABSURD_KINDS`) for 1-5 samples at 40-90% of the stroke."""
    m = MasterMotion(dt=dt, p_M=_feed(start, target, rng, dt))
    k = _stroke_sample(m, rng)
    samples = np.arange(k, min(k + int(rng.integers(1, 6)), m.p_M.shape[0]))
    u = rng.standard_normal(3)
    u /= np.linalg.norm(u)
    V = np.zeros(6)
    if kind == "speed_1e9":
        V[3:] = ABSURD * u
    elif kind == "turn_1e9":
        V[:3] = ABSURD * u
    else:
        V[3 + int(rng.integers(0, 3))] = np.nan if kind == "nan" else rng.choice([1, -1]) * np.inf
    return GlitchedMotion(motion=m, samples=samples, V_W=np.repeat(V[None], samples.size, 0))


def adversarial_motion(kind: str, start, target, dirs: Directions, *, seed=0,
                       dt: float = 0.005) -> MasterMotion | GlitchedMotion:
    """One seeded motion of ``kind`` (one of :data:`KINDS`) from the tool's start position to
    the feeding target (World, m)."""
    if kind not in KINDS:
        raise InputError("kind", f"expected one of {', '.join(KINDS)}, got {kind!r}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    if kind in JUMP_KINDS:
        D, _ = jump_directions(dirs)
        size = float(np.exp(rng.uniform(np.log(JUMP_SIZES[0]), np.log(JUMP_SIZES[-1]))))
        return handle_jump(start, target, rng, D[int(rng.integers(0, len(D)))], size, dt,
                           back=kind == "spike")
    if kind in ABSURD_KINDS:
        return absurd_command(start, target, rng, kind, dt)
    if kind == "tremor":
        return tremor(start, target, rng, dt)
    if kind == "pulse":
        return pulse(start, target, rng, dirs, dt)
    if kind == "bursts":
        return bursts(start, target, rng, dt)
    if kind == "cheek_left":
        return push(start, target, rng, dirs.left, dt)
    if kind == "cheek_right":
        return push(start, target, rng, -dirs.left, dt)
    if kind == "jaw":
        return push(start, target, rng, -dirs.up, dt)
    if kind == "drift":
        return drift(start, target, rng, dirs, dt)
    return random_walk(start, target, rng, dt)
