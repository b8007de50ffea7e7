"""Figures of stage 2: one instrument placement (F_safe contours, PSO convergence, views of the
FPSM, rod, implant path and virtual fixture in Center) and every site of a case side by side.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from implantplan.analyses.figures import save
from implantplan.analyses.figures.fpsm import mesh_section
from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import invert
from implantplan.systems.placement.planner import Placement

MM = 1e-3


def mesh_in_center(fpsm: Fpsm):
    """Vertices and faces of the FPSM's mesh in Center (m), or None when it is not available.

    The FPSM records the mesh path but (so far) not the file's units: ``settings["mesh_units"]``
    is used when present, else mm (scans); if the mesh then lands at a scale 30x off the model's
    own size, the other unit is tried, and the mesh is left out when neither fits."""
    source = fpsm.settings.get("mesh")
    if not source or not Path(str(source)).is_file():
        return None
    from implantplan.systems.fpsm.oral_mesh import load_oral_mesh

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


def plot_placement(fpsm: Fpsm, p: Placement, out_dir, *,
                   placed_length: float | None = None) -> list[Path]:
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
            save(fig, out_dir / name, dpi=110)
            paths.append(out_dir / name)

    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(np.arange(p.history.size), p.history, "-o", ms=2)
    ax.set_xlabel("PSO iteration")
    ax.set_ylabel(f"global best F_safe ({p.objective})")
    ax.set_title(f"convergence: {p.iterations} iterations, stop: {p.stopped}")
    ax.grid(alpha=0.3)
    save(fig, out_dir / "convergence.png", dpi=110)
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
    # the planned implant in its hole: from the entry point (the site) into the bone
    placed = None if placed_length is None else \
        np.array([p.X_CH[:3, 3], p.X_CH[:3, 3] - placed_length * p.X_CH[:3, 2]]) * mm
    gap = float(np.linalg.norm(implant[1] - hole))
    vf_lines = [ln * mm for ln in _vf_outline(p.vf)] if p.vf is not None else []
    mesh = mesh_in_center(fpsm)

    fig = plt.figure(figsize=(11, 10))
    views = (("XY", 0, 1), ("YZ", 1, 2), ("XZ", 0, 2))
    for k, (name, a, b) in enumerate(views):
        ax = fig.add_subplot(2, 2, k + 1)
        if mesh is not None:
            v = mesh[0] * mm
            step = max(1, v.shape[0] // 20000)
            ax.plot(v[::step, a], v[::step, b], ",", color="0.75", label="mesh")
        for n_c, c in enumerate(curves):
            ax.plot(c[:, a], c[:, b], color="tab:blue", lw=0.6, alpha=0.7,
                    label="FPSM slices" if n_c == 0 else None)
        for n_l, ln in enumerate(vf_lines):
            ax.plot(ln[:, a], ln[:, b], color="tab:green", lw=1.0,
                    label="virtual fixture" if n_l == 0 else None)
        ax.plot(rod[:, a], rod[:, b], color="tab:red", lw=2.5, label="rod (line1)")
        ax.plot(tip[:, a], tip[:, b], "--", color="tab:orange", lw=1.2, label="tip path (line2)")
        ax.plot(implant[:, a], implant[:, b], color="k", lw=3,
                label=f"tool at the feeding target: head to tip (d12 "
                      f"{p.implant_length * mm:.0f} mm), tip {gap:.1f} mm from the hole")
        if placed is not None:
            ax.plot(placed[:, a], placed[:, b], color="tab:purple", lw=4,
                    label=f"implant placed (entry to apex, {placed_length * mm:.0f} mm)")
        ax.plot(hole[a], hole[b], "ko", ms=5, label="hole (entry point)")
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
    if placed is not None:
        ax.plot(*placed.T, color="tab:purple", lw=4)
    ax.scatter(*hole, color="k", s=15)
    ax.set_xlabel("X (mm)")
    ax.set_ylabel("Y (mm)")
    ax.set_zlabel("Z (mm)")
    ax.set_title("isometric view")
    ax.view_init(elev=25, azim=-60)
    fig.suptitle(
        f"d_T = {p.d_T * mm:.3f} mm, theta_T = {np.rad2deg(p.theta_T):.3f} deg, "
        f"{'valid' if p.valid else 'INVALID: ' + p.reason}\n"
        "the tool drawn at its feeding target (before the feed); the feed carries it along "
        "line2 until the tip reaches the hole" + (", where the implant is placed"
                                                  if placed is not None else ""),
        fontsize=10,
    )
    save(fig, out_dir / "views.png", dpi=110)
    paths.append(out_dir / "views.png")
    return paths


def _contours(ax, fpsm, grid_u, grid_v, points, radius):
    """Draw the FPSM wall (d_safe = 0, blue) and the wall shrunk by ``radius`` (dashed)."""
    d = fpsm.d_safe(points)
    d = np.where(np.isfinite(d), d, 1.0)
    ax.contour(grid_u / MM, grid_v / MM, d, levels=[0.0], colors="tab:blue", linewidths=1.0)
    ax.contour(
        grid_u / MM,
        grid_v / MM,
        d - radius,
        levels=[0.0],
        colors="tab:blue",
        linewidths=0.8,
        linestyles="--",
    )


def plot_placements(opened, X_WC, fpsm, placements, names, path) -> Path:
    """Per site: side view (Center Z-Y) in the site's plane X = const and top view (Center Z-X)
    at the Tool origin's height, in mm; see the module docstring for what is drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    R_WC, p_WC = X_WC[:3, :3], X_WC[:3, 3]
    z_lo, z_hi = fpsm.z_range
    zs = np.linspace(z_lo - 0.01, z_hi + 0.005, 220)
    n = len(placements)
    fig, axes = plt.subplots(n, 3, figsize=(18, 5 * n), squeeze=False)
    for row, (pl, name) in enumerate(zip(placements, names, strict=True)):
        site = pl.X_CH[:3, 3]
        tool = pl.X_CT[:3, 3]
        p1, p2, D = pl.line1["start"], pl.line2["start"], pl.line1["direction"]
        # how far the lines run until they leave through the top slice
        t_end = (z_hi - p1[2]) / D[2] if D[2] > 1e-9 else 0.08
        e1, e2 = p1 + t_end * D, p2 + t_end * D
        views = (
            (0, 2, 1, site[0], "Center Z (mm, out of the mouth)", "Center Y (mm, up)", "side"),
            (1, 2, 0, tool[1], "Center Z (mm, out of the mouth)", "Center X (mm)", "top"),
        )
        for col, (fixed, iu, iv, value, xl, yl, kind) in enumerate(views):
            ax = axes[row][col]
            # mesh section in the plane Center[fixed] = value
            normal_W = R_WC[:, fixed]
            origin_W = p_WC + value * normal_W
            seg = mesh_section(opened, origin_W, normal_W)
            if len(seg):
                segC = (seg.reshape(-1, 3) - p_WC) @ R_WC  # mesh -> Center
                segC = segC.reshape(-1, 2, 3) / MM
                ax.add_collection(LineCollection(segC[:, :, [iu, iv]], colors="k", lw=0.6))
            vs = np.linspace(-0.05, 0.05, 200)
            U, Vg = np.meshgrid(zs, vs)
            pts = np.zeros(U.shape + (3,))
            pts[..., iu], pts[..., iv], pts[..., fixed] = U, Vg, value
            _contours(ax, fpsm, U, Vg, pts, pl.rod_radius)
            ax.axvline(z_hi / MM, color="0.5", lw=0.6, ls=":")
            ax.plot(*(np.stack([site, tool])[:, [iu, iv]] / MM).T, "g-", lw=2, label="implant axis")
            ax.plot(*(np.stack([p1, e1])[:, [iu, iv]] / MM).T, "r-", lw=2, label="line1 (rod)")
            ax.plot(*(np.stack([p2, e2])[:, [iu, iv]] / MM).T, "m-", lw=1.2, label="line2 (tip)")
            ax.plot(site[iu] / MM, site[iv] / MM, "go")
            ax.plot(tool[iu] / MM, tool[iv] / MM, "ks", ms=4)
            ax.set_xlim(zs[0] / MM, zs[-1] / MM)
            ax.set_ylim(-50, 50)
            ax.set_aspect("equal")
            ax.grid(True, lw=0.3)
            ax.set_xlabel(xl)
            ax.set_ylabel(yl)
            where = (
                f"the site's X = {value / MM:.1f} mm"
                if kind == "side"
                else f"the Tool's Y = {value / MM:.1f} mm"
            )
            ax.set_title(
                f"site {name}, {kind} view at {where}: d_T = {pl.d_T / MM:.1f} mm, "
                f"theta_T = {np.rad2deg(pl.theta_T):.1f} deg\n"
                f"f_safe line1 = {pl.f_safe_line1 / MM:.2f} mm, line2 = "
                f"{pl.f_safe_line2 / MM:.2f} mm (blue: wall, dashed: shrunk by r)",
                fontsize=9,
            )
        axes[row][0].legend(loc="lower left", fontsize=8)
        # what the objective sees: d_safe along each line up to the top slice (Eq. 10-12)
        ax = axes[row][2]
        t = np.linspace(0.0, t_end, 300)
        for start, radius, color, label in (
            (p1, pl.rod_radius, "r", "line1 (rod), model shrunk by r"),
            (p2, 0.0, "m", "line2 (implant tip)"),
        ):
            d = fpsm.d_safe(start + t[:, None] * D, radius=radius)
            ax.plot(t / MM, d / MM, color, label=label)
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_xlabel("distance along the line from its start (mm)")
        ax.set_ylabel("d_safe (mm)")
        ax.set_title(f"site {name}: safe distance along the lines to the mouth opening", fontsize=9)
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=8)
    path = save(fig, path, dpi=100)
    return path
