"""``implantplan phantom`` and a CBCT case end to end: the phantom of the default case, read back
through the case's ``mesh.path``, fits the FPSM as the mesh case does and keeps the sites on the
tissue (a coarse phantom by default); under ``sweep`` the 0.4 mm phantom plans like the mesh case
(curves, valid sites, feeding targets within 1 mm / 1 deg, every check passing, plan.dcm)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from implantplan.analyses import pipeline
from implantplan.analyses.case import case_from_dict, default_case_path, load_case
from implantplan.analyses.checks import anatomy_checks
from implantplan.analyses.cli import main
from implantplan.analyses.out_folder import MARKER
from implantplan.analyses.phantom import make_phantom_folder
from implantplan.systems.anatomy.dicom_plan import read_dicom_plan
from implantplan.systems.errors import InputError
from implantplan.systems.frames import apply

COARSE_MM = 1.5


def curve_distance(a, b, *, angles: int = 720) -> np.ndarray:
    """Per slice, the Hausdorff distance (m) between two FPSMs' closed curves (same slices)."""
    th = np.linspace(0, 2 * np.pi, angles, endpoint=False)
    out = []
    for z in a.slice_z:
        pa, pb = ([f.radius_at(th, np.full_like(th, z)) * np.cos(th),
                   f.radius_at(th, np.full_like(th, z)) * np.sin(th)] for f in (a, b))
        A, B = np.column_stack(pa), np.column_stack(pb)
        out.append(max(cKDTree(B).query(A)[0].max(), cKDTree(A).query(B)[0].max()))
    return np.array(out)


@pytest.fixture(scope="module")
def mesh_fit():
    case = load_case(default_case_path())
    return case, pipeline.fit_stage(case)


@pytest.fixture(scope="module")
def coarse(tmp_path_factory):
    out = tmp_path_factory.mktemp("phantom") / "default"
    info = make_phantom_folder(default_case_path(), out, voxel_mm=COARSE_MM, noise_hu=20.0,
                               seed=None, force=False)
    return out, info


def test_phantom_folder(coarse):
    out, info = coarse
    assert (out / MARKER).exists() and info["canals"] == 2
    assert len(list((out / "ct").glob("*.dcm"))) == info["slices"] == info["shape_kji"][0]
    case = load_case(out / "case.yaml")
    assert case.mesh.path == (out / "ct").resolve() or case.mesh.path == out / "ct"


def test_coarse_phantom_fits_like_the_mesh_case(coarse, mesh_fit):
    out, _ = coarse
    case, fit_m = mesh_fit
    cbct_case = load_case(out / "case.yaml")
    fit_c = pipeline.fit_stage(cbct_case)
    assert fit_c.cbct is not None and fit_c.cbct.info["patient_id"] == "PHANTOM-default"
    np.testing.assert_allclose(fit_c.fpsm.slice_z, fit_m.fpsm.slice_z)
    d = curve_distance(fit_m.fpsm, fit_c.fpsm)
    assert d.max() < 2.5 * COARSE_MM * 1e-3  # coarse voxels (0.4 mm: 0.5 mm, the sweep below)
    check = pipeline.site_stage(cbct_case, fit_c)
    assert np.all(check.distance < 0.5 * COARSE_MM * 1e-3) and np.all(check.axis_into_cavity)


def test_phantom_refuses_a_folder_it_does_not_own(tmp_path):
    (tmp_path / "mine.txt").write_text("user data")
    with pytest.raises(InputError, match="--out.*implantplan did not write"):
        make_phantom_folder(default_case_path(), tmp_path, voxel_mm=2.0, noise_hu=20.0,
                            seed=None, force=False)
    assert (tmp_path / "mine.txt").read_text() == "user data"
    with pytest.raises(InputError, match="--voxel-mm"):
        make_phantom_folder(default_case_path(), tmp_path / "new", voxel_mm=0.05, noise_hu=20.0,
                            seed=None, force=False)


