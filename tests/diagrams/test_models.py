"""Model files: the AUBO-i10 URDFs, the implanting actuator, the scenes and the plant builder."""

from __future__ import annotations

import importlib.util
import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydrake.geometry import Cylinder, Role
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant

from implantplan import models
from implantplan.diagrams import actuator_urdf as tools
from implantplan.diagrams import plant as scene
from implantplan.diagrams.plant import build_plant
from implantplan.systems.errors import InputError
from implantplan.systems.frames import rpy_to_rotation
from implantplan.systems.robot import kinematics, moprp

AUBO = models.model_path("aubo_i10/aubo_i10.urdf")
AUBO_360 = models.model_path("aubo_i10/aubo_i10_360.urdf")
MASSES = {  # DESIGN.md section 8, kg
    "base_link": 2.592,
    "shoulder_Link": 10.180,
    "upperArm_Link": 18.096,
    "foreArm_Link": 4.448,
    "wrist1_Link": 1.792,
    "wrist2_Link": 1.628,
    "wrist3_Link": 0.198,
}


def _load(path) -> MultibodyPlant:
    plant = MultibodyPlant(0.0)
    parser = Parser(plant)
    models.add_package(parser.package_map())
    parser.AddModels(str(path))
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("base_link"))
    plant.Finalize()
    return plant


def _generator():
    spec = importlib.util.spec_from_file_location(
        "generate_urdf", models.MODELS_DIR / "aubo_i10" / "generate_urdf.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("path", [AUBO, AUBO_360])
def test_urdf_parses_offline_with_names_and_actuators(path):
    plant = _load(path)
    assert plant.num_positions() == 6
    assert plant.num_actuators() == 6
    joints = [plant.get_joint(j) for j in plant.GetJointIndices()]
    names = tuple(j.name() for j in joints if j.num_positions() == 1)
    assert names == kinematics.JOINT_NAMES
    for link in kinematics.LINK_NAMES:
        assert plant.HasBodyNamed(link)


def test_flange_at_home():
    plant = _load(AUBO)
    ctx = plant.CreateDefaultContext()
    X = plant.CalcRelativeTransform(
        ctx, plant.GetFrameByName("base_link"), plant.GetFrameByName("wrist3_Link")
    )
    np.testing.assert_allclose(X.translation(), [0.0, -0.2953, 1.5132], atol=1e-12)
    # At home the flange z axis (J6) points along -y of the base (arm straight up, wrist out).
    np.testing.assert_allclose(X.rotation().matrix()[:, 2], [0.0, -1.0, 0.0], atol=1e-12)


def test_urdfs_differ_only_in_limits_and_match_generator():
    gen = _generator()
    a, b = AUBO.read_text(), AUBO_360.read_text()
    assert a == gen.urdf("175") and b == gen.urdf("360")
    diff = [(x, y) for x, y in zip(a.splitlines(), b.splitlines(), strict=True) if x != y]
    limit_lines = [d for d in diff if "<limit" in d[0]]
    assert len(limit_lines) == 6
    assert len(diff) == 6
    for x, y in limit_lines:
        # Identical apart from lower/upper.
        assert x.split("velocity=")[1] == y.split("velocity=")[1]
    lo175 = np.deg2rad(175.0)
    p175, p360 = _load(AUBO), _load(AUBO_360)
    np.testing.assert_allclose(p175.GetPositionUpperLimits(), lo175, rtol=0, atol=1e-15)
    np.testing.assert_allclose(p175.GetPositionLowerLimits(), -lo175, rtol=0, atol=1e-15)
    np.testing.assert_allclose(p360.GetPositionUpperLimits(), 2 * np.pi, rtol=0, atol=1e-15)
    vel = np.deg2rad([180, 180, 147, 180, 180, 180])
    np.testing.assert_allclose(p175.GetVelocityUpperLimits(), vel, rtol=1e-15)
    np.testing.assert_allclose(p360.GetVelocityUpperLimits(), vel, rtol=1e-15)


def test_masses_and_cylinder_inertias():
    plant = _load(AUBO)
    ctx = plant.CreateDefaultContext()
    for link, mass in MASSES.items():
        body = plant.GetBodyByName(link)
        assert body.default_mass() == pytest.approx(mass, abs=1e-12)
        M = body.CalcSpatialInertiaInBodyFrame(ctx)
        assert M.IsPhysicallyValid()
    # wrist3: solid disc r 0.0375, 0.031 thick, 0.198 kg, about its centre (hand computed).
    M = plant.GetBodyByName("wrist3_Link").CalcSpatialInertiaInBodyFrame(ctx)
    p_com = M.get_com()
    np.testing.assert_allclose(p_com, [0.0, 0.0, -0.0155], atol=1e-15)
    I_com = M.Shift(p_com).CalcRotationalInertia().CopyToFullMatrix3()
    izz = 0.198 * 0.0375**2 / 2  # 1.3921875e-4
    ixx = 0.198 * (3 * 0.0375**2 + 0.031**2) / 12  # 8.5466875e-5
    np.testing.assert_allclose(np.diag(I_com), [ixx, ixx, izz], rtol=1e-9)
    # upper arm: rod along x, length 0.647, r 0.058, 18.096 kg: I_xx = m r^2 / 2.
    M = plant.GetBodyByName("upperArm_Link").CalcSpatialInertiaInBodyFrame(ctx)
    I_com = M.Shift(M.get_com()).CalcRotationalInertia().CopyToFullMatrix3()
    assert I_com[0, 0] == pytest.approx(18.096 * 0.058**2 / 2, rel=1e-9)
    assert I_com[1, 1] == pytest.approx(18.096 * (3 * 0.058**2 + 0.647**2) / 12, rel=1e-9)


def _collision_pairs(diagram, plant, scene_graph, q):
    ctx = diagram.CreateDefaultContext()
    plant.SetPositions(plant.GetMyContextFromRoot(ctx), q)
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(ctx))
    inspector = scene_graph.model_inspector()
    pairs = set()
    for p in query.ComputePointPairPenetration():
        a = inspector.GetName(inspector.GetFrameId(p.id_A))
        b = inspector.GetName(inspector.GetFrameId(p.id_B))
        pairs.add(tuple(sorted((a, b))))
    distances = query.ComputeSignedDistancePairwiseClosestPoints(max_distance=10.0)
    return pairs, min(d.distance for d in distances)


