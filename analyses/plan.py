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
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from implantplan.analyses import checks as checks_
from implantplan.analyses import pipeline
from implantplan.analyses.case import Case, default_case_path, load_case
from implantplan.analyses.figures.plan import make_figures
from implantplan.analyses.progress import Progress
from implantplan.analyses.provenance import provenance
from implantplan.systems import seeds
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_json

DEMO_OUT = "out/implantplan-demo"  # out/ is where every README command writes
# Pass/fail limits of the checks (DESIGN.md section 4).


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
    p.add_argument("--no-figures", action="store_true",
                   help="skip the figures (and the 3D scene): plan.json, fpsm.json and a report "
                        "of tables only (studies of many cases)")
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
                     quiet=args.quiet, figures=not args.no_figures)
    failed = [c["name"] for c in plan["checks"] if not c["pass"]]
    print(f"plan: {args.out / 'plan.json'}")
    print(f"checks: {len(plan['checks']) - len(failed)} of {len(plan['checks'])} pass"
          + (f" (failed: {', '.join(failed)})" if failed else ""))
    print(f"time: {time.perf_counter() - t0:.1f} s")
    print(f"report: {(args.out / 'report.html').resolve()}")
    return 0


def plan_case(case: Case, out_dir: Path, *, runs: int | None = None, html_scene: bool = True,
              quiet: bool = False, figures: bool = True) -> dict:
    """Run every stage on ``case`` and write the plan into ``out_dir`` (atomically); without
    ``figures`` no PNG or 3D scene is drawn (plan.json does not depend on them)."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("--out", f"{out_dir} exists and is not a folder")
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    except OSError as exc:
        raise InputError("--out", f"cannot create a plan folder in {str(out_dir.parent)!r}: "
                         f"{exc.strerror or exc}") from None
    staging.chmod(0o777 & ~_umask())  # mkdtemp makes it 0700; a plan folder is for colleagues too
    try:
        plan = _plan_into(case, staging, runs=runs, html_scene=html_scene, quiet=quiet,
                          figures=figures)
        _swap_in(staging, out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    return plan


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _swap_in(staging: Path, out_dir: Path) -> None:
    old = None
    if out_dir.exists():
        old = out_dir.with_name(f".{out_dir.name}.old-{time.time_ns()}")
        out_dir.rename(old)
    staging.rename(out_dir)
    if old is not None:
        shutil.rmtree(old)


def _plan_into(case: Case, out: Path, *, runs, html_scene: bool, quiet: bool,
               figures: bool = True) -> dict:
    fig_dir = out / "figures"
    timing = {}

    prog = Progress("1/5 fpsm", quiet=quiet)
    fit = pipeline.fit_stage(case, progress=prog)
    fit.fpsm.save(out / "fpsm.json")
    timing["fpsm"] = prog.elapsed
    prog.say(f"fitted {case.fpsm.slices} slices x {case.fpsm.control_points} control points "
             f"in {prog.elapsed:.2f} s")

    sites_checked = pipeline.site_stage(case, fit)
    prog.say("sites on the tissue: " + ", ".join(
        f"{s.name} {d * 1e3:.2f} mm" for s, d in zip(case.sites, sites_checked.distance,
                                                    strict=True)))

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
    plan = plan_dict(case, fit, placements, robot, cap, sims, sites_checked)
    plan["timing"] = timing
    plan["provenance"] = provenance(case_file=case.source, meshes=[case.mesh.path],
                                    seed=case.seed)
    figs = {}
    if figures:
        fig_dir.mkdir()
        figs = make_figures(case, fit, placements, robot, cap, sims, fig_dir,
                            html_scene=html_scene, out=out)
    write_json(out / "plan.json", plan, kind="plan")
    from implantplan.analyses.report import write_report

    write_report(out / "report.html", plan, figs)
    n_png = sum(1 for _ in fig_dir.rglob("*.png"))
    prog.say(f"wrote plan.json, report.html and {n_png} figures")
    return plan


# -- the plan ------------------------------------------------------------------------------------


def plan_dict(case: Case, fit, placements, robot, cap, sims, sites_checked) -> dict:
    from implantplan.systems import actuator
    from implantplan.systems.robot import moprp

    sc = robot.scenario
    X_WC = sc.X_WO @ robot.X_OC
    d = fit.fpsm.diagnostics
    checks = checks_.fpsm_checks(d)
    sites = []
    for k, (site, p) in enumerate(zip(case.sites, placements, strict=True)):
        X_WT = sc.X_WO @ robot.X_OT[k]
        X_BE = moprp.target_pose(robot.base_xyz, robot.X_OT[k])
        sim = sims[k] if k < len(sims) else None
        sites.append({
            "name": site.name,
            "hole": {"position": site.position, "axis": site.axis, "frame": "Center"},
            "implant_length": site.implant_length,
            "rod_radius": site.rod_radius,
            "site_check": {"distance_to_tissue": float(sites_checked.distance[k]),
                           "tolerance": sites_checked.tolerance,
                           "axis_into_cavity": bool(sites_checked.axis_into_cavity[k])},
            "placement": {key: val for key, val in p.to_dict().items()
                          if key not in ("history", "vf")},
            "registration": p.verification.get("registration"),
            "feeding_target": {"X_CT": p.X_CT, "X_WT": X_WT, "X_BaseEnd": X_BE,
                               "note": "End (actuator tcp) = Tool rotated by R_OE"},
            "vf": p.vf.to_dict(),
            "ik": {"branch": int(robot.branch[k]), "q": robot.q[k], "q_pre": robot.q_pre[k],
                   "indices": dict(zip(moprp.INDEX_NAMES, robot.site_indices[k].tolist(),
                                       strict=True)),
                   **checks_.scene_graph_fields(robot.feed_clearance, k)},
            "capability": checks_.capability_fields(
                cap.cmap.params, reachable=cap.map_reachable[k], source=cap.map_source[k],
                index=cap.index[k], neighbourhood_index=cap.neighbourhood_index[k],
                ik_branches=cap.ik_branches[k]),
            "simulation": None if sim is None else {
                "runs": [{key: val for key, val in r.items() if key != "travel_curve"}
                         for r in sim["runs"]],
                "realtime_factor": sim["realtime_factor"]},
        })
        n = site.name
        checks += checks_.placement_checks(
            n, p, distance_to_tissue=float(sites_checked.distance[k]),
            tolerance=sites_checked.tolerance, clearance_margin=case.safety.clearance_margin)
        feed = robot.feed_clearance[k] if k < len(robot.feed_clearance) else None
        checks += checks_.layout_checks(n, feed, ik_branches=cap.ik_branches[k],
                                        neighbourhood_index=cap.neighbourhood_index[k])
        checks += checks_.feeding_checks(n, sim["runs"] if sim is not None else [])
    return {
        "case": {"name": case.name, "source": str(case.source), "seed": case.seed,
                 "random_streams": "numpy SeedSequence(seed) spawned per stage ("
                                   + ", ".join(seeds.STAGES) + ") and site (systems.seeds)",
                 "instrument": {"kind": case.instrument.kind, "urdf": case.instrument.urdf,
                                "note": "the instrument every tissue-side check verified; its "
                                        "solids per site in placement.verification.tool"}},
        "safety": case.safety.to_dict(),
        "fpsm": {
            "file": "fpsm.json",
            "slices": fit.fpsm.slices,
            "control_points": fit.fpsm.control_points,
            "z_range": list(fit.fpsm.z_range),
            "X_mesh_Center": fit.fpsm.X_WC,
            "method": case.fpsm.method,
            "coverage_mean": float(np.mean(d["coverage"])),
            "dense_penetration_rate": d.get("dense_penetration_rate_total"),
            "dense_max_depth": d["dense_max_depth_m"],
            "mouth_opening_deg": case.mesh.mouth_opening_deg,
        },
        "frames": {"X_WO": sc.X_WO, "X_OC": robot.X_OC, "X_WCenter": X_WC,
                   "X_FT": actuator.X_FT(), "posture": case.patient.posture, "scenario": sc.name},
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
            "selection_dropped": robot.selection_dropped,
            "confirmation": "Drake SceneGraph ComputeSignedDistancePairwiseClosestPoints along "
                            "every site's feed (steps <= 1 mm, 0.5 deg); a base that fails is "
                            "dropped and the next-ranked one taken",
        },
        "checks": checks,
        "passed": checks_.passed(checks),
    }


# -- figures --------------------------------------------------------------------------------------


