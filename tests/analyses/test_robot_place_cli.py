"""``implantplan robot place`` (analyses.robot): outputs, exit codes, --plan."""

import json

import numpy as np
import pytest
import yaml

from implantplan.analyses.cli import main
from implantplan.systems.files import read_json, read_yaml, write_json
from implantplan.systems.robot import moprp
from implantplan.systems.robot.nsga2 import domination_matrix

SMALL = ["--pop", "24", "--gen", "6", "--percentile-samples", "60", "--quiet"]


def _scenario_file(tmp_path, **changes):
    d = read_yaml(moprp.scenario_path("lying"))
    for key, value in changes.items():
        node = d
        parts = key.split(".")
        for k in parts[:-1]:
            node = node[k]
        node[parts[-1]] = value
    path = tmp_path / "scenario.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def test_small_run_writes_the_placement(tmp_path):
    out = tmp_path / "run"
    assert main(["robot", "place", "--scenario", "lying", *SMALL, "--out", str(out)]) == 0
    data = read_json(out / "placement.json", kind="robot_placement")
    for key in ("pareto", "selected", "gii", "evaluations", "seconds"):
        assert key in data
    F = np.array([[e["indices"][n] for n in moprp.INDEX_NAMES] for e in data["pareto"]])
    assert F.shape[0] >= 3
    assert not domination_matrix(F).any()  # the front is non-dominated
    sel = data["selected"]
    assert set(sel["percentiles"]) == set(moprp.INDEX_NAMES)
    assert all(0 <= v <= 100 for v in sel["percentiles"].values())
    assert len(sel["q"]) == 6 and 0 <= sel["branch"] < 8
    assert data["gii"]["poses"] == 100 and 0 < data["gii"]["gii"] < 1
    assert data["evaluations"] == 4 * 24 + 24 * (data["generations"] + 1)
    # the selection is on the front and reproduces its own indices
    sc = moprp.load_scenario("lying")
    ev = moprp.evaluate_bases(np.array([sel["base_xyz"]]), sc, np.random.default_rng(0))
    assert ev.feasible[0]
    # every written configuration carries its SceneGraph clearance, at least the scenario's
    assert all(e["scene_graph_clearance_m"] >= sc.clearance for e in data["pareto"])
    assert sel["scene_graph_clearance_m"] >= sc.clearance and len(sel["scene_graph_pair"]) == 2
    feed = sel["feed_clearance"]
    assert feed["distance_m"] >= feed["limit_m"] == sc.clearance and feed["samples"] >= 61
    conf = data["confirmation"]
    assert conf["front"] == len(data["pareto"]) + conf["pareto_dropped"]
    from implantplan.diagrams.arm_clearance import SceneGraphClearance

    check = SceneGraphClearance(sc, np.array(sel["base_xyz"]))(
        np.array([sel["q_pre"], sel["q"]]), max_distance=1.0)
    assert check.distance.min() == pytest.approx(sel["scene_graph_clearance_m"], abs=1e-12)
    for png in ("pareto_design", "pareto_objectives", "layout_after", "layout_before"):
        assert (out / f"{png}.png").stat().st_size > 1000
    html = (out / "layout.html").read_text()
    assert "<html" in html.lower() and len(html) > 10000


