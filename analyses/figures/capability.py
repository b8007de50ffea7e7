"""Figures of capability maps and RASSCMAP setups (seed 004): map slices coloured by index (HSV
red 0 to blue 1), best vs worst setup, and a static Meshcat HTML of coloured voxels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from implantplan.systems.capability import maps as cm
from implantplan.systems.capability import rasscmap as rm
from implantplan.systems.capability import setup_search as ss
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_text_atomic


def hsv_index_cmap():
    """Matplotlib colormap: HSV hue from red (index 0) to blue (index 1), Sec. 3."""
    import matplotlib.colors as mcolors
    import matplotlib.pyplot as plt

    return mcolors.ListedColormap(plt.get_cmap("hsv")(np.linspace(0.0, 2.0 / 3.0, 256)))


def plot_target_neighbourhoods(cmap: cm.CapabilityMap, X_BA: np.ndarray, names, path) -> Path:
    """PNG: for each feeding target (a row), the 3 x 3 x 3 voxels around it at their real size and
    position in base_link, one column per layer (below, at and above the target's voxel), each
    voxel coloured by its reachability index (HSV, red 0 to blue 1; grey = not in the map), the
    target marked. Axes in mm, zoomed to the neighbourhood."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from implantplan.analyses.figures import save

    g = cmap.grid
    v = g.voxel
    index_of = dict(zip(np.asarray(cmap.voxel_ids).tolist(), np.asarray(cmap.index).tolist(),
                        strict=True))
    colours = hsv_index_cmap()
    p_all = np.asarray(X_BA)[:, :3, 3]
    fig, axes = plt.subplots(len(p_all), 3, figsize=(13, 3.8 * len(p_all)), squeeze=False,
                             layout="constrained")
    for row, (name, p) in enumerate(zip(names, p_all, strict=True)):
        c = g.cells(p)
        for col, dk in enumerate((-1, 0, 1)):
            ax = axes[row, col]
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    ijk = c + (di, dj, dk)
                    inside = np.all((ijk >= 0) & (ijk < np.asarray(g.shape)))
                    vid = int(np.ravel_multi_index(tuple(ijk), g.shape)) if inside else -1
                    idx = index_of.get(vid)
                    lo = (g.origin + ijk * v) * 1e3
                    ax.add_patch(Rectangle((lo[0], lo[1]), v * 1e3, v * 1e3,
                                           facecolor="0.85" if idx is None else colours(idx),
                                           edgecolor="k", linewidth=0.6))
                    if idx is not None:
                        ax.text(lo[0] + v * 500, lo[1] + v * 500, f"{idx:.2f}", ha="center",
                                va="center", fontsize=7, color="w" if idx > 0.6 else "k")
            if dk == 0:
                ax.plot(p[0] * 1e3, p[1] * 1e3, marker="*", color="k", markersize=12,
                        linestyle="none", label="feeding target")
                ax.legend(loc="upper right", fontsize=7)
            zc = (g.origin[2] + (c[2] + dk + 0.5) * v) * 1e3
            ax.set_title(f"site {name}: layer z = {zc:.0f} mm"
                         + (" (target's)" if dk == 0 else ""), fontsize=9)
            lo_xy = (g.origin[:2] + (c[:2] - 1) * v) * 1e3
            ax.set_xlim(lo_xy[0] - 0.1 * v * 1e3, lo_xy[0] + 3.1 * v * 1e3)
            ax.set_ylim(lo_xy[1] - 0.1 * v * 1e3, lo_xy[1] + 3.1 * v * 1e3)
            ax.set_aspect("equal")
            ax.set_xlabel("x in base (mm)")
            ax.set_ylabel("y in base (mm)")
    sm = plt.cm.ScalarMappable(cmap=colours, norm=plt.Normalize(0, 1))
    fig.colorbar(sm, ax=axes.ravel().tolist(), label="reachability index (grey: not mapped)")
    fig.suptitle(f"capability around each feeding target ({v * 1e3:.0f} mm voxels)")
    return save(fig, path, dpi=90, tight=False)


def plot_map_slices(cmap: cm.CapabilityMap, path, *, n_slices: int = 6) -> None:
    """PNG: horizontal slices (xy) of the map at evenly spaced heights, voxels coloured by index."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    g = cmap.grid
    dense = np.full(g.size, np.nan)
    dense[cmap.voxel_ids] = cmap.index
    dense = dense.reshape(g.shape)
    ks = np.flatnonzero(np.any(np.isfinite(dense), axis=(0, 1)))
    if len(ks) == 0:
        raise InputError("map", "the map has no reachable voxel to draw")
    pick = ks[np.linspace(0, len(ks) - 1, n_slices).round().astype(int)]
    cols = 3
    rows = int(np.ceil(len(pick) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.8 * rows), squeeze=False)
    ext = [
        g.origin[0],
        g.origin[0] + g.shape[0] * g.voxel,
        g.origin[1],
        g.origin[1] + g.shape[1] * g.voxel,
    ]
    im = None
    for ax, k in zip(axes.ravel(), pick, strict=False):
        z = g.origin[2] + (k + 0.5) * g.voxel
        im = ax.imshow(
            dense[:, :, k].T, origin="lower", extent=ext, cmap=hsv_index_cmap(), vmin=0, vmax=1
        )
        ax.set_title(f"z = {z:.3f} m")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal")
    for ax in axes.ravel()[len(pick) :]:
        ax.axis("off")
    fig.colorbar(im, ax=axes.ravel().tolist(), label="reachability index")
    p = cmap.params
    fig.suptitle(
        f"capability map ({p.tool}, {p.voxel * 1000:g} mm, {p.directions} dirs, +-{p.limits} deg)"
    )
    fig.savefig(path, dpi=90)
    plt.close(fig)


def setup_points(problem: ss.SetupProblem, cand: int) -> tuple[np.ndarray, np.ndarray]:
    b, a = problem.split(np.array([cand]))
    if problem.patient.access == "unconstrained":
        idx = rm.unconstrained_index(problem.cmap, problem.bases[b], problem.points_W)[0]
        return problem.points_W, idx
    r = problem.rasscmap(int(b[0]), int(a[0]))
    return r.centres, r.index


def plot_best_worst(problem: ss.SetupProblem, best: int, worst: int, path) -> None:
    """PNG: best vs worst setup side by side (top and side views), RASSCMAP coloured by index."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 10))
    cmap = hsv_index_cmap()
    for col, (label, cand) in enumerate((("best", best), ("worst", worst))):
        pts, idx = setup_points(problem, cand)
        b, a = problem.split(np.array([cand]))
        X_WB = problem.bases[b[0]]
        for row, (i, j, names) in enumerate(((0, 1, ("x", "y")), (0, 2, ("x", "z")))):
            ax = axes[row, col]
            ax.scatter(pts[:, i], pts[:, j], c=idx, cmap=cmap, vmin=0, vmax=1, s=12, alpha=0.7)
            t = problem.task.poses[:, :3, 3]
            ax.scatter(t[:, i], t[:, j], marker="x", c="k", s=30, label="task poses")
            allb = problem.bases[:, :3, 3]
            ax.scatter(allb[:, i], allb[:, j], c="0.8", s=4, label="base candidates")
            ax.scatter([X_WB[i, 3]], [X_WB[j, 3]], marker="s", c="k", s=80, label="base")
            ax.arrow(
                X_WB[i, 3], X_WB[j, 3], 0.15 * X_WB[i, 0], 0.15 * X_WB[j, 0], width=0.008, color="k"
            )
            if problem.patient.access == "constrained":
                X_WA = problem.patient.access_points[a[0]][1]
                ax.scatter(
                    [X_WA[i, 3]], [X_WA[j, 3]], marker="v", c="m", s=80, label="access point"
                )
            ax.set_xlabel(f"{names[0]} (m)")
            ax.set_ylabel(f"{names[1]} (m)")
            ax.set_aspect("equal")
            if row == 0:
                ax.set_title(f"{label}: cost {problem.cost[cand]:.3f}, c_s {problem.c_s[cand]:.3f}")
        axes[0, col].legend(loc="best", fontsize=7)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def meshcat_html(points: np.ndarray, index: np.ndarray, path, *, voxel: float) -> bool:
    """Static Meshcat HTML of voxels coloured by index (headless, port chosen by Drake).

    Returns False (and writes nothing) when Meshcat cannot start here.
    """
    try:
        from pydrake.geometry import Meshcat, MeshcatParams
        from pydrake.perception import BaseField, Fields, PointCloud
    except ImportError:
        return False
    import matplotlib

    matplotlib.use("Agg")
    try:
        meshcat = Meshcat(MeshcatParams(host="localhost"))
    except RuntimeError:
        return False
    cloud = PointCloud(len(points), Fields(BaseField.kXYZs | BaseField.kRGBs))
    cloud.mutable_xyzs()[:] = np.asarray(points, dtype=np.float32).T
    rgb = (hsv_index_cmap()(np.asarray(index))[:, :3] * 255).astype(np.uint8)
    cloud.mutable_rgbs()[:] = rgb.T
    meshcat.SetObject("/rasscmap", cloud, point_size=voxel * 0.8)
    write_text_atomic(path, meshcat.StaticHtml())
    return True
