"""Benchmark: the supervisor's clearance per pose, the FPSM bound beside the capped scan bound.

Run: ``python -m implantplan.analyses.bench_scan_barrier --plan DIR [--seed S]``

Along every site's planned feed of a plan folder (poses every 0.5 mm, and as many again moved by
0.5 mm at random), prints per pose, side by side in one run: the FPSM's sound clearance
(``ToolClearance``) and the scan bound capped at 2, 3 and 5 mm (``CappedScanClearance``; the
supervisor's cap is its margin + ``diagrams.teleop.CAP_BAND``), each with its minimum, its
false-safe count against FCL on the scan (``ExactCavity.tool_clearance`` of the same solids) and
how far below FCL it is where FCL is below the cap.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from implantplan.analyses.live_setup import load_plan
from implantplan.systems.errors import InputError
from implantplan.systems.placement.scan_clearance import CappedScanClearance
from implantplan.systems.placement.tool_clearance import ToolClearance, feed_depth, feed_poses

CAPS = (2e-3, 3e-3, 5e-3)  # m


def per_pose(fn, X) -> tuple[float, np.ndarray]:
    """(us per pose, values) of ``fn`` on one pose at a time (as the 200 Hz loop calls it)."""
    fn(X[0])  # compiled once
    t = time.perf_counter()
    v = np.array([fn(x) for x in X])
    return 1e6 * (time.perf_counter() - t) / len(X), v


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plan", required=True, help="a plan folder (implantplan plan/demo)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:
        sp = load_plan(args.plan, reference=False)
        if sp.exact is None:
            raise InputError("--plan", "the case file the plan names is not there; the scan "
                             "bound needs its scan")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    print(f"{'site':<6} {'bound':<18} {'us/pose':>8} {'min (mm)':>9} {'false-safe':>11} "
          f"{'below FCL (mm)':>15}")
    for k, name in enumerate(sp.names):
        case = sp.teleop_case(k)
        X = np.asarray(sp.plan["sites"][k]["placement"]["X_CT"], dtype=float)
        P = feed_poses(X, feed_depth(sp.fpsm, X, case.tool), 0.5e-3)[0][0]
        Q = P.copy()
        Q[:, :3, 3] += rng.normal(0.0, 0.5e-3, (len(P), 3))
        P = np.ascontiguousarray(np.concatenate([P, Q]))
        fcl = case.scan.exact.tool_clearance(P, case.tool)
        rows = [("FPSM", ToolClearance(sp.fpsm, case.tool).one, np.inf)]
        rows += [(f"scan, cap {c * 1e3:g} mm", CappedScanClearance(case.scan, c).one, c)
                 for c in CAPS]
        for label, fn, cap in rows:
            us, v = per_pose(fn, P)
            near = fcl < cap
            gap = (f"{1e3 * float(np.max(np.minimum(fcl, cap)[near] - v[near])):.2f}"
                   if near.any() and np.isfinite(cap) else "-")
            print(f"{name:<6} {label:<18} {us:>8.1f} {1e3 * v.min():>9.2f} "
                  f"{int(np.sum(v > fcl + 1e-12)):>11d} {gap:>15}")
        print(f"{name:<6} {'FCL':<18} {'':>8} {1e3 * fcl.min():>9.2f}   ({len(P)} poses)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
