"""The awake patient study (DESIGN.md section 7): seeded feeds under head motion.

    implantplan analyze head-motion --out DIR [--runs 50] [--profiles breathing,swallow,...]
                                    [--plan PLAN_DIR]

Per profile, ``runs`` seeded runs (run i: operator motion i of ``feeding_runs(seed)``, head
motion and tracker noise on the streams (i, 0) and (i, 1) below ``seed``, systems.seeds) on
the default case, each three ways:

- *still*: the patient does not move (the reference path);
- *following*: head motion on, tracker, the arm following the tracked mouth, the HeadGuard;
- *ignoring*: head motion on, the arm ignoring the head (``follow=False``).

Measured per run, all relative to the TRUE (moving) head:

- the tool's path deviation: the distance from p_CenterT(t) to the still run's path (the
  polyline of its logged positions) at every logged step (mean, max), up to the guard's trigger
  (after it the tool backs out on purpose): how far the head motion pushes the tool off its
  path in the mouth;
- the time-indexed path error |p_CenterT(t) - p_CenterT_still(t)| over the same steps (keys
  ``path_error_*``): the deviation plus any delay along the path (the supervisor holding the
  feed while the head moves, which the ignoring arm, with no guard, never does);
- the exact clearance: FCL (systems.placement.exact_clearance) of the whole tool against the cavity
mesh,
  the tool transformed into the moving head's Center frame at every logged step (2 000 steps of
  a 10 s run); on the bundled default case (``--case scan``, the default) the opened scan per
  site (analyses.studies.scan_reference.exact_for), on ``--case cylinder`` the cylinder of its FPSM;
- the feed's completion: final distance to the target in the head frame <= 1 mm; a
  following feed the safety layer held short of it (a swallow grows the guard's margin
  past the clearance at the narrowest part of the feed, so the barrier holds the tool until
  the head slows; no guard stop) is run again with ``WAIT_SECONDS`` more of the operator's
  finish by eye, as a surgeon waits a swallow out (``waited`` in its row);
- after a startle: the time from its onset to the guard's stop (detection) and to the end of
  the back-out (the tool moved 90% of the back-out distance along the fixture's axis out of
  the deepest point it reached since the onset, measured on the tool itself in the true head
  frame);
- lost tracking (a dropout window mid-feed under breathing): the stop, the back-out and the
  clearance.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import trimesh

from implantplan.analyses import out_folder
from implantplan.diagrams import feeding as F
from implantplan.diagrams.teleop import TeleopCase, build_teleop, simulate
from implantplan.systems import seeds
from implantplan.systems.errors import InputError
from implantplan.systems.placement.exact_clearance import ExactCavity
from implantplan.systems.teleop.head_guard import GuardSettings
from implantplan.systems.teleop.head_motion import PROFILES, HeadMotion, neck_of
from implantplan.systems.teleop.master_device import feeding_runs
from implantplan.systems.teleop.tracker import TrackerParams
from implantplan.systems.validate import names

STUDY_PROFILES = PROFILES[1:]  # breathing, swallow, startle, drift, turn
WAIT_SECONDS = 4.0  # a following feed the safety layer held short of the target (no guard
# stop) when the operator's finish ends: the surgeon waits the hold out and finishes by eye this
# much longer (the run simulated again, same seeds; ``waited`` in its row)
BACKED_OUT_SHARE = 0.9  # the back-out counts as done when the tool moved 90% of the distance


def cylinder_cavity(fpsm, sections: int = 256) -> ExactCavity:
    """The exact reference of a cylinder FPSM (Fpsm.cylinder): the triangulated cylinder wall
    and floor in Center, open at the top slice (its vertices lie on the circle, so the mesh is
    inside the FPSM by at most r (1 - cos(pi / sections)), 4 um here)."""
    s = fpsm.settings or {}
    if s.get("method") != "cylinder":
        raise InputError("fpsm", "the head-motion study's exact reference needs the default case's "
                         "cylinder FPSM (no scan mesh travels with a plan)")
    z0, z1 = s["z_range_m"]
    over = 0.01  # built 10 mm taller and cut at the top slice: no lid left on the cut plane
    mesh = trimesh.creation.cylinder(radius=s["radius_m"], height=z1 - z0 + over,
                                     sections=sections)
    mesh.apply_translation([0.0, 0.0, 0.5 * (z0 + z1 + over)])
    return ExactCavity(mesh, z_top=z1)


def default_case(seed: int = 0, scenario: str = "lying"):
    """(case, instrument) of the default feeding case (the layout ``simulate feeding`` selects
    without a robot placement: the knee of the random feasible bases)."""
    inst = F.default_instrument(seed)
    sc, sc_plant = F.load_scenario(scenario)
    xyz, branch, _ = F.knee_layout(sc, seed=seed)
    name = sc.posture if sc.posture in ("lying", "sitting") else "arm"
    return F.make_case(name, sc_plant, xyz, branch, inst, label="selected"), inst


def _target_C(case: TeleopCase) -> np.ndarray:
    return (np.linalg.inv(case.X_WCenter) @ case.X_WTarget)[:3, 3]


def path_distance(p: np.ndarray, path: np.ndarray, chunk: int = 256) -> np.ndarray:
    """(n,) distance of points ``p`` (n, 3) to the polyline ``path`` (m, 3) (exact, by
    segments; a one-point path is that point)."""
    p, path = np.atleast_2d(p), np.atleast_2d(path)
    if path.shape[0] == 1:
        return np.linalg.norm(p - path[0], axis=1)
    a, d = path[:-1], np.diff(path, axis=0)
    dd = np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)
    out = np.empty(p.shape[0])
    for i in range(0, p.shape[0], chunk):
        q = p[i:i + chunk, None, :] - a[None]  # (c, m-1, 3)
        u = np.clip(np.einsum("cmj,mj->cm", q, d) / dd, 0.0, 1.0)
        out[i:i + chunk] = np.linalg.norm(q - u[..., None] * d, axis=2).min(axis=1)
    return out


def measure(run, still, case: TeleopCase, cavity: ExactCavity, *,
            event_time: float | None = None) -> dict:
    """The figures of one head-motion run against its still reference (module notes).
    ``event_time``: when the head's event began (a startle's onset; default the guard's
    trigger): the back-out is measured out of the deepest point the tool reached since then."""
    p = run.X_CT[:, :3, 3]
    err = np.linalg.norm(p - still.X_CT[: len(p), :3, 3], axis=1)
    dev = path_distance(p, still.X_CT[:, :3, 3])
    trig = -1.0
    if run.guard is not None and run.guard[-1, 0] > 0.5:
        trig = float(run.guard[-1, 2])
    upto = run.t < trig if trig >= 0 else np.ones(len(p), dtype=bool)
    clear = cavity.tool_clearance(run.X_CT, case.tool)
    out = {
        "path_deviation_mean": float(dev[upto].mean()) if upto.any() else 0.0,
        "path_deviation_max": float(dev[upto].max()) if upto.any() else 0.0,
        "path_error_mean": float(err[upto].mean()) if upto.any() else 0.0,
        "path_error_max": float(err[upto].max()) if upto.any() else 0.0,
        "exact_clearance_min": float(clear.min()),
        "final_error": float(np.linalg.norm(p[-1] - _target_C(case))),
        "trigger_time": trig,
        "trigger_cause": int(run.guard[-1, 3]) if run.guard is not None else 0,
        "realtime_factor": run.sim_seconds / run.wall_seconds,
    }
    out["reached_target"] = out["final_error"] <= F.TARGET_TOLERANCE
    out["_clearance"], out["_error"], out["_deviation"] = clear, err, dev
    if trig >= 0:
        out.update(back_out(run, case, trig, event_time))
    return out


def back_out(run, case: TeleopCase, trig: float, event_time: float | None = None) -> dict:
    """The guard's back-out measured on the tool in the TRUE head frame: along the fixture's
    axis, out of the deepest point it reached since the event (``event_time``, e.g. the onset;
    at the trigger ``trig`` it may still be carried in by the head it lags): the time it had
    backed out ``BACKED_OUT_SHARE`` of the guard's distance (-1: never) and how far it went."""
    p = run.X_CT[:, :3, 3]
    ref = trig if event_time is None else min(trig, float(event_time))
    k = int(np.searchsorted(run.t, ref))
    s = p[k:] @ case.vf.direction
    out_of_deepest = s - np.minimum.accumulate(s)
    dist = GuardSettings().retreat_distance
    done = np.flatnonzero((run.t[k:] >= trig) & (out_of_deepest >= BACKED_OUT_SHARE * dist))
    return {"backed_out_time": float(run.t[k + done[0]]) if done.size else -1.0,
            "backed_out_m": float(out_of_deepest.max())}


