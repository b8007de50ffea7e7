"""Live master input: a person's hand on the master device, read while the diagram runs.

The teleop diagram (diagrams.teleop) takes the operator's command as a handle *velocity* in the
master frame M (incremental mapping, systems.teleop.master_device). A live source answers one
question,
"what are the handle's velocity and angular velocity and which buttons are down at time t?"
(:class:`MasterInput`); the :class:`LiveMasterDevice` LeafSystem asks it once per control period
and keeps the answers, so a live run is recorded as the same uniformly sampled handle positions
and angle integrals a scripted or recorded run replays (``MasterMotion``, CSV
``t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad``): p_M[k+1] = p_M[k] + v_M[k] dt, r_M[k+1] = r_M[k] +
w_M[k] dt, and replaying the recording gives the command (v_M[k], w_M[k]) on [k dt, (k+1) dt)
again (the replay is the run).

Sources:

- :class:`KeyboardMaster`: keys (the studio binds them to Meshcat buttons with key codes) that
  move the handle along M's axes or turn it about them while pressed: a key press keeps its axis
  moving for ``hold`` seconds (a held key repeats), at ``speed`` (m/s) and ``rate`` (rad/s)
  stepped by the speed keys; pause stops it.
- :class:`SliderMaster`: Meshcat sliders set the handle's velocity (feed, lateral x/y, in mm/s)
  and its roll rate about the feed axis (deg/s); zero in the middle of each slider, a slider at
  zero is no motion.
- A haptic stylus (e.g. 3D Systems Touch through OpenHaptics, ``pyopenhaptics``) plugs in as
  another :class:`MasterInput`: read the stylus's position in its own frame in ``sample`` (its
  servo loop runs at 1 kHz, we sample at the diagram's period), difference it into a velocity,
  and map the stylus's buttons to ``buttons``. Nothing else in the studio changes. Not shipped:
  there is no device here to test it on.

M's axes in the studio (analyses.live_setup.feed_mapping): +x along the feed (into the mouth,
the fixture's axis), y and z across it ("lateral x" and "lateral y"). A roll is a turn about +x
(the rod's axis: the contra-angle's implant axis, perpendicular to the rod, swings about it), a
tilt a turn about y or z; all about the tool's TCP. The fixture bounds the tool's orientation,
roll and tilt alike, to beta (0.5 deg) of the planned Tool frame (systems.placement.fixture: the
geodesic angle to ``R_ref``), so with the fixture on these keys turn the tool by at most beta.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError
from implantplan.systems.teleop.master_device import IncrementalMapping, MasterMotion


@dataclass(frozen=True)
class MasterSample:
    """What the hand does at one instant: handle velocity (3,) in M (m/s), buttons held, and
    the handle's angular velocity (3,) in M (rad/s; zero by default)."""

    v_M: np.ndarray
    buttons: frozenset = frozenset()
    w_M: np.ndarray = field(default_factory=lambda: np.zeros(3))


class MasterInput(Protocol):
    """A live master device: ``sample(t)`` is called once per control period with increasing
    simulated times t (s) and answers the handle velocity, angular velocity and buttons at t."""

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
# ... and its turns (about the TCP): roll about the feed axis (M's x), tilt about the lateral axes.
KEY_ROTATIONS = {
    "roll+": np.array([1.0, 0.0, 0.0]),
    "roll-": np.array([-1.0, 0.0, 0.0]),
    "tilt_x+": np.array([0.0, 1.0, 0.0]),
    "tilt_x-": np.array([0.0, -1.0, 0.0]),
    "tilt_y+": np.array([0.0, 0.0, 1.0]),
    "tilt_y-": np.array([0.0, 0.0, -1.0]),
}


def _along(axes: dict, held: list, size: float) -> np.ndarray:
    """The held keys' axes summed and scaled to ``size`` (zero when none or they cancel)."""
    keys = [k for k in held if k in axes]
    if not keys:
        return np.zeros(3)
    v = np.sum([axes[k] for k in keys], axis=0)
    n = float(np.linalg.norm(v))
    return v * (size / n) if n > 0 else v


