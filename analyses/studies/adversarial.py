"""The adversarial-operator study of the safety layer on the default case.

Run: ``python -m implantplan.analyses.studies.adversarial [--seeds 4] [--normal 3] [--kinds K,..]
[--no-fixture] [--jumps] [--json FILE]``

The bundled default case (models/cases/default.yaml: the opened ArtiSynth scan, sites 36 and 46)
is planned as ``implantplan plan`` does (FPSM fit, placement with its virtual fixture, robot base;
analyses.pipeline), and every site's feeding diagram (command limits + fixture + safety
supervisor + estimator) replays the motions of systems.teleop.adversarial_operator: for each
site, each kind (bursts at 2-5x the feed speed, a push towards each cheek and into the jaw at
40 mm/s, a slow sideways drift, a random walk, a 2 mm tremor, lateral twitches, handle jumps of
50-1000 mm held or out and back, absurd twists: 1e9 m/s, 1e9 rad/s, NaN, inf) with ``--seeds``
seeds, plus ``--normal`` calm scripted feeds. ``--jumps`` runs the full jump sweep instead: every
size of :data:`~implantplan.systems.teleop.adversarial_operator.JUMP_SIZES` (50, 100, 200, 500,
1000 mm) x the 14 directions of
:func:`~implantplan.systems.teleop.adversarial_operator.jump_directions` (Center's 6 axis
directions and 8 diagonals) x held and out-and-back, per site.

At every logged pose (200 Hz) of every run:

- the **exact tool clearance**: FCL's (Coal, through ExactCavity) distance between the tool's
  body and the opened scan mesh (a BVH of its triangles; without the lips and cheeks in front of
  the mouth opening, which the case takes as retracted: :func:`exact_for`), the tool as the
  solids of the case's instrument (``TeleopCase.tool``, the body the supervisor bounds):
  analyses.studies.scan_reference; measured by FCL at every 8th pose and at every pose whose
  1-Lipschitz bound from its measured neighbours could be the run's smallest
  (:func:`~implantplan.analyses.studies.scan_reference.screened`: the smallest is FCL's, the
  others are proven above it; docs/measurements.md gives the share of poses measured and the
  time saved);
  and **between the logged poses**: the arm's joint-linear motion from one logged configuration
  to the next, sampled where it could come closer than the logged poses, with a certified lower
  bound over the whole swept motion (analyses.studies.scan_reference.swept_clearance);
- the fixture's body violation (the TCP and the rod's entry crossing against delta);
- the supervisor's barrier h (the FPSM clearance at the desired pose);
- the command limiter's faults (count, times) and how the arm moves: the largest TCP and joint
  step per control period over the run, on recovery (the second after a fault clears) and the
  largest TCP displacement while a fault holds the command.

Pass: exact clearance (at the poses and the certified bound between them) never below 0 nor
below margin - 0.2 mm, fixture violation below 0.5 mm, every jump and absurd twist a logged
fault, no step of the arm above the command limits' (linear_speed x period, with 10% for
DiffIK's linearization) on recovery, and every normal feed reaching the target (within 1 mm).
The printed table has one row per kind; the JSON holds every run.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from implantplan.analyses.studies.scan_reference import (  # noqa: F401  (the study's reference, re-exported)
    IMPLANT_AXIS_RADIUS,
    MARGIN_SLACK,
    MAX_VIOLATION,
    STEP_SLACK,
    ExactClearance,
    default_case_sites,
    exact_for,
    swept_clearance,
)
from implantplan.diagrams.feeding import FINISH_SECONDS, TARGET_TOLERANCE
from implantplan.diagrams.teleop import TeleopCase, build_teleop, simulate
from implantplan.systems import seeds as streams
from implantplan.systems.files import write_json
from implantplan.systems.teleop.adversarial_operator import (
    ABSURD_KINDS,
    JUMP_KINDS,
    JUMP_SIZES,
    KINDS,
    Directions,
    adversarial_motion,
    handle_jump,
    jump_directions,
)
from implantplan.systems.teleop.command_limits import CommandLimits
from implantplan.systems.teleop.master_device import feeding_runs
from implantplan.systems.teleop.supervisor import Barrier

RECOVERY_SECONDS = 1.0  # s: the window after a fault clears in which the arm's steps count
FAULT_KINDS = JUMP_KINDS + ABSURD_KINDS


def fault_windows(run) -> list[tuple[float, float]]:
    """(fault time, clear time) of every latch in a run's command log (inf: still held at the
    end), from the limiter's per-sample status (held flag and sample time)."""
    held = run.command[:, 2] > 0.5
    t = run.command[:, 5]
    out = []
    start = None
    for h, tk in zip(held, t, strict=True):
        if h and start is None:
            start = tk
        elif not h and start is not None:
            out.append((float(start), float(tk)))
            start = None
    if start is not None:
        out.append((float(start), np.inf))
    return out


