"""``implantplan capmap``: build / query / accuracy / plan through the CLI, exit codes."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from implantplan.analyses.cli import main
from implantplan.systems.capability import maps as cm
from implantplan.systems.files import read_json
from implantplan.systems.frames import rot_z, transform

CASES = str(Path(__file__).resolve().parents[2] / "models" / "capmap_cases")


@pytest.fixture(scope="module")
def map_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("maps") / "m.h5"
    # centre-sampled: a certified map this coarse certifies too little for the plan's 6 tasks
    code = main(["capmap", "build", "--voxel-mm", "100", "--directions", "40", "--workers", "1",
                 "--cell", "centre", "--out", str(path)])  # fmt: skip
    assert code == 0
    return path


def test_build_writes_a_loadable_map(map_path, capsys):
    m = cm.load(map_path, expect={"voxel": 0.1, "directions": 40, "limits": "175"})
    assert m.params.tool == "flange" and len(m.voxel_ids) > 0 and m.params.cell == "centre"


def test_build_with_self_collision_and_actuator(tmp_path):
    pytest.importorskip("implantplan.diagrams.actuator_urdf")
    path = tmp_path / "a.h5"
    code = main(["capmap", "build", "--voxel-mm", "300", "--directions", "6", "--workers", "1",
                 "--tool", "actuator", "--rolls", "4", "--self-collision",
                 "--out", str(path)])  # fmt: skip
    assert code == 0
    m = cm.load(path, expect={"tool": "actuator", "self_collision": True, "rolls": 4})
    assert m.params.cell == "certified"  # the default
    # the mapped frame is the implant tip, z along the implant axis (flange -y)
    np.testing.assert_allclose(m.params.X_FT_matrix()[:3, 2], [0.0, -1.0, 0.0], atol=1e-12)


def test_query_json(map_path, tmp_path):
    m = cm.load(map_path)
    row = int(np.argmax(m.index))  # the best certified voxel and one of its reachable directions
    d = int(np.flatnonzero(m.reach_rows([row])[0])[0])
    pose = transform(cm.frames_from_z(m.directions[d]) @ rot_z(0.7), m.centres()[row])
    poses = np.stack([pose, transform(np.eye(3), [4.0, 0.0, 0.0])])
    np.save(tmp_path / "p.npy", poses)
    code = main(["capmap", "query", str(map_path), "--poses", str(tmp_path / "p.npy"),
                 "--out", str(tmp_path / "q.json")])  # fmt: skip
    assert code == 0
    q = read_json(tmp_path / "q.json", kind="capmap_query")
    assert q["reachable"] == [True, False]
    assert q["index"] == [m.index[row], 0.0] and m.index[row] > 0
    # a centre map certifies nothing: the first answer is IK's, the second outside the reach
    assert q["answer"] == ["resolved by IK", "certified unreachable"]
    assert q["answers"] == {"certified reachable": 0, "certified unreachable": 1,
                            "resolved by IK": 1}
    assert q["index_map"] == "centre-sampled index (seed 004) of the centre map: flange, 100 mm " \
        "voxels, 40 directions x 1 roll(s), +-175 deg"


def test_query_answers_agree_with_exact_ik_and_say_where_they_came_from(tmp_path, capsys):
    """A certified map through the CLI: every answer is exact IK's, certified cells among them."""
    path = tmp_path / "c.h5"
    assert main(["capmap", "build", "--voxel-mm", "100", "--directions", "30", "--workers", "1",
                 "--out", str(path)]) == 0  # fmt: skip
    X = cm.random_poses(3000, seed=17, radius=1.8)
    np.save(tmp_path / "p.npy", X)
    capsys.readouterr()
    assert main(["capmap", "query", str(path), "--poses", str(tmp_path / "p.npy"),
                 "--out", str(tmp_path / "q.json")]) == 0  # fmt: skip
    line = json.loads(capsys.readouterr().out)
    q = read_json(tmp_path / "q.json", kind="capmap_query")
    exact = cm.exact_reachable(cm.load(path).params, X)
    assert q["reachable"] == exact.tolist()
    assert line["reachable"] == int(exact.sum()) and line["poses"] == 3000
    assert all(q["answers"][k] > 0 for k in q["answers"])
    ans = np.array(q["answer"])
    assert np.all(exact[ans == "certified reachable"]) and not np.any(
        exact[ans == "certified unreachable"])


