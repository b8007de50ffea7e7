"""Figures of a batch of cases (``implantplan batch``): every case's checks, pass/fail and margin,
and the summary page."""

from __future__ import annotations

import html

import numpy as np

from implantplan.systems.files import write_atomic

# how a check's margin is shown: file unit -> (display unit, factor)
DISPLAY = {"m": ("mm", 1e3), "rad": ("deg", 180.0 / np.pi)}
PASS, FAIL, ABSENT = 1.0, 0.0, 0.5


def _label(c: dict) -> str:
    """A column's label: the check's stable id (short; its name where a record has none) and
    the site."""
    return (c.get("id") or c["name"]) + (f" [{c['site']}]" if c.get("site") else "")


def plot_cohort_checks(records: list[dict], path) -> None:
    """PNG of :func:`cohort_checks_figure`, written atomically with every label inside it
    (``bbox_inches="tight"``)."""
    import matplotlib.pyplot as plt

    fig = cohort_checks_figure(records)

    def writer(tmp):
        fig.savefig(tmp, dpi=90, format="png", bbox_inches="tight", pad_inches=0.15)

    try:
        write_atomic(path, writer)
    finally:
        plt.close(fig)


def cohort_checks_figure(records: list[dict]):
    """A row per case, a column per check (id and site); green pass, red fail, grey absent
    (not planned, or a check that case has not); each cell shows the margin (mm for lengths,
    deg for angles, as is otherwise). A case that was not planned shows its status. The
    figure's height leaves room for the longest rotated check label."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.colors as mcolors
    import matplotlib.pyplot as plt

    columns: list[str] = []
    units: dict[str, str] = {}
    for r in records:
        for c in r["checks"]:
            if _label(c) not in units:
                columns.append(_label(c))
                units[_label(c)] = c["unit"]
    grid = np.full((len(records), max(1, len(columns))), ABSENT)
    text = [[""] * grid.shape[1] for _ in records]
    for i, r in enumerate(records):
        for c in r["checks"]:
            j = columns.index(_label(c))
            grid[i, j] = PASS if c["pass"] else FAIL
            unit, f = DISPLAY.get(c["unit"], (c["unit"], 1.0))
            text[i][j] = f"{c['margin'] * f:.3g}"
    fig_w = min(40.0, max(8.0, 3.0 + 0.55 * grid.shape[1]))
    # the rotated labels (7 pt, about 0.55 em a character, at 60 deg) need this much height
    longest = max((len(f"{c} (deg)") for c in columns), default=0)
    fig_h = 2.0 + 0.35 * len(records) + longest * 7 * 0.55 / 72 * np.sin(np.deg2rad(60))
    fig, ax = plt.subplots(figsize=(fig_w, fig_h), layout="constrained")
    cmap = mcolors.ListedColormap(["#d9534f", "#dddddd", "#5cb85c"])
    ax.imshow(grid, cmap=cmap, vmin=0, vmax=1, aspect="auto")
    for i, r in enumerate(records):
        if not r["checks"]:
            ax.text(-0.4, i, f"{r['status']}: {(r['reason'] or '')[:120]}", va="center",
                    ha="left", fontsize=7, color="#a00000")  # fmt: skip
        for j, t in enumerate(text[i]):
            if t:
                ax.text(j, i, t, ha="center", va="center", fontsize=6)
    ax.set_yticks(range(len(records)))
    ax.set_yticklabels([f"{r['case']} ({r['status']})" for r in records], fontsize=7)
    ax.set_xticks(range(len(columns)))
    ax.set_xticklabels(
        [f"{c} ({DISPLAY.get(units[c], (units[c], 1))[0]})" for c in columns],
        rotation=60, ha="right", fontsize=7,
    )  # fmt: skip
    n_pass = sum(r["status"] == "passed" for r in records)
    ax.set_title(f"checks of {len(records)} cases: {n_pass} passed; cell = margin "
                 "(>= 0 passes; green pass, red fail, grey absent)", fontsize=9)  # fmt: skip
    return fig


def summary_html(rows: list[dict], png: str) -> str:
    """The summary page: one row per case (status, checks, reason, link to its report) and the
    figure of :func:`plot_cohort_checks`."""
    colour = {"passed": "#dff0d8", "checks failed": "#fcf8e3"}
    head = ("case", "status", "plan exit code", "checks", "failed checks / reason", "seconds")
    body = []
    for r in rows:
        bg = colour.get(r["status"], "#f2dede")
        link = f"<a href='{html.escape(r['folder'])}/report.html'>{html.escape(r['case'])}</a>"
        case = link if r["status"] in colour else html.escape(r["case"])
        why = r["failed_checks"] or r["reason"]
        body.append(
            f"<tr style='background:{bg}'><td>{case}</td><td>{html.escape(r['status'])}</td>"
            f"<td>{r['plan_exit_code']}</td><td>{r['checks_passed']}/{r['checks_total']}</td>"
            f"<td>{html.escape(why)}</td><td>{r['seconds']}</td></tr>"
        )
    n_pass = sum(r["status"] == "passed" for r in rows)
    return (
        "<!doctype html><html><head><meta charset='utf-8'><title>implantplan batch</title>"
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}img{max-width:100%}</style>"
        f"</head><body><h1>Batch: {n_pass} of {len(rows)} cases passed</h1>"
        "<table><tr>"
        + "".join(f"<th>{h}</th>" for h in head)
        + "</tr>"
        + "".join(body)
        + f"</table><h2>Checks of every case</h2><img src='{html.escape(png)}' "
        "alt='checks of every case'></body></html>\n"
    )