@pytest.mark.parametrize("scenario", ["arm", "lying", "sitting"])
def test_home_pose_collision_free(scenario):
    diagram, plant, sg, _ = build_plant(scenario=scenario)
    pairs, clearance = _collision_pairs(diagram, plant, sg, np.zeros(6))
    assert pairs == set()
    assert clearance > 0.0


def test_real_collisions_are_detected():
    diagram, plant, sg, _ = build_plant(scenario="lying")
    # Upper arm swung down onto the cart below the base (condition 1 of seed 001).
    pairs, clearance = _collision_pairs(diagram, plant, sg, [0, -2.0, 0, 0, 0, 0])
    assert pairs == {("aubo::upperArm_Link", "cart::cart")}
    assert clearance < 0
    # Swung the other way (towards the mouth, World -x) onto the lying patient.
    pairs, _ = _collision_pairs(diagram, plant, sg, [0, 2.0, 0, 0, 0, 0])
    assert ("aubo::upperArm_Link", "patient::patient") in pairs
    # Elbow folded: the wrist (outboard of the forearm, in the upper arm's plane) lands on the
    # upper arm.
    pairs, _ = _collision_pairs(diagram, plant, sg, [0, 0, np.deg2rad(170), 0, 0, 0])
    assert ("aubo::upperArm_Link", "aubo::wrist1_Link") in pairs


@pytest.mark.parametrize("scenario", ["lying", "sitting"])
def test_default_layout_reaches_the_mouth_without_collision(scenario):
    """The default base (scene.DEFAULT_BASE_XYZ) is a feasible MOPRP base, and on its selected
    branch the TCP reaches the mouth frame (End axes R_OE in Oral) with SceneGraph finding the
    pre-feed and target configurations clear of the environment by the scenario's clearance."""
    sc = moprp.load_scenario(scenario)
    xyz = np.array(scene.DEFAULT_BASE_XYZ[scenario])
    ev = moprp.evaluate_bases(xyz[None], sc, np.random.default_rng(0))
    assert ev.feasible[0]
    diagram, plant, sg, h = build_plant(scenario=scenario)
    np.testing.assert_allclose(h.X_WBase, sc.X_WO @ moprp.base_pose(xyz), atol=1e-15)
    ctx = diagram.CreateDefaultContext()
    pc = plant.GetMyMutableContextFromRoot(ctx)
    query = sg.get_query_output_port()
    for q in (ev.q_pre[0], ev.q[0]):
        plant.SetPositions(pc, q)
        d = scene.environment_distance(
            query.Eval(sg.GetMyContextFromRoot(ctx)), sg.model_inspector(), h.environment, 1.0
        )
        assert d >= sc.clearance
        assert not _collision_pairs(diagram, plant, sg, q)[0]
    X_WM = plant.CalcRelativeTransform(pc, plant.world_frame(), h.mouth).GetAsMatrix4()
    X_WE = plant.CalcRelativeTransform(pc, plant.world_frame(), h.tcp).GetAsMatrix4()
    np.testing.assert_allclose(X_WE[:3, 3], X_WM[:3, 3], atol=1e-9)
    np.testing.assert_allclose(X_WE[:3, :3], X_WM[:3, :3] @ moprp.R_OE, atol=1e-9)