def test_a_bad_series_in_a_case_exits_2_naming_the_file(coarse, tmp_path, capsys):
    out, _ = coarse
    bad = tmp_path / "ct"
    bad.mkdir()
    for p in sorted((out / "ct").iterdir())[:5]:
        (bad / p.name).write_bytes(p.read_bytes())
    (bad / "readme.txt").write_text("not an image")
    (tmp_path / "canals.yaml").write_bytes((out / "canals.yaml").read_bytes())
    text = (out / "case.yaml").read_text().replace("path: ct", f"path: {bad}")
    (tmp_path / "case.yaml").write_text(text)
    code = main(["plan", str(tmp_path / "case.yaml"), "--out", str(tmp_path / "plan"),
                 "--no-figures", "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "mesh.path" in err and "readme.txt: not a DICOM file" in err


@pytest.mark.sweep
def test_the_04mm_phantom_plans_like_the_mesh_case(tmp_path, mesh_fit):
    from implantplan.analyses.plan import plan_case

    out = tmp_path / "phantom"
    make_phantom_folder(default_case_path(), out, voxel_mm=0.4, noise_hu=20.0, seed=None,
                        force=False)
    case_m, fit_m = mesh_fit
    case_c = load_case(out / "case.yaml")
    fit_c = pipeline.fit_stage(case_c)
    d = curve_distance(fit_m.fpsm, fit_c.fpsm)
    assert d.max() < 0.5e-3, d  # the bound (measured 0.48 mm at 0.4 mm voxels)
    plans = [plan_case(c, tmp_path / n, runs=0, html_scene=False, quiet=True, figures=False)
             for c, n in ((case_m, "mesh"), (case_c, "cbct"))]
    for pm, pc in zip(plans[0]["sites"], plans[1]["sites"], strict=True):
        assert pm["placement"]["valid"] and pc["placement"]["valid"]
        Xm = np.array(pm["feeding_target"]["X_CT"])
        Xc = np.array(pc["feeding_target"]["X_CT"])
        assert np.linalg.norm(Xm[:3, 3] - Xc[:3, 3]) < 1e-3
        cos = np.clip((np.trace(Xm[:3, :3].T @ Xc[:3, :3]) - 1) / 2, -1, 1)
        assert np.degrees(np.arccos(cos)) < 1.0
    assert plans[1]["passed"] and all(c["pass"] for c in plans[1]["checks"])
    assert plans[1]["scan"]["kind"] == "cbct"
    back = read_dicom_plan(tmp_path / "cbct" / "plan.dcm")
    X_WC = fit_c.fpsm.X_WC
    for b, s in zip(back, case_c.sites, strict=True):
        np.testing.assert_allclose(b["entry"], apply(X_WC, s.position), atol=1e-6)
    assert json.loads((tmp_path / "cbct" / "plan.json").read_text())["dicom"]["sr"] == "plan.dcm"


def test_coarse_phantom_anatomy_checks_pass_with_their_values(coarse):
    out, _ = coarse
    case = load_case(out / "case.yaml")
    assert len(case.anatomy.canals) == 2  # canals.yaml, from the case written beside it
    fit = pipeline.fit_stage(case)
    anatomy = pipeline.anatomy_stage(case, fit)
    checks = {(c["id"], c["site"]): c for c in anatomy_checks(anatomy)}
    assert set(checks) == {(i, s) for i in ("anatomy.canal_distance",
                                            "anatomy.adjacent_tooth_distance",
                                            "anatomy.inter_implant_distance",
                                            "anatomy.bone_around_implant")
                           for s in ("36", "46")}
    # the bone around the implant is bounded conservatively by about two voxels (2 mm at 1.5 mm
    # voxels: measured 0.2 / -0.55 mm of the ridge's 2.5 mm); the 0.4 mm phantom passes it
    # (1.85 mm at both sites: the sweep test below plans it with every check passing)
    assert all(c["pass"] for (i, _), c in checks.items() if i != "anatomy.bone_around_implant")
    for s in ("36", "46"):
        bone = checks[("anatomy.bone_around_implant", s)]
        assert bone["limit"] == 1e-3 and -1.0e-3 < bone["value"] <= 2.5e-3
    # the phantom's canal runs 5 mm under the apex: r 1.2 mm, a 15 deg tilted implant r 2 mm
    assert 2.5e-3 < checks[("anatomy.canal_distance", "36")]["value"] < 3.8e-3


@pytest.mark.parametrize(("gap_mm", "passes"), [(1.5, False), (2.5, True)])
def test_a_case_canal_1_5_mm_from_the_implant_fails_and_2_5_passes(mesh_fit, gap_mm, passes):
    """A canal (case key) under site 36's planned implant, ``gap_mm`` below its apex's flat
    end along the implant's axis, crossing it at right angles."""
    case, fit = mesh_fit
    entry, apex = pipeline.planned_implants(case, fit.fpsm.X_WC, scanned=True)
    axis = (entry[0] - apex[0]) / np.linalg.norm(entry[0] - apex[0])
    across = np.cross(axis, [1.0, 0, 0])
    across /= np.linalg.norm(across)
    centre = apex[0] - (gap_mm + 1.2) * 1e-3 * axis
    line = [(centre + s * 15e-3 * across) * 1e3 for s in (-1, 0, 1)]
    data = {**_raw_default(), "anatomy": {"canals": [
        {"polyline_mm": [p.tolist() for p in line], "radius_mm": 1.2}]}}
    with_canal = case_from_dict(data, source=default_case_path())
    anatomy = pipeline.anatomy_stage(with_canal, fit)
    (c,) = [c for c in anatomy_checks(anatomy)
            if c["id"] == "anatomy.canal_distance" and c["site"] == "36"]
    assert c["pass"] is passes
    assert c["value"] == pytest.approx(gap_mm * 1e-3, abs=1e-6)
    assert c["limit"] == 2e-3 and c["bound"] == "min"


def _raw_default() -> dict:
    from implantplan.systems.files import read_yaml

    return read_yaml(default_case_path(), field="case")
