"""The head-turn sweep of the awake-patient study (analyses.studies.head_turn): the swept bound
under a moving head against dense FCL samples, a few turns of the grid by default, the whole
grid under the ``sweep`` mark, and the command line's checks."""

import json

import numpy as np
import pytest

from implantplan.analyses.cli import main
from implantplan.analyses.studies import head_turn as H
from implantplan.analyses.studies.scan_reference import (
    exact_for,
    plan_sites,
    segment_paths,
    swept_clearance,
    tool_poses,
)
from implantplan.systems import actuator
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.teleop.tracker import TrackerParams


class _Arm:
    X_FE = actuator.X_FT()


@pytest.mark.parametrize("scale", [1e-3, 1e-2, 1e-1, 0.5])
def test_segment_paths_bound_every_tool_point_path(scale):
    """S of a joint-linear segment is at least the path length of points within ``reach`` of
    the TCP, sampled densely (200 random segments per joint-step scale), and the bound through
    the TCP's velocity is tight for small steps (within 10% at 1 mrad steps, median)."""
    rng = np.random.default_rng(7)
    reach = 0.2
    ratios = []
    for _ in range(200):
        q0 = rng.uniform(-3.0, 3.0, 6)
        dq = scale * rng.normal(size=6)
        S = segment_paths(_Arm, np.stack([q0, q0 + dq]), reach)[0]
        pts = rng.normal(size=(16, 3))
        pts *= reach / np.linalg.norm(pts, axis=1)[:, None]
        X = kin.fk(q0 + np.linspace(0.0, 1.0, 801)[:, None] * dq, _Arm.X_FE)
        x = np.einsum("nij,kj->nki", X[:, :3, :3], pts) + X[:, None, :3, 3]
        ratios.append(np.linalg.norm(np.diff(x, axis=0), axis=2).sum(axis=0).max() / S)
    assert max(ratios) <= 1.0
    if scale == 1e-3:
        assert np.median(ratios) > 0.9


@pytest.fixture(scope="module")
def sites(demo_plan):
    cases, mesh = plan_sites(demo_plan)
    return cases, mesh, [exact_for(tc, mesh) for tc in cases]


def test_swept_clearance_under_a_turning_head_bounds_dense_samples(sites):
    """The arm still at its feeding target while the head turns 1 deg at 60 deg/s (the tool
    stays free; a wider turn would carry the scan into it): the
    certified bound between the logged poses (every 5 ms) is at or below FCL at 40 poses per
    period, the logged clearance is the clearance in the moving head, and the head's share of S
    is what makes it hold (the arm alone would give S = 0)."""
    cases, _, exact = sites
    tc, ex = cases[0], exact[0]
    motion = H.motion_of(tc, 0)
    turn = H.Turn(0, np.deg2rad(1.0), np.deg2rad(60.0), 1.0, "mid")
    hm = H.head_of(tc, turn, motion)
    on = hm.params["onset_s"]
    t = on + np.arange(0.0, hm.params["seconds"], 0.005)
    res = kin.ik(np.linalg.inv(tc.X_WBase) @ tc.X_WE_target, limits=tc.limits, X_FT=tc.X_FE)
    sol = res.q[res.valid]
    q = sol[np.argmin(np.abs(sol - tc.q_start).sum(axis=1))]
    q_target = np.repeat(q[None], t.size, axis=0)
    swept = swept_clearance(tc, ex, q_target, head=hm, t=t)
    np.testing.assert_allclose(swept.at_poses, ex(tool_poses(tc, q_target, head=hm, t=t)))
    dense_t = on + np.arange(0.0, t[-1] - on, 0.005 / 40)
    dense = ex(tool_poses(tc, np.repeat(q_target[:1], dense_t.size, axis=0), head=hm,
                          t=dense_t))
    assert swept.bound <= dense.min() + 1e-9
    assert swept.bound <= swept.sampled <= swept.at_poses.min()
    assert swept.sampled_segments > 0
    assert np.all(swept.path > 0)  # the head moves the scan past the still tool
    assert dense.min() > 0.0 and np.ptp(swept.at_poses) > 5e-4  # free, and the turn matters
    # screened (FCL only where the smallest can be): the same smallest, where it is, and the
    # bounds it keeps elsewhere are below FCL's values there and not below the smallest
    sc = swept_clearance(tc, ex, q_target, head=hm, t=t, screen=True)
    assert sc.at_poses.min() == swept.at_poses.min()
    assert np.argmin(sc.at_poses) == np.argmin(swept.at_poses)
    assert sc.sampled == swept.sampled and sc.bound <= dense.min() + 1e-9
    skipped = ~sc.exact_at
    assert np.all(sc.at_poses[sc.exact_at] == swept.at_poses[sc.exact_at])
    assert np.all(sc.at_poses[skipped] <= swept.at_poses[skipped])
    assert np.all(sc.at_poses[skipped] >= swept.at_poses.min())


def _check(r, margin):
    """The acceptance at every logged pose of a run (module notes of head_turn)."""
    assert r["exact_clearance_min"] >= margin - H.MARGIN_SLACK, r
    assert r["exact_between_bound"] >= margin - H.MARGIN_SLACK, r
    assert r["exact_between_bound"] <= r["exact_between_sampled"] <= r["exact_clearance_min"]
    assert r["violation_max"] <= H.MAX_VIOLATION, r
    assert r["arm_jumps"] == 0 and r["tcp_step_max"] <= r["step_limit"], r


