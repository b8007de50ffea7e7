"""``implantplan capmap``: build / query capability maps, plan a RASSCMAP setup (seed 004).

Subcommands:

- ``capmap build [--voxel-mm V] [--directions K] [--limits 175|360] [--tool actuator] [--rolls R]
  [--self-collision] [--cell certified|centre] [--workers W] [--scheduler local|tcp://HOST:PORT]
  [--resume] --out map.h5`` (without ``--tool`` the mapped frame is the flange, wrist3_Link; with
  ``--tool actuator`` it is the actuator's implant tip, z along the implant axis, the drilling
  direction). Voxel blocks run on the engine of systems.capability.scaleout (a LocalCluster by
  default when W >
  1); finished blocks go to ``map.h5.blocks-<key>/`` so ``--resume`` redoes only the missing ones;
  the HDF5 is written once at the end (atomically) and the block folder removed. Progress (blocks
  done / total, ETA) on stderr; a summary on stdout.
- ``capmap query map.h5 --poses FILE.npy --out q.json``: poses N x 4 x 4 in base_link; JSON with
  ``reachable`` (bool, exact: the certified cell's answer, or closed-form IK at the pose where
  the cell is undecided), ``answer`` (what each rests on: "certified reachable", "certified
  unreachable" or "resolved by IK"), ``answers`` (their counts) and ``index`` (the voxel's
  centre-sampled reachability index, seed 004), one per pose.
- ``capmap accuracy map.h5 [--samples N] [--seed S]``: TP/FP/FN against direct IK.
- ``capmap show map.h5 --png slices.png [--html map.html]``: voxels coloured by index (HSV red 0
  to blue 1) as PNG slices and, optionally, a static Meshcat HTML.
- ``capmap plan --patient P.yaml --task T.yaml --robot R.yaml --out DIR [--method
  auto|exhaustive|ga] [--seed S] [--map M] [--store DIR] [--meshcat]``: best base (and access
  point), cost, maps used; writes ``plan.json``, ``best_vs_worst.png``, ``cmap_slices.png`` (and
  ``rasscmap_best.html`` with ``--meshcat``). If the robot YAML's map file is missing and the
  YAML has a ``build`` block, the map is built first and saved there.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from implantplan.analyses.figures.capability import (
    meshcat_html,
    plot_best_worst,
    plot_map_slices,
    setup_points,
)
from implantplan.analyses.progress import Progress
from implantplan.systems import validate
from implantplan.systems.actuator import actuator_map_frame
from implantplan.systems.capability import maps as cm
from implantplan.systems.capability import rasscmap_inputs as rin
from implantplan.systems.capability import scaleout
from implantplan.systems.capability import setup_search as ss
from implantplan.systems.capability import store as ms
from implantplan.systems.errors import InputError, PlanningFailure, fields_renamed
from implantplan.systems.files import write_json
from implantplan.systems.frames import invert


def tool_frame(tool: str | None) -> tuple[np.ndarray, str]:
    if tool in (None, "flange"):
        return np.eye(4), "flange"
    if tool == "actuator":
        return actuator_map_frame(), "actuator"
    raise InputError("tool", f"expected 'actuator' (or no --tool for the flange), got {tool!r}")


# IK poses per block: >= ~100 ms of work per task at ~1 M poses/s (the Dask per-task overhead is a
# few ms, analyses/bench_capmap.py), ~45 MB of poses per worker.
BLOCK_POSES = 100_000


def build_map(
    voxel_mm: float,
    directions: int,
    limits: str,
    tool: str | None,
    rolls: int | None,
    workers: int | None,
    *,
    self_collision: bool = False,
    cell: str = "certified",
    quiet: bool = False,
    scheduler: str | None = None,
    out: str | Path | None = None,
    resume: bool = False,
    poses_per_block: int = BLOCK_POSES,
) -> tuple[cm.CapabilityMap, dict]:
    """Build a map on the engine of ``scheduler`` / ``workers`` (systems.capability.scaleout);
    returns the
    map and what the build did (blocks, reused, computed, engine).

    With ``out`` the finished blocks go to the build's block store beside it
    (:class:`systems.capability.maps.BlockStore`), the map is written to ``out`` once, atomically,
    and the store is removed; ``resume`` reuses the blocks of an interrupted build (without it a
    store holding blocks is an error, so a forgotten flag never throws hours of work away).
    """
    X_FT, name = tool_frame(tool)
    params = cm.make_params(
        voxel_mm / 1000.0, directions, limits=limits, X_FT=X_FT, tool=name, rolls=rolls,
        self_collision=self_collision, cell=cell,
    )  # fmt: skip
    scaleout.check_scheduler(scheduler, workers)
    if int(poses_per_block) != poses_per_block or poses_per_block < 1:
        raise InputError("--block-poses", f"expected an integer >= 1, got {poses_per_block!r}")
    grid = cm.make_grid(params)
    prog = Progress("capmap build", quiet=quiet)
    n_vox = len(cm.candidate_voxels(params, grid))
    prog.say(
        f"{name}, {voxel_mm:g} mm voxels, {directions} directions, {params.rolls} roll(s), "
        f"limits +-{limits} deg: {n_vox} voxels x {directions * params.rolls} = "
        f"{n_vox * directions * params.rolls:,} IK poses"
    )
    store = None
    n_blocks = len(cm.blocks_of(params, poses_per_block))
    have = 0
    if out is not None:
        store = cm.BlockStore.beside(out, params, poses_per_block=poses_per_block)
        store.remove_partial()  # a block being written when a build was killed (kill -KILL)
        have = len(store.finished())
        if have and not resume:
            raise InputError(
                "--resume",
                f"{store.folder} holds {have} of {n_blocks} blocks of an interrupted build of "
                "this map: pass --resume to reuse them, or delete the folder",
            )
    with scaleout.engine(scheduler, workers, warm_up=[cm.__name__]) as eng:
        prog.say(
            f"{eng.description}: {n_blocks} blocks of <= {poses_per_block:,} poses"
            + (f", {have} done before (resumed)" if have else "")
        )
        eta = scaleout.Eta(n_blocks, skipped=have)
        cmap = cm.build(
            params,
            executor=eng.executor,
            workers=1,
            poses_per_block=poses_per_block,
            store=store,
            progress=lambda i, n: prog.step(i - 1, n, f"blocks, {eta.text(i)}"),
        )
    prog.say(f"done: {cmap.stats()['voxels_reachable']} reachable voxels")
    info = {"blocks": n_blocks, "blocks_reused": store.reused if store else 0,
            "blocks_computed": store.written if store else n_blocks,
            "engine": eng.description}  # fmt: skip
    if out is not None:
        cmap.save(out)
        store.remove()
    return cmap, info


BUILD_FLAGS = {"voxel": "--voxel-mm", "directions": "--directions", "rolls": "--rolls",
               "limits": "--limits", "cell": "--cell"}


def _cmd_build(args) -> int:
    t0 = time.perf_counter()
    with fields_renamed(BUILD_FLAGS):  # the core's names -> the flags typed
        cmap, info = build_map(
            args.voxel_mm, args.directions, args.limits, args.tool, args.rolls, args.workers,
            self_collision=args.self_collision, cell=args.cell, scheduler=args.scheduler,
            out=args.out, resume=args.resume, poses_per_block=args.block_poses,
        )  # fmt: skip
    summary = {
        "out": str(args.out),
        "params": cmap.params.as_dict(),
        "seconds": round(time.perf_counter() - t0, 3),
        **cmap.stats(),
        **info,
    }
    print(json.dumps(summary))
    return 0


def _load_poses(path) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise InputError("--poses", f"file {str(path)!r} does not exist")
    try:
        X = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise InputError("--poses", f"{path} is not a .npy array ({exc})") from None
    if X.ndim != 3:
        raise InputError("--poses", f"expected an N x 4 x 4 array, got shape {X.shape}")
    return validate.pose(X, "--poses", batch=True)


def _cmd_query(args) -> int:
    cmap = cm.load(args.map)
    X = _load_poses(args.poses)
    reach, source, index = cmap.answer(X)
    counts = {name: int(np.sum(source == code)) for code, name in cm.SOURCES.items()}
    write_json(
        args.out,
        {"map": str(args.map), "reachable": reach.tolist(), "index": index.tolist(),
         "answer": [cm.SOURCES[int(v)] for v in source], "answers": counts,
         "index_map": f"centre-sampled index (seed 004) of the {cmap.params.describe()}"},
        kind="capmap_query",
    )
    print(json.dumps({"out": str(args.out), "poses": len(X),
                      "reachable": int(reach.sum()), **counts}))
    return 0


def _cmd_accuracy(args) -> int:
    cmap = cm.load(args.map)
    if args.samples < 1:
        raise InputError("--samples", f"expected >= 1, got {args.samples}")
    X = cm.random_poses(args.samples, seed=args.seed, radius=cm.reach_radius(cmap.params))
    out = {"exact_roll": cm.accuracy(cmap, X), "some_roll": cm.accuracy(cmap, X, exact_roll=False)}
    print(json.dumps(out))
    return 0


def _cmd_show(args) -> int:
    cmap = cm.load(args.map)
    if args.slices < 1:
        raise InputError("--slices", f"expected >= 1, got {args.slices}")
    plot_map_slices(cmap, args.png, n_slices=args.slices)
    out = {"png": str(args.png)}
    if args.html:
        if meshcat_html(cmap.centres(), cmap.index, args.html, voxel=cmap.params.voxel):
            out["html"] = str(args.html)
        else:
            print("implantplan: Meshcat could not start here; no HTML written", file=sys.stderr)
    print(json.dumps(out))
    return 0


# ---------------------------------------------------------------------------------------------
# plan
# ---------------------------------------------------------------------------------------------


def resolve_map(robot: rin.Robot, override: str | None, *, quiet: bool = False) -> cm.CapabilityMap:
    """Load the robot's CMAP (or ``override``); build and save it first if missing + buildable."""
    path = Path(override) if override else robot.map_path
    expect = {"limits": robot.limits} if robot.limits else None
    if path.is_file():
        return cm.load(path, expect=expect)
    if override or robot.build is None:
        raise InputError(
            "robot.map", f"{path} does not exist; build it with `implantplan capmap build`"
        )
    b = robot.build
    cmap, _ = build_map(
        b.voxel_mm,
        b.directions,
        b.limits or robot.limits or "175",
        b.tool,
        b.rolls,
        b.workers,
        self_collision=b.self_collision,
        cell=b.cell,
        quiet=quiet,
        out=path,
    )
    return cmap


