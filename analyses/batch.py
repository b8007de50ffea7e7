"""``implantplan batch``: plan many cases in parallel (DESIGN.md section 11).

    implantplan batch CASE.yaml... | --cohort COHORT.yaml --out DIR [--scheduler local|tcp://H:P]
        [--workers N] [--runs K] [--no-figures] [--no-html-scene] [--quiet]
    implantplan batch --make-cohort CASE.yaml --cases N [--seed S] [--scale-sd F]
        [--rotation-deg D] [--shift-mm M] [--site-jitter-mm J] --out DIR

Each case is one task on the scale-out engine (systems.capability.scaleout: this process for
``--workers
1``, a LocalCluster on 127.0.0.1 by default otherwise, or a running cluster). A case is planned
into ``DIR/<case file stem>/`` exactly as ``implantplan plan CASE --out DIR/<stem>`` with the
same flags writes it (same seed, same plan.json apart from timings). A case that fails is
recorded with its reason and the exit code ``plan`` would have had, and the others go on.

Written into DIR (atomically, after the last case): ``summary.csv`` (one row per case),
``checks.csv`` (one row per check of every planned case), ``summary.json`` (kind
"batch_summary"), ``summary.png`` (every case's checks: pass/fail and margin) and
``summary.html`` (the table and the figure, with links to each case's report).

Statuses and the exit code of the batch (the first rule that applies):

* 1: some case hit an internal error (a bug, or a worker lost more often than its retries);
* 2: some case had bad input (status ``bad input``; ``plan`` would exit 2);
* 3: some case failed planning (``planning failed``; ``plan`` exits 3) or planned with a failed
  check (``checks failed``; ``plan`` exits 3 too);
* 0: every case ``passed`` (planned, every check passing).

Stopped early (Ctrl-C, SIGTERM), the batch kills its LocalCluster's workers and removes the
staging folders of the cases they were planning; the next batch into DIR removes those a killed
batch left (analyses.out_folder.remove_stale_inside).

``--make-cohort`` writes a synthetic cohort from one case (analyses.cohort.make_cohort).
"""

from __future__ import annotations

import csv
import io
import json
import re
import time
import traceback
from pathlib import Path

from implantplan.analyses import out_folder
from implantplan.analyses.progress import Progress, quiet_drake
from implantplan.systems.capability import scaleout
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.files import write_json, write_text_atomic

PASSED, CHECKS_FAILED, PLANNING_FAILED, BAD_INPUT, ERROR = (
    "passed", "checks failed", "planning failed", "bad input", "internal error",
)  # fmt: skip
# status -> (exit code `implantplan plan` would have had, rank in the batch's exit code)
PLAN_EXIT = {PASSED: 0, CHECKS_FAILED: 3, PLANNING_FAILED: 3, BAD_INPUT: 2, ERROR: 1}
WARM_UP = ("implantplan.analyses.plan", "implantplan.analyses.pipeline")
CSV_COLUMNS = ("case", "status", "plan_exit_code", "checks_passed", "checks_total",
               "failed_checks", "reason", "folder", "seconds", "case_file")  # fmt: skip


def batch_exit_code(statuses) -> int:
    """The batch's exit code from its cases' statuses (module docstring)."""
    statuses = set(statuses)
    if ERROR in statuses:
        return 1
    if BAD_INPUT in statuses:
        return 2
    if statuses & {PLANNING_FAILED, CHECKS_FAILED}:
        return 3
    return 0


def plan_one(case_file: str, out_dir: str, runs: int | None, figures: bool,
             html_scene: bool, force: bool = False, accept: tuple = (),
             memory_budget: float | None = None) -> dict:  # fmt: skip
    """One case, as ``implantplan plan`` does it: the task every worker runs (plain arguments
    in, a plain record out; user errors and planning failures are the record, not exceptions)."""
    from implantplan.analyses.case import load_case
    from implantplan.analyses.plan import plan_case

    quiet_drake()  # a worker process: Drake's INFO lines (Meshcat) dropped, repeats once

    t0 = time.perf_counter()
    rec = {"case": Path(case_file).stem, "case_file": str(case_file), "folder": str(out_dir),
           "reason": None, "checks": []}  # fmt: skip
    try:
        case = load_case(case_file)
        rec["case"] = case.name
        plan = plan_case(case, Path(out_dir), runs=runs, html_scene=html_scene, quiet=True,
                         figures=figures, force=force, accept=frozenset(accept),
                         memory_budget=memory_budget)  # fmt: skip
    except InputError as exc:
        rec.update(status=BAD_INPUT, reason=str(exc))
    except OSError as exc:  # as the CLI: an unreadable input or unwritable output is bad input
        where = f" {exc.filename!r}" if exc.filename else ""
        rec.update(status=BAD_INPUT, reason=f"cannot access{where}: {exc.strerror or exc}")
    except PlanningFailure as exc:
        rec.update(status=PLANNING_FAILED, reason=exc.reason)
    except Exception as exc:  # a bug: recorded with its place, the other cases go on
        where = traceback.extract_tb(exc.__traceback__)[-1]
        rec.update(status=ERROR, reason=f"{type(exc).__name__}: {exc} "
                   f"({Path(where.filename).name}:{where.lineno})")  # fmt: skip
    else:
        keys = ("id", "name", "site", "value", "limit", "unit", "margin", "pass")
        rec["checks"] = [{k: c[k] for k in keys} for c in plan["checks"]]
        failed = [_label(c) for c in plan["checks"] if not c["pass"]]
        rec.update(status=PASSED if plan["passed"] and not failed else CHECKS_FAILED,
                   reason=("failed: " + "; ".join(failed)) if failed else None)  # fmt: skip
    rec["plan_exit_code"] = PLAN_EXIT[rec["status"]]
    rec["seconds"] = time.perf_counter() - t0
    return rec


