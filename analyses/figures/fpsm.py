"""Figures of stage 1: the mouth opening (scanned vs opened sections) and the FPSM fit (slice
curves over the mesh sections, coverage and penetration per slice).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from implantplan.analyses.figures import save
from implantplan.systems.files import write_atomic

MM = 1e-3


def mesh_section(mesh, origin, normal):
    """(n, 2, 3) segments of the mesh's section by the plane through ``origin`` with ``normal``."""
    from trimesh.intersections import mesh_plane

    return mesh_plane(mesh, np.asarray(normal, float), np.asarray(origin, float))


def plot_mouth_opening(
    scanned,
    opened,
    path,
    *,
    planes_y=(0.0,),
    hinge_point=None,
    occlusal_point=None,
    occlusal_normal=None,
) -> Path:
    """Side views (mesh x-z, mm) of the scanned (grey) and opened (black) mesh, one panel per
    sagittal plane y = ``planes_y`` (m), with the hinge (red dot) and the occlusal plane."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    fig, axes = plt.subplots(1, len(planes_y), figsize=(6 * len(planes_y), 5), squeeze=False)
    for ax, y in zip(axes[0], planes_y, strict=True):
        for mesh, color, label in ((scanned, "0.6", "scanned"), (opened, "k", "opened")):
            s = mesh_section(mesh, (0.0, y, 0.0), (0.0, 1.0, 0.0)) / MM
            ax.add_collection(LineCollection(s[:, :, [0, 2]], colors=color, lw=0.8, label=label))
        if hinge_point is not None:
            h = np.asarray(hinge_point) / MM
            ax.plot(h[0], h[2], "ro", label="hinge")
        if occlusal_point is not None and occlusal_normal is not None:
            p, n = np.asarray(occlusal_point) / MM, np.asarray(occlusal_normal, float)
            xs = np.array([50.0, 160.0])
            # the plane's trace in y = const: n_x (x - p_x) + n_z (z - p_z) = 0 (n_y y ignored)
            if abs(n[2]) > 1e-9:
                zs = p[2] - n[0] * (xs - p[0]) / n[2]
                ax.plot(xs, zs, "b--", lw=0.8, label="occlusal plane")
        ax.autoscale()
        ax.set_aspect("equal")
        ax.grid(True, lw=0.3)
        ax.set_xlabel("mesh x (mm, front -> back)")
        ax.set_ylabel("mesh z (mm, up)")
        ax.set_title(f"sagittal section y = {y / MM:.1f} mm")
    axes[0][0].legend(loc="lower right", fontsize=8)
    path = save(fig, path, dpi=110)
    return path


def plot_fit(fpsm, mesh, out_dir) -> list[Path]:
    """Slice curves over the mesh sections (Center XY) and coverage/penetration per slice."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from trimesh.intersections import mesh_plane

    from implantplan.systems.fpsm.model import evaluate
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
