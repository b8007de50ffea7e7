"""Figures of the accuracy study (analyses.studies.accuracy): the error budget's bars per source
and the sensitivity curves, one PNG each per site."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from implantplan.analyses.figures import save

UNITS = {"entry": "mm", "apex": "mm", "angle": "deg"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _slug(label: str) -> str:
    return label.replace(" ", "_")


def plot_budget(study: dict, out_dir) -> list[Path]:
    """``accuracy_budget_<site>.png``: per deviation, bars of the mean per row (each source
    alone, all together) with the sd as error bars and the 95th percentile as a dot; the
    clinical means of the robots (Yomi, autonomous) as lines."""
    plt = _plt()
    out_dir = Path(out_dir)
    paths = []
    clinical = study.get("clinical", {})
    for label, entry in study["sites"].items():
        rows = [r for r in entry["budget"] if r != "none"]
        fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
        x = np.arange(len(rows))
        for ax, (k, unit) in zip(axes, UNITS.items(), strict=True):
            mean = [entry["budget"][r][k]["mean"] for r in rows]
            sd = [entry["budget"][r][k]["sd"] for r in rows]
            p95 = [entry["budget"][r][k]["p95"] for r in rows]
            colors = ["tab:red" if r == "all" else "tab:blue" for r in rows]
            ax.bar(x, mean, yerr=sd, color=colors, capsize=3, label="mean +- sd")
            ax.plot(x, p95, "k.", label="95th percentile")
            for (name, vals), style in zip(
                    [(n, v) for n, v in clinical.items() if not isinstance(
                        v[f"{k}_{unit}"], str)][:2], ("--", ":"), strict=False):
                ax.axhline(vals[f"{k}_{unit}"], color="gray", ls=style, lw=1,
                           label=f"{name.split(' (')[0]} (clinical mean)")
            ax.set_xticks(x, rows, rotation=30, ha="right")
            ax.set_ylabel(f"{k} deviation ({unit})")
            ax.set_title(k)
        axes[0].legend(fontsize=7)
        fig.suptitle(f"{label}: error budget ({study['runs']} runs per row)")
        paths.append(save(fig, out_dir / f"accuracy_budget_{_slug(label)}.png", dpi=110))
    return paths


def plot_sensitivity(study: dict, out_dir) -> list[Path]:
    """``accuracy_sensitivity_<site>.png``: mean and 95th percentile of each deviation against
    the tracker's latency, its rate, and the registration sigma."""
    plt = _plt()
    out_dir = Path(out_dir)
    paths = []
    for label, entry in study["sites"].items():
        sens = entry.get("sensitivity")
        if not sens:
            continue
        curves = (("tracker_latency_ms", "tracker latency (ms), head motion on"),
                  ("tracker_rate_hz", "tracker rate (Hz), head motion on"),
                  ("registration_sigma_scale", "registration sigma (x the plan's)"))
        fig, axes = plt.subplots(3, 3, figsize=(12, 9), sharex="col")
        for j, (curve, xlabel) in enumerate(curves):
            c = sens[curve]
            for i, (k, unit) in enumerate(UNITS.items()):
                ax = axes[i, j]
                ax.plot(c["x"], [r[k]["mean"] for r in c["rows"]], "o-", label="mean")
                ax.plot(c["x"], [r[k]["p95"] for r in c["rows"]], "s--", label="p95")
                ax.set_ylabel(f"{k} ({unit})")
                if i == 2:
                    ax.set_xlabel(xlabel)
        axes[0, 0].legend(fontsize=7)
        fig.suptitle(f"{label}: sensitivity ({sens['runs']} runs per point)")
        paths.append(save(fig, out_dir / f"accuracy_sensitivity_{_slug(label)}.png", dpi=110))
    return paths
