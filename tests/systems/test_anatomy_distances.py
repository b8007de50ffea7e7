"""Clinical distances (systems.anatomy.distances): exact segment distances against brute force,
the canal rule at 1.5 mm (fails, with the value) and 2.5 mm (passes), the inverse of the
jaw-opening map, and the voxel bounds never above the true distance."""

from __future__ import annotations

import numpy as np
import pytest

from implantplan.analyses.checks import anatomy_checks
from implantplan.systems.anatomy import distances as d
from implantplan.systems.anatomy.cbct import Volume
from implantplan.systems.fpsm.oral_mesh import opening_map


def _implant_and_canal(gap):
    """A vertical implant r 2 mm, 10 mm long, and a canal r 1.2 mm crossing under its apex with
    ``gap`` (m) between the surfaces."""
    entry, apex = np.array([0.0, 0, 0.02]), np.array([0.0, 0, 0.01])
    z = 0.01 - 1.2e-3 - gap
    canal = np.array([[-0.02, 0.0, z], [0.0, 0.0, z], [0.02, 0.0, z]])
    return entry, apex, canal


@pytest.mark.parametrize(("gap_mm", "passes"), [(1.5, False), (2.5, True)])
def test_a_canal_at_1_5_mm_fails_with_its_value_and_2_5_passes(gap_mm, passes):
    entry, apex, canal = _implant_and_canal(gap_mm * 1e-3)
    value = d.canal_clearance(entry, apex, 2e-3, canal, 1.2e-3)
    assert value == pytest.approx(gap_mm * 1e-3, abs=1e-9)  # under the flat end: exact
    anatomy = {"sites": [{"site": "36", "canal_clearance_m": value}]}
    (c,) = anatomy_checks(anatomy)
    assert c["id"] == "anatomy.canal_distance" and c["pass"] is passes
    assert c["value"] == pytest.approx(gap_mm * 1e-3) and c["limit"] == 2e-3


def test_point_cylinder_distance_is_exact():
    apex, entry = np.zeros(3), np.array([0, 0, 0.01])
    pts = np.array([[0.003, 0, 0.005], [0, 0, 0.013], [0.003, 0, -0.004], [0.001, 0, 0.002]])
    np.testing.assert_allclose(d.point_cylinder_distance(pts, apex, entry, 0.002),
                               [0.001, 0.003, np.hypot(0.001, 0.004), 0.0], atol=1e-15)


def test_inter_implant_clearances():
    e = np.array([[0, 0, 0.01], [0.008, 0, 0.01], [0.03, 0, 0.01]])
    a = e - [0, 0, 0.01]
    c = d.inter_implant_clearances(e, a, np.array([2e-3, 2e-3, 2.5e-3]))
    assert c[0, 1] == pytest.approx(4e-3, abs=1e-9) and c[1, 2] == pytest.approx(0.0175, abs=1e-9)
    assert np.isinf(c[0, 0])
    checks = anatomy_checks({"sites": [{"site": "a", "nearest_implant_m": 2.9e-3},
                                       {"site": "b", "nearest_implant_m": 3.1e-3}]})
    assert [x["pass"] for x in checks] == [False, True]


def test_as_scanned_inverts_the_opening_map():
    opening = {"hinge_point": np.array([0.15, 0, 0.12]), "hinge_axis": np.array([0, -1.0, 0]),
               "occlusal_point": np.array([0, 0, 0.1]), "occlusal_normal": np.array([0, 0, 1.0]),
               "blend": 0.02}
    rng = np.random.default_rng(1)
    p = rng.uniform([0.06, -0.03, 0.06], [0.14, 0.03, 0.12], size=(500, 3))
    q = opening_map(p, 25.0, opening["hinge_point"], opening["hinge_axis"],
                    opening["occlusal_point"], opening["occlusal_normal"], 0.02)[0]
    x = d.as_scanned(q, 25.0, opening)
    back = opening_map(x, 25.0, opening["hinge_point"], opening["hinge_axis"],
                       opening["occlusal_point"], opening["occlusal_normal"], 0.02)[0]
    np.testing.assert_allclose(back, q, atol=1e-9)  # a preimage, everywhere
    rigid = np.abs(p[:, 2] - 0.1) > 0.01  # outside the blend band the map is one-to-one
    np.testing.assert_allclose(x[rigid], p[rigid], atol=1e-9)


