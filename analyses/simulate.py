"""Teleoperated-feeding experiments of seed 001 ("Experimental validation") on the Drake diagram.

Commands::

    implantplan simulate feeding [--plan placement.json | --scenario lying|sitting]
        [--robot-placement placement.json] [--runs K] [--seed S] [--mode kinematic|dynamic]
        [--meshcat-html FILE] --out DIR
    implantplan simulate circle  [same case options] [--realizations R] --out DIR
    implantplan analyze layouts  [same case options] [--random N] [--runs K] --out DIR

**The case.** The instrument side (FPSM, feeding target X_CT, virtual fixture) comes from
``--plan`` (an ``implantplan instrument place`` result: its ``X_CT``, ``vf``, ``rod_radius``,
``implant_length`` and the FPSM it names in ``fpsm`` or ``inputs.fpsm``, a file or the model).
Without a plan the default case is seed 000's cylinder check (Sec. 5.3): a cylinder FPSM of
radius 50 mm from z = 0 to 100 mm (opening at 100 mm), hole (0, -50, 50) mm, axis +y, rod radius
6 mm, d12 31 mm, placed on the fly by systems.placement.planner (d_T = 62.5 mm, theta_T = 0). The
room
comes from the MOPRP scenario (``--scenario``, default lying): Oral (= the feeding target, seed
000's Tool frame) at the scenario's X_WO, so Center sits at X_WO X_CT^-1. The base layout comes
from ``--robot-placement`` (an ``implantplan robot place`` result: ``selected.base_xyz`` and
``selected.branch``); without it we pick a stand-in for MOPRP's choice: the knee point
(systems.robot.moprp.knee_point) of the non-dominated set of 300 random feasible bases.

The arm starts at the pre-feed pose (the TCP backed out along the rod by the scenario's feed
length) on the layout's branch, and the scripted operator (systems.teleop.master_device) feeds it to
the target through the virtual fixture.

**Experiments.** (a) feeding: K feeds with independent operator randomness; (b) error mapping: a
circle of radius 25 mm at 10 mm/s about the target with injected joint error; (c) GII over 100
poses about Oral (systems.robot.moprp.gii); (d) the selected layout against N random feasible ones
on
(a)-(c): bars and distributions (seed 001 Figs. 11, 13, 14) and ranks. The runners of (a) and
(b), the joint error model and the departures are diagrams.feeding's; the figures are
analyses.figures.simulation's.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from implantplan.analyses.figures.simulation import plot_circle, plot_feeding, plot_layouts
from implantplan.analyses.progress import Progress
from implantplan.analyses.studies.accuracy import register_analysis as register_accuracy_analysis
from implantplan.analyses.studies.head_motion import register_analysis as register_head_analysis
from implantplan.analyses.studies.moprp_fidelity import gii_units, register_analysis
from implantplan.diagrams.feeding import (  # the case and the runs (bench_teleop reads them here)
    FINISH_SECONDS,  # noqa: F401
    Instrument,
    default_instrument,
    knee_layout,
    layout_configurations,
    load_scenario,
    make_case,
    run_circle,
    run_feeding,
)
from implantplan.systems import actuator, seeds, validate
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.files import read_json, write_json, write_text_atomic
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import rotation_angle
from implantplan.systems.placement.fixture import VirtualFixture
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp
from implantplan.systems.teleop.master_device import Operator

# --------------------------------------------------------------------------------------------
# The case
# --------------------------------------------------------------------------------------------


def instrument_from_plan(path) -> Instrument:
    """Read an ``instrument place`` result (kind "placement") and the FPSM file it names."""
    path = Path(path)
    data = read_json(path, kind="placement", field="--plan")
    for key in ("X_CT", "vf"):
        if data.get(key) is None:
            raise InputError("--plan", f"{path}: missing {key!r}")
    ref = data.get("fpsm") or (data.get("inputs") or {}).get("fpsm")
    if isinstance(ref, dict):
        fpsm = Fpsm.from_dict(ref)
    elif isinstance(ref, str):
        fpsm_path = Path(ref)
        if not fpsm_path.is_absolute() and not fpsm_path.exists():
            fpsm_path = path.parent / fpsm_path
        fpsm = Fpsm.load(fpsm_path, field="--plan fpsm")
    else:
        raise InputError("--plan", f"{path}: expected 'fpsm' or 'inputs.fpsm' (file or model)")
    X_CT = validate.pose(data["X_CT"], f"--plan {path}: X_CT")
    return Instrument(
        fpsm,
        X_CT,
        VirtualFixture.from_dict(data["vf"]),
        float(data.get("rod_radius", actuator.ROD_RADIUS)),
        float(data.get("implant_length", actuator.IMPLANT_LENGTH)),
        str(path),
    )


def select_layout(sc, *, seed: int = 0, robot_placement=None, candidates: int = 300):
    """(base_xyz in Oral, branch, source): from a robot placement file, or the knee point of the
    non-dominated set of ``candidates`` random feasible bases."""
    if robot_placement is not None:
        data = read_json(robot_placement, kind="robot_placement", field="--robot-placement")
        sel = data.get("selected") or {}
        if "base_xyz" not in sel or "branch" not in sel:
            raise InputError("--robot-placement", "expected selected.base_xyz and .branch")
        return np.asarray(sel["base_xyz"], dtype=float), int(sel["branch"]), str(robot_placement)
    return knee_layout(sc, seed=seed, candidates=candidates)


# --------------------------------------------------------------------------------------------
# (a) feeding
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# (b) error mapping: the circle
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# (d) layouts
# --------------------------------------------------------------------------------------------


def rank_of_first(values, *, higher_is_better=False) -> int:
    """1-based rank of entry 0 among ``values`` (ties count in its favour)."""
    v = np.asarray(values, dtype=float)
    better = v[1:] > v[0] if higher_is_better else v[1:] < v[0]
    return int(1 + np.sum(better))


def analyze_layouts(
    scenario: str,
    inst: Instrument,
    *,
    random_layouts: int = 20,
    runs: int = 10,
    seed: int = 0,
    robot_placement=None,
    realizations: int = 10,
    operator: Operator | None = None,
    progress: Progress | None = None,
) -> dict:
    """The selected layout against ``random_layouts`` random feasible ones on (a)-(c)."""
    sc, sc_plant = load_scenario(scenario)
    scene = _scene_name(sc)
    xyz_sel, b_sel, source = select_layout(sc, seed=seed, robot_placement=robot_placement)
    rng = seeds.rng(seed, 1)
    xyz_r, _ = moprp.random_feasible(sc, 4 * random_layouts, rng)
    ev = moprp.evaluate_bases(xyz_r, sc, rng)
    layouts = [("win", xyz_sel, b_sel)]
    for x, b in zip(xyz_r, ev.branch, strict=True):
        if len(layouts) > random_layouts:
            break
        if b >= 0 and layout_configurations(sc_plant, x, int(b)) is not None:
            if run_circle(sc_plant, x, int(b), realizations=1, seed=seed) is not None:
                layouts.append((str(len(layouts)), x, int(b)))
    entries = []
    for i, (label, x, b) in enumerate(layouts):
        case = make_case(scene, sc_plant, x, b, inst, label=label)
        feed = run_feeding(case, runs=runs, seed=seed, operator=operator)
        circle = run_circle(sc_plant, x, b, realizations=realizations, seed=seed)
        g = moprp.gii(x, b, sc_plant, np.random.default_rng(seed), n=100)
        g_units = gii_units(x, b, sc_plant, np.random.default_rng(seed))
        r_feed = kin.ik(moprp.feed_poses(x, sc_plant.feed_length, sc_plant.feed_samples),
                        limits=sc_plant.limits, X_FT=sc_plant.X_FT)
        q_feed = np.where(r_feed.valid[:, b, None], r_feed.q[:, b], np.nan)
        travel = np.array([r["joint_travel"] for r in feed["runs"]])
        entries.append(
            {
                "label": label,
                "base_xyz": x,
                "branch": b,
                "joint_travel_runs": travel,
                "joint_travel_mean": float(travel.mean()),
                "path_error_realizations": None if circle is None else circle["per_realization"],
                "path_error_mean": np.nan if circle is None else circle["path_error_mean"],
                "gii": g["gii"],
                "gii_mm_deg": g_units["mm/deg"],
                "gii_reached": g["reached"],
                # the index MOPRP minimizes: travel along the ideal straight feed (no operator)
                "joint_variation_index": float(np.abs(np.diff(q_feed, axis=0)).sum()),
                "max_vf_violation": max(r["max_vf_violation"] for r in feed["runs"]),
                "collision_alarm": any(r["collision_alarm"] for r in feed["runs"]),
                "realtime_factor": feed["realtime_factor"],
            }
        )
        if progress is not None:
            progress.step(i, len(layouts), f"layout {label}")
    ranks = {
        "joint_travel": rank_of_first([e["joint_travel_mean"] for e in entries]),
        "path_error": rank_of_first([e["path_error_mean"] for e in entries]),
        "gii": rank_of_first([e["gii"] for e in entries], higher_is_better=True),
        "gii_mm_deg": rank_of_first([e["gii_mm_deg"] for e in entries], higher_is_better=True),
        "joint_variation_index": rank_of_first([e["joint_variation_index"] for e in entries]),
    }
    return {
        "scenario": scenario,
        "instrument": inst.source,
        "selected_source": source,
        "layouts": entries,
        "ranks": ranks,
        "of": len(entries),
        "runs_per_layout": runs,
        "operator": dataclasses.asdict(operator or Operator()),
        "seed": seed,
    }


# --------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------


def _case_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plan", type=Path, help="instrument placement JSON (instrument place)")
    p.add_argument(
        "--scenario", default="lying", help="MOPRP scenario: lying, sitting (default lying)"
    )
    p.add_argument(
        "--robot-placement", type=Path, help="robot placement JSON (robot place) for the layout"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def _operator_options(p: argparse.ArgumentParser) -> None:
    d = Operator()
    p.add_argument("--tremor-mm", type=float, default=1000 * d.tremor,
                   help=f"operator tremor amplitude, ~9 Hz (default {1000 * d.tremor:g} mm)")
    p.add_argument("--drift-mm", type=float, default=1000 * d.drift,
                   help=f"operator lateral drift RMS (default {1000 * d.drift:g} mm)")


def _operator(args) -> Operator:
    return dataclasses.replace(Operator(), tremor=args.tremor_mm / 1000, drift=args.drift_mm / 1000)


def register(subparsers) -> None:
    sim = subparsers.add_parser("simulate", help="teleoperated-feeding simulations (seed 001)")
    sub = sim.add_subparsers(dest="simulate_command", required=True, metavar="EXPERIMENT")
    p = sub.add_parser("feeding", help="K scripted feeds through the virtual fixture")
    _case_options(p)
    p.add_argument("--runs", type=int, default=10, help="feeds (default 10, the paper's)")
    p.add_argument("--mode", default="kinematic", choices=("kinematic", "dynamic"),
                   help="kinematic: the arm follows diff IK exactly (default); dynamic: 1 ms plant")
    p.add_argument("--meshcat-html", type=Path, help="write a static HTML replay of run 0")
    p.add_argument("--csv", type=Path, help="replay a studio recording (MasterDevice CSV with "
                   "its <name>.json case beside it) instead of scripted feeds")
    p.add_argument("--head-motion", help="the awake patient: breathing|swallow|startle|drift|"
                   "turn or a CSV of head displacements (t_s,x_m,y_m,z_m,rx_rad,ry_rad,"
                   "rz_rad); seeded by --seed; kinematic or dynamic mode; the arm follows the "
                   "tracked mouth")
    _operator_options(p)
    p.set_defaults(func=cmd_feeding)
    p = sub.add_parser("circle", help="circle r 25 mm at 10 mm/s with injected joint error")
    _case_options(p)
    p.add_argument("--realizations", type=int, default=10, help="joint error draws (default 10)")
    p.set_defaults(func=cmd_circle)

    ana = subparsers.add_parser("analyze", help="offline analyses of layouts")
    sub = ana.add_subparsers(dest="analyze_command", required=True, metavar="ANALYSIS")
    p = sub.add_parser("layouts", help="selected layout vs random feasible ones (Figs. 11, 13, 14)")
    _case_options(p)
    p.add_argument("--random", type=int, default=20, help="random layouts (default 20)")
    p.add_argument("--runs", type=int, default=10, help="feeds per layout (default 10)")
    p.add_argument("--realizations", type=int, default=10, help="joint error draws (default 10)")
    _operator_options(p)
    p.set_defaults(func=cmd_layouts)
    register_analysis(sub)
    register_head_analysis(sub)
    register_accuracy_analysis(sub)


def _check_count(value: int, name: str, lo: int = 1) -> None:
    if value < lo:
        raise InputError(name, f"expected an integer >= {lo}, got {value}")


def _setup(args, *, instrument: bool = True):
    """(instrument, scenario, scenario with the plant's TCP); without ``instrument`` (the circle
    runs the arm alone) a ``--plan`` is still read and checked, and no default one is placed
    (None)."""
    if args.scenario not in moprp.BUNDLED and not Path(args.scenario).is_file():
        raise InputError(
            "--scenario", f"expected lying, sitting or a YAML file, got {args.scenario!r}"
        )
    sc, sc_plant = load_scenario(args.scenario)
    inst = None
    if args.plan:
        inst = instrument_from_plan(args.plan)
    elif instrument:
        inst = default_instrument(args.seed)
    return inst, sc, sc_plant


def _scene_name(sc) -> str:
    return sc.posture if sc.posture in ("lying", "sitting") else "arm"


def _layout(args, progress, *, instrument: bool = True):
    """The case of ``args`` and its layout: (inst, sc, sc_plant, xyz, branch, source)."""
    inst, sc, sc_plant = _setup(args, instrument=instrument)
    xyz, branch, source = select_layout(sc, seed=args.seed, robot_placement=args.robot_placement)
    progress.say(f"layout {np.round(1000 * xyz).tolist()} mm branch {branch} ({source})")
    return inst, sc, sc_plant, xyz, branch, source


def cmd_replay(args) -> int:
    """``simulate feeding --csv FILE``: one recorded run replayed on its case."""
    from implantplan.analyses.live_setup import recorded_case, replay

    case, motion, info = recorded_case(args.csv)
    run = replay(case, motion)
    end = case.X_WE(run.q[-1])
    recorded = np.asarray(info.get("end_X_WE", np.full((4, 4), np.nan)), dtype=float)
    data = {"csv": str(args.csv), "site": info["site"], "base_xyz": info["base_xyz"],
            "duration_s": motion.duration, "end_X_WE": end,
            "end_difference_m": float(np.linalg.norm(end[:3, 3] - recorded[:3, 3])),
            "end_angle_difference_rad": float(rotation_angle(end[:3, :3] @ recorded[:3, :3].T)),
            "to_target_m": float(np.linalg.norm(end[:3, 3] - case.X_WTarget[:3, 3])),
            "max_vf_violation": float(np.max(run.violation)),
            "min_d_safe": float(np.min(run.min_d_safe)),
            "collision_alarm": bool(np.any(run.alarm)),
            "realtime_factor": run.sim_seconds / run.wall_seconds}
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "feeding.json", data, kind="feeding_replay")
    print(f"replay: {motion.duration:.2f} s, end {np.round(1e3 * end[:3, 3], 3).tolist()} mm, "
          f"{1e3 * data['end_difference_m']:.4f} mm and "
          f"{np.rad2deg(data['end_angle_difference_rad']):.4f} deg from the recorded end, "
          f"{1e3 * data['to_target_m']:.2f} mm to the target, alarm {data['collision_alarm']}")
    return 0


def cmd_feeding(args) -> int:
    if args.csv is not None:
        return cmd_replay(args)
    # every flag is checked before the instrument is placed and the layout searched
    _check_count(args.runs, "--runs")
    operator = _operator(args)
    head = None
    if args.head_motion is not None:
        from implantplan.systems.teleop.head_motion import HeadMotion

        if args.mode != "kinematic":
            raise InputError("--head-motion", "expected --mode kinematic with a head motion")
        head = HeadMotion.make(args.head_motion, seed=args.seed)  # checks the flag; made
        # again about the case's head once the layout is known (below)
    progress = Progress("simulate feeding", quiet=args.quiet)
    inst, sc, sc_plant, xyz, branch, source = _layout(args, progress)
    case = make_case(_scene_name(sc), sc_plant, xyz, branch, inst, label="selected")
    if head is not None:
        from implantplan.systems.teleop.head_motion import neck_of

        head = HeadMotion.make(args.head_motion, seed=args.seed, pivot=case.X_WCenter[:3, 3],
                               neck=neck_of(case.X_WCenter))  # about the case's head
    meshcat = None
    if args.meshcat_html is not None:
        from pydrake.geometry import Meshcat

        meshcat = Meshcat()
    t0 = time.perf_counter()
    result = run_feeding(
        case,
        runs=args.runs,
        seed=args.seed,
        mode=args.mode,
        operator=operator,
        meshcat=meshcat,
        progress=progress,
        head_motion=head,
    )
    if meshcat is not None:
        write_text_atomic(args.meshcat_html, meshcat.StaticHtml())
    runs = result["runs"]
    data = {
        "scenario": args.scenario,
        "mode": args.mode,
        "seed": args.seed,
        "instrument": inst.source,
        "layout": {"base_xyz": xyz, "branch": branch, "source": source},
        "X_WBase": case.X_WBase,
        "X_WTarget": case.X_WTarget,
        "operator": dataclasses.asdict(operator),
        "runs": runs,
        "realtime_factor": result["realtime_factor"],
        "head_motion": None if head is None else {"profile": head.profile, "seed": head.seed,
                                                  "params": head.params},
        "summary": {
            "joint_travel_mean": float(np.mean([r["joint_travel"] for r in runs])),
            "joint_travel_std": float(np.std([r["joint_travel"] for r in runs])),
            "max_vf_violation": max(r["max_vf_violation"] for r in runs),
            "min_d_safe": min(r["min_d_safe"] for r in runs),
            "any_alarm": any(r["collision_alarm"] for r in runs),
            "all_reached_target": all(r["reached_target"] for r in runs),
        },
        "wall_seconds_total": time.perf_counter() - t0,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "feeding.json", data, kind="feeding")
    plot_feeding(result, args.out)
    s = data["summary"]
    print(
        f"feeding: {len(runs)} runs, joint travel {s['joint_travel_mean']:.3f} "
        f"+- {s['joint_travel_std']:.3f} rad, max VF violation "
        f"{1000 * s['max_vf_violation']:.3f} mm, min d_safe {1000 * s['min_d_safe']:.1f} mm, "
        f"alarm {s['any_alarm']}, realtime factor {result['realtime_factor']:.1f}x"
    )
    return 0


def cmd_circle(args) -> int:
    _check_count(args.realizations, "--realizations")
    progress = Progress("simulate circle", quiet=args.quiet)
    _, sc, sc_plant, xyz, branch, source = _layout(args, progress, instrument=False)
    result = run_circle(sc_plant, xyz, branch, realizations=args.realizations, seed=args.seed)
    if result is None:
        raise PlanningFailure(f"branch {branch} cannot follow the circle continuously")
    data = {
        "scenario": args.scenario,
        "seed": args.seed,
        "layout": {"base_xyz": xyz, "branch": branch, "source": source},
        "circle": {"radius": 0.025, "speed": 0.010, "plane": "Oral Y-Z"},
        "joint_error_eps": sc_plant.eps,
        **result,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "circle.json", data, kind="circle")
    plot_circle(sc_plant, xyz, branch, result, args.out, seed=args.seed)
    print(
        f"circle: mean path error {1000 * result['path_error_mean']:.4f} mm, max "
        f"{1000 * result['path_error_max']:.4f} mm over {args.realizations} joint error draws"
    )
    return 0


def cmd_layouts(args) -> int:
    _check_count(args.random, "--random")
    _check_count(args.runs, "--runs")
    _check_count(args.realizations, "--realizations")
    operator = _operator(args)
    progress = Progress("analyze layouts", quiet=args.quiet)
    inst, sc, _ = _setup(args)
    result = analyze_layouts(
        args.scenario,
        inst,
        random_layouts=args.random,
        runs=args.runs,
        seed=args.seed,
        robot_placement=args.robot_placement,
        realizations=args.realizations,
        operator=operator,
        progress=progress,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "layouts.json", result, kind="layouts")
    plot_layouts(result, args.out)
    r = result["ranks"]
    n = result["of"]
    print(
        f"layouts: selected ranks joint travel {r['joint_travel']}/{n}, path error "
        f"{r['path_error']}/{n}, GII {r['gii']}/{n}"
    )
    return 0