def test_same_seed_same_front(tmp_path):
    args = ["robot", "place", "--scenario", "sitting", *SMALL, "--no-plots", "--seed", "5"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    a = json.loads((tmp_path / "a" / "placement.json").read_text())
    b = json.loads((tmp_path / "b" / "placement.json").read_text())
    assert a["pareto"] == b["pareto"] and a["selected"] == b["selected"]


def test_unreachable_bounds_exit_3(tmp_path, capsys):
    path = _scenario_file(tmp_path, **{"base_bounds_m.x": [4.0, 5.0]})
    code = main(["robot", "place", "--scenario", str(path), *SMALL, "--out", str(tmp_path / "o")])
    assert code == 3
    err = capsys.readouterr().err
    assert "no feasible base" in err and "no IK solution" in err


def test_inverted_bounds_exit_2(tmp_path, capsys):
    path = _scenario_file(tmp_path, **{"base_bounds_m.z": [0.5, -0.5]})
    code = main(["robot", "place", "--scenario", str(path), *SMALL, "--out", str(tmp_path / "o")])
    assert code == 2
    assert "base_bounds_m.z" in capsys.readouterr().err


def test_malformed_yaml_exit_2(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text("name: [unclosed\nbase_bounds_m: {x: [0, 1]\n")
    code = main(["robot", "place", "--scenario", str(path), *SMALL, "--out", str(tmp_path / "o")])
    assert code == 2
    assert "not valid YAML" in capsys.readouterr().err


def test_missing_scenario_exit_2(tmp_path):
    code = main(["robot", "place", "--scenario", str(tmp_path / "nope.yaml"), *SMALL,
                 "--out", str(tmp_path / "o")])
    assert code == 2


def test_plan_gives_the_oral_pose(tmp_path):
    sc = moprp.load_scenario("lying")
    X_WT = sc.X_WO.copy()
    X_WT[:3, 3] += [0.05, -0.02, 0.03]
    plan = tmp_path / "plan.json"
    write_json(plan, {"X_WT": X_WT}, kind="placement")
    out = tmp_path / "run"
    assert main(["robot", "place", "--scenario", "lying", "--plan", str(plan), *SMALL,
                 "--no-plots", "--out", str(out)]) == 0
    data = read_json(out / "placement.json")
    np.testing.assert_allclose(data["scenario"]["X_WO"], X_WT)
    assert "X_WT" in data["inputs"]["oral_from"]
    np.testing.assert_allclose(
        data["selected"]["X_WBase"], X_WT @ moprp.base_pose(data["selected"]["base_xyz"]))


def test_plan_without_a_target_exit_2(tmp_path, capsys):
    plan = tmp_path / "plan.json"
    write_json(plan, {"X_CT": np.eye(4)}, kind="placement")
    code = main(["robot", "place", "--scenario", "lying", "--plan", str(plan), *SMALL,
                 "--out", str(tmp_path / "o")])
    assert code == 2
    assert "X_WC" in capsys.readouterr().err


@pytest.mark.parametrize("flag", [["--pop", "2"], ["--weights", "0", "0", "0"]])
def test_bad_flags_exit_2(tmp_path, flag):
    args = ["robot", "place", "--scenario", "lying", *SMALL, *flag, "--out", str(tmp_path / "o")]
    assert main(args) == 2


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["lying", "sitting"])
def test_paper_setting_500_by_500(tmp_path, scenario):
    out = tmp_path / scenario
    assert main(["robot", "place", "--scenario", scenario, "--full", "--no-plots", "--quiet",
                 "--out", str(out)]) == 0
    data = read_json(out / "placement.json")
    assert data["generations"] == 500 and data["pop"] == 500
    assert len(data["pareto"]) >= 50


def test_drake_ik_path_matches_the_closed_form():
    """--ik drake: Drake's multi-start IK, tracked along the feed and labelled by the nearest
    closed-form branch, gives the same surviving branches and indices at a base."""
    import dataclasses

    from implantplan.analyses.robot import drake_ik_solver

    sc = dataclasses.replace(moprp.load_scenario("lying"), feed_samples=2)
    xyz = np.array([[0.6, -0.3, 0.0]])
    solver = drake_ik_solver(starts=64, seed=0, limits=sc.limits, X_FT=sc.X_FT)
    ev_d = moprp.evaluate_bases(xyz, sc, np.random.default_rng(0), ik_solver=solver)
    ev_c = moprp.evaluate_bases(xyz, sc, np.random.default_rng(0))
    assert ev_c.valid.sum() >= 2
    np.testing.assert_array_equal(ev_d.valid, ev_c.valid)
    np.testing.assert_allclose(ev_d.candidate_indices[ev_c.valid],
                               ev_c.candidate_indices[ev_c.valid], rtol=1e-5)
    # the feed's samples, and the head-motion feeds of the base (bases with a branch left)
    n_head = (moprp.head_displacements(sc).shape[0] - 1) * min(2, moprp.HEAD_FEED_SAMPLES)
    assert solver.stats["poses"] == 2 + n_head


@pytest.mark.slow
def test_drake_ik_on_the_scene_keeps_the_clearance():
    """--ik drake on the scenario's plant (MinimumDistanceLowerBoundConstraint at the scenario's
    clearance): every solution is clear in SceneGraph, and the branches that survive are the
    closed form's."""
    import dataclasses

    from implantplan.analyses.robot import drake_ik_solver
    from implantplan.diagrams.arm_clearance import SceneGraphClearance

    sc = dataclasses.replace(moprp.load_scenario("lying"), feed_samples=2)
    xyz = np.array([[0.6, -0.3, 0.0]])
    solver = drake_ik_solver(starts=64, seed=0, limits=sc.limits, X_FT=sc.X_FT, scenario=sc)
    ev_d = moprp.evaluate_bases(xyz, sc, np.random.default_rng(0), ik_solver=solver)
    ev_c = moprp.evaluate_bases(xyz, sc, np.random.default_rng(0))
    np.testing.assert_array_equal(ev_d.valid, ev_c.valid)
    assert solver.stats["min_distance_m"] == sc.clearance
    d = SceneGraphClearance(sc, xyz[0])(np.stack([ev_d.q[0], ev_d.q_pre[0]])).distance
    assert np.all(d >= sc.clearance - 1e-6)


def test_bench_agreement_new_model_safe_old_capsules_not():
    """The benchmark's SceneGraph comparison: the fast model has no false free; the old capsule
    model (reconstructed in the bench) calls SceneGraph collisions free."""
    from implantplan.analyses.bench_moprp import agreement

    res = agreement(n_bases=3, per_base=250, near_per_base=5, seed=3)
    assert res[("fast model", "random")].samples == 1500
    assert res[("fast model", "random")].false_free == 0
    assert res[("fast model", "near")].false_free == 0
    assert res[("old capsules", "random")].false_free > 0


def test_confirmation_drops_a_colliding_candidate_and_takes_the_next():
    """A front member whose reported configuration collides in SceneGraph is dropped, and the
    selection falls to the next-ranked member whose whole feed is clear."""
    from implantplan.analyses.robot import confirm_front
    from implantplan.diagrams import plant as scene

    sc = moprp.load_scenario("lying")
    X = np.array([scene.DEFAULT_BASE_XYZ["lying"], scene.DEFAULT_BASE_XYZ["lying"]])
    X[1, 2] += 0.01
    ev = moprp.evaluate_bases(X, sc, np.random.default_rng(0))
    assert ev.feasible.all()
    ev.q[0] = np.deg2rad([0, 0, 170, 0, 0, 0])  # elbow folded onto the upper arm
    conf = confirm_front(sc, X, ev, [0, 1])
    assert not conf["members_ok"][0] and conf["members_ok"][1]
    assert conf["clearance"][0] < 0 and conf["selection_dropped"] == [0]
    assert conf["selected"] == 1 and conf["feed"]["ok"]


@pytest.mark.sweep
def test_the_base_is_the_same_with_another_blas_kernel(tmp_path):
    """The search's result does not depend on the machine's BLAS: OpenBLAS's generic SSE3 kernel
    (OPENBLAS_CORETYPE=Prescott) changes the indices' last bits, and before the indices were
    rounded the wrist-flip ties and re-evaluated bases took another path (another base, 41
    instead of 60 generations)."""
    import os
    import subprocess
    import sys

    runs = {}
    procs = {}
    for name, kernel in (("default", None), ("prescott", "Prescott")):
        env = dict(os.environ)
        env.pop("OPENBLAS_CORETYPE", None)
        if kernel:
            env["OPENBLAS_CORETYPE"] = kernel
        procs[name] = subprocess.Popen(
            [sys.executable, "-m", "implantplan.analyses.cli", "robot", "place", "--scenario",
             "lying", "--pop", "100", "--gen", "60", "--percentile-samples", "60", "--quiet",
             "--out", str(tmp_path / name)], env=env, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT)
    for name, proc in procs.items():
        printed, _ = proc.communicate(timeout=600)
        assert proc.returncode == 0, printed.decode()
        runs[name] = read_json(tmp_path / name / "placement.json", kind="robot_placement")
    a, b = runs["default"], runs["prescott"]
    assert a["generations"] == b["generations"]
    assert a["selected"]["base_xyz"] == b["selected"]["base_xyz"]
    assert [e["base_xyz"] for e in a["pareto"]] == [e["base_xyz"] for e in b["pareto"]]
