"""``implantplan robot place``: MOPRP robot base placement (seed 001, DESIGN.md section 5).

    implantplan robot place --scenario lying|sitting|FILE.yaml [--plan plan.json] [--pop P]
        [--gen G] [--seed S] [--ik closed-form|drake] [--weights WD WE WJ]
        [--percentile-samples N] [--no-plots] --out DIR

Runs NSGA-II (systems.robot.nsga2) on the vectorized problem of systems.robot.moprp and writes
``DIR/placement.json`` (kind ``robot_placement``):

- ``pareto``: the feasible non-dominated bases, each {base_xyz (m, in Oral), indices {dexterity,
  error_range (m), joint_variation (rad)}, branch, q (rad, at the target), q_pre (rad, pre-feed)};
- ``selected``: the knee point (or the smallest weighted sum with ``--weights``), same fields plus
  ``percentiles`` (% of ``--percentile-samples`` random feasible bases it beats or ties, per
  index; the paper reports about 80-90, 99, 80-90), ``percentiles_strict`` (% it strictly
  beats) and ``X_WBase`` (the base pose in World);
- ``gii``: General Isotropy Index over 100 random poses about Oral on the selected branch;
- ``angular_error_range``: eps sigma_max(J_w) over every surviving candidate seen in the
  percentile sample (the paper's Eq. 20 claims it is constant);
- ``evaluations``, ``seconds`` (``seconds_evaluation``, ``seconds_optimizer``), ``generations``,
  ``stopped`` (hypervolume stagnation or the generation cap), the scenario and its source.

Plots (unless ``--no-plots``): ``pareto_design.png`` and ``pareto_objectives.png`` (3-D scatter,
the selection marked), ``layout_after.png`` / ``layout_before.png`` (the selected layout at the
target and at the pre-feed pose: arm capsules, cart, patient and chair, three views each) and
``layout.html`` (Meshcat static HTML: the Drake plant at the selected base with the scenario's
cart/patient/chair, the feed animated from pre-feed to target).

``--plan``: a JSON file giving the feeding target in the world: a top-level ``X_WT`` (4x4, m),
or ``X_CT`` (feeding target in the FPSM Center frame, as ``implantplan instrument place``
writes) together with ``X_WC`` (Center in World). The Oral frame is that feeding target (seed
000's Tool frame has Oral's axes: x along the rod away from the head, z along the implant axis);
it replaces the scenario's ``oral`` pose.

``--ik drake``: the same evaluation with Drake's multi-start IK (diagrams.ik_drake) instead of the
closed form; branches are followed along the feed by matching each sample's solutions to the
previous sample's (assignment on the wrapped joint distance). Slow: use a small --pop/--gen.

Exit 2 on bad input (bounds inverted or empty, malformed YAML, ...), exit 3 when no feasible
base exists in the bounds (the reason names the most common rejection).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from implantplan.analyses.figures.robot import plot_placement
from implantplan.analyses.progress import Progress
from implantplan.systems import seeds, validate
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.files import read_json, write_json
from implantplan.systems.frames import wrap_angle
from implantplan.systems.robot import moprp


def register(subparsers) -> None:
    robot = subparsers.add_parser("robot", help="robot base placement (MOPRP, seed 001)")
    sub = robot.add_subparsers(dest="robot_command", required=True, metavar="SUBCOMMAND")
    p = sub.add_parser("place", help="Pareto front of base positions by NSGA-II, and a selection")
    p.add_argument("--scenario", required=True,
                   help="bundled scenario (lying, sitting) or a scenario YAML file")
    p.add_argument("--plan", type=Path, default=None,
                   help="JSON with the feeding target (X_WT, or X_CT + X_WC) = the Oral pose")
    p.add_argument("--pop", type=int, default=None, help="population size (scenario: 500)")
    p.add_argument("--gen", type=int, default=None, help="max generations (scenario: 500)")
    p.add_argument("--seed", type=int, default=None, help="seed (scenario's seed by default)")
    p.add_argument("--ik", choices=("closed-form", "drake"), default="closed-form",
                   help="IK: closed form (default) or Drake multi-start InverseKinematics")
    p.add_argument("--drake-starts", type=int, default=64,
                   help="multi-start budget per pose for --ik drake")
    p.add_argument("--weights", nargs=3, type=float, default=None, metavar=("WD", "WE", "WJ"),
                   help="select by weighted normalized indices instead of the knee point")
    p.add_argument("--percentile-samples", type=int, default=None,
                   help="random feasible bases for the percentile ranks (scenario: 2000)")
    p.add_argument("--full", action="store_true",
                   help="run all generations (no hypervolume-stagnation stop)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.set_defaults(func=_place)


# --------------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------------


def _matrix(value, field: str) -> np.ndarray:
    return validate.pose(value, field)


def oral_pose_from_plan(path: Path) -> tuple[np.ndarray, str]:
    """The Oral pose in World from a plan/placement JSON (see module docstring)."""
    data = read_json(path, field="--plan")
    if "X_WT" in data:
        return _matrix(data["X_WT"], "--plan: X_WT"), "X_WT"
    if "X_CT" in data:
        if "X_WC" not in data:
            raise InputError("--plan", f"{path} has X_CT (target in Center) but no X_WC (Center "
                             "in World) to place it in the world; add X_WC or give X_WT")
        X_CT = _matrix(data["X_CT"], "--plan: X_CT")
        X_WC = _matrix(data["X_WC"], "--plan: X_WC")
        return X_WC @ X_CT, "X_WC @ X_CT"
    raise InputError("--plan", f"{path} has no feeding target: expected X_WT or X_CT with X_WC")


def _tool_pose(sc: moprp.Scenario) -> np.ndarray:
    """TCP in the flange frame from the modelled actuator (systems.actuator), one place for it."""
    from implantplan.systems.actuator import X_FT

    return X_FT(sc.actuator.rod_length)


def scenario_for(args) -> tuple[moprp.Scenario, dict]:
    sc = moprp.load_scenario(args.scenario)
    info = {"scenario": str(args.scenario), "oral_from": "scenario"}
    changes = {"X_FT": _tool_pose(sc)}
    if args.plan is not None:
        X_WO, how = oral_pose_from_plan(args.plan)
        changes["X_WO"] = X_WO
        info["oral_from"] = f"{args.plan} ({how})"
    for name, value, lo in (("pop", args.pop, 4), ("gen", args.gen, 1), ("seed", args.seed, 0),
                            ("percentile_samples", args.percentile_samples, 1)):
        if value is not None:
            if value < lo:
                raise InputError(f"--{name.replace('_', '-')}", f"expected >= {lo}, got {value}")
            changes[name] = int(value)
    if args.full:
        changes["patience"] = None
    return dataclasses.replace(sc, **changes), info


# --------------------------------------------------------------------------------------------
# Drake IK adapter
# --------------------------------------------------------------------------------------------


def drake_ik_solver(*, starts: int, seed: int, limits: str, X_FT, scenario=None):
    """An ``ik_solver`` for :func:`systems.robot.moprp.evaluate_bases` backed by diagrams.ik_drake.

    With a ``scenario``, each base position's IK runs on the scenario's plant with the base
    there (diagrams.plant.build_plant) and Drake's MinimumDistanceLowerBoundConstraint at the
    scenario's clearance, so every solution is clear in SceneGraph; the base position is
    recovered from the feed's last pose (the target End = Oral R_OE: X_OB = X_OE X_BE^-1).

    Each pose is solved by multi-start Drake IK; along the feed (axis -3 of the input), each
    sample's solutions are assigned to the previous sample's slots by minimum total wrapped joint
    distance, so slot b follows one branch continuously (a jump shows as a large step and is
    rejected by the continuity check). Slots are labelled by the closed-form branch nearest to the
    slot's solution at the target, so branch indices compare with the fast path.
    """
    from scipy.optimize import linear_sum_assignment

    from implantplan.diagrams.ik_drake import DrakeIk

    solver = DrakeIk(X_FT=X_FT, limits=limits)
    rng = np.random.default_rng(seed)
    stats = {"poses": 0, "seconds": 0.0,
             "min_distance_m": None if scenario is None else scenario.clearance}

    def scene_solver(X_BE):
        from implantplan.diagrams.plant import build_plant

        xyz = (moprp.X_OE @ np.linalg.inv(X_BE))[:3, 3]
        diagram, plant, _, _ = build_plant(scenario=scenario, limits=limits,
                                           X_WBase=scenario.X_WO @ moprp.base_pose(xyz))
        return DrakeIk(X_FT=X_FT, plant=plant, diagram=diagram,
                       min_distance=scenario.clearance)

    def solve(X_BT, *, limits, X_FT):
        # (..., K, 4, 4): the leading axes (bases, then e.g. head displacements) are flattened;
        # the scene-aware solver is built once per base (leading axis 0) from its first feed
        X_BT = np.asarray(X_BT, dtype=float)
        lead, K = X_BT.shape[:-3], X_BT.shape[-3]
        per_base = int(np.prod(lead[1:], dtype=int))
        X_BT = X_BT.reshape(-1, K, 4, 4)
        P = X_BT.shape[0]
        q = np.zeros((P, K, 8, 6))
        ok = np.zeros((P, K, 8), dtype=bool)
        t0 = time.perf_counter()
        ik_p = solver
        for p in range(P):
            prev = None
            if scenario is not None and p % per_base == 0:
                ik_p = scene_solver(X_BT[p, -1])
            for k in range(K):
                sols, _ = ik_p.solve(X_BT[p, k], starts=starts, seed=rng)
                sols = sols[:8]
                if prev is None:
                    q[p, k, : len(sols)] = sols
                    ok[p, k, : len(sols)] = True
                else:
                    slots = np.flatnonzero(prev[1])
                    if len(sols) and slots.size:
                        d = np.abs(wrap_angle(prev[0][slots, None, :]
                                              - sols[None, :, :])).sum(-1)
                        r, c = linear_sum_assignment(d)
                        q[p, k, slots[r]] = sols[c]
                        ok[p, k, slots[r]] = True
                prev = (q[p, k], ok[p, k])
        stats["poses"] += P * K
        stats["seconds"] += time.perf_counter() - t0
        # relabel slots by the nearest closed-form branch at the target
        cf_q, cf_ok = moprp.ik_closed_form(X_BT[:, -1], limits=limits, X_FT=X_FT)
        d = np.abs(wrap_angle(q[:, -1, :, None, :] - cf_q[:, None, :, :])).sum(-1)
        d = np.where(cf_ok[:, None, :], d, np.inf)
        q_out = np.zeros_like(q)
        ok_out = np.zeros_like(ok)
        for p in range(P):
            used = set()
            for s in np.flatnonzero(ok[p, -1]):
                b = int(np.argmin(d[p, s]))
                if np.isfinite(d[p, s, b]) and b not in used:
                    used.add(b)
                    q_out[p, :, b] = q[p, :, s]
                    ok_out[p, :, b] = ok[p, :, s]
        return q_out.reshape(*lead, K, 8, 6), ok_out.reshape(*lead, K, 8)

    solve.stats = stats
    return solve


# --------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------


def _entry(xyz, ev: moprp.BaseEvaluation, i: int) -> dict:
    return {
        "base_xyz": xyz[i],
        "indices": dict(zip(moprp.INDEX_NAMES, ev.objectives[i].tolist(), strict=True)),
        "branch": int(ev.branch[i]),
        "q": ev.q[i],
        "q_pre": ev.q_pre[i],
    }


def _explain(sc: moprp.Scenario, ik_solver):
    def explain(Xs, rng) -> str:
        ev = moprp.evaluate_bases(Xs, sc, rng, ik_solver=ik_solver)
        codes = ev.reason[ev.reason > 0]
        common = (np.bincount(codes, minlength=len(moprp.DROP_REASONS)).argmax()
                  if codes.size else moprp.DROP_IK)
        return (
            f"no feasible base among {Xs.shape[0]} samples of the bounds "
            f"x {sc.lower[0]:.3f}..{sc.upper[0]:.3f}, y {sc.lower[1]:.3f}..{sc.upper[1]:.3f}, "
            f"z {sc.lower[2]:.3f}..{sc.upper[2]:.3f} m (in Oral); most branches rejected "
            f"because: {moprp.DROP_REASONS[int(common)]}"
        )

    return explain


def confirm_front(sc: moprp.Scenario, Xf, ev: moprp.BaseEvaluation, order) -> dict:
    """SceneGraph confirmation of what the placement reports: each front
    member's pre-feed and target configurations, and for the selection its whole feed (steps
    of at most 1 mm / 0.5 deg); candidates are tried in ``order`` (the selection rule's ranking)
    and the first whose feed is clear is selected.

    Returns:
        dict(clearance (n,) SceneGraph distance of each member over q_pre and q, pair (n,) its
        closest pair, members_ok (n,) bool, selected (index or None), feed (the selected
        member's feed check), selection_dropped (candidates whose feed failed, in order)).
    """
    from implantplan.diagrams.arm_clearance import SceneGraphClearance, confirm_feed

    n = Xf.shape[0]
    dist = np.full(n, np.nan)
    pairs = [("", "")] * n
    checkers = {}
    for i in range(n):
        checkers[i] = SceneGraphClearance(sc, Xf[i])
        c = checkers[i](np.stack([ev.q_pre[i], ev.q[i]]), max_distance=1.0)
        _, dist[i], pairs[i] = c.worst()
    ok = dist >= sc.clearance
    dropped, selected, feed = [], None, None
    for i in order:
        if not ok[i]:
            dropped.append(int(i))
            continue
        check = confirm_feed(checkers[int(i)], sc, int(ev.branch[i]))
        if check["ok"]:
            selected, feed = int(i), check
            break
        dropped.append(int(i))
    return {"clearance": dist, "pair": pairs, "members_ok": ok, "selected": selected,
            "feed": feed, "selection_dropped": dropped}


def run_placement(sc: moprp.Scenario, *, ik: str = "closed-form", weights=None,
                  drake_starts: int = 64, progress: Progress | None = None) -> dict:
    """Run MOPRP on a scenario; returns the placement dict (raises PlanningFailure)."""
    progress = progress or Progress("robot place", quiet=True)
    t_start = time.perf_counter()
    ik_solver = moprp.ik_closed_form
    if ik == "drake":
        ik_solver = drake_ik_solver(starts=drake_starts,
                                    seed=seeds.seed(sc.seed, moprp.STREAM_DRAKE_IK),
                                    limits=sc.limits, X_FT=sc.X_FT, scenario=sc)
    elif ik != "closed-form":
        raise InputError("--ik", f"expected closed-form or drake, got {ik!r}")
    evaluate = moprp.problem(sc, ik_solver=ik_solver)

    def on_start(n_ok, n0):
        progress.say(f"{sc.name}: seeded population from {n0} samples ({n_ok} feasible); "
                     f"NSGA-II pop {sc.pop}, gen <= {sc.gen}")

    def on_gen(g, n_front, hv):
        progress.step(g - 1, sc.gen, f"generations, front {n_front}, hypervolume {hv:.4g}")

    res = moprp.search(sc, evaluate, explain=_explain(sc, ik_solver), on_start=on_start,
                       on_generation=on_gen)
    progress.say(f"stopped after {res.generations} generations ({res.stopped}), "
                 f"{res.evaluations} evaluations, {res.seconds_total:.1f} s")

    # branches and q of the front (fixed generator), then SceneGraph confirms what is reported
    Xf = res.X
    ev = moprp.evaluate_bases(Xf, sc, moprp.evaluation_rng(sc), ik_solver=ik_solver)
    t0 = time.perf_counter()
    conf = confirm_front(sc, Xf, ev, moprp.selection_order(ev.objectives, weights))
    t_confirm = time.perf_counter() - t0
    n_front = Xf.shape[0]
    if conf["selected"] is None:
        raise PlanningFailure(
            f"none of the {n_front} front bases is clear in SceneGraph along its feed by the "
            f"clearance {1000 * sc.clearance:.1f} mm (smallest distance "
            f"{1000 * np.nanmax(conf['clearance']):.2f} mm)")
    keep = np.flatnonzero(conf["members_ok"])
    progress.say(f"SceneGraph: {keep.size} of {n_front} front bases confirmed, "
                 f"{len(conf['selection_dropped'])} candidates dropped before the selection")
    sel = int(np.flatnonzero(keep == conf["selected"])[0])
    Xf, ev = Xf[keep], ev.subset(keep)  # exactly the configurations SceneGraph confirmed
    pareto = [_entry(Xf, ev, i) for i in range(Xf.shape[0])]
    for entry, i in zip(pareto, keep, strict=True):
        entry["scene_graph_clearance_m"] = float(conf["clearance"][i])
        entry["scene_graph_pair"] = list(conf["pair"][i])

    # percentile ranks against random feasible bases (closed form: the reference population)
    t0 = time.perf_counter()
    rng_pct = seeds.rng(sc.seed, moprp.STREAM_PERCENTILES)
    X_rand, F_rand = moprp.random_feasible(sc, sc.percentile_samples, rng_pct)
    pct = moprp.percentiles(ev.objectives[sel], F_rand)
    ev_rand = moprp.evaluate_bases(X_rand, sc, seeds.rng(sc.seed, moprp.STREAM_RANDOM_EVALUATE))
    ang = ev_rand.angular_error_range[np.isfinite(ev_rand.angular_error_range)]
    g = moprp.gii(Xf[sel], int(ev.branch[sel]), sc, seeds.rng(sc.seed, moprp.STREAM_GII))
    t_post = time.perf_counter() - t0

    selected = _entry(Xf, ev, sel)
    selected["percentiles"] = dict(zip(moprp.INDEX_NAMES, pct.tolist(), strict=True))
    pct_strict = moprp.percentiles(ev.objectives[sel], F_rand, strict=True)
    selected["percentiles_strict"] = dict(zip(moprp.INDEX_NAMES, pct_strict.tolist(),
                                              strict=True))
    selected["percentile_samples"] = int(X_rand.shape[0])
    selected["X_WBase"] = sc.X_WO @ moprp.base_pose(Xf[sel])
    selected["scene_graph_clearance_m"] = pareto[sel]["scene_graph_clearance_m"]
    selected["scene_graph_pair"] = pareto[sel]["scene_graph_pair"]
    feed = conf["feed"]
    selected["feed_clearance"] = {"distance_m": feed["distance"], "pair": feed["pair"],
                                  "samples": feed["samples"], "limit_m": feed["limit"]}
    selected["rule"] = "weights" if weights is not None else "knee"
    if weights is not None:
        selected["weights"] = list(weights)
    up = (sc.X_WO @ moprp.base_pose(np.zeros(3)))[:3, 2]
    tilt = float(np.degrees(np.arccos(np.clip(up[2], -1, 1))))
    out = {
        "scenario": {"name": sc.name, "posture": sc.posture, "X_WO": sc.X_WO,
                     "base_bounds_m": {"lower": sc.lower, "upper": sc.upper},
                     "joint_error_rad": sc.eps, "feed_length_m": sc.feed_length,
                     "feed_samples": sc.feed_samples, "X_FT": sc.X_FT, "limits": sc.limits,
                     "base_tilt_deg": tilt},
        "ik": ik,
        "pareto": pareto,
        "selected": selected,
        "gii": g,
        "angular_error_range": {
            "min_rad": float(ang.min()) if ang.size else None,
            "max_rad": float(ang.max()) if ang.size else None,
            "candidates": int(ang.size),
            "over_eps": [float(ang.min() / sc.eps), float(ang.max() / sc.eps)] if ang.size
            else None,
        },
        "evaluations": int(res.evaluations),
        "generations": int(res.generations),
        "stopped": res.stopped,
        "confirmation": {
            "checker": "Drake SceneGraph ComputeSignedDistancePairwiseClosestPoints",
            "clearance_m": sc.clearance,
            "front": n_front,
            "pareto_dropped": int(n_front - keep.size),
            "selection_dropped": len(conf["selection_dropped"]),
            "seconds": t_confirm,
        },
        "pop": int(sc.pop),
        "seed": int(sc.seed),
        "seconds": time.perf_counter() - t_start,
        "seconds_evaluation": res.seconds_evaluation,
        "seconds_optimizer": res.seconds_total - res.seconds_evaluation,
        "seconds_percentiles_gii": t_post,
    }
    if ik == "drake":
        out["drake_ik"] = dict(ik_solver.stats)
    return out


def _place(args: argparse.Namespace) -> int:
    progress = Progress("robot place", quiet=args.quiet)
    sc, info = scenario_for(args)
    if args.weights is not None:
        w = np.asarray(args.weights, dtype=float)
        if not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
            raise InputError("--weights", "expected three weights >= 0, not all 0")
    up = (sc.X_WO @ moprp.base_pose(np.zeros(3)))[:3, 2]
    tilt = float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))
    if tilt > 5.0:
        progress.say(f"warning: Base Z || Oral Y (DESIGN.md 5) tilts the base {tilt:.0f} deg from "
                     "World up for this Oral pose; the cart would not stand on the floor")
    out = run_placement(sc, ik=args.ik, weights=args.weights, drake_starts=args.drake_starts,
                        progress=progress)
    out["inputs"] = info
    path = write_json(args.out / "placement.json", out, kind="robot_placement")
    progress.say(f"wrote {path}")
    print(summary_table(out))
    if not args.no_plots:
        paths = plot_placement(sc, out, args.out)
        progress.say("plots: " + ", ".join(p.name for p in paths))
    return 0


def summary_table(out: dict) -> str:
    s = out["selected"]
    ind, pct, pst = s["indices"], s["percentiles"], s["percentiles_strict"]
    x, y, z = (1000 * np.asarray(s["base_xyz"])).tolist()
    rows = (("dexterity", "dexterity", 1.0), ("error_range_mm", "error_range", 1000.0),
            ("joint_var_deg", "joint_variation", 180.0 / np.pi))
    lines = [
        f"front {len(out['pareto'])} bases, {out['generations']} generations "
        f"({out['stopped']}), {out['evaluations']} evaluations, {out['seconds']:.1f} s",
        f"selected base_xyz_mm ({x:.0f}, {y:.0f}, {z:.0f}) branch {s['branch']}",
        "index             value        percentile (beats or ties / strictly beats)",
    ]
    for label, key, scale in rows:
        lines.append(f"{label:<17} {scale * ind[key]:<12.4g} {pct[key]:.1f}% / {pst[key]:.1f}%")
    lines.append(f"GII {out['gii']['gii']:.4g} ({out['gii']['reached']}/{out['gii']['poses']} "
                 "poses)")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# plots
# --------------------------------------------------------------------------------------------


