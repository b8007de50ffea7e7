"""The safety spec: the clinical margin, the fixture's admissible region, the registration
error, the alarm, the barrier and the command limits, one frozen object (DESIGN.md sections 4 and
7, "Margins" and "One safety spec").

A case's ``safety:`` section is read into a :class:`SafetySpec` (lengths in mm and angles in
degrees in the file, SI here) and passed whole down the planning chain and into the feeding
diagram: the placement verifies the fixture's admissible region against the margin
(systems.placement.planner.place_instrument) and builds the fixture with the same tolerances, the
registration Monte Carlo draws its errors (systems.placement.exact_clearance), the supervisor's
barrier keeps the margin at the spec's rate (systems.teleop.supervisor.Barrier.from_spec), the
estimator raises its alarm at the alarm margin and the command limiter enforces the command
limits (diagrams.teleop.build_teleop reads ``TeleopCase.safety``). plan.json writes the spec
once (``safety``, SI: :meth:`SafetySpec.to_dict`) and the studio and ``simulate`` read it back
(:meth:`SafetySpec.from_dict`), so what the plan verified is what the diagram executes.

Each default is written once, in the field's spec: ``SafetySpec()`` equals the spec of an empty
``safety:`` section, and the teleop systems' defaults are read from :data:`DEFAULT`. New safety
settings are new fields here, read by the same spec.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from functools import partial

import numpy as np

from implantplan.systems import validate as v
from implantplan.systems.errors import InputError

MM = 1e-3
DEG = np.pi / 180.0
_positive = partial(v.number, positive=True)
MAX_REGISTRATION_SAMPLES = 100_000  # registration Monte Carlo draws (docs/formats.md, Bounds)


def _mm_upto(high: float):
    """A length in mm, >= 0 and at most ``high`` (a physical range: more is a typo)."""
    return partial(v.number, nonneg=True, high=high)


@dataclass(frozen=True)
class CommandLimits:
    """The limits on the operator's tool twist before the virtual fixture (SI units; the
    limiter and its rule are systems.teleop.command_limits). Case file: ``safety.command_limits``
    with the keys below (mm/s, deg/s, mm, deg, s).

    Attributes:
        linear_speed: the TCP's speed limit (m/s): faster commands are clipped to it.
        angular_speed: the tool's angular speed limit (rad/s): faster commands are clipped.
        fault_jump: a command that moves the TCP more than this in one control period is a
            fault (m).
        fault_turn: a command that turns the tool more than this in one control period is a
            fault (rad).
        clear_after: a fault clears once the command has been within the speed limits for
            this long without interruption (s).

    The defaults (one each) and where they come from:

    - ``linear_speed`` 0.05 m/s: 5x the calm feed of seed 001's experiments (10 mm/s, the scripted
      operator's), 2.5x the studio's fastest key and slider (20 mm/s); and the fastest speed whose
      half-step, with the rotation's, keeps the swept bound above under 0.2 mm at 200 Hz;
    - ``angular_speed`` 6 deg/s (0.105 rad/s): the studio's default turning rate is 5 deg/s, the
      fixture bounds the orientation to 0.5-1 deg of the plan anyway, and the rod's far end (0.17 m
      from the TCP) then moves at most 18 mm/s;
    - ``fault_jump`` 5 mm per control period (1 m/s at 200 Hz): 20x the clipped step (0.25 mm) and
      100x the calm feed's; no hand on a stylus in the mouth moves 5 mm in 5 ms, and the smallest
      device jump the studies inject (50 mm) is 10x it;
    - ``fault_turn`` 3 deg per control period (600 deg/s at 200 Hz): 100x the angular limit;
    - ``clear_after`` 0.2 s: a glitching device's burst of bad samples stays one fault instead of
      letting single samples through between them, and the hold is short next to the operator's own
      reaction time.
    """

    linear_speed: float = v.spec(_positive, 50.0, key="linear_speed_mm_s", scale=MM)
    angular_speed: float = v.spec(_positive, 6.0, key="angular_speed_deg_s",
                                  scale=DEG)
    fault_jump: float = v.spec(_positive, 5.0, key="fault_jump_mm", scale=MM)
    fault_turn: float = v.spec(_positive, 3.0, key="fault_turn_deg", scale=DEG)
    clear_after: float = v.spec(_positive, 0.2, key="clear_after_s")

    def __post_init__(self):
        for f in fields(self):
            object.__setattr__(self, f.name, v.number(getattr(self, f.name),
                                                      f"command_limits.{f.name}", positive=True))

    def check_period(self, dt: float) -> float:
        """The control period ``dt`` (s) these limits run at, checked: a clipped command must
        not be a fault (linear_speed dt < fault_jump, angular_speed dt < fault_turn)."""
        dt = v.number(dt, "period", positive=True)
        if not (self.linear_speed * dt < self.fault_jump
                and self.angular_speed * dt < self.fault_turn):
            raise InputError("command_limits", f"expected the fault thresholds above one period "
                             f"({dt} s) at the speed limits")
        return dt

    def clear_samples(self, dt: float) -> int:
        """n_clear: consecutive clean samples that clear a fault at the period ``dt``."""
        return max(int(math.ceil(self.clear_after / dt - 1e-9)), 1)

    def step_path(self, reach: float, dt: float) -> float:
        """S (m): the longest path of a tool point within ``reach`` (m) of the TCP in one
        control period ``dt`` (s) at the limits (systems.teleop.command_limits); the clearance
        between two consecutive desired poses is at least the smaller of theirs minus S / 2."""
        return (self.linear_speed + float(reach) * self.angular_speed) * float(dt)

    def to_dict(self) -> dict:
        """The case-file form (mm/s, deg/s, mm, deg, s)."""
        return {f.metadata["key"]: getattr(self, f.name) / (f.metadata["scale"] or 1.0)
                for f in fields(self)}

    @classmethod
    def from_dict(cls, data, where: str = "command_limits") -> CommandLimits:
        """Read the case-file form; missing keys take the defaults, unknown keys are errors."""
        return v.parse(cls, data, where)


@dataclass(frozen=True)
class SafetySpec:
    """The safety settings of a plan (SI units).

    Attributes:
        clearance_margin: m; every clearance check keeps it (a minimum): a placement whose
            verified tool clearance is below it is invalid.
        lateral_tolerance: m; delta, how far the tool axis may leave line1 inside the mouth
            (the fixture's admissible region, verified whole).
        angle_tolerance: rad; beta, how far the tool's orientation may turn in that region.
        registration_sigma_translation: m; standard deviation per axis of the Center frame's
            registration error in the Monte Carlo.
        registration_sigma_rotation: rad; the same for its rotation vector.
        registration_samples: draws of the Monte Carlo (0 = off).
        alarm_margin: m; the FPSM estimator's alarm fires when the instrument's estimated
            clearance (min d_safe) falls below it (systems.teleop.fpsm_estimator).
        barrier_rate: 1/s; alpha of the supervisor's barrier: an approach to the margin slower
            than alpha (h - margin) passes (systems.teleop.supervisor).
        command_limits: the operator's command limits before the fixture (:class:`CommandLimits`).
    """

    clearance_margin: float = v.spec(_mm_upto(20.0), 1.0, key="clearance_mm", scale=MM)
    lateral_tolerance: float = v.spec(_mm_upto(10.0), 0.5, key="lateral_tolerance_mm", scale=MM)
    angle_tolerance: float = v.spec(partial(v.number, low=0.0, high=10.0), 1.0,
                                    key="angle_tolerance_deg", scale=DEG)
    registration_sigma_translation: float = v.spec(_mm_upto(10.0), 0.5,
                                                   key="registration_sigma_mm", scale=MM)
    registration_sigma_rotation: float = v.spec(partial(v.number, low=0.0, high=10.0), 0.5,
                                                key="registration_sigma_deg", scale=DEG)
    registration_samples: int = v.spec(partial(v.integer, low=0, high=MAX_REGISTRATION_SAMPLES),
                                       1000)
    alarm_margin: float = v.spec(_mm_upto(20.0), 1.0, key="alarm_margin_mm", scale=MM)
    barrier_rate: float = v.spec(partial(v.number, positive=True, high=1000.0), 20.0,
                                 key="barrier_rate_per_s")
    command_limits: CommandLimits = v.spec(v.section(CommandLimits), {})

    def __post_init__(self):
        # a spec built in code is held to what the file's checks allow (finite, >= 0)
        for f in fields(self):
            if f.name == "command_limits":
                if not isinstance(self.command_limits, CommandLimits):
                    raise InputError("safety.command_limits", "expected a CommandLimits, got "
                                     f"{type(self.command_limits).__name__}")
                continue
            v.number(getattr(self, f.name), f"safety.{f.name}", nonneg=True,
                     positive=f.name == "barrier_rate",
                     integer=f.name == "registration_samples")

    def to_dict(self) -> dict:
        """The spec as plan.json writes it (SI; :meth:`from_dict` reads it back)."""
        out = asdict(self)
        out["units"] = {"lengths": "m", "angles": "rad", "speeds": "m/s, rad/s",
                        "barrier_rate": "1/s", "clear_after": "s"}
        return out

    @classmethod
    def from_dict(cls, data, where: str = "plan.safety") -> SafetySpec:
        """Read :meth:`to_dict`'s form (SI); errors name ``where.key``."""
        d = dict(v.mapping(data, where))
        d.pop("units", None)
        names = tuple(f.name for f in fields(cls))
        v.unknown_keys(d, names, f"{where}.")
        cl = d.pop("command_limits", None) or {}
        v.unknown_keys(v.mapping(cl, f"{where}.command_limits"),
                       tuple(f.name for f in fields(CommandLimits)), f"{where}.command_limits.")
        try:
            return cls(**d, command_limits=CommandLimits(**cl))
        except TypeError as e:  # a value of the wrong kind
            raise InputError(where, "expected a safety spec as plan.json writes it "
                             f"({e})") from None

    @classmethod
    def from_yaml(cls, data, where: str = "safety") -> SafetySpec:
        """Parse a ``safety:`` mapping as written in a case file (mm, deg); errors name
        ``where.key``."""
        return v.parse(cls, data, where)


DEFAULT = SafetySpec()  # the defaults every safety setting's user reads (one default each)