def plan(
    patient_path,
    task_path,
    robot_path,
    out_dir,
    *,
    method: str = "auto",
    seed: int = 0,
    map_override: str | None = None,
    store_dir: str | None = None,
    meshcat: bool = False,
    quiet: bool = False,
) -> dict:
    """The ``capmap plan`` pipeline; returns the plan dict written to ``out_dir/plan.json``."""
    patient = rin.load_patient(patient_path)
    task = rin.load_task(task_path)
    robot = rin.load_robot(robot_path)
    prog = Progress("capmap plan", quiet=quiet)
    cmap = resolve_map(robot, map_override, quiet=quiet)
    store_root = Path(store_dir) if store_dir else robot.store
    if store_root is None:
        store_root = Path(str(map_override or robot.map_path) + ".rasscmaps")
    store = ms.RasscmapStore(store_root)
    problem = ss.SetupProblem(cmap, patient, task, robot, store=store)
    prog.say(f"{problem.n} candidates ({len(problem.bases)} bases x {problem.n_access} access)")
    res = ss.optimize(problem, method=method, seed=seed)
    prog.say(f"{res.method}: best cost {res.cost:.4f} in {res.seconds:.3f} s")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    def describe(cand: int) -> dict:
        b, a = problem.split(np.array([cand]))
        X_WB = problem.bases[b[0]]
        d = {
            "candidate": int(cand),
            "base_xyz_m": X_WB[:3, 3],
            "base_yaw_deg": float(np.degrees(np.arctan2(X_WB[1, 0], X_WB[0, 0]))),
            "X_WB": X_WB,
            "cost": float(problem.cost[cand]),
            "c_s": float(problem.c_s[cand]),
            "mean_task_index": float(problem.mean_c_t[cand]),
            "all_task_poses_reachable": bool(problem.all_reached[cand]),
        }
        if patient.access == "constrained":
            d["access_point"] = patient.access_points[a[0]][0]
        return d

    X_BT = invert(problem.bases[problem.split(np.array([res.best]))[0][0]])[None] @ task.poses
    # The final check uses the exact reference, not the map: closed-form IK at each task pose.
    exact = cm.exact_reachable(cmap.params, X_BT)
    exact_check = {
        "reference": "closed-form IK at each task pose from the best base (map's tool frame, "
                     "joint limits, self-collision when the map checks it)",
        "reachable": [bool(v) for v in exact],
        "poses": int(exact.size),
        "pass": bool(exact.all()),
    }  # fmt: skip
    data = {
        "patient": patient.id,
        "task": task.id,
        "robot": robot.name,
        "access": patient.access,
        "method": res.method,
        "seed": seed,
        "candidates": problem.n,
        "evaluations": res.evaluations,
        "generations": res.generations,
        "seconds": res.seconds,
        "cost_formula": "0 if any task pose unreachable else (mean task index + c_s) / 2",
        "best": describe(res.best),
        "worst": describe(res.worst),
        "task_poses_in_best_base": X_BT,
        "exact_check": exact_check,
        "maps_used": {
            "cmap": str(Path(map_override) if map_override else robot.map_path),
            "cmap_params": cmap.params.as_dict(),
            "cmap_key": cmap.params.key(),
            "rasscmap_store": str(store_root),
            "store_hits": store.hits,
            "store_misses": store.misses,
        },
    }
    plot_best_worst(problem, res.best, res.worst, out / "best_vs_worst.png")
    plot_map_slices(cmap, out / "cmap_slices.png")
    files = ["plan.json", "best_vs_worst.png", "cmap_slices.png"]
    if meshcat:
        pts, idx = setup_points(problem, res.best)
        if meshcat_html(pts, idx, out / "rasscmap_best.html", voxel=patient.voxel):
            files.append("rasscmap_best.html")
        else:
            prog.say("Meshcat could not start here; no HTML written")
    data["files"] = files
    write_json(out / "plan.json", data, kind="capmap_plan")
    if not exact_check["pass"]:
        missed = [i for i, v in enumerate(exact_check["reachable"]) if not v]
        raise PlanningFailure(
            f"the map's best base does not pass the exact check: closed-form IK finds no "
            f"solution for task pose(s) {missed} (plan written to {out / 'plan.json'})")
    return data


