"""``implantplan fpsm fit|cylinder``: build the FPSM of seed 000 (stage 1) and write it as JSON.

``fpsm fit MESH`` loads an oral mesh (any format trimesh reads), places the Center frame given
on the command line (mm, in the mesh's frame), fits the slices (systems.fpsm_fit) and writes
the model; ``--plots DIR`` adds the slices' curves over the mesh sections and the coverage and
dense-check penetration per slice. ``fpsm cylinder`` writes the analytic cylinder model used by
the paper's placement check (Sec. 5.3).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from implantplan.analyses.progress import Progress
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_atomic


def register(subparsers) -> None:
    fpsm = subparsers.add_parser("fpsm", help="finite-parameter surrogate model of the oral cavity")
    sub = fpsm.add_subparsers(dest="fpsm_command", required=True, metavar="SUBCOMMAND")

    fit = sub.add_parser("fit", help="fit the FPSM to an oral mesh (stage 1)")
    fit.add_argument("mesh", metavar="MESH", help="mesh file (STL, OBJ, PLY, OFF, GLB, ...)")
    fit.add_argument("--units", choices=("mm", "m"), default="mm", help="units of the mesh file")
    fit.add_argument(
        "--center-origin-mm",
        nargs=3,
        type=float,
        required=True,
        metavar=("X", "Y", "Z"),
        help="Center origin in the mesh frame (mm)",
    )
    fit.add_argument(
        "--center-z",
        nargs=3,
        type=float,
        required=True,
        metavar=("DX", "DY", "DZ"),
        help="Center Z axis (out of the mouth)",
    )
    fit.add_argument(
        "--center-x-hint",
        nargs=3,
        type=float,
        default=None,
        metavar=("DX", "DY", "DZ"),
        help="direction made orthogonal to Z for Center X",
    )
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
    fit.add_argument("--method", choices=("exact", "paper"), default="exact")
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
    cyl.add_argument("--radius-mm", type=float, required=True)
    cyl.add_argument("--z-min-mm", type=float, required=True)
    cyl.add_argument("--z-max-mm", type=float, required=True)
    cyl.add_argument("--slices", type=int, required=True)
    cyl.add_argument("--control-points", type=int, default=16)
    cyl.add_argument("--out", type=Path, required=True, help="output fpsm.json")
    cyl.set_defaults(func=_cylinder)


def _fit(args: argparse.Namespace) -> int:
    from implantplan.systems.fpsm_fit import fit_fpsm
    from implantplan.systems.oral_mesh import center_frame, load_oral_mesh

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
    from implantplan.systems.fpsm import Fpsm

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


def plot_fit(fpsm, mesh, out_dir) -> list[Path]:
    """Slice curves over the mesh sections (Center XY) and coverage/penetration per slice."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from trimesh.intersections import mesh_plane

    from implantplan.systems.fpsm import evaluate
    from implantplan.systems.frames import apply, invert

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    X_CW = invert(fpsm.X_WC)
    M = fpsm.slices
    cols = int(np.ceil(np.sqrt(M)))
    rows = int(np.ceil(M / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3 * cols, 3 * rows), squeeze=False)
    theta = np.linspace(0, 2 * np.pi, 721)
    for j, ax in enumerate(axes.flat):
        if j >= M:
            ax.axis("off")
            continue
        z = fpsm.slice_z[j]
        origin = apply(fpsm.X_WC, np.array([0.0, 0.0, z]))
        segments = mesh_plane(mesh, fpsm.X_WC[:3, 2], origin)
        if len(segments):
            seg_C = apply(X_CW, segments.reshape(-1, 3)).reshape(-1, 2, 3)[:, :, :2] * 1e3
            ax.add_collection(LineCollection(seg_C, colors="0.4", linewidths=0.8))
        r = evaluate(fpsm.rho[j][None, :], theta) * 1e3
        ax.plot(r * np.cos(theta), r * np.sin(theta), "C0-", lw=1.2)
        ax.plot(0, 0, "k+")
        ax.set_aspect("equal")
        ax.autoscale()
        ax.set_title(f"slice {j}: z = {z * 1e3:.1f} mm", fontsize=8)
        ax.tick_params(labelsize=6)
    fig.suptitle("FPSM slices (blue) over the mesh sections (grey), Center XY, mm")
    fig.tight_layout()
    curves = out_dir / "fpsm_slices.png"
    write_atomic(curves, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)

    d = fpsm.diagnostics
    fig, ax = plt.subplots(figsize=(7, 3.5))
    idx = np.arange(M)
    ax.bar(idx - 0.2, 100 * np.asarray(d["coverage"]), 0.4, label="coverage (own section)")
    ax.bar(
        idx + 0.2,
        100 * np.asarray(d["coverage_of_allowed"]),
        0.4,
        label="coverage of the allowed region",
    )
    ax.set_xlabel("slice")
    ax.set_ylabel("%")
    ax.set_ylim(0, 105)
    if "dense_penetration_rate" in d:
        ax2 = ax.twinx()
        ax2.plot(
            idx,
            100 * np.asarray(d["dense_penetration_rate"]),
            "C3o-",
            ms=3,
            label="dense-check penetration",
        )
        ax2.set_ylabel("penetration (%)", color="C3")
    ax.legend(loc="lower left", fontsize=7)
    ax.set_title(f"FPSM fit ({d['method']}): coverage and penetration per slice")
    fig.tight_layout()
    coverage = out_dir / "fpsm_coverage.png"
    write_atomic(coverage, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)
    return [curves, coverage]