@dataclass
class KeyboardMaster:
    """Keys move the handle: :meth:`press` an axis key (:data:`KEY_AXES`) or a turn key
    (:data:`KEY_ROTATIONS`) at simulated time t and the handle moves along it at the current
    speed (turns about it at the current rate) until ``hold`` seconds after the last press (key
    repeat keeps a held key pressed). ``faster``/``slower`` scale the speed and the rate by 1.5
    within [``min_speed``, ``max_speed``] and [``min_rate``, ``max_rate``]; ``pause`` toggles a
    stop of every motion.

    Attributes:
        speed: handle speed (m/s), 5 mm/s by default (seed 001's feeds run at ~10 mm/s).
        rate: handle turning rate (rad/s), 5 deg/s by default.
        hold: how long one key press keeps its axis moving (s); a browser's key repeat is ~30 Hz
            after ~0.5 s, so 0.6 s bridges the first repeat.
    """

    speed: float = 0.005
    hold: float = 0.6
    min_speed: float = 0.0005
    max_speed: float = 0.02
    paused: bool = False
    rate: float = float(np.deg2rad(5.0))
    min_rate: float = float(np.deg2rad(0.5))
    max_rate: float = float(np.deg2rad(30.0))
    _until: dict = field(default_factory=dict)  # key -> time its motion stops (s)

    def press(self, key: str, t: float) -> None:
        """A key press at simulated time ``t`` (an axis in :data:`KEY_AXES` or
        :data:`KEY_ROTATIONS`, ``faster``, ``slower`` or ``pause``)."""
        if key in KEY_AXES or key in KEY_ROTATIONS:
            self._until[key] = float(t) + self.hold
        elif key == "faster":
            self.speed = min(self.speed * 1.5, self.max_speed)
            self.rate = min(self.rate * 1.5, self.max_rate)
        elif key == "slower":
            self.speed = max(self.speed / 1.5, self.min_speed)
            self.rate = max(self.rate / 1.5, self.min_rate)
        elif key == "pause":
            self.paused = not self.paused
            self._until.clear()
        else:
            raise InputError("key", f"expected one of {sorted(KEY_AXES | KEY_ROTATIONS)} or "
                             f"faster/slower/pause, got {key!r}")

    def release(self) -> None:
        """Every axis stops now."""
        self._until.clear()

    def sample(self, t: float) -> MasterSample:
        held = [k for k, until in self._until.items() if t < until]
        if self.paused or not held:
            return MasterSample(np.zeros(3), frozenset(held))
        return MasterSample(_along(KEY_AXES, held, self.speed), frozenset(held),
                            _along(KEY_ROTATIONS, held, self.rate))


# The slider master's sliders: name -> (Meshcat label, half range, step, SI factor, M axis,
# True for a turn). Zero in the middle; mm/s and deg/s on the page, SI in the sample.
SLIDERS = {
    "feed": ("feed (mm/s)", 20.0, 0.5, 1e-3, 0, False),
    "lateral_x": ("lateral x (mm/s)", 10.0, 0.5, 1e-3, 1, False),
    "lateral_y": ("lateral y (mm/s)", 10.0, 0.5, 1e-3, 2, False),
    "roll": ("roll (deg/s)", 30.0, 1.0, float(np.deg2rad(1.0)), 0, True),
}


class SliderMaster:
    """Meshcat sliders as the master handle: each slider sets a velocity along (or a turning
    rate about) one of M's axes (:data:`SLIDERS`: feed +-20 mm/s, lateral x/y +-10 mm/s, roll
    about the feed axis +-30 deg/s), read at every sample; a slider at 0 is no motion there.

    Args:
        meshcat: the pydrake.geometry.Meshcat the sliders live on. Meshcat answers only on the
            thread that made it: call every method there (the studio steps the diagram on it);
            other threads read :attr:`last`.
        add: add the sliders now (at 0); :meth:`remove` takes them away again.
    """

    def __init__(self, meshcat, *, add: bool = True):
        self.meshcat = meshcat
        self.last = {name: 0.0 for name in SLIDERS}  # the values last read (mm/s, deg/s)
        if add:
            self.add()

    def add(self) -> None:
        """The sliders, at zero (a slider already there keeps its value)."""
        have = set(self.meshcat.GetSliderNames())
        for label, half, step, _, _, _ in SLIDERS.values():
            if label not in have:
                self.meshcat.AddSlider(label, -half, half, step, 0.0)

    def remove(self) -> None:
        for label, *_ in SLIDERS.values():
            if label in self.meshcat.GetSliderNames():
                self.meshcat.DeleteSlider(label)

    def stop(self) -> None:
        """Every slider back to zero (the studio's pause key with sliders)."""
        for label, *_ in SLIDERS.values():
            self.meshcat.SetSliderValue(label, 0.0)
        self.last = {name: 0.0 for name in SLIDERS}

    def values(self) -> dict:
        """The sliders' values as shown (mm/s, deg/s) by action name."""
        self.last = {name: float(self.meshcat.GetSliderValue(label))
                     for name, (label, *_) in SLIDERS.items()}
        return dict(self.last)

    def sample(self, t: float) -> MasterSample:
        v, w = np.zeros(3), np.zeros(3)
        for name, value in self.values().items():
            _, _, _, si, axis, turn = SLIDERS[name]
            (w if turn else v)[axis] += si * value
        return MasterSample(v, frozenset(), w)


