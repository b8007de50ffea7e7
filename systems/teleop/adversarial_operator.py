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
  Uhlenbeck, RMS ~15 mm/s, capped at 50 mm/s) for the whole feed.

Directions come from the case: ``u_in`` (into the mouth along the rod), Center x (the patient's
left) and Center y (up), given in World.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from implantplan.systems.errors import InputError
from implantplan.systems.teleop.master_device import MasterMotion, Operator, scripted_feed

KINDS = ("bursts", "cheek_left", "cheek_right", "jaw", "drift", "random_walk")
PUSH_SPEED = 0.040  # m/s, the push towards a cheek and into the jaw


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


def adversarial_motion(kind: str, start, target, dirs: Directions, *, seed=0,
                       dt: float = 0.005) -> MasterMotion:
    """One seeded motion of ``kind`` (one of :data:`KINDS`) from the tool's start position to
    the feeding target (World, m)."""
    if kind not in KINDS:
        raise InputError("kind", f"expected one of {', '.join(KINDS)}, got {kind!r}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
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
