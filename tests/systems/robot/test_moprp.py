"""MOPRP core (systems.robot.moprp): indices, selection, the scenario, the problem and the
search."""

import dataclasses

import numpy as np
import pytest

from implantplan.systems.errors import InputError
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp, nsga2


@pytest.fixture(scope="module")
def lying():
    return moprp.load_scenario("lying")


# ---------------------------------------------------------------- indices by hand


def test_indices_at_home_by_hand():
    """At q = 0 (DESIGN.md 8) the joint axes in base_link are z1 = z5 = +-e_z and
    z2 = z3 = z4 = z6 = +-e_y, so J_w J_w^T = diag(0, 4, 2): sigma_max(J_w) = 2 and J_w is rank
    deficient (cond = inf). With the flange as the tool, p_F = (0, -0.2953, 1.5132) and the
    joint origins (0, 0, 0.1632), (0, -0.2013, 0.1632), (0, -0.2013, 0.8102),
    (0, -0.2013, 1.4107), (0, -0.2013, 1.5132), p_F: every column of J_v = z_i x (p_F - p_i) is
    along x with magnitudes 0.2953, 1.35, 0.703, 0.1025, 0.094, 0. So J_v has rank 1 and
    sigma_max(J_v) = sqrt(0.2953^2 + 1.35^2 + 0.703^2 + 0.1025^2 + 0.094^2)."""
    eps = 1e-3
    q = np.zeros(6)
    path = np.array([[0, 0, 0, 0, 0, 0], [0.1, -0.2, 0, 0, 0, 0], [0.3, -0.1, 0, 0, 0, 0.05]])
    ind = moprp.indices(q, path, eps=eps, X_FT=np.eye(4))
    s_v = np.sqrt(0.2953**2 + 1.35**2 + 0.703**2 + 0.1025**2 + 0.094**2)
    assert ind["error_range"] == pytest.approx(eps * s_v, rel=1e-12)
    assert ind["angular_error_range"] == pytest.approx(2 * eps, rel=1e-12)
    assert ind["dexterity"] > 1e6  # both parts singular at home
    # |0.1| + |0.2| + |0.2| + |0.1| + |0.05| travelled along the path
    assert ind["joint_variation"] == pytest.approx(0.65, abs=1e-15)


def test_indices_match_svd_at_random_configurations():
    rng = np.random.default_rng(4)
    q = rng.uniform(-np.pi, np.pi, (50, 6))
    X_FT = moprp.Actuator().X_FT()
    ind = moprp.indices(q, np.stack([q, q], axis=1), eps=0.002, X_FT=X_FT)
    J = kin.jacobian_body(q, X_FT)
    sw = np.linalg.svd(J[:, :3], compute_uv=False)
    sv = np.linalg.svd(J[:, 3:], compute_uv=False)
    np.testing.assert_allclose(ind["dexterity"],
                               np.maximum(sw[:, 0] / sw[:, -1], sv[:, 0] / sv[:, -1]), rtol=1e-6)
    np.testing.assert_allclose(ind["error_range"], 0.002 * sv[:, 0], rtol=1e-10)
    np.testing.assert_allclose(ind["joint_variation"], 0.0)


def test_error_range_is_the_largest_tcp_error_of_the_joint_error_ball():
    """I_e = eps sigma_max(J_v): no joint error of norm eps moves the TCP further (to first
    order), and the top right-singular vector reaches it."""
    rng = np.random.default_rng(0)
    q = rng.uniform(-2, 2, 6)
    X_FT = moprp.Actuator().X_FT()
    eps = 1e-5
    ind = moprp.indices(q, q[None], eps=eps, X_FT=X_FT)
    dq = rng.normal(size=(2000, 6))
    dq *= eps / np.linalg.norm(dq, axis=1, keepdims=True)
    p0 = kin.fk(q, X_FT)[:3, 3]
    moved = np.linalg.norm(kin.fk(q + dq, X_FT)[:, :3, 3] - p0, axis=1)
    assert moved.max() <= ind["error_range"] * (1 + 1e-4)
    Jv = kin.jacobian_body(q, X_FT)[3:]
    v = np.linalg.svd(Jv)[2][0]
    best = np.linalg.norm(kin.fk(q + eps * v, X_FT)[:3, 3] - p0)
    assert best == pytest.approx(ind["error_range"], rel=1e-4)