class LiveMasterDevice(LeafSystem):
    """A live master input as the operator's commanded tool motion, recorded as it goes.

    .. pydrake_system::

        name: LiveMasterDevice
        output_ports:
        - V_WE_command
        - p_M
        - r_M

    ``V_WE_command`` (6): [R_WM w_M[k]; scale R_WM v_M[k]] in World on [k dt, (k+1) dt), with
    (v_M[k], w_M[k]) the source's answer at t = k dt, asked the first time sample k is needed
    and kept (a re-evaluated output, or a second context, sees the same command). ``p_M`` (3):
    the integrated handle position p_M[k]; ``r_M`` (3): the integrated angular velocity r_M[k].
    The ports match systems.teleop.master_device.MasterDevice, so diagrams.teleop wires either.
    A non-finite sample (a driver glitch) goes out as a NaN command, which the CommandLimiter
    after the master turns into a logged fault (hold); it is counted in ``non_finite_samples``
    and left out of the handle's integral (the recording stays finite).

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
        self._w: list[np.ndarray] = []
        self._p: list[np.ndarray] = [np.zeros(3)]
        self._r: list[np.ndarray] = [np.zeros(3)]
        self.non_finite_samples = 0  # samples the source gave as NaN/inf (faults downstream)
        self._V = self.DeclareVectorOutputPort("V_WE_command", 6, self._calc_velocity)
        self._pM = self.DeclareVectorOutputPort("p_M", 3, self._calc_handle)
        self._rM = self.DeclareVectorOutputPort("r_M", 3, self._calc_turn)

    def _sample(self, t: float) -> int:
        k = max(int(np.floor(t / self.dt + 1e-9)), 0)
        while len(self._v) <= k:
            s = self.source.sample(len(self._v) * self.dt)
            v = np.asarray(s.v_M, dtype=float).reshape(3)
            w = np.asarray(s.w_M, dtype=float).reshape(3)
            if not (np.all(np.isfinite(v)) and np.all(np.isfinite(w))):
                # a driver glitch: the command goes out as it came (the CommandLimiter after
                # the master faults on it, holds and logs); the handle's integral skips it
                self.non_finite_samples += 1
                self._v.append(v)
                self._w.append(w)
                self._p.append(self._p[-1].copy())
                self._r.append(self._r[-1].copy())
                continue
            self._v.append(v)
            self._w.append(w)
            self._p.append(self._p[-1] + v * self.dt)
            self._r.append(self._r[-1] + w * self.dt)
        return k

    def _calc_velocity(self, context, output: BasicVector):
        k = self._sample(context.get_time())
        if not (np.isfinite(self._v[k]).all() and np.isfinite(self._w[k]).all()):
            output.SetFromVector(np.full(6, np.nan))  # a glitch: the limiter faults on it
            return
        out = np.zeros(6)
        out[:3] = self._mapping.angular_to_world(self._w[k])
        out[3:] = self._mapping.to_world(self._v[k])
        output.SetFromVector(out)

    def _calc_handle(self, context, output: BasicVector):
        output.SetFromVector(self._p[self._sample(context.get_time())])

    def _calc_turn(self, context, output: BasicVector):
        output.SetFromVector(self._r[self._sample(context.get_time())])

    def recording(self, t_end: float) -> MasterMotion:
        """The handle positions p_M[0..n] and angle integrals r_M[0..n] of a run simulated to
        ``t_end`` = n dt: replayed by MasterDevice for n dt seconds it gives the same commands
        (v_M, w_M)[0..n-1]."""
        n = max(int(round(t_end / self.dt)), 1)
        self._sample(n * self.dt)
        return MasterMotion(dt=self.dt, p_M=np.array(self._p[: n + 1]),
                            r_M=np.array(self._r[: n + 1]))
