"""The certified clearance of a plan's fixture region against FCL at random poses of that region,
independently of how the certificate was reached (the worst-case loss or the branch and bound
over the region with FCL).

Run: ``python -m implantplan.analyses.studies.region_check [CASE ...] [--samples 8000]
[--seed 0]``.

Each case (default: the bundled default case) is fitted and placed as ``implantplan plan`` does
(a site that gets no placement is reported with the reason and skipped). For each placed site,
``--samples`` uniform random poses of the fixture's region along the whole feed
(:func:`systems.placement.tool_clearance.random_region_poses`: the feed offset, the TCP in the
lateral disc, the turn in the angle's ball at the TCP) get FCL's clearance of the head and the
implant (the solids whose region is a turn about the TCP; the long rod is held by its axis at
the mouth opening, which these samples do not keep). Printed per site: the certified value, how
it was reached, FCL's minimum over the samples and the false-safe count (samples closer than
the certified value). Exits 3 when any sample is.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from implantplan.analyses.progress import Progress
from implantplan.systems import seeds
from implantplan.systems.errors import InputError
from implantplan.systems.placement.tool_clearance import feed_poses, random_region_poses

MAX_SAMPLES = 200_000
FEED_STEP = 0.1e-3  # m, the feed poses the samples are drawn about


def check_site(exact, instrument, placement, safety, samples: int,
               rng: np.random.Generator) -> dict:
    """FCL at ``samples`` random poses of a placement's region vs its certified value."""
    ver = placement.verification
    turns = tuple(s for s, t in zip(instrument.shapes, instrument.turns_about_tcp(),
                                    strict=True) if t)
    solids = dataclasses.replace(instrument, shapes=turns)
    feed, _ = feed_poses(placement.X_CT, ver["feed_depth"], FEED_STEP)
    X = random_region_poses(feed[0], safety.lateral_tolerance, safety.angle_tolerance, samples,
                            rng)
    fcl = exact.tool_clearance(X, solids)
    certified = ver["clearance_certified"]
    region = (ver.get("scan_bound") or {}).get("region")
    return {"certified_m": certified,
            "how": "branch and bound with FCL" if region else "worst-case loss",
            "region": region, "solids": [s.name for s in turns], "samples": samples,
            "fcl_min_m": float(fcl.min()), "false_safe": int((fcl < certified).sum()),
            "gap_m": float(fcl.min() - certified)}


def study(cases, *, samples: int = 8000, seed: int = 0, progress: Progress | None = None) -> dict:
    from implantplan.analyses import pipeline
    from implantplan.analyses.case import load_case

    if not 1 <= samples <= MAX_SAMPLES:
        raise InputError("--samples", f"expected 1..{MAX_SAMPLES}, got {samples}")
    progress = progress or Progress("region-check", quiet=True)
    out = {}
    for c, path in enumerate(cases):
        case = load_case(path)
        fit = pipeline.fit_stage(case)
        exact = fit.exact(case.mesh.close_open_cuts)
        placements = pipeline.placement_stage(case, fit, require_valid=False)
        for k, (site, p) in enumerate(zip(case.sites, placements, strict=True)):
            key = f"{case.name}/{site.name}"
            if not p.valid:
                out[key] = {"refused": p.reason}
                progress.say(f"{key}: refused")
                continue
            out[key] = check_site(exact, case.instrument_at(site), p, case.safety, samples,
                                  seeds.rng(seed, c, k))
            progress.say(f"{key}: {out[key]['false_safe']} false-safe of {samples}")
    return {"seed": seed, "samples": samples, "sites": out}


def main(argv=None) -> int:
    from implantplan.analyses.case import default_case_path

    ap = argparse.ArgumentParser(prog="python -m implantplan.analyses.studies.region_check",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", nargs="*", type=Path)
    ap.add_argument("--samples", type=int, default=8000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        if args.seed < 0:
            raise InputError("--seed", f"expected an integer >= 0, got {args.seed}")
        res = study(args.cases or [default_case_path()], samples=args.samples, seed=args.seed,
                    progress=Progress("region-check"))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    bad = 0
    for key, r in res["sites"].items():
        if "refused" in r:
            print(f"{key}: refused ({r['refused'][:160]}...)")
            continue
        bad += r["false_safe"]
        extra = f", {r['region']['fcl_queries']} FCL queries" if r["region"] else ""
        print(f"{key}: certified {r['certified_m'] * 1e3:.3f} mm ({r['how']}{extra}); FCL over "
              f"{r['samples']} region samples ({'+'.join(r['solids'])}) min "
              f"{r['fcl_min_m'] * 1e3:.3f} mm, {r['gap_m'] * 1e3:.3f} mm above; false-safe "
              f"{r['false_safe']}")
    return 3 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