def motion_figures(run) -> dict:
    """The arm's steps (m, rad per control period) over the run, on recovery and under holds."""
    tcp = np.linalg.norm(np.diff(run.p_WE, axis=0), axis=1)
    joint = np.abs(np.diff(run.q, axis=0)).max(axis=1)
    t1 = run.t[1:]  # a step ends at its later log time
    recovery_tcp = recovery_joint = hold_motion = 0.0
    for t_fault, t_clear in fault_windows(run):
        during = (run.t >= t_fault) & (run.t <= t_clear)
        if during.any():
            p0 = run.p_WE[np.flatnonzero(during)[0]]
            hold_motion = max(hold_motion,
                              float(np.linalg.norm(run.p_WE[during] - p0, axis=1).max()))
        after = (t1 > t_clear) & (t1 <= t_clear + RECOVERY_SECONDS)
        if after.any():
            recovery_tcp = max(recovery_tcp, float(tcp[after].max()))
            recovery_joint = max(recovery_joint, float(joint[after].max()))
    return {"max_tcp_step": float(tcp.max()), "max_joint_step": float(joint.max()),
            "recovery_tcp_step": recovery_tcp, "recovery_joint_step": recovery_joint,
            "hold_motion": hold_motion}


def run_one(teleop, tc: TeleopCase, motion, exact: ExactClearance, *, finish_seconds=None):
    """Simulate one motion on a built diagram; the figures at every logged pose and between."""
    duration = motion.duration + (FINISH_SECONDS if finish_seconds is None else finish_seconds)
    run = simulate(teleop, duration, motion=motion)
    swept = swept_clearance(tc, exact, run.q, screen=True)  # FCL where the smallest can be
    err = float(np.linalg.norm(run.p_WE[-1] - tc.X_WTarget[:3, 3]))
    return {
        "min_exact_clearance": float(swept.at_poses.min()),
        "min_exact_between": swept.sampled,
        "min_exact_bound": swept.bound,
        "sampled_segments": swept.sampled_segments,
        "poses": int(swept.at_poses.size),
        "max_vf_violation": float(run.violation.max()),
        "max_angle_violation": float(run.angle_violation.max()),
        "min_barrier": float(run.barrier[:, 0].min()),
        "supervisor_active_share": float(run.barrier[:, 2].mean()),
        "alarm": bool(run.alarm.any()),
        "faults": run.fault_events,
        "fault_samples": int(run.fault_times.size),
        "fault_times": run.fault_times.tolist(),
        **motion_figures(run),
        "final_error": err,
        "reached_target": err <= TARGET_TOLERANCE,
        "sim_seconds": run.sim_seconds,
        "wall_seconds": run.wall_seconds,
    }


def _progress(progress, tc, kind, label, r):
    if progress is not None:
        progress(f"{tc.label:>8} {kind:>12} {label:>10}: exact "
                 f"{1e3 * r['min_exact_clearance']:7.3f} / between "
                 f"{1e3 * r['min_exact_bound']:7.3f} mm, VF "
                 f"{1e3 * r['max_vf_violation']:.3f} mm, h {1e3 * r['min_barrier']:.3f} mm, "
                 f"faults {r['faults']}, step {1e3 * r['max_tcp_step']:.3f} mm, "
                 f"reached {r['reached_target']}")