def _box_volume(h=0.5):
    """Bone (1000 HU) filling x, y in [-10, 10] mm, z in [-20, 0] mm; air above; h mm voxels."""
    n = int(round(40 / h)) + 1
    axis = -20 + h * np.arange(n)
    Z, Y, X = np.meshgrid(axis, axis, axis, indexing="ij")
    hu = np.where((np.abs(X) <= 10) & (np.abs(Y) <= 10) & (Z <= 0) & (Z >= -20), 1000.0, -1000.0)
    affine = np.diag([h, h, h, 1.0])
    affine[:3, 3] = -20
    return Volume(hu.astype(np.float32), affine)


def test_voxel_bounds_are_conservative_and_tight():
    vol = _box_volume()
    entry, apex = np.array([0.003, 0, -0.001]), np.array([0.003, 0, -0.011])
    margin, crest = d.bone_margin(vol, entry, apex, 2e-3, 300.0)
    true = 10e-3 - 3e-3 - 2e-3  # the nearest side wall (x = 10 mm) from the implant's surface
    assert margin <= true and margin > true - 1.5e-3
    assert crest == pytest.approx(0.0, abs=1e-3)
    teeth = d.tooth_clearance(vol, np.array([0.0, 0, 0.008]), np.array([0.0, 0, 0.004]), 1e-3,
                              300.0)
    # the bone top at z = 0, 4 mm under the implant's flat end
    assert teeth <= 4e-3 and teeth > 4e-3 - np.sqrt(3) * 0.5e-3


def _ball_volume(h=0.5, centre=(1.3, -0.7, 0.4), radius=4.0):
    """A tooth (2500 HU) ball in soft tissue, voxels of h mm over +-12 mm; centre and radius mm."""
    axis = -12 + h * np.arange(int(round(24 / h)) + 1)
    Z, Y, X = np.meshgrid(axis, axis, axis, indexing="ij")
    r = np.sqrt((X - centre[0]) ** 2 + (Y - centre[1]) ** 2 + (Z - centre[2]) ** 2)
    affine = np.diag([h, h, h, 1.0])
    affine[:3, 3] = -12
    return Volume(np.where(r <= radius, 2500.0, 40.0).astype(np.float32), affine)


def test_tooth_clearance_is_never_above_the_exact_distance_on_random_implants():
    import fcl

    vol = _ball_volume()
    ball = fcl.CollisionObject(fcl.Sphere(4e-3), fcl.Transform(np.array([1.3e-3, -0.7e-3, 0.4e-3])))
    rng = np.random.default_rng(3)
    false_safe, slack = 0, []
    for _ in range(200):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        apex = rng.uniform(-6e-3, 6e-3, 3) + 7e-3 * rng.normal(size=3) / np.sqrt(3)
        entry = apex + rng.uniform(6e-3, 12e-3) * axis
        r = rng.uniform(1.5e-3, 2.5e-3)
        exact = float(fcl.distance(d.implant_object(entry, apex, r), ball,
                                   fcl.DistanceRequest(enable_signed_distance=True),
                                   fcl.DistanceResult()))
        if not 0 < exact < 10e-3:
            continue
        fast = d.tooth_clearance(vol, entry, apex, r, 1800.0)
        false_safe += fast > exact + 1e-9
        slack.append(exact - fast)
    assert len(slack) > 50 and false_safe == 0
    # tight: within two voxel half-diagonals (0.87 mm at 0.5 mm voxels) of the exact distance
    assert max(slack) < np.sqrt(3) * 0.5e-3 + 1e-9


def _socket_volume(wall_mm, *, offset_mm=(0.0, 0.0), radius_mm=2.0, h=0.075):
    """A bone cylinder (1000 HU) along z, its crest flat at z = 0, 14 mm deep, of radius
    ``radius_mm + wall_mm`` around (0, 0) in soft tissue (40 HU), air above z = 2 mm; h mm voxels
    (a voxel is bone when its centre is). The implant of ``radius_mm`` sits around
    ``offset_mm``: the wall is ``wall_mm`` thick on the side it moves away from."""
    R = radius_mm + wall_mm + np.hypot(*offset_mm)
    xy = np.arange(-R - 1.0, R + 1.0 + 1e-9, h)
    z = np.arange(-15.0, 3.0 + 1e-9, h)
    Z, Y, X = np.meshgrid(z, xy, xy, indexing="ij")
    hu = np.where(Z > 2.0, -1000.0, 40.0)
    hu[(np.hypot(X, Y) <= R) & (Z <= 0) & (Z >= -14)] = 1000.0
    affine = np.diag([h, h, h, 1.0])
    affine[:3, 3] = [xy[0], xy[0], z[0]]
    return Volume(hu.astype(np.float32), affine)