def _public(m: dict) -> dict:
    return {k: v for k, v in m.items() if not k.startswith("_")}


class ScanCavity:
    """The bundled default case's exact reference for a site
    (analyses.studies.scan_reference.exact_for:
    the opened scan, FCL, the whole tool) taking poses in the head's Center frame."""

    def __init__(self, tc: TeleopCase, mesh):
        from implantplan.analyses.studies.scan_reference import exact_for

        self._exact = exact_for(tc, mesh)
        self._X_MC = tc.fpsm.X_WC  # the FPSM's X_WC is Center in the mesh frame

    def tool_clearance(self, X_CT: np.ndarray, tool=None) -> np.ndarray:
        return self._exact(self._X_MC @ np.asarray(X_CT, dtype=float))


def scan_cases(*, plan=None, progress=None) -> list:
    """[(teleop case, exact cavity)] per site: of the plan folder ``plan`` (its sites, fixtures
    and layout, its case's opened scan), or without one of the bundled default case (the scan,
    sites 36 and 46), planned as ``implantplan plan`` does."""
    from implantplan.analyses.studies.scan_reference import default_case_sites, plan_sites

    if plan is not None:
        cases, mesh = plan_sites(plan, field="--plan")
    else:
        cases, mesh = default_case_sites(progress=progress)
    return [(tc, ScanCavity(tc, mesh)) for tc in cases]


