"""The implant's insertion along its axis after the feed, and its deviation from the plan.

Geometry (seed 000 Eq. 18): the Tool frame at the feeding target is T = H (Rz(theta_T),
[0, 0, d_T]) with H the Hole frame (origin on the jaw surface, z out of the bone), so Tool z is
the implant axis and the implant points to -z. The instrument's implant ends at its tip
(:func:`implant_points`: the ``implant`` solid's lower end); the placed implant is the plan's
(the case's ``placed_implant_length_mm``, L, the surgeon's card's): its last L, apex = the
tip, platform = the tip + L z_T, placed with its platform on the hole's plane z_H = 0 and its
apex L below. The tool travels from the target along -z_T by

    depth = d_T + z_tip + L  (z_tip: the tip's z in T, -d12),

so the planned final Tool pose is X_CT* = X_CT Tz(-depth) (:func:`planned_insertion`). The
shipped actuator's implant is coaxial with the hole's axis, so its platform lands on the site;
the paper's thin tool (seed 000 Eq. 19) carries its implant line r off the TCP along x_T, and
so the plan's implant r off the site (the paper's line2).

**The insertion fixture.** After the feed the operator drives the tool along -z_T; the feed's
fixture (axis line1, the rod) would hold it on line1. :func:`insertion_fixture` is the same
virtual fixture (systems.placement.fixture) with its axis on the implant's: origin at the final
TCP, direction +z_T, the whole stroke its "inside" part (entry distance = depth), so the TCP and
the tool's axis stay within delta of the planned implant axis, the orientation within beta of
the plan, and the cap at s = 0 is the depth stop. The fixture law reads its Tool frame's x as
the constrained axis, so it sees the tool through R_INSERT (x' = z_T, y' = x_T, z' = y_T): the
same rotation error, the axis now the implant's. :class:`InsertionPhase` switches the diagram
from the feed's corrected twist to the insertion fixture's at the insertion's start (a context
parameter, per run) and releases the FPSM barrier from then on (the supervisor's
``barrier_release``): the implant enters the bone by design, which the FPSM (the cavity's free
space) calls a collision; the depth stop and the axis fixture guard the insertion instead (the
speed limits stay, the estimator still watches).

**Deviation** (:func:`implant_deviation`, vectorized over placed poses): at the placed Tool
pose X_CT the implant's platform and apex against the planned ones (entry and apex deviation,
m), the angle between the placed and planned implant axes (rad), and the depth reached along
the planned axis (m). Distances and angles are the same in the scan's frame (Center is fixed to
the scan by the FPSM's X_WC).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError
from implantplan.systems.placement.fixture import VirtualFixture
from implantplan.systems.teleop.master_device import MasterMotion

# the insertion fixture's Tool axes in the Tool frame: x' = z_T (the implant axis), y' = x_T,
# z' = y_T (a cyclic permutation: a rotation)
R_INSERT = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def implant_points(tool) -> tuple[np.ndarray, np.ndarray]:
    """(top, tip) of the instrument's implant in its Tool frame (m): the ends of its
    ``implant`` solid, the one with the larger z the top; an instrument without one: the
    Eq. 19 line from [line_offset, 0, 0] to [line_offset, 0, -d12]."""
    for s in tool.shapes:
        if s.name == "implant":
            a, b = np.asarray(s.a, dtype=float), np.asarray(s.b, dtype=float)
            return (a, b) if a[2] >= b[2] else (b, a)
    top = np.array([tool.line_offset, 0.0, 0.0])
    return top, top - np.array([0.0, 0.0, tool.implant_length])


def tz(dz: float) -> np.ndarray:
    X = np.eye(4)
    X[2, 3] = dz
    return X


@dataclass(frozen=True)
class PlannedImplant:
    """The plan's implant at a site (Center frame, SI units).

    Attributes:
        X_CT_target: (4, 4) the feeding target (Tool pose).
        depth: the insertion stroke along -z_T from the target (m).
        platform_T, apex_T: (3,) the implant's ends in the Tool frame.
    """

    X_CT_target: np.ndarray
    depth: float
    platform_T: np.ndarray
    apex_T: np.ndarray

    @property
    def X_CT_final(self) -> np.ndarray:
        """The planned final Tool pose: the target moved ``depth`` along -z_T."""
        return self.X_CT_target @ tz(-self.depth)

    @property
    def platform(self) -> np.ndarray:
        return self.X_CT_final[:3, :3] @ self.platform_T + self.X_CT_final[:3, 3]

    @property
    def apex(self) -> np.ndarray:
        return self.X_CT_final[:3, :3] @ self.apex_T + self.X_CT_final[:3, 3]

    @property
    def axis(self) -> np.ndarray:
        """The implant's axis, unit, from the apex to the platform (= Tool z)."""
        return self.X_CT_target[:3, 2]


