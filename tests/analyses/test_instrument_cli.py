"""``implantplan instrument place`` end to end: JSON contents, exit codes, plots, a real mesh."""

import json

import numpy as np
import pytest

from implantplan.analyses.cli import main
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.placement.fixture import VirtualFixture

ORAL = "models/oral/oralCavityMesh.obj"


@pytest.fixture(scope="module")
def cyl_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("cyl") / "fpsm.json"
    Fpsm.cylinder(0.05, 0.0, 0.1, 11).save(path)
    return path


def place(fpsm, out, *extra, hole=("0", "-50", "50"), axis=("0", "1", "0")):
    return main(
        [
            "instrument",
            "place",
            "--fpsm",
            str(fpsm),
            "--hole-mm",
            *hole,
            "--hole-axis",
            *axis,
            "--rod-radius-mm",
            "6",
            "--implant-length-mm",
            "31",
            "--quiet",
            "--out",
            str(out),
            *extra,
        ]
    )


def test_cylinder_case_writes_the_plan(cyl_file, tmp_path, capsys):
    out = tmp_path / "p.json"
    assert place(cyl_file, out, "--seed", "1", "--plots", str(tmp_path / "plots")) == 0
    data = json.loads(out.read_text())
    assert data["schema_version"] == 1 and data["kind"] == "placement"
    # hand-derived in tests/test_placement.py: rod radius 6 mm -> d_T = 62.5 mm, theta_T = 0
    assert data["d_T"] == pytest.approx(0.0625, abs=1e-5)
    assert data["theta_T"] == pytest.approx(0.0, abs=1e-3)
    # to 10 um: the PSO compares F rounded (seeds.rounded), F is flat to second order here
    assert data["f_safe_line1"] == pytest.approx(0.0315, abs=1e-5)
    assert data["f_safe_line2"] == pytest.approx(0.0315, abs=1e-5)
    assert data["valid"] is True
    for key in ("F_safe", "iterations", "evaluations", "seconds", "history", "X_CT", "seed"):
        assert key in data
    assert data["seed"] == 1
    X_CT = np.array(data["X_CT"])
    np.testing.assert_allclose(X_CT[:3, 3], [0, 0.0125, 0.05], atol=1e-5)
    grid = data["grid_check"]
    assert grid["distance_d_T"] <= 1e-4 and grid["distance_theta_T"] <= np.deg2rad(0.1)
    vf = VirtualFixture.from_dict(data["vf"])
    assert vf.cylinder_radius == pytest.approx(0.006)
    assert data["summary"]["d_T_mm"] == pytest.approx(62.5, abs=0.01)
    assert "d_T_mm" in capsys.readouterr().out
    for name in ("contour_global.png", "contour_magnified.png", "convergence.png", "views.png"):
        assert (tmp_path / "plots" / name).stat().st_size > 10_000


def test_objective_and_seed_options(cyl_file, tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    assert place(cyl_file, a, "--objective", "eq22", "--seed", "4") == 0
    assert place(cyl_file, b, "--objective", "eq22", "--seed", "4") == 0
    da, db = json.loads(a.read_text()), json.loads(b.read_text())
    assert da["objective"] == "eq22" and da["d_T"] == db["d_T"]
    assert da["grid_check"]["d_T"] == pytest.approx(0.081, abs=1e-5)  # hand-derived optimum


def test_planning_failure_exits_3_after_writing(tmp_path):
    tube = tmp_path / "tube.json"
    Fpsm.cylinder(0.005, 0.0, 0.1, 11).save(tube)  # 5 mm tube, 6 mm rod
    out = tmp_path / "p.json"
    assert place(tube, out, hole=("0", "-5", "50")) == 3
    data = json.loads(out.read_text())
    assert data["valid"] is False and "line1" in data["reason"]


@pytest.mark.parametrize(
    "args, kw, message",
    [
        ((), {"hole": ("0", "-50", "150")}, "outside the model's slices"),
        ((), {"hole": ("0", "-80", "50")}, "outside the model"),
        ((), {"hole": ("0", "nan", "50")}, "--hole-mm"),
        ((), {"axis": ("0", "0", "0")}, "hole_axis"),
        (("--d-t-range-mm", "90", "40"), {}, "--d-t-range-mm"),
        (("--hole-tolerance-mm", "-1"), {}, "--hole-tolerance-mm"),
    ],
)
def test_bad_input_exits_2(cyl_file, tmp_path, capsys, args, kw, message):
    out = tmp_path / "p.json"
    assert place(cyl_file, out, *args, **kw) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_missing_or_wrong_fpsm_file(tmp_path, capsys):
    assert place(tmp_path / "none.json", tmp_path / "p.json") == 2
    assert "--fpsm" in capsys.readouterr().err
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps({"schema_version": 1, "kind": "placement"}))
    assert place(wrong, tmp_path / "p.json") == 2


