"""The teleoperated-feeding diagram (DESIGN.md section 7).

```
MasterDevice --V_WE_command--> CommandLimiter --V_WE_limited--> VirtualFixtureForceLaw
VirtualFixtureForceLaw --V_WE_corrected--> SafetySupervisor --X_WE_desired--> DiffIK integrator
SafetySupervisor --X_WE_desired--> VirtualFixtureForceLaw (the commanded pose it constrains)
DiffIK --q_desired--> (kinematic) positions of the plant   | (dynamic) interpolator ->
                      inverse dynamics controller -> MultibodyPlant at 1 ms
q (plant) --> ToolPose --X_WE--> FpsmEstimator, MasterDevice (finishing)
(the supervisor evaluates its barrier at the desired pose it integrates)
loggers: q, supervisor barrier, command status, FPSM safety, alarm (the tool pose and the
         fixture's violation follow from q offline);  scene graph --> Meshcat (optional)
```

The operator's command is limited before the fixture (systems.teleop.command_limits: a
non-finite or absurd twist, or a jump of the handle, is a fault: held at zero, latched, logged;
a merely fast one is clipped to the speed limits), and the fixture and the barrier both act on
the desired pose the supervisor integrates, whose every step the supervisor keeps within the
same speed limits: the commanded pose stays in the fixture's admissible region and the tool
between two control steps within half a step of its ends (the reasoning is in
systems.teleop.command_limits).

One diagram per case: the master motion is a parameter of the context
(systems.teleop.master_device.MasterDevice.set_motion), so ``simulate(teleop, T, motion=m)``
replays any run on the same diagram (diagrams.feeding runs K feeds this way); so are the head's
motion and the tracker's noise seed (``head_motion=``, ``tracker_seed=``; HeadMotionSource.
set_motion, Tracker.set_seed). :func:`final_pose` is a run reduced to the tool's last pose, on
a diagram that may log the joints alone (``logs=False``): a study of many runs.

Two modes:

- ``kinematic`` (default for the experiments): Drake's DifferentialInverseKinematicsIntegrator
  (200 Hz) integrates its own joint positions, which *are* the arm's positions: the plant is the
  kinematic model (DiffIK's robot, and MultibodyPositionToGeometryPose feeds the scene graph);
  nothing integrates dynamics.
- ``dynamic``: the same q_desired goes through StateInterpolatorWithDiscreteDerivative to an
  InverseDynamicsController driving the discrete MultibodyPlant (1 ms step) through its actuators.

Frames: End = the actuator's ``tcp`` frame on the plant; seed 000's Tool frame (x along the rod
out of the mouth, z along the implant axis) is End rotated by R_ET = R_OE^T (systems.robot.moprp:
Oral
= Tool, and End's axes in Oral are R_OE). The FPSM and the virtual fixture live in the Center
frame, placed in World by ``X_WCenter``.

The awake patient (``head_motion``; DESIGN.md section 7): a HeadMotionSource
moves the patient body (all of the scenario's patient and chair geometry, rigidly with the head)
in the scene; a Tracker estimates the head pose; TrackedHeadFrame gives the fixture, the
estimator and the master the measured tool pose in the tracked head (X_WCenter0 X_WHead^-1
X_WE: the constant X_WCenter composed with the tracked head displacement) and sends DiffIK the
supervisor's desired pose carried with the tracked head, so the arm follows the mouth (the
tracked displacement stepped no faster than DiffIK's joints can follow, from DiffIK's joints:
systems.teleop.tracked_frame, so the arm makes every step of its command in that frame); a
HeadGuard between the fixture and the supervisor grows the supervisor's margin with the tracked
head speed and backs the tool out on lost tracking or a head too fast to follow. With
``follow=False`` the head moves but the arm ignores it (the comparison run). In dynamic mode the
plant owns its geometry poses, so the patient's collision geometry stays where the plan put it
(the arm's links meet it there; the tool, filtered against it, is guarded by the FPSM in the
tracked frame) while everything else (tracker, guard, fixture, the measured deviation) follows
the moving head as in kinematic mode.

The implant's insertion (``insertion``, systems.teleop.insertion): after the feed the operator
drives the tool along the implant's axis to the planned depth; a second VirtualFixtureForceLaw
holds the insertion fixture (the implant axis, the depth stop) and an InsertionPhase switches
the supervisor's input from the feed's fixture to it at the run's insertion start (the
``insertion_start`` of :func:`simulate`), releasing the FPSM barrier from then on (the implant
enters the bone by design; the speed limits stay). The operator then finishes by eye towards
the planned final TCP instead of the feeding target.

```
HeadMotion --X_WHead--> Tracker --X_WHead_est, V, lost--> TrackedHeadFrame, HeadGuard
HeadMotion --D_W--> MovePatient (plant's geometry poses, patient body displaced) --> SceneGraph
tool_pose --X_WE--> TrackedHeadFrame --X_WE_head--> fixture, estimator, master
fixture --> HeadGuard --V, margin_extra--> supervisor --X_WE_desired_head--> TrackedHeadFrame
TrackedHeadFrame --X_WE_desired--> DiffIK --q--> TrackedHeadFrame
```

The scene (arm, actuator, cart, chair and patient) is diagrams.plant's: build_plant returns a
finished diagram, so this module adds the same model directives and the same scenario geometry
(diagrams.plant.add_scenario_geometry, the MOPRP scenario's patient/chair/cart) to its own
builder, with the same collision filters.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    FramePoseVector,
    MeshcatVisualizer,
    MeshcatVisualizerParams,
    Role,
    SceneGraph,
)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.inverse_kinematics import (
    DifferentialInverseKinematicsIntegrator,
    DifferentialInverseKinematicsParameters,
)
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable
from pydrake.systems.analysis import Simulator
from pydrake.systems.controllers import InverseDynamicsController
from pydrake.systems.framework import BasicVector, DiagramBuilder, LeafSystem, ValueProducer
from pydrake.systems.primitives import LogVectorOutput, StateInterpolatorWithDiscreteDerivative
from pydrake.systems.rendering import MultibodyPositionToGeometryPose

from implantplan.diagrams import plant as scene
from implantplan.systems import actuator
from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import invert, transform
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.fixture import VirtualFixture
from implantplan.systems.placement.scan_clearance import CappedScanClearance, ScanClearance
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot.moprp import R_OE
from implantplan.systems.safety import SafetySpec
from implantplan.systems.teleop.command_limits import FAULT, CommandLimiter, CommandLimits
from implantplan.systems.teleop.fixture_system import VirtualFixtureForceLaw
from implantplan.systems.teleop.fpsm_estimator import FpsmEstimator, ToolLines
from implantplan.systems.teleop.head_guard import GuardSettings, HeadGuard
from implantplan.systems.teleop.head_motion import HeadMotion, HeadMotionSource
from implantplan.systems.teleop.insertion import R_INSERT, InsertionPhase
from implantplan.systems.teleop.master_device import IncrementalMapping, MasterDevice, MasterMotion
from implantplan.systems.teleop.supervisor import Barrier, SafetySupervisor
from implantplan.systems.teleop.tracked_frame import frame_step
from implantplan.systems.teleop.tracker import Tracker, TrackerParams

MODES = ("kinematic", "dynamic")
CAP_BAND = 2e-3  # m: the scan clearance of the barrier and the alarm is resolved up to their
# margin plus this (above it the value is the cap: the branch and bound stops there)
X_ET = transform(R_OE.T, np.zeros(3))  # seed 000's Tool frame in the plant's TCP frame (End)


@dataclass
class TeleopCase:
    """A feeding case in World (SI units).

    Attributes:
        scenario: the plant scene ("lying" / "sitting" / "arm").
        X_WBase: base_link pose in World.
        q_start: (6,) arm configuration at the start (the pre-feed pose).
        X_WCenter: the FPSM's Center frame in World.
        fpsm: the surrogate model (Center frame).
        vf: the virtual fixture (Center frame).
        X_WTarget: the feeding target: Tool (= Oral) pose in World.
        rod_radius, implant_length: the actuator (m), the paper's lines' radius and d12.
        limits: "175" or "360".
        label: free text for reports.
        instrument: the instrument in the mouth (systems.instrument), the body the supervisor
            and the estimator bound; None: the paper's tool of ``rod_radius`` and
            ``implant_length``.
        safety: the plan's safety spec: the barrier's margin and rate, the alarm margin and
            the command limits the diagram enforces (systems.safety; the plan's ``safety``).
        scan: the scan bound of ``instrument`` against the plan's opened scan
            (systems.placement.scan_clearance.ScanClearance): the clearance the supervisor's
            barrier and the estimator take, capped above their margins (the bound the plan
            certified the feed with); None: the FPSM's sound clearance.
    """

    scenario: str
    X_WBase: np.ndarray
    q_start: np.ndarray
    X_WCenter: np.ndarray
    fpsm: Fpsm
    vf: VirtualFixture
    X_WTarget: np.ndarray
    rod_radius: float = actuator.ROD_RADIUS
    implant_length: float = actuator.IMPLANT_LENGTH
    limits: str = "175"
    label: str = ""
    instrument: Instrument | None = None
    safety: SafetySpec = field(default_factory=SafetySpec)
    scan: ScanClearance | None = None

    @property
    def tool(self) -> Instrument:
        """The instrument the supervisor and the estimator bound (every solid; the plan's)."""
        if self.instrument is not None:
            return self.instrument
        return Instrument.paper(rod_radius=self.rod_radius, implant_length=self.implant_length)

    @property
    def X_FE(self) -> np.ndarray:
        """The plant's TCP (End) in the flange frame."""
        return actuator.X_FT()

    def X_WE(self, q) -> np.ndarray:
        """End pose(s) in World for configurations ``q`` (..., 6)."""
        return self.X_WBase @ kin.fk(q, self.X_FE)

    @property
    def X_WE_target(self) -> np.ndarray:
        return self.X_WTarget @ np.linalg.inv(X_ET)


class ToolPose(LeafSystem):
    """Forward kinematics of the arm + actuator: the TCP (End) pose from the joint positions.

    .. pydrake_system::

        name: ToolPose
        input_ports:
        - q
        output_ports:
        - X_WE
        - p_WE

    ``q`` (6, or the 12-vector arm state [q; v] when ``state_input``): joint positions.
    ``X_WE`` (abstract RigidTransform) and ``p_WE`` (3): the pose / position of the plant's
    ``tcp`` frame in World, from the plant's own kinematics in a private context (~2 us; the
    numpy core systems.robot.kinematics.fk gives the same pose, tested, at ~45 us a call).
    """

    def __init__(self, plant: MultibodyPlant, frame, *, state_input: bool = False):
        super().__init__()
        self._plant = plant
        self._frame = frame
        self._plant_context = plant.CreateDefaultContext()
        self._q = self.DeclareVectorInputPort("q", 12 if state_input else 6)
        self._X = self.DeclareAbstractOutputPort(
            "X_WE", lambda: AbstractValue.Make(RigidTransform()), self._calc_pose
        )
        self._p = self.DeclareVectorOutputPort("p_WE", 3, self._calc_position)

    def _calc_pose(self, context, value):
        q = self._q.Eval(context)[:6]
        self._plant.SetPositions(self._plant_context, q)
        value.set_value(self._frame.CalcPoseInWorld(self._plant_context))

    def _calc_position(self, context, output: BasicVector):
        output.SetFromVector(self._X.Eval(context).translation())


@dataclass
class Teleop:
    """A built feeding diagram and handles to its parts (keep it alive while simulating)."""

    diagram: object
    plant: MultibodyPlant
    scene_graph: SceneGraph
    mode: str
    master: MasterDevice
    vf: VirtualFixtureForceLaw
    supervisor: SafetySupervisor
    limiter: CommandLimiter
    estimator: FpsmEstimator
    diffik: DifferentialInverseKinematicsIntegrator
    tool_pose: ToolPose
    loggers: dict
    case: TeleopCase
    period: float
    visualizer: object = None
    interpolator: object = None
    keep: list = field(default_factory=list)
    head: HeadMotionSource | None = None
    tracker: Tracker | None = None
    guard: HeadGuard | None = None
    phase: InsertionPhase | None = None

    def initialize(self, context) -> None:
        """Put the arm, DiffIK and the fixture's desired pose at the case's start."""
        q0 = np.asarray(self.case.q_start, dtype=float)
        self.diffik.SetPositions(self.diffik.GetMyMutableContextFromRoot(context), q0)
        plant_context = self.plant.GetMyMutableContextFromRoot(context) if (
            self.mode == "dynamic"
        ) else None
        if plant_context is not None:
            self.plant.SetPositions(plant_context, self.plant.GetModelInstanceByName("aubo"), q0)
            self.interpolator.set_initial_position(
                self.interpolator.GetMyMutableContextFromRoot(context), q0
            )
        self.supervisor.set_desired_pose(
            self.supervisor.GetMyMutableContextFromRoot(context), self.case.X_WE(q0)
        )


def _rt(X) -> RigidTransform:
    return RigidTransform(RotationMatrix.ProjectToRotationMatrix(X[:3, :3]), X[:3, 3])


class TrackedHeadFrame(LeafSystem):
    """The tool in the tracked head and the desired pose carried with it (the awake patient).

    .. pydrake_system::

        name: TrackedHeadFrame
        input_ports:
        - X_WHead_estimated
        - X_WE_measured
        - X_WE_desired_head
        - q
        output_ports:
        - X_WE_head
        - X_WE_desired
        - H

    H, the tracked displacement of the head, is X_WHead_estimated X_WHead0^-1 stepped to no
    faster than the arm can follow (systems.teleop.tracked_frame.frame_step, from the last
    control step's H, at the joints ``q`` (6) of differential IK, with the plant's Jacobian of
    DiffIK's frame, against the joints' velocity limits ``qdot_max``): ``X_WE_head`` = H^-1
    X_WE_measured, the measured tool pose in the head-fixed World (where the constant X_WCenter
    holds: the fixture, the estimator and the master work there), and ``X_WE_desired`` = H
    X_WE_desired_head, the supervisor's desired pose carried with the head, for DiffIK. All
    abstract RigidTransforms. ``H`` (12): H itself, [p (3), R row-major (9)], for the logger
    (the frame the arm's command lives in, :attr:`FeedRun.X_CT_tracked`). State: H of the last
    control step (updated every ``period``, the control period).

    Args:
        X_WHead0: (4, 4) the head's pose at the start (H = identity there).
        plant, frame: the arm's plant (6 positions) and DiffIK's end-effector frame on it (a
            private context of the plant computes its pose and Jacobian, as in ToolPose).
        qdot_max: (6,) the joints' velocity limits (rad/s), differential IK's.
        period: the control period (s).
    """

    def __init__(self, X_WHead0, *, plant: MultibodyPlant, frame, qdot_max, period: float):
        super().__init__()
        self._X0_inv = invert(np.asarray(X_WHead0, dtype=float))
        self._plant, self._frame = plant, frame
        self._plant_context = plant.CreateDefaultContext()
        self._qdot_max = np.asarray(qdot_max, dtype=float).reshape(6)
        self._dt = float(period)
        make = lambda: AbstractValue.Make(RigidTransform())  # noqa: E731
        self._head = self.DeclareAbstractInputPort("X_WHead_estimated", make())
        self._meas = self.DeclareAbstractInputPort("X_WE_measured", make())
        self._des = self.DeclareAbstractInputPort("X_WE_desired_head", make())
        self._q = self.DeclareVectorInputPort("q", 6)
        self.DeclareDiscreteState(_h_vector(np.eye(4)))
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._update)
        self._H_entry = self.DeclareCacheEntry(
            description="H", value_producer=ValueProducer(
                allocate=AbstractValue.Make(np.eye(4)).Clone, calc=self._calc_H),
            prerequisites_of_calc={self.xd_ticket(), self.time_ticket(),
                                   self._head.ticket(), self._des.ticket(), self._q.ticket()})
        H_ticket = {self._H_entry.ticket()}
        self.DeclareAbstractOutputPort("X_WE_head", make, self._calc_head,
                                       prerequisites_of_calc=H_ticket | {self._meas.ticket()})
        self.DeclareAbstractOutputPort("X_WE_desired", make, self._calc_desired,
                                       prerequisites_of_calc=H_ticket | {self._des.ticket()})
        self.DeclareVectorOutputPort("H", 12, self._calc_H_vector,
                                     prerequisites_of_calc=H_ticket)

    def _calc_H(self, context, value):
        x = context.get_discrete_state(0).get_value()
        H_prev = np.eye(4)
        H_prev[:3, 3], H_prev[:3, :3] = x[:3], x[3:].reshape(3, 3)
        goal = self._head.Eval(context).GetAsMatrix4() @ self._X0_inv
        plant, pc, E = self._plant, self._plant_context, self._frame
        plant.SetPositions(pc, self._q.Eval(context))
        X_now = E.CalcPoseInWorld(pc).GetAsMatrix4()
        J_W = plant.CalcJacobianSpatialVelocity(pc, JacobianWrtVariable.kV, E, np.zeros(3),
                                                plant.world_frame(), plant.world_frame())
        H, _ = frame_step(H_prev, goal, self._des.Eval(context).GetAsMatrix4(), X_now, J_W,
                          self._qdot_max, self._dt)
        value.set_value(H)

    def _H(self, context) -> np.ndarray:
        return self._H_entry.Eval(context)

    def _update(self, context, discrete_state):
        discrete_state.get_mutable_vector(0).SetFromVector(_h_vector(self._H(context)))

    def _calc_H_vector(self, context, output: BasicVector):
        output.SetFromVector(_h_vector(self._H(context)))

    def _calc_head(self, context, value):
        value.set_value(_rt(invert(self._H(context)) @ self._meas.Eval(context).GetAsMatrix4()))

    def _calc_desired(self, context, value):
        value.set_value(_rt(self._H(context) @ self._des.Eval(context).GetAsMatrix4()))


def _h_vector(H) -> np.ndarray:
    """(12,) [p (3), R row-major (9)] of a pose (4, 4)."""
    return np.concatenate([H[:3, 3], H[:3, :3].ravel()])


class MovePatient(LeafSystem):
    """The plant's geometry poses with the patient body displaced by the head motion.

    .. pydrake_system::

        name: MovePatient
        input_ports:
        - geometry_pose
        - D_W
        output_ports:
        - geometry_pose

    ``geometry_pose`` (FramePoseVector) in: the plant's frames (MultibodyPositionToGeometryPose);
    out: the same with the patient body's frame pre-multiplied by ``D_W`` (abstract
    RigidTransform, the head's displacement in World).
    """

    def __init__(self, patient_frame_id):
        super().__init__()
        self._id = patient_frame_id
        self._in = self.DeclareAbstractInputPort("geometry_pose",
                                                 AbstractValue.Make(FramePoseVector()))
        self._D = self.DeclareAbstractInputPort("D_W", AbstractValue.Make(RigidTransform()))
        self.DeclareAbstractOutputPort("geometry_pose",
                                       lambda: AbstractValue.Make(FramePoseVector()), self._calc)

    def _calc(self, context, value):
        poses = self._in.Eval(context)
        out = value.get_mutable_value()
        out.clear()
        D = self._D.Eval(context)
        for i in poses.ids():
            out.set_value(i, D.multiply(poses.value(i)) if i == self._id else poses.value(i))


def add_teleop_scene(builder, case: TeleopCase, mode: str, plant_step: float):
    """The case's scene (diagrams.plant.add_scene: model directives with the base welded at
    X_WBase, the scenario's patient/chair/cart geometry and its collision filters) in
    ``builder``. Contact stays on in dynamic mode: the robot meets the same environment as
    MOPRP, with the rod, head and implant filtered against it (they enter the mouth, which the
    FPSM estimator guards)."""
    if mode == "dynamic":
        plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=plant_step)
    else:
        scene_graph = builder.AddSystem(SceneGraph())
        plant = MultibodyPlant(0.0)
        plant.RegisterAsSourceForSceneGraph(scene_graph)
    scene.add_scene(plant, scene_graph, case.scenario, case.X_WBase, case.limits, True)
    if plant.num_positions() != 6:
        raise InputError("scenario", f"expected a 6-DOF scene, got {plant.num_positions()} q")
    return plant, scene_graph