def test_angular_error_range_claim(lying):
    """Paper Eq. 20: the posture error range eps sigma_max(J_w) is 'a constant'. For this arm
    J_w J_w^T = z1 z1^T + 3 z2 z2^T + z5 z5^T + z6 z6^T (joints 2-4 parallel), so sigma_max
    lies in [sqrt(3), 2]: bounded within 15%, not constant. Measured on the candidates."""
    rng = np.random.default_rng(1)
    X = lying.lower + rng.random((400, 3)) * (lying.upper - lying.lower)
    ev = moprp.evaluate_bases(X, lying, rng)
    a = ev.angular_error_range[np.isfinite(ev.angular_error_range)] / lying.eps
    assert a.size > 100
    assert a.min() >= np.sqrt(3) - 1e-9 and a.max() <= 2 + 1e-9
    assert a.max() - a.min() > 0.1  # it does vary


# ---------------------------------------------------------------- target and feed


def test_target_orientation_follows_the_spec():
    X = moprp.target_pose([0.5, -0.2, 0.1])
    R_OB, R_OE = moprp.R_OB, moprp.R_OE
    # End Y along Oral Z, End X along -Oral Y; Base X || Oral X, Base Z || Oral Y
    np.testing.assert_allclose(R_OE[:, 1], [0, 0, 1])
    np.testing.assert_allclose(R_OE[:, 0], [0, -1, 0])
    np.testing.assert_allclose(R_OB[:, 0], [1, 0, 0])
    np.testing.assert_allclose(R_OB[:, 2], [0, 1, 0])
    # Oral origin seen from the base at p = (0.5, -0.2, 0.1): (-p.x, p.z, -p.y)
    np.testing.assert_allclose(X[:3, 3], [-0.5, 0.1, 0.2])
    np.testing.assert_allclose(X[:3, :3], R_OB.T @ R_OE)


def test_feed_backs_out_along_the_rod():
    F = moprp.feed_poses([0.6, -0.3, 0.0], 0.06, 4)
    z_E = F[-1, :3, 2]
    np.testing.assert_allclose(F[0, :3, 3], F[-1, :3, 3] - 0.06 * z_E, atol=1e-15)
    np.testing.assert_allclose(np.diff(F[:, :3, 3], axis=0), np.tile(0.02 * z_E, (3, 1)),
                               atol=1e-15)


def test_selected_configuration_reaches_the_target(lying):
    rng = np.random.default_rng(3)
    X = lying.lower + rng.random((200, 3)) * (lying.upper - lying.lower)
    ev = moprp.evaluate_bases(X, lying, rng)
    f = ev.feasible
    assert f.mean() > 0.3
    X_BE = kin.fk(ev.q[f], lying.X_FT)
    np.testing.assert_allclose(X_BE, moprp.target_pose(X[f]), atol=1e-9)
    X_pre = kin.fk(ev.q_pre[f], lying.X_FT)
    np.testing.assert_allclose(X_pre, moprp.feed_poses(X[f], lying.feed_length, 2)[:, 0],
                               atol=1e-9)
    # selected q is the branch's closed-form solution
    r = kin.ik(moprp.target_pose(X[f]), X_FT=lying.X_FT)
    np.testing.assert_allclose(ev.q[f], r.q[np.arange(f.sum()), ev.branch[f]], atol=1e-12)


# ---------------------------------------------------------------- rejections


def test_base_out_of_reach_rejects_every_branch(lying):
    ev = moprp.evaluate_bases([[3.0, 0.0, 0.0]], lying, np.random.default_rng(0))
    assert ev.branch[0] == -1 and not ev.valid.any()
    assert np.all(ev.reason == moprp.DROP_IK)
    assert ev.violation[0] == pytest.approx(1.0)  # every sample of every branch fails
    assert np.all(np.isinf(ev.objectives))


def test_condition_1_rejects_every_branch_at_a_reachable_base(lying):
    """A joint-2 range that no branch meets: every branch that exists is dropped by condition 1."""
    xyz = np.array([[0.6, -0.3, 0.0]])
    ok = moprp.evaluate_bases(xyz, lying, np.random.default_rng(0))
    assert ok.feasible[0]
    tight = dataclasses.replace(lying, joint2_range=np.array([3.0, 3.01]))
    ev = moprp.evaluate_bases(xyz, tight, np.random.default_rng(0))
    assert ev.branch[0] == -1
    assert set(np.unique(ev.reason)) <= {moprp.DROP_IK, moprp.DROP_JOINT2, moprp.DROP_CONTINUITY}
    assert np.sum(ev.reason == moprp.DROP_JOINT2) >= 1
    assert 0 < ev.violation[0]


