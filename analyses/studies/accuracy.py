"""Simulated implant accuracy (entry, apex, angle) and its error budget (DESIGN.md section 7).

    implantplan analyze accuracy [--plan DIR] [--runs N] [--sources a,b,...] [--seed S] --out DIR

Per site of the plan (or of the bundled default case, planned as ``implantplan plan`` does),
``runs`` seeded runs of the whole procedure in the teleop diagram: the scripted operator feeds
the tool to the feeding target, then drives it along the implant's axis to the planned depth
(systems.teleop.insertion: the insertion fixture, the depth stop) and finishes by eye. Each run
combines the error sources selected (:data:`SOURCES`; defaults in :data:`DEFAULTS`, where each
comes from in docs/measurements.md):

- ``registration``: the scan-to-patient registration error, drawn as the registration Monte Carlo
  draws it (systems.placement.exact_clearance.registration_errors, the plan's sigmas): the robot
  executes the plan in the registered frame, so the placed implant relative to the true anatomy
  is E^-1 X (exact: nothing in the loop sees the true anatomy);
- ``tracker``: the head tracker's noise, latency and rate (TrackerParams(); with the head still
  the arm follows the noisy estimate of a still head); off, the arm follows an ideal camera
  (no noise, no latency, 60 Hz);
- ``head``: head motion, run i the profile ``HEAD_PROFILES[i % 3]`` (breathing, swallow, drift
  as the head-motion study draws them), the arm following the tracked mouth;
- ``operator``: the scripted operator's drift, tremor, pauses and overshoot (Operator()) in the
  feed and in the insertion stroke; off, the nominal minimum-jerk strokes;
- ``dynamic``: the dynamic arm (1 ms plant, inverse dynamics controller) instead of the kinematic
  one.

Per run the placed implant's entry (platform), apex and axis-angle deviation from the plan and the
insertion depth reached (systems.teleop.insertion.implant_deviation). The error budget: the same
runs (the same random streams: source k of run i draws from ``seeds.rng(seed, k, i)``) with
each source alone and all together, mean / sd / 95th percentile per deviation and site.
Sensitivity curves: the deviation against the tracker's latency and rate (head motion and
tracker on) and against the registration sigma (scaled 0.25-4x).

The procedure: the feed starts ``--approach-mm`` (10 mm) before the target on the fixture's
axis (the exact IK branch nearest the plan's pre-feed configuration; ``full``: the plan's
pre-feed pose), the operator's feed at Operator().speed (10 mm/s), a 0.3 s hold, the insertion
stroke at 20 mm/s (the operator's jitter, pauses and an overshoot into the depth stop), then
2 s finishing by eye at the planned depth. The shortened approach is where this study saves
time: the placement's accuracy is decided at the target and on the insertion; the feed's
clearance along the whole approach is the head-motion study's and the plan's business.

Cost: a run's simulation depends on its random draws only through the sources that draw in the
loop (tracker, head, operator); the ``registration`` and ``dynamic`` rows (and all sources off)
have one simulation each, the registration composed after it per run. The simulations of a site
run in ``--workers`` processes (concurrent.futures).

Not modelled: drilling and insertion forces, bone density and deflection, the drill's wander in
the osteotomy, the arm's joint compliance and kinematic calibration, the scan's own error.
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from implantplan.analyses.case import Site as CaseSite
from implantplan.diagrams import feeding as F
from implantplan.diagrams.teleop import TeleopCase, build_teleop, final_pose
from implantplan.systems import seeds
from implantplan.systems.errors import InputError
from implantplan.systems.frames import invert
from implantplan.systems.placement.exact_clearance import registration_errors
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.teleop.head_motion import HeadMotion
from implantplan.systems.teleop.insertion import (
    PlannedImplant,
    append_stroke,
    implant_deviation,
    insertion_fixture,
    planned_insertion,
    tz,
)
from implantplan.systems.teleop.master_device import Operator, scripted_feed
from implantplan.systems.teleop.tracker import TrackerParams
from implantplan.systems.validate import choice

SOURCES = ("registration", "tracker", "head", "operator", "dynamic")
REGISTRATION, TRACKER, HEAD, OPERATOR, DYNAMIC = range(len(SOURCES))
IN_LOOP = ("tracker", "head", "operator")  # the sources that draw inside the simulation
HEAD_PROFILES = ("breathing", "swallow", "drift")
DEVIATIONS = ("entry", "apex", "angle")
MAX_RUNS = 10_000
HOLD_SECONDS = 0.3  # the operator's pause at the target before inserting
FINISH_SECONDS = F.FINISH_SECONDS  # after the script: the operator finishing by eye
INSERTION_SPEED = 0.02  # m/s: the insertion stroke's mean speed (module notes)
APPROACH_MM = 10.0  # default --approach-mm: the feed's last 10 mm (module notes)
MAX_APPROACH_MM = 100.0
# m: the case file's default placed implant (its one default: analyses.case.Site)
PLACED_LENGTH = CaseSite.__dataclass_fields__["placed_length"].default_factory()
MAX_WORKERS = 64
IDEAL_CAMERA = TrackerParams(rate=60.0, latency=0.0, noise_position=0.0, noise_angle=0.0,
                             predict_samples=0)
NOMINAL_OPERATOR = Operator(drift=0.0, tremor=0.0, pauses_per_feed=0.0, overshoot=(0.0, 0.0))
LATENCIES_MS = (0.0, 20.0, 50.0, 100.0)
RATES_HZ = (30.0, 45.0, 60.0)
REGISTRATION_SCALES = (0.25, 0.5, 1.0, 2.0, 4.0)
# the clinical figures of the issue (mean entry mm, apex mm, angle deg)
CLINICAL = {
    "Yomi (haptic robot)": (1.04, 0.95, 2.56),
    "autonomous robots (pooled, 299 implants)": (0.60, 0.63, 1.24),
    "in-vitro robot": (0.58, 0.69, 1.08),
    "freehand": ("1.3-2.8", "2.1-2.9", "6.9-9.9"),
}


def defaults() -> dict:
    """Each source's default magnitude (SI), as the run uses it (docs/measurements.md cites)."""
    trk, op = TrackerParams(), Operator()
    from implantplan.systems.safety import SafetySpec

    spec = SafetySpec()
    return {
        "registration": {"sigma_translation": spec.registration_sigma_translation,
                         "sigma_rotation": spec.registration_sigma_rotation,
                         "from": "the plan's safety spec (DESIGN.md section 4, Margins)"},
        "tracker": {"rate": trk.rate, "latency": trk.latency,
                    "noise_position": trk.noise_position, "noise_angle": trk.noise_angle,
                    "predict_samples": trk.predict_samples,
                    "from": "systems.teleop.tracker (the issue's 30-60 Hz, 20-50 ms; fast end)"},
        "head": {"profiles": list(HEAD_PROFILES),
                 "from": "systems.teleop.head_motion (seed 001; the head-motion study)"},
        "operator": {"drift": op.drift, "tremor": op.tremor, "speed": op.speed,
                     "pauses_per_feed": op.pauses_per_feed, "overshoot": list(op.overshoot),
                     "from": "systems.teleop.master_device.Operator"},
        "dynamic": {"plant_step": 0.001, "gains": [900.0, 1.0, 60.0],
                    "from": "diagrams.teleop.build_teleop (dynamic mode)"},
    }


