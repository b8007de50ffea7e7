"""The tracked head frame's step (systems.teleop.tracked_frame): the tracker's pose whenever the
arm can follow it in one control step, otherwise the largest share of the step it can."""

import numpy as np
import pytest

from implantplan.systems import actuator
from implantplan.systems.frames import invert, rotation_angle, rotation_vector, rotations
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.teleop.tracked_frame import (
    HEADROOM,
    frame_step,
    pose_difference,
    screw_share,
)

DT = 0.005
QDOT_MAX = np.array([np.pi, np.pi, 2.565634, np.pi, np.pi, np.pi])  # the AUBO-i10's (URDF)
Q = np.array([0.3, 0.2, 1.5, 0.4, 1.2, 0.1])  # an arm pose away from singularities
X_FE = actuator.X_FT()


def _arm():
    """(X_now, J_W) of the arm at Q, base at World."""
    return kin.fk(Q, X_FE), kin.jacobian_space(Q, X_FE)


def _turn(angle_deg, axis, point):
    """A head step: ``angle_deg`` about ``axis`` through ``point`` (World)."""
    R = rotations((np.deg2rad(angle_deg) * np.asarray(axis) / np.linalg.norm(axis))[None])[0]
    H = np.eye(4)
    H[:3, :3], H[:3, 3] = R, point - R @ point
    return H


def _rates(H, X_des, X_now, J):
    return np.linalg.solve(J, pose_difference(X_now, H @ X_des) / DT)


def test_pose_difference_is_the_first_order_step_of_the_joint_rates():
    """q + J^-1 V dt reaches the pose V was taken towards (to first order: differential IK's own
    linearization), with V = pose_difference / dt."""
    X_now, J = _arm()
    target = _turn(0.05, [0.3, -1.0, 0.2], X_now[:3, 3] + [0.0, 0.0, 0.1]) @ X_now
    target[:3, 3] += [1e-4, -5e-5, 2e-5]
    qd = np.linalg.solve(J, pose_difference(X_now, target) / DT)
    reached = kin.fk(Q + qd * DT, X_FE)
    err = pose_difference(reached, target)
    step = pose_difference(X_now, target)
    assert np.linalg.norm(err[3:]) < 0.02 * np.linalg.norm(step[3:])
    assert np.linalg.norm(err[:3]) < 0.02 * np.linalg.norm(step[:3])


def test_a_step_the_arm_can_make_is_the_trackers_pose():
    X_now, J = _arm()
    X_des = X_now.copy()
    X_des[:3, 3] += [1e-4, 0.0, 0.0]  # the supervisor's step: 0.1 mm
    goal = _turn(0.15, [0.0, 0.0, 1.0], X_now[:3, 3] - [0.0, 0.1, 0.0])  # a 30 deg/s head
    H, s = frame_step(np.eye(4), goal, X_des, X_now, J, QDOT_MAX, DT)
    assert s == 1.0 and np.array_equal(H, goal)


@pytest.mark.parametrize("angle_deg", [1.0, 3.0])
def test_a_jump_is_cut_to_the_share_the_joints_can_make(angle_deg):
    """A camera sample's correction of ``angle_deg`` in one control step (200-600 deg/s): the
    frame goes the largest share of the step (the same screw: rotation about the desired TCP)
    for which the joint rates stay within HEADROOM x their limits; the next steps go on towards
    the tracker's pose and reach it."""
    X_now, J = _arm()
    X_des = X_now.copy()
    goal = _turn(angle_deg, [0.2, 0.1, 1.0], X_now[:3, 3] - [0.0, 0.1, 0.02])
    assert np.any(np.abs(_rates(goal, X_des, X_now, J)) > QDOT_MAX)  # the arm cannot
    H, s = frame_step(np.eye(4), goal, X_des, X_now, J, QDOT_MAX, DT)
    assert 0.0 < s < 1.0
    r = np.abs(_rates(H, X_des, X_now, J))
    assert np.all(r <= HEADROOM * QDOT_MAX + 1e-9) and r.max() / (HEADROOM * QDOT_MAX).max() > 0.8
    np.testing.assert_allclose(rotation_vector(H[:3, :3]), s * rotation_vector(goal[:3, :3]),
                               atol=1e-12)
    p = X_des[:3, 3]  # the desired TCP moves along the goal's displacement of it
    np.testing.assert_allclose((H @ np.r_[p, 1.0])[:3] - p,
                               s * ((goal @ np.r_[p, 1.0])[:3] - p), atol=1e-12)
    # the arm follows (its joints move by the rates), the frame goes on, and reaches the goal
    q = Q.copy()
    for _ in range(20):
        X_now, J = kin.fk(q, X_FE), kin.jacobian_space(q, X_FE)
        H, s = frame_step(H, goal, X_des, X_now, J, QDOT_MAX, DT)
        q = q + _rates(H, X_des, X_now, J) * DT
        if s == 1.0:
            break
    assert s == 1.0 and np.array_equal(H, goal)


def test_the_frame_holds_when_the_command_alone_outruns_the_joints():
    X_now, J = _arm()
    X_des = X_now.copy()
    X_des[:3, 3] += [0.02, 0.0, 0.0]  # 20 mm in one step (4 m/s): no share is feasible
    goal = _turn(1.0, [0.0, 0.0, 1.0], X_now[:3, 3])
    H_prev = _turn(0.1, [1.0, 0.0, 0.0], X_now[:3, 3])
    H, s = frame_step(H_prev, goal, X_des, X_now, J, QDOT_MAX, DT)
    assert s == 0.0 and np.array_equal(H, H_prev)


def test_screw_share_ends_at_the_goal_and_rotates_about_the_point():
    goal = _turn(2.0, [0.0, 1.0, 0.0], np.array([0.1, 0.0, 0.3]))
    goal[:3, 3] += [1e-3, 0.0, -2e-3]
    H_prev = _turn(0.5, [1.0, 0.0, 0.0], np.zeros(3))
    p = np.array([0.05, 0.02, 0.2])
    np.testing.assert_allclose(screw_share(H_prev, goal, p, 1.0), goal, atol=1e-12)
    np.testing.assert_allclose(screw_share(H_prev, goal, p, 0.0), H_prev, atol=1e-12)
    half = screw_share(H_prev, goal, p, 0.5)
    D = goal @ invert(H_prev)
    assert rotation_angle((half @ invert(H_prev))[:3, :3][None])[0] == pytest.approx(
        0.5 * rotation_angle(D[:3, :3][None])[0])


def test_pose_difference_is_the_rotation_vector_and_the_translation():
    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b = np.eye(4), np.eye(4)
        a[:3, :3] = rotations(rng.normal(size=(1, 3)))[0]
        w = rng.normal(size=3) * rng.uniform(0.0, 3.0) / np.sqrt(3.0)
        b[:3, :3] = rotations(w[None])[0] @ a[:3, :3]
        a[:3, 3], b[:3, 3] = rng.normal(size=3), rng.normal(size=3)
        d = pose_difference(a, b)
        np.testing.assert_allclose(d[:3], rotation_vector(b[:3, :3] @ a[:3, :3].T), atol=1e-9)
        np.testing.assert_allclose(d[3:], b[:3, 3] - a[:3, 3])
    assert np.array_equal(pose_difference(a, a), np.zeros(6))
