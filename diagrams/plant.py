"""Build the MultibodyPlant + SceneGraph of a scene: AUBO-i10, implanting actuator, cart, chair.

Scenes are model directives in ``models/scenes/<scenario>.dmd.yaml`` (DESIGN.md section 5:
patient lying or sitting). :func:`build_plant` loads them with the ``implantplan`` package
registered on the parser (nothing is downloaded), replaces the world -> base_link weld by the
pose it is given, and optionally adds a Meshcat visualizer. ``scenario="arm"`` is the bare arm
(with the actuator when ``tool``), for kinematics checks.

Collision filtering: adjacent arm links are filtered by the URDF's collision filter groups (and
by MultibodyPlant's parent/child rule); everything welded to the world (cart, chair, patient,
base) is filtered among itself by MultibodyPlant; the actuator is welded to wrist3_Link, so it is
filtered against the flange only. Every other pair is checked.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.common.schema import Transform
from pydrake.geometry import MeshcatVisualizer, MeshcatVisualizerParams, Role, SceneGraph
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.parsing import LoadModelDirectives, Parser, ProcessModelDirectives
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, MultibodyPlant
from pydrake.multibody.tree import Frame, JacobianWrtVariable, ModelInstanceIndex
from pydrake.systems.framework import Diagram, DiagramBuilder

import models
from systems.errors import InputError

SCENARIOS = ("lying", "sitting", "arm")
ARM_FILES = {
    "175": "package://implantplan/aubo_i10/aubo_i10.urdf",
    "360": "package://implantplan/aubo_i10/aubo_i10_360.urdf",
}
ARM, CART, ACTUATOR, PATIENT = "aubo", "cart", "actuator", "patient"


@dataclass
class PlantHandles:
    """What callers need from a built scene.

    Attributes:
        arm, actuator, cart, patient: model instances (None when not in the scene).
        base, flange: the arm's base_link and wrist3_Link frames.
        tcp, implant_tip: the actuator's frames (None without the tool).
        mouth: the patient's ``mouth`` frame (None for ``scenario="arm"``).
        X_WBase: the base pose used, 4x4.
        scenario: the scenario name; limits: "175" or "360".
        visualizer: the MeshcatVisualizer, or None.
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


def directives_path(scenario: str) -> Path:
    """The model directives file of a scenario ("arm" uses the lying file, trimmed)."""
    if scenario not in SCENARIOS:
        raise InputError("scenario", f"expected one of {', '.join(SCENARIOS)}, got {scenario!r}")
    name = "lying" if scenario == "arm" else scenario
    return models.model_path(f"scenes/{name}.dmd.yaml")


