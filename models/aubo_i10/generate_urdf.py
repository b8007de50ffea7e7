"""Write ``aubo_i10.urdf`` (joint limits +-175 deg) and ``aubo_i10_360.urdf`` (+-360 deg).

Run ``python models/aubo_i10/generate_urdf.py`` after editing; the committed URDF files are what
Drake loads, and ``tests/test_models.py`` checks both are what this script writes and that they
differ only in the position limits.

Everything comes from DESIGN.md section 8 (AUBO's public description package): link and joint
names, joint origins (exact pi), masses, velocity limits and collision primitives. Inertias are
solid-cylinder approximations of each link's main body (see ``LINKS``); effort limits are the
AUBO-i10 rated joint torques class (207 N m for joints 1-3, 34 N m for joints 4-6), which only
matter for simulation, not for planning.
"""

from __future__ import annotations

import math
from pathlib import Path

HERE = Path(__file__).resolve().parent
PI = "3.141592653589793"
HALF_PI = "1.5707963267948966"

# name, parent, child, xyz, rpy, velocity limit (deg/s, written in rad/s), effort limit (N m)
JOINTS = [
    ("shoulder_joint", "base_link", "shoulder_Link", "0 0 0.1632", f"0 0 {PI}", 180, 207),
    (
        "upperArm_joint",
        "shoulder_Link",
        "upperArm_Link",
        "0 0.2013 0",
        f"-{HALF_PI} -{HALF_PI} 0",
        180,
        207,
    ),
    ("foreArm_joint", "upperArm_Link", "foreArm_Link", "0.647 0 0", f"{PI} 0 0", 147, 207),
    ("wrist1_joint", "foreArm_Link", "wrist1_Link", "0.6005 0 0", f"{PI} 0 {HALF_PI}", 180, 34),
    ("wrist2_joint", "wrist1_Link", "wrist2_Link", "0 0.1025 0", f"-{HALF_PI} 0 0", 180, 34),
    ("wrist3_joint", "wrist2_Link", "wrist3_Link", "0 -0.094 0", f"{HALF_PI} 0 0", 180, 34),
]

# Inertia model per link: a solid cylinder (radius r, length L) with its axis along "x" or "z"
# of the link frame, centred at com. I_axial = m r^2 / 2, I_transverse = m (3 r^2 + L^2) / 12.
# mass (kg), com (m), cylinder radius, length, axis
LINKS = {
    "base_link": (2.592, (0.0, 0.0, 0.031), 0.109, 0.062, "z"),
    "shoulder_Link": (10.180, (0.0, 0.0, 0.0), 0.076, 0.202, "z"),
    "upperArm_Link": (18.096, (0.3235, 0.0, 0.0), 0.058, 0.647, "x"),
    "foreArm_Link": (4.448, (0.30025, 0.0, 0.128), 0.044, 0.6005, "x"),
    "wrist1_Link": (1.792, (0.0, 0.0, -0.02), 0.045, 0.10, "z"),
    "wrist2_Link": (1.628, (0.0, -0.003, 0.005), 0.045, 0.10, "z"),
    "wrist3_Link": (0.198, (0.0, 0.0, -0.0155), 0.0375, 0.031, "z"),
}

# Collision (and visual) primitives in link frames, DESIGN.md section 8.
# ("cylinder", radius, length, xyz, rpy) | ("capsule", radius, length, xyz, rpy)
# | ("box", "sx sy sz", xyz, rpy). Cylinders and capsules run along z of their origin frame.
GEOMETRY = {
    "base_link": [("cylinder", 0.109, 0.062, "0 0 0.031", "0 0 0")],
    "shoulder_Link": [("cylinder", 0.076, 0.202, "0 0 0", "0 0 0")],
    "upperArm_Link": [
        # J2 housing about the joint axis, then the arm tube from J2 to J3.
        ("cylinder", 0.076, 0.14, "0 0 0", "0 0 0"),
        ("capsule", 0.058, 0.647, "0.3235 0 0", f"0 {HALF_PI} 0"),
    ],
    "foreArm_Link": [
        # J3 housing at z 0.064..0.19, then the tube from J3 to J4 at z 0.128.
        ("cylinder", 0.058, 0.126, "0 0 0.127", "0 0 0"),
        ("capsule", 0.044, 0.6005, "0.30025 0 0.128", f"0 {HALF_PI} 0"),
    ],
    "wrist1_Link": [("box", "0.08 0.12 0.10", "0 0 -0.02", "0 0 0")],
    "wrist2_Link": [("box", "0.08 0.12 0.10", "0 -0.003 0.005", "0 0 0")],
    "wrist3_Link": [("cylinder", 0.0375, 0.031, "0 0 -0.0155", "0 0 0")],
}

COLORS = {
    "base_link": ("grey", "0.35 0.35 0.38 1"),
    "shoulder_Link": ("white", "0.92 0.92 0.92 1"),
    "upperArm_Link": ("white", "0.92 0.92 0.92 1"),
    "foreArm_Link": ("white", "0.92 0.92 0.92 1"),
    "wrist1_Link": ("blue", "0.20 0.45 0.80 1"),
    "wrist2_Link": ("white", "0.92 0.92 0.92 1"),
    "wrist3_Link": ("grey", "0.35 0.35 0.38 1"),
}

LIMITS_DEG = {"175": 175.0, "360": 360.0}