def check_study(profiles, runs: int) -> None:
    """The study's own arguments (errors name the flag), checked before any work."""
    if runs < 1:
        raise InputError("--runs", f"expected an integer >= 1, got {runs}")
    names(profiles, "--profiles", STUDY_PROFILES)


def head_study(case: TeleopCase, inst, *, profiles=STUDY_PROFILES, runs: int = 50, seed: int = 0,
               tracker: TrackerParams | None = None, progress=None, keep_traces: int = 1,
               cavity=None) -> dict:
    """The study over ``runs`` seeded runs per profile (module notes); returns the JSON dict and,
    under ``"_traces"``, the time series of the ``keep_traces`` runs per profile with the lowest
    exact clearance while following (the worst cases, lowest first)."""
    check_study(profiles, runs)
    if cavity is None:
        cavity = cylinder_cavity(inst.fpsm)
    start = case.X_WE(case.q_start)[:3, 3]
    motions = feeding_runs(start, case.X_WTarget[:3, 3], runs=runs, seed=seed)
    pivot = case.X_WCenter[:3, 3]
    neck = neck_of(case.X_WCenter)
    still_tel = build_teleop(case)
    stills = []
    t0 = time.perf_counter()
    for m in motions:
        stills.append(simulate(still_tel, m.duration + F.FINISH_SECONDS, motion=m))
    margin = still_tel.supervisor.barrier.margin  # the case's safety spec's
    out = {"runs": runs, "seed": seed, "profiles": {}, "margin": margin}
    traces = {}
    base = tracker or TrackerParams()
    for prof in profiles:
        rows = []
        for i, m in enumerate(motions):
            hm = HeadMotion.make(prof, seed=seeds.seed(seed, i, 0), pivot=pivot, neck=neck)
            trk = dataclasses.replace(base, seed=seeds.seed(seed, i, 1))
            on = hm.params.get("onset_s") if prof in ("startle", "turn") else None
            fol, a, still = following_run(case, m, hm, trk, cavity, still=stills[i],
                                          still_teleop=still_tel, event_time=on)
            ign = simulate(build_teleop(case, head_motion=hm, follow=False), fol.sim_seconds,
                           motion=m)
            b = measure(ign, still, case, cavity)
            row = {"head": {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                            for k, v in hm.params.items()},
                   "following": _public(a), "ignoring": _public(b)}
            if prof in ("swallow", "startle", "turn"):
                on = hm.params["onset_s"]
                dur = hm.params.get("seconds", 0.2 if prof == "startle" else 1.0)
                outside = (fol.t < on) | (fol.t > on + dur + 0.5)
                row["following"]["exact_clearance_min_outside_event"] = float(
                    a["_clearance"][outside].min())
                if prof in ("startle", "turn") and a["trigger_time"] >= 0:
                    row["following"]["stop_after_onset_s"] = a["trigger_time"] - on
                    if a.get("backed_out_time", -1) >= 0:
                        row["following"]["backed_out_after_onset_s"] = a["backed_out_time"] - on
            rows.append(row)
            kept = traces.setdefault(prof, [])
            if keep_traces and (len(kept) < keep_traces
                                or a["exact_clearance_min"] < kept[-1]["clearance_min"]):
                kept.append({
                    "run": i, "runs": runs, "clearance_min": a["exact_clearance_min"],
                    "t": fol.t, "head_mm": 1000 * np.linalg.norm(
                        hm.displacement(fol.t)[0], axis=1),
                    "clearance_following": a["_clearance"], "clearance_ignoring": b["_clearance"],
                    "error_following": a["_error"], "error_ignoring": b["_error"],
                    "deviation_following": a["_deviation"],
                    "deviation_ignoring": b["_deviation"],
                    "trigger_time": a["trigger_time"], "margin": margin,
                    "margin_extra": fol.margin_extra})
                kept.sort(key=lambda tr: tr["clearance_min"])  # the lowest clearances first
                del kept[keep_traces:]
            if progress is not None:
                progress.step(i, runs, f"{prof}: deviation {1000 * a['path_deviation_max']:.2f}"
                              f" mm following, {1000 * b['path_deviation_max']:.2f} mm ignoring;"
                              f" clearance {1000 * a['exact_clearance_min']:.2f} mm")
        out["profiles"][prof] = {"summary": summarize(rows, prof, margin), "runs": rows}
    out["lost_tracking"] = lost_tracking(case, motions[0], seed=seed, cavity=cavity,
                                         still=stills[0], tracker=base)
    out["wall_seconds"] = time.perf_counter() - t0
    out["_traces"] = traces
    return out