def test_query_bad_input_exit_2(map_path, tmp_path):
    np.save(tmp_path / "bad.npy", np.zeros((3, 3)))
    args = ["capmap", "query", str(map_path), "--poses", str(tmp_path / "bad.npy"), "--out",
            str(tmp_path / "q.json")]  # fmt: skip
    assert main(args) == 2
    assert (
        main(["capmap", "query", str(tmp_path / "none.h5"), "--poses", "x.npy", "--out", "q"]) == 2
    )
    assert main(["capmap", "build", "--voxel-mm", "0", "--out", str(tmp_path / "x.h5")]) == 2


def test_show_writes_png(map_path, tmp_path):
    png = tmp_path / "s.png"
    assert main(["capmap", "show", str(map_path), "--png", str(png), "--slices", "3"]) == 0
    assert png.stat().st_size > 10_000
    assert main(["capmap", "show", str(map_path), "--png", str(png), "--slices", "0"]) == 2


def test_accuracy_command(map_path, capsys):
    assert main(["capmap", "accuracy", str(map_path), "--samples", "3000", "--seed", "4"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    acc = out["exact_roll"]
    assert acc["TP"] + acc["FP"] + acc["FN"] + acc["TN"] == pytest.approx(1.0)


def test_plan_pedicle_case(map_path, tmp_path, capsys):
    args = ["capmap", "plan", "--patient", f"{CASES}/pedicle_patient.yaml",
            "--task", f"{CASES}/pedicle_task.yaml", "--robot", f"{CASES}/pedicle_robot.yaml",
            "--out", str(tmp_path / "plan"), "--map", str(map_path),
            "--store", str(tmp_path / "store")]  # fmt: skip
    assert main(args) == 0
    plan = read_json(tmp_path / "plan" / "plan.json", kind="capmap_plan")
    assert plan["candidates"] == 800 and plan["method"] == "exhaustive"
    assert 0.0 < plan["best"]["cost"] <= 1.0
    assert plan["best"]["all_task_poses_reachable"]
    # the final check is exact IK at each task pose, independent of the map
    assert plan["exact_check"]["pass"] and plan["exact_check"]["poses"] == 6
    ref = cm.exact_reachable(cm.load(map_path).params, np.asarray(plan["task_poses_in_best_base"]))
    assert ref.all()
    assert plan["worst"]["cost"] <= plan["best"]["cost"]
    assert (tmp_path / "plan" / "best_vs_worst.png").stat().st_size > 10_000
    assert (tmp_path / "plan" / "cmap_slices.png").stat().st_size > 10_000


def test_plan_unreachable_exit_3_and_missing_map_exit_2(map_path, tmp_path):
    robot = {"robot": {"name": "aubo_i10", "map": str(map_path),
                       "base_ranges": [{"x": [5.0, 5.1], "y": 0.0}]}}  # fmt: skip
    (tmp_path / "far.yaml").write_text(yaml.safe_dump(robot))
    args = ["capmap", "plan", "--patient", f"{CASES}/pedicle_patient.yaml",
            "--task", f"{CASES}/pedicle_task.yaml", "--robot", str(tmp_path / "far.yaml"),
            "--out", str(tmp_path / "plan")]  # fmt: skip
    assert main(args) == 3
    robot["robot"]["map"] = "missing.h5"
    (tmp_path / "nomap.yaml").write_text(yaml.safe_dump(robot))
    args[args.index("--robot") + 1] = str(tmp_path / "nomap.yaml")
    assert main(args) == 2


def test_robot_build_block_takes_the_cell(tmp_path):
    robot = yaml.safe_load(Path(f"{CASES}/pedicle_robot.yaml").read_text())
    robot["robot"]["map"] = str(tmp_path / "built.h5")
    robot["robot"]["build"] = {"voxel_mm": 200, "directions": 12, "cell": "centre",
                               "workers": 1}  # fmt: skip
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(robot))
    args = ["capmap", "plan", "--patient", f"{CASES}/pedicle_patient.yaml",
            "--task", f"{CASES}/pedicle_task.yaml", "--robot", str(tmp_path / "r.yaml"),
            "--out", str(tmp_path / "plan")]  # fmt: skip
    assert main(args) in (0, 3)
    assert cm.load(tmp_path / "built.h5").params.cell == "centre"
