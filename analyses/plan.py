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
import time
from pathlib import Path

import numpy as np

from implantplan.analyses import budget, cards, out_folder, pipeline
from implantplan.analyses import checks as checks_
from implantplan.analyses.case import MAX_RUNS, Case, default_case_path, load_case
from implantplan.analyses.figures.plan import make_figures
from implantplan.analyses.progress import Progress
from implantplan.analyses.provenance import provenance
from implantplan.systems import seeds
from implantplan.systems import validate as v
from implantplan.systems.anatomy.cbct import scan_files
from implantplan.systems.anatomy.dicom_plan import PlannedImplant, StudyIds, write_dicom_plan
from implantplan.systems.errors import InputError
from implantplan.systems.files import to_jsonable, write_json
from implantplan.systems.frames import apply

DEMO_OUT = "out/implantplan-demo"  # out/ is where every README command writes
MIN_MARGIN_MM = 0.5  # a clinical margin below this needs --accept-small-margin
ACCEPT = ("accept-small-margin", "accept-repairs")
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
    p.add_argument("--out", required=default_out is None, default=default_out,
                   help="output folder" + (f" (default: ./{default_out})" if default_out else ""))
    p.add_argument("--runs", type=int, default=None,
                   help="feeding simulations per site (default: the case's simulation.runs)")
    p.add_argument("--no-html-scene", action="store_true",
                   help="skip the Meshcat static HTML of the layout")
    p.add_argument("--no-figures", action="store_true",
                   help="skip the figures (and the 3D scene): plan.json, fpsm.json and a report "
                        "of tables only (studies of many cases)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it holds files implantplan did not write")
    acceptance_flags(p)


def acceptance_flags(p: argparse.ArgumentParser) -> None:
    """The flags that let a user plan what a clinician would stop at (``plan``, ``demo``,
    ``batch``): each is recorded in plan.json (``acknowledged``) and marked in the report."""
    p.add_argument("--accept-small-margin", action="store_true",
                   help=f"plan with safety.clearance_mm below {MIN_MARGIN_MM:g} mm (marked in "
                        "the report)")
    p.add_argument("--accept-repairs", action="store_true",
                   help="plan a scan whose open boundary is more than "
                        f"{pipeline.MAX_OPEN_EDGE_SHARE * 100:.0f}%% of its edges "
                        "(marked in the report)")
    p.add_argument("--memory-budget-mb", type=float, default=None,
                   help="refuse a plan estimated to need more memory (default: half the "
                        "machine's, or $IMPLANTPLAN_MEMORY_BUDGET_MB)")


def _cmd_plan(args) -> int:
    out_folder.check_out(args.out, force=args.force)  # before any work (the text as typed)
    args.out = Path(args.out)
    return _run(load_case(args.case), args)


def _cmd_demo(args) -> int:
    out_folder.check_out(args.out, force=args.force)
    args.out = Path(args.out)
    return _run(load_case(default_case_path()), args)


def _run(case: Case, args) -> int:
    """Plan; exit 0 when every check passes, 3 when one fails (DESIGN.md section 3)."""
    if args.runs is not None:
        v.integer(args.runs, "--runs", low=0, high=MAX_RUNS)
    t0 = time.perf_counter()
    plan = plan_case(case, args.out, runs=args.runs, html_scene=not args.no_html_scene,
                     quiet=args.quiet, figures=not args.no_figures, force=args.force,
                     accept=accepted(args), memory_budget=memory_budget(args))
    failed = [c["name"] for c in plan["checks"] if not c["pass"]]
    print(f"plan: {args.out / 'plan.json'}")
    print(f"checks: {len(plan['checks']) - len(failed)} of {len(plan['checks'])} pass"
          + (f" (failed: {', '.join(failed)})" if failed else ""))
    print(f"time: {time.perf_counter() - t0:.1f} s")
    print(f"report: {(args.out / 'report.html').resolve()}")
    return 0 if not failed and plan["passed"] else 3


def accepted(args) -> frozenset:
    """The acceptance flags given (:func:`acceptance_flags`) as names."""
    return frozenset(name for name in ACCEPT if getattr(args, name.replace("-", "_"), False))


def memory_budget(args) -> float | None:
    """``--memory-budget-mb`` in bytes (None: analyses.budget's default)."""
    if getattr(args, "memory_budget_mb", None) is None:
        return None
    return v.number(args.memory_budget_mb, "--memory-budget-mb", positive=True) * 1e6


def check_plausible(case: Case, accept: frozenset = frozenset()) -> list[dict]:
    """What a clinician would stop at, before any work: a clinical margin below
    :data:`MIN_MARGIN_MM` needs ``accept_small_margin``. Returns the acknowledgements to record
    (plan.json ``acknowledged``)."""
    notes = []
    margin_mm = case.safety.clearance_margin * 1e3
    if margin_mm < MIN_MARGIN_MM:
        if "accept-small-margin" not in accept:
            raise InputError("safety.clearance_mm", f"{margin_mm:g} mm is below "
                             f"{MIN_MARGIN_MM:g} mm (robots place implants to about 1 mm); "
                             "expected >= 0.5 mm, or --accept-small-margin to plan with it")
        notes.append({"flag": "--accept-small-margin",
                      "what": f"safety.clearance_mm {margin_mm:g} mm, below {MIN_MARGIN_MM:g} "
                              "mm"})
    return notes


