"""The adversarial operator against the safety layer on the default case: a few runs
in the default suite, the study and the full jump sweep as slow tests. Exact clearance by FCL
against the opened scan at every logged pose and over the arm's motion between them."""

import numpy as np
import pytest

from implantplan.analyses.studies import adversarial as A
from implantplan.analyses.studies.scan_reference import plan_sites, swept_clearance
from implantplan.diagrams.feeding import FINISH_SECONDS
from implantplan.diagrams.teleop import build_teleop, simulate
from implantplan.systems.instrument import Instrument
from implantplan.systems.teleop.adversarial_operator import (
    Directions,
    adversarial_motion,
    handle_jump,
    jump_directions,
)
from implantplan.systems.teleop.command_limits import CommandLimits
from implantplan.systems.teleop.master_device import feeding_runs
from implantplan.systems.teleop.supervisor import Barrier

MARGIN = Barrier().margin


@pytest.fixture(scope="module")
def site(demo_plan):
    """Site 36 of the default case's plan folder, its teleop diagram and the exact reference."""
    cases, mesh = plan_sites(demo_plan)
    tc = cases[0]
    return tc, build_teleop(tc), A.exact_for(tc, mesh)


STEP_LIMIT = A.STEP_SLACK * CommandLimits().linear_speed * 0.005  # m per control period


def _check(r, *, fixture=True):
    assert r["min_exact_clearance"] > 0.0
    assert r["min_exact_clearance"] >= MARGIN - A.MARGIN_SLACK
    assert r["min_exact_bound"] >= MARGIN - A.MARGIN_SLACK  # between the logged poses too
    assert r["min_exact_bound"] <= r["min_exact_between"] <= r["min_exact_clearance"]
    if fixture:
        assert r["max_vf_violation"] < A.MAX_VIOLATION
    assert r["max_tcp_step"] <= STEP_LIMIT


SWEEP = pytest.mark.sweep  # the default run keeps one case of each family, CI runs them all


@pytest.mark.parametrize("kind, seed", [("cheek_left", 0), pytest.param("cheek_right", 1,
                                                                        marks=SWEEP),
                                        ("jaw", 2), pytest.param("bursts", 3, marks=SWEEP)])
def test_adversarial_motion_stays_clear_of_the_exact_anatomy(site, kind, seed):
    tc, teleop, exact = site
    start, target = tc.X_WE(tc.q_start)[:3, 3], tc.X_WTarget[:3, 3]
    motion = adversarial_motion(kind, start, target, Directions.of_case(tc.X_WTarget,
                                                                        tc.X_WCenter), seed=seed)
    _check(A.run_one(teleop, tc, motion, exact))


@pytest.mark.parametrize("kind, seed, fixture", [
    ("tremor", 0, True), pytest.param("pulse", 1, True, marks=SWEEP), ("jump", 0, True),
    pytest.param("spike", 1, False, marks=SWEEP), ("speed_1e9", 0, True), ("nan", 1, False),
    pytest.param("inf", 2, True, marks=SWEEP), pytest.param("turn_1e9", 3, False, marks=SWEEP)])
def test_jumps_and_absurd_commands_are_faults_not_motions(site, kind, seed, fixture):
    """A handle jump (50-1000 mm in one sample) or an absurd twist mid-feed: a logged fault, the
    tool held while it lasts, no jump of the arm when it clears, the feed still reaches the
    target; the clearance at and between the logged poses keeps margin - 0.2 mm, fixture on
    or off. Tremor and twitches keep the fixture's violation under 0.5 mm."""
    tc, teleop, exact = site
    start, target = tc.X_WE(tc.q_start)[:3, 3], tc.X_WTarget[:3, 3]
    motion = adversarial_motion(kind, start, target, Directions.of_case(tc.X_WTarget,
                                                                        tc.X_WCenter), seed=seed)
    r = A.run_one(teleop if fixture else build_teleop(tc, vf_enabled=False), tc, motion, exact)
    _check(r, fixture=fixture)
    if kind in A.FAULT_KINDS:
        assert r["faults"] >= 1
        assert r["recovery_tcp_step"] <= STEP_LIMIT
        assert r["hold_motion"] < 3 * 0.0005  # the steps in flight at the fault, no more
        assert r["reached_target"]
    else:
        assert r["faults"] == 0


