"""The instrument the safety layer protects against the instrument in the mouth, on the bundled
default case: what the plan's feed does to the shipped actuator, and the fast bound of the real
instrument against FCL on the scan.

Run: ``python -m implantplan.analyses.studies.instrument_check [--poses 20000] [--seed 0]
[--out DIR]``.

The default case is fitted and placed as ``implantplan plan`` does (its own instrument, the
case's ``instrument`` section), then for each site:

1. **The planned feed** (the feeding target backed out along the rod every 0.5 mm to above the
   mouth opening): the exact clearance (FCL against the opened scan,
   :meth:`systems.placement.exact_clearance.ExactCavity.tool_clearance`, every solid as it is) of
   the paper's thin tool and of the shipped actuator (systems.instrument), the smallest and the
   number of poses in tissue.
2. **Bound vs exact** on ``--poses`` random poses about the site's feed (lateral offsets up to
   8 mm, tilts up to 12 deg about the axis point at the head, every depth of the feed): the
   fast bound (:class:`systems.placement.tool_clearance.ToolClearance` of the actuator's capsule
   cover, certified against the FPSM) against the exact clearance against the scan. Printed:
   false-safe counts (the verdict: bound >= margin where exact < margin; the value: bound above
   exact by more than 1 um where the instrument is exactly free, the only place the exact value
   is a distance rather than a conservative depth), the largest such excess, and the share of
   poses exactly clear by >= margin + 0.2 mm that the bound calls clear by >= margin (how much
   free space the bound refuses).

Writes ``instrument_check.json`` to ``--out`` (a new folder) when given.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from implantplan.analyses.progress import Progress
from implantplan.systems import seeds
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_json
from implantplan.systems.frames import rotations
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.exact_clearance import ExactCavity
from implantplan.systems.placement.tool_clearance import (
    ToolClearance,
    feed_depth,
    feed_poses,
)

MAX_POSES = 1_000_000
FEED_STEP = 0.5e-3  # m, the independent check's spacing along the feed
LATERAL = 8e-3  # m, random lateral offset of the sampled poses
TILT = np.radians(12.0)  # rad, random tilt about the head centre


def sampled_poses(X_CT: np.ndarray, depth: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """n random poses about a planned feed: backed out by U(0, depth) along the rod, moved
    across the rod axis by up to :data:`LATERAL`, tilted by up to :data:`TILT` about the head
    centre (uniform rotation vectors in a ball)."""
    s = rng.uniform(0.0, depth, n)
    w = rng.normal(size=(n, 3))
    w *= (TILT * rng.uniform(0, 1, n) ** (1 / 3) / np.linalg.norm(w, axis=1))[:, None]
    lat = rng.uniform(-LATERAL, LATERAL, (n, 2))
    X = np.repeat(X_CT[None], n, axis=0)
    X[:, :3, 3] += s[:, None] * X_CT[:3, 0] + lat[:, :1] * X_CT[:3, 1] + lat[:, 1:] * X_CT[:3, 2]
    X[:, :3, :3] = rotations(w) @ X_CT[:3, :3]
    return X


def check_site(fpsm, exact: ExactCavity, X_CT: np.ndarray, *, poses: int, margin: float,
               rng: np.random.Generator) -> dict:
    """Both measurements (module notes) at one planned feeding target."""
    paper, real = Instrument.paper(), Instrument.actuator()
    out = {"feed": {}}
    for name, inst in (("paper", paper), ("actuator", real)):
        depth = feed_depth(fpsm, X_CT, inst)
        P, _ = feed_poses(X_CT, depth, FEED_STEP)
        c = exact.tool_clearance(P[0], inst)
        out["feed"][name] = {"exact_min_m": float(c.min()), "poses": int(c.size),
                             "poses_in_tissue": int((c <= 0).sum()),
                             "at_backout_m": float(np.argmin(c) * depth / max(c.size - 1, 1))}
    depth = feed_depth(fpsm, X_CT, real)
    X = sampled_poses(X_CT, depth, poses, rng)
    bound = ToolClearance(fpsm, real)(X)
    truth = exact.tool_clearance(X, real)
    excess = np.where(truth > 0, bound - truth, -np.inf)
    free = truth >= margin + 0.2e-3
    out["bound_vs_exact"] = {
        "poses": int(poses),
        "false_safe_verdict": int(((bound >= margin) & (truth < margin)).sum()),
        "false_safe_value": int((excess > 1e-6).sum()),
        "largest_excess_m": float(excess.max()),
        "exactly_in_tissue": int((truth <= 0).sum()),
        "exactly_free_by_margin_plus_0.2mm": int(free.sum()),
        "called_safe_share": float((bound[free] >= margin).mean()) if free.any() else None,
        "median_gap_m_where_free": float(np.median(truth[free] - bound[free]))
        if free.any() else None,
    }
    return out


def study(*, poses: int = 20_000, seed: int = 0, progress: Progress | None = None) -> dict:
    from implantplan.analyses import pipeline
    from implantplan.analyses.case import default_case_path, load_case

    if not 1 <= poses <= MAX_POSES:
        raise InputError("--poses", f"expected 1..{MAX_POSES}, got {poses}")
    progress = progress or Progress("instrument-check", quiet=True)
    case = load_case(default_case_path())
    fit = pipeline.fit_stage(case)
    placements = pipeline.placement_stage(case, fit)
    exact = fit.exact(case.mesh.close_open_cuts)  # the one the placement verified against
    sites = {}
    for k, (site, p) in enumerate(zip(case.sites, placements, strict=True)):
        progress.say(f"site {site.name}: {poses} poses")
        sites[site.name] = check_site(fit.fpsm, exact, p.X_CT, poses=poses,
                                      margin=case.safety.clearance_margin, rng=seeds.rng(seed, k))
    return {"case": case.name, "seed": seed, "margin_m": case.safety.clearance_margin,
            "feed_step_m": FEED_STEP, "sites": sites}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m implantplan.analyses.studies.instrument_check",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    try:
        if args.seed < 0:
            raise InputError("--seed", f"expected an integer >= 0, got {args.seed}")
        if args.out is not None and args.out.exists():
            raise InputError("--out", f"{args.out} exists; expected a new folder")
        res = study(poses=args.poses, seed=args.seed, progress=Progress("instrument-check"))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for name, s in res["sites"].items():
        for tool, f in s["feed"].items():
            print(f"site {name}: {tool:8s} feed exact min {1e3 * f['exact_min_m']:+.2f} mm, "
                  f"{f['poses_in_tissue']} of {f['poses']} poses in tissue "
                  f"(worst {1e3 * f['at_backout_m']:.1f} mm before the target)")
        b = s["bound_vs_exact"]
        share = "n/a" if b["called_safe_share"] is None else f"{100 * b['called_safe_share']:.1f}%"
        print(f"site {name}: bound vs FCL on {b['poses']} poses ({b['exactly_in_tissue']} in "
              f"tissue): false-safe verdicts {b['false_safe_verdict']}, values "
              f"{b['false_safe_value']} (largest excess {1e3 * b['largest_excess_m']:+.3f} mm); "
              f"free by margin + 0.2 mm called safe: {share}")
    if args.out is not None:
        args.out.mkdir(parents=True)
        write_json(args.out / "instrument_check.json", res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
