"""Implant sites against the scan (systems.fpsm.sites): on the tissue, axis into the cavity."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from implantplan.systems.fpsm.sites import check_sites, site_problems

R = 0.02  # a closed cylindrical "cavity" of radius 20 mm, 60 mm long, axis z, centred at z = 30 mm


@pytest.fixture(scope="module")
def cavity():
    mesh = trimesh.creation.cylinder(radius=R, height=0.06, sections=256)
    mesh.apply_translation([0, 0, 0.03])
    return mesh


def _wall(angle_deg, z, inset=0.0):
    a = np.radians(angle_deg)
    radial = np.array([np.cos(a), np.sin(a), 0.0])
    return radial * (R - inset) + [0, 0, z], -radial  # position, axis pointing to the cavity


def test_sites_on_the_wall_with_inward_axes_pass(cavity):
    sites = [_wall(a, z) for a, z in ((0, 0.01), (100, 0.03), (250, 0.05))]
    P, A = np.array([s[0] for s in sites]), np.array([s[1] for s in sites])
    check = check_sites(cavity, np.eye(4), P, A)
    # the 256-gon's flats lie at most R (1 - cos(pi/256)) = 1.5 um inside the circle
    assert np.all(check.distance < 2e-6) and check.ok.all()
    assert site_problems(check, cavity, np.eye(4), P) == [None, None, None]


def test_a_site_in_open_air_names_the_distance_and_the_limit(cavity):
    for inset, expect_ok in ((0.0009, True), (0.005, False), (0.010, False)):
        p, a = _wall(30, 0.03, inset=inset)
        check = check_sites(cavity, np.eye(4), [p], [a])
        assert check.distance[0] == pytest.approx(inset, abs=5e-6)  # the 256-gon vs the circle
        assert bool(check.ok[0]) is expect_ok
        if not expect_ok:
            (msg,) = site_problems(check, cavity, np.eye(4), [p])
            expected = f"lies {inset * 1e3:.2f} mm from the scanned tissue, expected at most 1 mm"
            assert expected in msg


def test_a_reversed_axis_is_named(cavity):
    p, a = _wall(60, 0.02)
    check = check_sites(cavity, np.eye(4), [p], [-a])
    assert check.on_surface[0] and not check.axis_into_cavity[0]
    assert check.reversed_into_cavity[0]
    (msg,) = site_problems(check, cavity, np.eye(4), [p])
    assert "does not point into the mouth" in msg and "reversed axis would point" in msg


def test_unit_slips_are_named(cavity):
    p_W, a = _wall(0, 0.02)
    X_WC = np.eye(4)
    X_WC[2, 3] = 0.03  # Center on the cylinder's axis, mid-length: the site is (0.02, 0, -0.01)
    p = p_W - X_WC[:3, 3]
    too_small = p / 1000.0  # typed 1000x too small: lands near the Center origin, in the air
    too_large = p * 1000.0
    check = check_sites(cavity, X_WC, [too_small, too_large], [a, a])
    assert not check.ok.any()
    msgs = site_problems(check, cavity, X_WC, [too_small, too_large])
    assert "metres typed into an _mm field (x1000" in msgs[0]
    assert "mm read as metres (/1000" in msgs[1]


def test_project_to_tissue_moves_a_site_along_its_axis_onto_the_wall(cavity):
    from implantplan.systems.fpsm.sites import project_to_tissue

    p, a = _wall(45, 0.03, inset=0.004)  # 4 mm off the wall, axis into the cavity
    q = project_to_tissue(cavity, np.eye(4), [p, p], [a, -a])
    assert np.linalg.norm(q[0] - (p - 0.004 * a)) < 2e-6  # back along -axis onto the wall
    assert np.linalg.norm(q[1] - (p + 0.036 * a)) < 2e-6  # reversed: the opposite wall, 36 mm
    assert check_sites(cavity, np.eye(4), q, [a, -a]).ok.all()
