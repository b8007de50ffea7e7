"""A geometry refusal tries larger mouth openings: the site is carried with the jaw
(pipeline.site_at_opening), checked by hand against the hinge rotation, and the probe's answer
(pipeline.opening_needed) is the first opening that plans."""

import dataclasses

import numpy as np
import pytest

from implantplan.analyses import pipeline
from implantplan.analyses.case import case_from_dict, default_case_path, load_case
from implantplan.systems.anatomy import distances as anatomy
from implantplan.systems.errors import PlanningFailure
from implantplan.systems.files import read_yaml


@pytest.fixture(scope="module")
def case():
    return load_case(default_case_path())


def _mesh_frame(case):
    X = pipeline.center_frame(case.center.origin, case.center.z_axis, x_hint=case.center.x_hint)
    return X[:3, :3], X[:3, 3]


def test_the_same_opening_leaves_the_site_where_it_is(case):
    for site in case.sites:
        moved = pipeline.site_at_opening(case, site, case.mesh.mouth_opening_deg)
        np.testing.assert_allclose(moved.position, site.position, atol=1e-9)
        np.testing.assert_allclose(moved.axis, site.axis, atol=1e-9)


def test_a_site_below_the_occlusal_band_turns_rigidly_about_the_hinge(case):
    """A site deep on the lower jaw (mesh z 45 mm, far below the occlusal band at z 90-110 mm)
    turns rigidly: 25 -> 35 deg is a turn of 10 deg about the hinge line through
    (150, 0, 120) mm along -y; by the right-hand rule about -y a point at (x, z) relative to the
    hinge goes to (x cos a - z sin a, z cos a + x sin a), a direction likewise."""
    R, t = _mesh_frame(case)
    hinge = np.array([0.150, 0.0, 0.120])
    a = np.deg2rad(10.0)
    site = dataclasses.replace(case.sites[0], position=np.array([0.012, -0.045, 0.035]),
                               axis=np.array([-0.3, 0.9, 0.3]) / np.linalg.norm([-0.3, 0.9, 0.3]))
    moved = pipeline.site_at_opening(case, site, 35.0)
    rel = R @ site.position + t - hinge
    want = hinge + np.array([rel[0] * np.cos(a) - rel[2] * np.sin(a), rel[1],
                             rel[2] * np.cos(a) + rel[0] * np.sin(a)])
    np.testing.assert_allclose(R @ moved.position + t, want, atol=1e-9)
    d = R @ site.axis
    want_axis = np.array([d[0] * np.cos(a) - d[2] * np.sin(a), d[1],
                          d[2] * np.cos(a) + d[0] * np.sin(a)])
    np.testing.assert_allclose(R @ moved.axis, want_axis, atol=1e-8)


def test_a_molar_in_the_band_keeps_its_place_on_the_scan(case):
    """The default sites' crowns lie just inside the occlusal band (the map is not rigid there):
    carried to 35 deg they stay the same point of the scan as scanned, as far from the hinge
    line, on the same side; their axis turned as the bone turns there (about the hinge, by the
    map's rotation at the site: less than the 10 deg of the rigid jaw, more than 9)."""
    R, t = _mesh_frame(case)
    m = case.mesh
    hinge = np.array([0.150, 0.0, 0.120])
    for site in case.sites:
        moved = pipeline.site_at_opening(case, site, 35.0)
        old_W, new_W = R @ site.position + t, R @ moved.position + t
        scanned = anatomy.as_scanned(np.stack([old_W, new_W]), 0.0, m.opening)
        np.testing.assert_allclose(
            anatomy.as_scanned(new_W[None], 35.0, m.opening)[0],
            anatomy.as_scanned(old_W[None], m.mouth_opening_deg, m.opening)[0], atol=1e-9)
        assert scanned.shape == (2, 3)
        dist = [np.linalg.norm((p - hinge)[[0, 2]]) for p in (old_W, new_W)]
        assert abs(dist[0] - dist[1]) < 1e-9 and abs(new_W[1] - old_W[1]) < 1e-12
        assert 5e-3 < np.linalg.norm(new_W - old_W) < 20e-3
        assert abs(np.linalg.norm(moved.axis) - 1.0) < 1e-12
        d, e = R @ site.axis, R @ moved.axis
        assert abs(e[1] - d[1]) < 1e-12  # a turn about the hinge line (along y)
        turn = np.degrees(np.arccos(np.clip(d[[0, 2]] @ e[[0, 2]] / np.linalg.norm(d[[0, 2]])
                                            / np.linalg.norm(e[[0, 2]]), -1, 1)))
        assert 9.0 < turn <= 10.0 + 1e-9


def test_there_and_back_again(case):
    site = case.sites[0]
    there = pipeline.site_at_opening(case, site, 40.0)
    opened = case_from_dict({**read_yaml(default_case_path()),
                             "mesh": {**read_yaml(default_case_path())["mesh"],
                                      "mouth_opening_deg": 40}}, source=default_case_path())
    back = pipeline.site_at_opening(opened, there, case.mesh.mouth_opening_deg)
    np.testing.assert_allclose(back.position, site.position, atol=1e-9)
    np.testing.assert_allclose(back.axis, site.axis, atol=1e-9)


def test_without_a_jaw_model_there_is_nothing_to_try():
    data = read_yaml(default_case_path())
    data["mesh"] = {**data["mesh"], "mouth_opening_deg": 45}
    case = case_from_dict(data, source=default_case_path())
    probe = pipeline.opening_needed(case, 0)
    assert probe["opening_deg"] is None and probe["tried"] == []
    assert "largest 45 deg" in probe["text"]


@pytest.mark.sweep
def test_a_site_refused_at_a_small_opening_names_the_opening_that_plans(case):
    """Site 36 of the default case with the mouth opened by 15 deg only (the site carried with
    the jaw): the actuator's head does not fit (FCL's best over every candidate is in the
    tissue), and the refusal names the first larger opening that plans: 20 deg is refused too
    (measured: FCL's best 0.68 mm < 1 mm), 25 deg (the default case) plans."""
    site = pipeline.site_at_opening(case, case.sites[0], 15.0)
    small = dataclasses.replace(
        case, mesh=dataclasses.replace(case.mesh, mouth_opening_deg=15.0), sites=(site,),
        safety=dataclasses.replace(case.safety, registration_samples=0))
    fit = pipeline.fit_stage(small)
    with pytest.raises(PlanningFailure) as info:
        pipeline.placement_stage(small, fit)
    message, probe = str(info.value), info.value.result["opening_probe"]
    assert "the site's geometry refuses" in message
    # the widest opening first (it plans: a smaller one may), then upwards from the case's
    assert [t["opening_deg"] for t in probe["tried"]] == [45.0, 20.0, 25.0]
    assert [t["valid"] for t in probe["tried"]] == [True, False, True]
    assert probe["opening_deg"] == 25.0
    assert probe["tried"][2]["clearance_certified"] >= case.safety.clearance_margin
    assert "it plans at a mouth opening of 25 deg (mesh.mouth_opening_deg" in message