def test_environment_filters_only_the_actuator_against_the_patient():
    """Robot vs environment: every pair is checked except the actuator (rod, head, implant enter
    the mouth by design) against the patient and chair; the cart is checked against everything
    not welded to the base."""
    _, plant, sg, h = build_plant(scenario="lying")
    inspector = sg.model_inspector()
    env = set(h.environment)
    names = {inspector.GetName(g) for g in env}
    assert names == {"patient::head", "patient::torso", "patient::legs", "patient::chair",
                     "patient::chair_column", "cart::cart"}
    robot = [g for g in inspector.GetAllGeometryIds(Role.kProximity) if g not in env]
    for g in robot:
        name = inspector.GetName(g)
        for e in env:
            patient = inspector.GetName(e).startswith("patient::")
            expected = (name.startswith("actuator::") and patient) or name.startswith(
                "aubo::base_link")
            assert inspector.CollisionFiltered(g, e) == expected, (name, inspector.GetName(e))


def _agreement(n_per_base: int, seed: int) -> tuple[float, int]:
    """Share of random configurations (uniform within the 175 deg limits) where SceneGraph and
    moprp.collision_clearance agree on arm-vs-environment collision at the scenario's clearance,
    at three base positions of the lying scenario."""
    sc = moprp.load_scenario("lying")
    rng = np.random.default_rng(seed)
    bases = [scene.DEFAULT_BASE_XYZ["lying"], (0.45, -0.3, 0.3), (0.8, 0.0, -0.5)]
    agree = total = 0
    for xyz in np.array(bases):
        diagram, plant, sg, h = build_plant(scenario=sc, X_WBase=sc.X_WO @ moprp.base_pose(xyz))
        ctx = diagram.CreateDefaultContext()
        pc = plant.GetMyMutableContextFromRoot(ctx)
        sgc = sg.GetMyContextFromRoot(ctx)
        inspector = sg.model_inspector()
        q = rng.uniform(-np.deg2rad(175), np.deg2rad(175), (n_per_base, 6))
        d_sg = np.empty(n_per_base)
        for k, qk in enumerate(q):
            plant.SetPositions(pc, qk)
            d_sg[k] = scene.environment_distance(
                sg.get_query_output_port().Eval(sgc), inspector, h.environment, 0.1
            )
        c = moprp.collision_clearance(q, np.repeat(xyz[None], n_per_base, axis=0), sc)
        d_caps = np.minimum(c["environment"], c["cabinet"])
        same = (d_sg < sc.clearance) == (d_caps < sc.clearance)
        # both models see collisions and clear configurations (the check is not one-sided)
        assert 0.1 < np.mean(d_caps < sc.clearance) < 0.9
        agree += int(same.sum())
        total += n_per_base
    return agree / total, total


def test_scene_graph_agrees_with_the_capsule_model():
    share, total = _agreement(1000, seed=7)
    print(f"SceneGraph vs capsule model: {100 * share:.2f}% of {total} configurations agree")
    assert share >= 0.99


@pytest.mark.slow
def test_scene_graph_agrees_with_the_capsule_model_paper_scale():
    share, total = _agreement(3334, seed=11)
    print(f"SceneGraph vs capsule model: {100 * share:.2f}% of {total} configurations agree")
    assert share >= 0.99


def test_filtered_pairs_are_exactly_adjacent_links():
    _, _, sg, _ = build_plant(scenario="arm", tool=True)
    inspector = sg.model_inspector()
    geoms = inspector.GetAllGeometryIds(Role.kProximity)
    body_of = {g: inspector.GetName(inspector.GetFrameId(g)) for g in geoms}
    chain = ["aubo::" + n for n in kinematics.LINK_NAMES] + ["actuator::actuator_base"]
    adjacent = {tuple(sorted(p)) for p in zip(chain, chain[1:], strict=False)}
    for g1, g2 in itertools.combinations(geoms, 2):
        b1, b2 = body_of[g1], body_of[g2]
        if b1 == b2:
            continue
        expected = tuple(sorted((b1, b2))) in adjacent
        assert inspector.CollisionFiltered(g1, g2) == expected, (b1, b2)