def test_actuator_into_the_forearm_is_condition_2():
    """With the arm upright (q1..q3 = 0) and the wrist turned over (q4 = q5 = 180 deg) the rod
    points straight down the forearm: the rod's axis meets the forearm capsule's axis. The rod
    (a cylinder) is enclosed by its capsule (clearance -(r_rod + r_forearm) = -0.05) and by
    boxes that the forearm's axis passes through (-r_forearm = -0.044); the model reports the
    largest of these lower bounds; at home the actuator is clear."""
    sc = moprp.load_scenario("lying")
    model = moprp.CollisionModel.for_scenario(sc)
    q = np.deg2rad([[0, 0, 0, 180, 180, 0], [0, 0, 0, 0, 0, 0]])
    d = moprp.collision_clearance(q, np.zeros((2, 3)), sc, model)["self"]
    assert d[0] == pytest.approx(-0.044, abs=1e-9)
    assert d[1] > sc.clearance


# ---------------------------------------------------------------- selection


def test_score_selection_by_hand():
    # ranks: A (0, 0, 1) = 1, B (1, 1, 0) = 2, C (2, 2, 2) = 6 -> A
    v = np.array([[[1.0, 1.0, 2.0], [2.0, 2.0, 1.0], [3.0, 3.0, 3.0]]])
    choice, score = moprp.select(v, np.ones((1, 3), bool), np.random.default_rng(0))
    assert choice[0] == 0 and score[0] == 1
    # without A, B wins (ranks B (0, 0, 0)); invalid candidates never count
    choice, score = moprp.select(v, np.array([[False, True, True]]), np.random.default_rng(0))
    assert choice[0] == 1 and score[0] == 0
    choice, score = moprp.select(v, np.zeros((1, 3), bool), np.random.default_rng(0))
    assert choice[0] == -1 and score[0] == -1


def test_tie_breaks_are_seeded():
    # A (1,1,3) and B (2,2,1) tie at 2 points each (A ranks 0,0,2; B 1,1,0); C is last
    v = np.tile(np.array([[[1.0, 1.0, 3.0], [2.0, 2.0, 1.0], [3.0, 3.0, 2.0]]]), (200, 1, 1))
    valid = np.ones((200, 3), bool)
    c1, s1 = moprp.select(v, valid, np.random.default_rng(7))
    c2, _ = moprp.select(v, valid, np.random.default_rng(7))
    np.testing.assert_array_equal(c1, c2)
    assert set(np.unique(c1)) == {0, 1}  # both tied candidates get picked, never C
    assert np.all(s1 == 2)
    c3, _ = moprp.select(v, valid, np.random.default_rng(8))
    assert not np.array_equal(c1, c3)


def test_evaluation_is_reproducible_with_the_seed(lying):
    X = lying.lower + np.random.default_rng(5).random((300, 3)) * (lying.upper - lying.lower)
    a = moprp.evaluate_bases(X, lying, np.random.default_rng(11))
    b = moprp.evaluate_bases(X, lying, np.random.default_rng(11))
    np.testing.assert_array_equal(a.branch, b.branch)
    np.testing.assert_array_equal(a.objectives, b.objectives)


def test_knee_point_and_percentiles_by_hand():
    F = np.array([[0.0, 10.0, 5.0], [10.0, 0.0, 5.0], [3.0, 3.0, 4.0], [10.0, 10.0, 0.0]])
    # normalized sums: 0+1+1 = 2, 2, 0.3+0.3+0.8 = 1.4, 2 -> index 2
    assert moprp.knee_point(F) == 2
    assert moprp.knee_point(F, weights=[1, 0, 0]) == 0
    with pytest.raises(InputError):
        moprp.knee_point(F, weights=[0, 0, 0])
    pct = moprp.percentiles([2.0, 5.0, 1.0], np.array([[1.0, 5.0, 0.0], [3.0, 6.0, 2.0],
                                                       [4.0, 4.0, 3.0], [2.0, 7.0, 4.0]]))
    np.testing.assert_allclose(pct, [75.0, 75.0, 75.0])
    strict = moprp.percentiles([2.0, 5.0, 1.0], np.array([[1.0, 5.0, 0.0], [3.0, 6.0, 2.0],
                                                          [4.0, 4.0, 3.0], [2.0, 7.0, 4.0]]),
                               strict=True)
    np.testing.assert_allclose(strict, [50.0, 50.0, 75.0])


def test_gii_poses_span_the_cube():
    X = moprp.gii_poses(2000, np.random.default_rng(0))
    d = X[:, :3, 3]
    assert np.abs(d).max() <= 0.025 and np.abs(d).max() > 0.024
    np.testing.assert_allclose(X[0, :3, :3] @ X[0, :3, :3].T, np.eye(3), atol=1e-12)


# ---------------------------------------------------------------- scenario validation


