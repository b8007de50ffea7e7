"""The independent check of the scan bound (analyses.studies.scan_bound_check) against FCL, and
the defect it found: the bound does not return for a capsule or sphere thicker than
res / RELATIVE (2 mm) whose axis passes 2.5-4 mm from the wall (it splits pieces forever)."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from implantplan.analyses.progress import Progress
from implantplan.analyses.studies import scan_bound_check as sbc
from implantplan.systems import seeds
from implantplan.systems.placement.scan_clearance import ScanClearance

HANG = textwrap.dedent("""
    import numpy as np, trimesh
    from implantplan.systems.instrument import Instrument, Shape
    from implantplan.systems.placement.distance_grid import build_grid
    from implantplan.systems.placement.scan_clearance import ScanClearance
    m = trimesh.creation.cylinder(radius=0.03, height=0.08, sections=96)
    m.apply_translation([0, 0, 0.04])
    keep = ~np.all(np.isclose(m.vertices[m.faces][..., 2], 0.08), axis=1)
    m = trimesh.Trimesh(m.vertices, m.faces[keep], process=False)
    ball = Instrument("ball", (Shape("head", "sphere", [0, 0, 0], [0, 0, 0], {r}),),
                      rod_radius={r}, implant_length=0.01)
    scan = ScanClearance(m, ball, grid=build_grid(m, spacing=1e-3))
    X = np.eye(4)
    X[:3, 3] = [0.03 * np.cos(np.pi / 96) - {d}, 0.0, 0.04]  # the centre {d} m from the wall
    print(int(scan.fast_verdict(X, 1e-3)[0]))
""")


def _verdict_in(seconds: float, *, d: float, r: float = 0.006):
    """The fast verdict of a sphere of radius r centred d from a cylinder cavity's wall, run in a
    child process; None if it does not return within ``seconds``."""
    try:
        out = subprocess.run([sys.executable, "-c", HANG.format(d=d, r=r)], capture_output=True,
                             text=True, timeout=seconds, check=True)
    except subprocess.TimeoutExpired:
        return None
    return int(out.stdout.split()[-1])


def test_the_bound_returns_near_and_far_from_the_wall():
    # the control of the reproducer below: centre 1.5 mm from the wall (penetrating 4.5 mm, an
    # exact node proves it) and 5 mm (penetrating 1 mm: undecided) return at once
    assert _verdict_in(60, d=0.0015) == -1
    assert _verdict_in(60, d=0.005) == 0


def test_the_bound_returns_for_a_sphere_penetrating_2_to_4_mm():
    # the relative resolution (5 % of a piece's bound) once kept splitting pieces with a bound
    # below -2 mm: a sphere of radius > 2 mm 2.5-4 mm from the wall never returned
    # it returns, never SAFE (unsafe, or undecided: resolved by FCL)
    assert _verdict_in(20, d=0.0035) in (-1, 0)


# -- the check itself ---------------------------------------------------------------------------

SMALL = 100  # poses per cavity x instrument in the default run


@pytest.fixture(scope="module")
def default(demo_plan):
    """The default cavity with the demo plan's placements (the run's shared plan)."""
    return sbc.default_cavity(Progress("test", quiet=True), demo_plan)


@pytest.fixture(scope="module")
def mirror(default):
    return sbc.copy_cavity(default[0], "mirror")


@pytest.fixture(scope="module")
def checked(default, mirror):
    """The small check: the default cavity and its mirror copy, both instruments."""
    base, margin = default
    out = {}
    for ci, cav in enumerate((base, mirror)):
        for ii, name in enumerate(sbc.INSTRUMENTS):
            scan = ScanClearance(cav.exact, sbc.instrument(name))
            X, kinds = sbc.pose_set(cav, scan, name, SMALL, margin, seeds.rng(7, ci, ii))
            out[cav.name, name] = (scan, X, kinds,
                                   sbc.measure(scan, cav.exact, scan.instrument, X, kinds, margin))
    return out


def test_no_false_safe_on_the_default_cavity_and_its_mirror(checked, default):
    margin = default[1]
    assert default[0].exact is not None and margin == pytest.approx(1e-3)
    for (cav, name), (_, X, kinds, r) in checked.items():
        assert r["false_safe_verdict"] == 0, (cav, name, r["worst_pose"])
        assert r["false_safe_value"] == 0, (cav, name, r["worst_pose"])
        skipped = r["not_evaluated_nonterminating"].get("poses", 0)
        assert r["poses"] + skipped == len(X) and r["poses"] >= SMALL // 2
        # the adversarial poses are what they say: brackets within BAND of the margin
        fcl = r["by_kind"]
        for kind in ("margin_above", "margin_below"):
            assert fcl[kind]["poses"] > 0, (cav, name, kind)
        assert margin <= fcl["margin_above"]["fcl_min_m"] <= fcl["margin_above"]["fcl_max_m"] \
            <= margin + sbc.BAND
        assert margin - sbc.BAND <= fcl["margin_below"]["fcl_min_m"] \
            <= fcl["margin_below"]["fcl_max_m"] < margin
        assert {"random", "margin_above", "margin_below"} <= set(kinds.tolist())
    # the actuator is all cylinders: the bound returns everywhere, nothing is skipped
    assert not checked["default", "actuator"][3]["not_evaluated_nonterminating"]


class ShiftedBound:
    """A deliberately broken bound: ScanClearance's lower bound raised by ``shift``."""

    def __init__(self, scan: ScanClearance, shift: float):
        self.scan, self.shift = scan, shift

    def bounds(self, X, target=sbc.GAP_CAP):
        lower, upper = self.scan.bounds(X, target - self.shift)
        return lower + self.shift, upper

    def fast_verdict(self, X, clearance):
        return self.scan.fast_verdict(X, clearance - self.shift)


