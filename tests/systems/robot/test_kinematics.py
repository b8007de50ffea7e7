"""Closed-form kinematics of the AUBO-i10 (systems.robot.kinematics)."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from implantplan.systems.errors import InputError
from implantplan.systems.frames import rot_z, transform
from implantplan.systems.robot import kinematics as k


def random_q(n, seed=0, limit=np.pi):
    return np.random.default_rng(seed).uniform(-limit, limit, (n, 6))


def test_flange_at_home_matches_the_published_value():
    X = k.fk(np.zeros(6))
    np.testing.assert_allclose(X[:3, 3], [0.0, -0.2953, 1.5132], atol=1e-12)
    # flange +z points along base -y at home (J6 axis horizontal), by the joint table
    np.testing.assert_allclose(X[:3, 2], [0.0, -1.0, 0.0], atol=1e-12)


def test_fk_matches_the_dh_model():
    """The URDF chain and the standard DH model of DESIGN.md section 8 are the same arm."""
    q = random_q(200, seed=3)
    th = np.stack([q[:, 0], q[:, 1] - np.pi / 2, -q[:, 2], q[:, 3] - np.pi / 2, q[:, 4],
                   q[:, 5] + np.pi], axis=-1)
    d = [k.DH_D1, 0, 0, k.DH_D4, k.DH_D5, k.DH_D6]
    a = [0, k.DH_A2, k.DH_A3, 0, 0, 0]
    alpha = [np.pi / 2, 0, 0, np.pi / 2, -np.pi / 2, 0]
    X = np.broadcast_to(np.eye(4), (200, 4, 4))
    for i in range(6):
        ct, st_ = np.cos(th[:, i]), np.sin(th[:, i])
        ca, sa = np.cos(alpha[i]), np.sin(alpha[i])
        A = np.zeros((200, 4, 4))
        A[:, 0] = np.stack([ct, -st_ * ca, st_ * sa, a[i] * ct], -1)
        A[:, 1] = np.stack([st_, ct * ca, -ct * sa, a[i] * st_], -1)
        A[:, 2, 1:] = [sa, ca, d[i]]
        A[:, 3, 3] = 1
        X = X @ A
    np.testing.assert_allclose(k.fk(q), X, atol=1e-12)


def test_jacobian_matches_finite_differences():
    q = random_q(20, seed=1)
    X_FT = transform(rot_z(0.3), [0.01, 0.02, 0.15])
    J = k.jacobian_space(q, X_FT)
    h = 1e-6
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        Xp, Xm = k.fk(q + dq, X_FT), k.fk(q - dq, X_FT)
        v = (Xp[:, :3, 3] - Xm[:, :3, 3]) / (2 * h)
        dR = (Xp[:, :3, :3] - Xm[:, :3, :3]) / (2 * h) @ np.swapaxes(k.fk(q, X_FT)[:, :3, :3], 1, 2)
        w = np.stack([dR[:, 2, 1], dR[:, 0, 2], dR[:, 1, 0]], -1)
        np.testing.assert_allclose(J[:, 3:, i], v, atol=1e-8)
        np.testing.assert_allclose(J[:, :3, i], w, atol=1e-8)
    Jb = k.jacobian_body(q, X_FT)
    R = k.fk(q, X_FT)[:, :3, :3]
    np.testing.assert_allclose(R @ Jb[:, 3:], J[:, 3:], atol=1e-12)


def test_ik_round_trip_10k():
    q = random_q(10_000, seed=7, limit=np.deg2rad(175))
    X = k.fk(q)
    r = k.ik(X)
    dp, dR = k.pose_error(k.fk(r.q), X[:, None])
    assert dp[r.valid].max() < 1e-9 and dR[r.valid].max() < 1e-9
    # away from singularities (smallest singular value of J > 1e-3) the generating q is among the
    # valid solutions
    regular = np.linalg.svd(k.jacobian_space(q), compute_uv=False)[:, -1] > 1e-3
    found = np.any((k.wrapped_distance(r.q, q[:, None]) < 1e-7) & r.valid, axis=1)
    assert regular.mean() > 0.99
    assert found[regular].all()


def test_ik_with_tool_frame_round_trip():
    X_FT = transform(rot_z(0.5) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]), [0.0, 0.03, 0.2])
    q = random_q(500, seed=11, limit=np.deg2rad(170))
    X = k.fk(q, X_FT)
    r = k.ik(X, X_FT=X_FT)
    dp, dR = k.pose_error(k.fk(r.q, X_FT), X[:, None])
    assert dp[r.valid].max() < 1e-9 and dR[r.valid].max() < 1e-9
    assert np.any((k.wrapped_distance(r.q, q[:, None]) < 1e-7) & r.valid, axis=1).all()


def test_branch_index_is_stable_along_a_path():
    """Following a smooth path, each branch's solution moves continuously."""
    q0 = np.array([0.3, -0.4, 1.2, 0.5, 1.0, 0.2])
    s = np.linspace(0, 1, 200)[:, None]
    q = q0 + s * np.array([0.2, 0.1, -0.3, 0.2, 0.3, 0.1])
    r = k.ik(k.fk(q), limits="360")
    kept = r.valid.all(axis=0)  # branches that exist along the whole path
    assert kept.sum() >= 4
    steps = k.wrapped_distance(r.q[1:, kept], r.q[:-1, kept])
    assert steps.max() < 0.05
    # and the generating solution keeps its branch index all along
    branch = np.argmin(k.wrapped_distance(r.q, q[:, None]), axis=1)
    assert np.all(branch == branch[0])


