"""The safety spec: the clinical margin, the fixture's admissible region and the registration
error, one frozen object (DESIGN.md sections 4 and 7, "Margins" and "One safety spec").

A case's ``safety:`` section is read into a :class:`SafetySpec` (lengths in mm and angles in
degrees in the file, SI here) and passed whole down the planning chain: the placement verifies
its admissible region against its margin (systems.placement.planner.place_instrument) and the
registration Monte Carlo draws its errors (systems.placement.exact_clearance). Each default is
written once, in the field's spec: ``SafetySpec()`` equals the spec of an empty ``safety:``
section. New safety settings are new fields here, read by the same spec.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import partial

import numpy as np

from implantplan.systems import validate as v

MM = 1e-3
DEG = np.pi / 180.0


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
    """

    clearance_margin: float = v.spec(v.nonneg, 1.0, key="clearance_mm", scale=MM)
    lateral_tolerance: float = v.spec(v.nonneg, 0.5, key="lateral_tolerance_mm", scale=MM)
    angle_tolerance: float = v.spec(partial(v.number, low=0.0, high=10.0), 1.0,
                                    key="angle_tolerance_deg", scale=DEG)
    registration_sigma_translation: float = v.spec(v.nonneg, 0.5, key="registration_sigma_mm",
                                                   scale=MM)
    registration_sigma_rotation: float = v.spec(partial(v.number, low=0.0, high=10.0), 0.5,
                                                key="registration_sigma_deg", scale=DEG)
    registration_samples: int = v.spec(partial(v.integer, low=0), 1000)

    def __post_init__(self):
        # a spec built in code is held to what the file's checks allow (finite, >= 0)
        for f in fields(self):
            v.number(getattr(self, f.name), f"safety.{f.name}", nonneg=True,
                     integer=f.name == "registration_samples")

    @classmethod
    def from_yaml(cls, data, where: str = "safety") -> SafetySpec:
        """Parse a ``safety:`` mapping as written in a case file (mm, deg); errors name
        ``where.key``."""
        return v.parse(cls, data, where)
