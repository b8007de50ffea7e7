"""Every kind of YAML file the project reads (case, MOPRP scenario, RASSCMAP patient/task/robot,
cohort): a typo'd key and a duplicated key are input errors naming the key, through the loader
and through the command (exit 2, the field in the message, no traceback, nothing written).

Each test edits the text of a bundled file, so the file stays in the form users write it."""

from pathlib import Path

import pytest

from implantplan import models
from implantplan.analyses.case import default_case_path, load_case
from implantplan.analyses.cli import main
from implantplan.analyses.cohort import load_cohort
from implantplan.systems.capability import rasscmap_inputs as rin
from implantplan.systems.errors import InputError
from implantplan.systems.robot import moprp

CAPMAP_CASES = models.MODELS_DIR / "capmap_cases"


def _edited(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, old  # the edit hits exactly the line meant
    return text.replace(old, new)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _case_text(**scenario) -> str:
    text = default_case_path().read_text()
    if scenario:
        text = _edited(text, "robot: {scenario: lying,", f"robot: {{scenario: {scenario['path']},")
    return text


def _scenario_text() -> str:
    return moprp.scenario_path("lying").read_text()


# -- case ----------------------------------------------------------------------------------------

CASE_EDITS = {
    "typo in a section": ("safety: {clearance_mm: 1.0,", "safety: {clearence_mm: 1.0,",
                          "safety.clearence_mm: unknown key"),
    "typo at the top": ("seed: 0\n", "sede: 0\n", "sede: unknown key"),
    "typo in a site": ("placed_implant_length_mm: 10.0}\n  - {name: \"46\"",
                       "placed_implant_lenght_mm: 10.0}\n  - {name: \"46\"",
                       "sites[0].placed_implant_lenght_mm: unknown key"),
    "duplicate in a section": ("fpsm: {slices: 15,", "fpsm: {slices: 15, slices: 16,",
                               "fpsm.slices: duplicate key"),
    "duplicate at the top": ("seed: 0\n", "seed: 0\nseed: 3\n", "seed: duplicate key"),
    "duplicate in a site": ("- {name: \"46\",", "- {name: \"46\", name: \"47\",",
                            "sites[1].name: duplicate key"),
    "duplicate section": ("placement: {objective: eq14}\n",
                          "placement: {objective: eq14}\nplacement: {objective: eq22}\n",
                          "placement: duplicate key"),
}


@pytest.mark.parametrize("name", list(CASE_EDITS))
def test_case_key_errors_name_the_key(name, tmp_path):
    old, new, message = CASE_EDITS[name]
    path = _write(tmp_path, "case.yaml", _edited(_case_text(), old, new))
    with pytest.raises(InputError) as err:
        load_case(path)
    assert message in str(err.value)


def test_a_duplicate_key_names_both_lines(tmp_path):
    text = _edited(_case_text(), "seed: 0\n", "seed: 0\nseed: 3\n")
    line = text.splitlines().index("seed: 0") + 1
    with pytest.raises(InputError, match=rf"^seed: duplicate key in .*case\.yaml \(line "
                                         rf"{line + 1}, first given on line {line}\)"):
        load_case(_write(tmp_path, "case.yaml", text))


@pytest.mark.parametrize("name", ["typo in a section", "duplicate in a section"])
def test_plan_exits_2_naming_the_case_key(name, tmp_path, capsys):
    old, new, message = CASE_EDITS[name]
    path = _write(tmp_path, "case.yaml", _edited(_case_text(), old, new))
    out = tmp_path / "out"
    assert main(["plan", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not out.exists()


def test_plan_exits_2_on_an_alias_in_the_case(tmp_path, capsys):
    text = _edited(_case_text(), "safety: {clearance_mm: 1.0,", "safety: &s {clearance_mm: 1.0,")
    path = _write(tmp_path, "case.yaml", text + "extra: *s\n")
    assert main(["plan", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "case: " in err and "aliases are not supported" in err and "&s" in err


# -- scenario ------------------------------------------------------------------------------------

SCENARIO_EDITS = {
    "typo at the top": ("clearance_m: 0.005\n", "clearence_m: 0.02\n",
                        "clearence_m: unknown key"),
    "typo in an obstacle": ("radius_m: 0.13}", "radius_mm: 0.13}",
                            "obstacles[2].radius_mm: unknown key"),
    "a capsule's key on a box": ("size_m: [0.60, 2.00, 0.20]}",
                                 "size_m: [0.60, 2.00, 0.20], radius_m: 0.1}",
                                 "obstacles[3].radius_m: unknown key"),
    "typo in a section": ("  rod_radius_m: 0.006", "  rod_radius: 0.006",
                          "actuator.rod_radius: unknown key"),
    "typo in the ga": ("hv_tol: 0.001}", "hv_toll: 0.001}", "ga.hv_toll: unknown key"),
    "duplicate in the ga": ("ga: {pop: 500,", "ga: {pop: 500, pop: 400,", "ga.pop: duplicate key"),
    "duplicate in an obstacle": ("{name: legs,", "{name: legs, name: shins,",
                                 "obstacles[2].name: duplicate key"),
    "duplicate at the top": ("clearance_m: 0.005\n", "clearance_m: 0.005\nclearance_m: 0.02\n",
                             "clearance_m: duplicate key"),
}


@pytest.mark.parametrize("name", list(SCENARIO_EDITS))
def test_scenario_key_errors_name_the_key(name, tmp_path):
    old, new, message = SCENARIO_EDITS[name]
    path = _write(tmp_path, "scenario.yaml", _edited(_scenario_text(), old, new))
    with pytest.raises(InputError) as err:
        moprp.load_scenario(path)
    assert message in str(err.value)


@pytest.mark.parametrize("name", ["typo at the top", "typo in an obstacle", "duplicate in the ga"])
def test_plan_exits_2_naming_the_key_of_the_cases_scenario(name, tmp_path, capsys):
    old, new, message = SCENARIO_EDITS[name]
    scenario = _write(tmp_path, "room.yaml", _edited(_scenario_text(), old, new))
    path = _write(tmp_path, "case.yaml", _case_text(path=str(scenario)))
    out = tmp_path / "out"
    assert main(["plan", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert "room.yaml" in err  # which file: the case names its scenario by path
    assert not out.exists()


def test_robot_place_exits_2_naming_the_scenario_key(tmp_path, capsys):
    old, new, message = SCENARIO_EDITS["typo in an obstacle"]
    scenario = _write(tmp_path, "room.yaml", _edited(_scenario_text(), old, new))
    assert main(["robot", "place", "--scenario", str(scenario), "--quiet",
                 "--out", str(tmp_path / "o")]) == 2
    assert message in capsys.readouterr().err


# -- RASSCMAP inputs -----------------------------------------------------------------------------

RASSCMAP_EDITS = {
    "patient typo": ("dental_patient.yaml", "  map_depth: 0.10", "  map_dept: 0.10",
                     "patient.map_dept: unknown key"),
    "patient duplicate": ("dental_patient.yaml", "  map_depth: 0.10",
                          "  map_depth: 0.10\n  map_depth: 0.20",
                          "patient.map_depth: duplicate key"),
    "task typo": ("dental_task.yaml", "{xyz: [-0.035, 0.0, 1.00], rpy_deg:",
                  "{xyz: [-0.035, 0.0, 1.00], rpy:", "task.poses[2].rpy: unknown key"),
    "task duplicate": ("dental_task.yaml", "{xyz: [-0.035, 0.0, 1.00],",
                       "{xyz: [-0.035, 0.0, 1.00], xyz: [0, 0, 1],",
                       "task.poses[2].xyz: duplicate key"),
    "robot typo": ("dental_robot.yaml", "  rotation_step_deg: 15", "  rotation_step: 15",
                   "robot.rotation_step: unknown key"),
    "robot build typo": ("dental_robot.yaml", "build: {voxel_mm: 50,", "build: {voxel: 50,",
                         "robot.build.voxel: unknown key"),
    "robot duplicate": ("dental_robot.yaml", "yaw_deg: [90, 270]}",
                        "yaw_deg: [90, 270], yaw_deg: [0, 90]}",
                        "robot.base_ranges[1].yaw_deg: duplicate key"),
}
LOADERS = {"patient": rin.load_patient, "task": rin.load_task, "robot": rin.load_robot}


@pytest.mark.parametrize("name", list(RASSCMAP_EDITS))
def test_rasscmap_key_errors_name_the_key(name, tmp_path):
    file, old, new, message = RASSCMAP_EDITS[name]
    path = _write(tmp_path, file, _edited((CAPMAP_CASES / file).read_text(), old, new))
    with pytest.raises(InputError) as err:
        LOADERS[name.split()[0]](path)
    assert message in str(err.value)


def test_capmap_plan_exits_2_naming_the_key(tmp_path, capsys):
    files = {kind: CAPMAP_CASES / f"dental_{kind}.yaml" for kind in LOADERS}
    file, old, new, message = RASSCMAP_EDITS["robot duplicate"]
    files["robot"] = _write(tmp_path, file, _edited(files["robot"].read_text(), old, new))
    out = tmp_path / "out"
    assert main(["capmap", "plan", "--patient", str(files["patient"]), "--task",
                 str(files["task"]), "--robot", str(files["robot"]), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


# -- cohort --------------------------------------------------------------------------------------

COHORT = "schema_version: 1\nname: molars\ncases: [a.yaml, b.yaml]\n"
COHORT_EDITS = {
    "typo": ("cases: [", "case: [", "case: unknown key"),
    "duplicate": ("name: molars\n", "name: molars\nname: premolars\n", "name: duplicate key"),
}


@pytest.mark.parametrize("name", list(COHORT_EDITS))
def test_cohort_key_errors_name_the_key(name, tmp_path):
    name_, files = load_cohort(_write(tmp_path, "cohort.yaml", COHORT))
    assert name_ == "molars" and [f.name for f in files] == ["a.yaml", "b.yaml"]
    old, new, message = COHORT_EDITS[name]
    path = _write(tmp_path, "cohort.yaml", _edited(COHORT, old, new))
    with pytest.raises(InputError) as err:
        load_cohort(path)
    assert message in str(err.value)


def test_batch_exits_2_naming_the_cohort_key(tmp_path, capsys):
    old, new, message = COHORT_EDITS["duplicate"]
    path = _write(tmp_path, "cohort.yaml", _edited(COHORT, old, new))
    assert main(["batch", "--cohort", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


# -- the unedited files read (so each failure above comes from its edit) --------------------------


def test_the_bundled_files_read(tmp_path):
    assert load_case(_write(tmp_path, "case.yaml", _case_text())).name == "default"
    assert moprp.load_scenario(_write(tmp_path, "s.yaml", _scenario_text())).clearance == 0.005
    for kind, load in LOADERS.items():
        load(_write(tmp_path, f"dental_{kind}.yaml",
                    (CAPMAP_CASES / f"dental_{kind}.yaml").read_text()))


def test_the_old_name_of_d12_is_still_read_with_a_note_once(monkeypatch, capsys):
    import yaml

    from implantplan.analyses import case as case_module
    from implantplan.analyses.case import case_from_dict, default_case_path, load_case

    monkeypatch.setattr(case_module, "notes_printed", set())
    data = yaml.safe_load(default_case_path().read_text())
    data["instrument"] = "paper"  # d12 per site is the paper tool's
    for s in data["sites"]:
        s["implant_length_mm"] = 32.0
    old = case_from_dict(data, source=default_case_path())
    assert [s.implant_length for s in old.sites] == pytest.approx([0.032, 0.032])
    assert old.instrument_at(old.sites[0]).implant_length == pytest.approx(0.032)
    new = load_case(default_case_path())
    assert [new.instrument_at(s).implant_length for s in new.sites] == pytest.approx(
        [0.031, 0.031])  # the actuator's own
    err = capsys.readouterr().err
    assert err.count("note: sites[0].implant_length_mm is read as head_to_tip_mm") == 1
    assert "sites[1]" not in err  # once per run, not per site
    data["sites"][0]["head_to_tip_mm"] = 31.0
    with pytest.raises(InputError, match=r"sites\[0\]\.implant_length_mm: .*not both"):
        case_from_dict(data, source=default_case_path())


@pytest.mark.parametrize("text,where", [
    ("a: !!python/object:os.system {}\n", "line 1, column 4"),
    ("base: {x: 1}\nb:\n  <<: {x: 2}\n", "line 3, column 3"),
    ("a: [1, 2\n", "line 2, column 1"),
    ("a: b: c\n", "line 1, column 5"),
])
def test_a_yaml_syntax_error_is_one_line_naming_where(tmp_path, text, where):
    """PyYAML's marked errors span lines (the offending line copied, a caret under it); the
    message a user reads is one line with the line and column."""
    from implantplan.systems.files import read_yaml

    path = tmp_path / "case.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        read_yaml(path, field="case")
    message = str(info.value)
    assert "\n" not in message and where in message and "not valid YAML" in message
