"""``implantplan plan CASE.yaml --out DIR`` and ``implantplan demo``: one command from scan to plan.

Runs the stages of analyses.pipeline on a case file and writes, into DIR:

- ``plan.json`` (kind "plan"): everything a robot controller needs — the FPSM (file and summary),
  per site the placement, feeding target (in Center, World and base), virtual fixture, IK branch
  and pre-feed configuration, capability and feeding-simulation figures; the chosen base; and
  ``checks``, each with its value, limit, margin and pass/fail. Timings sit under ``timing`` only,
  so the same case and seed give the same plan apart from that key.
- ``fpsm.json``, ``figures/*.png``, ``layout.html`` (Meshcat static HTML of the selected layout)
  and ``report.html`` (one page: the plots of each stage, tables in mm/deg, the checks, the 3D
  scene).

Everything is written into a temporary folder beside DIR and moved into place at the end, so a
failed run never leaves a half-written plan (a previous DIR stays as it was). A planning failure
exits 3 with the reason; bad input exits 2 naming the field.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from implantplan.analyses import pipeline
from implantplan.analyses.case import Case, default_case_path, load_case
from implantplan.analyses.figures.plan import make_figures
from implantplan.analyses.progress import Progress
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_json
from implantplan.systems.frames import wrap_angle

DEMO_OUT = "implantplan-demo"
# Pass/fail limits of the checks (DESIGN.md section 4 and issue 6 acceptance figures).
MAX_PENETRATION_DEPTH = 0.5e-3  # m, dense check of the FPSM fit
GRID_TOL_D = 0.1e-3  # m, PSO vs exhaustive grid
GRID_TOL_THETA = np.deg2rad(0.1)
MIN_CAPABILITY = 0.5  # mean reachability index around a feeding target
MAX_VF_VIOLATION = 1e-3  # m


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "plan", help="plan a case: FPSM, placements + VF, robot base, capability, feeding sim",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("case", type=Path, help="case YAML (see models/cases/default.yaml)")
    _common(p, default_out=None)
    p.set_defaults(func=_cmd_plan)

    d = subparsers.add_parser(
        "demo", help="plan the bundled default case (real oral mesh, two implants, lying)",
    )
    _common(d, default_out=Path(DEMO_OUT))
    d.set_defaults(func=_cmd_demo)


def _common(p: argparse.ArgumentParser, default_out: Path | None) -> None:
    p.add_argument("--out", type=Path, required=default_out is None, default=default_out,
                   help="output folder" + (f" (default: ./{default_out})" if default_out else ""))
    p.add_argument("--runs", type=int, default=None,
                   help="feeding simulations per site (default: the case's simulation.runs)")
    p.add_argument("--no-html-scene", action="store_true",
                   help="skip the Meshcat static HTML of the layout")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def _cmd_plan(args) -> int:
    return _run(load_case(args.case), args)


def _cmd_demo(args) -> int:
    return _run(load_case(default_case_path()), args)


def _run(case: Case, args) -> int:
    if args.runs is not None and args.runs < 0:
        raise InputError("--runs", f"expected a number >= 0, got {args.runs}")
    t0 = time.perf_counter()
    plan = plan_case(case, args.out, runs=args.runs, html_scene=not args.no_html_scene,
                     quiet=args.quiet)
    failed = [c["name"] for c in plan["checks"] if not c["pass"]]
    print(f"plan: {args.out / 'plan.json'}")
    print(f"checks: {len(plan['checks']) - len(failed)} of {len(plan['checks'])} pass"
          + (f" (failed: {', '.join(failed)})" if failed else ""))
    print(f"time: {time.perf_counter() - t0:.1f} s")
    print(f"report: {(args.out / 'report.html').resolve()}")
    return 0


def plan_case(case: Case, out_dir: Path, *, runs: int | None = None, html_scene: bool = True,
              quiet: bool = False) -> dict:
    """Run every stage on ``case`` and write the plan into ``out_dir`` (atomically)."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("--out", f"{out_dir} exists and is not a folder")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        plan = _plan_into(case, staging, runs=runs, html_scene=html_scene, quiet=quiet)
        _swap_in(staging, out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    return plan


def _swap_in(staging: Path, out_dir: Path) -> None:
    old = None
    if out_dir.exists():
        old = out_dir.with_name(f".{out_dir.name}.old-{time.time_ns()}")
        out_dir.rename(old)
    staging.rename(out_dir)
    if old is not None:
        shutil.rmtree(old)


def _plan_into(case: Case, out: Path, *, runs, html_scene: bool, quiet: bool) -> dict:
    figures = out / "figures"
    figures.mkdir()
    timing = {}

    prog = Progress("1/5 fpsm", quiet=quiet)
    fit = pipeline.fit_stage(case, progress=prog)
    fit.fpsm.save(out / "fpsm.json")
    timing["fpsm"] = prog.elapsed
    prog.say(f"fitted {case.slices} slices x {case.control_points} control points "
             f"in {prog.elapsed:.2f} s")

    prog = Progress("2/5 placement", quiet=quiet)
    placements = pipeline.placement_stage(case, fit.fpsm, progress=prog, mesh=fit.opened)
    timing["placement"] = prog.elapsed

    prog = Progress("3/5 robot base", quiet=quiet)
    robot = pipeline.robot_stage(case, placements, progress=prog)
    timing["robot"] = prog.elapsed
    prog.say(f"base at {np.round(robot.base_xyz * 1e3).tolist()} mm in Oral, branches "
             f"{robot.branch.tolist()}")

    prog = Progress("4/5 capability", quiet=quiet)
    cap = pipeline.capability_stage(case, robot, progress=prog)
    timing["capability"] = prog.elapsed

    prog = Progress("5/5 feeding sim", quiet=quiet)
    sims = pipeline.simulation_stage(case, fit, placements, robot, runs=runs, progress=prog)
    timing["simulation"] = prog.elapsed

    prog = Progress("report", quiet=quiet)
    plan = plan_dict(case, fit, placements, robot, cap, sims)
    plan["timing"] = timing
    figs = make_figures(case, fit, placements, robot, cap, sims, figures,
                        html_scene=html_scene, out=out)
    write_json(out / "plan.json", plan, kind="plan")
    from implantplan.analyses.report import write_report

    write_report(out / "report.html", plan, figs)
    n_png = sum(1 for _ in (out / "figures").rglob("*.png"))
    prog.say(f"wrote plan.json, report.html and {n_png} figures")
    return plan


# -- the plan ------------------------------------------------------------------------------------


def _check(name: str, value: float, limit: float, *, unit: str, upper: bool, site=None) -> dict:
    """A check and its margin: an upper limit passes when value <= limit (margin limit - value
    >= 0, so "0 alarms <= 0" passes), a lower limit when value > limit (strictly: a clearance
    of exactly 0 is contact)."""
    margin = (limit - value) if upper else (value - limit)
    passed = margin >= 0 if upper else margin > 0
    return {"name": name, "site": site, "value": float(value), "limit": float(limit),
            "unit": unit, "margin": float(margin), "pass": bool(passed),
            "limit_kind": "max" if upper else "min"}


def plan_dict(case: Case, fit, placements, robot, cap, sims) -> dict:
    from implantplan.systems import actuator, moprp

    sc = robot.scenario
    X_WC = sc.X_WO @ robot.X_OC
    d = fit.fpsm.diagnostics
    checks = [_check("fpsm dense-check penetration depth", d["dense_max_depth_m"],
                     MAX_PENETRATION_DEPTH, unit="m", upper=True)]
    sites = []
    for k, (site, p) in enumerate(zip(case.sites, placements, strict=True)):
        grid = (p.to_dict().get("grid_check") or {})
        X_WT = sc.X_WO @ robot.X_OT[k]
        X_BE = moprp.target_pose(robot.base_xyz, robot.X_OT[k])
        sim = sims[k] if k < len(sims) else None
        sites.append({
            "name": site.name,
            "hole": {"position": site.position, "axis": site.axis, "frame": "Center"},
            "implant_length": site.implant_length,
            "rod_radius": site.rod_radius,
            "placement": {key: val for key, val in p.to_dict().items()
                          if key not in ("history", "vf")},
            "registration": p.verification.get("registration"),
            "feeding_target": {"X_CT": p.X_CT, "X_WT": X_WT, "X_BaseEnd": X_BE,
                               "note": "End (actuator tcp) = Tool rotated by R_OE"},
            "vf": p.vf.to_dict(),
            "ik": {"branch": int(robot.branch[k]), "q": robot.q[k], "q_pre": robot.q_pre[k],
                   "indices": dict(zip(moprp.INDEX_NAMES, robot.site_indices[k].tolist(),
                                       strict=True))},
            "capability": {"map_reachable": bool(cap.map_reachable[k]),
                           "voxel_index": float(cap.index[k]),
                           "neighbourhood_index": float(cap.neighbourhood_index[k]),
                           "ik_branches_within_limits": int(cap.ik_branches[k])},
            "simulation": None if sim is None else {
                "runs": [{key: val for key, val in r.items() if key != "travel_curve"}
                         for r in sim["runs"]],
                "realtime_factor": sim["realtime_factor"]},
        })
        n = site.name
        checks.append(_check("line1 (rod) clearance", p.d_safe_min_line1, case.clearance_margin,
                             unit="m", upper=False, site=n))
        checks.append(_check("line2 (implant path) clearance", p.d_safe_min_line2,
                             case.clearance_margin, unit="m", upper=False, site=n))
        ver = p.verification
        if ver:
            checks.append(_check("tool clearance over the feed and the fixture's region "
                                 "(certified, FPSM)", ver["clearance_certified"],
                                 ver["clearance_margin"], unit="m", upper=False, site=n))
            if ver.get("clearance_exact_min") is not None:
                checks.append(_check("tool clearance over the feed and the fixture's region "
                                     "(exact, FCL against the scan)", ver["clearance_exact_min"],
                                     ver["clearance_margin"], unit="m", upper=False, site=n))
        if "x" in grid:
            dd = abs(p.d_T - float(grid["x"][0]))
            dth = abs(wrap_angle(p.theta_T - float(grid["x"][1])))
            checks.append(_check("PSO vs grid optimum, d_T", dd, GRID_TOL_D, unit="m",
                                 upper=True, site=n))
            checks.append(_check("PSO vs grid optimum, theta_T", dth, GRID_TOL_THETA,
                                 unit="rad", upper=True, site=n))
        checks.append(_check("IK branches at the feeding target", cap.ik_branches[k], 0,
                             unit="branches", upper=False, site=n))
        checks.append(_check("capability index around the target", cap.neighbourhood_index[k],
                             MIN_CAPABILITY, unit="1", upper=False, site=n))
        if sim is not None and sim["runs"]:
            runs = sim["runs"]
            checks.append(_check("feeds missing the target", sum(not r["reached_target"]
                                 for r in runs), 0, unit="runs", upper=True, site=n))
            checks.append(_check("max VF violation", max(r["max_vf_violation"] for r in runs),
                                 MAX_VF_VIOLATION, unit="m", upper=True, site=n))
            checks.append(_check("min d_safe of the rod during feeds",
                                 min(r["min_d_safe"] for r in runs), 0.0, unit="m",
                                 upper=False, site=n))
            checks.append(_check("FPSM collision alarms", sum(r["collision_alarm"]
                                 for r in runs), 0, unit="runs", upper=True, site=n))
    return {
        "case": {"name": case.name, "source": str(case.source), "seed": case.seed},
        "fpsm": {
            "file": "fpsm.json",
            "slices": fit.fpsm.slices,
            "control_points": fit.fpsm.control_points,
            "z_range": list(fit.fpsm.z_range),
            "X_mesh_Center": fit.fpsm.X_WC,
            "method": case.fit_method,
            "coverage_mean": float(np.mean(d["coverage"])),
            "dense_penetration_rate": d.get("dense_penetration_rate_total"),
            "dense_max_depth": d["dense_max_depth_m"],
            "mouth_opening_deg": case.mouth_opening_deg,
        },
        "frames": {"X_WO": sc.X_WO, "X_OC": robot.X_OC, "X_WCenter": X_WC,
                   "X_FT": actuator.X_FT(), "posture": case.posture, "scenario": sc.name},
        "sites": sites,
        "base": {
            "xyz_in_oral": robot.base_xyz,
            "X_WBase": robot.X_WBase,
            "indices_worst_over_sites": dict(zip(moprp.INDEX_NAMES, robot.indices.tolist(),
                                                 strict=True)),
            "percentiles": dict(zip(moprp.INDEX_NAMES, robot.percentiles.tolist(),
                                    strict=True)),
            "percentile_samples": robot.percentile_samples,
            "pareto": [{"base_xyz": x, "indices": dict(zip(moprp.INDEX_NAMES, f.tolist(),
                                                           strict=True))}
                       for x, f in zip(robot.pareto_xyz, robot.pareto_F, strict=True)],
            "evaluations": robot.evaluations,
            "generations": robot.generations,
            "rule": "knee point; objectives = worst over the sites",
        },
        "checks": checks,
        "passed": all(c["pass"] for c in checks),
    }


# -- figures --------------------------------------------------------------------------------------