@dataclasses.dataclass(frozen=True)
class Site:
    """A site of the study: its feeding case and its planned implant."""

    case: TeleopCase
    plan: PlannedImplant
    scan: object = None  # the opened scan (trimesh, mesh frame), for the exact clearance

    @property
    def label(self) -> str:
        return self.case.label

    @property
    def X_CT_target(self) -> np.ndarray:
        return self.plan.X_CT_target


def parse_sources(text: str) -> tuple[str, ...]:
    """``--sources``: comma-separated names from :data:`SOURCES` (``all``: every one)."""
    names = tuple(s.strip() for s in str(text).split(",") if s.strip())
    if names == ("all",):
        return SOURCES
    if not names:
        raise InputError("--sources", f"expected names from {', '.join(SOURCES)} (or all)")
    for n in names:
        choice(n, "--sources", SOURCES)
    if len(set(names)) != len(names):
        raise InputError("--sources", f"expected each source once, got {','.join(names)}")
    return tuple(s for s in SOURCES if s in names)


def check_runs(runs: int, field: str = "--runs") -> None:
    if not isinstance(runs, int | np.integer) or runs < 1 or runs > MAX_RUNS:
        raise InputError(field, f"expected an integer in 1..{MAX_RUNS}, got {runs}")


def parse_approach(text) -> float | None:
    """``--approach-mm``: ``full`` (None: from the plan's pre-feed pose) or a length in mm,
    0 < mm <= MAX_APPROACH_MM; returns m."""
    if str(text).strip().lower() == "full":
        return None
    try:
        mm = float(text)
    except ValueError:
        mm = float("nan")
    if not (0.0 < mm <= MAX_APPROACH_MM):
        raise InputError("--approach-mm", f"expected full or a length in mm in (0, "
                         f"{MAX_APPROACH_MM:g}], got {text!r}")
    return mm * 1e-3


