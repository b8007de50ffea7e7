"""``implantplan analyze moprp-fidelity``: why does the selected layout not win as in seed 001?

    implantplan analyze moprp-fidelity [--scenario lying|sitting] [--draws D] [--random N]
        [--pool P] [--seed S] [--quiet] --out DIR

Seed 001 reports its selected layout best on GII and beaten by only 3 of 20 random layouts on
joint variation; ``implantplan analyze layouts`` ranked ours 10th-15th on joint travel and last
on GII. This study measures each candidate cause on the same footing, with the
closed-form kinematics only (no Drake simulation), over ``--draws`` independent draws of
``--random`` random layouts (a single draw of 20 is noisy: the rank of a fixed layout among 20
random ones moves by several places between draws):

1. **Units.** GII = sigma_min / sigma_max of the 6x6 body Jacobian [J_w; J_v] mixes rad and m:
   in SI (J_v in m/rad) against the paper's likely MATLAB units (J_v in mm/deg, J_w in deg/deg,
   i.e. J_v scaled by 1000 pi / 180). The error index I_e = eps sigma_max(J_v) and dexterity are
   a constant factor and unit-free per block: their ranks do not depend on units (checked).
   Also the GII of the translational Jacobian J_v alone (unit-free).
2. **Selection rule** on the NSGA-II front (systems.robot.moprp.search): the knee (normalized
objective
   space, equal weights: the default), score-based (rank points over the front, summed, as the
   paper's Fig. 4 does among branches), the raw weighted sum in SI and in mm/deg (what an
   unnormalized MATLAB sum would pick), and joint variation alone.
3. **Operator model** in the joint-travel experiment: travel of the closed-form IK along the
   scripted operator's TCP path (systems.teleop.master_device.scripted_feed): ideal straight feed,
   tremor only, drift only, pauses only (pauses add time, not travel, in a kinematic replay), and
   the default operator (tremor, drift, pauses, overshoot).
4. **How the random layouts are drawn**: uniform feasible bases in the scenario's bounds (what
   ``analyze layouts`` does), feasible bases within 100 mm of the selection, and random members
   of the final NSGA-II front.

Writes ``DIR/moprp_fidelity.json`` (kind ``moprp_fidelity``) and ``DIR/moprp_fidelity.png``, and
prints the table of ranks: for each variant and metric the median rank of the selection among
its 20 random layouts (1 = best) and the share of draws where it ranks within the paper's
result (GII: 1st; joint travel: top 4).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from implantplan.analyses import out_folder
from implantplan.analyses.progress import Progress
from implantplan.systems import actuator, seeds
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_json
from implantplan.systems.frames import invert
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp
from implantplan.systems.teleop.master_device import IncrementalMapping, Operator, scripted_feed

MM_PER_M_DEG_PER_RAD = 1000.0 * np.pi / 180.0  # J_v (m/rad) -> (mm/deg)
OPERATORS = {
    "ideal": Operator(drift=0.0, tremor=0.0, pauses_per_feed=0.0, overshoot=(0.0, 0.0)),
    "tremor only": Operator(drift=0.0, pauses_per_feed=0.0, overshoot=(0.0, 0.0)),
    "drift only": Operator(tremor=0.0, pauses_per_feed=0.0, overshoot=(0.0, 0.0)),
    "pauses only": Operator(drift=0.0, tremor=0.0, overshoot=(0.0, 0.0)),
    "default operator": Operator(),
}
RULES = ("knee", "score", "raw sum SI", "raw sum mm/deg", "joint variation only")
DRAWS = ("uniform feasible in bounds", "within 100 mm of the selection", "GA front members")


def gii_units(xyz, branch: int, sc: moprp.Scenario, rng, n: int = 100) -> dict:
    """GII over ``n`` random poses about Oral on ``branch`` (moprp.gii's poses), in SI and with
    J_v in mm/deg (J_w in deg/deg); NaN when no pose is reached."""
    X_BEp = invert(moprp.base_pose(xyz)) @ moprp.gii_poses(n, rng)
    q, ok = moprp.ik_closed_form(X_BEp, limits=sc.limits, X_FT=sc.X_FT)
    if not np.any(ok[:, branch]):
        return {"SI": np.nan, "mm/deg": np.nan, "J_v": np.nan}
    J = kin.jacobian_body(q[ok[:, branch], branch], sc.X_FT)
    out = {}
    for name, scale in (("SI", 1.0), ("mm/deg", MM_PER_M_DEG_PER_RAD)):
        Js = J.copy()
        Js[:, 3:] *= scale
        s = np.linalg.svd(Js, compute_uv=False)
        out[name] = float(s.min() / s.max())
    s = np.linalg.svd(J[:, 3:], compute_uv=False)  # the translational Jacobian alone
    out["J_v"] = float(s.min() / s.max())
    return out


def operator_travel(xyz, branch: int, sc: moprp.Scenario, operator: Operator, *,
                    feeds: int = 3, seed: int = 0) -> float:
    """Mean joint travel (rad) of the closed-form IK on ``branch`` following the scripted
    operator's TCP path from the pre-feed pose to the target (orientation held), over
    ``feeds`` feeds; NaN when the branch cannot follow it."""
    start = moprp.feed_poses(xyz, sc.feed_length, 2)[0][:3, 3]  # TCP pre-feed, in Base
    target = moprp.target_pose(xyz)
    mapping = IncrementalMapping()
    rng = np.random.default_rng(seed)
    travel = []
    for _ in range(feeds):
        motion = scripted_feed(start, target[:3, 3], seed=rng, operator=operator,
                               mapping=mapping)
        p_B = start + mapping.to_world(motion.p_M)
        X = np.broadcast_to(target, (p_B.shape[0], 4, 4)).copy()
        X[:, :3, 3] = p_B
        r = kin.ik(X, limits=sc.limits, X_FT=sc.X_FT)
        if not np.all(r.valid[:, branch]):
            return float("nan")
        q = r.q[:, branch]
        step = np.abs(np.diff(q, axis=0))
        if step.max() > sc.max_joint_step:
            return float("nan")
        travel.append(float(step.sum()))
    return float(np.mean(travel))


def select(front_F, rule: str, rng) -> int:
    """Index of the front member chosen by ``rule`` (see the module docstring)."""
    F = np.asarray(front_F, dtype=float)
    if rule == "knee":
        return moprp.knee_point(F)
    if rule == "score":
        choice, _ = moprp.select(F[None], np.ones((1, F.shape[0]), bool), rng)
        return int(choice[0])
    if rule == "raw sum SI":
        return int(np.argmin(F.sum(axis=1)))
    if rule == "raw sum mm/deg":
        return int(np.argmin(F[:, 0] + 1000 * F[:, 1] + np.degrees(F[:, 2])))
    if rule == "joint variation only":
        return int(np.argmin(F[:, 2]))
    raise InputError("rule", f"expected one of {', '.join(RULES)}, got {rule!r}")


def layout_metrics(xyz, sc: moprp.Scenario, rng, *, seed: int = 0) -> list[dict]:
    """Per base (MOPRP-feasible): branch, indices, GII in both units and the joint travel of
    every operator model."""
    ev = moprp.evaluate_bases(xyz, sc, rng)
    out = []
    for i in np.flatnonzero(ev.feasible):
        b = int(ev.branch[i])
        g = gii_units(xyz[i], b, sc, np.random.default_rng(seed))
        m = {"base_xyz": xyz[i], "branch": b,
             "dexterity": float(ev.objectives[i, 0]), "error_range": float(ev.objectives[i, 1]),
             # eps in deg times sigma_max(J_v in mm/deg) = 1000 eps sigma_max(J_v in m/rad)
             "error_range_mm_deg": float(1000.0 * ev.objectives[i, 1]),
             "joint_variation": float(ev.objectives[i, 2]),
             "gii SI": g["SI"], "gii mm/deg": g["mm/deg"], "gii J_v": g["J_v"]}
        for name, op in OPERATORS.items():
            m[f"travel {name}"] = operator_travel(xyz[i], b, sc, op, seed=seed)
        out.append(m)
    return out


METRICS = (("gii SI", True), ("gii mm/deg", True), ("gii J_v", True), ("joint_variation", False),
           ("error_range", False), ("error_range_mm_deg", False),
           *((f"travel {name}", False) for name in OPERATORS))


def rank(value: float, others, higher_is_better: bool) -> int:
    """1-based rank of ``value`` among ``others`` (ties in its favour; NaN others ignored)."""
    o = np.asarray(others, dtype=float)
    o = o[np.isfinite(o)]
    return int(1 + np.sum(o > value if higher_is_better else o < value))


def study(scenario: str = "lying", *, draws: int = 25, random_layouts: int = 20,
          pool: int = 300, seed: int = 0, progress: Progress | None = None) -> dict:
    """The four candidate causes (module docstring); returns the JSON-ready result."""
    progress = progress or Progress("moprp-fidelity", quiet=True)
    sc = moprp.load_scenario(scenario, X_FT=actuator.X_FT())
    sc = dataclasses.replace(sc, pop=min(sc.pop, 200), gen=min(sc.gen, 150),
                             seed=seeds.seed(sc.seed, seed))
    res = moprp.search(sc, moprp.problem(sc))
    progress.say(f"{sc.name}: front of {res.X.shape[0]} bases after {res.generations} "
                 "generations")
    rng = np.random.default_rng(seed)
    chosen = {}
    for rule in RULES:
        k = select(res.F, rule, np.random.default_rng(seed))
        chosen[rule] = layout_metrics(res.X[k : k + 1], sc, rng, seed=seed)[0]
    progress.say("selections: " + "; ".join(
        f"{r} {np.round(1000 * chosen[r]['base_xyz']).astype(int).tolist()} mm" for r in RULES))

    # pools of random layouts, metrics computed once per pool
    X_uni, _ = moprp.random_feasible(sc, pool, rng)
    sel = chosen["knee"]["base_xyz"]
    lo, hi = np.maximum(sc.lower, sel - 0.1), np.minimum(sc.upper, sel + 0.1)
    near = dataclasses.replace(sc, lower=lo, upper=hi)
    X_near, _ = moprp.random_feasible(near, pool, rng)
    pools = {}
    for name, X in zip(DRAWS, (X_uni, X_near, res.X), strict=True):
        pools[name] = layout_metrics(X[:pool], sc, rng, seed=seed)
        progress.say(f"pool '{name}': {len(pools[name])} feasible layouts")

    def ranks_of(layout, pool_metrics) -> dict:
        draw_rng = seeds.rng(seed, 1)
        n = len(pool_metrics)
        out = {m: [] for m, _ in METRICS}
        for _ in range(draws):
            idx = draw_rng.choice(n, size=min(random_layouts, n), replace=False)
            for m, hib in METRICS:
                out[m].append(rank(layout[m], [pool_metrics[i][m] for i in idx], hib))
        return {m: {"median": float(np.median(r)),
                    "best_share": float(np.mean(np.asarray(r) == 1)),
                    "top4_share": float(np.mean(np.asarray(r) <= 4)), "ranks": r}
                for m, r in out.items()}

    table = []
    for rule in RULES:
        for draw in DRAWS:
            if rule != "knee" and draw != DRAWS[0]:
                continue  # rules compared on the default draw, draws with the default rule
            table.append({"rule": rule, "draw": draw,
                          "ranks": ranks_of(chosen[rule], pools[draw])})
    return {"scenario": sc.name, "front": int(res.X.shape[0]), "generations": res.generations,
            "draws": draws, "random_layouts": random_layouts, "pool": pool, "seed": seed,
            "selected": chosen, "table": table,
            "operators": {k: dataclasses.asdict(v) for k, v in OPERATORS.items()}}


def table_text(result: dict) -> str:
    """The table of ranks: median rank among the random layouts (share of draws at rank 1 for
    GII, in the top 4 for travel)."""
    cols = [m for m, _ in METRICS]
    lines = [f"{result['scenario']}: median rank of the selection among "
             f"{result['random_layouts']} random layouts over {result['draws']} draws "
             "(GII: % of draws ranked 1st; others: % in the top 4)",
             "| rule | random layouts | " + " | ".join(cols) + " |",
             "|" + "---|" * (len(cols) + 2)]
    for row in result["table"]:
        cells = []
        for m in cols:
            r = row["ranks"][m]
            share = r["best_share"] if m.startswith("gii") else r["top4_share"]
            cells.append(f"{r['median']:.0f} ({100 * share:.0f}%)")
        lines.append(f"| {row['rule']} | {row['draw']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(result: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = [m for m, _ in METRICS]
    rows = result["table"]
    fig, ax = plt.subplots(figsize=(12, 0.5 * len(rows) + 2.5))
    M = np.array([[row["ranks"][m]["median"] for m in cols] for row in rows])
    im = ax.imshow(M, cmap="RdYlGn_r", vmin=1, vmax=result["random_layouts"] + 1, aspect="auto")
    for i in range(M.shape[0]):
        for j in range(M.shape[1]):
            ax.text(j, i, f"{M[i, j]:.0f}", ha="center", va="center", fontsize=8)
    ax.set_xticks(range(len(cols)), cols, rotation=35, ha="right", fontsize=8)
    ax.set_yticks(range(len(rows)), [f"{r['rule']} / {r['draw']}" for r in rows], fontsize=8)
    ax.set_title(f"{result['scenario']}: median rank of the selection among "
                 f"{result['random_layouts']} random layouts (1 = best)")
    fig.colorbar(im, ax=ax, shrink=0.7, label="median rank")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def register_analysis(sub) -> None:
    """Add ``moprp-fidelity`` to the ``analyze`` subcommands (analyses.simulate)."""
    p = sub.add_parser("moprp-fidelity", help="why the selected layout does (not) win: units, "
                       "selection rule, operator model, random-layout draw")
    p.add_argument("--scenario", default="lying", help="bundled scenario or scenario YAML")
    p.add_argument("--draws", type=int, default=25, help="draws of the random layouts")
    p.add_argument("--random", type=int, default=20, help="random layouts per draw (paper: 20)")
    p.add_argument("--pool", type=int, default=300, help="feasible layouts per pool")
    p.add_argument("--seed", type=int, default=0, help="seed of the random layouts (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder (moprp_fidelity.json and .png)")
    p.set_defaults(func=_cmd)


def _cmd(args: argparse.Namespace) -> int:
    for name in ("draws", "random", "pool"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name}", f"expected >= 1, got {getattr(args, name)}")
    out_folder.check_out(args.out, force=None)  # before any work
    progress = Progress("moprp-fidelity", quiet=args.quiet)
    result = study(args.scenario, draws=args.draws, random_layouts=args.random, pool=args.pool,
                   seed=args.seed, progress=progress)
    out_folder.claim(args.out, "moprp_fidelity")
    write_json(args.out / "moprp_fidelity.json", result, kind="moprp_fidelity")
    plot(result, args.out / "moprp_fidelity.png")
    print(table_text(result))
    return 0