def as_rigid_transform(X, field_name: str = "X_WBase") -> RigidTransform:
    """A RigidTransform from a 4x4 array (checked: finite, proper rotation) or a RigidTransform."""
    if isinstance(X, RigidTransform):
        return X
    X = np.asarray(X, dtype=float)
    if X.shape != (4, 4):
        raise InputError(field_name, f"expected a 4x4 pose, got shape {X.shape}")
    if not np.all(np.isfinite(X)):
        raise InputError(field_name, "pose must be finite (found NaN or inf)")
    R = X[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-9 or abs(np.linalg.det(R) - 1.0) > 1e-9:
        raise InputError(field_name, "rotation part is not a proper rotation matrix")
    if np.abs(X[3] - [0.0, 0.0, 0.0, 1.0]).max() > 0:
        raise InputError(field_name, "last row must be [0, 0, 0, 1]")
    # Re-orthonormalize below 1e-9 so Drake's strict rotation check accepts it.
    return RigidTransform(RotationMatrix.ProjectToRotationMatrix(R), X[:3, 3])


def scene_directives(scenario: str, X_WBase, limits: str, tool: bool):
    """Load the scenario's directives and edit them in memory; returns (directives, X_WBase)."""
    if limits not in ARM_FILES:
        raise InputError("limits", f"expected '175' or '360', got {limits!r}")
    directives = LoadModelDirectives(str(directives_path(scenario)))
    keep_models = {ARM} | ({ACTUATOR} if tool else set())
    if scenario != "arm":
        keep_models |= {CART, PATIENT}
    kept = []
    X_used = None
    for d in directives.directives:
        if d.add_model is not None:
            if d.add_model.name not in keep_models:
                continue
            if d.add_model.name == ARM:
                d.add_model.file = ARM_FILES[limits]
        elif d.add_weld is not None:
            owner = d.add_weld.child.split("::")[0]
            if owner not in keep_models:
                continue
            if d.add_weld.child == f"{ARM}::base_link":
                if X_WBase is not None:
                    d.add_weld.X_PC = Transform(as_rigid_transform(X_WBase))
                elif scenario == "arm":
                    d.add_weld.X_PC = Transform(RigidTransform())
                X_used = d.add_weld.X_PC.GetDeterministicValue()
        kept.append(d)
    directives.directives = kept
    return directives, X_used


def build_plant(
    *,
    scenario: str = "lying",
    X_WBase=None,
    limits: str = "175",
    tool: bool = True,
    time_step: float = 0.0,
    meshcat=None,
) -> tuple[Diagram, MultibodyPlant, SceneGraph, PlantHandles]:
    """Build plant + scene graph of a scene and return ``(diagram, plant, scene_graph, handles)``.

    Args:
        scenario: "lying", "sitting" (patient in the chair, robot on its cart) or "arm" (bare arm).
        X_WBase: pose of base_link in World (4x4 or RigidTransform); None keeps the scenario's
            default layout (identity for "arm").
        limits: "175" or "360", which arm URDF to load.
        tool: weld the implanting actuator to the flange.
        time_step: MultibodyPlant time step (0 = continuous).
        meshcat: a ``pydrake.geometry.Meshcat`` to visualize in, or None.

    Returns:
        The built Diagram, its MultibodyPlant and SceneGraph, and :class:`PlantHandles`.
    """
    directives, X_used = scene_directives(scenario, X_WBase, limits, tool)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=time_step)
    parser = Parser(plant)
    models.add_package(parser.package_map())
    ProcessModelDirectives(directives, plant, parser)
    plant.Finalize()
    visualizer = None
    if meshcat is not None:
        visualizer = MeshcatVisualizer.AddToBuilder(
            builder, scene_graph, meshcat, MeshcatVisualizerParams(role=Role.kIllustration)
        )
    diagram = builder.Build()
    diagram.set_name(f"implantplan_{scenario}")

    def instance(name):
        return plant.GetModelInstanceByName(name) if plant.HasModelInstanceNamed(name) else None

    arm, actuator = instance(ARM), instance(ACTUATOR)
    patient = instance(PATIENT)
    handles = PlantHandles(
        arm=arm,
        actuator=actuator,
        cart=instance(CART),
        patient=patient,
        base=plant.GetFrameByName("base_link", arm),
        flange=plant.GetFrameByName("wrist3_Link", arm),
        tcp=plant.GetFrameByName("tcp", actuator) if actuator is not None else None,
        implant_tip=plant.GetFrameByName("implant_tip", actuator) if actuator is not None else None,
        mouth=plant.GetFrameByName("mouth", patient) if patient is not None else None,
        X_WBase=np.asarray(X_used.GetAsMatrix4()),
        scenario=scenario,
        limits=limits,
        visualizer=visualizer,
    )
    return diagram, plant, scene_graph, handles


def fk_jacobian_loop(
    plant: MultibodyPlant, context, base: Frame, frame: Frame, q, X_FT=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drake's FK and Jacobians over a batch of configurations, one SetPositions at a time.

    The MultibodyPlant reference for ``systems.kinematics`` (tests, benchmarks): the same
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