def test_actuator_tcp_where_documented():
    diagram, plant, _, h = build_plant(scenario="arm")
    ctx = plant.GetMyContextFromRoot(diagram.CreateDefaultContext())
    rng = np.random.default_rng(3)
    for q in rng.uniform(-3, 3, size=(5, 6)):
        plant.SetPositions(ctx, q)
        X_FT = plant.CalcRelativeTransform(ctx, h.flange, h.tcp).GetAsMatrix4()
        np.testing.assert_allclose(X_FT, tools.X_FT(), atol=1e-14)
        p_FTip = plant.CalcRelativeTransform(ctx, h.flange, h.implant_tip).translation()
        np.testing.assert_allclose(p_FTip, [0.0, -0.031, 0.16], atol=1e-14)
        # numpy kinematics with the tool transform agrees with Drake's tcp frame.
        X_BT = plant.CalcRelativeTransform(ctx, h.base, h.tcp).GetAsMatrix4()
        np.testing.assert_allclose(kinematics.fk(q, tools.X_FT()), X_BT, atol=1e-12)
    # The shipped file is the default of the generator.
    assert models.model_path("tools/implanting_actuator.urdf").read_text() == (
        tools.actuator_urdf()
    )


def test_actuator_parameters_reach_the_geometry():
    text = tools.actuator_urdf(rod_radius=0.004, implant_length=0.025, rod_length=0.2)
    plant = MultibodyPlant(0.0)
    from pydrake.geometry import SceneGraph

    sg = SceneGraph()
    plant.RegisterAsSourceForSceneGraph(sg)
    Parser(plant).AddModelsFromString(text, "urdf")
    plant.Finalize()
    inspector = sg.model_inspector()
    radii = {
        inspector.GetName(g): inspector.GetShape(g).radius()
        for g in inspector.GetAllGeometryIds(Role.kProximity)
        if isinstance(inspector.GetShape(g), Cylinder)
    }
    assert radii["implanting_actuator::rod_collision"] == 0.004
    tip = plant.GetFrameByName("implant_tip").GetFixedPoseInBodyFrame().translation()
    np.testing.assert_allclose(tip, [0.0, -0.025, 0.2], atol=1e-15)
    np.testing.assert_allclose(tools.X_FT(0.2)[:3, 3], [0, 0, 0.2])
    mass, com, inertia = tools.actuator_inertia()
    assert mass == pytest.approx(0.385)
    assert np.all(np.linalg.eigvalsh(inertia) > 0)
    with pytest.raises(InputError, match="rod_radius"):
        tools.actuator_urdf(rod_radius=-0.006)
    with pytest.raises(InputError, match="implant_length"):
        tools.actuator_urdf(implant_length=float("nan"))


def test_scene_frames_and_base_pose():
    X = np.eye(4)
    X[:3, :3] = rpy_to_rotation(np.array([0.0, 0.0, 0.7]))
    X[:3, 3] = [0.3, 0.7, 0.6]
    diagram, plant, sg, h = build_plant(scenario="sitting", X_WBase=X, limits="360")
    ctx = plant.GetMyContextFromRoot(diagram.CreateDefaultContext())
    X_WB = plant.CalcRelativeTransform(ctx, plant.world_frame(), h.base).GetAsMatrix4()
    np.testing.assert_allclose(X_WB, X, atol=1e-14)
    np.testing.assert_allclose(h.X_WBase, X, atol=1e-14)
    np.testing.assert_allclose(plant.GetPositionUpperLimits(), 2 * np.pi)
    # The mouth is the scenario's Oral frame: (0, 0, 1.20), rpy (90, 0, 0) deg.
    X_WM = plant.CalcRelativeTransform(ctx, plant.world_frame(), h.mouth).GetAsMatrix4()
    np.testing.assert_allclose(X_WM[:3, 3], [0.0, 0.0, 1.20], atol=1e-15)
    np.testing.assert_allclose(X_WM[:3, 1], [0, 0, 1], atol=1e-12)  # Oral Y up
    np.testing.assert_allclose(X_WM[:3, 2], [0, -1, 0], atol=1e-12)  # Oral Z = -World Y
    # The cart box hangs under the base at the scenario's cabinet pose in Base.
    X_BC = plant.CalcRelativeTransform(
        ctx, h.base, plant.GetFrameByName("cart", h.cart)
    ).GetAsMatrix4()
    np.testing.assert_allclose(X_BC[:3, 3], [0.15, 0.0, -1.0], atol=1e-15)
    np.testing.assert_allclose(X_BC[:3, :3], np.eye(3), atol=1e-15)
    # Obstacles are World-fixed with the scenario's names, shapes and poses.
    inspector = sg.model_inspector()
    query = sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(
        diagram.CreateDefaultContext()))
    by_name = {inspector.GetName(g): g for g in h.environment}
    head = inspector.GetShape(by_name["patient::head"])
    assert (head.radius(), head.length()) == pytest.approx((0.10, 0.10))
    X_WHead = query.GetPoseInWorld(by_name["patient::head"])
    np.testing.assert_allclose(X_WHead.translation(), [0.0, 0.08, 1.21], atol=1e-12)
    np.testing.assert_allclose(X_WHead.rotation().matrix()[:, 2], [0, 0, 1], atol=1e-12)
    back = inspector.GetShape(by_name["patient::chair_back"])
    assert (back.width(), back.depth(), back.height()) == pytest.approx((0.6, 0.1, 1.0))
    np.testing.assert_allclose(query.GetPoseInWorld(by_name["patient::chair_back"]).translation(),
                               [0.0, 0.40, 0.90], atol=1e-12)