def diffik_parameters(plant: MultibodyPlant, q0, period: float):
    """DiffIK settings: full-pose tracking, the URDF's joint position and velocity limits."""
    params = DifferentialInverseKinematicsParameters(6, 6)
    params.set_time_step(period)
    params.set_nominal_joint_position(np.asarray(q0, dtype=float))
    params.set_joint_position_limits(
        (plant.GetPositionLowerLimits(), plant.GetPositionUpperLimits())
    )
    params.set_joint_velocity_limits(
        (plant.GetVelocityLowerLimits(), plant.GetVelocityUpperLimits())
    )
    params.set_end_effector_velocity_flag(np.ones(6, dtype=bool))
    return params


def build_teleop(
    case: TeleopCase,
    motion: MasterMotion | None = None,
    *,
    mode: str = "kinematic",
    mapping: IncrementalMapping | None = None,
    vf_enabled: bool = True,
    supervisor_enabled: bool = True,
    barrier: Barrier | None = None,
    finish: bool = True,
    period: float = 0.005,
    plant_step: float = 0.001,
    stiffness: float = 2000.0,
    damping: float = 100.0,
    alarm_margin: float | None = None,
    estimator_period: float = 0.02,
    gains: tuple[float, float, float] = (900.0, 1.0, 60.0),
    meshcat=None,
    master=None,
    head_motion: HeadMotion | None = None,
    tracker: TrackerParams | None = None,
    follow: bool = True,
    guard: GuardSettings | None = None,
    limits: CommandLimits | None = None,
    insertion: VirtualFixture | None = None,
    logs: bool = True,
) -> Teleop:
    """Wire the feeding diagram of one case; it replays any master motion.

    The motion is a parameter of the context (MasterDevice.set_motion): ``simulate(teleop, T,
    motion=m)`` runs ``m`` in a fresh context, so all the runs of a case share this diagram.

    Args:
        case: the scene, layout, FPSM, fixture and start configuration.
        motion: the default context's master handle motion (scripted or recorded); None: the
            hand at rest until a run sets one.
        mode: "kinematic" or "dynamic" (see the module docstring).
        mapping: master -> slave incremental mapping (identity by default).
        vf_enabled: False lets the command through unfiltered (experiments without the fixture).
        supervisor_enabled: False integrates the fixture's command without the barrier filter.
        barrier: the supervisor's settings (margin, rate); None: the case's safety spec's
            (:meth:`systems.teleop.supervisor.Barrier.from_spec`).
        finish: the operator finishes by eye towards the feeding target after the script.
        period: control period of DiffIK, the fixture, the estimator and the loggers (s).
        plant_step: the plant's time step in dynamic mode (s).
        stiffness, damping: the fixture's admittance (N/m, N s/m).
        alarm_margin: FPSM alarm threshold on min d_safe (m); None: the case's safety spec's.
        estimator_period: update period of the FPSM estimator and its loggers (s).
        gains: (kp, ki, kd) of the inverse dynamics controller (dynamic mode).
        meshcat: a pydrake.geometry.Meshcat, or None.
        master: a master system to use instead of MasterDevice (a LeafSystem with the output
            port ``V_WE_command``, e.g. systems.teleop.master_input.LiveMasterDevice); ``motion``,
            ``mapping`` and ``finish`` are then its business (no finishing input is wired).
        head_motion: the awake patient's head motion (module notes; in dynamic mode the
            patient's collision geometry stays put); None: the patient is still.
        tracker: the camera's settings (TrackerParams() if None) when ``head_motion`` is set.
        follow: with ``head_motion``, False lets the arm ignore the head (no tracker, no guard).
        guard: the HeadGuard's settings (GuardSettings() if None).
        limits: the command limits (the CommandLimiter before the fixture and every step the
            supervisor integrates); None: the case's safety spec's.
        insertion: the insertion fixture (Center frame; systems.teleop.insertion.
            insertion_fixture): the implant's insertion after the feed (module notes); None: the
            feed alone.
        logs: False logs the joints alone (what :func:`final_pose` reads; :func:`simulate`
            needs every log): a study of many runs that keeps only the placed pose.
    """
    if mode not in MODES:
        raise InputError("mode", f"expected kinematic or dynamic, got {mode!r}")
    tracking = head_motion is not None and follow
    builder = DiagramBuilder()
    plant, scene_graph = add_teleop_scene(builder, case, mode, plant_step)
    tcp = plant.GetFrameByName("tcp")
    q0 = np.asarray(case.q_start, dtype=float)

    if master is not None:
        finish = False
    target = case.X_WTarget[:3, 3] if finish else None
    if finish and insertion is not None:  # finish by eye at the planned depth
        target = case.X_WCenter[:3, :3] @ insertion.origin + case.X_WCenter[:3, 3]
    master = builder.AddSystem(master or MasterDevice(motion, mapping, target_W=target))
    master.set_name("master")
    spec = case.safety
    limits = spec.command_limits if limits is None else limits
    barrier = Barrier.from_spec(spec) if barrier is None else barrier
    alarm_margin = spec.alarm_margin if alarm_margin is None else alarm_margin
    limiter = builder.AddSystem(CommandLimiter(limits, period=period))
    limiter.set_name("command_limiter")
    params = tracker or TrackerParams()
    barrier_clearance = alarm_clearance = None
    if case.scan is not None:
        # the cap above the margin: CAP_BAND, plus what the head guard adds to the margin
        # while the head moves no faster than the arm follows (beyond, the guard retreats)
        settings = guard or GuardSettings()
        extra = (settings.follow_speed * (params.latency + params.period + period)
                 + params.error_bound()) if tracking else 0.0
        barrier_clearance = CappedScanClearance(case.scan, barrier.margin + CAP_BAND + extra)
        alarm_clearance = CappedScanClearance(case.scan, alarm_margin + CAP_BAND)
    vf = builder.AddSystem(
        VirtualFixtureForceLaw(
            case.vf,
            case.X_WCenter,
            R_ET=X_ET[:3, :3],
            period=period,
            stiffness=stiffness,
            damping=damping,
            enabled=vf_enabled,
            integrate=False,
        )
    )
    vf.set_name("virtual_fixture")
    supervisor = builder.AddSystem(
        SafetySupervisor(
            case.fpsm,
            case.X_WCenter,
            case.X_WE(q0),
            case.tool,
            R_ET=X_ET[:3, :3],
            barrier=barrier,
            period=period,
            enabled=supervisor_enabled,
            margin_input=tracking,
            release_input=insertion is not None,
            limits=limits,
            clearance=barrier_clearance,
        )
    )
    supervisor.set_name("safety_supervisor")
    lines = ToolLines.contra_angle(case.rod_radius, case.implant_length,
                                   tool=case.tool).expressed_in(X_ET)
    estimator = builder.AddSystem(
        FpsmEstimator(
            case.fpsm,
            case.X_WCenter,
            lines,
            alarm_margin=alarm_margin,
            period=estimator_period,
            clearance=alarm_clearance,
        )
    )
    estimator.set_name("fpsm_estimator")
    diffik = builder.AddSystem(
        DifferentialInverseKinematicsIntegrator(
            plant,
            tcp,
            period,
            diffik_parameters(plant, q0, period),
            log_only_when_result_state_changes=True,
        )
    )
    diffik.set_name("diff_ik")
    tool_pose = builder.AddSystem(ToolPose(plant, tcp, state_input=(mode == "dynamic")))
    tool_pose.set_name("tool_pose")

    builder.Connect(master.GetOutputPort("V_WE_command"), limiter.GetInputPort("V_WE_command"))
    builder.Connect(limiter.GetOutputPort("V_WE_limited"), vf.GetInputPort("V_WE_command"))
    # the fixture constrains the commanded pose (the supervisor's state: no algebraic loop)
    builder.Connect(supervisor.GetOutputPort("X_WE_desired"), vf.GetInputPort("X_WE"))
    corrected, phase = vf.GetOutputPort("V_WE_corrected"), None
    if insertion is not None:
        vf_in = builder.AddSystem(VirtualFixtureForceLaw(
            insertion, case.X_WCenter, R_ET=X_ET[:3, :3] @ R_INSERT, period=period,
            stiffness=stiffness, damping=damping, enabled=vf_enabled, integrate=False))
        vf_in.set_name("insertion_fixture")
        builder.Connect(limiter.GetOutputPort("V_WE_limited"), vf_in.GetInputPort("V_WE_command"))
        builder.Connect(supervisor.GetOutputPort("X_WE_desired"), vf_in.GetInputPort("X_WE"))
        phase = builder.AddSystem(InsertionPhase())
        phase.set_name("insertion_phase")
        builder.Connect(corrected, phase.GetInputPort("V_WE_feed"))
        builder.Connect(vf_in.GetOutputPort("V_WE_corrected"), phase.GetInputPort("V_WE_insertion"))
        corrected = phase.GetOutputPort("V_WE_corrected")
    head = trk = head_guard = frame = None
    measured = tool_pose.GetOutputPort("X_WE")
    if head_motion is not None:
        head = builder.AddSystem(HeadMotionSource(head_motion, case.X_WCenter))
        head.set_name("head_motion")
    if tracking:
        trk = builder.AddSystem(Tracker(params, case.X_WCenter))
        trk.set_name("tracker")
        builder.Connect(head.GetOutputPort("X_WHead"), trk.GetInputPort("X_WHead"))
        frame = builder.AddSystem(TrackedHeadFrame(
            case.X_WCenter, plant=plant, frame=tcp, period=period,
            qdot_max=np.minimum(-plant.GetVelocityLowerLimits(),
                                plant.GetVelocityUpperLimits())))
        frame.set_name("tracked_head_frame")
        builder.Connect(trk.GetOutputPort("X_WHead_predicted"),
                        frame.GetInputPort("X_WHead_estimated"))
        builder.Connect(measured, frame.GetInputPort("X_WE_measured"))
        builder.Connect(supervisor.GetOutputPort("X_WE_desired"),
                        frame.GetInputPort("X_WE_desired_head"))
        builder.Connect(frame.GetOutputPort("X_WE_desired"), diffik.GetInputPort("X_AE_desired"))
        builder.Connect(diffik.GetOutputPort("joint_positions"), frame.GetInputPort("q"))
        measured = frame.GetOutputPort("X_WE_head")
        axis_W = case.X_WCenter[:3, :3] @ case.vf.direction
        head_guard = builder.AddSystem(HeadGuard(
            axis_W, lag=params.latency + params.period + period,
            error_bound=params.error_bound(), settings=guard, period=period))
        head_guard.set_name("head_guard")
        builder.Connect(corrected, head_guard.GetInputPort("V_WE_corrected"))
        builder.Connect(trk.GetOutputPort("V_WHead_estimated"),
                        head_guard.GetInputPort("V_WHead_estimated"))
        builder.Connect(trk.GetOutputPort("lost"), head_guard.GetInputPort("lost"))
        builder.Connect(measured, head_guard.GetInputPort("X_WE"))
        builder.Connect(head_guard.GetOutputPort("V_WE_guarded"),
                        supervisor.GetInputPort("V_WE_corrected"))
        builder.Connect(head_guard.GetOutputPort("margin_extra"),
                        supervisor.GetInputPort("margin_extra"))
    else:
        builder.Connect(corrected, supervisor.GetInputPort("V_WE_corrected"))
        builder.Connect(supervisor.GetOutputPort("X_WE_desired"),
                        diffik.GetInputPort("X_AE_desired"))
    if phase is not None:
        builder.Connect(phase.GetOutputPort("barrier_release"),
                        supervisor.GetInputPort("barrier_release"))
    builder.Connect(measured, estimator.GetInputPort("X_WT"))
    if finish:
        builder.Connect(measured, master.GetInputPort("X_WE_measured"))

    arm = plant.GetModelInstanceByName("aubo")
    keep, interp = [], None
    if mode == "kinematic":
        q_port = diffik.GetOutputPort("joint_positions")
        to_pose = builder.AddSystem(MultibodyPositionToGeometryPose(plant))
        builder.Connect(q_port, to_pose.get_input_port())
        poses = to_pose.get_output_port()
        if head is not None and plant.HasBodyNamed(scene.PATIENT):
            move = builder.AddSystem(MovePatient(
                plant.GetBodyFrameIdOrThrow(plant.GetBodyByName(scene.PATIENT).index())))
            move.set_name("move_patient")
            builder.Connect(poses, move.GetInputPort("geometry_pose"))
            builder.Connect(head.GetOutputPort("D_W"), move.GetInputPort("D_W"))
            poses = move.GetOutputPort("geometry_pose")
        builder.Connect(poses, scene_graph.get_source_pose_port(plant.get_source_id()))
        keep.append(plant)  # not owned by the diagram in this mode
        builder.Connect(q_port, tool_pose.GetInputPort("q"))
    else:
        interp = builder.AddSystem(
            StateInterpolatorWithDiscreteDerivative(6, period, suppress_initial_transient=True)
        )
        kp, ki, kd = gains
        controller = builder.AddSystem(
            InverseDynamicsController(plant, [kp] * 6, [ki] * 6, [kd] * 6, False)
        )
        builder.Connect(diffik.GetOutputPort("joint_positions"), interp.get_input_port())
        builder.Connect(interp.get_output_port(), controller.get_input_port_desired_state())
        builder.Connect(
            plant.get_state_output_port(arm), controller.get_input_port_estimated_state()
        )
        builder.Connect(controller.get_output_port_control(), plant.get_actuation_input_port())
        q_port = plant.get_state_output_port(arm)
        builder.Connect(q_port, tool_pose.GetInputPort("q"))

    loggers = {"q": LogVectorOutput(q_port, builder, period)}
    if logs:
        loggers.update({
            "barrier": LogVectorOutput(supervisor.GetOutputPort("barrier"), builder, period),
            "command": LogVectorOutput(limiter.GetOutputPort("command_status"), builder, period),
            "safety": LogVectorOutput(estimator.GetOutputPort("safety"), builder,
                                      estimator_period),
            "alarm": LogVectorOutput(estimator.GetOutputPort("alarm"), builder,
                                     estimator_period),
        })
    if head_guard is not None and logs:
        loggers["guard"] = LogVectorOutput(head_guard.GetOutputPort("mode"), builder, period)
        loggers["margin_extra"] = LogVectorOutput(head_guard.GetOutputPort("margin_extra"),
                                                  builder, period)
        loggers["lost"] = LogVectorOutput(trk.GetOutputPort("lost"), builder, period)
        loggers["tracked"] = LogVectorOutput(frame.GetOutputPort("H"), builder, period)
    if phase is not None and logs:
        loggers["phase"] = LogVectorOutput(phase.GetOutputPort("phase"), builder, period)
    visualizer = None
    if meshcat is not None:
        visualizer = MeshcatVisualizer.AddToBuilder(
            builder, scene_graph, meshcat, MeshcatVisualizerParams(role=Role.kIllustration)
        )
    diagram = builder.Build()
    diagram.set_name(f"teleop_{mode}")
    return Teleop(
        diagram=diagram,
        plant=plant,
        scene_graph=scene_graph,
        mode=mode,
        master=master,
        vf=vf,
        supervisor=supervisor,
        limiter=limiter,
        estimator=estimator,
        diffik=diffik,
        tool_pose=tool_pose,
        loggers=loggers,
        case=case,
        period=period,
        visualizer=visualizer,
        interpolator=interp,
        keep=keep,
        head=head,
        tracker=trk,
        guard=head_guard,
        phase=phase,
    )


