"""Build the MultibodyPlant + SceneGraph of a scene: AUBO-i10, implanting actuator, cart, patient.

One model of the room: the MOPRP scenario (``models/scenarios/<name>.yaml``, read by
``systems.robot.moprp.load_scenario``; DESIGN.md section 5: patient lying or sitting) is the source
of
truth for the patient, the chair, the cart and the Oral (mouth) frame. :func:`build_plant` loads
the model files (arm, actuator) through in-memory model directives (:func:`scene_directives`,
the ``implantplan`` package registered on the parser, nothing downloaded), welds base_link at
the pose it is given, and for a scenario adds the scenario's geometry
(:func:`add_scenario_geometry`): the obstacles as World-fixed capsules and boxes (collision +
visual, the scenario's names) on a ``patient`` body welded to World, with a ``mouth`` frame at
the scenario's X_WO, and the cart box on a ``cart`` body welded to base_link at the scenario's
``cabinet.box`` pose in Base. ``scenario="arm"`` is the bare arm (with the actuator when
``tool``), for kinematics checks. Meshcat visualization is optional.

Collision filtering: adjacent arm links are filtered by the URDF's collision filter groups (and
by MultibodyPlant's parent/child rule); everything welded to the world (cart, patient, base) is
filtered among itself by MultibodyPlant; the actuator is welded to wrist3_Link, so it is
filtered against the flange. :func:`filter_environment_pairs` adds one rule: the actuator's
shapes (rod, head, implant) are not checked against the patient and chair, they enter the mouth
by design (their clearance is the FPSM's job, seed 000). Every other pair is checked, and the
fast model of ``systems.robot.arm_collision`` checks exactly the same pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.common.schema import Transform
from pydrake.geometry import (
    Box,
    Capsule,
    CollisionFilterDeclaration,
    GeometrySet,
    MeshcatVisualizer,
    MeshcatVisualizerParams,
    Role,
    SceneGraph,
)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.parsing import (
    AddModel,
    AddWeld,
    ModelDirective,
    ModelDirectives,
    Parser,
    ProcessModelDirectives,
)
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, CoulombFriction, MultibodyPlant
from pydrake.multibody.tree import (
    FixedOffsetFrame,
    Frame,
    JacobianWrtVariable,
    ModelInstanceIndex,
    SpatialInertia,
)
from pydrake.systems.framework import Diagram, DiagramBuilder

from implantplan import models
from implantplan.systems import validate
from implantplan.systems.errors import InputError
from implantplan.systems.frames import frame_from_z
from implantplan.systems.robot import arm_collision, moprp

SCENARIOS = ("lying", "sitting", "arm")
ARM_FILES = {
    "175": "package://implantplan/aubo_i10/aubo_i10.urdf",
    "360": "package://implantplan/aubo_i10/aubo_i10_360.urdf",
}
ACTUATOR_FILE = "package://implantplan/tools/implanting_actuator.urdf"
ARM, CART, ACTUATOR, PATIENT = "aubo", "cart", "actuator", "patient"
# Default base positions in Oral (m) of the bundled scenarios: the knee of 100 random feasible
# MOPRP bases (analyses.simulate.select_layout, seed 0), rounded to 1 cm; tests/test_models.py
# checks they stay feasible for MOPRP and collision-free in SceneGraph along the feed.
DEFAULT_BASE_XYZ = {"lying": (0.56, -0.15, -0.25), "sitting": (0.56, -0.33, -0.25)}
OBSTACLE_RGBA = {"capsule": (1.0, 0.85, 0.7, 0.6), "box": (0.8, 0.7, 0.5, 0.6)}
CART_RGBA = (0.5, 0.5, 0.55, 0.6)


@dataclass
class PlantHandles:
    """What callers need from a built scene.

    Attributes:
        arm, actuator, cart, patient: model instances (None when not in the scene).
        base, flange: the arm's base_link and wrist3_Link frames.
        tcp, implant_tip: the actuator's frames (None without the tool).
        mouth: the scenario's Oral (feeding target) frame at X_WO, on the patient body (None for
            ``scenario="arm"``).
        X_WBase: the base pose used, 4x4.
        scenario: the scenario name; limits: "175" or "360".
        visualizer: the MeshcatVisualizer, or None.
        environment: SceneGraph ids of the patient/chair/cart collision geometries.
    """

    arm: ModelInstanceIndex
    actuator: ModelInstanceIndex | None
    cart: ModelInstanceIndex | None
    patient: ModelInstanceIndex | None
    base: Frame
    flange: Frame
    tcp: Frame | None
    implant_tip: Frame | None
    mouth: Frame | None
    X_WBase: np.ndarray
    scenario: str
    limits: str
    visualizer: MeshcatVisualizer | None = field(default=None)
    environment: tuple = field(default=())


@dataclass(frozen=True)
class ScenarioGeometry:
    """What :func:`add_scenario_geometry` added: model instances, the mouth frame, geometry ids."""

    patient: ModelInstanceIndex
    cart: ModelInstanceIndex
    mouth: Frame
    environment: tuple
    obstacles: tuple = ()


def resolve_scenario(scenario) -> moprp.Scenario | None:
    """The MOPRP scenario of ``scenario``: None for "arm", a bundled name, a YAML path or a
    :class:`systems.robot.moprp.Scenario` (returned as is)."""
    if isinstance(scenario, moprp.Scenario):
        return scenario
    if isinstance(scenario, (str, Path)):
        if str(scenario) == "arm":
            return None
        if str(scenario) in moprp.BUNDLED or Path(scenario).is_file():
            return moprp.load_scenario(scenario)
    raise InputError(
        "scenario",
        f"expected one of {', '.join(SCENARIOS)}, a scenario YAML file or a Scenario, "
        f"got {scenario!r}",
    )


def default_base_pose(sc: moprp.Scenario | None) -> np.ndarray:
    """X_WBase used when none is given: identity for the bare arm, :data:`DEFAULT_BASE_XYZ` for
    the bundled scenarios, else the centre of the scenario's base bounds (not checked for
    collisions: pass X_WBase for other scenarios)."""
    if sc is None:
        return np.eye(4)
    xyz = DEFAULT_BASE_XYZ.get(sc.name, (sc.lower + sc.upper) / 2)
    return sc.X_WO @ moprp.base_pose(np.asarray(xyz, dtype=float))


def as_rigid_transform(X, field_name: str = "X_WBase") -> RigidTransform:
    """A RigidTransform from a 4x4 array (checked: finite, proper rotation) or a RigidTransform."""
    if isinstance(X, RigidTransform):
        return X
    X = validate.pose(X, field_name)
    # Re-orthonormalize (within validate's tolerance) so Drake's strict rotation check accepts it.
    return RigidTransform(RotationMatrix.ProjectToRotationMatrix(X[:3, :3]), X[:3, 3])


def scene_directives(scenario, X_WBase, limits: str, tool: bool):
    """Model directives of the model files of a scene: the arm (base_link welded to World at
    X_WBase, or the scenario's default) and the actuator on the flange when ``tool``.

    The scenario's environment is not a model file: add it with :func:`add_scenario_geometry`.

    Returns:
        ``(directives, X_WBase)``, the pose as a RigidTransform.
    """
    sc = resolve_scenario(scenario)
    if limits not in ARM_FILES:
        raise InputError("limits", f"expected '175' or '360', got {limits!r}")
    X = as_rigid_transform(default_base_pose(sc) if X_WBase is None else X_WBase)
    items = [
        ModelDirective(add_model=AddModel(name=ARM, file=ARM_FILES[limits])),
        ModelDirective(
            add_weld=AddWeld(parent="world", child=f"{ARM}::base_link", X_PC=Transform(X))
        ),
    ]
    if tool:
        items += [
            ModelDirective(add_model=AddModel(name=ACTUATOR, file=ACTUATOR_FILE)),
            ModelDirective(
                add_weld=AddWeld(parent=f"{ARM}::wrist3_Link", child=f"{ACTUATOR}::actuator_base")
            ),
        ]
    return ModelDirectives(directives=items), X


def _rt(X) -> RigidTransform:
    return RigidTransform(RotationMatrix(np.asarray(X)[:3, :3]), np.asarray(X)[:3, 3])


def add_scenario_geometry(plant: MultibodyPlant, sc: moprp.Scenario) -> ScenarioGeometry:
    """Add a scenario's environment to an unfinalized plant that holds the arm.

    The obstacles become collision + visual geometry (the scenario's names) on a ``patient``
    body welded to World at the identity, so they are World-fixed; the ``mouth`` frame on it is
    the scenario's Oral pose X_WO. The cart box (``cabinet.box``) goes on a ``cart`` body welded
    to base_link at X_BC. Both bodies are massless (welded, they carry no dynamics).
    """
    friction = CoulombFriction(0.5, 0.5)
    patient = plant.AddModelInstance(PATIENT)
    body = plant.AddRigidBody(PATIENT, patient, SpatialInertia.Zero())
    plant.WeldFrames(plant.world_frame(), body.body_frame())
    ids = []
    for o in sc.obstacles:
        if o.kind == "box":
            shape, X = Box(*(2 * o.half_size)), o.X_WB
        else:
            axis = o.p1 - o.p0
            length = float(np.linalg.norm(axis))
            z = axis / length if length > 0 else np.array([0.0, 0.0, 1.0])
            shape, X = Capsule(o.radius, length), frame_from_z((o.p0 + o.p1) / 2, z)
        ids.append(plant.RegisterCollisionGeometry(body, _rt(X), shape, o.name, friction))
        plant.RegisterVisualGeometry(body, _rt(X), shape, o.name, np.array(OBSTACLE_RGBA[o.kind]))
    mouth = plant.AddFrame(FixedOffsetFrame("mouth", body.body_frame(), _rt(sc.X_WO)))
    cart = plant.AddModelInstance(CART)
    cart_body = plant.AddRigidBody(CART, cart, SpatialInertia.Zero())
    plant.WeldFrames(plant.GetFrameByName("base_link"), cart_body.body_frame(), _rt(sc.X_BC))
    box = Box(*(2 * sc.cabinet_half))
    obstacles = tuple(ids)
    ids.append(plant.RegisterCollisionGeometry(cart_body, RigidTransform(), box, CART, friction))
    plant.RegisterVisualGeometry(cart_body, RigidTransform(), box, CART, np.array(CART_RGBA))
    return ScenarioGeometry(patient=patient, cart=cart, mouth=mouth, environment=tuple(ids),
                            obstacles=obstacles)


def filter_environment_pairs(plant: MultibodyPlant, scene_graph: SceneGraph,
                             geometry: ScenarioGeometry) -> None:
    """Exclude the actuator vs patient/chair pairs (see the module docstring; the rule is
    ``systems.robot.arm_collision.TOOL_VS_PATIENT_FILTERED``)."""
    if not arm_collision.TOOL_VS_PATIENT_FILTERED or not plant.HasModelInstanceNamed(ACTUATOR):
        return
    tool = plant.GetModelInstanceByName(ACTUATOR)
    tool_ids = [g for b in plant.GetBodyIndices(tool)
                for g in plant.GetCollisionGeometriesForBody(plant.get_body(b))]
    scene_graph.collision_filter_manager().Apply(
        CollisionFilterDeclaration().ExcludeBetween(GeometrySet(list(geometry.obstacles)),
                                                    GeometrySet(tool_ids))
    )


def environment_distance(query, inspector, environment, max_distance: float) -> float:
    """Smallest signed distance (m) of the unfiltered robot-vs-environment pairs of a SceneGraph
    query object, or +inf when none is within ``max_distance``."""
    env = set(environment)
    d = [
        p.distance
        for p in query.ComputeSignedDistancePairwiseClosestPoints(max_distance=max_distance)
        if (p.id_A in env) != (p.id_B in env)
    ]
    return min(d, default=float("inf"))


def add_scene(plant: MultibodyPlant, scene_graph: SceneGraph, scenario, X_WBase, limits: str,
              tool: bool):
    """Fill an empty plant registered with ``scene_graph`` with a scene and finalize it: the
    model files (:func:`scene_directives`), the scenario's geometry
    (:func:`add_scenario_geometry`) and its collision filters (:func:`filter_environment_pairs`).
    The one recipe of :func:`build_plant` and of diagrams.teleop's own diagram.

    Returns:
        ``(X_WBase, geometry)``: the base pose used (RigidTransform) and the
        :class:`ScenarioGeometry` (None for "arm").
    """
    sc = resolve_scenario(scenario)
    directives, X_used = scene_directives(sc if sc is not None else "arm", X_WBase, limits, tool)
    parser = Parser(plant)
    models.add_package(parser.package_map())
    ProcessModelDirectives(directives, plant, parser)
    env = add_scenario_geometry(plant, sc) if sc is not None else None
    plant.Finalize()
    if env is not None:
        filter_environment_pairs(plant, scene_graph, env)
    return X_used, env


def build_plant(
    *,
    scenario="lying",
    X_WBase=None,
    limits: str = "175",
    tool: bool = True,
    time_step: float = 0.0,
    meshcat=None,
) -> tuple[Diagram, MultibodyPlant, SceneGraph, PlantHandles]:
    """Build plant + scene graph of a scene and return ``(diagram, plant, scene_graph, handles)``.

    Args:
        scenario: "lying", "sitting" (the bundled MOPRP scenarios), a scenario YAML path, a
            :class:`systems.robot.moprp.Scenario`, or "arm" (bare arm).
        X_WBase: pose of base_link in World (4x4 or RigidTransform); None keeps the scenario's
            default layout (:func:`default_base_pose`; identity for "arm").
        limits: "175" or "360", which arm URDF to load.
        tool: weld the implanting actuator to the flange.
        time_step: MultibodyPlant time step (0 = continuous).
        meshcat: a ``pydrake.geometry.Meshcat`` to visualize in, or None.

    Returns:
        The built Diagram, its MultibodyPlant and SceneGraph, and :class:`PlantHandles`.
    """
    sc = resolve_scenario(scenario)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=time_step)
    X_used, env = add_scene(
        plant, scene_graph, sc if sc is not None else "arm", X_WBase, limits, tool
    )
    visualizer = None
    if meshcat is not None:
        visualizer = MeshcatVisualizer.AddToBuilder(
            builder, scene_graph, meshcat, MeshcatVisualizerParams(role=Role.kIllustration)
        )
    diagram = builder.Build()
    name = "arm" if sc is None else sc.name
    diagram.set_name(f"implantplan_{name}")

    def instance(n):
        return plant.GetModelInstanceByName(n) if plant.HasModelInstanceNamed(n) else None

    arm, actuator = instance(ARM), instance(ACTUATOR)
    handles = PlantHandles(
        arm=arm,
        actuator=actuator,
        cart=env.cart if env else None,
        patient=env.patient if env else None,
        base=plant.GetFrameByName("base_link", arm),
        flange=plant.GetFrameByName("wrist3_Link", arm),
        tcp=plant.GetFrameByName("tcp", actuator) if actuator is not None else None,
        implant_tip=plant.GetFrameByName("implant_tip", actuator) if actuator is not None else None,
        mouth=env.mouth if env else None,
        X_WBase=np.asarray(X_used.GetAsMatrix4()),
        scenario=name,
        limits=limits,
        visualizer=visualizer,
        environment=env.environment if env else (),
    )
    return diagram, plant, scene_graph, handles


def fk_jacobian_loop(
    plant: MultibodyPlant, context, base: Frame, frame: Frame, q, X_FT=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drake's FK and Jacobians over a batch of configurations, one SetPositions at a time.

    The MultibodyPlant reference for ``systems.robot.kinematics`` (tests, benchmarks): the same
    quantities and conventions as ``fk``, ``jacobian_space`` and ``jacobian_body``.

    Args:
        plant, context: a finalized plant whose positions are the 6 arm joints, and its context.
        base, frame: base_link and the flange (wrist3_Link) frames.
        q: (n, 6) configurations.
        X_FT: 4x4 pose of the tool frame in ``frame`` (None = the flange itself).

    Returns:
        ``(X_BT (n,4,4), J_space (n,6,6), J_body (n,6,6))``: CalcRelativeTransform, and
        CalcJacobianSpatialVelocity(kQDot) at the tool origin measured in ``base``, expressed
        in ``base`` and in the tool frame (rows [w; v]).
    """
    q = np.asarray(q, dtype=float).reshape(-1, plant.num_positions())
    X_FT = np.eye(4) if X_FT is None else np.asarray(X_FT, dtype=float)
    p_FT, R_FT = X_FT[:3, 3], X_FT[:3, :3]
    n = len(q)
    X = np.empty((n, 4, 4))
    Js = np.empty((n, 6, 6))
    Jb = np.empty((n, 6, 6))
    wrt = JacobianWrtVariable.kQDot
    for i, qi in enumerate(q):
        plant.SetPositions(context, qi)
        X[i] = plant.CalcRelativeTransform(context, base, frame).GetAsMatrix4()
        Js[i] = plant.CalcJacobianSpatialVelocity(context, wrt, frame, p_FT, base, base)
        Jb[i] = plant.CalcJacobianSpatialVelocity(context, wrt, frame, p_FT, base, frame)
    X = X @ X_FT
    Jb[:, :3] = R_FT.T @ Jb[:, :3]  # re-express from the flange's axes in the tool's
    Jb[:, 3:] = R_FT.T @ Jb[:, 3:]
    return X, Js, Jb
