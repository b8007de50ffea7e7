"""The fast collision model against the Drake plant it is generated from."""

from __future__ import annotations

import numpy as np
import pytest
from pydrake.geometry import Box, Capsule, Cylinder, Role, Sphere

from implantplan.diagrams import arm_clearance as acl
from implantplan.diagrams.plant import build_plant
from implantplan.systems.robot import arm_collision as ac
from implantplan.systems.robot import moprp


def _dims(shape) -> tuple[str, tuple]:
    if isinstance(shape, Box):
        return "box", (shape.width(), shape.depth(), shape.height())
    if isinstance(shape, Cylinder):
        return "cylinder", (shape.radius(), shape.length())
    if isinstance(shape, Capsule):
        return "capsule", (shape.radius(), shape.length())
    if isinstance(shape, Sphere):
        return "sphere", (shape.radius(),)
    raise AssertionError(type(shape))


@pytest.mark.parametrize("scenario", ["lying", "sitting"])
def test_shapes_and_pairs_are_the_plants(scenario):
    """Shape by shape (kind, size, pose in World at a random configuration) and pair by pair
    (SceneGraph's collision candidates) the fast model is the plant's SceneGraph."""
    sc = moprp.load_scenario(scenario)
    model = moprp.collision_model(sc)
    xyz = np.array([0.6, -0.2, 0.1])
    diagram, plant, sg, h = build_plant(scenario=sc, X_WBase=sc.X_WO @ moprp.base_pose(xyz))
    ctx = diagram.CreateDefaultContext()
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, 6)
    plant.SetPositions(plant.GetMyMutableContextFromRoot(ctx), h.arm, q)
    query = sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(ctx))
    inspector = sg.model_inspector()
    ids = {inspector.GetName(g): g for g in inspector.GetAllGeometryIds(Role.kProximity)}
    assert set(ids) == {s.name for s in model.shapes}
    X_BW = ac.world_in_base(xyz, sc.X_WO, moprp.R_OB)[0]
    F = model.scene_frames(q[None], X_BW)[0]
    X_WB = h.X_WBase
    for s in model.shapes:
        g = ids[s.name]
        kind, size = _dims(inspector.GetShape(g))
        assert (kind, size) == (s.kind, pytest.approx(s.size, abs=1e-15)), s.name
        X_W = query.GetPoseInWorld(g).GetAsMatrix4()
        np.testing.assert_allclose(X_WB @ F[s.frame] @ s.X_FG, X_W, atol=1e-12, err_msg=s.name)
    candidates = {frozenset((inspector.GetName(a), inspector.GetName(b)))
                  for a, b in inspector.GetCollisionCandidates()}
    ours = {frozenset(model.pair_names(m)) for m in range(len(model.pairs))}
    assert ours == candidates


def _agreement(n_bases: int, per_base: int, near_per_base: int, seed: int):
    rng = np.random.default_rng(seed)
    total = near = acl.Agreement(0, 0, 0, 0)
    for scenario in ("lying", "sitting"):
        sc = moprp.load_scenario(scenario)
        model = moprp.collision_model(sc)
        for xyz in acl.random_bases(sc, n_bases, rng):
            q = rng.uniform(-np.deg2rad(175), np.deg2rad(175), (per_base, 6))
            total = total + acl.compare_at_base(sc, xyz, q, model=model)
            qn = acl.near_target_configurations(sc, xyz, near_per_base, rng)
            near = near + acl.compare_at_base(sc, xyz, qn, model=model)
    return total, near


def test_fast_model_never_calls_a_scene_graph_collision_free():
    """A few thousand random configurations over random bases in both scenarios' bounds, and
    configurations near the feeding target (perturbed by up to 10 deg and 20 mm): no false
    free; false rejects at most 2% of the configurations SceneGraph finds clear."""
    total, near = _agreement(n_bases=6, per_base=250, near_per_base=30, seed=11)
    print(f"random: {total}; near target: {near}")
    assert total.samples == 3000 and near.samples > 500
    assert total.false_free == 0 and near.false_free == 0, (total, near)
    assert 0.1 * total.samples < total.scene_graph_free < 0.9 * total.samples  # not one-sided
    assert total.false_reject_rate <= 0.02 and near.false_reject_rate <= 0.02


@pytest.mark.slow
def test_fast_model_never_calls_a_scene_graph_collision_free_at_scale():
    """Acceptance: 100,000 random configurations over 200 random bases (both
    scenarios) and more than 10,000 near the feeding targets."""
    total, near = _agreement(n_bases=100, per_base=500, near_per_base=20, seed=12)
    print(f"random: {total}; near target: {near}")
    assert total.samples == 100_000 and near.samples >= 10_000
    assert total.false_free == 0 and near.false_free == 0, (total, near)
    assert total.false_reject_rate <= 0.02 and near.false_reject_rate <= 0.02


def test_feed_path_steps_and_confirmation():
    """The confirmed feed moves the TCP <= 1 mm and every joint <= 0.5 deg per step, and the
    default layout's feed is clear in SceneGraph by the scenario's clearance."""
    from implantplan.diagrams import plant as scene

    sc = moprp.load_scenario("lying")
    xyz = np.array(scene.DEFAULT_BASE_XYZ["lying"])
    ev = moprp.evaluate_bases(xyz[None], sc, np.random.default_rng(0))
    branch = int(ev.branch[0])
    q = acl.feed_path(sc, xyz, branch)
    assert q.shape[0] >= 61 and np.all(np.isfinite(q))
    assert np.abs(np.diff(q, axis=0)).max() <= np.deg2rad(0.5)
    np.testing.assert_allclose(q[0], ev.q_pre[0], atol=1e-9)
    np.testing.assert_allclose(q[-1], ev.q[0], atol=1e-9)
    res = acl.confirm_feed(acl.SceneGraphClearance(sc, xyz), sc, branch)
    assert res["ok"] and res["distance"] >= sc.clearance and res["samples"] == q.shape[0]
    assert all(res["pair"]) and res["limit"] == sc.clearance