def study(*, seeds: int = 4, normal: int = 3, seed: int = 0, barrier: Barrier | None = None,
          kinds=KINDS, fixture: bool = True, limits: CommandLimits | None = None,
          progress=print) -> dict:
    """Every site x (kinds x seeds + normal feeds) of the default case; see the module docs.
    ``fixture=False`` leaves the supervisor alone against the operator."""
    runs = []
    for k, tc, teleop, exact, start, target in _sites(barrier, limits, fixture):
        barrier, limits = teleop.supervisor.barrier, teleop.limiter.limits
        dirs = Directions.of_case(tc.X_WTarget, tc.X_WCenter)
        todo = [(kind, i, adversarial_motion(kind, start, target, dirs,
                                             seed=np.random.SeedSequence([seed, k, j, i])))
                for j, kind in enumerate(KINDS) if kind in kinds for i in range(seeds)]
        todo += [("normal", i, m) for i, m in
                 enumerate(feeding_runs(start, target, runs=normal,
                                        seed=streams.seed(seed, k)))
                 if normal > 0]
        for kind, i, motion in todo:
            r = run_one(teleop, tc, motion, exact)
            r.update(site=tc.label, kind=kind, seed=i)
            runs.append(r)
            _progress(progress, tc, kind, f"#{i}", r)
    return _result(runs, barrier, limits, fixture)


def jump_study(*, sizes=JUMP_SIZES, seed: int = 0, fixture: bool = True,
               barrier: Barrier | None = None, limits: CommandLimits | None = None,
               progress=print) -> dict:
    """The full jump sweep (module docstring): per site, every size x direction x (held, out and
    back), each jump at a seeded time of a seeded calm feed."""
    runs = []
    for k, tc, teleop, exact, start, target in _sites(barrier, limits, fixture):
        barrier, limits = teleop.supervisor.barrier, teleop.limiter.limits
        D, names = jump_directions(Directions.of_case(tc.X_WTarget, tc.X_WCenter))
        for b, kind in enumerate(JUMP_KINDS):
            for i, size in enumerate(sizes):
                for j, (d, name) in enumerate(zip(D, names, strict=True)):
                    rng = np.random.default_rng(np.random.SeedSequence([seed, k, b, i, j]))
                    motion = handle_jump(start, target, rng, d, size, back=kind == "spike")
                    r = run_one(teleop, tc, motion, exact)
                    r.update(site=tc.label, kind=kind, size=float(size), direction=name)
                    runs.append(r)
                    _progress(progress, tc, kind, f"{1e3 * size:.0f} {name}", r)
    return _result(runs, barrier, limits, fixture)


def _sites(barrier: Barrier, limits: CommandLimits, fixture: bool):
    """Per site of the default case: (index, teleop case, its diagram, the exact reference, the
    start and target TCP positions in World); ``barrier`` and ``limits`` None: the case's safety
    spec's (what its diagram executes)."""
    cases, mesh = default_case_sites()
    for k, tc in enumerate(cases):
        teleop = build_teleop(tc, barrier=barrier, vf_enabled=fixture, limits=limits)
        yield (k, tc, teleop, exact_for(tc, mesh), tc.X_WE(tc.q_start)[:3, 3],
               tc.X_WTarget[:3, 3])


def _result(runs, barrier, limits, fixture) -> dict:
    return {"runs": runs, "margin": barrier.margin, "alpha": barrier.alpha, "fixture": fixture,
            "limits": limits.to_dict(), "summary": summarize(runs, barrier.margin, limits)}