def _geometry_xml(item) -> str:
    kind = item[0]
    if kind == "cylinder":
        return f'<cylinder radius="{item[1]}" length="{item[2]}"/>'
    if kind == "capsule":
        return f'<drake:capsule radius="{item[1]}" length="{item[2]}"/>'
    if kind == "box":
        return f'<box size="{item[1]}"/>'
    raise ValueError(f"unknown primitive {kind!r}")


def _origin(item) -> str:
    xyz, rpy = item[-2], item[-1]
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def cylinder_inertia(mass: float, radius: float, length: float, axis: str) -> tuple:
    """(ixx, iyy, izz) of a solid cylinder about its centre, axis along "x" or "z"."""
    axial = mass * radius**2 / 2.0
    transverse = mass * (3.0 * radius**2 + length**2) / 12.0
    if axis == "z":
        return transverse, transverse, axial
    if axis == "x":
        return axial, transverse, transverse
    raise ValueError(axis)


def _fmt(v: float) -> str:
    return repr(round(v, 12))


def urdf(limits: str = "175") -> str:
    """URDF text of the AUBO-i10 with +-175 deg or +-360 deg position limits."""
    lim = math.radians(LIMITS_DEG[limits])
    out = [
        '<?xml version="1.0"?>',
        "<!-- GENERATED by models/aubo_i10/generate_urdf.py from DESIGN.md section 8; "
        "do not edit by hand. -->",
        "<!-- AUBO-i10. Position limits: aubo_i10.urdf +-175 deg, aubo_i10_360.urdf +-360 deg; "
        "the two files differ only there. Inertias: solid cylinders about each link's main "
        "body (generate_urdf.LINKS). -->",
        '<robot name="aubo_i10" xmlns:drake="http://drake.mit.edu">',
    ]
    for link, (mass, com, r, length, axis) in LINKS.items():
        ixx, iyy, izz = cylinder_inertia(mass, r, length, axis)
        cname, rgba = COLORS[link]
        out.append(f'  <link name="{link}">')
        out.append("    <inertial>")
        out.append(f'      <origin xyz="{com[0]} {com[1]} {com[2]}" rpy="0 0 0"/>')
        out.append(f'      <mass value="{mass}"/>')
        out.append(
            f'      <inertia ixx="{_fmt(ixx)}" ixy="0" ixz="0" iyy="{_fmt(iyy)}" iyz="0" '
            f'izz="{_fmt(izz)}"/>'
        )
        out.append("    </inertial>")
        for i, item in enumerate(GEOMETRY[link]):
            geo = _geometry_xml(item)
            out.append(f'    <visual name="{link}_visual_{i}">')
            out.append(f"      {_origin(item)}")
            out.append(f"      <geometry>{geo}</geometry>")
            out.append(f'      <material name="{cname}"><color rgba="{rgba}"/></material>')
            out.append("    </visual>")
            out.append(f'    <collision name="{link}_collision_{i}">')
            out.append(f"      {_origin(item)}")
            out.append(f"      <geometry>{geo}</geometry>")
            out.append("    </collision>")
        out.append("  </link>")
    for name, parent, child, xyz, rpy, vel_deg, effort in JOINTS:
        vel = math.radians(vel_deg)
        out.append(f'  <joint name="{name}" type="revolute">')
        out.append(f'    <parent link="{parent}"/>')
        out.append(f'    <child link="{child}"/>')
        out.append(f'    <origin xyz="{xyz}" rpy="{rpy}"/>')
        out.append('    <axis xyz="0 0 1"/>')
        out.append(
            f'    <limit lower="{-lim!r}" upper="{lim!r}" velocity="{vel!r}" effort="{effort}"/>'
        )
        out.append("  </joint>")
    for name, *_ in JOINTS:
        motor = name.replace("_joint", "_motor")
        out.append(f'  <transmission name="{name}_trans">')
        out.append("    <type>transmission_interface/SimpleTransmission</type>")
        out.append(f'    <joint name="{name}">')
        out.append(
            "      <hardwareInterface>hardware_interface/EffortJointInterface</hardwareInterface>"
        )
        out.append("    </joint>")
        out.append(f'    <actuator name="{motor}">')
        out.append("      <mechanicalReduction>1</mechanicalReduction>")
        out.append("    </actuator>")
        out.append("  </transmission>")
    # Adjacent links touch at their joint housings by design: filter each parent/child pair.
    # (MultibodyPlant filters parent/child pairs too; the groups make it explicit for any tool.)
    for name, parent, child, *_ in JOINTS:
        group = name.replace("_joint", "_adjacent")
        out.append(f'  <drake:collision_filter_group name="{group}">')
        out.append(f'    <drake:member link="{parent}"/>')
        out.append(f'    <drake:member link="{child}"/>')
        out.append(f'    <drake:ignored_collision_filter_group name="{group}"/>')
        out.append("  </drake:collision_filter_group>")
    out.append("</robot>")
    return "\n".join(out) + "\n"


def path_for(limits: str) -> Path:
    return HERE / ("aubo_i10.urdf" if limits == "175" else "aubo_i10_360.urdf")


def main() -> None:
    for limits in LIMITS_DEG:
        path_for(limits).write_text(urdf(limits))
        print(f"wrote {path_for(limits)}")


if __name__ == "__main__":
    main()