def following_run(case: TeleopCase, motion, head_motion: HeadMotion, tracker: TrackerParams,
                  cavity, *, still, still_teleop, event_time: float | None = None):
    """One feed with the arm following the moving head, measured against the ``still`` run
    (simulated on ``still_teleop``): ``(run, figures, still)``. A feed the safety layer held
    short of the target with no guard stop is run again with the operator finishing by eye
    ``WAIT_SECONDS`` longer (module notes; the figures' ``waited``), measured against the still
    run of the same length."""
    T = motion.duration + F.FINISH_SECONDS
    teleop = build_teleop(case, head_motion=head_motion, tracker=tracker)
    run = simulate(teleop, T, motion=motion)
    m = measure(run, still, case, cavity, event_time=event_time)
    m["waited"] = not m["reached_target"] and m["trigger_time"] < 0
    if m["waited"]:  # the same run again (the same seeds, deterministic), a longer finish
        T += WAIT_SECONDS
        still = simulate(still_teleop, T, motion=motion)
        run = simulate(teleop, T, motion=motion)
        m = measure(run, still, case, cavity, event_time=event_time) | {"waited": True}
    return run, m, still


def summarize(rows: list, prof: str, margin: float) -> dict:
    fol = [r["following"] for r in rows]
    ign = [r["ignoring"] for r in rows]
    s = {
        "runs": len(rows),
        "path_deviation_mean_following": float(np.mean([r["path_deviation_mean"] for r in fol])),
        "path_deviation_max_following": float(np.max([r["path_deviation_max"] for r in fol])),
        "path_deviation_mean_ignoring": float(np.mean([r["path_deviation_mean"] for r in ign])),
        "path_deviation_max_ignoring": float(np.max([r["path_deviation_max"] for r in ign])),
        "path_error_mean_following": float(np.mean([r["path_error_mean"] for r in fol])),
        "path_error_max_following": float(np.max([r["path_error_max"] for r in fol])),
        "path_error_mean_ignoring": float(np.mean([r["path_error_mean"] for r in ign])),
        "path_error_max_ignoring": float(np.max([r["path_error_max"] for r in ign])),
        "exact_clearance_min_following": float(min(r["exact_clearance_min"] for r in fol)),
        "exact_clearance_min_ignoring": float(min(r["exact_clearance_min"] for r in ign)),
        "runs_below_zero_following": int(sum(r["exact_clearance_min"] < 0 for r in fol)),
        "runs_below_margin_minus_0p2mm_following": int(sum(
            r.get("exact_clearance_min_outside_event", r["exact_clearance_min"])
            < margin - 0.0002 for r in fol)),
        "reached_target_following": int(sum(r["reached_target"] for r in fol)),
        "waited_following": int(sum(r.get("waited", False) for r in fol)),
        "guard_triggered_following": int(sum(r["trigger_time"] >= 0 for r in fol)),
        "realtime_factor_min_following": float(min(r["realtime_factor"] for r in fol)),
    }
    if prof in ("startle", "turn"):
        stops = [r["stop_after_onset_s"] for r in fol if "stop_after_onset_s" in r]
        backs = [r["backed_out_after_onset_s"] for r in fol if "backed_out_after_onset_s" in r]
        s["stop_after_onset_max_s"] = float(max(stops)) if stops else None
        s["backed_out_after_onset_max_s"] = float(max(backs)) if backs else None
        s["backed_out_runs"] = len(backs)
    return s


