"""``implantplan batch``: a synthetic cohort of 8 cases (one broken) on a 2-worker LocalCluster
(marked ``cluster``): 7 plans, 1 recorded failure, the documented exit code, and the same plans as
each case planned alone; a cohort of 2 in this process by default; the bad-input path, the
exit-code rule and the generator's determinism."""

import csv
import json
from pathlib import Path

import pytest
import yaml

from implantplan.analyses.batch import batch_exit_code
from implantplan.analyses.cli import main
from implantplan.analyses.cohort import load_cohort
from implantplan.analyses.out_folder import MARKER
from implantplan.analyses.provenance import without_volatile
from tests.analyses.cases import default_case_data, write_case

FAST = ["--runs", "0", "--no-figures", "--quiet"]
BROKEN = 5  # this case's first site gets an axis into the bone: no collision-free placement


def _small_case(folder: Path) -> Path:
    """The default case with a small FPSM, robot search and map (tests.analyses.cases), no
    feeds."""
    data = default_case_data(small=True)
    data["simulation"]["runs"] = 0
    return write_case(folder / "small.yaml", data)


def _make_cohort(root: Path, cases: int) -> list[Path]:
    """``cases`` perturbed copies of the small case (seed 3), the one at ``BROKEN`` (or the last
    of a shorter cohort) given a handle too thick for this mouth: (cohort file, case files)."""
    # perturbations within what the default case's 1.5 mm certified clearance at site 36 (margin
    # 1 mm) takes:
    # the generator's defaults (3 % scale, 2 deg, 1 mm) leave about half of a cohort without a
    # placement, which is what the case is like, not what this test is about
    assert main(["batch", "--make-cohort", str(_small_case(root)), "--cases", str(cases),
                 "--seed", "3", "--scale-sd", "0.005", "--rotation-deg", "0.3", "--shift-mm",
                 "0.2", "--site-jitter-mm", "0.2", "--out", str(root / "cases")]) == 0
    path = root / "cases" / "cohort.yaml"
    files = load_cohort(path)[1]
    broken = yaml.safe_load(files[min(BROKEN, cases - 1)].read_text())
    broken["instrument"] = "paper"
    broken["sites"][0]["rod_radius_mm"] = 20.0  # a paper tool's handle too thick for this mouth
    files[min(BROKEN, cases - 1)].write_text(yaml.safe_dump(broken))
    return path, files


def _plan_json(folder: Path) -> dict:
    plan = without_volatile(json.loads((folder / "plan.json").read_text()))
    plan.pop("case")  # names the case file's folder
    return plan


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    root = tmp_path_factory.mktemp("cohort")
    path, files = _make_cohort(root, 8)
    out = root / "out"
    code = main(["batch", "--cohort", str(path), "--out", str(out), "--workers", "2",
                 "--scheduler", "local", *FAST])  # fmt: skip
    return files, out, code


@pytest.mark.sweep  # two plans (11 s); the batch's bad input and figure run by default
def test_a_cohort_of_two_in_this_process(tmp_path):
    """No cluster (--workers 1 plans in this process): one plan, one recorded planning failure,
    exit 3 (a batch's plan is the case planned alone: the cluster tests below)."""
    path, files = _make_cohort(tmp_path, 2)
    out = tmp_path / "out"
    code = main(["batch", "--cohort", str(path), "--out", str(out), "--workers", "1", *FAST])
    assert code == 3
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["case"] for r in rows] == ["default-00", "default-01"]
    assert [r["status"] for r in rows] == ["passed", "planning failed"]
    assert rows[1]["plan_exit_code"] == "3" and "site 36" in rows[1]["reason"]
    assert (out / rows[0]["folder"] / "plan.json").is_file()
    assert not (out / rows[1]["folder"] / "plan.json").exists()
    assert json.loads((out / "summary.json").read_text())["exit_code"] == 3
    # the refusal tried the jaw model's widest opening once (analyses.pipeline.opening_needed)
    assert "not even the jaw model's widest opening (45 deg) places it" in rows[1]["reason"]


@pytest.mark.cluster
def test_cohort_of_eight_with_one_broken_case(cohort):
    files, out, code = cohort
    assert code == 3  # a planning failure, no bad input
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["case"] for r in rows] == [f"default-{i:02d}" for i in range(8)]
    status = [r["status"] for r in rows]
    assert status.count("passed") == 7 and status[BROKEN] == "planning failed"
    bad = rows[BROKEN]
    assert bad["plan_exit_code"] == "3" and "site 36" in bad["reason"]
    assert "no collision-free instrument placement" in bad["reason"]
    for i, r in enumerate(rows):
        assert (out / r["folder"] / "plan.json").is_file() == (i != BROKEN)
        if i != BROKEN:
            assert r["checks_passed"] == r["checks_total"] != "0" and r["plan_exit_code"] == "0"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kind"] == "batch_summary" and summary["exit_code"] == 3
    assert summary["counts"]["passed"] == 7 and summary["counts"]["planning failed"] == 1
    checks = list(csv.DictReader((out / "checks.csv").open()))
    assert {c["case"] for c in checks} == {r["case"] for i, r in enumerate(rows) if i != BROKEN}
    page = (out / "summary.html").read_text()
    assert "7 of 8 cases passed" in page and "summary.png" in page
    assert (out / "summary.png").stat().st_size > 10_000
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == [MARKER]


