"""The case pipeline end to end: ``implantplan plan`` / ``demo``, plan.json, report.html, and the
catalogue of bad inputs (each a clear message and exit code, never a half-written plan)."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from implantplan import models
from implantplan.analyses.case import default_case_path, load_case
from implantplan.analyses.cli import main
from implantplan.systems.errors import InputError

FAST = ["--runs", "1", "--no-html-scene", "--quiet"]


def test_demo_writes_a_complete_passing_plan(demo_plan):
    plan = json.loads((demo_plan / "plan.json").read_text())
    assert plan["schema_version"] == 1 and plan["kind"] == "plan"
    for key in ("fpsm", "sites", "base", "checks"):
        assert key in plan
    assert plan["passed"] and all(c["pass"] for c in plan["checks"])
    assert [s["name"] for s in plan["sites"]] == ["36", "46"]
    for s in plan["sites"]:
        assert s["placement"]["valid"] and s["placement"]["d_safe_min_line1"] > 0
        assert len(s["ik"]["q_pre"]) == 6 and 0 <= s["ik"]["branch"] < 8
        # the fixture's axis is the rod (line1) of the placement
        np.testing.assert_allclose(s["vf"]["direction"], s["placement"]["line1"]["direction"],
                                   atol=1e-12)
        assert s["simulation"]["runs"][0]["reached_target"]
        # SceneGraph confirmed the feed: each reported configuration carries its clearance
        feed = s["ik"]["feed_clearance"]
        assert feed["limit_m"] == 0.005 and feed["samples"] >= 61 and all(feed["pair"])
        for key in ("scene_graph_clearance_m", "scene_graph_clearance_pre_m"):
            assert s["ik"][key] >= feed["distance_m"] >= feed["limit_m"]
    arm = [c for c in plan["checks"] if c["name"] == "arm clearance along the feed (SceneGraph)"]
    assert [c["site"] for c in arm] == ["36", "46"]
    assert all(c["pass"] and c["limit"] == 0.005 and " / " in c["pair"] for c in arm)
    assert plan["base"]["selection_dropped"] >= 0
    assert (demo_plan / "fpsm.json").is_file() and (demo_plan / "layout.html").is_file()
    html = (demo_plan / "report.html").read_text()
    for img in __import__("re").findall(r"src='([^']+)'", html):
        assert (demo_plan / img).is_file(), img
    assert "PASS" in html and "<iframe" in html
    assert "arm clearance along the feed (SceneGraph) (aubo::" in html


def test_feeding_targets_are_consistent_across_frames(demo_plan):
    """The End target from the plan's base pose and q reproduces the feeding target in World."""
    from implantplan.diagrams import tools
    from implantplan.systems import kinematics as kin
    from implantplan.systems.moprp import R_OE

    plan = json.loads((demo_plan / "plan.json").read_text())
    X_WB = np.array(plan["base"]["X_WBase"])
    for s in plan["sites"]:
        X_WE = X_WB @ kin.fk(np.array(s["ik"]["q"]), tools.X_FT())
        X_WT = np.array(s["feeding_target"]["X_WT"])
        np.testing.assert_allclose(X_WE[:3, 3], X_WT[:3, 3], atol=1e-9)
        np.testing.assert_allclose(X_WE[:3, :3], X_WT[:3, :3] @ R_OE, atol=1e-9)
        # and the Tool pose in World is Center's pose times X_CT
        X_WC = np.array(plan["frames"]["X_WCenter"])
        np.testing.assert_allclose(X_WC @ np.array(s["feeding_target"]["X_CT"]), X_WT, atol=1e-12)


def _case(tmp_path, **edits) -> Path:
    data = yaml.safe_load(default_case_path().read_text())
    data["mesh"]["path"] = str(models.model_path("oral/oralCavityMesh.obj"))
    for dotted, value in edits.items():
        d = data
        keys = dotted.split(".")
        for k in keys[:-1]:
            d = d[int(k)] if isinstance(d, list) else d[k]
        if value is _DELETE:
            del d[keys[-1]]
        elif isinstance(d, list):
            d[int(keys[-1])] = value
        else:
            d[keys[-1]] = value
    path = tmp_path / "case.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


_DELETE = object()


def test_same_seed_same_plan(tmp_path):
    case = _case(tmp_path)
    plans = []
    for name in ("a", "b"):
        assert main(["plan", str(case), "--out", str(tmp_path / name), *FAST]) == 0
        plan = json.loads((tmp_path / name / "plan.json").read_text())
        plan.pop("timing")
        for s in plan["sites"]:
            s["placement"].pop("seconds")
            for r in s["simulation"]["runs"]:
                r.pop("wall_seconds")
            s["simulation"].pop("realtime_factor")
        plans.append(plan)
    assert plans[0] == plans[1]


def _nan_mesh(tmp_path) -> Path:
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 2 3 4\nf 1 3 4\n")
    return path