def lost_tracking(case: TeleopCase, motion, *, seed: int, cavity: ExactCavity, still,
                  tracker: TrackerParams, start_share: float = 0.5, seconds: float = 1.0) -> dict:
    """Breathing with the marker occluded from ``start_share`` of the operator's script for
    ``seconds``: the guard must stop the feed and back out; the exact clearance stays >= 0."""
    t_drop = start_share * motion.duration
    trk = dataclasses.replace(tracker, seed=seed, dropouts=((t_drop, t_drop + seconds),))
    hm = HeadMotion.make("breathing", seed=seed, pivot=case.X_WCenter[:3, 3])
    run = simulate(build_teleop(case, head_motion=hm, tracker=trk),
                   motion.duration + F.FINISH_SECONDS, motion=motion)
    m = measure(run, still, case, cavity)
    return {"dropout_s": [t_drop, t_drop + seconds], **_public(m),
            "stop_after_dropout_s": m["trigger_time"] - t_drop if m["trigger_time"] >= 0
            else None}


def _print_summary(result: dict, prefix: str = "") -> None:
    for prof, entry in result["profiles"].items():
        s = entry["summary"]
        mm = {k: 1000 * v for k, v in s.items() if isinstance(v, float) and (
            "error" in k or "deviation" in k) or k.startswith("exact")}
        line = (f"{prefix}{prof}: {s['runs']} runs, path deviation mean/max "
                f"{mm['path_deviation_mean_following']:.2f}/"
                f"{mm['path_deviation_max_following']:.2f} mm following vs "
                f"{mm['path_deviation_mean_ignoring']:.2f}/"
                f"{mm['path_deviation_max_ignoring']:.2f} mm ignoring (time-indexed "
                f"{mm['path_error_mean_following']:.2f}/{mm['path_error_max_following']:.2f} vs "
                f"{mm['path_error_mean_ignoring']:.2f}/{mm['path_error_max_ignoring']:.2f} mm); "
                f"exact clearance min "
                f"{mm['exact_clearance_min_following']:.2f} mm "
                f"({s['runs_below_zero_following']} runs < 0); reached "
                f"{s['reached_target_following']} ({s['waited_following']} after a wait); "
                f"guard {s['guard_triggered_following']}")
        if prof in ("startle", "turn") and s["stop_after_onset_max_s"] is not None:
            back = s["backed_out_after_onset_max_s"]
            line += (f"; stop <= {s['stop_after_onset_max_s']:.3f} s after onset, backed out "
                     f"{s['backed_out_runs']}/{s['runs']} runs"
                     + ("" if back is None else f" (<= {back:.3f} s after onset)"))
        print(line)
    lt = result["lost_tracking"]
    print(f"{prefix}lost tracking: stop {lt['stop_after_dropout_s']} s after the dropout, backed "
          f"out {1000 * lt.get('backed_out_m', 0.0):.1f} mm, exact clearance min "
          f"{1000 * lt['exact_clearance_min']:.2f} mm")


