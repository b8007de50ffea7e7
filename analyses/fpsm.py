"""``implantplan fpsm fit|cylinder``: build the FPSM of seed 000 (stage 1) and write it as JSON.

``fpsm fit MESH`` loads an oral mesh (any format trimesh reads), places the Center frame given
on the command line (mm, in the mesh's frame), fits the slices (systems.fpsm.fit) and writes
the model; ``--plots DIR`` adds the slices' curves over the mesh sections and the coverage and
dense-check penetration per slice. ``fpsm cylinder`` writes the analytic cylinder model used by
the paper's placement check (Sec. 5.3).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from implantplan.analyses.figures.fpsm import plot_fit
from implantplan.analyses.progress import Progress
from implantplan.systems.errors import InputError

POINT, DIRECTION = ("X", "Y", "Z"), ("DX", "DY", "DZ")  # metavars of 3-vector options


def register(subparsers) -> None:
    fpsm = subparsers.add_parser("fpsm", help="finite-parameter surrogate model of the oral cavity")
    sub = fpsm.add_subparsers(dest="fpsm_command", required=True, metavar="SUBCOMMAND")

    fit = sub.add_parser("fit", help="fit the FPSM to an oral mesh (stage 1)")
    fit.add_argument("mesh", metavar="MESH", help="mesh file (STL, OBJ, PLY, OFF, GLB, ...)")
    fit.add_argument("--units", choices=("mm", "m"), default="mm", help="units of the mesh file")
    fit.add_argument("--center-origin-mm", nargs=3, type=float, required=True, metavar=POINT,
                     help="Center origin in the mesh frame (mm)")
    fit.add_argument("--center-z", nargs=3, type=float, required=True, metavar=DIRECTION,
                     help="Center Z axis (out of the mouth)")
    fit.add_argument("--center-x-hint", nargs=3, type=float, default=None, metavar=DIRECTION,
                     help="direction made orthogonal to Z for Center X")
    fit.add_argument("--slices", type=int, default=15, help="number of slices M")
    fit.add_argument("--control-points", type=int, default=15, help="control radii per slice N")
    fit.add_argument("--samples", type=int, default=150, help="sample angles per slice Z")
    fit.add_argument(
        "--z-range-mm",
        nargs=2,
        type=float,
        default=None,
        metavar=("A", "B"),
        help="first and last slice height along Center Z (mm); default: the "
        "stretch of the axis inside the cavity",
    )
    fit.add_argument("--method", choices=("exact", "paper"), default="exact",
                     help="exact: max area by LPs (default); paper: Eq. 7-9 gradient descent")
    fit.add_argument("--margin-mm", type=float, default=0.0, help="clearance from the walls (mm)")
    fit.add_argument(
        "--cap-radius-mm",
        type=float,
        default=None,
        help="wall distance (mm) for rays that meet no wall (open scans)",
    )
    fit.add_argument(
        "--close-open-cuts",
        action="store_true",
        help="close the mesh's open boundary loops (centroid fans) before casting",
    )
    fit.add_argument(
        "--check-factor",
        type=int,
        default=8,
        help="dense penetration check: this many times the angles and heights",
    )
    fit.add_argument("--plots", type=Path, default=None, metavar="DIR", help="write plots here")
    fit.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    fit.add_argument("--out", type=Path, required=True, help="output fpsm.json")
    fit.set_defaults(func=_fit)

    cyl = sub.add_parser("cylinder", help="an analytic cylinder FPSM (for checks)")
    cyl.add_argument("--radius-mm", type=float, required=True, help="cylinder radius (mm)")
    cyl.add_argument("--z-min-mm", type=float, required=True, help="bottom (throat) z (mm)")
    cyl.add_argument("--z-max-mm", type=float, required=True,
                     help="top z, the mouth opening (mm)")
    cyl.add_argument("--slices", type=int, required=True, help="number of slices M (>= 2)")
    cyl.add_argument("--control-points", type=int, default=16,
                     help="control radii per slice N (default 16)")
    cyl.add_argument("--out", type=Path, required=True, help="output fpsm.json")
    cyl.set_defaults(func=_cylinder)


def _fit(args: argparse.Namespace) -> int:
    from implantplan.systems.fpsm.fit import fit_fpsm
    from implantplan.systems.fpsm.oral_mesh import center_frame, load_oral_mesh

    progress = Progress("fpsm fit", quiet=args.quiet)
    scale = 1e-3
    for name in ("margin_mm", "cap_radius_mm"):
        value = getattr(args, name)
        if value is not None and not np.isfinite(value):
            raise InputError("--" + name.replace("_", "-"), "expected a finite number")
    progress.say(f"loading {args.mesh} ({args.units})")
    mesh = load_oral_mesh(args.mesh, units=args.units, field="MESH")
    X_WC = center_frame(
        np.asarray(args.center_origin_mm) * scale, args.center_z, x_hint=args.center_x_hint
    )
    fpsm = fit_fpsm(
        mesh,
        X_WC,
        slices=args.slices,
        control_points=args.control_points,
        samples=args.samples,
        z_range=None if args.z_range_mm is None else np.asarray(args.z_range_mm) * scale,
        method=args.method,
        margin=args.margin_mm * scale,
        cap_radius=None if args.cap_radius_mm is None else args.cap_radius_mm * scale,
        close_open_cuts=args.close_open_cuts,
        check_factor=args.check_factor,
        progress=progress,
    )
    fpsm.save(args.out)
    progress.say(f"wrote {args.out}")
    print(summary_table(fpsm))
    if args.plots is not None:
        paths = plot_fit(fpsm, mesh, args.plots)
        progress.say("plots: " + ", ".join(str(p) for p in paths))
    return 0


def _cylinder(args: argparse.Namespace) -> int:
    from implantplan.systems.fpsm.model import Fpsm

    fpsm = Fpsm.cylinder(
        args.radius_mm * 1e-3,
        args.z_min_mm * 1e-3,
        args.z_max_mm * 1e-3,
        args.slices,
        control_points=args.control_points,
    )
    fpsm.save(args.out)
    print(
        f"wrote {args.out}: cylinder radius {args.radius_mm} mm, z {args.z_min_mm}.."
        f"{args.z_max_mm} mm, {args.slices} slices x {args.control_points} control points"
    )
    return 0


def summary_table(fpsm) -> str:
    """Per-slice table: height, coverage, penetration at the samples and on the dense check."""
    d = fpsm.diagnostics
    rows = [
        f"{'slice':>5} {'z_mm':>8} {'coverage_%':>10} {'of_allowed_%':>12} "
        f"{'pene_samples':>12} {'dense_pene_%':>12} {'time_ms':>8}"
    ]
    dense = d.get("dense_penetration_rate", [float("nan")] * fpsm.slices)
    for j in range(fpsm.slices):
        rows.append(
            f"{j:>5} {fpsm.slice_z[j] * 1e3:>8.2f} {100 * d['coverage'][j]:>10.1f} "
            f"{100 * d['coverage_of_allowed'][j]:>12.1f} {d['penetrating_samples'][j]:>12d} "
            f"{100 * dense[j]:>12.3f} {1e3 * d['slice_seconds'][j]:>8.1f}"
        )
    s = d["seconds"]
    rows.append(
        f"method {d['method']}: cast {s['cast']:.3f} s, solve {s['solve']:.3f} s, total "
        f"{s['total']:.3f} s; rays without a wall: {d['rays_without_wall']} of {d['rays_cast']}"
    )
    if "dense_penetration_rate_total" in d:
        rows.append(
            f"dense check: {d['dense_rays']} rays, penetration rate "
            f"{100 * d['dense_penetration_rate_total']:.3f} %, max depth "
            f"{1e3 * d['dense_max_depth_m']:.3f} mm"
        )
    return "\n".join(rows)


