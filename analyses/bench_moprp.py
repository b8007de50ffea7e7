"""MOPRP benchmark.

Run: ``python -m implantplan.analyses.bench_moprp [--scenario lying] [--agreement N]``.

Prints, measured side by side in one run:

1. evaluations/s of the problem (``systems.moprp.evaluate_bases``) with the closed-form IK vs
   the Drake multi-start IK path (``--ik drake``: diagrams.ik_drake, 64 starts per pose), ratio;
2. the paper-setting run (500 x 500, all generations): wall time split into problem evaluation
   and optimizer overhead (our compiled NSGA-II: sort, crowding, variation, hypervolume);
3. time-to-front: the time until the front's hypervolume is within 1% of the 500 x 500 front's
   (common normalization: the final front's ideal and nadir, reference at nadir + 10% range),
   and the default run that stops on hypervolume stagnation (time, generations, its hypervolume
   relative to the 500 x 500 front's);
4. agreement of the capsule collision test (condition 2 and the arm's self pairs) with Drake's
   SceneGraph on random configurations (the URDF's cylinders/boxes/capsules, diagrams.plant).

The issue's reference numbers: pymoo NSGA-II ~56 s of its own bookkeeping at 500 x 500, pygmo
~14 s; targets: evaluation < 20% of the total (we read it as the optimizer's overhead < 20%, the
meaningful target: see the report), time-to-front < 15 s.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from implantplan.systems import moprp
from implantplan.systems.nsga2 import hypervolume, nsga2

# capsule name -> body name in the Drake plant (arm URDF + actuator URDF)
BODY_OF = {
    "base": "base_link",
    "shoulder": "shoulder_Link",
    "upper_arm_housing": "upperArm_Link",
    "upper_arm": "upperArm_Link",
    "forearm_housing": "foreArm_Link",
    "forearm": "foreArm_Link",
    "wrist1": "wrist1_Link",
    "wrist2": "wrist2_Link",
    "wrist3": "wrist3_Link",
    "actuator_rod": "actuator_base",
    "actuator_head": "actuator_base",
    "actuator_implant": "actuator_base",
    "actuator_body": "actuator_base",
}


def evals_per_second(sc, n_closed=20000, n_drake=2, starts=64):
    """(closed-form evals/s, Drake evals/s, Drake IK poses solved, same surviving branches,
    largest objective difference on the Drake-evaluated bases)."""
    from implantplan.analyses.robot_place import drake_ik_solver

    rng = np.random.default_rng(0)
    X = sc.lower + rng.random((n_closed, 3)) * (sc.upper - sc.lower)
    moprp.evaluate_bases(X[:50], sc, rng)  # compile
    t = time.perf_counter()
    moprp.evaluate_bases(X, sc, rng)
    cf = n_closed / (time.perf_counter() - t)
    solver = drake_ik_solver(starts=starts, seed=0, limits=sc.limits, X_FT=sc.X_FT)
    Xd = X[:n_drake]
    t = time.perf_counter()
    ev_d = moprp.evaluate_bases(Xd, sc, rng, ik_solver=solver)
    dk = n_drake / (time.perf_counter() - t)
    ev_c = moprp.evaluate_bases(Xd, sc, np.random.default_rng(1))
    same = np.array_equal(ev_d.valid, ev_c.valid)
    both = ev_d.feasible & ev_c.feasible
    diff = float(np.abs(ev_d.objectives[both] - ev_c.objectives[both]).max()) if both.any() \
        else float("nan")
    return cf, dk, solver.stats["poses"], same, diff


def _normalized_hv(F, lo, hi):
    span = np.where(hi > lo, hi - lo, 1.0)
    return hypervolume((F - lo) / span, np.full(3, 1.1))


def paper_run(sc, seed):
    """The 500 x 500 run without early stop, with its history; and the default stagnation run."""
    full = dataclasses.replace(sc, patience=None)
    ev = moprp.problem(full)
    r = nsga2(ev, sc.lower, sc.upper, pop=sc.pop, gen=sc.gen, seed=seed, patience=None,
              record_history=True)
    F_final = r.F[r.front]
    lo, hi = F_final.min(axis=0), F_final.max(axis=0)
    hv_final = _normalized_hv(F_final, lo, hi)
    t_front = None
    for g, secs, n_eval, _, F in r.history:
        if F.shape[0] and _normalized_hv(F, lo, hi) >= 0.99 * hv_final:
            t_front = (g, secs, n_eval)
            break
    r2 = nsga2(moprp.problem(sc), sc.lower, sc.upper, pop=sc.pop, gen=sc.gen, seed=seed,
               patience=sc.patience, hv_tol=sc.hv_tol)
    hv2 = _normalized_hv(r2.F[r2.front], lo, hi) / hv_final
    return r, t_front, r2, hv2


def scenegraph_agreement(n=10000, seed=0, limits="175"):
    """Compare capsule clearances with Drake's SceneGraph on ``n`` random configurations.

    Pairs: the bodies of systems.moprp.SELF_PAIRS (actuator vs arm links, wrists vs base/
    shoulder/upper arm, forearm vs base/shoulder). Per configuration, "in collision" = any of
    these body pairs penetrates (Drake: ComputePointPairPenetration on the URDF geometry;
    capsules: clearance < 0). Returns a dict with the agreement and the confusion counts.
    """
    from implantplan.diagrams.plant import build_plant

    diagram, plant, scene_graph, handles = build_plant(scenario="arm", tool=True, limits=limits)
    context = diagram.CreateDefaultContext()
    pc = plant.GetMyMutableContextFromRoot(context)
    sgc = scene_graph.GetMyContextFromRoot(context)
    inspector = scene_graph.model_inspector()
    body_pairs = set()
    for a, b in moprp.SELF_PAIRS:
        body_pairs.add(frozenset((BODY_OF[a], BODY_OF[b])))

    def body_name(gid):
        return plant.GetBodyFromFrameId(inspector.GetFrameId(gid)).name()

    sc = moprp.load_scenario("lying")
    sc = dataclasses.replace(sc, X_FT=sc.actuator.X_FT())
    model = moprp.CollisionModel.for_scenario(sc)
    rng = np.random.default_rng(seed)
    lim = np.deg2rad(175.0) if limits == "175" else np.pi
    Q = rng.uniform(-lim, lim, (n, 6))
    d_caps = moprp.collision_clearance(Q, np.zeros((n, 3)), sc, model)["self"]
    drake_hit = np.zeros(n, dtype=bool)
    query_port = scene_graph.get_query_output_port()
    t = time.perf_counter()
    for i in range(n):
        plant.SetPositions(pc, handles.arm, Q[i])
        qo = query_port.Eval(sgc)
        for pen in qo.ComputePointPairPenetration():
            if frozenset((body_name(pen.id_A), body_name(pen.id_B))) in body_pairs:
                drake_hit[i] = True
                break
    t_drake = time.perf_counter() - t
    caps_hit = d_caps < 0
    return {
        "configurations": n,
        "agreement": float(np.mean(caps_hit == drake_hit)),
        "both_collide": int(np.sum(caps_hit & drake_hit)),
        "both_free": int(np.sum(~caps_hit & ~drake_hit)),
        "capsules_only": int(np.sum(caps_hit & ~drake_hit)),
        "drake_only": int(np.sum(~caps_hit & drake_hit)),
        "drake_seconds": t_drake,
        "clearance_of_disagreements_mm": (1000 * np.abs(d_caps[caps_hit != drake_hit])).tolist(),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="lying")
    ap.add_argument("--agreement", type=int, default=10000,
                    help="random configurations for the SceneGraph check (0 = skip)")
    ap.add_argument("--drake-bases", type=int, default=2)
    ap.add_argument("--skip-paper-run", action="store_true")
    args = ap.parse_args(argv)
    sc = moprp.load_scenario(args.scenario)

    cf, dk, poses, same, diff = evals_per_second(sc, n_drake=args.drake_bases)
    print(f"== evaluation throughput ({sc.name}, {sc.feed_samples} feed samples per base)")
    print(f"closed-form IK path : {cf:12.1f} bases/s")
    print(f"Drake IK path       : {dk:12.4f} bases/s  ({poses} poses, 64 starts each)")
    print(f"ratio               : {cf / dk:12.0f} x")
    print(f"same surviving branches on the Drake-evaluated bases: {same}; largest objective "
          f"difference {diff:.2e}")

    if not args.skip_paper_run:
        r, t_front, r2, hv2 = paper_run(sc, seed=sc.seed + 1)
        print(f"\n== paper setting {sc.pop} x {sc.gen} ({sc.name})")
        print(f"total               : {r.seconds_total:8.2f} s   front {r.front.size}")
        print(f"problem evaluation  : {r.seconds_eval:8.2f} s   "
              f"({100 * r.seconds_eval / r.seconds_total:.1f}%)")
        over = r.seconds_total - r.seconds_eval
        print(f"optimizer overhead  : {over:8.2f} s   ({100 * over / r.seconds_total:.1f}%)   "
              "[pymoo ~56 s, pygmo ~14 s measured by the issue author]")
        if t_front is not None:
            print(f"time-to-front (HV within 1% of the 500x500 front's): {t_front[1]:.2f} s "
                  f"(generation {t_front[0]}, {t_front[2]} evaluations)   [target < 15 s]")
        print(f"stagnation stop (patience {sc.patience}, tol {sc.hv_tol}): "
              f"{r2.seconds_total:.2f} s, {r2.generations} generations, "
              f"HV = {100 * hv2:.2f}% of the 500x500 front's, front {r2.front.size}")

    if args.agreement > 0:
        a = scenegraph_agreement(args.agreement)
        print(f"\n== capsules vs Drake SceneGraph ({a['configurations']} random configurations, "
              "self pairs of the collision-free principle)")
        print(f"agreement           : {100 * a['agreement']:.2f}%")
        print(f"both collide / both free / capsules only / Drake only: {a['both_collide']} / "
              f"{a['both_free']} / {a['capsules_only']} / {a['drake_only']}")
        dis = np.asarray(a["clearance_of_disagreements_mm"])
        if dis.size:
            print(f"|capsule clearance| at disagreements: median {np.median(dis):.1f} mm, "
                  f"max {dis.max():.1f} mm")
        print(f"Drake query time    : {1e3 * a['drake_seconds']:.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