def tracker_from_args(args) -> TrackerParams:
    """The camera of ``--tracker-rate-hz``, ``--tracker-latency-ms``, ``--prediction-samples``
    (errors name the flag)."""
    flags = (("--tracker-rate-hz", "rate", args.tracker_rate_hz, 1.0),
             ("--tracker-latency-ms", "latency", args.tracker_latency_ms, 1e-3),
             ("--prediction-samples", "predict_samples", args.prediction_samples, 1))
    kw = {}
    for flag, name, value, scale in flags:
        if value is None:
            continue
        try:
            kw[name] = value * scale
            TrackerParams(**kw)
        except InputError as e:
            raise InputError(flag, str(e).split(': ', 1)[-1]) from None
    return TrackerParams(**kw, smooth=bool(getattr(args, "tracker_smooth", False)))


def cmd_head_motion(args) -> int:
    from implantplan.analyses.figures.head import plot_head
    from implantplan.analyses.progress import Progress
    from implantplan.analyses.report import render_head_motion
    from implantplan.systems.files import to_jsonable, write_json, write_text_atomic

    progress = Progress("analyze head-motion", quiet=args.quiet)
    if args.turn_sweep:
        return cmd_turn_sweep(args, progress)
    profiles = tuple(p.strip() for p in args.profiles.split(",") if p.strip())
    check_study(profiles, args.runs)
    tracker = tracker_from_args(args)
    if args.plan is not None and args.case == "cylinder":
        raise InputError("--plan", "a plan folder is studied on its own scan; expected no "
                         "--case cylinder with it")
    trk = {"rate": tracker.rate, "latency": tracker.latency,
           "predict_samples": tracker.predict_samples, "smooth": tracker.smooth,
           "noise_position": tracker.noise_position, "noise_angle": tracker.noise_angle}
    out = Path(args.out)
    out_folder.check_out(out, force=None)  # before any work: a folder of the user's is refused
    if args.case == "cylinder":
        case, inst = default_case(args.seed)
        result = head_study(case, inst, profiles=profiles, runs=args.runs, seed=args.seed,
                            progress=progress, tracker=tracker)
        traces = result.pop("_traces")
        out_folder.claim(out, "head_motion")
        figs = {"cylinder": [p.name for p in plot_head(traces, out)]}
        study = {"case": "cylinder", "tracker": trk, **result}
        study["passed"] = _never_below_zero({"cylinder": result})
        write_json(out / "head_motion.json", study, kind="head_motion")
        _print_summary(result)
    else:
        # a plan folder or the bundled default case: the scan, each site, FCL against the
        # moving opened scan
        if args.plan is None:
            progress.say("planning the bundled default case (scan, sites 36 and 46)")
        cases = scan_cases(plan=args.plan)
        if args.plan is not None:
            progress.say(f"the plan in {args.plan}: {len(cases)} sites, its case's opened scan")
        sites, figs = {}, {}
        for tc, cavity in cases:
            result = head_study(tc, None, profiles=profiles, runs=args.runs, seed=args.seed,
                                progress=progress, cavity=cavity, tracker=tracker)
            traces = result.pop("_traces")
            out_folder.claim(out, "head_motion")
            (out / tc.label).mkdir(parents=True, exist_ok=True)
            figs[tc.label] = [f"{tc.label}/{p.name}"
                              for p in plot_head(traces, out / tc.label)]
            sites[tc.label] = result
            _print_summary(result, prefix=f"{tc.label} ")
        study = {"case": "scan", "plan": None if args.plan is None else str(args.plan),
                 "tracker": trk, "sites": sites,
                 "passed": _never_below_zero(sites)}
        write_json(out / "head_motion.json", study, kind="head_motion")
    write_text_atomic(out / "report.html", render_head_motion(to_jsonable(study), figs))
    print(f"exact clearance never below 0 in any run: {'yes' if study['passed'] else 'NO'}; "
          f"wrote {out / 'head_motion.json'} and {out / 'report.html'}")
    return 0 if study["passed"] else 3  # a failed check exits 3 (DESIGN.md section 3)