def _label(check: dict) -> str:
    return check["name"] + (f" (site {check['site']})" if check.get("site") else "")


def case_folders(case_files) -> list[str]:
    """One folder name per case: the case file's stem, made unique with -2, -3, ..."""
    seen, out = {}, []
    for f in case_files:
        stem = re.sub(r"[^A-Za-z0-9._-]", "_", Path(f).stem) or "case"
        seen[stem] = seen.get(stem, 0) + 1
        out.append(stem if seen[stem] == 1 else f"{stem}-{seen[stem]}")
    return out


def run_batch(case_files, out_dir, *, scheduler: str | None = None, workers: int | None = None,
              runs: int | None = None, figures: bool = True, html_scene: bool = True,
              quiet: bool = False, force: bool = False, accept: tuple = (),
              memory_budget: float | None = None) -> tuple[list[dict], int]:  # fmt: skip
    """Plan every case on the engine; write the summaries; returns (records, exit code).
    ``out_dir`` holding anything implantplan did not write is refused unless ``force``
    (analyses.out_folder); it is marked as a batch folder."""
    out_dir = out_folder.check_out(out_dir, force=force)
    if runs is not None and runs < 0:
        raise InputError("--runs", f"expected a number >= 0, got {runs}")
    scaleout.check_scheduler(scheduler, workers)
    case_files = [Path(f).resolve() for f in case_files]
    if not case_files:
        raise InputError("cases", "expected at least one case file (or --cohort)")
    out_dir.mkdir(parents=True, exist_ok=True)
    out_folder.mark(out_dir, "batch")
    out_folder.remove_stale_inside(out_dir)  # cases' staging folders of a batch that was killed
    folders = case_folders(case_files)
    tasks = [(str(f), str(out_dir.resolve() / d), runs, figures, html_scene, force,
              tuple(sorted(accept)), memory_budget)
             for f, d in zip(case_files, folders, strict=True)]  # fmt: skip
    records: list = [None] * len(tasks)
    prog = Progress("batch", quiet=quiet)
    try:
        with scaleout.engine(scheduler, workers, warm_up=WARM_UP) as eng:
            prog.say(f"{len(tasks)} cases on {eng.description}")
            eta = scaleout.Eta(len(tasks))
            done = 0
            for i, rec in scaleout.run_unordered(eng, plan_one, tasks, on_error=_lost(tasks)):
                records[i] = rec
                done += 1
                prog.say(
                    f"{done}/{len(tasks)} cases, {eta.text(done)}: {rec['case']}: "
                    f"{rec['status']}" + (f" ({rec['reason']})" if rec["reason"] else "")
                )
    finally:
        # a batch stopped early (Ctrl-C, SIGTERM): the engine killed its local workers, whose
        # cases' staging folders stay behind named with their pids; those processes are gone
        # (joined) once the engine is closed
        out_folder.remove_stale_inside(out_dir)
    write_summary(out_dir, records)
    code = batch_exit_code(r["status"] for r in records)
    return records, code


def _lost(task: tuple):
    """The record of a task that failed outside plan_one (its worker lost beyond the retries)."""

    def record(i, exc) -> dict:
        return {"case": Path(task[i][0]).stem, "case_file": task[i][0], "folder": task[i][1],
                "status": ERROR, "checks": [], "reason": f"{type(exc).__name__}: {exc}",
                "plan_exit_code": PLAN_EXIT[ERROR], "seconds": float("nan")}  # fmt: skip

    return record


