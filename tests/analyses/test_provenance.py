"""The provenance block of a plan (analyses.provenance)."""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

from implantplan import models
from implantplan.analyses.provenance import provenance, sha256_file, without_volatile

ROOT = Path(__file__).resolve().parents[2]


def test_sha256_of_a_file_is_hashlib_of_its_bytes(tmp_path):
    path = tmp_path / "case.yaml"
    path.write_bytes(b"schema_version: 1\n" * 1000)
    assert sha256_file(path, chunk=7) == hashlib.sha256(path.read_bytes()).hexdigest()


def test_provenance_names_software_inputs_command_and_seed():
    case = models.model_path("cases/default.yaml")
    mesh = models.model_path("oral/oralCavityMesh.obj")
    block = provenance(case_file=case, meshes=[mesh], seed=7, argv=["implantplan", "demo"])
    assert block["seed"] == 7 and block["command"] == ["implantplan", "demo"]
    assert block["inputs"]["case"]["sha256"] == hashlib.sha256(case.read_bytes()).hexdigest()
    assert block["inputs"]["meshes"][0]["sha256"] == hashlib.sha256(mesh.read_bytes()).hexdigest()
    for name in ("implantplan", "python", "drake", "numpy", "scipy", "trimesh"):
        assert block["software"][name]
    assert block["utc"].endswith("+00:00")
    if (ROOT / ".git").exists():  # run from a checkout (the editable install of the tests)
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
        assert block["git"]["commit"] == head


def test_without_volatile_leaves_the_plan_and_drops_only_timings():
    plan = {"timing": {"fpsm": 1.0}, "provenance": {"utc": "x"}, "passed": True,
            "sites": [{"name": "36", "placement": {"seconds": 0.1, "d_T": 0.04},
                       "simulation": {"realtime_factor": 9.0,
                                      "runs": [{"wall_seconds": 2.0, "joint_travel": 1.5}]}}]}
    assert without_volatile(plan) == {
        "passed": True,
        "sites": [{"name": "36", "placement": {"d_T": 0.04},
                   "simulation": {"runs": [{"joint_travel": 1.5}]}}]}
    assert plan["timing"] == {"fpsm": 1.0}  # the input is not modified
