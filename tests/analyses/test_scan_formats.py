"""The default case from the scan saved in other scanner formats (issue: STL is what dental
scanners export). Text formats carry the OBJ's numbers exactly and plan identically; binary STL and
PLY store single precision (the vertices move by up to 7.6e-6 mm), which the FPSM fit and the
placements follow to within 1e-8 m, while the NSGA-II base search may pick another member of its
flat Pareto front (any bit of difference changes a GA's trajectory)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
import yaml

from implantplan import models
from implantplan.analyses.cli import main
from implantplan.analyses.provenance import without_volatile
from tests.analyses.cases import default_case_data
from tests.conftest import SMALL_PLAN_FLAGS

FAST = ["--runs", "0", "--no-figures", "--quiet"]


def _read(out) -> dict:
    plan = without_volatile(json.loads((out / "plan.json").read_text()))
    plan.pop("case")  # names the case file
    return plan


def _plan(tmp_path, name, file_type=None, scale=1.0, case=None, flags=FAST):
    """``case`` (default: the default case, tests.analyses.cases) planned with ``flags`` from the
    scan saved as ``file_type`` (None: the bundled OBJ): plan.json without its volatile parts."""
    case = default_case_data() if case is None else case
    source = models.model_path("oral/oralCavityMesh.obj")
    if file_type is not None:
        mesh = trimesh.load(source, process=False, force="mesh")
        mesh.apply_scale(scale)
        path = tmp_path / f"{name}.{'stl' if file_type.startswith('stl') else file_type}"
        mesh.export(path, file_type=file_type)
        case["mesh"]["path"] = str(path)
        case["mesh"]["units"] = "mm" if scale == 1.0 else "m"
    case_path = tmp_path / f"{name}.yaml"
    case_path.write_text(yaml.safe_dump(case))
    out = tmp_path / f"out_{name}"
    assert main(["plan", str(case_path), "--out", str(out), *flags]) == 0
    return _read(out)


def test_the_scan_as_ascii_stl_fits_exactly_like_the_obj(tmp_path):
    """The default run: the scan saved as ASCII STL opens to the OBJ's vertices and triangles
    and fits to its FPSM bit for bit (the whole plan from it: the sweep test below)."""
    from implantplan.analyses import pipeline
    from implantplan.analyses.case import case_from_dict

    path = tmp_path / "scan.stl"
    trimesh.load(models.model_path("oral/oralCavityMesh.obj"), process=False,
                 force="mesh").export(path, file_type="stl_ascii")
    fits = []
    for mesh_path in (None, path):
        data = default_case_data()
        if mesh_path is not None:
            data["mesh"]["path"] = str(mesh_path)
        fits.append(pipeline.fit_stage(case_from_dict(data, source=tmp_path / "case.yaml")))
    obj, stl = fits
    # STL is a triangle soup: the same vertices and triangles, in another order
    np.testing.assert_array_equal(np.unique(stl.opened.vertices, axis=0),
                                  np.unique(obj.opened.vertices, axis=0))
    tri = [np.unique(np.sort(f.vertices[f.faces].reshape(-1, 9), axis=1), axis=0)
           for f in (stl.opened, obj.opened)]
    np.testing.assert_array_equal(*tri)
    fpsm = []
    for fit in (stl, obj):
        d = fit.fpsm.to_dict()
        d["settings"].pop("mesh")  # the file it was read from
        d["diagnostics"] = {k: v for k, v in d["diagnostics"].items() if "seconds" not in k}
        fpsm.append(json.dumps(d))
    assert fpsm[0] == fpsm[1]


@pytest.mark.sweep
def test_the_scan_as_ascii_stl_plans_exactly_like_the_obj(tmp_path, small_plan):
    """The small case (its feeds included) from the ASCII STL against the run's shared plan of
    it from the OBJ (tests/conftest.py ``small_plan``), and the default case's own sizes."""
    case_path, obj_plan = small_plan
    case = yaml.safe_load(case_path.read_text())
    assert case["mesh"]["path"] == str(models.model_path("oral/oralCavityMesh.obj"))
    assert _plan(tmp_path, "ascii", "stl_ascii", case=case,
                 flags=SMALL_PLAN_FLAGS) == _read(obj_plan)
    assert _plan(tmp_path, "ascii_full", "stl_ascii") == _plan(tmp_path, "obj")


@pytest.mark.slow
@pytest.mark.parametrize("file_type, scale", [("stl", 1.0), ("ply", 1.0), ("stl", 1e-3),
                                              ("ply", 1e-3)])
def test_single_precision_formats_give_the_same_fpsm_and_placements(tmp_path, file_type, scale):
    ref = _plan(tmp_path, "obj")
    got = _plan(tmp_path, f"{file_type}_{scale:g}", file_type, scale)
    for a, b in zip(ref["sites"], got["sites"], strict=True):
        for key in ("d_T", "d_safe_min_line1", "d_safe_min_line2"):
            assert abs(a["placement"][key] - b["placement"][key]) < 1e-8, key
        assert abs(a["placement"]["theta_T"] - b["placement"]["theta_T"]) < 1e-6
        Xa, Xb = np.array(a["feeding_target"]["X_CT"]), np.array(b["feeding_target"]["X_CT"])
        np.testing.assert_allclose(Xa[:3, 3], Xb[:3, 3], rtol=0, atol=1e-8)  # m
        np.testing.assert_allclose(Xa[:3, :3], Xb[:3, :3], rtol=0, atol=1e-6)  # theta_T's 1e-6
    assert got["passed"] and [c["id"] for c in got["checks"]] == [c["id"] for c in ref["checks"]]