def summarize(runs: list[dict], margin: float, limits: CommandLimits | None = None,
              period: float = 0.005) -> dict:
    """Per kind and overall: runs, worst exact clearance at the poses and between them, worst
    violation, faults, the arm's largest steps, failures."""
    limits = limits or CommandLimits()
    step_limit = STEP_SLACK * limits.linear_speed * period
    out = {}
    for kind in sorted({r["kind"] for r in runs}) + ["all"]:
        rs = [r for r in runs if kind in ("all", r["kind"])]
        bound = min(r["min_exact_bound"] for r in rs)
        out[kind] = {
            "runs": len(rs),
            "min_exact_clearance": min(r["min_exact_clearance"] for r in rs),
            "min_exact_between": min(r["min_exact_between"] for r in rs),
            "min_exact_bound": bound,
            "below_zero": sum(r["min_exact_bound"] < 0 for r in rs),
            "below_margin_slack": sum(r["min_exact_bound"] < margin - MARGIN_SLACK for r in rs),
            "max_vf_violation": max(r["max_vf_violation"] for r in rs),
            "violation_over": sum(r["max_vf_violation"] >= MAX_VIOLATION for r in rs),
            "min_barrier": min(r["min_barrier"] for r in rs),
            "faults": sum(r["faults"] for r in rs),
            "unfaulted": sum(r["kind"] in FAULT_KINDS and r["faults"] == 0 for r in rs),
            "max_tcp_step": max(r["max_tcp_step"] for r in rs),
            "max_recovery_step": max(r["recovery_tcp_step"] for r in rs),
            "recovery_jumps": sum(r["recovery_tcp_step"] > step_limit for r in rs),
            "max_hold_motion": max(r["hold_motion"] for r in rs),
            "reached": sum(r["reached_target"] for r in rs),
            "poses": sum(r["poses"] for r in rs),
        }
    return out


def print_summary(res: dict) -> None:
    print(f"\n{'kind':>12} {'runs':>5} {'poses':>7} {'exact mm':>9} {'between':>8} {'bound':>7} "
          f"{'<m-0.2':>7} {'VF mm':>6} {'h mm':>6} {'faults':>6} {'step mm':>8} {'recov':>6} "
          f"{'hold':>6} {'reached':>8}")
    for kind, s in res["summary"].items():
        print(f"{kind:>12} {s['runs']:>5} {s['poses']:>7} {1e3 * s['min_exact_clearance']:>9.3f} "
              f"{1e3 * s['min_exact_between']:>8.3f} {1e3 * s['min_exact_bound']:>7.3f} "
              f"{s['below_margin_slack']:>7} {1e3 * s['max_vf_violation']:>6.3f} "
              f"{1e3 * s['min_barrier']:>6.3f} {s['faults']:>6} {1e3 * s['max_tcp_step']:>8.3f} "
              f"{1e3 * s['max_recovery_step']:>6.3f} {1e3 * s['max_hold_motion']:>6.3f} "
              f"{s['reached']:>4}/{s['runs']}")
    print(f"margin {1e3 * res['margin']:.1f} mm, fixture {'on' if res['fixture'] else 'off'}, "
          f"limits {res['limits']}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="seeds per kind and site")
    parser.add_argument("--normal", type=int, default=3, help="calm feeds per site")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kinds", help=f"comma-separated subset of {','.join(KINDS)}")
    parser.add_argument("--no-fixture", action="store_true",
                        help="the supervisor alone (the fixture passes every command)")
    parser.add_argument("--jumps", action="store_true",
                        help="the full jump sweep (sizes x 14 directions x held/out and back)")
    parser.add_argument("--json", help="write every run here")
    args = parser.parse_args(argv)
    kinds = KINDS if not args.kinds else tuple(args.kinds.split(","))
    unknown = sorted(set(kinds) - set(KINDS))
    if unknown:
        parser.error(f"unknown kinds: {', '.join(unknown)}")
    t0 = time.perf_counter()
    if args.jumps:
        res = jump_study(seed=args.seed, fixture=not args.no_fixture)
    else:
        res = study(seeds=args.seeds, normal=args.normal, seed=args.seed, kinds=kinds,
                    fixture=not args.no_fixture)
    print_summary(res)
    print(f"{time.perf_counter() - t0:.0f} s")
    if args.json:
        write_json(args.json, res, kind="adversarial")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
