"""Drake multi-start IK against the closed form (branch counts on a sample of poses)."""

from __future__ import annotations

import numpy as np
import pytest

from implantplan import models
from implantplan.diagrams import actuator_urdf as tools
from implantplan.diagrams.ik_drake import DrakeIk, ik_drake
from implantplan.diagrams.plant import build_plant
from implantplan.systems.errors import InputError
from implantplan.systems.frames import transform
from implantplan.systems.robot import kinematics
from implantplan.systems.robot.moprp import R_OE

LIM175 = np.deg2rad(175.0)


@pytest.fixture(scope="module")
def solver():
    return DrakeIk()


def _wrapped(a, b):
    return np.linalg.norm(np.mod(a - b + np.pi, 2 * np.pi) - np.pi, axis=-1)


def _check_against_closed_form(solver, X, seed, limits="175", X_FT=None):
    """Drake's solutions are exactly the closed form's valid branches (as sets)."""
    closed = kinematics.ik(X, limits=limits, X_FT=X_FT)
    expected = closed.q[closed.valid]
    q, info = solver.solve(X, seed=seed)
    assert info.branches == len(q)
    assert len(q) == len(expected), (len(q), len(expected), info)
    for qi in q:  # each Drake solution is one closed-form branch...
        assert _wrapped(expected, qi).min() < 1e-6
    for qe in expected:  # ...and every branch is found
        assert _wrapped(q, qe).min() < 1e-6
    # every returned solution reproduces the pose and lies within the limits
    if len(q):
        dp, dR = kinematics.pose_error(kinematics.fk(q, X_FT), np.broadcast_to(X, (len(q), 4, 4)))
        assert dp.max() < 1e-9 and dR.max() < 1e-9
        lim = kinematics.joint_limits(limits)
        assert np.all((q >= lim[0]) & (q <= lim[1]))
    return len(q)


def _poses(n, seed, limits=LIM175):
    rng = np.random.default_rng(seed)
    return kinematics.fk(rng.uniform(-limits, limits, size=(n, 6)))


def test_branch_sets_match_closed_form_on_a_few_poses(solver):
    counts = [_check_against_closed_form(solver, X, seed=i) for i, X in enumerate(_poses(4, 11))]
    assert sum(counts) > 4 * 3  # generic poses have several branches within +-175 deg


@pytest.mark.slow
def test_branch_counts_match_closed_form_on_50_poses(solver):
    counts = [_check_against_closed_form(solver, X, seed=i) for i, X in enumerate(_poses(50, 7))]
    print(f"50 poses: {sum(counts)} branches, all counts equal to the closed form")


def test_same_seed_same_output(solver):
    X = _poses(1, 3)[0]
    q1, _ = solver.solve(X, starts=24, seed=9)
    q2, _ = solver.solve(X, starts=24, seed=9)
    np.testing.assert_array_equal(q1, q2)


def test_any_urdf_and_tool_frame():
    """The +-360 deg model loaded by path, solving for the actuator TCP (X_FT)."""
    X_FT = tools.X_FT()
    path = str(models.model_path("aubo_i10/aubo_i10_360.urdf"))
    s = DrakeIk(urdf=path, base_frame="base_link", tool_frame="wrist3_Link", X_FT=X_FT)
    rng = np.random.default_rng(4)
    X = kinematics.fk(rng.uniform(-np.pi, np.pi, 6), X_FT)
    n = _check_against_closed_form(s, X, seed=1, limits="360", X_FT=X_FT)
    assert n >= 1


def test_out_of_reach_is_empty_with_reason(solver):
    X = np.eye(4)
    X[:3, 3] = [2.0, 0.0, 0.5]  # beyond the arm's 1.5 m reach
    q, info = ik_drake(X, solver=solver, starts=8)
    assert q.shape == (0, 6)
    assert info.branches == 0 and "no start converged" in info.reason
    assert not kinematics.ik(X).valid.any()


@pytest.mark.parametrize("starts", [16, pytest.param(128, marks=pytest.mark.sweep)])
def test_min_distance_keeps_only_collision_free_branches(starts):
    """Every solution the constrained solver returns keeps 5 mm and is a branch of the free
    solver's (128 starts); with 128 starts too (the sweep) they are exactly the free branches
    that keep 5 mm."""
    diagram, plant, sg, h = build_plant(scenario="lying")
    s = DrakeIk(
        plant=plant,
        diagram=diagram,
        tool_frame="wrist3_Link",
        X_FT=tools.X_FT(),
        min_distance=0.005,
    )
    free = DrakeIk(plant=plant, diagram=diagram, tool_frame="wrist3_Link", X_FT=tools.X_FT())
    # The default lying layout's task: TCP at the mouth frame (Oral), End axes R_OE in Oral.
    X_WO = h.mouth.CalcPoseInWorld(plant.CreateDefaultContext()).GetAsMatrix4()
    X_WT = X_WO @ transform(R_OE, np.zeros(3))
    X_BT = np.linalg.solve(h.X_WBase, X_WT)
    q_all, _ = free.solve(X_BT, seed=0)
    q_safe, info = s.solve(X_BT, seed=0, starts=starts)
    clear = np.array([s._clearance(q) for q in q_all])
    print(f"clearances of all branches (m): {np.round(clear, 4)}; kept {info.branches}")
    assert len(q_all) >= 1 and len(q_safe) >= 1
    if starts == 128:
        assert len(q_safe) == np.sum(clear >= 0.005)
    for q in q_safe:
        assert s._clearance(q) >= 0.005 - 1e-6
        assert _wrapped(q_all, q).min() < 1e-6


def test_bad_input():
    s = DrakeIk()
    with pytest.raises(InputError, match="X_BT"):
        s.solve(np.eye(3))
    with pytest.raises(InputError, match="X_BT"):
        s.solve(np.full((4, 4), np.nan))
    with pytest.raises(InputError, match="starts"):
        s.solve(np.eye(4), starts=0)
    with pytest.raises(InputError, match="limits"):
        DrakeIk(limits="90")
    with pytest.raises(InputError, match="min_distance"):
        DrakeIk(min_distance=-1.0)
