"""The head-turn sweep of the awake-patient study (``analyze head-motion --turn-sweep``).

A deterministic grid of head turns about the neck (systems.teleop.head_motion, profile
``turn``: :meth:`HeadMotion.turn`, a minimum-jerk step about the cranial axis 40 mm behind
Center's origin): every amplitude x peak speed x direction (+1 / -1 along the cranial axis) x
onset (a share of the operator's script: early 0.25, mid 0.5, late 0.75) x site, on the same
operator feed (run 0 of ``feeding_runs(seed)``) and the same tracker noise stream, the arm
following the tracked mouth with the HeadGuard (the diagram of ``simulate feeding
--head-motion``). Measured per run, relative to the TRUE (moving) head:

- the exact clearance of the whole instrument (FCL against the moving opened scan,
  analyses.studies.scan_reference.exact_for) at every logged pose (200 Hz) and between them:
  the certified bound over the swept motion under the moving head
  (analyses.studies.scan_reference.swept_clearance with the head: one piece of code for the
  adversarial study and this one);
- the fixture's body violation (the TCP and the rod's entry crossing against the lateral
  tolerance, ``VirtualFixture.body_violation``) at every logged pose, in the frame of the
  TRACKED head (``FeedRun.violation_tracked``: the frame the fixture and the supervisor
  integrate the command in, where the fixture holds the tool) and in the TRUE head's (which
  adds the camera's error: its lag and noise, below);
- the arm's steps: the TCP's largest step between consecutive control steps in the tracked
  head's frame, in the true head's and in World. An **arm jump** is a step of the TCP in the
  tracked head's frame larger than the command limits allow in one control step
  (``STEP_SLACK`` x linear_speed x period, the adversarial study's rule: 10% for DiffIK's
  linearization; the rules are scan_reference's): the arm moving other than its command
  (DiffIK stuck, then catching up).
  Relative to the TRUE head the tool also moves by the change of the camera's error between
  two control steps (at every camera sample, with a still head too: the noise of two samples,
  up to about 0.4 mm at the tool), and in World by the head's own motion;
- differential IK's reports (Drake's warnings "Differential IK started returning status
  ...": each a change of its status, e.g. to "stuck"), counted per run;
- the guard: when it stopped the feed after the onset, and whether the tool backed out 90% of
  the guard's distance (head_motion.back_out).

Pass (the acceptance of the head turn): exact clearance at the poses and over the swept motion
>= margin - ``MARGIN_SLACK`` (the case's SafetySpec margin), fixture violation in the tracked
head's frame <= ``MAX_VIOLATION``, no arm jump, at every logged pose of every run. The true
head's violation and steps are reported beside (the camera's share; the clearance, the safety
figure, is always the true head's).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from implantplan.analyses.studies.head_motion import back_out
from implantplan.analyses.studies.scan_reference import (
    MARGIN_SLACK,
    MAX_VIOLATION,
    STEP_SLACK,
    exact_for,
    swept_clearance,
)
from implantplan.diagrams import feeding as F
from implantplan.diagrams.teleop import TeleopCase, build_teleop, simulate
from implantplan.systems import seeds
from implantplan.systems.errors import InputError
from implantplan.systems.teleop.head_motion import HeadMotion, neck_of
from implantplan.systems.teleop.master_device import feeding_runs
from implantplan.systems.teleop.tracker import TrackerParams
from implantplan.systems.validate import names

AMPLITUDES_DEG = (10.0, 15.0)
SPEEDS_DEG_S = (30.0, 45.0, 60.0)
DIRECTIONS = (1.0, -1.0)
ONSETS = {"early": 0.25, "mid": 0.5, "late": 0.75}  # share of the operator's script
MAX_AMPLITUDE_DEG = 30.0  # bounds of the flags (the issue: up to 15 deg at up to 60 deg/s)
MAX_SPEED_DEG_S = 120.0
MAX_LIST = 10  # values per flag
MAX_WORKERS = 2


@dataclass(frozen=True)
class Turn:
    """One run of the grid (SI units): site index, amplitude (rad), peak rate (rad/s),
    direction (+1 / -1 along the cranial axis), onset name."""

    site: int
    angle: float
    peak_rate: float
    sign: float
    onset: str

    @property
    def label(self) -> str:
        return (f"{np.rad2deg(self.angle):.0f} deg {np.rad2deg(self.peak_rate):.0f} deg/s "
                f"{'+' if self.sign > 0 else '-'} {self.onset}")


def grid(sites: int, *, amplitudes_deg=AMPLITUDES_DEG, speeds_deg_s=SPEEDS_DEG_S,
         directions=DIRECTIONS, onsets=tuple(ONSETS)) -> list[Turn]:
    """Every combination, site-major (the order of the JSON's runs)."""
    check_grid(amplitudes_deg, speeds_deg_s, directions, onsets)
    return [Turn(k, float(np.deg2rad(a)), float(np.deg2rad(v)), float(d), o)
            for k in range(sites) for a in amplitudes_deg for v in speeds_deg_s
            for d in directions for o in onsets]


def check_grid(amplitudes_deg, speeds_deg_s, directions=DIRECTIONS, onsets=tuple(ONSETS)):
    """The sweep's values (errors name the flag), checked before any work."""
    for flag, values, hi in (("--turn-amplitudes-deg", amplitudes_deg, MAX_AMPLITUDE_DEG),
                             ("--turn-speeds-deg-s", speeds_deg_s, MAX_SPEED_DEG_S)):
        if not 1 <= len(values) <= MAX_LIST:
            raise InputError(flag, f"expected 1-{MAX_LIST} values, got {len(values)}")
        for v in values:
            if not (np.isfinite(v) and 0 < v <= hi):
                raise InputError(flag, f"expected values in (0, {hi:g}], got {v}")
    for d in directions:
        if d not in (1.0, -1.0):
            raise InputError("directions", f"expected +1 or -1, got {d}")
    names(onsets, "--turn-onsets", ONSETS)


def parse_list(text: str, flag: str) -> tuple[float, ...]:
    """A comma-separated list of numbers (errors name ``flag``)."""
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise InputError(flag, f"expected comma-separated numbers, got {text!r}") from None


class _DiffIkReports(logging.Filter):
    """Counts Drake's differential IK status reports (installed first on the "drake" logger,
    so a filter that drops repeats after it does not hide them from the count)."""

    def __init__(self):
        super().__init__("diffik-reports")
        self.reports = 0
        self.stuck = 0

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        if "Differential IK" in text or "differential IK" in text:
            self.reports += 1
            self.stuck += "stuck" in text.lower()
        return True


def motion_of(tc: TeleopCase, seed: int):
    """The operator's feed every run of the sweep replays (run 0 of ``feeding_runs``)."""
    return feeding_runs(tc.X_WE(tc.q_start)[:3, 3], tc.X_WTarget[:3, 3], runs=1, seed=seed)[0]


def head_of(tc: TeleopCase, turn: Turn, motion) -> HeadMotion:
    """The turn of ``turn`` about the neck of ``tc``'s head at its onset in ``motion``."""
    return HeadMotion.turn(angle=turn.angle, peak_rate=turn.peak_rate, sign=turn.sign,
                           onset=ONSETS[turn.onset] * motion.duration,
                           pivot=tc.X_WCenter[:3, 3], neck=neck_of(tc.X_WCenter))


def run_turn(tc: TeleopCase, exact, turn: Turn, *, seed: int = 0,
             tracker: TrackerParams | None = None) -> dict:
    """Simulate one turn of the grid and measure it (module notes) with the camera ``tracker``
    (TrackerParams() if None; its noise seeded from ``seed``); the result's ``_trace`` holds
    the time series of the figure."""
    motion = motion_of(tc, seed)
    hm = head_of(tc, turn, motion)
    trk = dataclasses.replace(tracker or TrackerParams(), seed=seeds.seed(seed, 0, 1))
    teleop = build_teleop(tc, head_motion=hm, tracker=trk)
    counter = _DiffIkReports()
    drake = logging.getLogger("drake")
    drake.filters.insert(0, counter)
    try:
        run = simulate(teleop, motion.duration + F.FINISH_SECONDS, motion=motion)
    finally:
        drake.removeFilter(counter)
    # FCL where the run's smallest can be (scan_reference.screened), a proven bound elsewhere
    swept = swept_clearance(tc, exact, run.q, head=hm, t=run.t, screen=True)
    limits, period = teleop.limiter.limits, teleop.period
    step_limit = STEP_SLACK * limits.linear_speed * period
    trk_step = np.linalg.norm(np.diff(run.X_CT_tracked[:, :3, 3], axis=0), axis=1)
    rel = np.linalg.norm(np.diff(run.X_CT[:, :3, 3], axis=0), axis=1)
    world = np.linalg.norm(np.diff(run.p_WE, axis=0), axis=1)
    onset = hm.params["onset_s"]
    trig = float(run.guard[-1, 2]) if run.guard[-1, 0] > 0.5 else -1.0
    out = {
        "site": tc.label.removeprefix("site "), "amplitude_deg": float(np.rad2deg(turn.angle)),
        "peak_speed_deg_s": float(np.rad2deg(turn.peak_rate)), "direction": turn.sign,
        "onset": turn.onset, "onset_s": onset, "turn_seconds": hm.params["seconds"],
        "poses": int(run.t.size),
        "exact_clearance_min": float(swept.at_poses.min()),
        "exact_clearance_min_time": float(run.t[int(np.argmin(swept.at_poses))]),
        "exact_between_sampled": swept.sampled, "exact_between_bound": swept.bound,
        "sampled_segments": swept.sampled_segments,
        "violation_max": float(run.violation_tracked.max()),
        "violation_max_time": float(run.t[int(np.argmax(run.violation_tracked))]),
        "violation_max_true_head": float(run.violation.max()),
        "angle_violation_max_true_head": float(run.angle_violation.max()),
        "tcp_step_max": float(trk_step.max()),
        "tcp_step_max_time": float(run.t[1 + int(np.argmax(trk_step))]),
        "tcp_step_max_true_head": float(rel.max()),
        "tcp_step_max_world": float(world.max()),
        "step_limit": step_limit,
        "arm_jumps": int((trk_step > step_limit).sum()),
        "diffik_reports": counter.reports, "diffik_stuck": counter.stuck,
        "trigger_time": trig,
        "trigger_cause": int(run.guard[-1, 3]),
        "stop_after_onset_s": trig - onset if trig >= 0 else None,
        "final_error": float(np.linalg.norm(
            run.X_CT[-1, :3, 3] - (np.linalg.inv(tc.X_WCenter) @ tc.X_WTarget)[:3, 3])),
        "wall_seconds": run.wall_seconds, "sim_seconds": run.sim_seconds,
    }
    if trig >= 0:
        b = back_out(run, tc, trig, onset)
        out["backed_out_m"] = b["backed_out_m"]
        out["backed_out"] = b["backed_out_time"] >= 0
        out["backed_out_after_onset_s"] = (b["backed_out_time"] - onset
                                           if b["backed_out_time"] >= 0 else None)
    else:
        out["backed_out"], out["backed_out_m"] = False, 0.0
    margin = teleop.supervisor.barrier.margin
    out["margin"] = margin
    out["passed"] = bool(min(out["exact_clearance_min"], out["exact_between_bound"])
                         >= margin - MARGIN_SLACK and out["violation_max"] <= MAX_VIOLATION
                         and out["arm_jumps"] == 0)
    out["_trace"] = {"t": run.t, "clearance": swept.at_poses, "measured": swept.exact_at,
                     "violation": run.violation_tracked, "violation_true": run.violation,
                     "step": np.concatenate([[0.0], trk_step]),
                     "step_true": np.concatenate([[0.0], rel]), "onset_s": onset,
                     "turn_seconds": hm.params["seconds"], "trigger_time": trig,
                     "margin": margin, "step_limit": step_limit,
                     "label": f"{tc.label}, {turn.label}"}
    return out


_WORKER: dict = {}


def _init_worker(cases, mesh, seed, tracker=None):
    _WORKER.update(cases=cases, mesh=mesh, seed=seed, tracker=tracker, exact={})


def _run_in_worker(turn: Turn) -> dict:
    from implantplan.analyses.progress import quiet_drake

    quiet_drake()
    tc = _WORKER["cases"][turn.site]
    exact = _WORKER["exact"].get(turn.site)
    if exact is None:
        exact = _WORKER["exact"][turn.site] = exact_for(tc, _WORKER["mesh"])
    return run_turn(tc, exact, turn, seed=_WORKER["seed"], tracker=_WORKER["tracker"])


def turn_sweep(cases, mesh, turns: list[Turn], *, seed: int = 0, workers: int = 1,
               tracker: TrackerParams | None = None, progress=None) -> dict:
    """Every turn of ``turns`` on the teleop ``cases`` (per site) against ``mesh`` (the opened
    scan) with the camera ``tracker`` (TrackerParams() if None); returns the JSON dict, the
    worst run's trace under ``"_worst"``."""
    if not 1 <= workers <= MAX_WORKERS:
        raise InputError("--workers", f"expected an integer in 1..{MAX_WORKERS}, got {workers}")
    t0 = time.perf_counter()
    _init_worker(cases, mesh, seed, tracker)
    runs = []
    if workers > 1:
        pool = ProcessPoolExecutor(max_workers=workers - 1, initializer=_init_worker,
                                   initargs=(cases, mesh, seed, tracker))
        try:
            # this process runs every other turn itself: ``workers`` processes in all
            futures = {i: pool.submit(_run_in_worker, tn)
                       for i, tn in enumerate(turns) if i % workers}
            for i, tn in enumerate(turns):
                r = futures[i].result() if i in futures else _run_in_worker(tn)
                runs.append(r)
                _say(progress, i, len(turns), r)
        finally:  # interrupted (Ctrl-C, SIGTERM): the queued turns are dropped, not waited for
            pool.shutdown(wait=True, cancel_futures=True)
    else:
        for i, tn in enumerate(turns):
            r = _run_in_worker(tn)
            runs.append(r)
            _say(progress, i, len(turns), r)
    worst = min(runs, key=lambda r: (r["passed"], min(r["exact_clearance_min"],
                                                      r["exact_between_bound"])))
    traces = worst["_trace"]
    runs = [{k: v for k, v in r.items() if not k.startswith("_")} for r in runs]
    margin = runs[0]["margin"]
    return {"seed": seed, "margin": margin, "margin_slack": MARGIN_SLACK,
            "max_violation": MAX_VIOLATION, "step_limit": runs[0]["step_limit"],
            "runs": runs, "table": table(runs), "summary": summarize(runs),
            "passed": all(r["passed"] for r in runs),
            "wall_seconds": time.perf_counter() - t0, "_worst": traces}


def _say(progress, i, n, r):
    if progress is not None:
        progress.step(i, n, f"site {r['site']} {r['amplitude_deg']:.0f} deg "
                      f"{r['peak_speed_deg_s']:.0f} deg/s {r['direction']:+.0f} {r['onset']}: "
                      f"exact {1e3 * r['exact_clearance_min']:.2f} / between "
                      f"{1e3 * r['exact_between_bound']:.2f} mm, VF "
                      f"{1e3 * r['violation_max']:.2f} mm (true head "
                      f"{1e3 * r['violation_max_true_head']:.2f}), step "
                      f"{1e3 * r['tcp_step_max']:.2f} mm (true head "
                      f"{1e3 * r['tcp_step_max_true_head']:.2f})")


def summarize(runs: list[dict]) -> dict:
    """Over all runs: the worst of each figure and the counts."""
    return {
        "runs": len(runs),
        "exact_clearance_min": min(r["exact_clearance_min"] for r in runs),
        "exact_between_bound_min": min(r["exact_between_bound"] for r in runs),
        "violation_max": max(r["violation_max"] for r in runs),
        "violation_max_true_head": max(r["violation_max_true_head"] for r in runs),
        "tcp_step_max": max(r["tcp_step_max"] for r in runs),
        "tcp_step_max_true_head": max(r["tcp_step_max_true_head"] for r in runs),
        "tcp_step_max_world": max(r["tcp_step_max_world"] for r in runs),
        "runs_with_arm_jumps": sum(r["arm_jumps"] > 0 for r in runs),
        "diffik_reports": sum(r["diffik_reports"] for r in runs),
        "diffik_stuck": sum(r["diffik_stuck"] for r in runs),
        "guard_stopped": sum(r["trigger_time"] >= 0 for r in runs),
        "backed_out": sum(r["backed_out"] for r in runs),
        "failed": sum(not r["passed"] for r in runs),
    }


def table(runs: list[dict]) -> list[dict]:
    """One row per site x peak speed x direction (over amplitudes and onsets), in mm."""
    rows = {}
    for r in runs:
        key = (r["site"], r["peak_speed_deg_s"], r["direction"])
        rows.setdefault(key, []).append(r)
    out = []
    for (site, speed, d), rs in rows.items():
        out.append({
            "site": site, "peak_speed_deg_s": speed, "direction": d, "runs": len(rs),
            "exact_mm": 1e3 * min(r["exact_clearance_min"] for r in rs),
            "between_mm": 1e3 * min(r["exact_between_bound"] for r in rs),
            "violation_mm": 1e3 * max(r["violation_max"] for r in rs),
            "violation_true_mm": 1e3 * max(r["violation_max_true_head"] for r in rs),
            "step_mm": 1e3 * max(r["tcp_step_max"] for r in rs),
            "step_true_mm": 1e3 * max(r["tcp_step_max_true_head"] for r in rs),
            "jumps": sum(r["arm_jumps"] for r in rs),
            "stuck": sum(r["diffik_stuck"] for r in rs),
            "stopped": sum(r["trigger_time"] >= 0 for r in rs),
            "backed_out": sum(r["backed_out"] for r in rs),
            "failed": sum(not r["passed"] for r in rs)})
    return out


def print_table(result: dict) -> None:
    print(f"{'site':>6} {'deg/s':>6} {'dir':>4} {'runs':>5} {'exact mm':>9} {'between':>8} "
          f"{'VF mm':>6} {'(true)':>7} {'step mm':>8} {'(true)':>7} {'jumps':>6} {'stuck':>6} "
          f"{'stopped':>8} {'backed':>7} {'failed':>7}")
    for r in result["table"]:
        print(f"{r['site']:>6} {r['peak_speed_deg_s']:>6.0f} {r['direction']:>+4.0f} "
              f"{r['runs']:>5} {r['exact_mm']:>9.3f} {r['between_mm']:>8.3f} "
              f"{r['violation_mm']:>6.3f} {r['violation_true_mm']:>7.3f} {r['step_mm']:>8.3f} "
              f"{r['step_true_mm']:>7.3f} {r['jumps']:>6} {r['stuck']:>6} "
              f"{r['stopped']:>8} {r['backed_out']:>7} {r['failed']:>7}")
    s = result["summary"]
    print(f"margin {1e3 * result['margin']:.1f} mm (pass: exact >= "
          f"{1e3 * (result['margin'] - MARGIN_SLACK):.1f} mm at the poses and between, VF <= "
          f"{1e3 * MAX_VIOLATION:.1f} mm and no TCP step > "
          f"{1e3 * result['step_limit']:.3f} mm in the tracked head's frame; (true): the true "
          f"head's, with the camera's error); differential IK reports "
          f"{s['diffik_reports']} ({s['diffik_stuck']} stuck) in {s['runs']} runs; "
          f"{s['failed']} runs failed; {result['wall_seconds']:.0f} s")


def plot_worst(trace: dict, out_dir) -> list:
    """``head_turn_worst.png``: exact clearance, fixture violation and the TCP's step relative
    to the head against time for the worst run of the sweep."""
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t = np.asarray(trace["t"])
    fig, axes = plt.subplots(3, 1, figsize=(9, 7.5), sharex=True)
    c, measured = 1e3 * np.asarray(trace["clearance"]), np.asarray(trace["measured"])
    axes[0].plot(t, c, color="0.7", lw=0.8, label="proven lower bound (FCL not needed there)")
    axes[0].plot(t[measured], c[measured], ".", ms=2.5, color="tab:blue",
                 label="exact clearance (FCL)")
    axes[0].axhline(1e3 * trace["margin"], color="k", ls="--", lw=0.8, label="margin")
    axes[0].axhline(1e3 * (trace["margin"] - MARGIN_SLACK), color="tab:red", ls=":", lw=0.8,
                    label="margin - 0.2 mm")
    axes[0].set_ylabel("clearance (mm)")
    axes[1].plot(t, 1e3 * np.asarray(trace["violation_true"]), color="0.6", lw=0.8,
                 label="true head (with the camera's error)")
    axes[1].plot(t, 1e3 * np.asarray(trace["violation"]), color="tab:orange",
                 label="tracked head (the fixture's frame)")
    axes[1].axhline(1e3 * MAX_VIOLATION, color="tab:red", ls=":", lw=0.8)
    axes[1].set_ylabel("fixture violation (mm)")
    axes[1].legend(loc="upper left", fontsize=8)
    axes[2].plot(t, 1e3 * np.asarray(trace["step_true"]), color="0.6", lw=0.8,
                 label="true head")
    axes[2].plot(t, 1e3 * np.asarray(trace["step"]), color="tab:green", label="tracked head")
    axes[2].axhline(1e3 * trace["step_limit"], color="tab:red", ls=":", lw=0.8)
    axes[2].set_ylabel("TCP step per\ncontrol step (mm)")
    axes[2].legend(loc="upper left", fontsize=8)
    axes[2].set_xlabel("time (s)")
    for ax in axes:
        ax.axvspan(trace["onset_s"], trace["onset_s"] + trace["turn_seconds"], color="0.9")
        if trace["trigger_time"] >= 0:
            ax.axvline(trace["trigger_time"], color="tab:purple", lw=0.8)
    axes[0].legend(loc="lower left", fontsize=8)
    axes[0].set_title(f"worst head turn: {trace['label']} (grey: the turn; purple: guard stop)")
    fig.tight_layout()
    path = out_dir / "head_turn_worst.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]