def _far_scenario(tmp_path) -> Path:
    data = yaml.safe_load(models.model_path("scenarios/lying.yaml").read_text())
    data["base_bounds_m"] = {"x": [3.0, 3.5], "y": [-0.7, 0.1], "z": [-0.5, 0.5]}
    path = tmp_path / "far.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


# (edits, expected exit code, a piece of the message)
CATALOGUE = {
    "missing case file": (None, 2, "case: file"),
    "missing mesh file": ({"mesh.path": "nowhere.obj"}, 2, "mesh.path: file"),
    "wrong units": ({"mesh.units": "cm"}, 2, "mesh.units: expected one of mm, m"),
    "NaN vertices": ("nan-mesh", 2, "NaN"),
    "unknown key (a typo)": ({"fpsm.slice": 15}, 2, "fpsm.slice: unknown key"),
    "inverted z range": ({"fpsm.z_range_mm": [65.0, 0.0]}, 2, "fpsm.z_range_mm"),
    "zero axis": ({"sites.0.axis": [0, 0, 0]}, 2, "sites[0].axis: expected a non-zero"),
    "site outside the cavity": ({"sites.0.position_mm": [0.0, -200.0, 37.1]}, 2,
                                "sites[0] (site 36): hole: lies 166"),
    "mesh in mm read as m": ({"mesh.units": "m"}, 2, "center.origin_mm: [135.0, 0.0, 90.0] mm "
                             "lies outside the mesh's bounding box"),
    "axis into the bone": ({"sites.0.axis": [0.258819, -0.965926, 0.0]}, 3, "site 36"),
    "no base reaches the sites": ("far-scenario", 3, "no base position in the bounds"),
    "contradicting posture and scenario": ({"robot.scenario": "sitting"}, 2,
                                           "robot.scenario: the bundled scenario"),
    "duplicate site names": ({"sites.1.name": "36"}, 2, "sites[1].name"),
}


@pytest.mark.parametrize("name", list(CATALOGUE))
def test_bad_inputs_fail_cleanly_and_keep_the_previous_plan(name, tmp_path, capsys, demo_plan):
    edits, code, message = CATALOGUE[name]
    out = tmp_path / "out"
    shutil.copytree(demo_plan, out)  # a previous plan that must survive the failed run
    before = (out / "plan.json").read_bytes()
    if edits is None:
        case = tmp_path / "missing.yaml"
    elif edits == "nan-mesh":
        case = _case(tmp_path, **{"mesh.path": str(_nan_mesh(tmp_path))})
    elif edits == "far-scenario":
        case = _case(tmp_path, **{"robot.scenario": str(_far_scenario(tmp_path))})
    else:
        case = _case(tmp_path, **edits)
    assert main(["plan", str(case), "--out", str(out), *FAST]) == code
    err = capsys.readouterr().err
    assert message in err, err
    assert "Traceback" not in err
    assert (out / "plan.json").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_case_loader_reads_the_default_case():
    case = load_case(default_case_path())
    assert case.name == "default" and len(case.sites) == 2
    assert case.mouth_opening_deg == 25 and case.opening["blend"] == pytest.approx(0.02)
    np.testing.assert_allclose(case.sites[0].position, [0.0139, -0.0241, 0.0371])
    assert case.sites[0].rod_radius == pytest.approx(0.006)
    assert case.posture == "lying" and case.scenario == "lying"


def test_case_loader_requires_sites(tmp_path):
    with pytest.raises(InputError, match="sites: expected a list"):
        load_case(_case(tmp_path, sites=[]))


def test_rerun_into_the_same_folder_replaces_the_plan_without_simulation(tmp_path):
    case = _case(tmp_path)
    out = tmp_path / "out"
    args = ["plan", str(case), "--out", str(out), "--runs", "0", "--no-html-scene", "--quiet"]
    assert main(args) == 0
    (out / "stale.txt").write_text("from the previous run")
    assert main(args) == 0
    plan = json.loads((out / "plan.json").read_text())
    assert all(s["simulation"] is None for s in plan["sites"])
    sim_checks = {"feeds missing the target", "max VF violation", "FPSM collision alarms",
                  "min d_safe of the rod during feeds"}
    assert sim_checks.isdisjoint(c["name"] for c in plan["checks"])
    assert not (out / "stale.txt").exists()  # the folder is the new run's, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["case.yaml", "out"]


def test_check_margins_and_limits():
    from implantplan.analyses.plan import _check

    assert _check("alarms", 0, 0, unit="runs", upper=True)["pass"]
    assert not _check("alarms", 1, 0, unit="runs", upper=True)["pass"]
    c = _check("clearance", 0.004, 0.0, unit="m", upper=False)
    assert c["pass"] and c["margin"] == pytest.approx(0.004)
    assert not _check("clearance", 0.0, 0.0, unit="m", upper=False)["pass"]  # contact
    c = _check("violation", 0.0015, 0.001, unit="m", upper=True)
    assert not c["pass"] and c["margin"] == pytest.approx(-0.0005)
