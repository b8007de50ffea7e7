"""A plan's DICOM files as DCMTK reads them (DESIGN.md section 12: validated with DCMTK where
installed): ``dcmdump`` and ``dcm2json`` parse the plan.dcm that ``implantplan plan`` wrote
(the small plan of the default case: tests.conftest.small_plan) and its Encapsulated STLs
without an error line, and find the Implantation Plan SR's SOP class UID; ``dsrdump`` reads its
content tree; ``dciodvfy`` (dicom3tools) checks the IOD where it is installed.

Each test skips, with the reason, only where its tool is not installed (Debian's ``dcmtk``,
which ``.ci/run`` installs; ``dciodvfy`` is dicom3tools', not installed there)."""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest

IMPLANTATION_PLAN_SR = "1.2.840.10008.5.1.4.1.1.88.70"
ENCAPSULATED_STL = "1.2.840.10008.5.1.4.1.1.104.3"


def _needs(tool: str, package: str = "dcmtk"):
    return pytest.mark.skipif(shutil.which(tool) is None,
                              reason=f"{tool} is not installed (Debian's {package})")


def _run(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run(list(argv), capture_output=True, text=True, timeout=120)


def _errors(text: str) -> list[str]:
    """DCMTK's error and fatal log lines (``E: ...``, ``F: ...``)."""
    return [line for line in text.splitlines() if line.startswith(("E:", "F:"))]


@pytest.fixture(scope="module")
def plan_dir(small_plan):
    folder = small_plan[1]
    assert (folder / "plan.dcm").is_file()
    return folder


@_needs("dcmdump")
def test_dcmdump_parses_plan_dcm_and_names_the_sop_class(plan_dir):
    run = _run("dcmdump", "-Un", str(plan_dir / "plan.dcm"))  # -Un: UIDs as numbers
    assert run.returncode == 0, run.stderr
    assert not _errors(run.stdout + run.stderr), run.stderr
    sop = [line for line in run.stdout.splitlines() if line.startswith("(0008,0016)")]
    assert len(sop) == 1 and f"[{IMPLANTATION_PLAN_SR}]" in sop[0], sop
    meta = [line for line in run.stdout.splitlines() if line.startswith("(0002,0002)")]
    assert len(meta) == 1 and f"[{IMPLANTATION_PLAN_SR}]" in meta[0], meta
    assert "(0040,a504)" in run.stdout  # ContentTemplateSequence (TID 7000)
    plan = json.loads((plan_dir / "plan.json").read_text())
    for name in [plan["dicom"]["scan_stl"], *(f["dcm"] for f in plan["dicom"]["implants"])]:
        run = _run("dcmdump", "-Un", str(plan_dir / name))
        assert run.returncode == 0 and not _errors(run.stdout + run.stderr), (name, run.stderr)
        assert f"[{ENCAPSULATED_STL}]" in run.stdout and "model/stl" in run.stdout, name


@_needs("dcm2json")
def test_dcm2json_converts_plan_dcm(plan_dir):
    run = _run("dcm2json", str(plan_dir / "plan.dcm"))
    assert run.returncode == 0, run.stderr
    assert not _errors(run.stderr), run.stderr
    data = json.loads(run.stdout)
    assert data["00080016"] == {"vr": "UI", "Value": [IMPLANTATION_PLAN_SR]}
    assert data["00080060"]["Value"] == ["SR"]
    (template,) = data["0040A504"]["Value"]  # ContentTemplateSequence
    assert template["0040DB00"]["Value"] == ["7000"]  # TemplateIdentifier: TID 7000
    plan = json.loads((plan_dir / "plan.json").read_text())
    assert data["00100020"]["Value"] == [plan["dicom"]["patient_id"]]
    assert data["0020000D"]["Value"] == [plan["dicom"]["study_instance_uid"]]


@_needs("dsrdump")
def test_dsrdump_reads_the_plans_content_tree(plan_dir):
    run = _run("dsrdump", str(plan_dir / "plan.dcm"))
    assert run.returncode == 0, run.stderr
    assert not _errors(run.stdout + run.stderr), run.stderr
    assert "Implantation Plan SR Document" in run.stdout
    plan = json.loads((plan_dir / "plan.json").read_text())
    assert run.stdout.count("Selected Implant Component") >= len(plan["sites"])


@_needs("dciodvfy", "dicom3tools")
def test_dciodvfy_accepts_the_iod(plan_dir):
    run = _run("dciodvfy", str(plan_dir / "plan.dcm"))
    assert not [line for line in (run.stdout + run.stderr).splitlines()
                if line.startswith("Error")], run.stdout + run.stderr