def sites_of(*, plan=None, approach: float | None = None, progress=None) -> list[Site]:
    """The study's sites: of the plan folder ``plan`` or of the bundled default case, each
    feed starting ``approach`` m before its target (:func:`approach_case`; None: the plan's
    pre-feed pose)."""
    from implantplan.analyses.live_setup import load_plan

    if plan is not None:
        from implantplan.analyses.live_setup import opened_scan

        sp = load_plan(plan, field="--plan", reference=False)
        cases = [sp.teleop_case(k) for k in range(len(sp.names))]
        d_T = [float(s["placement"]["d_T"]) for s in sp.plan["sites"]]
        # a plan written before the placed implant had a length: the case file's default
        length = [float(s.get("placed_implant_length", PLACED_LENGTH)) for s in sp.plan["sites"]]
        scan = opened_scan(sp)
    else:  # planned as implantplan plan does (scan_reference.default_case_sites)
        from implantplan.analyses import pipeline
        from implantplan.analyses.case import default_case_path, load_case

        if progress is not None:
            progress.say("planning the bundled default case (scan, sites 36 and 46)")
        case = load_case(default_case_path())
        fit = pipeline.fit_stage(case)
        placements = pipeline.placement_stage(case, fit)
        cases = pipeline.teleop_cases(case, fit, placements,
                                      pipeline.robot_stage(case, placements))
        d_T = [p.d_T for p in placements]
        length = [site.placed_length for site in case.sites]
        scan = fit.opened
    out = []
    for tc, d, L in zip(cases, d_T, length, strict=True):
        X_CT = np.linalg.inv(tc.X_WCenter) @ tc.X_WTarget
        out.append(Site(case=approach_case(tc, approach),
                        plan=planned_insertion(X_CT, d, tc.tool, L), scan=scan))
    return out


def approach_case(tc: TeleopCase, approach: float | None) -> TeleopCase:
    """The case whose feed starts ``approach`` m back from the target along the fixture's axis
    (the tool at the target's orientation; the exact IK branch nearest the plan's pre-feed
    configuration), or the plan's own pre-feed start (None)."""
    if approach is None:
        return tc
    D_W = tc.X_WCenter[:3, :3] @ tc.vf.direction
    X_WE = tc.X_WE_target.copy()
    X_WE[:3, 3] += approach * D_W
    res = kin.ik(invert(tc.X_WBase) @ X_WE, limits=tc.limits, X_FT=tc.X_FE)
    if not res.valid.any():
        raise InputError("--approach-mm", f"{tc.label}: no IK branch within the joint limits "
                         f"{approach * 1e3:g} mm before the target; expected a shorter approach")
    q = res.q[res.valid]
    q0 = q[np.argmin(kin.wrapped_distance(q, tc.q_start))]
    return dataclasses.replace(tc, q_start=q0)


def insertion_clearance(site: Site, samples: int = 45) -> dict | None:
    """The exact (FCL) clearance to the opened scan of the instrument without its implant
    (rod, head) along the planned insertion, ``samples`` depths from the target to the planned
    depth: the barrier is released while inserting (systems.teleop.insertion), so this is what
    the insertion does to the tissue around the implant. None without the scan."""
    if site.scan is None:
        return None
    from implantplan.analyses.studies.scan_reference import exact_for

    tool = site.case.tool
    body = dataclasses.replace(tool, shapes=tuple(x for x in tool.shapes if x.name != "implant"))
    exact = exact_for(dataclasses.replace(site.case, instrument=body), site.scan)
    depth = np.linspace(0.0, site.plan.depth, samples)
    X_CT = site.plan.X_CT_target @ np.stack([tz(-d) for d in depth])
    c = exact(site.case.fpsm.X_WC @ X_CT)
    free = depth[: int(np.argmax(c < 0))] if np.any(c < 0) else depth
    return {"depth_m": depth.tolist(), "clearance_m": c.tolist(), "min_m": float(c.min()),
            "free_to_depth_m": float(free[-1]) if free.size else 0.0,
            "parts": [x.name for x in body.shapes],
            "reference": "FCL against the opened scan (faces below the mouth opening)"}