def cmd_turn_sweep(args, progress) -> int:
    """``--turn-sweep``: the head-turn grid (analyses.studies.head_turn); every flag checked
    before any planning or simulation; exit 3 when a run fails the acceptance."""
    from implantplan.analyses.report import render_head_turn
    from implantplan.analyses.studies import head_turn as H
    from implantplan.systems.files import to_jsonable, write_json, write_text_atomic

    amplitudes = H.parse_list(args.turn_amplitudes_deg, "--turn-amplitudes-deg")
    speeds = H.parse_list(args.turn_speeds_deg_s, "--turn-speeds-deg-s")
    onsets = tuple(o.strip() for o in args.turn_onsets.split(",") if o.strip())
    H.check_grid(amplitudes, speeds, onsets=onsets)
    if not 1 <= args.workers <= H.MAX_WORKERS:
        raise InputError("--workers", f"expected an integer in 1..{H.MAX_WORKERS}, "
                         f"got {args.workers}")
    if args.case == "cylinder":
        raise InputError("--turn-sweep", "the sweep measures against the moving scan; expected "
                         "no --case cylinder with it")
    tracker = tracker_from_args(args)
    out = Path(args.out)
    out_folder.check_out(out, force=None)
    from implantplan.analyses.studies.scan_reference import default_case_sites, plan_sites

    if args.plan is not None:
        cases, mesh = plan_sites(args.plan, field="--plan")
    else:
        progress.say("planning the bundled default case (scan, sites 36 and 46)")
        cases, mesh = default_case_sites()
    turns = H.grid(len(cases), amplitudes_deg=amplitudes, speeds_deg_s=speeds, onsets=onsets)
    progress.say(f"{len(turns)} head turns on {len(cases)} sites, {args.workers} process(es)")
    result = H.turn_sweep(cases, mesh, turns, seed=args.seed, workers=args.workers,
                          tracker=tracker, progress=progress)
    worst = result.pop("_worst")
    out_folder.claim(out, "head_motion")
    figs = [p.name for p in H.plot_worst(worst, out)]
    study = {"case": "scan", "plan": None if args.plan is None else str(args.plan),
             "tracker": {"rate": tracker.rate, "latency": tracker.latency,
                         "predict_samples": tracker.predict_samples, "smooth": tracker.smooth},
             "turn_sweep": result, "figures": figs, "passed": result["passed"]}
    write_json(out / "head_motion.json", study, kind="head_motion")
    write_text_atomic(out / "report.html", render_head_turn(to_jsonable(study), figs))
    H.print_table(result)
    print(f"every head turn meets the acceptance: {'yes' if study['passed'] else 'NO'}; "
          f"wrote {out / 'head_motion.json'} and {out / 'report.html'}")
    return 0 if study["passed"] else 3