def test_real_oral_mesh_end_to_end(tmp_path):
    # Fit the bundled oral cavity (ArtiSynth), then place a 2 mm rod with a 10 mm implant at a
    # site on the cavity wall (theta 180 deg, z 60 mm in Center), axis into the cavity and
    # tilted towards the opening. The mouth opening of this scan is only 3-11 mm in radius:
    # the paper's tool (6 mm rod, 31 mm implant) has no safe placement at this site (exit 3).
    fpsm_path = tmp_path / "oral.json"
    code = main(
        [
            "fpsm", "fit", ORAL, "--units", "mm", "--center-origin-mm", "140", "0", "100",
            "--center-z", "-1", "0", "0", "--center-x-hint", "0", "-1", "0", "--slices", "15",
            "--control-points", "15", "--samples", "150", "--close-open-cuts",
            "--check-factor", "0", "--quiet", "--out", str(fpsm_path),
        ]
    )  # fmt: skip
    assert code == 0
    fpsm = Fpsm.load(fpsm_path)
    r = float(fpsm.radius_at(np.pi, 0.06))
    hole = [f"{-r * 1e3:.6f}", "0", "60"]
    out = tmp_path / "p.json"
    args = ["instrument", "place", "--fpsm", str(fpsm_path), "--hole-mm", *hole,
            "--hole-axis", "1", "0", "0.3", "--quiet"]  # fmt: skip
    tool = ["--rod-radius-mm", "2", "--implant-length-mm", "10"]
    # the certified clearance of that tool over the feed and the fixture's region is only
    # about 0.1 mm here: below the default 1 mm clinical margin, a planning failure
    assert main([*args, *tool, "--out", str(out)]) == 3
    tool += ["--clearance-margin-mm", "0"]
    assert main([*args, *tool, "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["valid"] and data["f_safe_line1"] > 0 and data["f_safe_line2"] > 0
    assert data["grid_check"]["distance_d_T"] <= 1e-4
    assert data["grid_check"]["distance_theta_T"] <= np.deg2rad(0.1)
    # the feeding target is inside the cavity and the rod really is collision-free:
    # its points sampled densely from the start up to the top slice all have d_safe > 0
    line1 = data["line1"]
    start, u = np.array(line1["start"]), np.array(line1["direction"])
    s = np.linspace(0, (fpsm.z_range[1] - start[2]) / u[2], 400)
    assert np.all(fpsm.d_safe(start + s[:, None] * u, radius=0.002) > -1e-4)
    # the plots find the fit's mesh and put it in Center, whatever units the settings claim
    from implantplan.analyses.figures.placement import mesh_in_center

    v, _ = mesh_in_center(fpsm)
    d = fpsm.to_dict()
    d["settings"]["mesh_units"] = "m"  # wrong: the file is in mm
    np.testing.assert_array_equal(mesh_in_center(Fpsm.from_dict(d))[0], v)
    # the open cavity surrounds the slices: ~all slice-curve points are inside the mesh's box
    assert np.all(v.min(axis=0)[:2] < -0.02) and np.all(v.max(axis=0)[:2] > 0.02)
    paper_tool = ["--rod-radius-mm", "6", "--implant-length-mm", "31"]
    assert main([*args, *paper_tool, "--out", str(tmp_path / "q.json")]) == 3
    data = json.loads((tmp_path / "q.json").read_text())
    assert not data["valid"] and data["settings"]["pso_runs"] == 4  # 1 + 3 restarts


def test_bench_placement_runs_small(cyl_file, capsys):
    """The benchmark runs small (its timings are printed, never asserted); on its sample of the
    real cavity's rods the sound bound calls none safe that FCL says collide."""
    from implantplan.analyses.bench_placement import main as bench

    assert bench(["--fpsm", str(cyl_file), "--repeats", "1", "--rods", "500", "--loop-rods",
                  "20", "--sound-rods", "2000", "--fcl-rods", "500"]) == 0
    out = capsys.readouterr().out
    assert "cylinder (Sec. 5.3)" in out and "rods/s" in out
    assert out.count("True") >= 4  # both cases valid, both batches agree with numpy
    assert "2,000 rods" in out and "FCL on the first 500" in out
    assert "rods called safe by the sound bound that FCL says collide: 0 of 500" in out
