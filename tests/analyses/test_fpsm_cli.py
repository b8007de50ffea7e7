"""``implantplan fpsm fit|cylinder`` through analyses.cli.main: files, exit codes, messages."""

from __future__ import annotations

import json

import numpy as np
import pytest

from implantplan.analyses.cli import main
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.fpsm.oral_mesh import DEFAULT_CAVITY, procedural_oral_cavity


@pytest.fixture(scope="module")
def cavity_stl_mm(tmp_path_factory):
    """The procedural cavity written in mm as STL, axis along mesh z from 0 to 80 mm."""
    cavity = procedural_oral_cavity(noise=0.02, seed=3, angular_resolution=64, axial_resolution=24)
    mesh = cavity.mesh.copy()
    mesh.apply_scale(1000.0)
    path = tmp_path_factory.mktemp("mesh") / "cavity.stl"
    mesh.export(path)
    return path


def test_cylinder_command_writes_the_model(tmp_path, capsys):
    out = tmp_path / "cyl.json"
    code = main(
        [
            "fpsm",
            "cylinder",
            "--radius-mm",
            "50",
            "--z-min-mm",
            "0",
            "--z-max-mm",
            "100",
            "--slices",
            "11",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    f = Fpsm.load(out)
    assert f.rho.shape == (11, 16)
    assert np.allclose(f.rho, 0.05) and np.allclose(f.slice_z, np.linspace(0, 0.1, 11))
    assert json.loads(out.read_text())["schema_version"] == 1
    assert "cylinder radius 50.0 mm" in capsys.readouterr().out


def test_cylinder_command_rejects_a_bad_radius(tmp_path, capsys):
    code = main(
        [
            "fpsm",
            "cylinder",
            "--radius-mm",
            "-5",
            "--z-min-mm",
            "0",
            "--z-max-mm",
            "100",
            "--slices",
            "11",
            "--out",
            str(tmp_path / "c.json"),
        ]
    )
    assert code == 2
    assert "radius" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()


def test_fit_command_on_a_procedural_mesh_in_mm(tmp_path, cavity_stl_mm, capsys):
    out = tmp_path / "fpsm.json"
    code = main(
        [
            "fpsm",
            "fit",
            str(cavity_stl_mm),
            "--units",
            "mm",
            "--center-origin-mm",
            "0",
            "0",
            "40",
            "--center-z",
            "0",
            "0",
            "1",
            "--slices",
            "6",
            "--control-points",
            "10",
            "--samples",
            "60",
            "--margin-mm",
            "0.5",
            "--check-factor",
            "2",
            "--quiet",
            "--plots",
            str(tmp_path / "plots"),
            "--out",
            str(out),
        ]
    )
    assert code == 0
    f = Fpsm.load(out)
    assert f.rho.shape == (6, 10)
    assert f.settings["margin_m"] == pytest.approx(5e-4)
    assert f.settings["method"] == "exact"
    # axis inside from z = -40 to +40 mm around the origin; slices inset by half a spacing
    h = 0.08 / 6
    assert f.slice_z[0] == pytest.approx(-0.04 + h / 2, abs=1e-6)
    assert f.slice_z[-1] == pytest.approx(0.04 - h / 2, abs=1e-6)
    assert f.diagnostics["penetrating_samples"] == [0] * 6
    text = capsys.readouterr().out
    assert "coverage_%" in text and "dense check" in text
    assert (tmp_path / "plots" / "fpsm_slices.png").stat().st_size > 1000
    assert (tmp_path / "plots" / "fpsm_coverage.png").stat().st_size > 1000


def test_fit_paper_method_and_explicit_range(tmp_path, cavity_stl_mm):
    out = tmp_path / "paper.json"
    code = main(
        [
            "fpsm",
            "fit",
            str(cavity_stl_mm),
            "--center-origin-mm",
            "0",
            "0",
            "0",
            "--center-z",
            "0",
            "0",
            "1",
            "--slices",
            "3",
            "--control-points",
            "8",
            "--samples",
            "48",
            "--z-range-mm",
            "20",
            "60",
            "--method",
            "paper",
            "--check-factor",
            "0",
            "--quiet",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    f = Fpsm.load(out)
    assert np.allclose(f.slice_z, [0.02, 0.04, 0.06])
    assert f.settings["paper"]["alpha_mm"] == 0.1


def test_real_mesh_open_cut_is_exit_2_naming_the_fix(tmp_path, capsys):
    o = DEFAULT_CAVITY["center_origin_mm"]
    args = [
        "fpsm",
        "fit",
        str(DEFAULT_CAVITY["path"]),
        "--units",
        "mm",
        "--center-origin-mm",
        *map(str, o),
        "--center-z",
        "-1",
        "0",
        "0",
        "--center-x-hint",
        "0",
        "-1",
        "0",
        "--check-factor",
        "0",
        "--quiet",
    ]
    code = main([*args, "--z-range-mm", "5", "80", "--out", str(tmp_path / "a.json")])
    assert code == 2
    err = capsys.readouterr().err
    assert "meet no wall" in err and "--cap-radius-mm" in err and "Traceback" not in err
    code = main([*args, "--close-open-cuts", "--out", str(tmp_path / "b.json")])
    assert code == 0
    assert Fpsm.load(tmp_path / "b.json").diagnostics["rays_without_wall"] == 0


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--center-z", "0", "0", "0"], "center_z"),
        (["--center-z", "0", "0", "1", "--samples", "4"], "samples"),
        (["--center-z", "0", "0", "1", "--margin-mm", "-1"], "margin"),
        (["--center-z", "0", "0", "1", "--cap-radius-mm", "nan"], "cap-radius"),
    ],
)
def test_bad_fit_arguments_are_exit_2(tmp_path, cavity_stl_mm, capsys, extra, needle):
    code = main(
        ["fpsm", "fit", str(cavity_stl_mm), *"--center-origin-mm 0 0 40".split(), *extra,
         "--quiet", "--out", str(tmp_path / "x.json")]
    )
    assert code == 2
    assert needle in capsys.readouterr().err


def test_bad_mesh_files_are_exit_2(tmp_path, capsys):
    missing = tmp_path / "missing.stl"
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    for path, needle in ((missing, "does not exist"), (nan, "NaN")):
        code = main(["fpsm", "fit", str(path), *"--center-origin-mm 0 0 0 --center-z 0 0 1".split(),
                     "--quiet", "--out", str(tmp_path / "x.json")])
        assert code == 2
        assert needle in capsys.readouterr().err