@pytest.mark.cluster
def test_a_batch_plan_equals_the_case_planned_alone(cohort, tmp_path):
    files, out, _ = cohort  # one case here (all of them: the slow test below)
    assert main(["plan", str(files[0]), "--out", str(tmp_path / "alone"), *FAST]) == 0
    assert _plan_json(out / files[0].stem) == _plan_json(tmp_path / "alone")


@pytest.mark.slow
def test_every_batch_plan_equals_the_case_planned_alone(cohort, tmp_path):
    files, out, _ = cohort
    for k, f in enumerate(files):
        if k != BROKEN:
            assert main(["plan", str(f), "--out", str(tmp_path / f.stem), *FAST]) == 0
            assert _plan_json(out / f.stem) == _plan_json(tmp_path / f.stem)


def test_bad_input_is_recorded_and_exits_2(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["batch", str(tmp_path / "missing.yaml"), str(tmp_path / "missing.yaml"),
                 "--out", str(out), "--workers", "1", *FAST])  # fmt: skip
    assert code == 2
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["folder"] for r in rows] == ["missing", "missing-2"]
    assert all(r["status"] == "bad input" and r["plan_exit_code"] == "2" for r in rows)
    assert "case: file" in rows[0]["reason"] and "does not exist" in rows[0]["reason"]
    assert "Traceback" not in capsys.readouterr().err
    # errors of the command itself exit 2 before planning anything
    assert main(["batch", "--out", str(tmp_path / "x"), "--workers", "1"]) == 2
    assert main(["batch", "a.yaml", "--make-cohort", "b.yaml", "--out", str(tmp_path)]) == 2
    assert main(["batch", "a.yaml", "--out", str(tmp_path), "--scheduler", "nowhere"]) == 2
    (tmp_path / "bad.yaml").write_text("schema_version: 1\ncases: []\n")
    assert main(["batch", "--cohort", str(tmp_path / "bad.yaml"), "--out", str(out)]) == 2
    assert "cases: expected a list" in capsys.readouterr().err


def test_exit_code_rule():
    assert batch_exit_code(["passed"] * 3) == 0
    assert batch_exit_code(["passed", "checks failed"]) == 3
    assert batch_exit_code(["planning failed", "passed"]) == 3
    assert batch_exit_code(["planning failed", "bad input"]) == 2
    assert batch_exit_code(["bad input", "internal error"]) == 1


def test_make_cohort_same_seed_same_files(tmp_path):
    case = _small_case(tmp_path)
    for name in ("a", "b"):
        assert main(["batch", "--make-cohort", str(case), "--cases", "2", "--seed", "3",
                     "--out", str(tmp_path / name)]) == 0  # fmt: skip
    a = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert a == ["cohort.yaml", "default-00.obj", "default-00.yaml", "default-01.obj",
                 "default-01.yaml"]  # fmt: skip
    for n in a:
        assert (tmp_path / "a" / n).read_bytes() == (tmp_path / "b" / n).read_bytes(), n
    c0 = yaml.safe_load((tmp_path / "a" / "default-00.yaml").read_text())
    c1 = yaml.safe_load((tmp_path / "a" / "default-01.yaml").read_text())
    assert c0["sites"][0]["position_mm"] != c1["sites"][0]["position_mm"]
    assert c0["center"] == c1["center"]  # the planning frame stays; the anatomy moves in it


def test_the_summary_figure_keeps_every_check_label_inside_it(tmp_path):
    """Many checks with long ids at several sites: every x and y label lies inside the saved
    figure (they were cut off at the bottom)."""
    import matplotlib.pyplot as plt

    from implantplan.analyses.figures.batch import cohort_checks_figure, plot_cohort_checks

    checks = [{"id": f"placement.tool_clearance_exact_{k:02d}", "name": "x" * 80, "site": s,
               "value": 1.0, "limit": 0.5, "unit": "m", "margin": 0.5, "pass": k % 3 > 0}
              for k in range(16) for s in ("36", "46")]
    records = [{"case": f"case{i}", "status": "passed", "reason": None, "checks": checks}
               for i in range(3)]
    fig = cohort_checks_figure(records)
    try:
        fig.canvas.draw()
        box = fig.bbox
        ax = fig.axes[0]
        labels = ax.get_xticklabels() + ax.get_yticklabels()
        assert len(labels) == len(checks) + len(records)
        for t in labels:
            e = t.get_window_extent()
            assert e.x0 >= box.x0 - 0.5 and e.y0 >= box.y0 - 0.5, t.get_text()
            assert e.x1 <= box.x1 + 0.5 and e.y1 <= box.y1 + 0.5, t.get_text()
        # the column labels name the check by its id and site, not its long name
        assert ax.get_xticklabels()[0].get_text() == \
            "placement.tool_clearance_exact_00 [36] (mm)"
    finally:
        plt.close(fig)
    plot_cohort_checks(records, tmp_path / "summary.png")
    assert (tmp_path / "summary.png").stat().st_size > 10_000