def procedure(site: Site, i: int, seed: int, *, operator: bool):
    """(master motion, insertion start s, duration s) of run ``i``: the feed from the case's
    start to the target and the insertion stroke to the planned depth (module notes)."""
    tc = site.case
    start = tc.X_WE(tc.q_start)[:3, 3]
    target = tc.X_WTarget[:3, 3]
    final = tc.X_WCenter[:3, :3] @ site.plan.X_CT_final[:3, 3] + tc.X_WCenter[:3, 3]
    op = Operator() if operator else NOMINAL_OPERATOR
    feed = scripted_feed(start, target, seed=seeds.rng(seed, OPERATOR, i, 0), operator=op,
                         settle=0.0)
    op = dataclasses.replace(op, speed=INSERTION_SPEED)
    stroke = scripted_feed(target, final, seed=seeds.rng(seed, OPERATOR, i, 1), operator=op,
                           settle=0.0)
    motion = append_stroke(feed, stroke, HOLD_SECONDS)
    return motion, feed.duration + HOLD_SECONDS, motion.duration + FINISH_SECONDS


def run_key(sources, i: int, tracker: TrackerParams | None = None) -> tuple:
    """What a run's simulation depends on: (in-loop sources, mode, run or -1, camera)."""
    loop = tuple(s for s in sources if s in IN_LOOP)
    mode = "dynamic" if "dynamic" in sources else "kinematic"
    trk = None
    if "tracker" in loop or "head" in loop:
        trk = (tracker or TrackerParams()) if "tracker" in loop else IDEAL_CAMERA
    return loop, mode, i if loop else -1, trk


class Simulations:
    """The simulated placements of a site, cached by what changes them (:func:`run_key`).

    One diagram per (mode, camera settings but the seed): the master motion, the head motion
    and the tracker's noise seed are parameters of a run's context
    (diagrams.teleop.final_pose), so a worker builds each diagram once and replays every run
    of the row on it."""

    def __init__(self, site: Site, seed: int):
        self.site, self.seed = site, seed
        self._fixture = insertion_fixture(site.case.vf, site.plan)
        self._diagrams: dict = {}
        self.cache: dict = {}
        self.sim_seconds = 0.0
        self.wall_seconds = 0.0

    def _diagram(self, mode: str, camera: TrackerParams | None):
        """The diagram of ``mode`` (with the head and ``camera`` when given: its seed and the
        head's motion are set per run); only the joints logged."""
        key = (mode, None if camera is None else dataclasses.replace(camera, seed=0))
        if key not in self._diagrams:
            head = {}
            if camera is not None:
                head = {"head_motion": HeadMotion.make("still"), "tracker": key[1]}
            self._diagrams[key] = build_teleop(self.site.case, mode=mode,
                                               insertion=self._fixture, logs=False, **head)
        return self._diagrams[key]

    def simulate(self, key: tuple) -> tuple[np.ndarray, float, float]:
        """(placed Tool pose (4, 4) in the true moving head's Center, registration not yet
        applied; simulated s; wall s) of the run ``key``."""
        loop, mode, i, trk = key
        motion, t_ins, T = procedure(self.site, max(i, 0), self.seed,
                                     operator="operator" in loop)
        tc = self.site.case
        head = {}
        if trk is not None:
            if "head" in loop:
                hm = HeadMotion.make(HEAD_PROFILES[i % len(HEAD_PROFILES)],
                                     seed=seeds.seed(self.seed, HEAD, i),
                                     pivot=tc.X_WCenter[:3, 3])
            else:
                hm = HeadMotion.make("still")
            head = {"head_motion": hm, "tracker_seed": seeds.seed(self.seed, TRACKER, max(i, 0))}
        run = final_pose(self._diagram(mode, trk), T, motion=motion, insertion_start=t_ins,
                         **head)
        return run.X_CT, run.sim_seconds, run.wall_seconds

    def fill(self, keys, pool=None, index: int = 0, progress=None) -> None:
        """Simulate the ``keys`` not cached yet (in ``pool``'s processes when given)."""
        todo = [k for k in dict.fromkeys(keys) if k not in self.cache]
        todo.sort(key=lambda k: (k[1] != "dynamic", k[3] is None))  # the slowest first
        if pool is None:
            results = map(self.simulate, todo)
        else:
            results = pool.map(_simulate_task, [(index, k) for k in todo])
        for j, (k, (X, sim_s, wall_s)) in enumerate(zip(todo, results, strict=True)):
            if progress is not None:
                progress.step(j, len(todo), f"simulations of {self.site.label}")
            self.cache[k] = X
            self.sim_seconds += sim_s
            self.wall_seconds += wall_s

    @property
    def simulations(self) -> int:
        return len(self.cache)


