"""Figures of the teleop experiments (seed 001): joint swing of the feeds (Fig. 12c), the
error-mapping circle (Fig. 10) and the selected layout against random ones (Figs. 11, 13, 14).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from implantplan.diagrams.feeding import CIRCLE_LIMITS, circle_path, joint_error
from implantplan.systems.frames import invert, transform
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp


def plot_layouts(result: dict, out_dir) -> list[Path]:
    """Bars of the means and distributions per layout (seed 001 Figs. 11, 13, 14)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    entries = result["layouts"]
    labels = [e["label"] for e in entries]
    colors = ["tab:red"] + ["tab:gray"] * (len(entries) - 1)
    paths = []
    specs = [
        ("path_error", "path_error_mean", "path_error_realizations", 1000.0,
         "mean path error (mm)", "Error mapping: circle r 25 mm at 10 mm/s (cf. seed 001 Fig. 11)"),
        ("joint_travel", "joint_travel_mean", "joint_travel_runs", 1.0,
         "joint travel (rad)", "Joint variation over the feeds (cf. seed 001 Fig. 13)"),
    ]
    for name, mean_key, dist_key, scale, ylabel, title in specs:
        fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        means = np.array([e[mean_key] for e in entries], dtype=float) * scale
        ax1.bar(range(len(entries)), means, color=colors)
        ax1.set_ylabel(ylabel)
        ax1.set_title(title + f"  rank of 'win': {result['ranks'][name]}/{len(entries)}")
        data = [
            np.asarray(e[dist_key], dtype=float) * scale if e[dist_key] is not None else []
            for e in entries
        ]
        ax2.boxplot(data, positions=range(len(entries)))
        ax2.set_ylabel(ylabel)
        ax2.set_xticks(range(len(entries)), labels)
        ax2.set_xlabel("layout ('win' = selected)")
        fig.tight_layout()
        path = out_dir / f"layouts_{name}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    fig, ax = plt.subplots(figsize=(9, 3.5))
    ax.bar(range(len(entries)), [e["gii"] for e in entries], color=colors)
    ax.set_xticks(range(len(entries)), labels)
    ax.set_ylabel("GII")
    ax.set_title(
        f"GII over 100 poses (cf. seed 001 Fig. 14)  rank of 'win': "
        f"{result['ranks']['gii']}/{len(entries)}"
    )
    fig.tight_layout()
    path = out_dir / "layouts_gii.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    paths.append(path)
    return paths


def plot_feeding(result: dict, out_dir) -> Path:
    """Cumulative joint travel of every run (seed 001 Fig. 12c)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for i, r in enumerate(result["runs"]):
        c = r["travel_curve"]
        ax.plot(c["t"], c["joint_travel"], lw=1, label=f"run {i}" if i < 10 else None)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("cumulative joint travel (rad)")
    ax.set_title("Joint swing during the feeds")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    path = Path(out_dir) / "feeding_travel.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_circle(sc_plant, xyz, branch, result, out_dir, seed=0) -> Path:
    """Desired and executed circle (first realization), magnified error (seed 001 Fig. 10)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, d_O = circle_path()
    X_OEs = transform(np.broadcast_to(moprp.R_OE, (t.size, 3, 3)), d_O)
    X_BO = invert(moprp.base_pose(xyz))
    r = kin.ik(X_BO @ X_OEs, limits=CIRCLE_LIMITS, X_FT=sc_plant.X_FT)
    q = np.unwrap(r.q[:, branch], axis=0)
    dq = joint_error(q, t, sc_plant.eps, 1, seed)[0]
    X_OB = moprp.base_pose(xyz)
    p_des = (X_OB @ kin.fk(q, sc_plant.X_FT))[:, :3, 3]
    p_exe = (X_OB @ kin.fk(q + dq, sc_plant.X_FT))[:, :3, 3]
    gain = 20.0
    p_mag = p_des + gain * (p_exe - p_des)
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.plot(1000 * p_des[:, 1], 1000 * p_des[:, 2], "k-", label="desired")
    ax.plot(1000 * p_mag[:, 1], 1000 * p_mag[:, 2], "r-", lw=1, label=f"executed (error x{gain:g})")
    ax.set_aspect("equal")
    ax.set_xlabel("Oral Y (mm)")
    ax.set_ylabel("Oral Z (mm)")
    ax.set_title(f"mean path error {1000 * result['path_error_mean']:.3f} mm")
    ax.legend()
    fig.tight_layout()
    path = Path(out_dir) / "circle.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