def _raw():
    from implantplan.systems.files import read_yaml

    return read_yaml(moprp.scenario_path("lying"))


@pytest.mark.parametrize("pair", [[0.5, 0.2], [0.3, 0.3]])
def test_inverted_or_empty_bounds_are_rejected(pair):
    d = _raw()
    d["base_bounds_m"]["x"] = pair
    with pytest.raises(InputError, match=r"base_bounds_m\.x"):
        moprp.scenario_from_dict(d)


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        (("joint_error_deg",), -1.0, "joint_error_deg"),
        (("feed_length_m",), "far", "feed_length_m"),
        (("base_bounds_m", "y"), [0.0], r"base_bounds_m\.y"),
        (("cabinet", "joint2_range_deg"), [90, -90], "joint2_range_deg"),
        (("posture",), "standing", "posture"),
        (("ga", "pop"), 2, r"ga\.pop"),
    ],
)
def test_bad_fields_name_the_field(path, value, field):
    d = _raw()
    node = d
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    with pytest.raises(InputError, match=field):
        moprp.scenario_from_dict(d)


def test_both_bundled_scenarios_load():
    for name in moprp.BUNDLED:
        sc = moprp.load_scenario(name)
        assert sc.posture == name
        # the bundled Oral frames keep the base upright: Oral Y = World up
        np.testing.assert_allclose(sc.X_WO[:3, 1], [0, 0, 1], atol=1e-12)


# ---------------------------------------------------------------- the search


def test_nsga2_moprp_front_is_feasible_and_non_dominated(lying):
    r = nsga2.nsga2(moprp.problem(lying), lying.lower, lying.upper, pop=40, gen=15, seed=2,
                    patience=None)
    F = r.F[r.front]
    assert F.shape[0] >= 5 and np.all(r.cv[r.front] <= 0)
    D = nsga2.domination_matrix(F)
    assert not D.any()
    assert r.evaluations == 40 * 16


def test_search_returns_a_feasible_non_dominated_front(lying):
    sc = dataclasses.replace(lying, pop=40, gen=10)
    res = moprp.search(sc, moprp.problem(sc))
    assert res.X.shape[0] >= 5 and res.F.shape == (res.X.shape[0], 3)
    assert not nsga2.domination_matrix(res.F).any()
    ev = moprp.evaluate_bases(res.X, sc, np.random.default_rng(0))
    assert ev.feasible.all()
    assert res.evaluations == 4 * 40 + 40 * (res.generations + 1)
    order = moprp.selection_order(res.F)
    assert order[0] == moprp.knee_point(res.F) and sorted(order) == list(range(res.X.shape[0]))


def test_search_without_feasible_samples_explains(lying):
    from implantplan.systems.errors import PlanningFailure

    sc = dataclasses.replace(lying, pop=8, gen=2, lower=np.array([4.0, 0.0, 0.0]),
                             upper=np.array([5.0, 0.1, 0.1]))
    with pytest.raises(PlanningFailure, match="why: 32"):
        moprp.search(sc, moprp.problem(sc), explain=lambda X, rng: f"why: {X.shape[0]}")


def test_cart_clearance_by_hand():
    """Bundled Oral pose: Base axes = World axes, base at Oral (1, 0, 0) = World (1, 0, 0.85);
    the cart spans World x 0.85..1.45, y -0.25..0.25, z -1.15..0.85."""
    d = _raw()
    d["obstacles"] = [
        {"name": "box", "type": "box", "center_m": [0.5, 0.0, 0.5], "size_m": [0.4, 0.4, 0.4]},
    ]
    sc = moprp.scenario_from_dict(d)
    # box x 0.3..0.7: 0.15 from the cart's face at x = 0.85
    assert moprp.cart_clearance([[1.0, 0.0, 0.0]], sc)[0] == pytest.approx(0.15)
    # moving the base 0.2 towards the box makes them overlap
    assert moprp.cart_clearance([[0.8, 0.0, 0.0]], sc)[0] == 0.0
    d["obstacles"] = [{"name": "cap", "type": "capsule", "p0_m": [0.5, 0.0, 0.3],
                       "p1_m": [0.5, 0.0, 0.6], "radius_m": 0.1}]
    sc = moprp.scenario_from_dict(d)
    assert moprp.cart_clearance([[1.0, 0.0, 0.0]], sc)[0] == pytest.approx(0.25)
    # a base whose cart overlaps the patient is infeasible for every branch
    ev = moprp.evaluate_bases([[0.5, 0.0, 0.0]], sc, np.random.default_rng(0))
    assert ev.branch[0] == -1 and np.all(np.isin(ev.reason, [moprp.DROP_IK, moprp.DROP_CART]))