@dataclass
class FeedRun:
    """What one simulated run measured (SI units)."""

    t: np.ndarray  # (n,) log times
    q: np.ndarray  # (n, 6)
    p_WE: np.ndarray  # (n, 3)
    violation: np.ndarray  # (n,) the fixture's body violation at every logged pose (m)
    t_safety: np.ndarray  # (m,) times of the estimator's log
    f_safe_line1: np.ndarray
    f_safe_line2: np.ndarray
    min_d_safe: np.ndarray
    alarm: np.ndarray  # (n,) bool
    sim_seconds: float
    wall_seconds: float
    X_CT: np.ndarray | None = None  # (n, 4, 4) the measured Tool pose in Center
    angle_violation: np.ndarray | None = None  # (n,) the fixture's orientation violation (rad)
    barrier: np.ndarray | None = None  # (n, 3) the supervisor's [h, scale, active]
    head_D: np.ndarray | None = None  # (n, 4, 4) the head's true displacement (head motion)
    guard: np.ndarray | None = None  # (n, 4) the HeadGuard's [mode, backed out, t, cause]
    margin_extra: np.ndarray | None = None  # (n,) what the guard added to the margin (m)
    lost: np.ndarray | None = None  # (n,) bool: the tracker's lost flag
    command: np.ndarray | None = None  # (n, 6) the CommandLimiter's status log
    phase: np.ndarray | None = None  # (n,) 1 while inserting (an insertion diagram)
    # (n, 4, 4) the measured Tool pose in Center of the TRACKED head (the frame the supervisor
    # integrates the command in): the arm's pose at log k in the head displacement DiffIK was
    # given at its update one period before (log k - 1; a log shows the state before that
    # instant's updates)
    X_CT_tracked: np.ndarray | None = None
    violation_tracked: np.ndarray | None = None  # (n,) the fixture's violation there (m)

    @property
    def fault_times(self) -> np.ndarray:
        """Times (s) of the command samples that were faults (the limiter held them)."""
        if self.command is None:
            return np.zeros(0)
        return self.command[self.command[:, 0] == FAULT, 5]

    @property
    def fault_events(self) -> int:
        """Faults that set the limiter's latch over the run."""
        return 0 if self.command is None else int(self.command[-1, 4])

    @property
    def joint_travel(self) -> float:
        """Sum over joints of the integrated |qdot| (seed 001 Eq. 23), from the log (rad)."""
        return float(np.abs(np.diff(self.q, axis=0)).sum())

    def first_alarm_time(self) -> float | None:
        hit = np.flatnonzero(self.alarm)
        return float(self.t_safety[hit[0]]) if hit.size else None


def _run(teleop: Teleop, duration: float, *, motion, insertion_start, head_motion,
         tracker_seed, recording: bool = False):
    """Advance the diagram from the case's start to ``duration`` in a fresh context with the
    run's parameters (:func:`simulate`); returns (context, wall s of AdvanceTo)."""
    if not np.isfinite(duration) or duration <= 0:
        raise InputError("duration", f"expected a duration > 0 s, got {duration}")
    if head_motion is not None and teleop.head is None:
        raise InputError("head_motion", "expected a diagram built with a head motion")
    if tracker_seed is not None and teleop.tracker is None:
        raise InputError("tracker_seed", "expected a diagram built with a tracker")
    if insertion_start is not None and teleop.phase is None:
        raise InputError("insertion_start", "expected a diagram built with an insertion")
    simulator = Simulator(teleop.diagram)
    context = simulator.get_mutable_context()
    if motion is not None:
        teleop.master.set_motion(context, motion)
    if head_motion is not None:
        teleop.head.set_motion(context, head_motion)
    if tracker_seed is not None:
        teleop.tracker.set_seed(context, tracker_seed)
    if insertion_start is not None:
        teleop.phase.set_start(context, insertion_start)
    diffik_context = teleop.diffik.GetMyMutableContextFromRoot(context)
    teleop.diffik.GetInputPort("use_robot_state").FixValue(diffik_context, False)
    teleop.initialize(context)
    if recording and teleop.visualizer is not None:
        teleop.visualizer.StartRecording()
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(duration)
    wall = time.perf_counter() - start
    if recording and teleop.visualizer is not None:
        teleop.visualizer.StopRecording()
        teleop.visualizer.PublishRecording()
    return context, wall


def _tool_in_center(teleop: Teleop, context, q: np.ndarray, t: np.ndarray):
    """(X_WE (n, 4, 4), X_CT (n, 4, 4), head D (n, 4, 4) or None) of logged joints ``q``
    (n, 6) at times ``t``: the tool in the TRUE (moving) head's Center, D(t) X_WCenter."""
    case = teleop.case
    X_WE = case.X_WE(q)  # the tool's poses from the logged joints (no pose logger in the loop)
    if teleop.head is None:
        return X_WE, np.linalg.inv(case.X_WCenter) @ X_WE @ X_ET, None
    head_D = teleop.head.motion_in(context).D(t)
    return X_WE, np.linalg.inv(case.X_WCenter) @ invert(head_D) @ X_WE @ X_ET, head_D


@dataclass(frozen=True)
class FinalPose:
    """Where one run left the tool (:func:`final_pose`)."""

    X_CT: np.ndarray  # (4, 4) the measured Tool pose in Center at the last log
    t: float  # s, the time of that log
    sim_seconds: float
    wall_seconds: float


def final_pose(teleop: Teleop, duration: float, *, motion: MasterMotion | None = None,
               insertion_start: float | None = None, head_motion: HeadMotion | None = None,
               tracker_seed: int | None = None) -> FinalPose:
    """The run of :func:`simulate` (the same arguments) reduced to the tool's last logged pose:
    ``simulate(...).X_CT[-1]``, the same numbers, from a diagram built with or without
    ``logs``."""
    context, wall = _run(teleop, duration, motion=motion, insertion_start=insertion_start,
                         head_motion=head_motion, tracker_seed=tracker_seed)
    log = teleop.loggers["q"].FindLog(context)
    t = log.sample_times()[-1:].copy()
    q = log.data()[:6, -1:].T.copy()
    X_CT = _tool_in_center(teleop, context, q, t)[1][0]
    return FinalPose(X_CT=X_CT, t=float(t[0]), sim_seconds=float(context.get_time()),
                     wall_seconds=wall)


def simulate(teleop: Teleop, duration: float, *, motion: MasterMotion | None = None,
             recording: bool = False, insertion_start: float | None = None,
             head_motion: HeadMotion | None = None, tracker_seed: int | None = None) -> FeedRun:
    """Run the diagram from the case's start for ``duration`` seconds of simulated time, in a
    fresh context replaying ``motion`` (None: the motion the diagram was built with); an
    insertion diagram starts inserting at ``insertion_start`` (s; None: never). The head's
    motion and the tracker's noise seed are parameters of the context too: ``head_motion`` and
    ``tracker_seed`` replace the diagram's for this run (None: the diagram's)."""
    if "safety" not in teleop.loggers:
        raise InputError("logs", "expected a diagram built with logs=True (final_pose reads "
                         "one without)")
    context, wall = _run(teleop, duration, motion=motion, insertion_start=insertion_start,
                         head_motion=head_motion, tracker_seed=tracker_seed,
                         recording=recording)
    logs = {k: v.FindLog(context) for k, v in teleop.loggers.items()}
    safety = logs["safety"].data().T
    q = logs["q"].data().T[:, :6].copy()
    # the fixture's violation at every logged pose, offline (one batched call, not in the loop)
    case = teleop.case
    t_log = logs["q"].sample_times().copy()
    X_WE, X_CT, head_D = _tool_in_center(teleop, context, q, t_log)
    violation, angle_violation = case.vf.body_violation(X_CT)
    extra = {}
    if "phase" in logs:
        extra["phase"] = logs["phase"].data()[0] > 0.5
    if "tracked" in logs:
        Hv = logs["tracked"].data().T
        H = np.repeat(np.eye(4)[None], Hv.shape[0], axis=0)
        H[:, :3, 3], H[:, :3, :3] = Hv[:, :3], Hv[:, 3:].reshape(-1, 3, 3)
        H_used = np.concatenate([H[:1], H[:-1]])  # DiffIK's result at log k used log k - 1's
        X_CT_tracked = np.linalg.inv(case.X_WCenter) @ invert(H_used) @ X_WE @ X_ET
        extra.update(X_CT_tracked=X_CT_tracked,
                     violation_tracked=case.vf.body_violation(X_CT_tracked)[0])
    if "guard" in logs:
        extra.update(guard=logs["guard"].data().T.copy(),
                     margin_extra=logs["margin_extra"].data()[0].copy(),
                     lost=logs["lost"].data()[0] > 0.5)
    return FeedRun(
        t=t_log,
        q=q,
        p_WE=X_WE[:, :3, 3].copy(),
        violation=violation,
        t_safety=logs["safety"].sample_times().copy(),
        f_safe_line1=safety[:, 0].copy(),
        f_safe_line2=safety[:, 1].copy(),
        min_d_safe=safety[:, 2].copy(),
        alarm=logs["alarm"].data()[0] > 0.5,
        sim_seconds=float(context.get_time()),
        wall_seconds=wall,
        X_CT=X_CT,
        angle_violation=angle_violation,
        barrier=logs["barrier"].data().T.copy(),
        command=logs["command"].data().T.copy(),
        head_D=head_D,
        **extra,
    )

