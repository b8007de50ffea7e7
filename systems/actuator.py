"""The contra-angle implanting actuator: its dimensions and frames, the one definition every
layer uses (seed 000 Sec. 4 and 5.2; DESIGN.md section 2, "one actuator definition").

Frames, in the flange frame F (wrist3_Link: origin at the flange face centre, +z out along J6):

- ``tcp`` (DESIGN.md's End, seed 000's line1/line2 crossing): at the head centre, on the rod axis
  at z = ``rod_length``, with the flange's orientation: X_FT = translation (0, 0, rod_length).
- ``implant_tip``: at distance ``implant_length`` (d12) from the TCP along -y (the implant axis is
  F's y axis): p_FTip = (0, -implant_length, rod_length).
- the mapped frame A of the capability maps (seed 004): at the implant tip, z along the drilling
  direction (F's -y), x = F's x: X_FA = (R_x(pi/2), p_FTip).

Departure from the paper: it gives no rod length; 0.16 m (a contra-angle handpiece with its
motor) is our default, a parameter. diagrams/actuator_urdf.py turns these numbers into the URDF.
"""

from __future__ import annotations

import numpy as np

from implantplan.systems.errors import InputError
from implantplan.systems.frames import rot_x, transform

ROD_RADIUS = 0.006  # m, seed 000 Sec. 5.2
IMPLANT_LENGTH = 0.031  # m, d12 in seed 000 Sec. 5.2
ROD_LENGTH = 0.16  # m, flange face to the TCP (our choice, see module docstring)
HEAD_RADIUS = 0.008  # m
HEAD_HEIGHT = 0.014  # m, along the implant axis
IMPLANT_RADIUS = 0.002  # m
ROD_MASS, HEAD_MASS, IMPLANT_MASS = 0.35, 0.03, 0.005  # kg


def check_positive(**values: float) -> None:
    """Every named length is a finite number > 0 (m), else an InputError naming it."""
    for name, v in values.items():
        if not (np.isfinite(v) and v > 0):
            raise InputError(name, f"expected a positive length in m, got {v!r}")


def X_FT(rod_length: float = ROD_LENGTH) -> np.ndarray:
    """Pose of the TCP frame in the flange frame (4x4): translation (0, 0, rod_length)."""
    check_positive(rod_length=rod_length)
    return transform(np.eye(3), [0.0, 0.0, rod_length])


def p_FTip(rod_length: float = ROD_LENGTH, implant_length: float = IMPLANT_LENGTH) -> np.ndarray:
    """Position of the implant tip in the flange frame: (0, -implant_length, rod_length)."""
    check_positive(rod_length=rod_length, implant_length=implant_length)
    return np.array([0.0, -implant_length, rod_length])


def actuator_map_frame(rod_length: float = ROD_LENGTH,
                       implant_length: float = IMPLANT_LENGTH) -> np.ndarray:
    """X_FA: the implant tip of the actuator, z = drilling direction (flange -y), x = flange x.

    The actuator is a contra-angle piece: its implant axis is the TCP's y axis, perpendicular to
    the flange z, so roll about the approach axis is not free for this frame (capability maps
    sample it).
    """
    return transform(rot_x(np.pi / 2), p_FTip(rod_length, implant_length))
