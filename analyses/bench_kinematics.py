"""Benchmark: closed-form kinematics vs Drake's generic path, measured side by side in one run.

Prints:
  - closed-form IK (all 8 branches) poses/s on a batch of 100,000 poses, one core;
  - Drake multi-start IK (diagrams.ik_drake, the cross-check path) poses/s on a few poses;
  - their ratio (target: closed form >= 200,000 poses/s and >= 1000x Drake's path);
  - FK + Jacobian batch throughput of the numpy core vs a MultibodyPlant loop
    (diagrams.plant.fk_jacobian_loop: SetPositions, CalcRelativeTransform and two
    CalcJacobianSpatialVelocity per configuration).

Run: ``python -m implantplan.analyses.bench_kinematics [--batch 100000] [--drake-poses 5]
[--starts 64]``.
"""

from __future__ import annotations

import argparse
import timeit

import numpy as np


def _best_of(fn, repeats: int) -> float:
    """Fastest of ``repeats`` single calls (s), timeit.repeat (garbage collection off)."""
    return min(timeit.repeat(fn, number=1, repeat=repeats))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=100_000)
    parser.add_argument("--drake-poses", type=int, default=5)
    parser.add_argument("--starts", type=int, default=128, help="Drake starts per pose")
    parser.add_argument("--plant-configs", type=int, default=2000)
    args = parser.parse_args(argv)

    from implantplan.diagrams.ik_drake import DrakeIk
    from implantplan.diagrams.plant import fk_jacobian_loop
    from implantplan.systems.robot import kinematics as kin

    rng = np.random.default_rng(0)
    lim = np.deg2rad(175.0)
    q = rng.uniform(-lim, lim, (args.batch, 6))
    X = kin.fk(q)
    kin.ik(X[:10])  # compile (numba cache) outside the timing

    t_ik = _best_of(lambda: kin.ik(X), 3)
    cf_rate = args.batch / t_ik
    res = kin.ik(X)
    print(f"closed-form IK : {cf_rate:12,.0f} poses/s  ({args.batch} poses, 8 branches, "
          f"{res.valid.sum(axis=1).mean():.2f} valid branches/pose)")

    solver = DrakeIk()
    counts, infos = [], []

    def drake_poses():
        for i in range(args.drake_poses):
            q_d, info = solver.solve(X[i], starts=args.starts, seed=i)
            counts.append((len(q_d), int(res.valid[i].sum())))
            infos.append(info)

    t_drake = timeit.timeit(drake_poses, number=1)
    info = infos[-1]
    drake_rate = args.drake_poses / t_drake
    print(f"Drake IK       : {drake_rate:12,.2f} poses/s  ({args.drake_poses} poses, "
          f"{args.starts} starts each, solver {info.solver})")
    print(f"ratio          : {cf_rate / drake_rate:12,.0f}x  (target >= 1000x)")
    print("branch counts Drake/closed-form: " + " ".join(f"{a}/{b}" for a, b in counts))

    n = args.plant_configs
    qs = q[:n]
    t_np = _best_of(lambda: (kin.fk(qs), kin.jacobian_space(qs), kin.jacobian_body(qs)), 3)
    plant, context = solver.plant, solver.plant_context
    base, flange = plant.GetFrameByName("base_link"), plant.GetFrameByName("wrist3_Link")

    def plant_loop():
        fk_jacobian_loop(plant, context, base, flange, qs)

    t_plant = _best_of(plant_loop, 1)
    print(f"FK+Jacobian    : numpy {n / t_np:12,.0f} configs/s, MultibodyPlant loop "
          f"{n / t_plant:10,.0f} configs/s, ratio {t_plant / t_np:,.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