def write_summary(out_dir: Path, records: list[dict]) -> None:
    """summary.csv, checks.csv, summary.json, summary.png and summary.html (module docstring)."""
    from implantplan.analyses.figures.batch import plot_cohort_checks, summary_html

    out_dir = Path(out_dir)
    rows = []
    for r in records:
        n_pass = sum(c["pass"] for c in r["checks"])
        rows.append({
            "case": r["case"], "status": r["status"], "plan_exit_code": r["plan_exit_code"],
            "checks_passed": n_pass, "checks_total": len(r["checks"]),
            "failed_checks": "; ".join(_label(c) for c in r["checks"] if not c["pass"]),
            "reason": r["reason"] or "", "folder": Path(r["folder"]).name,
            "seconds": f"{r['seconds']:.2f}", "case_file": r["case_file"],
        })  # fmt: skip
    write_text_atomic(out_dir / "summary.csv", _csv(CSV_COLUMNS, rows))
    check_rows = [{"case": r["case"], **{k: c[k] for k in ("name", "site", "value", "limit",
                                                           "unit", "margin", "pass")}}
                  for r in records for c in r["checks"]]  # fmt: skip
    write_text_atomic(
        out_dir / "checks.csv",
        _csv(("case", "name", "site", "value", "limit", "unit", "margin", "pass"), check_rows),
    )
    write_json(out_dir / "summary.json", {
        "cases": records, "exit_code": batch_exit_code(r["status"] for r in records),
        "counts": {s: sum(r["status"] == s for r in records) for s in PLAN_EXIT},
    }, kind="batch_summary")  # fmt: skip
    plot_cohort_checks(records, out_dir / "summary.png")
    write_text_atomic(out_dir / "summary.html", summary_html(rows, "summary.png"))


def _csv(columns, rows) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


# -- the command ---------------------------------------------------------------------------------


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "batch", help="plan many cases in parallel (Dask), one folder each, with a summary",
        description=__doc__.split("\n\n")[0],
    )  # fmt: skip
    p.add_argument("cases", nargs="*", type=Path, help="case YAML files")
    p.add_argument("--cohort", type=Path, default=None, help="a cohort YAML listing case files")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--scheduler", default=None, help=scaleout.SCHEDULER_HELP)
    p.add_argument("--workers", type=int, default=None, help=scaleout.WORKERS_HELP)
    p.add_argument(
        "--runs",
        type=int,
        default=None,
        help="feeding simulations per site (default: each case's simulation.runs)",
    )
    p.add_argument("--no-figures", action="store_true", help="as plan --no-figures")
    p.add_argument("--no-html-scene", action="store_true", help="as plan --no-html-scene")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--force", action="store_true",
                   help="replace --out (and case folders) even if they hold files implantplan "
                        "did not write")
    p.add_argument("--accept-small-margin", action="store_true",
                   help="as plan --accept-small-margin")
    p.add_argument("--accept-repairs", action="store_true", help="as plan --accept-repairs")
    p.add_argument("--memory-budget-mb", type=float, default=None,
                   help="as plan --memory-budget-mb, per case")
    g = p.add_argument_group("synthetic cohort (--make-cohort)")
    g.add_argument(
        "--make-cohort",
        type=Path,
        default=None,
        metavar="CASE",
        help="write a synthetic cohort made from CASE into --out, plan nothing",
    )
    g.add_argument("--cases", dest="n_cases", type=int, default=8, help="cases (default 8)")
    g.add_argument("--seed", type=int, default=0, help="perturbation seed (default 0)")
    g.add_argument("--scale-sd", type=float, default=0.03, help="sd of the scale (default 0.03)")
    g.add_argument("--rotation-deg", type=float, default=2.0, help="sd of the rotation angle")
    g.add_argument("--shift-mm", type=float, default=1.0, help="sd of each shift component")
    g.add_argument("--site-jitter-mm", type=float, default=0.5, help="sd of each site's jitter")
    p.set_defaults(func=_cmd_batch)


def _cmd_batch(args) -> int:
    if args.make_cohort is not None:
        if args.cases or args.cohort:
            raise InputError("--make-cohort", "plans nothing: give no CASES or --cohort with it")
        from implantplan.analyses.cohort import make_cohort

        path = make_cohort(args.make_cohort, Path(args.out), args.n_cases, seed=args.seed,
                           scale_sd=args.scale_sd, rotation_deg=args.rotation_deg,
                           shift_mm=args.shift_mm, site_jitter_mm=args.site_jitter_mm)  # fmt: skip
        print(json.dumps({"cohort": str(path), "cases": args.n_cases}))
        return 0
    from implantplan.analyses.plan import accepted, memory_budget

    out_folder.check_out(args.out, force=args.force)  # before any work
    args.out = Path(args.out)
    files = list(args.cases)
    if args.cohort is not None:
        if files:
            raise InputError("--cohort", "give case files or --cohort, not both")
        from implantplan.analyses.cohort import load_cohort

        files = load_cohort(args.cohort)[1]
    records, code = run_batch(files, args.out, scheduler=args.scheduler, workers=args.workers,
                              runs=args.runs, figures=not args.no_figures,
                              html_scene=not args.no_html_scene, quiet=args.quiet,
                              force=args.force, accept=accepted(args),
                              memory_budget=memory_budget(args))  # fmt: skip
    counts = {s: sum(r["status"] == s for r in records) for s in PLAN_EXIT}
    print(json.dumps({"out": str(args.out), "cases": len(records),
                      **{k.replace(" ", "_"): n for k, n in counts.items()},
                      "exit_code": code, "summary": str(args.out / "summary.html")}))  # fmt: skip
    return code