def test_the_largest_jump_into_the_mouth_is_a_fault(site):
    """1000 mm in one sample along Center's diagonal into the mouth, towards the jaw and the
    right cheek (-x -y -z), with the fixture off: held, logged, no motion."""
    tc, _, exact = site
    start, target = tc.X_WE(tc.q_start)[:3, 3], tc.X_WTarget[:3, 3]
    D, names = jump_directions(Directions.of_case(tc.X_WTarget, tc.X_WCenter))
    d = D[names.index("-x-y-z")]
    motion = handle_jump(start, target, np.random.default_rng(7), d, 1.0)
    r = A.run_one(build_teleop(tc, vf_enabled=False), tc, motion, exact)
    _check(r, fixture=False)
    assert r["faults"] == 1 and r["fault_samples"] == 1
    assert r["reached_target"]


def test_normal_feed_reaches_the_target_safely(site):
    tc, teleop, exact = site
    start, target = tc.X_WE(tc.q_start)[:3, 3], tc.X_WTarget[:3, 3]
    r = A.run_one(teleop, tc, feeding_runs(start, target, runs=1, seed=5)[0], exact)
    _check(r)
    assert r["reached_target"]


def test_without_the_safety_layer_the_push_enters_the_tissue(site):
    """The check can fail: with neither fixture nor supervisor the cheek push goes into tissue
    (the exact reference says so) and the estimator's alarm fires. The screened reference the
    runs use (scan_reference.screened: FCL only where the smallest can be) on this run, in and
    out of the tissue, against FCL at every logged pose: the same smallest and where it is, the
    same sampled minimum, a certified bound at or below it; every pose left unmeasured is below
    FCL there and at or above the smallest; fewer than half the poses measured."""
    tc, _, exact = site
    start, target = tc.X_WE(tc.q_start)[:3, 3], tc.X_WTarget[:3, 3]
    motion = adversarial_motion("cheek_left", start, target,
                                Directions.of_case(tc.X_WTarget, tc.X_WCenter), seed=0)
    free = build_teleop(tc, vf_enabled=False, supervisor_enabled=False)
    run = simulate(free, motion.duration + FINISH_SECONDS, motion=motion)
    assert run.alarm.any()
    full = swept_clearance(tc, exact, run.q)
    sc = swept_clearance(tc, exact, run.q, screen=True)
    assert full.at_poses.min() < 0.0
    assert sc.at_poses.min() == full.at_poses.min()
    assert np.argmin(sc.at_poses) == np.argmin(full.at_poses)
    assert sc.sampled == full.sampled and sc.bound <= full.sampled
    skipped = ~sc.exact_at
    assert np.all(sc.at_poses[sc.exact_at] == full.at_poses[sc.exact_at])
    assert np.all(sc.at_poses[skipped] <= full.at_poses[skipped])
    assert np.all(sc.at_poses[skipped] >= full.at_poses.min())
    assert skipped.any() and sc.exact_at.mean() < 0.5, sc.exact_at.mean()


def test_the_supervisor_alone_keeps_the_margin_against_the_exact_anatomy(site):
    """Fixture off: the barrier on the sound FPSM clearance stops the push at h = 1 mm, and the
    exact clearance stays above margin - 0.2 mm."""
    tc, _, exact = site
    start, target = tc.X_WE(tc.q_start)[:3, 3], tc.X_WTarget[:3, 3]
    motion = adversarial_motion("jaw", start, target,
                                Directions.of_case(tc.X_WTarget, tc.X_WCenter), seed=2)
    r = A.run_one(build_teleop(tc, vf_enabled=False), tc, motion, exact)
    assert r["supervisor_active_share"] > 0.0
    assert r["min_barrier"] >= MARGIN - 1e-6
    assert r["min_exact_clearance"] >= MARGIN - A.MARGIN_SLACK