def test_out_of_reach_is_empty_with_reason():
    X = transform(np.eye(3), [3.0, 0.0, 0.5])  # 3 m away: beyond the 1.25 m reach
    r = k.ik(X)
    assert not r.valid.any()
    assert set(r.reasons().ravel()) <= {k.REASONS[k.REASON_ELBOW], k.REASONS[k.REASON_WRIST]}
    # wrist centre on the shoulder axis: inside the d4 cylinder
    X = transform(np.eye(3), [0.0, 0.0, 0.8 + k.DH_D6])
    r = k.ik(X)
    assert not r.valid.any() and (r.reason == k.REASON_SHOULDER).all()
    assert np.isfinite(r.q).all()


def test_wrist_singularity_gives_finite_valid_solutions():
    q = np.array([0.2, -0.5, 1.0, 0.3, 0.0, 0.4])  # q5 = 0: wrist singular
    X = k.fk(q)
    r = k.ik(X)
    assert np.isfinite(r.q).all()
    assert r.singular[r.valid].any()
    dp, dR = k.pose_error(k.fk(r.q), X)
    assert dp[r.valid].max() < 1e-9 and dR[r.valid].max() < 1e-9


def test_joint_limits_175_vs_360():
    q = np.array([3.1, -0.5, 1.0, 0.3, 0.7, 0.4])  # q1 = 177.6 deg
    X = k.fk(q)
    r175, r360 = k.ik(X, limits="175"), k.ik(X, limits="360")
    same = k.wrapped_distance(r175.q, q) < 1e-7
    assert same.any() and not r175.valid[same].any()
    assert (r175.reason[same] == k.REASON_LIMITS).all()
    assert ((k.wrapped_distance(r360.q, q) < 1e-7) & r360.valid).any()
    copies, mask = k.joint_copies(q, limits="360")
    assert mask.sum() == 64  # every joint has two copies within ±360 deg
    assert np.allclose(k.fk(copies[mask]), X, atol=1e-12)
    assert k.joint_copies(q, limits="175")[1].sum() == 0


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((3, 3)), "shape"),
        (np.full((4, 4), np.nan), "finite"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "proper rotation"),
        (np.diag([2.0, 1.0, 1.0, 1.0]), "proper rotation"),
    ],
)
def test_malformed_poses_are_clear_errors(bad, match):
    with pytest.raises(InputError, match=match):
        k.ik(bad)


def test_malformed_joints_are_clear_errors():
    with pytest.raises(InputError, match="q"):
        k.fk(np.zeros(5))
    with pytest.raises(InputError, match="finite"):
        k.fk(np.array([0, 0, np.nan, 0, 0, 0]))
    with pytest.raises(ValueError, match="limits"):
        k.ik(np.eye(4), limits="180")


@settings(max_examples=200, deadline=None)
@given(arrays(float, 6, elements=st.floats(-3.05, 3.05)))
def test_property_fk_ik_round_trip(q):
    # Not asserted: the double singularity, elbow fully stretched (|sin q3| < 1e-6) with the wrist
    # within 1e-6 rad of singular but not exactly singular. The noise of theta6 there (about
    # 1e-16 / |sin q5|) moves the wrist centre beyond the reach by more than the 1e-9 tolerance.
    assume(not (abs(np.sin(q[2])) < 1e-6 and 0 < abs(np.sin(q[4])) < 1e-6))
    X = k.fk(q)
    r = k.ik(X)
    dp, dR = k.pose_error(k.fk(r.q), X)
    assert r.valid.any()
    assert dp[r.valid].max() < 1e-9 and dR[r.valid].max() < 1e-9
    if np.linalg.svd(k.jacobian_space(q), compute_uv=False)[-1] > 1e-3:  # away from singularities
        assert ((k.wrapped_distance(r.q, q) < 1e-7) & r.valid).any()


@settings(max_examples=100, deadline=None)
@given(arrays(float, 6, elements=st.floats(-3.0, 3.0)))
def test_property_jacobian_rank_matches_singularity(q):
    sv = np.linalg.svd(k.jacobian_space(q), compute_uv=False)
    assert sv[0] > 0.1  # never the zero map
    assert np.all(np.isfinite(sv))


def test_singular_wrist_with_q6_zero_beyond_a_limit_is_solved_with_another_theta6():
    """At q5 = 0 joints 4 and 6 are aligned: q4 + q6 is what the pose fixes (with q2, q3). The
    default rule q6 = 0 would need q4 = -3.125 rad, beyond -175 deg; a reachable pose must still
    get a solution within the limits (found by hypothesis: q = (0, 0, 0, -0.375, 0, -2.75))."""
    q = np.array([0.0, 0.0, 0.0, -0.375, 0.0, -2.75])
    X = k.fk(q)
    r = k.ik(X)
    assert r.valid.any() and r.singular[r.valid].all()
    dp, dR = k.pose_error(k.fk(r.q), X)
    assert dp[r.valid].max() < 1e-9 and dR[r.valid].max() < 1e-9
    lo, hi = k.joint_limits("175")
    assert np.all((r.q[r.valid] >= lo) & (r.q[r.valid] <= hi))