def _cmd_plan(args) -> int:
    data = plan(
        args.patient, args.task, args.robot, args.out, method=args.method, seed=args.seed,
        map_override=args.map, store_dir=args.store, meshcat=args.meshcat,
    )  # fmt: skip
    best = data["best"]
    line = {
        "best_base_xyz_m": [round(float(v), 4) for v in best["base_xyz_m"]],
        "best_base_yaw_deg": round(best["base_yaw_deg"], 2),
        "access_point": best.get("access_point"),
        "cost": round(best["cost"], 4),
        "exact_check": f"{sum(data['exact_check']['reachable'])} of {data['exact_check']['poses']} "
                       "task poses reached by exact IK",
        "worst_cost": round(data["worst"]["cost"], 4),
        "method": data["method"],
        "seconds": round(data["seconds"], 4),
        "out": str(args.out),
    }
    print(json.dumps(line))
    return 0


def register(subparsers) -> None:
    """Add ``capmap build|query|accuracy|plan`` to the implantplan CLI."""
    p = subparsers.add_parser("capmap", help="capability maps and RASSCMAP setup planning")
    sub = p.add_subparsers(dest="capmap_command", required=True, metavar="SUBCOMMAND")

    b = sub.add_parser("build", help="build a capability map (HDF5)")
    b.add_argument("--voxel-mm", type=float, default=50.0, help="voxel edge in mm (default 50)")
    b.add_argument("--directions", type=int, default=100, help="approach directions (default 100)")
    b.add_argument("--limits", choices=("175", "360"), default="175", help="joint limits, deg")
    b.add_argument("--tool", choices=("actuator",), default=None, help="map the actuator's tip")
    b.add_argument("--rolls", type=int, default=None, help="roll samples (off-axis tools only)")
    b.add_argument("--workers", type=int, default=None, help=scaleout.WORKERS_HELP)
    b.add_argument("--scheduler", default=None, help=scaleout.SCHEDULER_HELP)
    b.add_argument(
        "--block-poses", type=int, default=BLOCK_POSES,
        help=f"IK poses per block, one task each (default {BLOCK_POSES:,}: >= ~100 ms of work)",
    )  # fmt: skip
    b.add_argument(
        "--resume", action="store_true",
        help="reuse the finished blocks of an interrupted build of the same map (<out>.blocks-*)",
    )  # fmt: skip
    b.add_argument(
        "--self-collision", action="store_true", help="also require self-collision-free IK"
    )
    b.add_argument(
        "--cell", choices=("certified", "centre"), default="certified",
        help="certified (default): the paper's centre-sampled bits plus cells certified "
        "reachable throughout (the rest resolved by IK when queried); centre: the paper's bits "
        "only (every query resolved by IK)",
    )  # fmt: skip
    b.add_argument("--out", required=True, help="output .h5")
    b.set_defaults(func=_cmd_build)

    q = sub.add_parser("query", help="query a map with poses (N x 4 x 4 .npy in base_link)")
    q.add_argument("map", help="capability map (.h5)")
    q.add_argument("--poses", required=True, help="N x 4 x 4 poses in base_link (.npy, m)")
    q.add_argument("--out", required=True, help="output JSON")
    q.set_defaults(func=_cmd_query)

    a = sub.add_parser("accuracy", help="TP/FP/FN of a map against direct IK")
    a.add_argument("map", help="capability map (.h5)")
    a.add_argument("--samples", type=int, default=100_000,
                   help="random poses checked against direct IK (default 100000)")
    a.add_argument("--seed", type=int, default=0, help="seed of the random poses (default 0)")
    a.set_defaults(func=_cmd_accuracy)

    sh = sub.add_parser("show", help="pictures of a map: PNG slices, optional Meshcat HTML")
    sh.add_argument("map", help="capability map (.h5)")
    sh.add_argument("--png", required=True, help="output PNG of horizontal slices")
    sh.add_argument("--slices", type=int, default=6, help="horizontal slices drawn (default 6)")
    sh.add_argument("--html", default=None, help="also write a static Meshcat HTML here")
    sh.set_defaults(func=_cmd_show)

    pl = sub.add_parser("plan", help="best base pose / access point from patient, task, robot")
    pl.add_argument("--patient", required=True, help="patient YAML (body part, access points)")
    pl.add_argument("--task", required=True, help="task YAML (task poses)")
    pl.add_argument("--robot", required=True, help="robot YAML (map, base pose ranges)")
    pl.add_argument("--out", required=True, help="output directory")
    pl.add_argument("--method", choices=("auto", "exhaustive", "ga"), default="auto",
                    help="setup search: exhaustive when small (auto, default) or the GA")
    pl.add_argument("--seed", type=int, default=0, help="GA seed (default 0)")
    pl.add_argument("--map", default=None, help="use this map instead of the robot YAML's")
    pl.add_argument("--store", default=None, help="RASSCMAP store directory")
    pl.add_argument("--meshcat", action="store_true", help="also write a static Meshcat HTML")
    pl.set_defaults(func=_cmd_plan)


if __name__ == "__main__":  # pragma: no cover
    from implantplan.analyses.cli import main

    sys.exit(main(["capmap", *sys.argv[1:]]))