def test_exact_reference_by_hand():
    """FCL on a box room: the tool's rod (radius 6 mm) 10 mm from a wall has clearance 4 mm."""
    import trimesh

    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    ex = A.ExactClearance(box.vertices, box.faces,
                          Instrument.paper(rod_radius=0.006, implant_length=0.031, rod_length=0.04))
    X = np.eye(4)
    X[:3, :3] = np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # Tool x -> +z, Tool z -> -x
    X[:3, 3] = [0.0, 0.034, 0.0]  # the rod's axis at y = 34 mm, the box's wall at y = 50 mm
    d = ex(X[None])[0]
    # the rod (radius 6) 10 mm from the wall y = 50; the implant axis from [r,0,0] to
    # [r,0,-d12] in T runs to x = +31 mm (19 mm from x = 50); the head sphere: 10 mm; the rod's
    # end cap reaches z = 6 + 40 + 6 = 52 mm: through the top face (z = 50) by 2 mm
    assert d == pytest.approx(-0.002, abs=2e-4)
    X[:3, 3] = [0.0, 0.034, -0.02]  # 20 mm lower: rod top at z = 32 mm: 12 mm below the top
    assert ex(X[None])[0] == pytest.approx(0.010, abs=1e-6)  # the rod's side, 10 mm


@pytest.mark.slow
def test_the_54_run_study():
    res = A.study(seeds=4, normal=3, progress=None)
    s = res["summary"]["all"]
    assert s["runs"] >= 50
    assert s["below_zero"] == 0 and s["below_margin_slack"] == 0
    assert s["violation_over"] == 0
    assert s["unfaulted"] == 0 and s["recovery_jumps"] == 0
    normal = res["summary"]["normal"]
    assert normal["reached"] == normal["runs"]


@pytest.mark.slow
def test_the_54_run_study_with_the_supervisor_alone():
    s = A.study(seeds=4, normal=3, fixture=False, progress=None)["summary"]["all"]
    assert s["below_zero"] == 0 and s["below_margin_slack"] == 0
    assert s["unfaulted"] == 0 and s["recovery_jumps"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("fixture", [True, False])
def test_the_full_jump_sweep(fixture):
    """Every jump size (50-1000 mm) x 14 directions x held/out and back x both sites."""
    res = A.jump_study(fixture=fixture, progress=None)
    s = res["summary"]["all"]
    assert s["runs"] == 2 * 2 * 5 * 14
    assert s["below_zero"] == 0 and s["below_margin_slack"] == 0
    assert s["unfaulted"] == 0 and s["recovery_jumps"] == 0
    if fixture:
        assert s["violation_over"] == 0


@pytest.mark.sweep
def test_the_plan_folder_holds_the_cases_the_pipeline_plans(demo_plan):
    """The tests above read the default case's plan folder; the studies plan the case
    themselves (default_case_sites): both give the same teleop cases and the same scan."""
    planned, mesh = A.default_case_sites()
    read, mesh_read = plan_sites(demo_plan)
    np.testing.assert_array_equal(mesh_read.vertices, mesh.vertices)
    np.testing.assert_array_equal(mesh_read.faces, mesh.faces)
    assert len(planned) == len(read) == 2
    for a, b in zip(planned, read, strict=True):
        assert (a.scenario, a.label, a.limits) == (b.scenario, b.label, b.limits)
        assert (a.rod_radius, a.implant_length) == (b.rod_radius, b.implant_length)
        for name in ("X_WBase", "q_start", "X_WCenter", "X_WTarget"):
            np.testing.assert_allclose(getattr(b, name), getattr(a, name), rtol=0, atol=1e-12,
                                       err_msg=name)
        assert b.vf.to_dict() == a.vf.to_dict()
        np.testing.assert_array_equal(b.fpsm.rho, a.fpsm.rho)
        np.testing.assert_array_equal(b.fpsm.slice_z, a.fpsm.slice_z)
        np.testing.assert_array_equal(b.fpsm.X_WC, a.fpsm.X_WC)
