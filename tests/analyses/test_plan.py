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
from implantplan.analyses.provenance import without_volatile
from implantplan.systems.errors import InputError
from tests.analyses.cases import default_case_data
from tests.conftest import SMALL_PLAN_FLAGS

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


def test_capability_answers_are_exact_and_say_where_they_came_from(demo_run):
    """Never "NOT reachable" where IK reaches: each site's answer is the certified cell's or
    closed-form IK's at the target, and says which; the index names its map."""
    folder, printed = demo_run
    plan = json.loads((folder / "plan.json").read_text())
    for s in plan["sites"]:
        cap = s["capability"]
        assert cap["map_reachable"] == (cap["ik_branches_within_limits"] > 0)
        assert cap["map_answer"] in ("certified reachable", "resolved by IK")
        assert cap["index_map"].startswith("centre-sampled index (seed 004) of the certified map")
        assert f"site {s['name']}: reachable ({cap['map_answer']})" in printed
    assert "NOT reachable" not in printed
    assert "reachable (how it is known)" in (folder / "report.html").read_text()


def test_feeding_targets_are_consistent_across_frames(demo_plan):
    """The End target from the plan's base pose and q reproduces the feeding target in World."""
    from implantplan.diagrams import actuator_urdf as tools
    from implantplan.systems.robot import kinematics as kin
    from implantplan.systems.robot.moprp import R_OE

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


def _case(tmp_path, *, small: bool = False, **edits) -> Path:
    """The default case (tests.analyses.cases; ``small``: its small sizes) with ``edits`` (dotted
    keys), written to ``tmp_path/case.yaml``."""
    data = default_case_data(small=small)
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


# both sizes plan twice (11 s for the small case): CI runs them (sweep)
@pytest.mark.sweep
@pytest.mark.parametrize("size", ["small", "full"])
def test_same_seed_same_plan(tmp_path, size, request):
    """Every stage with its feeds, twice from one seed: the same plan (the small case by
    default, its first plan the run's shared one (tests/conftest.py ``small_plan``, planned in
    whichever worker process asked first); the default case's own sizes in the sweep)."""
    if size == "small":
        case, first = request.getfixturevalue("small_plan")
        flags = SMALL_PLAN_FLAGS
    else:
        case, flags, first = _case(tmp_path), FAST, tmp_path / "a"
        assert main(["plan", str(case), "--out", str(first), *flags]) == 0
    assert main(["plan", str(case), "--out", str(tmp_path / "b"), *flags]) == 0
    plans = [json.loads((folder / "plan.json").read_text()) for folder in (first, tmp_path / "b")]
    for plan in plans:
        assert plan["provenance"]["seed"] == plan["case"]["seed"]
    assert without_volatile(plans[0]) == without_volatile(plans[1])


