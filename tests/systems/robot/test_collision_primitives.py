"""The fast conservative collision model (systems.robot.arm_collision) and its exact primitives."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from implantplan.systems.frames import rot_z, transform
from implantplan.systems.robot import arm_collision as ac
from implantplan.systems.robot import collision_primitives as cp
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp
from implantplan.systems.robot.arm_collision import box_box, seg_box


def _surface_points(shape: ac.Shape, n: int, rng) -> np.ndarray:
    """``n`` points on the surface of a shape, in its own frame (G)."""
    if shape.kind == "box":
        h = np.asarray(shape.size) / 2
        p = rng.uniform(-1, 1, (n, 3)) * h
        axis = rng.integers(0, 3, n)
        p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * h[axis]
        return p
    if shape.kind == "sphere":
        v = rng.normal(size=(n, 3))
        return shape.size[0] * v / np.linalg.norm(v, axis=1, keepdims=True)
    r, length = shape.size
    phi = rng.uniform(0, 2 * np.pi, n)
    if shape.kind == "cylinder":
        z = rng.uniform(-length / 2, length / 2, n)
        rho = np.full(n, r)
        cap = rng.random(n) < 0.4  # flat ends, including their rims
        z[cap] = np.where(rng.random(cap.sum()) < 0.5, -length / 2, length / 2)
        rho[cap] = r * np.sqrt(rng.random(cap.sum()))
        rho[: n // 10] = r  # rims exactly
        z[: n // 10] = np.where(np.arange(n // 10) % 2, -length / 2, length / 2)
        return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    # capsule: the side and the two hemispheres
    v = rng.normal(size=(n, 3))
    v = r * v / np.linalg.norm(v, axis=1, keepdims=True)
    side = rng.random(n) < 0.5
    v[side, 2] = 0.0
    v[side, :2] = r * np.stack([np.cos(phi[side]), np.sin(phi[side])], axis=1)
    shift = np.where(side, rng.uniform(-length / 2, length / 2, n),
                     np.sign(v[:, 2]) * length / 2)
    v[:, 2] += shift
    return v


def _inside(kind, X_FE, dims, p_F) -> np.ndarray:
    local = (p_F - X_FE[:3, 3]) @ X_FE[:3, :3]
    if kind == ac.KIND_BOX:
        return np.all(np.abs(local) <= dims + 1e-12, axis=1)
    a, r = dims[0], dims[1]
    z = np.clip(local[:, 2], -a, a)
    return np.hypot(np.hypot(local[:, 0], local[:, 1]), local[:, 2] - z) <= r + 1e-12


@pytest.mark.parametrize("scenario", ["lying", "sitting", None])
def test_surface_points_of_every_shape_lie_inside_every_enclosure(scenario):
    """Each collision shape of the plant (URDF arm and actuator, the scenario's cart, patient
    and chair) is contained in each of its primitives: 4000 surface points per shape."""
    sc = moprp.load_scenario(scenario) if scenario else None
    shapes, _ = ac.scene_shapes(sc)
    kinds = {s.kind for s in shapes}
    assert "cylinder" in kinds and "box" in kinds and "capsule" in kinds
    rng = np.random.default_rng(0)
    for shape in shapes:
        p_G = _surface_points(shape, 4000, rng)
        p_F = p_G @ shape.X_FG[:3, :3].T + shape.X_FG[:3, 3]
        centre = shape.X_FG[:3, 3]
        assert np.all(np.linalg.norm(p_F - centre, axis=1) <= ac.bounding_radius(shape) + 1e-12)
        for kind, X_FE, dims in ac.enclosures(shape):
            assert np.all(_inside(kind, X_FE, dims, p_F)), shape.name


def test_cylinder_enclosures_are_the_capsule_and_two_boxes():
    s = ac.Shape("c", "b", 1, "cylinder", np.eye(4), (0.1, 0.4))
    enc = ac.enclosures(s)
    assert [k for k, _, _ in enc] == [ac.KIND_CAPSULE, ac.KIND_BOX, ac.KIND_BOX]
    np.testing.assert_allclose(enc[0][2], [0.2, 0.1, 0.0])
    np.testing.assert_allclose(enc[1][2], [0.1, 0.1, 0.2])
    np.testing.assert_allclose(enc[2][1][:3, :3], rot_z(np.pi / 4), atol=1e-15)


def test_segment_box_distance_is_exact():
    """Against dense sampling along the segment (the exact value is never above the sampled
    minimum, and within the sampling step of it); hand cases: parallel to a face, through."""
    rng = np.random.default_rng(1)
    t = np.linspace(0, 1, 20001)
    for _ in range(500):
        a, d = rng.normal(size=3) * 0.3, rng.normal(size=3) * 0.5
        h = rng.random(3) * 0.2 + 0.01
        exact = seg_box(*a, *d, *h)
        q = np.maximum(np.abs(a + t[:, None] * d) - h, 0.0)
        sampled = np.sqrt((q ** 2).sum(axis=1)).min()
        assert exact <= sampled + 1e-15
        assert sampled - exact <= np.linalg.norm(d) * 1e-4
    parallel = seg_box(-1.0, 0.3, 0.25, 2.0, 0.0, 0.0, 0.1, 0.1, 0.2)
    assert parallel == pytest.approx(np.hypot(0.2, 0.05))
    assert seg_box(-1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.1, 0.1, 0.1) == 0.0


def test_box_box_distance_hand_cases():
    h = np.array([0.5, 0.5, 0.5])
    A = np.eye(4)
    B = transform(np.eye(3), [1.3, 0.0, 0.0])
    assert box_box(A, h, B, h) == pytest.approx(0.3)
    # B turned 45 deg about z: its edge points at A's face, at 1.3 - 0.5 sqrt(2) from the centre
    B45 = transform(rot_z(np.pi / 4), [1.3, 0.0, 0.0])
    assert box_box(A, h, B45, h) == pytest.approx(1.3 - 0.5 * np.sqrt(2) - 0.5)
    assert box_box(A, h, transform(np.eye(3), [0.9, 0.2, 0.0]), h) == 0.0
    assert box_box(A, h, A, 0.1 * h) == 0.0  # one inside the other


def test_model_distance_never_exceeds_sampled_surface_distance():
    """Without Drake: per configuration, the model's smallest distance of each group is at most
    the distance between sampled surface points of every checked pair (the samples give an
    upper bound of the true distance, the model a lower bound)."""
    sc = moprp.load_scenario("lying")
    model = moprp.collision_model(sc)
    rng = np.random.default_rng(2)
    pts = [_surface_points(s, 300, rng) @ s.X_FG[:3, :3].T + s.X_FG[:3, 3]
           for s in model.shapes]
    xyz = np.array([0.56, -0.15, -0.25])
    q = rng.uniform(-np.pi, np.pi, (12, 6))
    c = moprp.collision_clearance(q, xyz, sc, model)
    X_BW = ac.world_in_base(xyz, sc.X_WO, moprp.R_OB)[0]
    for n in range(q.shape[0]):
        F = model.scene_frames(q[n : n + 1], X_BW)[0]
        posed = [p @ F[s.frame, :3, :3].T + F[s.frame, :3, 3]
                 for p, s in zip(pts, model.shapes, strict=True)]
        for m, (i, j) in enumerate(model.pairs):
            diff = posed[i][:, None, :] - posed[j][None, :, :]
            upper = np.sqrt((diff ** 2).sum(-1)).min()
            group = ac.GROUPS[model.pair_group[m]]
            assert c[group][n] <= upper + 1e-12, model.pair_names(m)


def test_pairs_are_the_unfiltered_ones_in_three_groups():
    sc = moprp.load_scenario("lying")
    model = moprp.collision_model(sc)
    names = {frozenset(model.pair_names(m)) for m in range(len(model.pairs))}
    # the pairs the old hand list missed are checked
    assert frozenset({"aubo::foreArm_Link_collision_1", "aubo::wrist3_Link_collision_0"}) in names
    assert frozenset({"aubo::upperArm_Link_collision_1", "aubo::wrist1_Link_collision_0"}) in names
    # adjacent links, welded bodies, the actuator vs the patient: filtered
    adjacent = {"aubo::foreArm_Link_collision_1", "aubo::wrist1_Link_collision_0"}
    assert frozenset(adjacent) not in names
    assert frozenset({"aubo::wrist3_Link_collision_0", "actuator::rod_collision"}) not in names
    assert frozenset({"actuator::rod_collision", "patient::head"}) not in names
    assert frozenset({"aubo::base_link_collision_0", "cart::cart"}) not in names
    groups = {ac.GROUPS[g] for g in model.pair_group}
    assert groups == {"self", "environment", "cabinet"}
    for m, g in enumerate(model.pair_group):
        a, b = model.pair_names(m)
        expect = "cabinet" if "cart::cart" in (a, b) else (
            "environment" if a.startswith("patient::") or b.startswith("patient::") else "self")
        assert ac.GROUPS[g] == expect


def test_cutoff_keeps_verdicts_and_lower_bounds():
    sc = moprp.load_scenario("sitting")
    model = moprp.collision_model(sc)
    rng = np.random.default_rng(4)
    q = rng.uniform(-np.pi, np.pi, (400, 6))
    xyz = np.array([0.56, -0.33, -0.25])
    full = moprp.collision_clearance(q, xyz, sc, model)
    fast = moprp.collision_clearance(q, xyz, sc, model, cutoff=sc.clearance)
    for g in ac.GROUPS:
        assert np.all(fast[g] <= full[g] + 1e-15)
        np.testing.assert_array_equal(moprp.is_clear(fast[g], sc.clearance),
                                      moprp.is_clear(full[g], sc.clearance))
    assert 0.05 < np.mean(moprp.is_clear(full["self"], sc.clearance)) < 0.95


def test_bare_arm_model_and_frames():
    model = ac.model_for(None, tool=False)
    assert all(not s.name.startswith("actuator::") for s in model.shapes)
    F = model.scene_frames(np.zeros((1, 6)))
    np.testing.assert_allclose(F[0, 1:7], kin.joint_frames(np.zeros(6)))
    d, pair = model.clearance(np.zeros((1, 6)))
    assert np.isfinite(d[0, 0]) and d[0, 0] > 0 and pair[0, 0] >= 0
    assert np.isinf(d[0, 1]) and pair[0, 1] == -1


# ---------------------------------------------------------------- capsule primitives


def test_segment_distances_by_hand():
    a = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    # parallel, offset by 2 in y
    assert cp.segment_distance(a, a + [0, 2, 0]) == pytest.approx(2.0)
    # skew: a along x at z=0, b along y through (0.5, *, 3)
    b = np.array([[0.5, -1, 3.0], [0.5, 1, 3.0]])
    assert cp.segment_distance(a, b) == pytest.approx(3.0)
    # beyond the end: closest points are the endpoints (1,0,0) and (2,0,1)
    c = np.array([[2.0, 0, 1], [3.0, 0, 1]])
    assert cp.segment_distance(a, c) == pytest.approx(np.sqrt(2))
    # point (degenerate segment) above the middle
    p = np.array([[0.5, 0.0, 0.7], [0.5, 0.0, 0.7]])
    assert cp.segment_distance(a, p) == pytest.approx(0.7)
    assert cp.capsule_clearance(a, 0.1, b, 0.2) == pytest.approx(2.7)


def test_segment_box_distance_by_hand():
    box = np.eye(4)
    half = np.array([0.5, 0.5, 0.5])
    seg = np.array([[2.0, 0, 0], [2.0, 0, 3.0]])
    assert cp.segment_box_distance(seg, box, half) == pytest.approx(1.5)
    seg2 = np.array([[1.5, 1.5, -3.0], [1.5, 1.5, 3.0]])  # passes the vertical edge
    assert cp.segment_box_distance(seg2, box, half) == pytest.approx(np.sqrt(2))
    assert cp.segment_box_distance(np.array([[-2.0, 0, 0], [2.0, 0, 0]]), box, half) == 0.0
    # batched version agrees with the single one, rotated box
    from implantplan.systems.frames import rot_z, transform

    Xb = transform(rot_z(np.pi / 4), [1.0, 0.0, 0.0])
    d1 = cp.segment_box_distance(seg, Xb, half)
    d2 = cp.min_box_clearance(seg[None, None], np.zeros(1), Xb[None, :3, :3],
                              Xb[None, None, :3, 3], half[None])
    assert d2[0] == pytest.approx(float(d1), abs=1e-9)


@settings(max_examples=50, deadline=None)
@given(arrays(np.float64, (2, 2, 3), elements=st.floats(-1, 1)))
def test_segment_distance_is_the_min_over_samples(S):
    t = np.linspace(0, 1, 401)
    pa = S[0, 0] + t[:, None] * (S[0, 1] - S[0, 0])
    pb = S[1, 0] + t[:, None] * (S[1, 1] - S[1, 0])
    brute = np.linalg.norm(pa[:, None] - pb[None], axis=-1).min()
    d = cp.segment_distance(S[0], S[1])
    # a segment shorter than 1 nm (squared length <= 1e-18 m^2) counts as its start point, so
    # the distance may exceed the samples' by that much (hypothesis found 2e-12 m segments)
    assert d <= brute + 1e-9
    assert d >= brute - 2 * np.linalg.norm(S[:, 1] - S[:, 0], axis=-1).max() / 400 - 1e-12


def test_arm_capsules_at_home_by_hand():
    from implantplan.analyses.bench_moprp import OLD_ARM_CAPSULES

    seg, rad = cp.arm_capsules(np.zeros(6), OLD_ARM_CAPSULES)
    names = [c.name for c in OLD_ARM_CAPSULES]
    ua = seg[names.index("upper_arm")]
    np.testing.assert_allclose(ua, [[0, -0.2013, 0.1632], [0, -0.2013, 0.8102]], atol=1e-12)
    fa = seg[names.index("forearm")]
    # forearm capsule at z 0.128 of its frame = base y offset (the frame's z is base +y here)
    np.testing.assert_allclose(fa[:, 2], [0.8102, 1.4107], atol=1e-12)
    assert rad[names.index("upper_arm")] == 0.058
    # batched shapes
    seg2, _ = cp.arm_capsules(np.zeros((4, 2, 6)), OLD_ARM_CAPSULES)
    assert seg2.shape == (4, 2, len(OLD_ARM_CAPSULES), 2, 3)


def test_min_capsule_clearance_matches_pairwise():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(20, 3, 2, 3))
    B = rng.normal(size=(20, 4, 2, 3))
    ra, rb = rng.random(3) * 0.1, rng.random(4) * 0.1
    full = cp.capsule_clearance(A[:, :, None], ra[None, :, None], B[:, None], rb[None, None])
    np.testing.assert_allclose(cp.min_capsule_clearance(A, ra, B, rb), full.min(axis=(1, 2)))
    pairs = np.array([[0, 1], [2, 3]])
    np.testing.assert_allclose(cp.min_capsule_clearance(A, ra, B, rb, pairs),
                               np.minimum(full[:, 0, 1], full[:, 2, 3]))