def test_scenario_as_object_or_file(tmp_path):
    sc = moprp.load_scenario("lying")
    _, _, _, h = build_plant(scenario=sc)
    assert h.scenario == "lying"
    np.testing.assert_allclose(h.X_WBase, scene.default_base_pose(sc), atol=1e-15)
    text = moprp.scenario_path("lying").read_text().replace("name: lying", "name: custom")
    path = tmp_path / "custom.yaml"
    path.write_text(text)
    _, _, _, h = build_plant(scenario=path)
    assert h.scenario == "custom"
    # not a bundled name: the default base is the centre of the bounds, (0.7, -0.2, 0) in Oral;
    # Oral Y is World Z, the mouth at 0.85 m: the base at (0.7, 0, 0.65) in World
    np.testing.assert_allclose(h.X_WBase[:3, 3], [0.7, 0.0, 0.65], atol=1e-12)


def test_build_plant_rejects_bad_input():
    with pytest.raises(InputError, match="scenario"):
        build_plant(scenario="standing")
    with pytest.raises(InputError, match="limits"):
        build_plant(limits="180")
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(InputError, match="X_WBase"):
        build_plant(X_WBase=bad)
    with pytest.raises(InputError, match="X_WBase"):
        build_plant(X_WBase=np.full((4, 4), np.nan))
    with pytest.raises(InputError, match="X_WBase"):
        build_plant(X_WBase=np.eye(3))


def test_meshcat_is_optional_and_works_on_an_ephemeral_port():
    from pydrake.geometry import Meshcat, MeshcatParams

    meshcat = Meshcat(MeshcatParams(port=0))
    diagram, _, _, h = build_plant(scenario="sitting", meshcat=meshcat)
    assert h.visualizer is not None
    diagram.ForcedPublish(diagram.CreateDefaultContext())
    assert meshcat.HasPath("/drake/visualizer/aubo/wrist3_Link")
    assert meshcat.HasPath("/drake/visualizer/patient")
    assert build_plant(scenario="sitting")[3].visualizer is None


@settings(max_examples=25, deadline=None)
@given(
    rod_radius=st.floats(0.002, 0.012),
    implant_length=st.floats(0.012, 0.05),
    rod_length=st.floats(0.05, 0.3),
)
def test_actuator_frames_follow_parameters(rod_radius, implant_length, rod_length):
    text = tools.actuator_urdf(rod_radius, implant_length, rod_length=rod_length)
    plant = MultibodyPlant(0.0)
    Parser(plant).AddModelsFromString(text, "urdf")
    plant.Finalize()
    tcp = plant.GetFrameByName("tcp").GetFixedPoseInBodyFrame().GetAsMatrix4()
    tip = plant.GetFrameByName("implant_tip").GetFixedPoseInBodyFrame().translation()
    np.testing.assert_allclose(tcp, tools.X_FT(rod_length), atol=1e-15)
    np.testing.assert_allclose(tip, tools.p_FTip(rod_length, implant_length), atol=1e-15)
    # Eq. 19: the tip lies d12 from the rod axis, on the implant axis through the TCP.
    assert np.linalg.norm(tip - tcp[:3, 3]) == pytest.approx(implant_length, abs=1e-15)
    assert plant.GetBodyByName("actuator_base").default_mass() == pytest.approx(0.385)