def _same_to_rounding(a, b, path="plan"):
    """The paths where two plans differ beyond rounding: 1e-9 relative, or 1e-10 absolute (m;
    the exact distances' GJK stops at its tolerance, ~1e-11 m, at other last bits of its
    inputs)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{path}: keys {sorted(a.keys() ^ b.keys())}"]
        return [d for k in a for d in _same_to_rounding(a[k], b[k], f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} vs {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in
                _same_to_rounding(x, y, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float):
        return [] if a == pytest.approx(b, rel=1e-9, abs=1e-10) else [f"{path}: {a} vs {b}"]
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


@pytest.mark.sweep
def test_same_seed_same_plan_with_another_blas_kernel(tmp_path, small_plan):
    """The small case planned with OpenBLAS's generic kernel (OPENBLAS_CORETYPE=Prescott: other
    last bits in every BLAS and LAPACK result, as on another machine) is the same plan to
    rounding: the same placements, PSO iterations, base, branches and checks (before the
    searches compared rounded values, the base and the PSO's iterations moved)."""
    import os
    import subprocess
    import sys

    case, first = small_plan
    env = dict(os.environ, OPENBLAS_CORETYPE="Prescott")
    done = subprocess.run([sys.executable, "-m", "implantplan.analyses.cli", "plan", str(case),
                           "--out", str(tmp_path / "b"), *SMALL_PLAN_FLAGS], env=env,
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout + done.stderr
    plans = [without_volatile(json.loads((folder / "plan.json").read_text()))
             for folder in (first, tmp_path / "b")]
    for plan in plans:
        plan.pop("provenance", None)
    differences = _same_to_rounding(*plans)
    assert differences == [], "\n".join(differences)


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


def _box_mouth(tmp_path) -> Path:
    """A 300 mm box around the Center origin used as "the mouth": every site is far from it."""
    import trimesh

    box = trimesh.creation.box(extents=[300.0, 300.0, 300.0])
    box.apply_translation([135.0, 0.0, 90.0])
    path = tmp_path / "box.stl"
    box.export(path)
    return path


def _written(tmp_path, name: str, content: bytes | str) -> Path:
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return path


SITE_36 = np.array([14.3, -25.5, 37.1])  # mm in Center, on the tissue (models/cases/default.yaml)
AXIS_36 = np.array([-0.258819, 0.965926, 0.0])

# name -> (how to make the case: edits of the default case, or a callable(tmp_path) -> case path,
#          expected exit code, a piece of the message)
CATALOGUE = {
    "missing case file": (lambda t: t / "missing.yaml", 2, "case: file"),
    "case is a folder": (lambda t: t, 2, "case: "),
    "case is not YAML": (lambda t: _written(t, "c.yaml", "mesh: [unclosed\n"), 2,
                         "is not valid YAML"),
    "case is a list": (lambda t: _written(t, "c.yaml", "- 1\n- 2\n"), 2,
                       "must hold a YAML mapping"),
    "case is binary": (lambda t: _written(t, "c.yaml", b"\xff\xfe\x00\x81"), 2,
                       "is not a UTF-8 text file"),
    "unknown schema version": ({"schema_version": 2}, 2, "schema_version: expected 1"),
    "missing mesh file": ({"mesh.path": "nowhere.obj"}, 2, "mesh.path: file"),
    "mesh is a folder": ("mesh-folder", 2, "mesh.path: "),
    "corrupt STL": ("corrupt-stl", 2, "the file is corrupt or not a mesh format"),
    "wrong units": ({"mesh.units": "cm"}, 2, "mesh.units: expected one of mm, m"),
    "NaN vertices": ("nan-mesh", 2, "NaN"),
    "close_open_cuts not a bool": ({"mesh.close_open_cuts": "yes"}, 2,
                                   "mesh.close_open_cuts: expected true or false"),
    "mouth opened too far": ({"mesh.mouth_opening_deg": 60}, 2, "mesh.mouth_opening_deg"),
    "unknown key (a typo)": ({"fpsm.slice": 15}, 2, "fpsm.slice: unknown key"),
    "too few slices": ({"fpsm.slices": 1}, 2, "fpsm.slices"),
    "unknown fit method": ({"fpsm.method": "fast"}, 2, "fpsm.method"),
    "inverted z range": ({"fpsm.z_range_mm": [65.0, 0.0]}, 2, "fpsm.z_range_mm"),
    "zero Center axis": ({"center.z_axis": [0, 0, 0]}, 2, "center.z_axis"),
    "no sites": ({"sites": []}, 2, "sites: expected a list of at least one"),
    "zero axis": ({"sites.0.axis": [0, 0, 0]}, 2, "sites[0].axis: expected a non-zero"),
    "negative implant length": ({"sites.0.head_to_tip_mm": -5}, 2,
                                "sites[0].head_to_tip_mm"),
    "negative rod radius": ({"sites.0.rod_radius_mm": -1}, 2, "sites[0].rod_radius_mm"),
    "duplicate site names": ({"sites.1.name": "36"}, 2, "sites[1].name"),
    "site far outside the cavity": ({"sites.0.position_mm": [0.0, -200.0, 37.1]}, 2,
                                    "sites[0] (36): lies 1"),
    "site 5 mm off the jaw into the air": (
        {"sites.0.position_mm": (SITE_36 + 5 * AXIS_36).tolist()}, 2,
        "mm from the scanned tissue, expected at most 1 mm"),
    "site 10 mm off the jaw into the air": (
        {"sites.0.position_mm": (SITE_36 + 10 * AXIS_36).tolist()}, 2,
        "mm from the scanned tissue, expected at most 1 mm"),
    "site typed in metres": ({"sites.0.position_mm": (SITE_36 / 1000).tolist()}, 2,
                             "looks like metres typed into an _mm field"),
    "axis into the bone": ({"sites.0.axis": (-AXIS_36).tolist()}, 2,
                           "reversed axis would point into the cavity"),
    "a box as the mouth": ("box-mouth", 2, "sites[0] (36): lies"),
    "site tolerance not positive": ({"site_check.tolerance_mm": 0}, 2,
                                    "site_check.tolerance_mm"),
    "mesh in mm read as m": ({"mesh.units": "m"}, 2, "center.origin_mm: [135.0, 0.0, 90.0] mm "
                             "lies outside the mesh's bounding box"),
    "unknown objective": ({"placement.objective": "eq99"}, 2, "placement.objective"),
    "unknown posture": ({"patient.posture": "standing"}, 2, "patient.posture"),
    "contradicting posture and scenario": ({"robot.scenario": "sitting"}, 2,
                                           "robot.scenario: the bundled scenario"),
    "population too small": ({"robot.pop": 2}, 2, "robot.pop"),
    "voxel too small": ({"capability.voxel_mm": 1}, 2, "capability.voxel_mm"),
    "unknown simulation mode": ({"simulation.mode": "fast"}, 2, "simulation.mode"),
    "negative seed": ({"seed": -1}, 2, "seed"),
    "no base reaches the sites": ("far-scenario", 3, "no base position in the bounds"),
}


def _make_case(tmp_path, how) -> Path:
    if callable(how):
        return how(tmp_path)
    if how == "nan-mesh":
        return _case(tmp_path, **{"mesh.path": str(_nan_mesh(tmp_path))})
    if how == "far-scenario":  # fails at the robot stage: the small case's fit and placement
        return _case(tmp_path, small=True, **{"robot.scenario": str(_far_scenario(tmp_path))})
    if how == "mesh-folder":
        return _case(tmp_path, **{"mesh.path": str(tmp_path)})
    if how == "corrupt-stl":
        bad = _written(tmp_path, "scan.stl", b"solid x\n\x00\xff\xfe not a mesh" * 40)
        return _case(tmp_path, **{"mesh.path": str(bad)})
    if how == "box-mouth":
        return _case(tmp_path, **{"mesh.path": str(_box_mouth(tmp_path)),
                                  "mesh.close_open_cuts": False})
    return _case(tmp_path, **how)


@pytest.mark.parametrize("name", list(CATALOGUE))
def test_bad_inputs_fail_cleanly_and_keep_the_previous_plan(name, tmp_path, capsys, demo_plan):
    how, code, message = CATALOGUE[name]
    out = tmp_path / "out"
    shutil.copytree(demo_plan, out)  # a previous plan that must survive the failed run
    before = (out / "plan.json").read_bytes()
    case = _make_case(tmp_path, how)
    assert main(["plan", str(case), "--out", str(out), *FAST]) == code
    err = capsys.readouterr().err
    assert message in err, err
    assert "Traceback" not in err
    assert (out / "plan.json").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_the_catalogue_has_at_least_30_bad_inputs():
    assert len(CATALOGUE) >= 30


@pytest.mark.parametrize("where", ["/proc/no-such-dir/plan", "file-as-parent"])
def test_an_unwritable_out_folder_is_exit_2_naming_out(where, tmp_path, capsys):
    if where == "file-as-parent":
        (tmp_path / "f").write_text("x")
        where = str(tmp_path / "f" / "plan")
    case = _case(tmp_path)
    assert main(["plan", str(case), "--out", where, *FAST]) == 2
    err = capsys.readouterr().err
    assert "--out: cannot " in err and "Traceback" not in err


def test_an_unreadable_case_file_is_exit_2_naming_the_case(tmp_path, capsys, monkeypatch):
    case = _case(tmp_path)
    real = Path.read_text

    def deny(self, *args, **kwargs):  # root reads any file, so deny it the way the OS would
        if self == case:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "read_text", deny)
    assert main(["plan", str(case), "--out", str(tmp_path / "out"), *FAST]) == 2
    err = capsys.readouterr().err
    assert "case: cannot read" in err and "Permission denied" in err


def test_case_loader_reads_the_default_case():
    case = load_case(default_case_path())
    assert case.name == "default" and len(case.sites) == 2
    assert case.mesh.mouth_opening_deg == 25 and case.mesh.opening["blend"] == pytest.approx(0.02)
    assert case.mesh.path == models.model_path("oral/oralCavityMesh.obj")
    np.testing.assert_allclose(case.sites[0].position, SITE_36 * 1e-3)
    assert case.sites[0].rod_radius == pytest.approx(0.006)
    assert case.patient.posture == "lying" and case.robot.scenario == "lying"
    # the two margins are two fields: the FPSM fit's offset and the clinical margin
    assert case.fpsm.margin == 0.0 and case.safety.clearance_margin == pytest.approx(0.001)
    assert case.safety.angle_tolerance == pytest.approx(np.radians(1.0))


def test_case_loader_requires_sites(tmp_path):
    with pytest.raises(InputError, match="sites: expected a list"):
        load_case(_case(tmp_path, sites=[]))


def test_rerun_into_the_same_folder_replaces_the_plan_without_simulation(tmp_path, small_plan):
    case = _case(tmp_path, small=True, **{"safety.registration_samples": 0})
    out = tmp_path / "out"
    shutil.copytree(small_plan[1], out)  # the previous run's plan (with its feeds) in the folder
    assert any(s["simulation"] for s in json.loads((out / "plan.json").read_text())["sites"])
    args = ["plan", str(case), "--out", str(out), "--runs", "0", "--no-figures", "--quiet"]
    (out / "stale.txt").write_text("not the plan's")
    assert main(args) == 2  # a file put into the plan folder is the user's: refused, kept
    assert (out / "stale.txt").read_text() == "not the plan's"
    assert main([*args, "--force"]) == 0
    plan = json.loads((out / "plan.json").read_text())
    assert all(s["simulation"] is None for s in plan["sites"])
    sim_checks = {"feeds missing the target", "max VF violation", "FPSM collision alarms",
                  "min d_safe of the rod during feeds"}
    assert sim_checks.isdisjoint(c["name"] for c in plan["checks"])
    assert not (out / "stale.txt").exists()  # the folder is the new run's, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["case.yaml", "out"]


def test_check_margins_and_limits():
    from implantplan.analyses.checks import check as _check

    assert _check("a.alarms", "alarms", 0, 0, unit="runs", upper=True)["pass"]
    assert not _check("a.alarms", "alarms", 1, 0, unit="runs", upper=True)["pass"]
    c = _check("a.clearance", "clearance", 0.004, 0.0, unit="m", upper=False)
    assert c["pass"] and c["margin"] == pytest.approx(0.004) and c["bound"] == "min"
    assert not _check("a.clearance", "clearance", 0.0, 0.0, unit="m", upper=False)["pass"]
    c = _check("a.violation", "violation", 0.0015, 0.001, unit="m", upper=True)
    assert not c["pass"] and c["margin"] == pytest.approx(-0.0005) and c["bound"] == "max"
    assert c["id"] == "a.violation"


def test_every_check_of_the_demo_has_a_stable_unique_id_and_a_bound(demo_plan):
    plan = json.loads((demo_plan / "plan.json").read_text())
    keys = [(c["id"], c["site"]) for c in plan["checks"]]
    assert len(set(keys)) == len(keys)
    assert all(c["bound"] in ("min", "max") for c in plan["checks"])
    assert {c["id"] for c in plan["checks"]} >= {"fpsm.penetration_depth", "site.on_tissue",
                                                  "placement.line1_clearance"}
    html = (demo_plan / "report.html").read_text()
    assert "max (value &lt;= limit)" in html and "Provenance" in html
    assert plan["provenance"]["inputs"]["case"]["sha256"]


def test_the_demo_plan_validates_against_the_shipped_json_schema(demo_plan):
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(models.model_path("schemas/plan.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    plan = json.loads((demo_plan / "plan.json").read_text())
    jsonschema.Draft202012Validator(schema).validate(plan)
    broken = json.loads(json.dumps(plan))
    broken["checks"][0]["bound"] = "at most"  # the schema would catch a wrong check
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(broken, schema, cls=jsonschema.Draft202012Validator)