_WORKER: dict = {}


def _init_worker(sites, seed) -> None:
    _WORKER["sims"] = [Simulations(s, seed) for s in sites]


def _simulate_task(task):
    index, key = task
    return _WORKER["sims"][index].simulate(key)


def registration_draw(seed: int, i: int, spec, scale: float = 1.0) -> np.ndarray:
    """E^-1 of run ``i`` (the Monte Carlo's sampler on the stream (REGISTRATION, i)), its
    sigmas scaled by ``scale``."""
    spec = dataclasses.replace(
        spec, registration_sigma_translation=scale * spec.registration_sigma_translation,
        registration_sigma_rotation=scale * spec.registration_sigma_rotation)
    return registration_errors(spec, seeds.rng(seed, REGISTRATION, i), 1)[0]


def row_keys(sources, runs: int, tracker=None) -> list[tuple]:
    return [run_key(sources, i, tracker) for i in range(runs)]


def deviations(sim: Simulations, sources, runs: int, *, tracker=None,
               registration_scale: float = 1.0, pool=None, index: int = 0) -> dict:
    """Per-run deviation arrays (m, rad) of ``runs`` runs with ``sources``; the depth reached
    is the robot's own (in the registered frame)."""
    keys = row_keys(sources, runs, tracker)
    sim.fill(keys, pool, index)
    X = np.array([sim.cache[k] for k in keys])
    depth = implant_deviation(X, sim.site.plan)["depth_reached"]
    if "registration" in sources:
        spec = sim.site.case.safety
        E_inv = np.array([registration_draw(sim.seed, i, spec, registration_scale)
                          for i in range(runs)])
        X = E_inv @ X
    out = implant_deviation(X, sim.site.plan)
    out["depth_reached"] = depth
    return out


def summarize(dev: dict) -> dict:
    """mean, sd, p95 per deviation (mm and deg) and the depth reached (mm, min and mean)."""
    out = {}
    for k in DEVIATIONS:
        v = np.asarray(dev[k]) * (np.rad2deg(1.0) if k == "angle" else 1e3)
        out[k] = {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if v.size > 1 else 0.0,
                  "p95": float(np.percentile(v, 95))}
    d = np.asarray(dev["depth_reached"]) * 1e3
    out["depth_reached_mm"] = {"min": float(d.min()), "mean": float(d.mean())}
    return out


def budget_rows(sources) -> dict:
    """The budget's rows: all sources off, each selected source alone, all together."""
    rows = {"none": ()}
    rows.update({s: (s,) for s in sources})
    rows["all"] = tuple(sources)
    return rows


def sensitivity_rows(runs: int) -> list[tuple]:
    """[(curve, x, sources, tracker, registration scale)] of the sensitivity curves."""
    base = TrackerParams()
    out = [("tracker_latency_ms", ms, ("tracker", "head"),
            dataclasses.replace(base, latency=ms * 1e-3), 1.0) for ms in LATENCIES_MS]
    out += [("tracker_rate_hz", hz, ("tracker", "head"), dataclasses.replace(base, rate=hz), 1.0)
            for hz in RATES_HZ]
    out += [("registration_sigma_scale", k, ("registration",), None, k)
            for k in REGISTRATION_SCALES]
    return out