def _never_below_zero(sites: dict) -> bool:
    """True when no run of any profile, nor the lost-tracking run, went below 0 clearance."""
    for res in sites.values():
        if any(e["summary"]["runs_below_zero_following"] for e in res["profiles"].values()):
            return False
        if res["lost_tracking"]["exact_clearance_min"] < 0:
            return False
    return True


def register_analysis(sub) -> None:
    """Add ``head-motion`` to the ``analyze`` subcommands (analyses.simulate)."""
    p = sub.add_parser("head-motion", help="the awake patient: seeded feeds under head motion, "
                       "following vs ignoring the head, exact clearance")
    p.add_argument("--runs", type=int, default=50, help="seeded runs per profile (default 50)")
    p.add_argument("--profiles", default=",".join(STUDY_PROFILES),
                   help="comma-separated profiles (default all four)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    p.add_argument("--case", choices=("scan", "cylinder"), default="scan",
                   help="scan: the bundled default case (opened scan, each site, FCL against the "
                   "moving scan; figures in a folder per site); cylinder: seed 000's cylinder "
                   "feeding case of `simulate feeding` (default scan)")
    p.add_argument("--plan", type=Path, default=None,
                   help="a plan folder (implantplan plan or demo) to study instead of planning "
                   "the bundled default case: its sites, fixtures and layout, FCL against its "
                   "case's opened scan (the case file the plan names must be there)")
    p.add_argument("--tracker-rate-hz", type=float, default=None,
                   help="the camera's rate, 30-60 Hz (default 60)")
    p.add_argument("--tracker-latency-ms", type=float, default=None,
                   help="the camera's latency, 0-100 ms (default 20)")
    p.add_argument("--prediction-samples", type=int, default=None,
                   help="samples of the latency-compensating prediction, 0 (off) or 2-6 "
                   "(default 2)")
    p.add_argument("--tracker-smooth", action="store_true",
                   help="the camera's prediction for a fast head, blended between samples "
                   "(systems/teleop/tracker.py, Smoothing; off by default)")
    p.add_argument("--turn-sweep", action="store_true",
                   help="instead of the profiles: the deterministic grid of head turns about "
                   "the neck (amplitudes x peak speeds x both directions x onsets x sites), "
                   "exact clearance at the poses and over the swept motion, fixture violation, "
                   "arm jumps, differential IK reports, back-outs; exit 3 if a run fails")
    p.add_argument("--turn-amplitudes-deg", default="10,15",
                   help="the sweep's amplitudes, deg, each in (0, 30] (default 10,15)")
    p.add_argument("--turn-speeds-deg-s", default="30,45,60",
                   help="the sweep's peak speeds, deg/s, each in (0, 120] (default 30,45,60)")
    p.add_argument("--turn-onsets", default="early,mid,late",
                   help="the sweep's onsets in the feed: early, mid, late (a quarter, half, "
                   "three quarters of the operator's script; default all three)")
    p.add_argument("--workers", type=int, default=1,
                   help="processes of the sweep, 1 or 2 (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder (head_motion.json, report.html and head_<profile>.png)")
    p.set_defaults(func=cmd_head_motion)