def test_the_check_catches_a_bound_raised_by_half_a_millimetre(checked, default):
    base, margin = default
    for name in sbc.INSTRUMENTS:
        scan, X, kinds, honest = checked["default", name]
        broken = sbc.measure(ShiftedBound(scan, 0.5e-3), base.exact, scan.instrument, X, kinds,
                             margin)
        assert honest["false_safe_verdict"] == 0
        assert broken["false_safe_verdict"] > 0 and broken["false_safe_value"] > 0
        assert broken["largest_excess_m"] > 0.3e-3
        assert broken["worst_pose"] is not None


def test_copies_move_the_mesh_and_the_poses_together(default):
    base, _ = default
    rng = np.random.default_rng(3)
    site, X_CT, depth = base.feeds[0]
    for name in ("mirror", "rigid"):
        cav = sbc.copy_cavity(base, name)
        A = sbc.similarity(name)
        # winding kept: the copy's normals are the original's, moved (reflected) with it
        Q = A[:3, :3]
        assert np.mean(np.sum(cav.exact.mesh.face_normals
                              * (base.exact.mesh.face_normals @ Q.T), axis=1)) > 0.99
        for inst_name in sbc.INSTRUMENTS:
            inst = sbc.instrument(inst_name)
            X = sbc.sampled_poses(X_CT, depth[inst_name], 40, rng)
            a = base.exact.tool_clearance(X, inst)
            b = cav.exact.tool_clearance(sbc.transform_poses(X, A), inst)
            free = a > 0  # where free FCL's value is a distance: the same for the moved pair
            assert free.sum() > 10
            # the reference's GJK stops within its gap (python-fcl's differed by up to 9 um
            # between a mesh and its moved copy); a wrong transform moves the walls by mm
            np.testing.assert_allclose(b[free], a[free], atol=1e-8)
    # the scaled copies keep the Center origin and scale positions, not the instrument
    S = sbc.similarity("scale1.1")
    Y = sbc.transform_poses(X_CT, S)[0]
    np.testing.assert_allclose(Y[:3, 3], 1.1 * X_CT[:3, 3])
    np.testing.assert_allclose(Y[:3, :3], X_CT[:3, :3])


@pytest.mark.parametrize("argv, field", [
    (["--poses", "0"], "--poses"), (["--poses", "1000001"], "--poses"),
    (["--poses", "many"], "--poses"), (["--seed", "-1"], "--seed"), (["--seed", "x"], "--seed"),
])
def test_bad_input_exits_2_naming_the_field(argv, field, capsys):
    assert sbc.main(argv) == 2
    err = capsys.readouterr().err
    assert field in err and "Traceback" not in err


def test_an_existing_out_folder_is_refused(tmp_path, capsys):
    assert sbc.main(["--poses", "10", "--out", str(tmp_path)]) == 2
    assert "--out" in capsys.readouterr().err


@pytest.mark.sweep
def test_full_scale_no_false_safe():
    res = sbc.study(poses=12_000, seed=0)
    assert res["poses_total"] >= 100_000
    for r in res["rows"]:
        assert r["false_safe_verdict"] == 0, (r["cavity"], r["instrument"], r["worst_pose"])
        assert r["false_safe_value"] == 0, (r["cavity"], r["instrument"], r["worst_pose"])
    shares = {(r["cavity"], r["instrument"]): r["called_safe_share"] for r in res["rows"]}
    print("called-safe share of the poses free by margin + 0.2 mm:", shares)
    assert min(shares.values()) >= 0.9, shares  # measured: 100% in every row (2026-12-03)


# FCL's -1 for a grazing cylinder (found by the full-scale check: default cavity, actuator, a
# grazing pose; the rod's axis 6.006 mm from the scan, the rod 6 mm in radius)
GRAZING_ROD = np.array([
    [-0.3859732880922723, 0.8771241423774927, -0.28579338644865104, -0.0073530446284089945],
    [-0.12268598228491095, 0.25824212274799974, 0.9582583971922154, 0.010412128634026794],
    [0.9143154655970915, 0.40492498675329397, 0.007936275752419114, 0.05920051123850115],
    [0.0, 0.0, 0.0, 1.0]])


