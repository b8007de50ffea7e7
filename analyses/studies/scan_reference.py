"""The exact reference of the teleop studies on the bundled default case (the adversarial
operator, analyses.studies.adversarial; the awake patient, analyses.studies.head_motion): the case
planned as
``implantplan plan`` does, and FCL (Coal, through ExactCavity) between the whole tool and the
opened scan.

The instrument is the teleop case's :class:`systems.instrument.Instrument` (the body the
barrier bounds), each solid as it is: a capsule's clearance is its axis's FCL distance to the scan
minus its radius (exact while the axis is free), minus its radius where the axis itself touches
the scan (at or below the true value); a cylinder's is FCL's cylinder-to-mesh distance while it
is free. FCL's contact depths in a mesh are not used: zero or denormal depths were seen for real
contacts, which made a 0.61 mm contact read as 0.

**Between logged poses** (:func:`swept_clearance`). The loggers see the arm every control
period; between two logged configurations q_k, q_k+1 the arm moves (a joint-position controlled
arm interpolates) along q(s) = q_k + s dq, s in [0, 1]. A tool point x moves at
|dx/ds| = |sum_i dq_i z_i x (x - o_i)| <= sum_i |dq_i| |x - o_i| (z_i, o_i joint i's axis and
origin), and |x - o_i| <= reach + |p - o_i| with p the TCP and reach the tool's largest distance
from it. Only joints j >= i turn p about o_i, so g(s) = max_i |p - o_i| grows at most as
g' <= (sum_j |dq_j|) g, g(s) <= g(0) e^(sum |dq|). A point's path over the segment is therefore
at most S = sum_i |dq_i| (reach + e^(sum |dq|) |p - o_i|(q_k)). That sum ignores how the
joints' motions cancel (an elbow and a wrist turning against each other move the TCP little), so
S is also bounded through the TCP's velocity v_p(s) = sum_j dq_j z_j x (p - o_j) and the
angular velocity w(s) = sum_j dq_j z_j, known exactly at s = 0: with A = sum |dq| and
G = e^A max_i |p - o_i|(q_k) (the bound of g above), z_j turns at most at A (joints before j
turn it) and p - o_j changes at most at A G, so |dv_p/ds| <= 2 A^2 G and |dw/ds| <= A^2; a point
within ``reach`` of p moves at |v_p + w x (x - p)|, and over the segment at most
|v_p(0)| + A^2 G + reach (|w(0)| + A^2 / 2). S is the smaller of the two bounds, and the
distance to the scan being 1-Lipschitz, every pose of the segment is at least
min(c_k, c_k+1) - S / 2 clear.
Segments whose bound is below the smallest logged clearance are sampled at ``substeps``
interior configurations (FCL at each) and the bound is applied to the sub-segments (S /
substeps each): the sampled minimum, and a certified lower bound of the clearance over the
whole swept motion.

**Under a moving head** (``head``: the run's :class:`~implantplan.systems.teleop.head_motion.
HeadMotion`, ``t`` its log times) the scan moves with the head, D(t) x = R (x - p) + p + u, and
the clearance is that of the tool in the head's frame, D(t)^-1 X_WT. A tool point x(t) seen from
the head moves at most |dx/dt| + |omega| |x - p - u| + |du/dt| (differentiate R^T (x - p - u)),
so each segment's S grows by dt (omega_max rho + v_max) with ``head.speed_bounds()`` =
(omega_max, v_max) and rho = |p_k - p - u_k| + reach + S_arm + dt v_max (the farthest a tool
point gets from the pivot's image over the segment); the samples between logged poses take the
head at the same share of the period as the arm's configuration (the arm's q_k + s dq at
t_k + s dt).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import trimesh

from implantplan.analyses import pipeline
from implantplan.analyses.case import default_case_path, load_case
from implantplan.diagrams.teleop import X_ET, TeleopCase
from implantplan.systems.errors import InputError
from implantplan.systems.frames import invert
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.exact_clearance import ExactCavity
from implantplan.systems.robot import kinematics as kin

IMPLANT_AXIS_RADIUS = 1e-4  # m: the implant as its axis (a thin capsule for FCL)
# The pass rules of the studies measured against this reference (the adversarial operator, the
# head turns), defined once:
MARGIN_SLACK = 0.0002  # m: the exact clearance may dip this far below the margin
MAX_VIOLATION = 0.0005  # m: the fixture's body violation must stay below this
STEP_SLACK = 1.1  # DiffIK's linearization: an arm step may exceed the limit's by 10%


class ExactClearance:
    """FCL clearance of the whole instrument to a triangle mesh (both in the mesh frame, m):
    :meth:`systems.placement.exact_clearance.ExactCavity.tool_clearance` (every solid as it is),
    the implant's radius-0 axis of the paper tool as a capsule of ``IMPLANT_AXIS_RADIUS``. No
    start-in-tissue test: the opened scan is not the Center-axis star-shaped cavity that test
    assumes.
    """

    def __init__(self, vertices, faces, tool: Instrument):
        mesh = trimesh.Trimesh(np.asarray(vertices, dtype=float), np.asarray(faces), process=False)
        self._cavity = ExactCavity(mesh)
        self._tool = thickened(tool, IMPLANT_AXIS_RADIUS)

    @property
    def reach(self) -> float:
        """The largest distance (m) of a point of the tool from its Tool origin (the TCP)."""
        a, b, r = self._tool.capsules_T()  # the cover contains every solid
        ends = np.maximum(np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1))
        return float(np.max(ends + r))

    def __call__(self, X_MT: np.ndarray) -> np.ndarray:
        """(K,) clearance (m) of the instrument at poses X_MT (K, 4, 4) of its Tool frame in the
        mesh frame: the smallest over its solids; exact while a solid is free, at or below the
        true value where it touches (FCL's contact depths in a mesh are not used: zero or
        denormal depths were seen for real contacts)."""
        return self._cavity.tool_clearance(np.asarray(X_MT, dtype=float).reshape(-1, 4, 4),
                                           self._tool, check_start=False)


def thickened(tool: Instrument, radius: float) -> Instrument:
    """The instrument with every solid at least ``radius`` thick (a radius-0 axis becomes a
    thin capsule FCL can measure)."""
    shapes = tuple(dataclasses.replace(s, radius=max(s.radius, radius)) for s in tool.shapes)
    return dataclasses.replace(tool, shapes=shapes)


def default_case_sites(*, progress=None):
    """(teleop cases per site, the opened scan mesh) of the bundled default case, planned as
    ``implantplan plan`` does."""
    case = load_case(default_case_path())
    fit = pipeline.fit_stage(case)
    placements = pipeline.placement_stage(case, fit)
    robot = pipeline.robot_stage(case, placements)
    return pipeline.teleop_cases(case, fit, placements, robot), fit.opened


def plan_sites(folder, *, field: str = "--plan"):
    """(teleop cases per site, the opened scan mesh) of a plan folder (``implantplan plan`` or
    ``demo``): the sites, fixtures and layout as planned, the scan of the case file the plan
    names; errors name ``field``."""
    from implantplan.analyses.live_setup import load_plan, opened_scan

    sp = load_plan(folder, field=field, reference=False)
    mesh = opened_scan(sp)
    if mesh is None:
        raise InputError(field, f"{sp.folder}: the case file the plan names "
                         f"({sp.plan['case']['source']}) is not there; the exact reference "
                         "needs its scan")
    return [sp.teleop_case(k) for k in range(len(sp.names))], mesh


def exact_for(tc: TeleopCase, mesh) -> ExactClearance:
    """The exact reference for a site: the opened scan without the tissue in front of the
    mouth opening (faces with a vertex beyond the FPSM's top slice plane: the lips and cheeks
    there are retracted in surgery, the case's own assumption), the tool of ``tc``."""
    V = np.asarray(mesh.vertices, dtype=float)
    X_CM = np.linalg.inv(tc.fpsm.X_WC)  # mesh frame -> Center
    z = V @ X_CM[2, :3] + X_CM[2, 3]
    faces = np.asarray(mesh.faces)
    keep = np.all(z[faces] <= tc.fpsm.z_range[1], axis=1)
    return ExactClearance(V, faces[keep], tc.tool)


@dataclass(frozen=True)
class Swept:
    """The whole tool's exact clearance along a logged run (m).

    Attributes:
        at_poses: (n,) at every logged configuration: FCL's value where ``exact_at``, elsewhere
            a lower bound above the run's smallest (``screen``, :func:`swept_clearance`).
        sampled: the smallest at the logged and the sampled configurations between them.
        bound: a certified lower bound over the whole swept motion (module docstring).
        path: (n - 1,) S of each segment: the longest path of a tool point over it (m).
        sampled_segments: how many segments were sampled.
        exact_at: (n,) where ``at_poses`` is FCL's value (all of them unless screened).
    """

    at_poses: np.ndarray
    sampled: float
    bound: float
    path: np.ndarray
    sampled_segments: int
    exact_at: np.ndarray


SCREEN_STRIDE = 8  # screened runs: FCL at every 8th logged pose first (:func:`screened`)


def screened(values, P: np.ndarray, *, stride: int = SCREEN_STRIDE):
    """The logged poses' clearance with FCL only where it can be the run's smallest: ``values``
    (an index array -> FCL's clearance at those poses), ``P`` (n,) the poses' path coordinate
    (the cumulative S: no tool point moves farther than P_j - P_i between poses i < j).

    FCL at every ``stride``-th pose and the last; a pose between known ones is at least
    L_j = max over its nearest known neighbours i of c_i - |P_j - P_i| (the clearance is
    1-Lipschitz in the tool's points' motion). Poses whose L_j is not above zero (a contact
    cannot be ruled out: a touching solid's value is not its distance) or not above the
    smallest known value are measured, until none is left: the smallest value and where it is
    are FCL's, as if every pose were measured; every other pose is proven free and at least its
    L_j. Returns (c: FCL's value where ``known``, L_j elsewhere; known (n,) bool)."""
    n = P.shape[0]
    c = np.full(n, np.nan)
    known = np.zeros(n, dtype=bool)
    todo = np.unique(np.r_[np.arange(0, n, stride), n - 1])
    index = np.arange(n)
    while todo.size:
        c[todo] = values(todo)
        known[todo] = True
        left = np.maximum.accumulate(np.where(known, index, -1))
        right = np.minimum.accumulate(np.where(known, index, n)[::-1])[::-1]
        L = np.maximum(c[left] - (P - P[left]), c[right] - (P[right] - P))  # first, last known
        smallest = c[known].min()
        todo = np.flatnonzero(~known & ((L <= 0.0) | (L < smallest)))
    c[~known] = L[~known]
    return c, known


def tool_poses(tc: TeleopCase, q, *, head=None, t=None) -> np.ndarray:
    """(n, 4, 4) the Tool frame in the scan mesh's frame at configurations ``q`` (n, 6); with
    ``head`` (a HeadMotion) at times ``t`` (n,), in the moving head's (module notes)."""
    X_WT = tc.X_WE(q) @ X_ET
    if head is not None:
        X_WT = invert(head.D(np.asarray(t, dtype=float).reshape(-1))) @ X_WT
    return tc.fpsm.X_WC @ np.linalg.inv(tc.X_WCenter) @ X_WT


def segment_paths(tc: TeleopCase, q, reach: float) -> np.ndarray:
    """(n - 1,) S per segment of the joint-linear motion between consecutive configurations
    ``q`` (n, 6): the longest path of a tool point within ``reach`` of the TCP (module
    docstring)."""
    q = np.asarray(q, dtype=float)
    frames = kin.joint_frames(q[:-1])  # base frame: distances are frame-free
    p = kin.fk(q[:-1], tc.X_FE)[:, None, :3, 3]
    o, z = frames[:, :, :3, 3], frames[:, :, :3, 2]  # joint i's origin and axis at q_k
    d = np.linalg.norm(p - o, axis=2)  # (n - 1, 6): |p - o_i| at q_k
    dq = np.diff(q, axis=0)
    a = np.abs(dq)
    A = a.sum(axis=1)
    grow = np.exp(A)
    coarse = (a * (reach + grow[:, None] * d)).sum(axis=1)
    G = grow * d.max(axis=1)
    w0 = np.linalg.norm(np.einsum("ki,kij->kj", dq, z), axis=1)
    v0 = np.linalg.norm(np.einsum("ki,kij->kj", dq, np.cross(z, p - o)), axis=1)
    through_tcp = v0 + A * A * G + reach * (w0 + 0.5 * A * A)
    return np.minimum(coarse, through_tcp)


def head_paths(tc: TeleopCase, q, t, head, reach: float, arm: np.ndarray) -> np.ndarray:
    """(n - 1,) what the moving head adds to each segment's S (module notes): dt (omega_max
    rho + v_max), ``arm`` the segments' S of the arm alone."""
    w_max, v_max = head.speed_bounds()
    t = np.asarray(t, dtype=float)
    dt = np.diff(t)
    p = tc.X_WE(np.asarray(q, dtype=float)[:-1])[:, :3, 3]
    centre = head.pivot + head.displacement(t[:-1])[0]  # the pivot's image p + u
    rho = np.linalg.norm(p - centre, axis=1) + reach + arm + dt * v_max
    return dt * (w_max * rho + v_max)


def swept_clearance(tc: TeleopCase, exact: ExactClearance, q, *, substeps: int = 8,
                    at_poses=None, head=None, t=None, screen: bool = False) -> Swept:
    """The exact clearance of the tool at the logged configurations ``q`` (n, 6) of a run and
    over the arm's motion between them (module docstring). ``at_poses``: the clearance at the
    configurations if already computed; ``head`` (a HeadMotion) and ``t`` (n,) the log times:
    against the moving head's scan (module notes). ``screen``: FCL only at the poses that can
    hold the run's smallest clearance (:func:`screened`; the smallest, the sampled minimum and
    the certified bound are as sound, ``at_poses`` is FCL's only where ``exact_at``)."""
    q = np.asarray(q, dtype=float)
    if head is not None and (t is None or np.shape(t) != (q.shape[0],)):
        raise InputError("t", f"expected the {q.shape[0]} log times with a head motion")
    if q.shape[0] >= 2:
        S = segment_paths(tc, q, exact.reach)
        if head is not None:
            S = S + head_paths(tc, q, t, head, exact.reach, S)
    if at_poses is not None:
        c, known = np.asarray(at_poses, dtype=float), np.ones(q.shape[0], dtype=bool)
    else:
        X = tool_poses(tc, q, head=head, t=t)
        if screen and q.shape[0] >= 2:
            c, known = screened(lambda k: exact(X[k]), np.r_[0.0, np.cumsum(S)])
        else:
            c, known = exact(X), np.ones(q.shape[0], dtype=bool)
    if q.shape[0] < 2:
        return Swept(c, float(c.min()), float(c.min()), np.zeros(0), 0, known)
    ends = np.minimum(c[:-1], c[1:])
    todo = np.flatnonzero((ends - 0.5 * S < c.min()) & (S > 0.0))
    sampled, bound = float(c.min()), float(c.min())
    if todo.size:
        s = np.arange(1, substeps) / substeps
        qs = q[todo, None, :] + s[None, :, None] * (q[todo + 1] - q[todo])[:, None, :]
        ts = None
        if head is not None:
            t = np.asarray(t, dtype=float)
            ts = (t[todo, None] + s[None, :] * (t[todo + 1] - t[todo])[:, None]).reshape(-1)
        cs = exact(tool_poses(tc, qs.reshape(-1, 6), head=head, t=ts)).reshape(
            todo.size, substeps - 1)
        chain = np.concatenate([c[todo, None], cs, c[todo + 1, None]], axis=1)
        sub = np.minimum(chain[:, :-1], chain[:, 1:]) - 0.5 * (S[todo] / substeps)[:, None]
        sampled = min(sampled, float(cs.min()))
        bound = min(bound, float(sub.min()))
    return Swept(c, sampled, bound, S, int(todo.size), known)
