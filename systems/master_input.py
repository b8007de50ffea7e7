"""Live master input: a person's hand on the master device, read while the diagram runs.

The teleop diagram (diagrams.teleop) takes the operator's command as a handle *velocity* in the
master frame M (incremental mapping, systems.master_device). A live source answers one question,
"what is the handle velocity and which buttons are down at time t?" (:class:`MasterInput`); the
:class:`LiveMasterDevice` LeafSystem asks it once per control period and keeps the answers, so a
live run is recorded as the same uniformly sampled handle positions a scripted or recorded run
replays (``MasterMotion``, CSV ``t_s,x_m,y_m,z_m``): p_M[k+1] = p_M[k] + v_M[k] dt, and replaying
the recording gives the command v_M[k] on [k dt, (k+1) dt) again (the replay is the run).

Sources:

- :class:`KeyboardMaster`: keys (the studio binds them to Meshcat buttons with key codes) that
  move the handle along M's axes while pressed: a key press keeps its axis moving for ``hold``
  seconds (a held key repeats), at ``speed`` (m/s) stepped by the speed keys; pause stops it.
- A haptic stylus (e.g. 3D Systems Touch through OpenHaptics, ``pyopenhaptics``) plugs in as
  another :class:`MasterInput`: read the stylus's position in its own frame in ``sample`` (its
  servo loop runs at 1 kHz, we sample at the diagram's period), difference it into a velocity,
  and map the stylus's buttons to ``buttons``. Nothing else in the studio changes. Not shipped:
  there is no device here to test it on.

Orientation: the incremental mapping commands translation only (the fixture holds the axis; the
CSV has no orientation columns), so a live source gives no angular velocity either.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError
from implantplan.systems.master_device import IncrementalMapping, MasterMotion


@dataclass(frozen=True)
class MasterSample:
    """What the hand does at one instant: handle velocity (3,) in M (m/s) and buttons held."""

    v_M: np.ndarray
    buttons: frozenset = frozenset()


class MasterInput(Protocol):
    """A live master device: ``sample(t)`` is called once per control period with increasing
    simulated times t (s) and answers the handle velocity and buttons at t."""

    def sample(self, t: float) -> MasterSample: ...


# The keyboard's axes: feed along the fixture (M's +x is the feed direction the studio sets up
# with the mapping), lateral x/y across it.
KEY_AXES = {
    "feed_in": np.array([1.0, 0.0, 0.0]),
    "feed_out": np.array([-1.0, 0.0, 0.0]),
    "lateral_x+": np.array([0.0, 1.0, 0.0]),
    "lateral_x-": np.array([0.0, -1.0, 0.0]),
    "lateral_y+": np.array([0.0, 0.0, 1.0]),
    "lateral_y-": np.array([0.0, 0.0, -1.0]),
}


@dataclass
class KeyboardMaster:
    """Keys move the handle: :meth:`press` an axis key at simulated time t and the handle moves
    along it at the current speed until ``hold`` seconds after the last press (key repeat keeps
    a held key pressed). ``faster``/``slower`` scale the speed by 1.5 within
    [``min_speed``, ``max_speed``]; ``pause`` toggles a stop of every motion.

    Attributes:
        speed: handle speed (m/s), 5 mm/s by default (seed 001's feeds run at ~10 mm/s).
        hold: how long one key press keeps its axis moving (s); a browser's key repeat is ~30 Hz
            after ~0.5 s, so 0.6 s bridges the first repeat.
    """

    speed: float = 0.005
    hold: float = 0.6
    min_speed: float = 0.0005
    max_speed: float = 0.02
    paused: bool = False
    _until: dict = field(default_factory=dict)  # key -> time its motion stops (s)

    def press(self, key: str, t: float) -> None:
        """A key press at simulated time ``t`` (an axis in :data:`KEY_AXES`, ``faster``,
        ``slower`` or ``pause``)."""
        if key in KEY_AXES:
            self._until[key] = float(t) + self.hold
        elif key == "faster":
            self.speed = min(self.speed * 1.5, self.max_speed)
        elif key == "slower":
            self.speed = max(self.speed / 1.5, self.min_speed)
        elif key == "pause":
            self.paused = not self.paused
            self._until.clear()
        else:
            raise InputError("key", f"expected one of {sorted(KEY_AXES)} or faster/slower/pause, "
                             f"got {key!r}")

    def release(self) -> None:
        """Every axis stops now."""
        self._until.clear()

    def sample(self, t: float) -> MasterSample:
        held = [k for k, until in self._until.items() if t < until]
        if self.paused or not held:
            return MasterSample(np.zeros(3), frozenset(held))
        v = np.sum([KEY_AXES[k] for k in held], axis=0)
        n = float(np.linalg.norm(v))
        return MasterSample(v * (self.speed / n) if n > 0 else v, frozenset(held))


class LiveMasterDevice(LeafSystem):
    """A live master input as the operator's commanded tool motion, recorded as it goes.

    .. pydrake_system::

        name: LiveMasterDevice
        output_ports:
        - V_WE_command
        - p_M

    ``V_WE_command`` (6): [0; scale R_WM v_M[k]] in World on [k dt, (k+1) dt), with v_M[k] the
    source's answer at t = k dt, asked the first time sample k is needed and kept (a re-evaluated
    output, or a second context, sees the same command). ``p_M`` (3): the integrated handle
    position p_M[k]. The ports match systems.master_device.MasterDevice, so diagrams.teleop
    wires either.

    The recording (:meth:`recording`) lives in this system, not in a context: one live run per
    system.
    """

    def __init__(self, source: MasterInput, mapping: IncrementalMapping | None = None, *,
                 dt: float = 0.005):
        super().__init__()
        if not np.isfinite(dt) or dt <= 0:
            raise InputError("dt", f"expected a sample period > 0 s, got {dt}")
        self.source = source
        self._mapping = mapping or IncrementalMapping()
        self.dt = float(dt)
        self._v: list[np.ndarray] = []
        self._p: list[np.ndarray] = [np.zeros(3)]
        self._V = self.DeclareVectorOutputPort("V_WE_command", 6, self._calc_velocity)
        self._pM = self.DeclareVectorOutputPort("p_M", 3, self._calc_handle)

    def _sample(self, t: float) -> int:
        k = max(int(np.floor(t / self.dt + 1e-9)), 0)
        while len(self._v) <= k:
            s = self.source.sample(len(self._v) * self.dt)
            v = np.asarray(s.v_M, dtype=float).reshape(3)
            if not np.all(np.isfinite(v)):
                raise InputError("master input", f"expected a finite handle velocity, got {v}")
            self._v.append(v)
            self._p.append(self._p[-1] + v * self.dt)
        return k

    def _calc_velocity(self, context, output: BasicVector):
        k = self._sample(context.get_time())
        out = np.zeros(6)
        out[3:] = self._mapping.to_world(self._v[k])
        output.SetFromVector(out)

    def _calc_handle(self, context, output: BasicVector):
        output.SetFromVector(self._p[self._sample(context.get_time())])

    def recording(self, t_end: float) -> MasterMotion:
        """The handle positions p_M[0..n] of a run simulated to ``t_end`` = n dt: replayed by
        MasterDevice for n dt seconds it gives the same commands v_M[0..n-1]."""
        n = max(int(round(t_end / self.dt)), 1)
        self._sample(n * self.dt)
        return MasterMotion(dt=self.dt, p_M=np.array(self._p[: n + 1]))