def test_the_reference_stays_above_its_floor_for_a_grazing_cylinder(default):
    """python-fcl's distance query answered -1 ('in collision') for this grazing rod that its
    collide query called free, so the reference reported -1 m, below its own floor -r."""
    base, _ = default
    actuator = sbc.instrument("actuator")
    value = base.exact.tool_clearance(GRAZING_ROD[None], actuator)[0]
    assert value >= -max(s.radius for s in actuator.shapes)
    # the rod lies inside the capsule about its axis: never closer than that capsule
    rod = next(s for s in actuator.shapes if s.name == "rod")
    R, p = GRAZING_ROD[:3, :3], GRAZING_ROD[:3, 3]
    a, b = R @ rod.a + p, R @ rod.b + p
    capsule = base.exact.capsule_clearance(a, b, rod.radius)[0]
    assert base.exact.cylinder_clearance(a, b, rod.radius)[0] >= capsule - 1e-9 > -1e-4


def test_an_unknown_cavity_exits_2(capsys):
    assert sbc.main(["--poses", "10", "--cavities", "default,moon"]) == 2
    assert "--cavities" in capsys.readouterr().err


# python-fcl's cylinder distance above the true distance (found by the check on another subject,
# cohort-00 x actuator: the bound's upper estimate proved UNSAFE where FCL said clear)
HEAD_NEAR_MARGIN = np.array([
    [0.2103346151934873, 0.9559446805563744, 0.2047660063764964, 0.004530174456698],
    [-0.01723546910370545, -0.20579308064438195, 0.9784437370455543, 0.01239647774083738],
    [0.977477512915864, -0.2093298250963456, -0.02680925342023741, 0.06323317507561166],
    [0.0, 0.0, 0.0, 1.0]])


def test_the_reference_is_at_most_the_distance_of_points_of_the_solid():
    """python-fcl's GJK gave the actuator's head 1.0014 mm at this pose where points of the
    head's surface are 0.9507 mm from the scan (libigl, exact point distances): 0.05 mm high, on
    the unsafe side of the 1 mm margin. The reference (Coal) must not be above those points."""
    import igl

    from implantplan.analyses import pipeline
    from implantplan.analyses.case import load_case
    from implantplan.systems.placement.exact_clearance import ExactCavity

    cav, _ = _cohort_00_exact(pipeline, load_case, ExactCavity)
    head = next(s for s in sbc.instrument("actuator").shapes if s.name == "head")
    R, p = HEAD_NEAR_MARGIN[:3, :3], HEAD_NEAR_MARGIN[:3, 3]
    a, b = R @ head.a + p, R @ head.b + p
    fcl = cav.cylinder_clearance(a, b, head.radius)[0]
    n = (b - a) / np.linalg.norm(b - a)
    e1 = np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    t, phi = np.linspace(0, 1, 400), np.linspace(0, 2 * np.pi, 360, endpoint=False)
    ring = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    P = (a + t[:, None, None] * (b - a) + head.radius * ring[None]).reshape(-1, 3)
    d = np.sqrt(igl.point_mesh_squared_distance(
        np.ascontiguousarray(P), np.ascontiguousarray(cav.mesh.vertices),
        np.ascontiguousarray(cav.mesh.faces, dtype=np.int64))[0])
    assert fcl <= d.min() + 1e-6, (fcl, d.min())


def _cohort_00_exact(pipeline, load_case, ExactCavity):
    import tempfile
    from pathlib import Path

    from implantplan.analyses.case import default_case_path
    from implantplan.analyses.cohort import load_cohort, make_cohort

    with tempfile.TemporaryDirectory() as tmp:
        _, files = load_cohort(make_cohort(default_case_path(), Path(tmp), 1, seed=0))
        case = load_case(files[0])
        fit = pipeline.fit_stage(case)
        return ExactCavity.from_scan(fit.opened, fit.fpsm,
                                     close_open_cuts=case.mesh.close_open_cuts), case


@pytest.mark.sweep
def test_a_plan_folder_gives_the_cavity_placed_again(default):
    """``--plan``: the demo plan's feeds are the default case placed again (same seed)."""
    again, margin = sbc.default_cavity(Progress("test", quiet=True))
    assert margin == default[1]
    assert len(again.feeds) == len(default[0].feeds)
    for (name_a, X_a, depth_a), (name_b, X_b, depth_b) in zip(again.feeds, default[0].feeds,
                                                              strict=True):
        assert name_a == name_b and depth_a == pytest.approx(depth_b, abs=1e-12)
        np.testing.assert_allclose(X_a, X_b, rtol=0, atol=1e-12)
    assert len(again.exact.mesh.faces) == len(default[0].exact.mesh.faces)
