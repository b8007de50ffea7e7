"""The contra-angle implanting actuator welded to the AUBO-i10 flange (seed 000 Sec. 4 and 5.2).

Geometry, in the flange frame F (wrist3_Link: origin at the flange face centre, +z out along J6):

- handle rod: a cylinder of radius ``rod_radius`` along +z from the flange face to the head;
- head: a cylinder of radius ``head_radius`` whose axis is the implant axis (F's y axis), centred
  on the rod axis at z = ``rod_length``;
- implant (with its drive shaft): a cylinder of radius ``implant_radius`` along -y from the head
  to the implant tip, at distance ``implant_length`` (d12) from the rod axis.

TCP frame ``tcp`` (DESIGN.md's End): at the head centre, where the rod axis (line1 of Eq. 19)
meets the implant axis, with the flange's orientation. So End z runs along the rod towards the
head and End y along the implant axis from the tip to the head, which is what seed 001 asks
(End Y along Oral Z, End X along -Oral Y): in seed 000's Tool frame (x along line1 away from the
head, z along the implant axis) the implant tip is T_ct [0, 0, -d12] and line2 runs through it
parallel to the rod, as Eq. 19 uses. The frame ``implant_tip`` sits at the tip.

The dimensions, X_FT and p_FTip are systems.actuator's (one definition for every layer; they are
re-exported here). X_FT = translation (0, 0, rod_length). Departure from the paper: the paper gives
no rod length; 0.16 m (a contra-angle handpiece with its motor) is our default, a parameter.
Masses: rod 0.35 kg (handle and motor), head 0.03 kg, implant 0.005 kg, lumped into one body
whose inertia is that of the rod as a solid cylinder plus the head and implant as point masses.
"""

from __future__ import annotations

import numpy as np

from implantplan.systems.actuator import (  # noqa: F401  (re-exported: one definition)
    HEAD_HEIGHT,
    HEAD_MASS,
    HEAD_RADIUS,
    IMPLANT_LENGTH,
    IMPLANT_MASS,
    IMPLANT_RADIUS,
    ROD_LENGTH,
    ROD_MASS,
    ROD_RADIUS,
    X_FT,
    p_FTip,
)
from implantplan.systems.actuator import check_positive as _check_positive
from implantplan.systems.errors import InputError


def _f(v) -> str:
    return repr(float(v))


