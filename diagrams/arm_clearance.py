"""Drake SceneGraph confirmation of arm configurations (the exact reference of the fast model).

``ComputeSignedDistancePairwiseClosestPoints`` on the scenario's plant (:func:`diagrams.plant.
build_plant`, the base welded where the planner put it) over every pair SceneGraph does not
filter: the arm and actuator against themselves, the cart, the patient and the chair. This is
what the planner's reported configurations are confirmed with: the selected
base along its whole feed, every Pareto member written out; ``systems.robot.arm_collision`` is the
fast conservative model checked against it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from implantplan.diagrams.plant import PATIENT, build_plant
from implantplan.systems.errors import InputError
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp


@dataclass(frozen=True)
class Clearance:
    """Smallest SceneGraph signed distance over configurations.

    Attributes:
        distance: (N,) per configuration (m; +inf when no pair is within ``max_distance``).
        pair: per configuration the two geometry names of its closest pair ("" when none).
        patient: (N,) the same over the pairs with a patient or chair geometry (the
            scenario's obstacles), +inf when none is within ``max_distance``.
        patient_pair: per configuration its closest such pair.
    """

    distance: np.ndarray
    pair: tuple[tuple[str, str], ...]
    patient: np.ndarray | None = None
    patient_pair: tuple[tuple[str, str], ...] = ()

    def worst(self) -> tuple[int, float, tuple[str, str]]:
        """(index, distance, pair) of the configuration with the smallest distance."""
        k = int(np.argmin(self.distance))
        return k, float(self.distance[k]), self.pair[k]


class SceneGraphClearance:
    """The scenario's plant with the base at one position, queried for signed distances.

    Args:
        sc: the MOPRP scenario (its X_WO, obstacles, cart, limits).
        xyz: base position in Oral (m).
    """

    def __init__(self, sc: moprp.Scenario, xyz):
        xyz = np.asarray(xyz, dtype=float)
        if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
            raise InputError("base_xyz", f"expected a finite (3,) position in m, got {xyz}")
        self.xyz = xyz
        self.diagram, self.plant, self.scene_graph, self.handles = build_plant(
            scenario=sc, X_WBase=sc.X_WO @ moprp.base_pose(xyz), limits=sc.limits, tool=True)
        self._context = self.diagram.CreateDefaultContext()
        self._plant_context = self.plant.GetMyMutableContextFromRoot(self._context)
        self._sg_context = self.scene_graph.GetMyContextFromRoot(self._context)
        self._query = self.scene_graph.get_query_output_port()
        self._inspector = self.scene_graph.model_inspector()

    def __call__(self, q, *, max_distance: float = 0.05) -> Clearance:
        """Smallest signed distance of each configuration ``q`` (N, 6) over the unfiltered pairs
        (pairs farther than ``max_distance`` are not reported: +inf when none is closer)."""
        q = np.asarray(q, dtype=float).reshape(-1, 6)
        d = np.full(q.shape[0], np.inf)
        d_pat = np.full(q.shape[0], np.inf)
        pairs, pat_pairs = [], []
        for k, qk in enumerate(q):
            self.plant.SetPositions(self._plant_context, self.handles.arm, qk)
            best, pair = np.inf, ("", "")
            best_p, pair_p = np.inf, ("", "")
            for r in self._query.Eval(self._sg_context).ComputeSignedDistancePairwiseClosestPoints(
                    max_distance=max_distance):
                names = (self._inspector.GetName(r.id_A), self._inspector.GetName(r.id_B))
                if r.distance < best:
                    best, pair = r.distance, names
                if r.distance < best_p and any(n.startswith(PATIENT + "::") for n in names):
                    best_p, pair_p = r.distance, names
            d[k], d_pat[k] = best, best_p
            pairs.append(pair)
            pat_pairs.append(pair_p)
        return Clearance(distance=d, pair=tuple(pairs), patient=d_pat,
                         patient_pair=tuple(pat_pairs))


def feed_path(sc: moprp.Scenario, xyz, branch: int, *, X_OT=None, step: float = 0.001,
              step_angle: float = np.deg2rad(0.5)) -> np.ndarray:
    """Configurations along the straight feed from the pre-feed pose to the target on one IK
    branch, sampled so that the TCP moves at most ``step`` (m) and no joint more than
    ``step_angle`` (rad) between samples (the samples are refined until both hold).

    Returns:
        (K, 6) joint vectors; rows with no solution on the branch are NaN.
    """
    n = max(int(np.ceil(sc.feed_length / step)) + 1, sc.feed_samples, 2)
    for _ in range(8):
        X = moprp.feed_poses(np.asarray(xyz, dtype=float), sc.feed_length, n, X_OT)
        r = kin.ik(X, limits=sc.limits, X_FT=sc.X_FT)
        q = np.where(r.valid[:, branch, None], r.q[:, branch], np.nan)
        jump = np.nanmax(np.abs(np.diff(q, axis=0))) if np.all(np.isfinite(q)) else 0.0
        if jump <= step_angle:
            return q
        n = int(np.ceil(n * jump / step_angle)) + 1
    return q


PATIENT_REACH = 0.1  # m: SceneGraph reports the pairs closer than this along a confirmed feed


def confirm_feed(checker: SceneGraphClearance, sc: moprp.Scenario, branch: int, *,
                 X_OT=None) -> dict:
    """SceneGraph clearance along the selected branch's whole feed at the checker's base, and
    the joint headroom along that feed and along the feed of every head displacement the
    scenario allows (:func:`systems.robot.moprp.head_displacements`).

    Returns:
        dict(distance (m, the smallest along the feed), pair [name, name], samples, ok (every
        sample reached, distance >= the scenario's clearance and every joint's headroom >= the
        scenario's), limit (= clearance), distance_pre / distance_target (m, at the pre-feed
        and target configurations), headroom (6,) (rad, per joint, the smallest over the feeds;
        -inf where a displaced feed leaves the branch), headroom_limit (rad)).
    """
    q = feed_path(sc, checker.xyz, branch, X_OT=X_OT)
    reached = bool(np.all(np.isfinite(q)))
    X_OT0 = np.eye(4) if X_OT is None else np.asarray(X_OT, dtype=float)
    paths = [q] + [feed_path(sc, checker.xyz, branch, X_OT=D @ X_OT0)
                   for D in moprp.head_displacements(sc)[1:]]
    room = np.min([np.where(np.isfinite(p), kin.joint_headroom(np.nan_to_num(p), sc.limits),
                            -np.inf).min(axis=0) for p in paths], axis=0)
    head = {"headroom": room, "headroom_limit": float(sc.joint_headroom)}
    room_ok = bool(np.all(room >= sc.joint_headroom))
    c = checker(q[np.all(np.isfinite(q), axis=1)],
                max_distance=max(PATIENT_REACH, 2 * sc.clearance))
    if not reached:
        return {"distance": float("-inf"), "pair": ["", ""], "samples": int(q.shape[0]),
                "ok": False, "limit": sc.clearance, "distance_pre": float("nan"),
                "distance_target": float("nan"), **head}
    _, dist, pair = c.worst()
    kp = int(np.argmin(c.patient))
    return {"distance": dist, "pair": list(pair), "samples": int(q.shape[0]),
            "ok": bool(dist >= sc.clearance) and room_ok, "limit": sc.clearance,
            "distance_pre": float(c.distance[0]), "distance_target": float(c.distance[-1]),
            "patient_distance": float(c.patient[kp]), "patient_pair": list(c.patient_pair[kp]),
            "max_distance": PATIENT_REACH, **head}


# --------------------------------------------------------------------------------------------
# The fast model against SceneGraph on many samples (tests, analyses/bench_moprp.py)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Agreement:
    """Fast-model verdicts against SceneGraph's at the scenario's clearance.

    Attributes:
        samples: configurations compared.
        scene_graph_free: how many SceneGraph finds clear (distance >= clearance).
        false_free: the fast model calls clear, SceneGraph finds closer than the clearance (must
            be 0).
        false_reject: the fast model rejects, SceneGraph finds clear.
        worst_false_free: (distance SceneGraph, fast lower bound, pair) of the worst false-free
            case, None when there is none.
    """

    samples: int
    scene_graph_free: int
    false_free: int
    false_reject: int
    worst_false_free: tuple | None = None

    @property
    def false_reject_rate(self) -> float:
        """False rejects over the configurations SceneGraph finds clear."""
        return self.false_reject / max(self.scene_graph_free, 1)

    def __add__(self, other: Agreement) -> Agreement:
        worst = [w for w in (self.worst_false_free, other.worst_false_free) if w is not None]
        return Agreement(self.samples + other.samples,
                         self.scene_graph_free + other.scene_graph_free,
                         self.false_free + other.false_free,
                         self.false_reject + other.false_reject,
                         min(worst, key=lambda w: w[0]) if worst else None)


def compare_at_base(sc: moprp.Scenario, xyz, q, *, model=None) -> Agreement:
    """Compare the fast model (systems.robot.arm_collision via moprp.collision_clearance) with
    SceneGraph on configurations ``q`` (N, 6) at one base position ``xyz``."""
    q = np.asarray(q, dtype=float).reshape(-1, 6)
    if q.shape[0] == 0:
        return Agreement(0, 0, 0, 0)
    model = model or moprp.collision_model(sc)
    c = moprp.collision_clearance(q, xyz, sc, model, cutoff=sc.clearance)
    d_fast = np.minimum(np.minimum(c["self"], c["environment"]), c["cabinet"])
    fast_free = moprp.is_clear(d_fast, sc.clearance)
    sg = SceneGraphClearance(sc, xyz)(q, max_distance=max(0.02, 2 * sc.clearance))
    sg_free = sg.distance >= sc.clearance
    bad = np.flatnonzero(fast_free & ~sg_free)
    worst = None
    if bad.size:
        k = bad[np.argmin(sg.distance[bad])]
        worst = (float(sg.distance[k]), float(d_fast[k]), sg.pair[k])
    return Agreement(int(q.shape[0]), int(sg_free.sum()), int(bad.size),
                     int(np.sum(~fast_free & sg_free)), worst)


def random_bases(sc: moprp.Scenario, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` uniform base positions in the scenario's bounds (m, in Oral)."""
    return sc.lower + rng.random((n, 3)) * (sc.upper - sc.lower)


def near_target_configurations(sc: moprp.Scenario, xyz, n: int, rng: np.random.Generator, *,
                               max_angle: float = np.deg2rad(10.0),
                               max_offset: float = 0.02) -> np.ndarray:
    """IK solutions (all branches within the joint limits) at up to ``n`` feeding targets
    perturbed from the scenario's End target by a rotation of up to ``max_angle`` (rad, uniform
    axis) and a shift of up to ``max_offset`` (m, uniform in the ball); (m <= 8 n, 6)."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = max_angle * rng.random(n)
    shift = rng.normal(size=(n, 3))
    shift *= (max_offset * rng.random(n) ** (1 / 3) / np.linalg.norm(shift, axis=1))[:, None]
    K = np.zeros((n, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K = K - np.swapaxes(K, 1, 2)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    R = np.eye(3) + s * K + (1 - c) * K @ K  # Rodrigues
    X_EEp = np.zeros((n, 4, 4))
    X_EEp[:, :3, :3], X_EEp[:, :3, 3], X_EEp[:, 3, 3] = R, shift, 1.0
    X_BE = moprp.target_pose(np.asarray(xyz, dtype=float)) @ X_EEp
    r = kin.ik(X_BE, limits=sc.limits, X_FT=sc.X_FT)
    return r.q[r.valid]
