"""``implantplan instrument place``: the feeding target and virtual fixture of one implant site
(seed 000 stage 2, systems.placement), written as a placement JSON, with the paper's plots.

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

from implantplan.analyses.progress import Progress
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.files import write_json
from implantplan.systems.fpsm import Fpsm
from implantplan.systems.frames import invert
from implantplan.systems.placement import Placement, default_bounds, place_instrument

MM = 1e-3


def register(subparsers) -> None:
    inst = subparsers.add_parser("instrument", help="instrument placement (feeding target + VF)")
    sub = inst.add_subparsers(dest="instrument_command", required=True, metavar="SUBCOMMAND")
    p = sub.add_parser("place", help="place the feeding target by PSO (seed 000, stage 2)")
    p.add_argument("--fpsm", type=Path, required=True, help="FPSM JSON (implantplan fpsm ...)")
    p.add_argument(
        "--hole-mm",
        nargs=3,
        type=float,
        required=True,
        metavar=("X", "Y", "Z"),
        help="implant site in Center (mm)",
    )
    p.add_argument(
        "--hole-axis",
        nargs=3,
        type=float,
        required=True,
        metavar=("DX", "DY", "DZ"),
        help="hole axis in Center, from the bone into the cavity",
    )
    p.add_argument("--rod-radius-mm", type=float, required=True, help="handle rod radius r (mm)")
    p.add_argument("--implant-length-mm", type=float, required=True, help="implant length d12")
    p.add_argument("--objective", choices=("eq14", "eq21", "eq22"), default="eq14")
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
            np.angle(np.exp(1j * (p.theta_T - g.get("theta_T", np.nan))))
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


def _mesh_in_center(fpsm: Fpsm):
    """Vertices and faces of the FPSM's mesh in Center (m), or None when it is not available.

    The FPSM records the mesh path but (so far) not the file's units: ``settings["mesh_units"]``
    is used when present, else mm (scans); if the mesh then lands at a scale 30x off the model's
    own size, the other unit is tried, and the mesh is left out when neither fits."""
    source = fpsm.settings.get("mesh")
    if not source or not Path(str(source)).is_file():
        return None
    from implantplan.systems.oral_mesh import load_oral_mesh

    first = fpsm.settings.get("mesh_units", "mm")
    size = max(float(np.max(np.abs(fpsm.rho))), fpsm.z_range[1] - fpsm.z_range[0])
    X_CW = invert(fpsm.X_WC)
    for units in (first, "m" if first == "mm" else "mm"):
        try:
            mesh = load_oral_mesh(source, units=units)
        except InputError:
            return None
        v = mesh.vertices @ X_CW[:3, :3].T + X_CW[:3, 3]
        ratio = float(np.median(np.linalg.norm(v, axis=1))) / size
        if 1 / 30 < ratio < 30:
            return v, np.asarray(mesh.faces)
    return None


def _slice_curves(fpsm: Fpsm, samples: int = 180) -> np.ndarray:
    """(M, samples + 1, 3) closed slice curves in Center (m)."""
    th = np.linspace(0, 2 * np.pi, samples + 1)
    r = fpsm.radius_at(th[None, :], fpsm.slice_z[:, None])
    z = np.broadcast_to(fpsm.slice_z[:, None], r.shape)
    return np.stack([r * np.cos(th), r * np.sin(th), z], axis=-1)


def _vf_outline(vf, extra: float = 0.0) -> list[np.ndarray]:
    """Generator lines of the VF surface (m) in four meridian half-planes."""
    s, r = vf.profile()
    e1 = np.cross(vf.direction, [1.0, 0, 0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(vf.direction, [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(vf.direction, e1)
    out = []
    for a in np.linspace(0, 2 * np.pi, 4, endpoint=False):
        e = np.cos(a) * e1 + np.sin(a) * e2
        out.append(vf.origin + s[:, None] * vf.direction + r[:, None] * e)
    return out


def plot_placement(fpsm: Fpsm, p: Placement, out_dir) -> list[Path]:
    """Contour (global + magnified), convergence and 2D/3D views; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    mm = 1e3

    if p.grid is not None:
        for key, name, title in (
            ("coarse", "contour_global.png", "F_safe over the whole search box"),
            ("fine", "contour_magnified.png", "F_safe near the optimum"),
        ):
            g = p.grid[key]
            F = g.F
            hi = np.percentile(F, 90) if key == "coarse" else F.max()
            fig, ax = plt.subplots(figsize=(6.5, 4.8))
            cs = ax.contourf(
                np.rad2deg(g.theta_T),
                g.d_T * mm,
                np.clip(F, None, hi),
                levels=40,
                cmap="viridis_r",
            )
            fig.colorbar(cs, ax=ax, label=f"F_safe ({p.objective})")
            ax.plot(np.rad2deg(p.theta_T), p.d_T * mm, "r*", ms=12, label="PSO")
            ax.plot(
                np.rad2deg(p.grid["theta_T"]), p.grid["d_T"] * mm, "wx", ms=9, label="grid best"
            )
            ax.set_xlabel("theta_T (deg)")
            ax.set_ylabel("d_T (mm)")
            ax.set_title(title)
            ax.legend(loc="best", fontsize=8)
            fig.tight_layout()
            fig.savefig(out_dir / name, dpi=110)
            plt.close(fig)
            paths.append(out_dir / name)

    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(np.arange(p.history.size), p.history, "-o", ms=2)
    ax.set_xlabel("PSO iteration")
    ax.set_ylabel(f"global best F_safe ({p.objective})")
    ax.set_title(f"convergence: {p.iterations} iterations, stop: {p.stopped}")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_dir / "convergence.png", dpi=110)
    plt.close(fig)
    paths.append(out_dir / "convergence.png")

    # Scene in Center (mm).
    curves = _slice_curves(fpsm) * mm
    z_top = fpsm.z_range[1]
    D = np.asarray(p.line1["direction"])
    reach = (z_top - np.asarray(p.line1["start"])[2]) / D[2] if D[2] > 1e-9 else 0.05
    reach = max(reach, 0.0) + 0.03
    rod = np.array([p.line1["start"], np.asarray(p.line1["start"]) + reach * D]) * mm
    tip = np.array([p.line2["start"], np.asarray(p.line2["start"]) + reach * D]) * mm
    tool = p.X_CT[:3, 3]
    implant = np.array([tool, tool - p.implant_length * p.X_CT[:3, 2]]) * mm
    hole = p.X_CH[:3, 3] * mm
    vf_lines = [ln * mm for ln in _vf_outline(p.vf)] if p.vf is not None else []
    mesh = _mesh_in_center(fpsm)

    fig = plt.figure(figsize=(11, 10))
    views = (("XY", 0, 1), ("YZ", 1, 2), ("XZ", 0, 2))
    for k, (name, a, b) in enumerate(views):
        ax = fig.add_subplot(2, 2, k + 1)
        if mesh is not None:
            v = mesh[0] * mm
            step = max(1, v.shape[0] // 20000)
            ax.plot(v[::step, a], v[::step, b], ",", color="0.75", label="mesh")
        for c in curves:
            ax.plot(c[:, a], c[:, b], color="tab:blue", lw=0.6, alpha=0.7)
        for ln in vf_lines:
            ax.plot(ln[:, a], ln[:, b], color="tab:green", lw=1.0)
        ax.plot(rod[:, a], rod[:, b], color="tab:red", lw=2.5, label="rod (line1)")
        ax.plot(tip[:, a], tip[:, b], "--", color="tab:orange", lw=1.2, label="tip path (line2)")
        ax.plot(implant[:, a], implant[:, b], color="k", lw=3, label="implant")
        ax.plot(hole[a], hole[b], "ko", ms=5, label="hole")
        ax.set_xlabel(f"{name[0]} (mm)")
        ax.set_ylabel(f"{name[1]} (mm)")
        ax.set_title(f"{name} view (Center)")
        ax.set_aspect("equal", adjustable="datalim")
        if k == 0:
            ax.legend(fontsize=7, loc="best")
    ax = fig.add_subplot(2, 2, 4, projection="3d")
    if mesh is not None:
        v = mesh[0] * mm
        step = max(1, v.shape[0] // 5000)
        ax.scatter(v[::step, 0], v[::step, 1], v[::step, 2], s=0.2, c="0.7", alpha=0.3)
    for c in curves:
        ax.plot(c[:, 0], c[:, 1], c[:, 2], color="tab:blue", lw=0.6, alpha=0.7)
    for ln in vf_lines:
        ax.plot(ln[:, 0], ln[:, 1], ln[:, 2], color="tab:green", lw=1.0)
    ax.plot(*rod.T, color="tab:red", lw=2.5)
    ax.plot(*tip.T, "--", color="tab:orange", lw=1.2)
    ax.plot(*implant.T, color="k", lw=3)
    ax.scatter(*hole, color="k", s=15)
    ax.set_xlabel("X (mm)")
    ax.set_ylabel("Y (mm)")
    ax.set_zlabel("Z (mm)")
    ax.set_title("isometric view")
    ax.view_init(elev=25, azim=-60)
    fig.suptitle(
        f"d_T = {p.d_T * mm:.3f} mm, theta_T = {np.rad2deg(p.theta_T):.3f} deg, "
        f"{'valid' if p.valid else 'INVALID: ' + p.reason}",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(out_dir / "views.png", dpi=110)
    plt.close(fig)
    paths.append(out_dir / "views.png")
    return paths
