"""Joint-limit headroom (DESIGN.md section 7): MOPRP drops a branch that comes closer to a
joint limit than the scenario's headroom along the feed or under the head motions."""

import dataclasses

import numpy as np

from implantplan.systems import actuator
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp


def test_joint_headroom_is_the_distance_to_the_nearer_limit():
    q = np.deg2rad([[170.0, -170.0, 0.0, 5.0, -100.0, 180.0]])
    np.testing.assert_allclose(np.rad2deg(kin.joint_headroom(q)),
                               [[5.0, 5.0, 175.0, 170.0, 75.0, -5.0]], atol=1e-12)


def test_head_displacements_are_the_identity_and_twelve_moves_of_the_envelope():
    sc = moprp.load_scenario("lying", X_FT=actuator.X_FT())
    D = moprp.head_displacements(sc)
    assert D.shape == (13, 4, 4)
    np.testing.assert_array_equal(D[0], np.eye(4))
    moves = np.linalg.norm(D[1:, :3, 3], axis=1)
    angles = np.arccos(np.clip((np.trace(D[1:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert np.sum(np.isclose(moves, 0.005)) == 6 and np.sum(np.isclose(angles, np.deg2rad(1))) == 6
    none = moprp.head_displacements(dataclasses.replace(sc, head_translation=0.0,
                                                        head_rotation=0.0))
    assert none.shape == (1, 4, 4)


def test_moprp_keeps_only_branches_with_the_headroom_asked_for():
    sc = moprp.load_scenario("lying", X_FT=actuator.X_FT())
    rng = np.random.default_rng(3)
    X = sc.lower + rng.random((300, 3)) * (sc.upper - sc.lower)
    model = moprp.collision_model(sc)
    loose = moprp.evaluate_bases(X, dataclasses.replace(sc, joint_headroom=0.0), rng,
                                 model=model)
    ev = moprp.evaluate_bases(X, sc, rng, model=model)
    assert ev.feasible.sum() > 0 and ev.feasible.sum() < loose.feasible.sum()
    assert np.any(ev.reason == moprp.DROP_HEADROOM)
    assert np.all(ev.valid <= loose.valid)  # headroom only ever removes branches
    # every kept base: its branch, re-solved along the feed (every sample) and the displaced
    # feeds (start, middle, end), keeps the headroom on every joint (independent of
    # evaluate_bases' own bookkeeping; the confirmation checks the fine paths, see
    # tests/analyses/test_headroom_plan.py)
    for p in np.flatnonzero(ev.feasible)[:20]:
        b = int(ev.branch[p])
        worst = np.inf
        for k, D in enumerate(moprp.head_displacements(sc)):
            n = sc.feed_samples if k == 0 else moprp.HEAD_FEED_SAMPLES
            Xf = moprp.feed_poses(X[p], sc.feed_length, n, D)
            r = kin.ik(Xf, limits=sc.limits, X_FT=sc.X_FT)
            assert np.all(r.valid[:, b])
            worst = min(worst, kin.joint_headroom(r.q[:, b]).min())
        assert worst >= sc.joint_headroom - 1e-12
        np.testing.assert_allclose(ev.headroom[p].min(), worst, atol=1e-12)