@pytest.mark.parametrize(("wall_mm", "passes"), [(0.8, False), (1.2, True)])
def test_bone_around_an_implant_in_a_bone_cylinder(wall_mm, passes):
    """A 4 mm implant, 10 mm long from 1 mm above the crest, centred in a bone cylinder whose
    wall is 0.8 mm (fails the 1 mm rule) or 1.2 mm (passes) thick."""
    vol = _socket_volume(wall_mm)
    entry, apex = np.array([0.0, 0, 1e-3]), np.array([0.0, 0, -9e-3])
    margin, crest = d.bone_margin(vol, entry, apex, 2e-3, 300.0)
    assert crest == pytest.approx(1e-3, abs=0.1e-3)
    # conservative (never above the wall), within a half step and two voxel half-diagonals of
    # it (one subtracted, one where the nearest voxel's centre may lie): measured 0.69 / 1.10 mm
    h = 0.075e-3
    assert wall_mm * 1e-3 - h / 2 - np.sqrt(3) * h - 1e-9 <= margin <= wall_mm * 1e-3
    (c,) = anatomy_checks({"sites": [{"site": "36", "bone_margin_m": margin,
                                      "bone_crest_depth_m": crest}]})
    assert c["id"] == "anatomy.bone_around_implant" and c["pass"] is passes
    assert c["limit"] == 1e-3 and c["bound"] == "min" and c["value"] == margin


def test_the_facial_wall_of_an_anterior_maxillary_implant_needs_1_5_mm():
    """The implant 1.8 mm off the cylinder's centre towards +y: its wall is 1.2 mm thick on the
    +y (facial) side and 4.8 mm on the other: 1 mm around it passes, 1.5 mm facial fails at
    tooth 11 and is not asked at 36; facing -y the facial wall is the thick one."""
    vol = _socket_volume(1.2, offset_mm=(0.0, 1.8))
    entry, apex = np.array([0.0, 1.8e-3, 1e-3]), np.array([0.0, 1.8e-3, -9e-3])
    around, _ = d.bone_margin(vol, entry, apex, 2e-3, 300.0)
    facial, _ = d.bone_margin(vol, entry, apex, 2e-3, 300.0, facial=[0.0, 1.0, 0.2])
    other, _ = d.bone_margin(vol, entry, apex, 2e-3, 300.0, facial=[0.0, -1.0, 0.0])
    assert 1.0e-3 < around <= 1.2e-3 and facial == around
    assert other > 3.0e-3  # the thick side: 4.8 mm across, less the 60 deg sector's slant
    assert d.anterior_maxilla("11") and d.anterior_maxilla("23") and not d.anterior_maxilla("36")
    assert not d.anterior_maxilla("14") and not d.anterior_maxilla("site-a")
    checks = anatomy_checks({"sites": [
        {"site": "11", "bone_margin_m": around, "facial_bone_margin_m": facial},
        {"site": "21", "bone_margin_m": other, "facial_bone_margin_m": other}]})
    got = {(c["site"], c["id"]): c["pass"] for c in checks}
    assert got == {("11", "anatomy.bone_around_implant"): True,
                   ("11", "anatomy.facial_bone_anterior_maxilla"): False,
                   ("21", "anatomy.bone_around_implant"): True,
                   ("21", "anatomy.facial_bone_anterior_maxilla"): True}
    (f,) = [c for c in checks if c["id"] == "anatomy.facial_bone_anterior_maxilla"
            and c["site"] == "11"]
    assert f["limit"] == 1.5e-3 and f["value"] == facial


def test_an_oblique_crest_leaves_a_thin_wedge_that_fails():
    """The 1.2 mm cylinder's crest cut at 38 deg across the implant (bone only under the plane
    z = -tan(38 deg) y, mm): on its low side (+y) the implant enters bone through a wedge
    thinner than 1 mm for its first 0.8 mm (1.28 mm per mm deeper), which the rings below the
    side's first point in bone (0.47 mm apart) and a voxel's diagonal meet: the rule fails
    (measured 0.65 mm; 1.10 mm with the crest flat)."""
    vol = _socket_volume(1.2)
    n = vol.hu.shape
    k, j = np.meshgrid(np.arange(n[0]), np.arange(n[1]), indexing="ij")
    z = vol.affine[2, 3] + vol.affine[2, 2] * k
    y = vol.affine[1, 3] + vol.affine[1, 1] * j
    above = (z > -np.tan(np.deg2rad(38.0)) * y)[..., None] & (vol.hu > 300)
    vol.hu[above] = 40.0
    margin, _ = d.bone_margin(vol, np.array([0.0, 0, 1e-3]), np.array([0.0, 0, -9e-3]), 2e-3,
                              300.0)
    assert margin < 0.8e-3
    (c,) = anatomy_checks({"sites": [{"site": "36", "bone_margin_m": margin}]})
    assert not c["pass"]