def planned_insertion(X_CT_target, d_T: float, tool, placed_length: float) -> PlannedImplant:
    """The planned implant of a site whose feeding target is ``X_CT_target`` at distance ``d_T``
    from the hole along its axis, ``placed_length`` (m) long (module notes): its platform on
    the hole's plane."""
    X = np.asarray(X_CT_target, dtype=float)
    top_T, apex_T = implant_points(tool)
    L = float(placed_length)
    if not (np.isfinite(L) and 0 < L <= top_T[2] - apex_T[2] + 1e-12):
        raise InputError("placed_implant_length", f"expected a length in (0, "
                         f"{(top_T[2] - apex_T[2]) * 1e3:.1f}] mm (the instrument's implant), "
                         f"got {L * 1e3:.2f} mm")
    platform_T = apex_T + np.array([0.0, 0.0, L])
    depth = float(d_T) + float(apex_T[2]) + L
    if not np.isfinite(depth) or depth <= 0:
        raise InputError("d_T", f"expected the implant's platform above the hole at the target "
                         f"(insertion depth > 0), got {depth * 1e3:.2f} mm")
    return PlannedImplant(X_CT_target=X, depth=depth, platform_T=platform_T, apex_T=apex_T)


def insertion_fixture(vf: VirtualFixture, plan: PlannedImplant) -> VirtualFixture:
    """The fixture of the insertion (module notes): the feed's tolerances, cones and radius,
    the axis on the implant's, the depth stop at the planned depth."""
    X = plan.X_CT_final
    return VirtualFixture(
        origin=X[:3, 3], direction=X[:3, 2], entry_distance=plan.depth,
        cylinder_radius=vf.cylinder_radius, segment_lengths=vf.segment_lengths,
        half_angles=vf.half_angles, cap=True, lateral_tolerance=vf.lateral_tolerance,
        angle_tolerance=vf.angle_tolerance, R_ref=X[:3, :3] @ R_INSERT)


def implant_deviation(X_CT, plan: PlannedImplant) -> dict:
    """Entry, apex and angle deviation and the depth reached of implants placed at Tool poses
    ``X_CT`` (..., 4, 4) in Center, against ``plan`` (module notes; arrays of the leading
    shape, m and rad)."""
    X = np.asarray(X_CT, dtype=float)
    R, p = X[..., :3, :3], X[..., :3, 3]
    platform = np.einsum("...ij,j->...i", R, plan.platform_T) + p
    apex = np.einsum("...ij,j->...i", R, plan.apex_T) + p
    cos = np.clip(np.einsum("...i,i->...", R[..., :, 2], plan.axis), -1.0, 1.0)
    # the angle from the cross product's norm near 0 (arccos loses digits there)
    sin = np.linalg.norm(np.cross(R[..., :, 2], plan.axis), axis=-1)
    return {
        "entry": np.linalg.norm(platform - plan.platform, axis=-1),
        "apex": np.linalg.norm(apex - plan.apex, axis=-1),
        "angle": np.arctan2(sin, cos),
        "depth_reached": (plan.X_CT_target[:3, 3] - p) @ plan.axis,
    }


def append_stroke(feed: MasterMotion, stroke: MasterMotion, hold: float = 0.0) -> MasterMotion:
    """The operator's whole procedure: ``feed``, ``hold`` seconds still, then ``stroke`` (same
    sample period; each motion's handle positions relative to its own start)."""
    if abs(feed.dt - stroke.dt) > 1e-12:
        raise InputError("dt", f"expected one sample period, got {feed.dt} and {stroke.dt}")
    n_hold = int(round(hold / feed.dt))
    end = feed.p_M[-1]
    p = np.vstack([feed.p_M, np.repeat(end[None], n_hold, axis=0),
                   end + stroke.p_M - stroke.p_M[0]])
    return MasterMotion(dt=feed.dt, p_M=p)


class InsertionPhase(LeafSystem):
    """The feed's corrected twist until the insertion starts, the insertion fixture's after.

    .. pydrake_system::

        name: InsertionPhase
        input_ports:
        - V_WE_feed
        - V_WE_insertion
        output_ports:
        - V_WE_corrected
        - barrier_release
        - phase

    ``V_WE_feed``, ``V_WE_insertion`` (6): the two fixtures' corrected twists ([w; v], World).
    ``V_WE_corrected`` (6): the first before the start time, the second from it on.
    ``barrier_release`` and ``phase`` (1): 0 feeding, 1 inserting (the supervisor's barrier is
    released while inserting: module notes). The start time (s) is a numeric parameter of the
    context (:meth:`set_start`; default +inf: never), so one diagram serves every run.
    """

    def __init__(self):
        super().__init__()
        self._feed = self.DeclareVectorInputPort("V_WE_feed", 6)
        self._ins = self.DeclareVectorInputPort("V_WE_insertion", 6)
        self._start = self.DeclareNumericParameter(BasicVector([np.inf]))
        self.DeclareVectorOutputPort("V_WE_corrected", 6, self._calc_twist)
        self.DeclareVectorOutputPort("barrier_release", 1, self._calc_phase)
        self.DeclareVectorOutputPort("phase", 1, self._calc_phase)

    def set_start(self, context, t_start: float) -> None:
        """Start the insertion at ``t_start`` (s) in ``context`` (this system's or the root)."""
        own = self.GetMyMutableContextFromRoot(context)
        own.get_mutable_numeric_parameter(self._start).SetAtIndex(0, float(t_start))

    def _inserting(self, context) -> bool:
        return context.get_time() >= context.get_numeric_parameter(self._start).GetAtIndex(0)

    def _calc_twist(self, context, output: BasicVector):
        port = self._ins if self._inserting(context) else self._feed
        output.SetFromVector(port.Eval(context))

    def _calc_phase(self, context, output: BasicVector):
        output.SetAtIndex(0, 1.0 if self._inserting(context) else 0.0)