def site_study(sim: Simulations, sources, runs: int, sensitivity_runs: int, *, pool=None,
               index: int = 0, progress=None) -> dict:
    """A site's budget and sensitivity curves (every simulation first, in ``pool``)."""
    rows = budget_rows(sources)
    sens = sensitivity_rows(sensitivity_runs) if sensitivity_runs else []
    keys = [k for srcs in rows.values() for k in row_keys(srcs, runs)]
    keys += [k for _, _, srcs, trk, _ in sens for k in row_keys(srcs, sensitivity_runs, trk)]
    sim.fill(keys, pool, index, progress)
    budget = {}
    for name, srcs in rows.items():
        dev = deviations(sim, srcs, runs)
        budget[name] = {"sources": list(srcs), **summarize(dev),
                        "runs": {k: np.asarray(v).tolist() for k, v in dev.items()}}
        if progress is not None:
            r = budget[name]
            progress.say(f"{sim.site.label} {name}: entry {r['entry']['mean']:.3f} mm, apex "
                         f"{r['apex']['mean']:.3f} mm, angle {r['angle']['mean']:.3f} deg "
                         f"(depth reached >= {r['depth_reached_mm']['min']:.1f} of "
                         f"{sim.site.plan.depth * 1e3:.1f} mm)")
    out = {"budget": budget}
    if sens:
        spec = sim.site.case.safety
        curves = {
            "tracker_latency_ms": {"x": [], "rate_hz": TrackerParams().rate, "rows": []},
            "tracker_rate_hz": {"x": [], "latency_ms": TrackerParams().latency * 1e3,
                                "rows": []},
            "registration_sigma_scale": {
                "x": [], "sigma_mm": spec.registration_sigma_translation * 1e3,
                "sigma_deg": float(np.rad2deg(spec.registration_sigma_rotation)), "rows": []},
        }
        for curve, x, srcs, trk, scale in sens:
            dev = deviations(sim, srcs, sensitivity_runs, tracker=trk, registration_scale=scale)
            curves[curve]["x"].append(x)
            curves[curve]["rows"].append(summarize(dev))
        out["sensitivity"] = {"runs": sensitivity_runs, "sources": {
            "tracker_latency_ms": ["tracker", "head"], "tracker_rate_hz": ["tracker", "head"],
            "registration_sigma_scale": ["registration"]}, **curves}
    return out


def accuracy_study(sites, *, sources=SOURCES, runs: int = 200, seed: int = 0,
                   sensitivity_runs: int = 10, workers: int = 1, progress=None) -> dict:
    """The study over ``sites`` (module notes); returns the JSON dict."""
    check_runs(runs)
    if sensitivity_runs:
        check_runs(sensitivity_runs, "--sensitivity-runs")
    t0 = time.perf_counter()
    out = {"runs": runs, "seed": seed, "sources": list(sources), "defaults": defaults(),
           "approach": None, "deviations": {"entry": "mm", "apex": "mm", "angle": "deg"},
           "sites": {}}
    pool = None
    if workers > 1:
        pool = ProcessPoolExecutor(max_workers=workers, initializer=_init_worker,
                                   initargs=(list(sites), seed))
    try:
        for index, site in enumerate(sites):
            sim = Simulations(site, seed)
            entry = {"planned": {"depth_m": site.plan.depth,
                                 "platform_C": site.plan.platform.tolist(),
                                 "apex_C": site.plan.apex.tolist(),
                                 "axis_C": site.plan.axis.tolist()},
                     **site_study(sim, sources, runs, sensitivity_runs, pool=pool, index=index,
                                  progress=progress)}
            entry["insertion_clearance"] = insertion_clearance(site)
            entry["simulations"] = sim.simulations
            entry["sim_seconds"] = sim.sim_seconds
            entry["wall_seconds_in_simulation"] = sim.wall_seconds
            out["sites"][site.label] = entry
    finally:
        if pool is not None:
            pool.shutdown()
    out["wall_seconds"] = time.perf_counter() - t0
    return out


def table(study: dict) -> list[dict]:
    """The budget as flat rows (site, row, sources, mean/sd/p95 of each deviation; mm, deg),
    the rows the JSON's ``table`` holds and the command prints."""
    rows = []
    for label, entry in study["sites"].items():
        for name, r in entry["budget"].items():
            rows.append({"site": label, "row": name, "sources": ",".join(r["sources"]) or "-",
                         **{f"{k}_{s}": r[k][s] for k in DEVIATIONS for s in ("mean", "sd", "p95")},
                         "depth_reached_min_mm": r["depth_reached_mm"]["min"],
                         "depth_planned_mm": entry["planned"]["depth_m"] * 1e3})
    return rows


def _check_out(out: Path) -> None:
    """--out: a new folder, an empty one or a previous study's (it holds accuracy.json)."""
    if out.exists() and (not out.is_dir() or (any(out.iterdir())
                                              and not (out / "accuracy.json").is_file())):
        raise InputError("--out", f"{out} holds other files; expected a new or empty folder "
                         "(or a previous accuracy study's)")


