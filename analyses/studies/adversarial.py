"""The adversarial-operator study of the safety layer on the default case.

Run: ``python -m implantplan.analyses.studies.adversarial [--seeds 4] [--normal 3] [--no-fixture]
[--json FILE]``

The bundled default case (models/cases/default.yaml: the opened ArtiSynth scan, sites 36 and 46)
is planned as ``implantplan plan`` does (FPSM fit, placement with its virtual fixture, robot base;
analyses.pipeline), and every site's feeding diagram (fixture + safety supervisor + estimator)
replays the motions of systems.teleop.adversarial_operator: for each site, each of the six kinds
(bursts at 2-5x the feed speed, a push towards each cheek and into the jaw at 40 mm/s, a slow
sideways drift, a random walk) with ``--seeds`` seeds, plus ``--normal`` calm scripted feeds.
The defaults give 2 x (6 x 4 + 3) = 54 runs.

At every logged pose (200 Hz) of every run:

- the **exact tool clearance**: FCL (python-fcl) distance between the tool's body and the opened
  scan mesh (a BVH of its triangles; without the lips and cheeks in front of the mouth opening,
  which the case takes as retracted: :func:`exact_for`), the tool as the capsules of
  systems.placement.tool_clearance.Instrument (the body the supervisor bounds: the handle rod,
  radius
  r, from P1 = [r, 0, 0] along Tool x for 0.2 m; the head, a sphere of radius r at the TCP; the
  implant from [r, 0, 0] to [r, 0, -d12], its axis, here of radius 0.1 mm):
  analyses.studies.scan_reference;
- the fixture's body violation (the TCP and the rod's entry crossing against delta);
- the supervisor's barrier h (the FPSM clearance at the desired pose).

Pass: exact clearance never below 0 nor below margin - 0.2 mm, fixture violation
below 0.5 mm, and every normal feed reaching the target (within 1 mm). The printed table has one
row per kind; the JSON holds every run.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from implantplan.analyses.studies.scan_reference import (  # noqa: F401  (the study's reference, re-exported)
    IMPLANT_AXIS_RADIUS,
    ExactClearance,
    default_case_sites,
    exact_for,
)
from implantplan.diagrams.feeding import FINISH_SECONDS, TARGET_TOLERANCE
from implantplan.diagrams.teleop import TeleopCase, build_teleop, simulate
from implantplan.systems import seeds as streams
from implantplan.systems.files import write_json
from implantplan.systems.teleop.adversarial_operator import KINDS, Directions, adversarial_motion
from implantplan.systems.teleop.master_device import feeding_runs
from implantplan.systems.teleop.supervisor import Barrier

MARGIN_SLACK = 0.0002  # m: the exact clearance may dip this far below the margin
MAX_VIOLATION = 0.0005  # m: the fixture's body violation must stay below this


def run_one(teleop, tc: TeleopCase, motion, exact: ExactClearance, *, finish_seconds=None):
    """Simulate one motion on a built diagram; the figures at every logged pose."""
    duration = motion.duration + (FINISH_SECONDS if finish_seconds is None else finish_seconds)
    run = simulate(teleop, duration, motion=motion)
    X_MT = tc.fpsm.X_WC @ run.X_CT  # the FPSM's X_WC is Center in the mesh frame
    c = exact(X_MT)
    err = float(np.linalg.norm(run.p_WE[-1] - tc.X_WTarget[:3, 3]))
    return {
        "min_exact_clearance": float(c.min()),
        "poses": int(c.size),
        "max_vf_violation": float(run.violation.max()),
        "max_angle_violation": float(run.angle_violation.max()),
        "min_barrier": float(run.barrier[:, 0].min()),
        "supervisor_active_share": float(run.barrier[:, 2].mean()),
        "alarm": bool(run.alarm.any()),
        "final_error": err,
        "reached_target": err <= TARGET_TOLERANCE,
        "sim_seconds": run.sim_seconds,
        "wall_seconds": run.wall_seconds,
    }


def study(*, seeds: int = 4, normal: int = 3, seed: int = 0, barrier: Barrier | None = None,
          kinds=KINDS, fixture: bool = True, progress=print) -> dict:
    """Every site x (kinds x seeds + normal feeds) of the default case; see the module docs.
    ``fixture=False`` leaves the supervisor alone against the operator."""
    cases, mesh = default_case_sites()
    barrier = barrier or Barrier()
    runs = []
    for k, tc in enumerate(cases):
        teleop = build_teleop(tc, barrier=barrier, vf_enabled=fixture)
        exact = exact_for(tc, mesh)
        start, target = tc.X_WE(tc.q_start)[:3, 3], tc.X_WTarget[:3, 3]
        dirs = Directions.of_case(tc.X_WTarget, tc.X_WCenter)
        todo = [(kind, i, adversarial_motion(kind, start, target, dirs,
                                             seed=np.random.SeedSequence([seed, k, j, i])))
                for j, kind in enumerate(kinds) for i in range(seeds)]
        todo += [("normal", i, m) for i, m in
                 enumerate(feeding_runs(start, target, runs=normal,
                                        seed=streams.seed(seed, k)))
                 if normal > 0]
        for kind, i, motion in todo:
            r = run_one(teleop, tc, motion, exact)
            r.update(site=tc.label, kind=kind, seed=i)
            runs.append(r)
            if progress is not None:
                progress(f"{tc.label:>8} {kind:>12} #{i}: exact "
                         f"{1e3 * r['min_exact_clearance']:7.3f} mm, VF "
                         f"{1e3 * r['max_vf_violation']:.3f} mm, h "
                         f"{1e3 * r['min_barrier']:.3f} mm, reached {r['reached_target']}")
    return {"runs": runs, "margin": barrier.margin, "alpha": barrier.alpha, "fixture": fixture,
            "summary": summarize(runs, barrier.margin)}


def summarize(runs: list[dict], margin: float) -> dict:
    """Per kind and overall: runs, worst exact clearance, worst violation, failures."""
    out = {}
    for kind in sorted({r["kind"] for r in runs}) + ["all"]:
        rs = [r for r in runs if kind in ("all", r["kind"])]
        exact = min(r["min_exact_clearance"] for r in rs)
        viol = max(r["max_vf_violation"] for r in rs)
        out[kind] = {
            "runs": len(rs),
            "min_exact_clearance": exact,
            "below_zero": sum(r["min_exact_clearance"] < 0 for r in rs),
            "below_margin_slack": sum(r["min_exact_clearance"] < margin - MARGIN_SLACK
                                      for r in rs),
            "max_vf_violation": viol,
            "violation_over": sum(r["max_vf_violation"] >= MAX_VIOLATION for r in rs),
            "min_barrier": min(r["min_barrier"] for r in rs),
            "reached": sum(r["reached_target"] for r in rs),
            "poses": sum(r["poses"] for r in rs),
        }
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="seeds per kind and site")
    parser.add_argument("--normal", type=int, default=3, help="calm feeds per site")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-fixture", action="store_true",
                        help="the supervisor alone (the fixture passes every command)")
    parser.add_argument("--json", help="write every run here")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    res = study(seeds=args.seeds, normal=args.normal, seed=args.seed,
                fixture=not args.no_fixture)
    print(f"\n{'kind':>12} {'runs':>5} {'poses':>7} {'min exact mm':>13} {'<0':>4} "
          f"{'<m-0.2':>7} {'max VF mm':>10} {'min h mm':>9} {'reached':>8}")
    for kind, s in res["summary"].items():
        print(f"{kind:>12} {s['runs']:>5} {s['poses']:>7} {1e3 * s['min_exact_clearance']:>13.3f} "
              f"{s['below_zero']:>4} {s['below_margin_slack']:>7} "
              f"{1e3 * s['max_vf_violation']:>10.3f} {1e3 * s['min_barrier']:>9.3f} "
              f"{s['reached']:>4}/{s['runs']}")
    print(f"margin {1e3 * res['margin']:.1f} mm, fixture {'on' if res['fixture'] else 'off'}; "
          f"{time.perf_counter() - t0:.0f} s")
    if args.json:
        write_json(args.json, res, kind="adversarial")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