def plan_case(case: Case, out_dir: Path, *, runs: int | None = None, html_scene: bool = True,
              quiet: bool = False, figures: bool = True, force: bool = False,
              accept: frozenset = frozenset(), memory_budget: float | None = None) -> dict:
    """Run every stage on ``case`` and write the plan into ``out_dir`` (atomically, in a marked
    plan folder: analyses.out_folder); without ``figures`` no PNG or 3D scene is drawn (plan.json
    does not depend on them). Before any work: ``out_dir`` holding anything but a plan is
    refused unless ``force``; the plan's memory estimate is checked against ``memory_budget``
    (bytes; analyses.budget); what :func:`check_plausible` and the scan's repairs stop at needs
    its name in ``accept``."""
    out_dir = out_folder.check_out(out_dir, force=force)
    budget.check(case, runs=runs, budget=memory_budget)
    notes = check_plausible(case, accept)
    with out_folder.staged(out_dir, "plan") as staging:
        plan = _plan_into(case, staging, runs=runs, html_scene=html_scene, quiet=quiet,
                          figures=figures, accept=accept, notes=notes)
    return plan


def _plan_into(case: Case, out: Path, *, runs, html_scene: bool, quiet: bool,
               figures: bool = True, accept: frozenset = frozenset(),
               notes: list | None = None) -> dict:
    fig_dir = out / "figures"
    timing = {}

    prog = Progress("1/5 fpsm", quiet=quiet)
    notes = list(notes or [])
    fit = pipeline.fit_stage(case, progress=prog, accept_repairs="accept-repairs" in accept,
                             notes=notes)
    fit.fpsm.save(out / "fpsm.json")
    timing["fpsm"] = prog.elapsed
    prog.say(f"fitted {case.fpsm.slices} slices x {case.fpsm.control_points} control points "
             f"in {prog.elapsed:.2f} s")

    sites_checked = pipeline.site_stage(case, fit)
    prog.say("sites on the tissue: " + ", ".join(
        f"{s.name} {d * 1e3:.2f} mm" for s, d in zip(case.sites, sites_checked.distance,
                                                    strict=True)))

    prog = Progress("2/5 placement", quiet=quiet)
    placements = pipeline.placement_stage(case, fit, progress=prog)
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
    if notes:
        plan["acknowledged"] = notes
    anatomy = pipeline.anatomy_stage(case, fit)
    if anatomy is not None:
        for site, rec in zip(plan["sites"], anatomy["sites"], strict=True):
            site["anatomy"] = rec
        plan["checks"] += checks_.anatomy_checks(anatomy)
        plan["passed"] = checks_.passed(plan["checks"])
    plan["timing"] = timing
    plan["scan"] = scan_record(fit)
    plan["provenance"] = provenance(case_file=case.source, meshes=scan_files(case.mesh.path),
                                    seed=case.seed)
    figs = {}
    if figures:
        fig_dir.mkdir()
        figs = make_figures(case, fit, placements, robot, cap, sims, fig_dir,
                            html_scene=html_scene, out=out)
    plan["dicom"] = write_plan_dicom(case, fit, out)
    write_json(out / "plan.json", plan, kind="plan")
    from implantplan.analyses.report import write_report

    write_report(out / "report.html", plan, figs)
    n_png = sum(1 for _ in fig_dir.rglob("*.png"))
    prog.say(f"wrote plan.json, report.html and {n_png} figures")
    return plan


# -- the plan ------------------------------------------------------------------------------------


def write_plan_dicom(case: Case, fit, out: Path) -> dict:
    """plan.dcm (Implantation Plan SR) with the scan and implant STLs (systems.anatomy.
    dicom_plan) in the opened mesh frame the sites are planned in; identifiers from the CBCT
    series, else the case's ``patient.id``/``patient.name`` (default: the case's name)."""
    from pydicom.uid import generate_uid

    X_WC = fit.fpsm.X_WC
    implants = [PlannedImplant(site=s.name, entry=apply(X_WC, s.position),
                               axis=X_WC[:3, :3] @ s.axis, diameter=s.implant_diameter,
                               length=s.placed_length) for s in case.sites]
    info = fit.cbct.info if fit.cbct is not None else {}
    ids = StudyIds(
        patient_id=info.get("patient_id") or case.patient.id or case.name,
        patient_name=info.get("patient_name") or case.patient.name or case.name,
        study_uid=info.get("study_instance_uid")
        or str(generate_uid(entropy_srcs=["implantplan", str(case.name), str(case.seed)])),
        study_id=info.get("study_id") or "1",
        accession_number=info.get("accession_number", ""),
        frame_uid=(info.get("frame_of_reference_uid") or None)
        if case.mesh.mouth_opening_deg == 0 else None)
    files = write_dicom_plan(out, fit.opened, implants, ids)
    frame = ("the case's mesh frame" + (" after the jaw-opening model" if
             case.mesh.mouth_opening_deg > 0 else "") + (" (DICOM patient frame, LPS, mm)"
             if fit.cbct is not None else "") + ", mm")
    return {**files, "frame": frame, "patient_id": ids.patient_id,
            "study_instance_uid": ids.study_uid}


def scan_record(fit) -> dict:
    """plan.json's ``scan``: what the scan was (a mesh file, or a CBCT and its series, surfaces
    and thresholds) and the frame the case's coordinates are in."""
    if fit.cbct is None:
        return {"kind": "mesh", "frame": "the scan file's coordinates (the case's mesh frame)"}
    return {"kind": "cbct", **fit.cbct.info}


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
            "implant_length": p.implant_length,
            "placed_implant_length": site.placed_length,
            "rod_radius": p.rod_radius,
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
    plan = {
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
    plan["cards"] = cards.surgeon_cards(to_jsonable(plan))
    return plan


# -- figures --------------------------------------------------------------------------------------