@pytest.mark.parametrize("flags, name", [
    (["--turn-amplitudes-deg", "0"], "--turn-amplitudes-deg"),
    (["--turn-amplitudes-deg", "10,x"], "--turn-amplitudes-deg"),
    (["--turn-speeds-deg-s", "500"], "--turn-speeds-deg-s"),
    (["--turn-speeds-deg-s", ",".join(["30"] * 11)], "--turn-speeds-deg-s"),
    (["--turn-onsets", "noon"], "--turn-onsets"),
    (["--workers", "3"], "--workers"),
    (["--case", "cylinder"], "--turn-sweep"),
    (["--tracker-rate-hz", "90"], "--tracker-rate-hz"),
])
def test_turn_sweep_flags_are_checked_before_any_work(tmp_path, capsys, flags, name):
    out = tmp_path / "x"
    code = main(["analyze", "head-motion", "--turn-sweep", *flags, "--out", str(out), "--quiet"])
    assert code == 2
    assert name in capsys.readouterr().err
    assert not out.exists()


# the default run: the fastest turn at its widest, one each way, mid-feed and late
# one turn per site; the default run keeps the shorter one (site 46), CI runs both
SMALL = [pytest.param(H.Turn(0, np.deg2rad(15.0), np.deg2rad(60.0), 1.0, "mid"),
                      id="site0-15 deg 60 deg/s + mid", marks=pytest.mark.sweep),
         pytest.param(H.Turn(1, np.deg2rad(15.0), np.deg2rad(60.0), -1.0, "late"),
                      id="site1-15 deg 60 deg/s - late")]


# the default camera carries a moving head at its rate (systems/teleop/tracker.py, Moving head):
# before that its prediction lagged a fast turn and corrected it by a jump at every camera
# sample, arm jumps at 45-60 deg/s (docs/measurements.md, the awake patient: the head-turn
# sweep); a correction the joints cannot make in one control step is taken over the next by the
# tracked head frame (systems/teleop/tracked_frame.py); the smoothed camera
# (TrackerParams.smooth) passes them too but loses clearance in a startle, so it is not the
# default. Both run in the sweep group (CI)
CAMERAS = [pytest.param(TrackerParams(), id="default-camera", marks=pytest.mark.sweep),
           pytest.param(TrackerParams(smooth=True), id="smoothed-camera",
                        marks=pytest.mark.sweep)]  # not the default camera (it fails a startle)


@pytest.mark.parametrize("camera", CAMERAS)
@pytest.mark.parametrize("turn", SMALL)
def test_a_fast_head_turn_meets_the_acceptance(sites, turn, camera):
    """Exact clearance >= margin - 0.2 mm at every logged pose and over the swept motion,
    fixture violation <= 0.5 mm and no arm jump; the guard stops the feed and backs out, and
    differential IK never reports stuck."""
    cases, _, exact = sites
    r = H.run_turn(cases[turn.site], exact[turn.site], turn, tracker=camera)
    assert r["trigger_time"] >= 0 and r["backed_out"], r
    assert r["diffik_stuck"] == 0, r
    _check(r, r["margin"])


def test_a_camera_correction_the_joints_cannot_follow_at_once_is_no_arm_jump(sites):
    """The default camera, site 46, 15 deg at 30 deg/s +, early: during the guard's back-out a
    camera sample's correction turns the predicted head faster than a wrist joint can follow in
    one control step (docs/measurements.md, the head-turn sweep); the tracked head frame takes it
    over the next step (systems/teleop/tracked_frame.py), so the arm makes every step of its
    command there: no arm jump, and the run meets the acceptance."""
    cases, _, exact = sites
    turn = H.Turn(1, np.deg2rad(15.0), np.deg2rad(30.0), 1.0, "early")
    r = H.run_turn(cases[1], exact[1], turn)
    assert r["trigger_time"] >= 0 and r["backed_out"] and r["diffik_stuck"] == 0, r
    _check(r, r["margin"])


@pytest.mark.sweep
@pytest.mark.parametrize("camera", [pytest.param([], id="default-camera"),
                                    pytest.param(["--tracker-smooth"], id="smoothed-camera")])
def test_the_full_turn_sweep_meets_the_acceptance(demo_plan, tmp_path, capsys, camera):
    """The whole grid (2 amplitudes x 3 peak speeds x 2 directions x 3 onsets x 2 sites, the
    command as docs/commands.md gives it), with the default camera and the smoothed one: every
    run meets the acceptance at every logged pose; the JSON, the table, the report and the worst
    run's figure are written. (The default camera's history: 45 of 72 failed before the
    tracker's moving-head rule, 1 before the tracked head frame's step bound;
    docs/measurements.md.)"""
    out = tmp_path / "turns"
    code = main(["analyze", "head-motion", "--turn-sweep", "--plan", str(demo_plan),
                 *camera, "--workers", "2", "--out", str(out), "--quiet"])
    printed = capsys.readouterr().out
    data = json.loads((out / "head_motion.json").read_text())
    res = data["turn_sweep"]
    assert len(res["runs"]) == 72 and len(res["table"]) == 12
    assert (out / "head_turn_worst.png").is_file() and "head_turn_worst.png" in (
        out / "report.html").read_text()
    assert "every head turn meets the acceptance" in printed
    for r in res["runs"]:
        _check(r, res["margin"])
        if r["trigger_time"] >= 0:
            assert r["backed_out"], r
        assert r["diffik_stuck"] == 0, r
    assert res["passed"] and data["passed"] and code == 0
