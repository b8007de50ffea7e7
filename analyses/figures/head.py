"""Figures of the awake-patient study (analyses.studies.head_motion): per profile, against time, the
head's motion, the tool's deviation from its path relative to the mouth (following vs ignoring
the head; dotted: the time-indexed error, which also counts the supervisor's holds) and the
exact clearance against the moving cavity with the margin."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_head(traces: dict, out_dir) -> list[Path]:
    """One PNG per profile (``head_<profile>.png``) from the first trace of each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for prof, runs in traces.items():
        tr = runs[0]
        t = np.asarray(tr["t"])
        fig, axes = plt.subplots(3, 1, figsize=(9, 7.5), sharex=True)
        axes[0].plot(t, tr["head_mm"], color="tab:purple")
        axes[0].set_ylabel("head displacement (mm)")
        dev_f, dev_i = tr.get("deviation_following"), tr.get("deviation_ignoring")
        if dev_f is not None:
            # following: up to the guard's trigger (after it the tool backs out on purpose)
            upto = t < tr["trigger_time"] if tr["trigger_time"] >= 0 else np.ones(len(t), bool)
            axes[1].plot(t[upto], 1000 * np.asarray(dev_f)[upto], label="following the mouth")
            axes[1].plot(t, 1000 * np.asarray(dev_i), label="ignoring the head")
            axes[1].plot(t[upto], 1000 * np.asarray(tr["error_following"])[upto],
                         color="tab:blue", ls=":", lw=0.8,
                         label="following, time-indexed (incl. holds)")
            axes[1].set_ylabel("deviation from path\nrel. mouth (mm)")
        else:
            axes[1].plot(t, 1000 * np.asarray(tr["error_following"]),
                         label="following the mouth")
            axes[1].plot(t, 1000 * np.asarray(tr["error_ignoring"]), label="ignoring the head")
            axes[1].set_ylabel("path error rel. mouth (mm)")
        axes[1].legend(loc="upper left")
        axes[2].plot(t, 1000 * np.asarray(tr["clearance_following"]), label="following")
        axes[2].plot(t, 1000 * np.asarray(tr["clearance_ignoring"]), label="ignoring")
        margin = 1000 * tr["margin"]
        extra = tr.get("margin_extra")
        if extra is not None:
            axes[2].plot(t[: len(extra)], margin + 1000 * np.asarray(extra), "k--", lw=0.8,
                         label="margin + tracking allowance")
        axes[2].axhline(margin, color="k", lw=0.8, label="margin")
        axes[2].axhline(0.0, color="tab:red", lw=0.8)
        axes[2].set_ylabel("exact clearance (mm)")
        axes[2].set_xlabel("t (s)")
        axes[2].legend(loc="upper left")
        if tr["trigger_time"] >= 0:
            for ax in axes:
                ax.axvline(tr["trigger_time"], color="tab:red", ls=":", lw=1.0)
        which = (f"run {tr['run']}, the lowest clearance of {tr['runs']}" if "run" in tr
                 else "run 0")
        axes[0].set_title(f"Awake patient: {prof} ({which}; red dotted: the guard stops and "
                          "backs out)")
        fig.tight_layout()
        path = out_dir / f"head_{prof}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths
