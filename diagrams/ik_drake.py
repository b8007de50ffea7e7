"""Inverse kinematics by Drake's optimizer: multi-start enumeration of a 6-DOF arm's IK branches.

DESIGN.md section 5: the closed form (``systems.robot.kinematics.ik``) gives the AUBO-i10's 8
branches
directly; this path enumerates the same set with ``pydrake.multibody.inverse_kinematics``
(MathematicalProgram), more slowly, for any 6-DOF URDF. It is the cross-check of the closed form
and the fallback for arms without one.

Per target pose X_BT (tool frame T in the base frame B):

1. One program: the pose as three PositionConstraint equalities (the
   TCP and the tips of its x and y axes at ``AXIS_POINT``; smooth, unlike OrientationConstraint's
   trace inequality whose gradient vanishes at zero error) and, when asked,
   MinimumDistanceLowerBoundConstraint (collision-free with the given clearance, through the
   scene graph of the plant's diagram).
   Revolute joints are left unbounded in the program and wrapped into their limits afterwards
   (q and q + 2 pi are the same pose; with the limits in the program SNOPT stops in a local
   infeasibility minimum from about 85% of random starts on the AUBO, without them from about
   20%); other joints keep their bounds.
2. ``starts`` initial guesses uniform within the joint limits (numpy Generator from ``seed``:
   same seed, same output), each solved with SNOPT (IPOPT when SNOPT is not in the wheel).
3. Each solver success is polished by Gauss-Newton steps on the exact pose error with Drake's
   own FK and Jacobian (the solver stops at its feasibility tolerance, about 1e-6), then kept if
   the pose error is below
   ``pose_tol`` (m and rad), it lies within the limits and (if asked) keeps the clearance.
4. Kept solutions are de-duplicated by wrapped joint distance (``dedup_tol``): q and q + 2 pi on a
   joint count once, as in the closed form's branch count.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.multibody.tree import JacobianWrtVariable, JointIndex
from pydrake.solvers import IpoptSolver, SnoptSolver
from pydrake.systems.framework import DiagramBuilder

from implantplan import models
from implantplan.systems import validate
from implantplan.systems.errors import InputError
from implantplan.systems.frames import wrap_angle
from implantplan.systems.robot.kinematics import wrapped_distance

AXIS_POINT = 0.1  # m, distance of the two axis points constraining the orientation
DEFAULT_URDF = {"175": "aubo_i10/aubo_i10.urdf", "360": "aubo_i10/aubo_i10_360.urdf"}


@dataclass
class IkDrakeInfo:
    """What one multi-start run did.

    Attributes:
        starts: initial guesses tried; solved: solver successes; kept: solutions that passed the
            polish, limit and clearance checks (before de-duplication); branches: distinct
            solutions returned.
        max_position_error, max_rotation_error: worst pose error of the returned solutions (m, rad).
        solver: solver name; time_s: wall time of the run.
        reason: "ok", or why nothing was returned.
    """

    starts: int
    solved: int
    kept: int
    branches: int
    max_position_error: float
    max_rotation_error: float
    solver: str
    time_s: float
    reason: str = field(default="ok")


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    """Axis * angle of a rotation matrix (log map), accurate near 0 and pi."""
    aa = RotationMatrix.ProjectToRotationMatrix(R).ToAngleAxis()
    return aa.axis() * aa.angle()


class DrakeIk:
    """Multi-start IK on a MultibodyPlant (any 6-DOF arm), reusable across many poses.

    Args:
        urdf: model file of the arm (path or ``package://implantplan/...``); None = the AUBO-i10
            with ``limits``. Ignored when ``plant`` is given.
        base_frame, tool_frame: frame names in the model (the pose is of ``tool_frame`` in
            ``base_frame``).
        X_FT: 4x4 pose of the TCP in ``tool_frame`` (e.g. ``diagrams.actuator_urdf.X_FT()`` with the
            flange), or None.
        limits: "175" or "360" for the default AUBO model.
        plant, diagram: a finalized plant inside a built diagram (e.g. from
            ``diagrams.plant.build_plant``) to use instead of loading ``urdf``; needed for
            ``min_distance`` against a scene. Its positions must be exactly the 6 arm joints.
        min_distance: required clearance (m) between all unfiltered geometry pairs, or None.
        influence_distance: MinimumDistanceLowerBoundConstraint's influence distance offset (m).
    """

    def __init__(
        self,
        *,
        urdf: str | None = None,
        base_frame: str = "base_link",
        tool_frame: str = "wrist3_Link",
        X_FT=None,
        limits: str = "175",
        plant=None,
        diagram=None,
        min_distance: float | None = None,
        influence_distance: float = 0.02,
    ):
        if plant is None:
            if urdf is None:
                if limits not in DEFAULT_URDF:
                    raise InputError("limits", f"expected '175' or '360', got {limits!r}")
                urdf = str(models.model_path(DEFAULT_URDF[limits]))
            builder = DiagramBuilder()
            plant, _ = AddMultibodyPlantSceneGraph(builder, time_step=0.0)
            parser = Parser(plant)
            models.add_package(parser.package_map())
            parser.AddModels(urdf)
            plant.WeldFrames(plant.world_frame(), plant.GetFrameByName(base_frame))
            plant.Finalize()
            diagram = builder.Build()
        elif diagram is None:
            raise InputError("diagram", "a plant passed in needs its diagram")
        if plant.num_positions() != 6:
            n = plant.num_positions()
            raise InputError("plant", f"expected a 6-DOF arm, got {n} positions")
        if min_distance is not None and not (np.isfinite(min_distance) and min_distance >= 0):
            raise InputError("min_distance", f"expected a clearance >= 0 in m, got {min_distance}")
        self.plant, self.diagram = plant, diagram
        self.context = diagram.CreateDefaultContext()
        self.plant_context = plant.GetMyMutableContextFromRoot(self.context)
        self.base = plant.GetFrameByName(base_frame)
        self.tool = plant.GetFrameByName(tool_frame)
        X = np.eye(4) if X_FT is None else validate.pose(X_FT, "X_FT")
        self.X_FT = RigidTransform(RotationMatrix.ProjectToRotationMatrix(X[:3, :3]), X[:3, 3])
        self.lower = plant.GetPositionLowerLimits()
        self.upper = plant.GetPositionUpperLimits()
        if not (np.all(np.isfinite(self.lower)) and np.all(np.isfinite(self.upper))):
            raise InputError("plant", "every joint needs finite position limits to sample starts")
        self.revolute = np.zeros(6, dtype=bool)
        for i in range(plant.num_joints()):
            joint = plant.get_joint(JointIndex(i))
            if joint.num_positions() == 1 and joint.type_name() == "revolute":
                self.revolute[joint.position_start()] = True
        self.min_distance = min_distance
        self.influence_distance = influence_distance
        snopt = SnoptSolver()
        self.solver = snopt if snopt.available() and snopt.enabled() else IpoptSolver()

    def _wrap(self, q: np.ndarray) -> np.ndarray | None:
        """Each revolute joint's copy (mod 2 pi) within its limits nearest 0; None if none fits."""
        q = q.copy()
        rev = self.revolute
        q[rev] = wrap_angle(q[rev])  # [-pi, pi)
        for shift in (2.0 * np.pi, -2.0 * np.pi):
            out = rev & ((q < self.lower) | (q > self.upper))
            q[out] += shift
            back = out & ((q < self.lower) | (q > self.upper))
            q[back] -= shift
        if np.any(q < self.lower - 1e-12) or np.any(q > self.upper + 1e-12):
            return None
        return np.clip(q, self.lower, self.upper)

    def pose(self, q: np.ndarray) -> np.ndarray:
        """X_BT (4x4) of the TCP at configuration q."""
        self.plant.SetPositions(self.plant_context, q)
        X_BF = self.plant.CalcRelativeTransform(self.plant_context, self.base, self.tool)
        return (X_BF @ self.X_FT).GetAsMatrix4()

    def _polish(self, q, R_target, p_target, iterations: int = 12):
        """Gauss-Newton on [rotation vector; position] error with Drake's FK and Jacobian."""
        p_FT = self.X_FT.translation()
        R_FT = self.X_FT.rotation().matrix()
        for _ in range(iterations):
            self.plant.SetPositions(self.plant_context, q)
            X_BF = self.plant.CalcRelativeTransform(self.plant_context, self.base, self.tool)
            R_BT = X_BF.rotation().matrix() @ R_FT
            p_BT = X_BF.translation() + X_BF.rotation().matrix() @ p_FT
            err = np.concatenate([_rotation_vector(R_target @ R_BT.T), p_target - p_BT])
            if np.abs(err).max() < 1e-14:
                break
            J = self.plant.CalcJacobianSpatialVelocity(
                self.plant_context,
                JacobianWrtVariable.kQDot,
                self.tool,
                p_FT,
                self.base,
                self.base,
            )
            q = q + np.linalg.lstsq(J, err, rcond=None)[0]
        return q

    def _clearance(self, q) -> float:
        """Smallest signed distance among unfiltered geometry pairs at q (inf if none)."""
        self.plant.SetPositions(self.plant_context, q)
        port = self.plant.get_geometry_query_input_port()
        query = port.Eval(self.plant_context)
        pairs = query.ComputeSignedDistancePairwiseClosestPoints(max_distance=1.0)
        return min((p.distance for p in pairs), default=np.inf)

    def solve(
        self,
        X_BT,
        *,
        starts: int = 128,
        seed: int | np.random.Generator = 0,
        pose_tol: float = 1e-9,
        dedup_tol: float = 1e-4,
    ) -> tuple[np.ndarray, IkDrakeInfo]:
        """All distinct IK solutions of one pose found from ``starts`` random initial guesses.

        Args:
            X_BT: 4x4 target pose of the TCP in the base frame.
            starts: number of initial guesses (uniform within the joint limits).
            seed: seed or numpy Generator for the initial guesses.
            pose_tol: accept a solution when its position error (m) and rotation error (rad)
                are both below this after polishing.
            dedup_tol: two solutions are the same branch when their wrapped joint distance
                (rad) is below this.

        Returns:
            ``(q, info)``: q (k, 6) distinct solutions (k may be 0, then ``info.reason`` says
            why), sorted lexicographically; info an :class:`IkDrakeInfo`.
        """
        t0 = time.perf_counter()
        X = validate.pose(X_BT, "X_BT")
        R_target, p_target = X[:3, :3], X[:3, 3]
        if not (isinstance(starts, int | np.integer) and starts >= 1):
            raise InputError("starts", f"expected a positive integer, got {starts!r}")
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)

        ik = InverseKinematics(self.plant, self.plant_context, with_joint_limits=False)
        # The pose as three point equalities: the TCP and the tips of its x and y axes (length
        # AXIS_POINT) at their targets. Smooth, well-conditioned equality constraints, unlike the
        # trace form of OrientationConstraint whose gradient vanishes at zero error.
        for p_T in (np.zeros(3), AXIS_POINT * np.eye(3)[0], AXIS_POINT * np.eye(3)[1]):
            p_FQ = self.X_FT.multiply(p_T)
            p_BQ = p_target + R_target @ p_T
            ik.AddPositionConstraint(self.tool, p_FQ, self.base, p_BQ, p_BQ)
        if self.min_distance is not None:
            ik.AddMinimumDistanceLowerBoundConstraint(self.min_distance, self.influence_distance)
        prog = ik.prog()
        if not np.all(self.revolute):
            fixed = ~self.revolute
            prog.AddBoundingBoxConstraint(self.lower[fixed], self.upper[fixed], ik.q()[fixed])
        guesses = rng.uniform(self.lower, self.upper, size=(starts, 6))
        solved, kept = 0, []
        for q0 in guesses:
            result = self.solver.Solve(prog, q0, None)
            if not result.is_success():
                continue
            solved += 1
            q = self._wrap(self._polish(result.GetSolution(ik.q()), R_target, p_target))
            if q is None:
                continue
            X_q = self.pose(q)
            dp = np.linalg.norm(X_q[:3, 3] - p_target)
            dR = np.linalg.norm(_rotation_vector(R_target.T @ X_q[:3, :3]))
            if dp > pose_tol or dR > pose_tol:
                continue
            if self.min_distance is not None and self._clearance(q) < self.min_distance - 1e-6:
                continue
            kept.append((q, dp, dR))
        distinct: list[tuple[np.ndarray, float, float]] = []
        for q, dp, dR in kept:
            if all(float(wrapped_distance(q, o[0])) > dedup_tol for o in distinct):
                distinct.append((q, dp, dR))
        q_out = np.array([d[0] for d in distinct]).reshape(-1, 6)
        order = np.lexsort(q_out.T[::-1]) if len(q_out) else np.zeros(0, dtype=int)
        reason = "ok"
        if not distinct:
            reason = (
                "no start converged (pose out of reach, or too few starts)"
                if solved == 0
                else "solver results failed the pose/limit/clearance checks"
            )
        info = IkDrakeInfo(
            starts=starts,
            solved=solved,
            kept=len(kept),
            branches=len(distinct),
            max_position_error=max((d[1] for d in distinct), default=np.nan),
            max_rotation_error=max((d[2] for d in distinct), default=np.nan),
            solver=self.solver.solver_id().name(),
            time_s=time.perf_counter() - t0,
            reason=reason,
        )
        return q_out[order], info


def ik_drake(
    X_BT,
    *,
    solver: DrakeIk | None = None,
    starts: int = 128,
    seed: int | np.random.Generator = 0,
    **options,
) -> tuple[np.ndarray, IkDrakeInfo]:
    """Enumerate the IK branches of one pose with Drake (see :class:`DrakeIk` for ``options``).

    Pass a prebuilt ``solver`` to reuse its plant across many poses (what benchmarks time).

    Returns:
        ``(q (k, 6), info)``.
    """
    if solver is None:
        solver = DrakeIk(**options)
    elif options:
        raise InputError("options", "pass model options either to DrakeIk or here, not both")
    return solver.solve(X_BT, starts=starts, seed=seed)