def actuator_inertia(
    rod_radius: float = ROD_RADIUS,
    rod_length: float = ROD_LENGTH,
    implant_length: float = IMPLANT_LENGTH,
) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, centre of mass in F, 3x3 rotational inertia about the centre of mass, in F)."""
    m = np.array([ROD_MASS, HEAD_MASS, IMPLANT_MASS])
    p = np.array(
        [
            [0.0, 0.0, rod_length / 2.0],
            [0.0, 0.0, rod_length],
            [0.0, -implant_length / 2.0, rod_length],
        ]
    )
    mass = float(m.sum())
    com = (m[:, None] * p).sum(axis=0) / mass
    t = ROD_MASS * (3.0 * rod_radius**2 + rod_length**2) / 12.0
    I_rod = np.diag([t, t, ROD_MASS * rod_radius**2 / 2.0])
    inertia = I_rod.copy()
    # The rod's own spread about its centre, plus every part's mass moved to the common centre of
    # mass (parallel-axis theorem).
    for mi, pi in zip(m, p, strict=True):
        d = pi - com
        inertia += mi * (d @ d * np.eye(3) - np.outer(d, d))
    return mass, com, inertia


def actuator_urdf(
    rod_radius: float = ROD_RADIUS,
    implant_length: float = IMPLANT_LENGTH,
    *,
    rod_length: float = ROD_LENGTH,
    head_radius: float = HEAD_RADIUS,
    head_height: float = HEAD_HEIGHT,
    implant_radius: float = IMPLANT_RADIUS,
) -> str:
    """URDF text of the implanting actuator; weld its ``actuator_base`` link to the flange.

    Args:
        rod_radius: handle rod radius r in m (seed 000: 6 mm).
        implant_length: d12 in m, TCP (rod axis) to implant tip (seed 000: 31 mm).
        rod_length: flange face to the TCP along the flange z axis, m.
        head_radius, head_height: the contra-angle head cylinder (axis = implant axis), m.
        implant_radius: radius of the implant and drive shaft, m.

    Returns:
        The URDF as a string (links ``actuator_base``; frames ``tcp`` and ``implant_tip``).
    """
    _check_positive(
        rod_radius=rod_radius,
        implant_length=implant_length,
        rod_length=rod_length,
        head_radius=head_radius,
        head_height=head_height,
        implant_radius=implant_radius,
    )
    if implant_length <= head_height / 2.0:
        raise InputError("implant_length", "expected more than half the head height")
    if rod_length <= head_radius:
        raise InputError("rod_length", "expected more than the head radius")
    mass, com, inertia = actuator_inertia(rod_radius, rod_length, implant_length)
    L, d12 = rod_length, implant_length
    rod_len = L - head_radius / 2.0  # the rod ends inside the head
    shaft = d12 - head_height / 2.0  # implant + drive shaft below the head
    half_pi = "1.5707963267948966"
    parts = [
        (
            "rod",
            f'<cylinder radius="{rod_radius!r}" length="{rod_len!r}"/>',
            f"0 0 {rod_len / 2.0!r}",
            "0 0 0",
            "0.75 0.75 0.78 1",
        ),
        (
            "head",
            f'<cylinder radius="{head_radius!r}" length="{head_height!r}"/>',
            f"0 0 {L!r}",
            f"{half_pi} 0 0",
            "0.55 0.55 0.60 1",
        ),
        (
            "implant",
            f'<cylinder radius="{implant_radius!r}" length="{shaft!r}"/>',
            f"0 {-(head_height / 2.0 + shaft / 2.0)!r} {L!r}",
            f"{half_pi} 0 0",
            "0.85 0.70 0.30 1",
        ),
    ]
    out = [
        '<?xml version="1.0"?>',
        f"<!-- Contra-angle implanting actuator (diagrams/actuator_urdf.py): "
        f"rod r={rod_radius!r} m, "
        f"TCP at z={L!r} m on the flange axis, implant tip at d12={d12!r} m along -y. -->",
        '<robot name="implanting_actuator" xmlns:drake="http://drake.mit.edu">',
        '  <link name="actuator_base">',
        "    <inertial>",
        f'      <origin xyz="{_f(com[0])} {_f(com[1])} {_f(com[2])}" rpy="0 0 0"/>',
        f'      <mass value="{mass!r}"/>',
        f'      <inertia ixx="{_f(inertia[0, 0])}" ixy="{_f(inertia[0, 1])}" '
        f'ixz="{_f(inertia[0, 2])}" iyy="{_f(inertia[1, 1])}" iyz="{_f(inertia[1, 2])}" '
        f'izz="{_f(inertia[2, 2])}"/>',
        "    </inertial>",
    ]
    for name, geo, xyz, rpy, rgba in parts:
        out += [
            f'    <visual name="{name}_visual">',
            f'      <origin xyz="{xyz}" rpy="{rpy}"/>',
            f"      <geometry>{geo}</geometry>",
            f'      <material name="{name}_color"><color rgba="{rgba}"/></material>',
            "    </visual>",
            f'    <collision name="{name}_collision">',
            f'      <origin xyz="{xyz}" rpy="{rpy}"/>',
            f"      <geometry>{geo}</geometry>",
            "    </collision>",
        ]
    out += [
        "  </link>",
        f'  <frame name="tcp" link="actuator_base" xyz="0 0 {L!r}" rpy="0 0 0"/>',
        f'  <frame name="implant_tip" link="actuator_base" xyz="0 {-d12!r} {L!r}" rpy="0 0 0"/>',
        "</robot>",
    ]
    return "\n".join(out) + "\n"


def write_default(path=None) -> str:
    """Write the default actuator to ``models/tools/implanting_actuator.urdf``; return the path."""
    from implantplan.models import MODELS_DIR
    from implantplan.systems.files import write_text_atomic

    target = MODELS_DIR / "tools" / "implanting_actuator.urdf" if path is None else path
    write_text_atomic(target, actuator_urdf())
    return str(target)


if __name__ == "__main__":
    print(write_default())
