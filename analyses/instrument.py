"""``implantplan instrument place``: the feeding target and virtual fixture of one implant site
(seed 000 stage 2, systems.placement.planner), written as a placement JSON, with the paper's plots.

    implantplan instrument place --fpsm fpsm.json --hole-mm X Y Z --hole-axis DX DY DZ \\
        --rod-radius-mm 6 --implant-length-mm 31 [--objective eq14|eq21|eq22] [--seed S] \\
        [--plots DIR] --out placement.json

The hole and its axis are given in the FPSM's Center frame (mm; the axis from the bone into the
cavity). The JSON holds d_T (m), theta_T (rad), f_safe of both lines, F_safe, validity, the PSO
run (iterations, evaluations, seconds, history), X_CT (the feeding target in Center), the grid
check and the virtual fixture. Exit 3 (planning failure) when a line is unsafe at the optimum;
the JSON is written first. Plots (``--plots``): contour of F_safe over (d_T, theta_T), global and
magnified around the optimum (the paper's Fig. 18a-c), PSO convergence (Fig. 18d), and XY / YZ /
XZ / isometric views of the FPSM slices, rod, implant, implant-tip path and VF (Fig. 17), with
the oral mesh when the FPSM's settings name a mesh file that exists.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from implantplan.analyses.figures.placement import plot_placement
from implantplan.analyses.progress import Progress
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.files import write_json
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import wrap_angle
from implantplan.systems.placement.planner import Placement, default_bounds, place_instrument
from implantplan.systems.safety import SafetySpec

MM = 1e-3


POINT, DIRECTION = ("X", "Y", "Z"), ("DX", "DY", "DZ")  # metavars of 3-vector options


def register(subparsers) -> None:
    inst = subparsers.add_parser("instrument", help="instrument placement (feeding target + VF)")
    sub = inst.add_subparsers(dest="instrument_command", required=True, metavar="SUBCOMMAND")
    p = sub.add_parser("place", help="place the feeding target by PSO (seed 000, stage 2)")
    p.add_argument("--fpsm", type=Path, required=True, help="FPSM JSON (implantplan fpsm ...)")
    p.add_argument("--hole-mm", nargs=3, type=float, required=True, metavar=POINT,
                   help="implant site in Center (mm)")
    p.add_argument("--hole-axis", nargs=3, type=float, required=True, metavar=DIRECTION,
                   help="hole axis in Center, from the bone into the cavity")
    p.add_argument("--rod-radius-mm", type=float, required=True, help="handle rod radius r (mm)")
    p.add_argument("--implant-length-mm", type=float, required=True, help="implant length d12")
    p.add_argument("--objective", choices=("eq14", "eq21", "eq22"), default="eq14",
                   help="Eq. 14 signed square roots (default), Eq. 21 linear, Eq. 22 squares")
    p.add_argument("--seed", type=int, default=0, help="PSO seed")
    p.add_argument(
        "--d-t-range-mm",
        nargs=2,
        type=float,
        default=None,
        metavar=("MIN", "MAX"),
        help="bounds on d_T (mm); default d12 .. d12 + 2 max(rho)",
    )
    p.add_argument(
        "--theta-range-deg",
        nargs=2,
        type=float,
        default=(-180.0, 180.0),
        metavar=("MIN", "MAX"),
        help="bounds on theta_T (deg)",
    )
    p.add_argument(
        "--hole-tolerance-mm",
        type=float,
        default=5.0,
        help="how far the site may lie outside the FPSM (mm); it sits on the jaw surface",
    )
    p.add_argument("--particles", type=int, default=30, help="PSO swarm size")
    p.add_argument("--clearance-margin-mm", type=float, default=1.0,
                   help="clinical margin: a placement whose verified tool clearance is below "
                        "it is a planning failure (exit 3)")
    p.add_argument("--lateral-tolerance-mm", type=float, default=0.5,
                   help="the fixture's lateral tolerance of the tool axis, verified")
    p.add_argument("--angle-tolerance-deg", type=float, default=1.0,
                   help="the fixture's angular tolerance of the tool, verified")
    p.add_argument(
        "--restarts",
        type=int,
        default=3,
        help="further PSO runs while the optimum collides (0 = the paper's single run)",
    )
    p.add_argument("--plots", type=Path, default=None, metavar="DIR", help="write plots here")
    p.add_argument("--out", type=Path, required=True, help="placement JSON to write")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=_place)


def _finite(values, field: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise InputError(field, f"expected finite numbers, got {arr.tolist()}")
    return arr


def _place(args: argparse.Namespace) -> int:
    progress = Progress("instrument place", quiet=args.quiet)
    hole = _finite(args.hole_mm, "--hole-mm") * MM
    axis = _finite(args.hole_axis, "--hole-axis")
    rod = float(_finite(args.rod_radius_mm, "--rod-radius-mm")) * MM
    d12 = float(_finite(args.implant_length_mm, "--implant-length-mm")) * MM
    if rod < 0:
        raise InputError("--rod-radius-mm", "expected a radius >= 0 mm")
    if d12 <= 0:
        raise InputError("--implant-length-mm", "expected a length > 0 mm")
    tol = float(_finite(args.hole_tolerance_mm, "--hole-tolerance-mm")) * MM
    if tol < 0:
        raise InputError("--hole-tolerance-mm", "expected a tolerance >= 0 mm")
    if args.particles < 1:
        raise InputError("--particles", "expected at least 1 particle")
    if args.restarts < 0:
        raise InputError("--restarts", "expected 0 or more")
    limits = {}
    for flag, value in (("--clearance-margin-mm", args.clearance_margin_mm),
                        ("--lateral-tolerance-mm", args.lateral_tolerance_mm),
                        ("--angle-tolerance-deg", args.angle_tolerance_deg)):
        limits[flag] = float(_finite(value, flag))
        if limits[flag] < 0:
            raise InputError(flag, f"expected a value >= 0, got {value!r}")
    safety = SafetySpec(clearance_margin=limits["--clearance-margin-mm"] * MM,
                        lateral_tolerance=limits["--lateral-tolerance-mm"] * MM,
                        angle_tolerance=np.radians(limits["--angle-tolerance-deg"]))
    fpsm = Fpsm.load(args.fpsm, field="--fpsm")
    bounds = default_bounds(fpsm, d12)
    if args.d_t_range_mm is not None:
        bounds[:, 0] = _finite(args.d_t_range_mm, "--d-t-range-mm") * MM
    bounds[:, 1] = np.deg2rad(_finite(args.theta_range_deg, "--theta-range-deg"))
    for col, name in ((0, "--d-t-range-mm"), (1, "--theta-range-deg")):
        if bounds[1, col] < bounds[0, col]:
            raise InputError(name, "expected MIN <= MAX")
    progress.say(
        f"FPSM {fpsm.slices} slices x {fpsm.control_points} control points; objective "
        f"{args.objective}, seed {args.seed}"
    )
    placement = place_instrument(
        fpsm,
        hole,
        axis,
        rod_radius=rod,
        implant_length=d12,
        objective=args.objective,
        bounds=bounds,
        seed=args.seed,
        particles=args.particles,
        hole_tolerance=tol,
        restarts=args.restarts,
        safety=safety,
    )
    progress.say(
        f"PSO {placement.iterations} iterations, {placement.evaluations} evaluations, "
        f"{placement.seconds * 1e3:.1f} ms"
    )
    data = placement.to_dict()
    data["inputs"] = {
        "fpsm": str(args.fpsm),
        "hole_Center_m": hole,
        "hole_axis_Center": axis / np.linalg.norm(axis),
    }
    data["summary"] = summary_row(placement)
    write_json(args.out, data, kind="placement")
    print(summary_table(placement))
    progress.say(f"wrote {args.out}")
    if args.plots is not None:
        paths = plot_placement(fpsm, placement, args.plots)
        progress.say("plots: " + ", ".join(str(p) for p in paths))
    if not placement.valid:
        raise PlanningFailure(placement.reason, result=data)
    return 0


def summary_row(p: Placement) -> dict:
    g = p.grid or {}
    return {
        "d_T_mm": p.d_T / MM,
        "theta_T_deg": np.rad2deg(p.theta_T),
        "f_safe_line1_mm": p.f_safe_line1 / MM,
        "f_safe_line2_mm": p.f_safe_line2 / MM,
        "F_safe": p.F_safe,
        "valid": p.valid,
        "iterations": p.iterations,
        "evaluations": p.evaluations,
        "pso_ms": p.seconds * 1e3,
        "grid_d_T_mm": g.get("d_T", np.nan) / MM,
        "grid_theta_T_deg": np.rad2deg(g.get("theta_T", np.nan)),
        "pso_minus_grid_d_T_mm": (p.d_T - g.get("d_T", np.nan)) / MM,
        "pso_minus_grid_theta_T_deg": np.rad2deg(
            wrap_angle(p.theta_T - g.get("theta_T", np.nan))
        ),
    }


def summary_table(p: Placement) -> str:
    row = summary_row(p)
    width = max(len(k) for k in row)
    lines = [f"{'quantity':<{width}}  value"]
    for k, v in row.items():
        text = str(v) if isinstance(v, (bool, np.bool_)) else f"{v:.6g}"
        lines.append(f"{k:<{width}}  {text}")
    if not p.valid:
        lines.append(f"{'reason':<{width}}  {p.reason}")
    return "\n".join(lines)


# -- plots -------------------------------------------------------------------------------------


