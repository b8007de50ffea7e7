"""implantplan simulate feeding|circle and analyze layouts, through the CLI."""

import json

import pytest

from implantplan.analyses import simulate as S
from implantplan.analyses.cli import main
from implantplan.systems.fpsm.model import Fpsm


def read(path):
    return json.loads(path.read_text())


def test_feeding_writes_the_runs(tmp_path):
    out = tmp_path / "feed"
    assert main(["simulate", "feeding", "--runs", "2", "--seed", "3", "--out", str(out),
                 "--quiet"]) == 0
    data = read(out / "feeding.json")
    assert data["kind"] == "feeding" and data["schema_version"] == 1
    assert len(data["runs"]) == 2
    for run in data["runs"]:
        for key in ("joint_travel", "min_d_safe", "max_vf_violation", "collision_alarm",
                    "sim_seconds", "wall_seconds"):
            assert key in run
        assert run["max_vf_violation"] < 0.001 and not run["collision_alarm"]
        assert run["reached_target"]
    assert data["realtime_factor"] > 0
    assert data["operator"]["tremor"] == pytest.approx(5e-5)
    assert data["runs"][0]["joint_travel"] != data["runs"][1]["joint_travel"]
    assert (out / "feeding_travel.png").stat().st_size > 0


def test_feeding_from_an_instrument_plan(tmp_path):
    fpsm_path = Fpsm.cylinder(0.05, 0.0, 0.1, slices=11).save(tmp_path / "fpsm.json")
    plan = tmp_path / "placement.json"
    code = main(["instrument", "place", "--fpsm", str(fpsm_path), "--hole-mm", "0", "-50", "50",
                 "--hole-axis", "0", "1", "0", "--rod-radius-mm", "6",
                 "--implant-length-mm", "31", "--out", str(plan)])
    assert code == 0
    out = tmp_path / "feed"
    assert main(["simulate", "feeding", "--plan", str(plan), "--runs", "1", "--out", str(out),
                 "--quiet"]) == 0
    data = read(out / "feeding.json")
    assert data["instrument"] == str(plan)
    assert data["runs"][0]["reached_target"] and not data["runs"][0]["collision_alarm"]


def test_circle_writes_the_path_error(tmp_path, monkeypatch):
    """The circle runs the arm alone: no instrument is placed for it (a --plan is still read)."""

    def no_placement(*args, **kwargs):
        raise AssertionError("the circle placed an instrument")

    monkeypatch.setattr(S, "default_instrument", no_placement)
    assert main(["simulate", "circle", "--plan", str(tmp_path / "none.json"), "--out",
                 str(tmp_path / "x"), "--quiet"]) == 2
    out = tmp_path / "circle"
    assert main(["simulate", "circle", "--realizations", "3", "--out", str(out), "--quiet"]) == 0
    data = read(out / "circle.json")
    # joint errors of ~0.1 deg on a ~1 m arm: a path error of the order of a millimetre
    assert 1e-4 < data["path_error_mean"] < 5e-3
    assert data["path_error_max"] >= data["path_error_mean"]
    assert (out / "circle.png").stat().st_size > 0


def test_layouts_ranks_and_plots(tmp_path):
    out = tmp_path / "layouts"
    assert main(["analyze", "layouts", "--random", "2", "--runs", "1", "--realizations", "2",
                 "--out", str(out), "--quiet"]) == 0
    data = read(out / "layouts.json")
    assert data["of"] == 3 and data["layouts"][0]["label"] == "win"
    for key in ("joint_travel", "path_error", "gii", "gii_mm_deg", "joint_variation_index"):
        assert 1 <= data["ranks"][key] <= 3
    for name in ("path_error", "joint_travel", "gii"):
        assert (out / f"layouts_{name}.png").stat().st_size > 0


@pytest.mark.parametrize(
    "argv, field",
    [
        (["simulate", "feeding", "--runs", "0"], "--runs"),
        (["simulate", "feeding", "--plan", "/nonexistent.json"], "--plan"),
        (["simulate", "circle", "--scenario", "standing"], "--scenario"),
        (["analyze", "layouts", "--random", "0"], "--random"),
        (["simulate", "feeding", "--tremor-mm", "-1"], "tremor"),
        (["analyze", "layouts", "--drift-mm", "-1"], "drift"),
        (["simulate", "feeding", "--head-motion", "sneeze"], "--head-motion"),
        (["simulate", "feeding", "--head-motion", "drift", "--mode", "dynamic"], "--head-motion"),
    ],
)
def test_bad_input_exits_2(tmp_path, capsys, monkeypatch, argv, field):
    """Every flag is checked before the instrument is placed or a layout searched."""

    def no_work(*args, **kwargs):
        raise AssertionError("placed the instrument or searched a layout before the flags")

    monkeypatch.setattr(S, "default_instrument", no_work)
    monkeypatch.setattr(S, "knee_layout", no_work)
    assert main([*argv, "--out", str(tmp_path / "x"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert field in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()



def test_rank_of_first_by_hand():
    assert S.rank_of_first([1.0, 2.0, 3.0]) == 1
    assert S.rank_of_first([2.0, 1.0, 3.0]) == 2
    assert S.rank_of_first([2.0, 1.0, 3.0], higher_is_better=True) == 2
    assert S.rank_of_first([1.0, 1.0, 0.5]) == 2  # ties count in its favour