def cmd_accuracy(args) -> int:
    from implantplan.analyses.figures.accuracy import plot_budget, plot_sensitivity
    from implantplan.analyses.progress import Progress
    from implantplan.systems.files import write_json

    progress = Progress("analyze accuracy", quiet=args.quiet)
    # every flag is checked before any planning or simulation
    sources = parse_sources(args.sources)
    check_runs(args.runs)
    if args.sensitivity_runs != 0:
        check_runs(args.sensitivity_runs, "--sensitivity-runs")
    approach = parse_approach(args.approach_mm)
    if not 1 <= args.workers <= MAX_WORKERS:
        raise InputError("--workers", f"expected an integer in 1..{MAX_WORKERS}, "
                         f"got {args.workers}")
    out = Path(args.out)
    _check_out(out)
    if args.plan is not None and not (Path(args.plan) / "plan.json").is_file():
        raise InputError("--plan", f"{args.plan}: expected a plan folder with a plan.json")
    sites = sites_of(plan=args.plan, approach=approach, progress=progress)
    study = accuracy_study(sites, sources=sources, runs=args.runs, seed=args.seed,
                           sensitivity_runs=args.sensitivity_runs, workers=args.workers,
                           progress=progress)
    study["plan"] = None if args.plan is None else str(args.plan)
    study["approach"] = approach
    study["table"] = table(study)
    study["clinical"] = {k: dict(zip(("entry_mm", "apex_mm", "angle_deg"), v, strict=True))
                         for k, v in CLINICAL.items()}
    out.mkdir(parents=True, exist_ok=True)
    figs = plot_budget(study, out / "figures")
    if args.sensitivity_runs:
        figs += plot_sensitivity(study, out / "figures")
    study["figures"] = [str(p.relative_to(out)) for p in figs]
    write_json(out / "accuracy.json", study, kind="accuracy")
    for r in study["table"]:
        print(f"{r['site']:>8} {r['row']:>12}: entry {r['entry_mean']:.3f} +- {r['entry_sd']:.3f}"
              f" (p95 {r['entry_p95']:.3f}) mm, apex {r['apex_mean']:.3f} +- {r['apex_sd']:.3f} "
              f"(p95 {r['apex_p95']:.3f}) mm, angle {r['angle_mean']:.3f} +- {r['angle_sd']:.3f} "
              f"(p95 {r['angle_p95']:.3f}) deg; depth reached >= {r['depth_reached_min_mm']:.1f}"
              f" of {r['depth_planned_mm']:.1f} mm")
    for label, entry in study["sites"].items():
        c = entry["insertion_clearance"]
        if c is not None:
            print(f"{label} insertion: the {' and '.join(c['parts'])} stay clear of the scan to "
                  f"{c['free_to_depth_m'] * 1e3:.1f} of {entry['planned']['depth_m'] * 1e3:.1f} "
                  f"mm (exact clearance min {c['min_m'] * 1e3:.2f} mm; the barrier is released "
                  "while inserting)")
    print(f"wrote {out / 'accuracy.json'} and {len(figs)} figures in {study['wall_seconds']:.0f} s")
    return 0


def register_analysis(sub) -> None:
    """Add ``accuracy`` to the ``analyze`` subcommands (analyses.simulate)."""
    p = sub.add_parser("accuracy", help="simulated implant accuracy (entry, apex, angle) and its "
                       "error budget per source")
    p.add_argument("--plan", type=Path, default=None,
                   help="a plan folder (implantplan plan or demo) instead of planning the bundled "
                   "default case")
    p.add_argument("--runs", type=int, default=200, help="seeded runs per row (default 200)")
    p.add_argument("--sources", default="all",
                   help=f"comma-separated error sources from {','.join(SOURCES)} (default all)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    p.add_argument("--sensitivity-runs", type=int, default=10,
                   help="runs per point of the sensitivity curves (0: none; default 10)")
    p.add_argument("--approach-mm", default=str(APPROACH_MM),
                   help="each feed starts this far (mm) before the target along the fixture's "
                   "axis, or full: from the plan's pre-feed pose (default 10)")
    p.add_argument("--workers", type=int, default=2,
                   help="processes simulating runs in parallel (default 2)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder (accuracy.json, figures/)")
    p.set_defaults(func=cmd_accuracy)
