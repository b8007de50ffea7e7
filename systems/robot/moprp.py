"""MOPRP: multi-objective preoperative robot (base) placement (seed 001; DESIGN.md section 5).

The paper's equations were lost from its text; DESIGN.md section 5 is the spec. The pipeline for
a batch of base positions p (P, 3), all vectorized:

1. **Target** (paper "Target position and posture"): End (actuator TCP) coincides with Oral, End Y
   along Oral Z, End X along -Oral Y; Base X || Oral X, Base Z || Oral Y. So the rotation Base->End
   is a constant and only the position varies: X_BE(p) = X_OB(p)^-1 X_OE (:func:`target_pose`).
2. **IK enumeration** (paper Eq. 6): all 8 closed-form branches (systems.robot.kinematics.ik), each
   keeping its branch index, at ``feed_samples`` poses along the straight feed from the pre-feed
   pose (TCP backed out along the feeding axis, End -Z, by the feed length) to the target.
3. **Removing invalid results** (paper Eq. 7, the collision-free principle): a branch survives if
   it exists within the joint limits at every feed sample and moves continuously (no joint steps
   more than ``max_joint_step`` between samples, so the same branch is followed along the feed);
   condition 1: joint 2 within the range that keeps the upper arm off the cabinet; condition 2:
   the actuator clear of the arm's links; plus the arm clear of the patient/chair and of the
   cabinet box: every pair the plant's SceneGraph checks, with the fast conservative model
   generated from the plant's geometry (systems.robot.arm_collision) at the pre-feed and target
   configurations (SceneGraph confirms the reported ones, diagrams.arm_clearance).
4. **Indices** (paper Eq. 8-22, all minimized), from the body Jacobian J = [J_w; J_v] at the target
   (:func:`indices`): dexterity I_d = max(cond J_v, cond J_w); error range I_e = eps sigma_max(J_v)
   (the largest TCP position error for a joint error ball ||dq|| <= eps, Eq. 15-19); joint variation
   I_j = sum over joints of the distance travelled along the feed (Eq. 22-23, sampled).
   The paper's Eq. 20 claims the angular error range eps sigma_max(J_w) is a constant; we compute
   it alongside (``angular_error_range``) so the claim can be checked numerically.
5. **Score-based selection** (paper Fig. 4): rank each index among a base's surviving branches,
   sum the ranks, the smallest sum wins; ties broken by the seeded generator (:func:`select`).
6. The GA's problem (:func:`evaluate_bases`): objectives (P, 3) of the selected branch, constraint
   violation (P,) (0 when some branch survives, else a graded measure of how far the best branch
   is from surviving), the branch index and q.

Departures from the paper, each for a reason: the feeding axis is the actuator's rod (End -Z),
which the paper's Fig. 6 implies but does not state; joint variation follows the sampled straight
feed on the same branch instead of only its two end configurations (the paper's Eq. 23 measures
travelled distance, not the end-to-end difference); the patient/chair and the cabinet box are
extra collision checks that the paper handled by condition 1 alone.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields

import numpy as np

from implantplan.systems import seeds
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.frames import invert, rpy_to_rotation, transform
from implantplan.systems.robot import arm_collision
from implantplan.systems.robot import collision_primitives as cp
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot.nsga2 import non_dominated_sort, nsga2

# The scenario schema lives in systems.robot.scenario; its names are part of this module's
# interface.
from implantplan.systems.robot.scenario import (  # noqa: F401
    BUNDLED,
    Actuator,
    Obstacle,
    Scenario,
    load_scenario,
    scenario_from_dict,
    scenario_path,
)

# Base axes in Oral (columns): Base X = Oral X, Base Y = -Oral Z, Base Z = Oral Y.
R_OB = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
# End axes in Oral (columns): End X = -Oral Y, End Y = Oral Z, End Z = X x Y = -Oral X.
R_OE = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
R_BE = R_OB.T @ R_OE
X_OE = transform(R_OE, np.zeros(3))  # End in Oral (or in Tool, for a site's target)
INDEX_NAMES = ("dexterity", "error_range", "joint_variation")
HEAD_FEED_SAMPLES = 3  # poses along each displaced feed in the search (start, middle, end)

# --------------------------------------------------------------------------------------------
# Target, feed, IK
# --------------------------------------------------------------------------------------------


def base_pose(xyz) -> np.ndarray:
    """X_OB (..., 4, 4): the base at position ``xyz`` in Oral with the fixed orientation R_OB."""
    return transform(R_OB, np.asarray(xyz, dtype=float))


def target_pose(xyz, X_OT=None) -> np.ndarray:
    """X_BE (..., 4, 4): the TCP target seen from the base at ``xyz``.

    The target is End = Oral rotated by R_OE (the paper's convention), or, for several implant
    sites served from one base, End = T rotated by R_OE where ``X_OT`` is the site's feeding
    target (seed 000's Tool frame) in Oral: the base keeps its orientation R_OB relative to
    Oral, only the target moves.
    """
    xyz = np.asarray(xyz, dtype=float)
    if X_OT is None:
        return transform(R_BE, -np.einsum("ji,...j->...i", R_OB, xyz))
    return invert(base_pose(xyz)) @ np.asarray(X_OT, dtype=float) @ X_OE


def feed_poses(xyz, feed_length: float, samples: int, X_OT=None) -> np.ndarray:
    """X_BE along the straight feed (..., samples, 4, 4): sample 0 is the pre-feed pose (TCP backed
    out along End -Z by ``feed_length``), the last is the target (see :func:`target_pose`)."""
    X = target_pose(xyz, X_OT)
    s = np.linspace(-feed_length, 0.0, samples)  # offset along End Z
    z_B = X[..., None, :3, 2]
    out = np.broadcast_to(X[..., None, :, :], X.shape[:-2] + (samples, 4, 4)).copy()
    out[..., :3, 3] += s[:, None] * z_B
    return out


def head_displacements(sc: Scenario) -> np.ndarray:
    """(H, 4, 4) displacements D_O of the head in Oral the feed must follow with its joint
    headroom: the identity, then a translation of ``sc.head_translation`` along +-each Oral
    axis and a rotation of ``sc.head_rotation`` about +-each Oral axis through the Oral origin
    (the mouth); the displaced feeding target is D_O X_OT. Zero sizes drop their six."""
    D = [np.eye(4)]
    for k in range(3):
        for sign in (1.0, -1.0):
            if sc.head_translation > 0:
                D.append(transform(np.eye(3), sign * sc.head_translation * np.eye(3)[k]))
            if sc.head_rotation > 0:
                D.append(transform(rpy_to_rotation(sign * sc.head_rotation * np.eye(3)[k]),
                                   np.zeros(3)))
    return np.array(D)


def feed_headroom(q, ok, limits) -> np.ndarray:
    """The smallest joint headroom (rad, :func:`kinematics.joint_headroom`) per joint over the
    feed samples and head displacements: ``q`` (..., H, K, 6) and ``ok`` (..., H, K) ->
    (..., 6); -inf for every joint where some pose has no solution on the branch."""
    h = kin.joint_headroom(np.where(ok[..., None], q, 0.0), limits)
    h = np.where(ok[..., None], h, -np.inf)
    return h.min(axis=(-3, -2))


# --------------------------------------------------------------------------------------------
# Indices (paper Eq. 8-23)
# --------------------------------------------------------------------------------------------


def _sv_extremes(A) -> tuple[np.ndarray, np.ndarray]:
    """(sigma_min, sigma_max) of (..., 3, n) matrices from the eigenvalues of A A^T."""
    ev = np.linalg.eigvalsh(A @ np.swapaxes(A, -1, -2))
    ev = np.clip(ev, 0.0, None)
    return np.sqrt(ev[..., 0]), np.sqrt(ev[..., -1])


def indices(q, q_path, *, eps: float, X_FT) -> dict[str, np.ndarray]:
    """The three MOPRP indices (and the angular error range, for the Eq. 20 check).

    Args:
        q: (..., 6) target configurations.
        q_path: (..., K, 6) configurations along the feed ending at ``q`` (same branch).
        eps: joint error radius (rad).
        X_FT: TCP in the flange frame.

    Returns:
        dict with ``dexterity`` = max(cond J_v, cond J_w) (Eq. 8-9), ``error_range`` =
        eps sigma_max(J_v) (m, Eq. 15-19), ``angular_error_range`` = eps sigma_max(J_w) (rad,
        Eq. 20), ``joint_variation`` = sum_i sum_k |q_i(k+1) - q_i(k)| (rad, Eq. 22-23).
    """
    J = kin.jacobian_body(q, X_FT)
    Jw, Jv = J[..., :3, :], J[..., 3:, :]
    wmin, wmax = _sv_extremes(Jw)
    vmin, vmax = _sv_extremes(Jv)
    with np.errstate(divide="ignore"):
        cond_w = np.where(wmin > 0, wmax / np.where(wmin > 0, wmin, 1.0), np.inf)
        cond_v = np.where(vmin > 0, vmax / np.where(vmin > 0, vmin, 1.0), np.inf)
    travel = np.abs(np.diff(np.asarray(q_path, dtype=float), axis=-2)).sum(axis=(-1, -2))
    return {
        "dexterity": np.maximum(cond_v, cond_w),
        "error_range": eps * vmax,
        "angular_error_range": eps * wmax,
        "joint_variation": travel,
    }


# --------------------------------------------------------------------------------------------
# Score-based selection (paper Fig. 4)
# --------------------------------------------------------------------------------------------


def select(values, valid, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Pick one representative branch per base by rank points, ties broken by ``rng``.

    Args:
        values: (P, B, 3) indices of each base's B candidate branches (all minimized).
        valid: (P, B) which candidates survived the collision-free principle.
        rng: generator for the tie-break (one uniform draw per candidate).

    Returns:
        ``(choice, score)``: chosen branch (P,) (-1 when none is valid) and the winner's score
        (sum over indices of its rank among the valid candidates, 0 = best in all; -1 if none).
    """
    values = np.asarray(values, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    v = np.where(valid[..., None], values, np.inf)
    # rank = number of valid candidates strictly better in that index (ties share the rank)
    better = (v[:, None, :, :] < v[:, :, None, :]) & valid[:, None, :, None]
    rank = better.sum(axis=2)  # (P, B, 3)
    score = np.where(valid, rank.sum(axis=-1), np.iinfo(np.int64).max // 4).astype(float)
    key = score + 0.5 * rng.random(valid.shape)  # tie-break inside equal integer scores
    choice = np.argmin(key, axis=1)
    any_valid = valid.any(axis=1)
    best = np.take_along_axis(score, choice[:, None], axis=1)[:, 0]
    return np.where(any_valid, choice, -1), np.where(any_valid, best, -1).astype(int)


# --------------------------------------------------------------------------------------------
# Collision-free principle (paper Eq. 7)
# --------------------------------------------------------------------------------------------


CollisionModel = arm_collision.ArmCollisionModel


def collision_model(sc: Scenario) -> arm_collision.ArmCollisionModel:
    """The fast conservative model of the scenario's plant (systems.robot.arm_collision): the arm
    and
    actuator shapes from the URDFs, the scenario's cart, patient and chair, every pair the
    plant's SceneGraph does not filter."""
    return arm_collision.model_for(sc)


def collision_clearance(q, xyz, sc: Scenario, model: CollisionModel | None = None, *,
                        cutoff: float = np.inf):
    """Lower bounds of the clearances (m) of configurations ``q`` (N, 6) with the base at ``xyz``
    (N, 3), from the fast model (never above SceneGraph's signed distance).

    Args:
        cutoff: pairs farther apart than this may report a lower bound >= cutoff instead of
            their distance (a verdict at the scenario's clearance needs cutoff >= clearance).

    Returns:
        dict with ``self`` (arm and actuator against themselves: condition 2 and the links),
        ``environment`` (vs patient/chair), ``cabinet`` (vs the cart box under the base), each
        (N,), +inf when there is nothing to test; and ``pair`` (N, 3) the closest pair's index
        per group into ``model.pairs`` (-1 when none).
    """
    model = model or collision_model(sc)
    q = np.asarray(q, dtype=float).reshape(-1, 6)
    xyz = np.broadcast_to(np.asarray(xyz, dtype=float), (q.shape[0], 3))
    d, pair = model.clearance(q, arm_collision.world_in_base(xyz, sc.X_WO, R_OB), cutoff=cutoff)
    out = {g: d[:, k] for k, g in enumerate(arm_collision.GROUPS)}
    out["pair"] = pair
    return out


def is_clear(d, clearance: float) -> np.ndarray:
    """Verdict on fast-model distances: clear when d >= clearance, up to the floating-point
    rounding of the kinematic chain (:data:`systems.robot.arm_collision.ROUNDING`, 1e-12 m)."""
    return np.asarray(d) >= clearance - arm_collision.ROUNDING


_BOX_CORNERS = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
_BOX_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                       if np.sum(_BOX_CORNERS[a] != _BOX_CORNERS[b]) == 1])


def box_edges(X, half) -> np.ndarray:
    """The 12 edges (..., 12, 2, 3) of boxes: centre poses X (..., 4, 4), half sizes (..., 3)."""
    corners = (_BOX_CORNERS * np.asarray(half)[..., None, :]) @ np.swapaxes(
        np.asarray(X)[..., :3, :3], -1, -2) + np.asarray(X)[..., None, :3, 3]
    return corners[..., _BOX_EDGES, :]


def cart_clearance(xyz, sc: Scenario) -> np.ndarray:
    """Clearance (m) between the cart/cabinet box (fixed under the base) and the patient/chair,
    per base position (P,). Two boxes overlap iff an edge of one meets the other or one holds
    the other's centre, so box-box is tested by edges both ways plus the centres (0 = touching
    or overlapping; the clearance is exact when the closest features are an edge and a face)."""
    xyz = np.atleast_2d(np.asarray(xyz, dtype=float))
    n = xyz.shape[0]
    out = np.full(n, np.inf)
    if not sc.obstacles:
        return out
    X_BW = invert(base_pose(xyz)) @ invert(sc.X_WO)  # (P, 4, 4)
    R_BW = X_BW[0, :3, :3]
    cart_edges = box_edges(sc.X_BC, sc.cabinet_half)  # (12, 2, 3) in Base
    cart_seg = np.broadcast_to(cart_edges, (n, 12, 2, 3))
    cart_R = sc.X_BC[None, :3, :3]
    cart_p = np.broadcast_to(sc.X_BC[:3, 3], (n, 1, 3))
    zeros12 = np.zeros(12)
    for o in sc.obstacles:
        if o.kind == "capsule":
            seg_B = np.array([o.p0, o.p1]) @ R_BW.T + X_BW[:, None, :3, 3]  # (P, 2, 3)
            d = cp.min_box_clearance(seg_B[:, None], np.array([o.radius]), cart_R, cart_p,
                                     sc.cabinet_half[None])
        else:
            R_box = (R_BW @ o.X_WB[:3, :3])[None]
            p_box = (o.X_WB[:3, 3] @ R_BW.T + X_BW[:, :3, 3])[:, None]  # (P, 1, 3)
            d1 = cp.min_box_clearance(cart_seg, zeros12, R_box, p_box, o.half_size[None])
            X_o = transform(R_box[0], p_box[:, 0])  # (P, 4, 4)
            d2 = cp.min_box_clearance(box_edges(X_o, o.half_size), zeros12, cart_R, cart_p,
                                      sc.cabinet_half[None])
            inside = np.all(np.abs(p_box[:, 0] - sc.X_BC[:3, 3]) <= sc.cabinet_half, axis=1)
            local = (sc.X_BC[:3, 3] - p_box[:, 0]) @ R_box[0]
            inside |= np.all(np.abs(local) <= o.half_size, axis=1)
            d = np.where(inside, 0.0, np.minimum(d1, d2))
        out = np.minimum(out, d)
    return out


# --------------------------------------------------------------------------------------------
# The problem evaluated by the GA
# --------------------------------------------------------------------------------------------


@dataclass
class BaseEvaluation:
    """Evaluation of P base positions (see :func:`evaluate_bases`).

    Attributes:
        objectives: (P, 3) [dexterity, error_range, joint_variation] of the selected branch
            (+inf where infeasible).
        violation: (P,) 0 when feasible, else > 0 (how far the closest branch is from surviving).
        branch: (P,) selected branch index 0..7, -1 when infeasible.
        q, q_pre: (P, 6) selected configuration at the target / at the pre-feed pose (NaN if none).
        valid: (P, 8) which branches survived.
        headroom: (P, 6) smallest joint headroom (rad) of the selected branch along the feed
            and under the head motions (NaN if none).
        reason: (P, 8) int, why each branch was dropped (see ``DROP_REASONS``).
        candidate_indices: (P, 8, 3) indices of every surviving branch (inf elsewhere).
        angular_error_range: (P, 8) eps sigma_max(J_w) per surviving branch (NaN elsewhere).
    """

    objectives: np.ndarray
    violation: np.ndarray
    branch: np.ndarray
    q: np.ndarray
    q_pre: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    candidate_indices: np.ndarray
    angular_error_range: np.ndarray
    headroom: np.ndarray

    @property
    def feasible(self) -> np.ndarray:
        return self.branch >= 0

    def subset(self, index) -> BaseEvaluation:
        """The evaluation of the bases ``index`` (an index array or mask over P)."""
        return BaseEvaluation(**{f.name: getattr(self, f.name)[index] for f in fields(self)})


(DROP_OK, DROP_IK, DROP_CONTINUITY, DROP_JOINT2, DROP_SELF, DROP_ENV, DROP_CABINET,
 DROP_CART, DROP_HEADROOM) = range(9)
DROP_REASONS = {
    DROP_OK: "ok",
    DROP_IK: "no IK solution within the joint limits somewhere along the feed",
    DROP_CONTINUITY: "branch jumps between feed samples (not continuous)",
    DROP_JOINT2: "condition 1: joint 2 outside the range clear of the cabinet",
    DROP_SELF: "condition 2: actuator or wrist hits the arm",
    DROP_ENV: "arm hits the patient or chair",
    DROP_CABINET: "arm hits the cabinet",
    DROP_CART: "the cart itself overlaps the patient or chair at this base position",
    DROP_HEADROOM: "a joint comes closer to its limit than the headroom along the feed or "
                   "under the head motions",
}


def ik_closed_form(X_BT, *, limits, X_FT):
    """The default IK enumeration: closed form, 8 branches with stable branch indices."""
    r = kin.ik(X_BT, limits=limits, X_FT=X_FT)
    return r.q, r.valid


def evaluate_bases(
    xyz,
    sc: Scenario,
    rng: np.random.Generator,
    *,
    ik_solver=ik_closed_form,
    model: CollisionModel | None = None,
    X_OT=None,
) -> BaseEvaluation:
    """Evaluate base positions ``xyz`` (P, 3) in Oral: the GA's vectorized problem.

    Args:
        xyz: (P, 3) base positions (m, in Oral).
        sc: scenario.
        rng: generator for the score-based selection's tie-breaks.
        ik_solver: ``(X_BT (..., 4, 4), limits=, X_FT=) -> (q (..., B, 6), valid (..., B))``;
            slot b must be the same branch at every feed sample (the closed form guarantees it;
            other solvers must track their solutions, see analyses.robot).
        model: precomputed collision model (built from ``sc`` if None).
        X_OT: the feeding target (Tool frame) in Oral when it is not Oral itself (several
            implant sites from one base; see :func:`target_pose`).
    """
    xyz = np.atleast_2d(np.asarray(xyz, dtype=float))
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError("xyz", f"expected (P, 3) base positions, got {xyz.shape}")
    P = xyz.shape[0]
    model = model or collision_model(sc)
    K = sc.feed_samples
    X = feed_poses(xyz, sc.feed_length, K, X_OT)  # (P, K, 4, 4)
    q, ok = ik_solver(X, limits=sc.limits, X_FT=sc.X_FT)  # (P, K, B, 6), (P, K, B)
    B = q.shape[2]
    q = np.swapaxes(q, 1, 2)  # (P, B, K, 6)
    ok = np.swapaxes(ok, 1, 2)  # (P, B, K)
    ik_fail = (~ok).sum(axis=-1) / K
    alive = ik_fail == 0
    reason = np.where(alive, DROP_OK, DROP_IK)
    step = np.abs(np.diff(q, axis=2)).max(axis=(-1, -2))
    jump = alive & (step > sc.max_joint_step)
    reason = np.where(jump, DROP_CONTINUITY, reason)
    alive &= ~jump
    viol = ik_fail + np.where(jump, 0.5, 0.0)

    # the cart under the base must stand clear of the patient and chair (independent of q)
    d_cart = cart_clearance(xyz, sc)
    cart_bad = d_cart < sc.clearance
    viol = viol + np.where(cart_bad, sc.clearance - np.minimum(d_cart, sc.clearance) + 1e-3,
                           0.0)[:, None]
    reason = np.where(alive & cart_bad[:, None], DROP_CART, reason)
    alive &= ~cart_bad[:, None]

    lo2, hi2 = sc.joint2_range
    q2 = q[..., 1]  # (P, B, K)
    j2_excess = np.maximum(np.maximum(lo2 - q2, q2 - hi2), 0.0).max(axis=-1)
    j2_bad = alive & (j2_excess > 0)
    reason = np.where(j2_bad, DROP_JOINT2, reason)
    viol = viol + np.where(alive, j2_excess, 0.0)
    alive &= ~j2_bad

    # joint headroom along the feed and under the head motions (DESIGN.md section 7): every
    # joint keeps sc.joint_headroom from its limits at every feed sample and at the start,
    # middle and end of the feed to every displaced target (the same branch slot: the closed
    # form keeps its branch index), for the bases with a branch left; SceneGraph's confirmation
    # checks the whole fine path of every displaced feed (diagrams.arm_clearance.confirm_feed)
    room = feed_headroom(q[:, :, None], ok[:, :, None], sc.limits)  # (P, B, 6)
    D = head_displacements(sc)
    pa = np.flatnonzero(alive.any(axis=1))
    if D.shape[0] > 1 and pa.size:
        X_OT0 = np.eye(4) if X_OT is None else np.asarray(X_OT, dtype=float)
        Xh = feed_poses(xyz[pa, None], sc.feed_length, min(K, HEAD_FEED_SAMPLES),
                        D[1:] @ X_OT0)  # (Pa, H-1, Kh, 4, 4)
        qh, okh = ik_solver(Xh, limits=sc.limits, X_FT=sc.X_FT)  # (Pa, H-1, Kh, B, 6)
        room[pa] = np.minimum(room[pa], feed_headroom(np.moveaxis(qh, 3, 1),
                                                      np.moveaxis(okh, 3, 1), sc.limits))
    room_min = room.min(axis=-1)
    short = alive & (room_min < sc.joint_headroom)
    reason = np.where(short, DROP_HEADROOM, reason)
    viol = viol + np.where(short, np.minimum(sc.joint_headroom - room_min, 1.0) + 1e-3, 0.0)
    alive &= ~short

    # collisions at the pre-feed and target configurations of the surviving branches
    pb, bb = np.nonzero(alive)
    if pb.size:
        q_ends = np.stack([q[pb, bb, 0], q[pb, bb, -1]], axis=1).reshape(-1, 6)
        xyz_ends = np.repeat(xyz[pb], 2, axis=0)
        d = collision_clearance(q_ends, xyz_ends, sc, model, cutoff=sc.clearance)
        deficit_total = np.zeros(pb.size)
        for key, code in (("cabinet", DROP_CABINET), ("environment", DROP_ENV),
                          ("self", DROP_SELF)):
            dk = d[key].reshape(-1, 2).min(axis=1)
            bad = ~is_clear(dk, sc.clearance)
            deficit_total += np.where(bad, np.maximum(sc.clearance - dk, 1e-9), 0.0)
            sub = reason[pb, bb]
            reason[pb, bb] = np.where(bad, code, sub)
        hit = deficit_total > 0
        viol[pb, bb] += deficit_total + np.where(hit, 1e-3, 0.0)
        alive[pb[hit], bb[hit]] = False

    cand = np.full((P, B, 3), np.inf)
    ang = np.full((P, B), np.nan)
    pb, bb = np.nonzero(alive)
    if pb.size:
        ind = indices(q[pb, bb, -1], q[pb, bb], eps=sc.eps, X_FT=sc.X_FT)
        cand[pb, bb] = seeds.rounded(np.stack([ind[n] for n in INDEX_NAMES], axis=-1))
        ang[pb, bb] = ind["angular_error_range"]
        finite = np.all(np.isfinite(cand[pb, bb]), axis=-1)
        alive[pb[~finite], bb[~finite]] = False  # exactly singular: not a usable candidate

    choice, _ = select(cand, alive, rng)
    feasible = choice >= 0
    c = np.where(feasible, choice, 0)
    rows = np.arange(P)
    objectives = np.where(feasible[:, None], cand[rows, c], np.inf)
    q_sel = np.where(feasible[:, None], q[rows, c, -1], np.nan)
    q_pre = np.where(feasible[:, None], q[rows, c, 0], np.nan)
    violation = np.where(feasible, 0.0, np.maximum(viol.min(axis=1), 1e-6))
    headroom = np.where(feasible[:, None], room[rows, c], np.nan)
    return BaseEvaluation(
        objectives=objectives, violation=violation, branch=choice, q=q_sel, q_pre=q_pre,
        valid=alive, reason=reason, candidate_indices=cand, angular_error_range=ang,
        headroom=headroom,
    )


def problem(sc: Scenario, *, ik_solver=ik_closed_form):
    """The GA's evaluate callable: ``(X (n, 3), rng) -> (objectives, violation)``."""
    model = collision_model(sc)

    def evaluate(X, rng):
        ev = evaluate_bases(X, sc, rng, ik_solver=ik_solver, model=model)
        F = np.where(np.isfinite(ev.objectives), ev.objectives, 1e12)
        return F, ev.violation

    return evaluate


# --------------------------------------------------------------------------------------------
# After the GA: selection on the front, percentile ranks, GII
# --------------------------------------------------------------------------------------------


def knee_point(F, weights=None) -> int:
    """Index of the selected front point: each objective normalized to [0, 1] over the front, the
    smallest weighted sum (equal weights: the point farthest below the plane through the
    normalized extremes, a knee in the sense of Das 1999)."""
    return int(selection_order(F, weights)[0])


def selection_order(F, weights=None) -> np.ndarray:
    """Front indices from the selected point (:func:`knee_point`) to the least preferred: the
    order in which candidates are taken when a better-ranked one fails confirmation."""
    F = np.asarray(F, dtype=float)
    if F.ndim != 2 or F.shape[0] == 0:
        raise InputError("front", "expected a non-empty (n, m) front")
    w = np.ones(F.shape[1]) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (F.shape[1],) or np.any(w < 0) or not np.any(w > 0):
        raise InputError("weights", f"expected {F.shape[1]} non-negative weights, not all 0")
    lo, hi = F.min(axis=0), F.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    return np.argsort(((F - lo) / span) @ w, kind="stable")


def initial_population(sc: Scenario, evaluate, rng: np.random.Generator, pop: int):
    """Seed the GA: 4 * pop uniform samples of the bounds, the feasible ones first (then the
    least violating), so the first generation already spans the feasible region.

    Returns:
        ``(X0 (pop, 3), samples, (X (4 pop, 3), violation (4 pop,)))``.
    """
    X = sc.lower + rng.random((4 * pop, 3)) * (sc.upper - sc.lower)
    F, cv = evaluate(X, rng)
    order = np.lexsort((F[:, 0], cv))
    return X[order[:pop]], X.shape[0], (X, cv)


@dataclass
class Front:
    """What :func:`search` found: the feasible non-dominated bases and the run's figures.

    Attributes:
        X: (n, 3) base positions (m, in Oral); F: (n, 3) objectives (:data:`INDEX_NAMES`).
        evaluations: base evaluations including the initial samples; generations, stopped: as
            systems.robot.nsga2 reports them; seconds_evaluation / seconds_total: wall time in the
            problem / in the whole run; initial_feasible: feasible bases among the initial
            samples; initial_samples: how many were drawn.
    """

    X: np.ndarray
    F: np.ndarray
    evaluations: int
    generations: int
    stopped: str
    seconds_evaluation: float
    seconds_total: float
    initial_feasible: int
    initial_samples: int


# Random streams below the scenario's seed (systems.seeds), one per use. The evaluation stream is
# the same wherever a base is evaluated (the search's front, SceneGraph's confirmation, the
# studio), so a base gets the same indices everywhere.
(STREAM_INIT, STREAM_NSGA, STREAM_EVALUATE, STREAM_PERCENTILES, STREAM_RANDOM_EVALUATE, STREAM_GII,
 STREAM_DRAKE_IK) = range(7)


def evaluation_rng(sc: Scenario) -> np.random.Generator:
    """The generator a base's evaluation draws from (the same for every caller)."""
    return seeds.rng(sc.seed, STREAM_EVALUATE)


def search(sc: Scenario, evaluate, *, explain=None, on_start=None, on_generation=None) -> Front:
    """The MOPRP search (NSGA-II, systems.robot.nsga2) over the base position, for one target or
    many.

    Args:
        sc: scenario (bounds, ga settings, seed).
        evaluate: the problem ``(X (n, 3), rng) -> (F (n, 3), violation (n,))``, e.g.
            :func:`problem` or a several-site combination of it.
        explain: ``(X, rng) -> str``, why no initial sample is feasible (the PlanningFailure's
            message); None gives a generic message.
        on_start: ``(feasible, samples)`` called after the initial sampling.
        on_generation: ``(generation, front_size, hypervolume)`` progress callback.

    Raises:
        PlanningFailure: no feasible base among the initial samples or on the final front.
    """
    t0 = time.perf_counter()
    rng = seeds.rng(sc.seed, STREAM_INIT)
    X0, n0, (Xs, cvs) = initial_population(sc, evaluate, rng, sc.pop)
    t_init = time.perf_counter() - t0
    n_ok = int(np.sum(cvs <= 0))
    if n_ok == 0:
        raise PlanningFailure(explain(Xs, rng) if explain is not None else
                              f"no feasible base among {Xs.shape[0]} samples of the bounds")
    if on_start is not None:
        on_start(n_ok, n0)
    res = nsga2(evaluate, sc.lower, sc.upper, pop=sc.pop, gen=sc.gen,
                seed=seeds.seed(sc.seed, STREAM_NSGA), initial=X0, patience=sc.patience,
                hv_tol=sc.hv_tol, on_generation=on_generation)
    Xf = res.X[res.front]
    F, cv = evaluate(Xf, evaluation_rng(sc))
    keep = np.flatnonzero(cv <= 0)
    keep = keep[non_dominated_sort(F[keep]) == 0]
    if keep.size == 0:
        raise PlanningFailure("the optimizer found no feasible base in the bounds")
    return Front(X=Xf[keep], F=F[keep], evaluations=int(res.evaluations + n0),
                 generations=int(res.generations), stopped=res.stopped,
                 seconds_evaluation=res.seconds_eval + t_init,
                 seconds_total=time.perf_counter() - t0, initial_feasible=n_ok,
                 initial_samples=n0)


def random_feasible(sc: Scenario, n: int, rng: np.random.Generator, *, ik_solver=ik_closed_form,
                    max_tries: int = 50, batch: int | None = None):
    """Up to ``n`` uniformly random feasible bases in the bounds (rejection sampling).

    Returns ``(xyz (m, 3), evaluation)`` with m <= n (fewer when feasible bases are rare)."""
    model = collision_model(sc)
    batch = batch or max(4 * n, 1000)
    found_x, found_f = [], []
    count = 0
    for _ in range(max_tries):
        X = sc.lower + rng.random((batch, 3)) * (sc.upper - sc.lower)
        ev = evaluate_bases(X, sc, rng, ik_solver=ik_solver, model=model)
        keep = ev.feasible
        found_x.append(X[keep])
        found_f.append(ev.objectives[keep])
        count += int(keep.sum())
        if count >= n:
            break
    xyz = np.concatenate(found_x)[:n]
    F = np.concatenate(found_f)[:n]
    return xyz, F


def percentiles(f_selected, F_random, *, strict: bool = False) -> np.ndarray:
    """Percentile rank per index: % of random feasible bases that the selection beats or ties
    (index value >= the selection's; all indices are minimized), or only beats (> ) when
    ``strict`` (the two differ where an index has a plateau, e.g. dexterity at sqrt(3))."""
    F_random = np.asarray(F_random, dtype=float)
    if F_random.shape[0] == 0:
        return np.full(np.shape(f_selected), np.nan)
    f = np.asarray(f_selected)[None, :]
    worse = F_random > f if strict else F_random >= f
    return 100.0 * np.mean(worse, axis=0)


def gii_poses(n: int, rng: np.random.Generator, *, half_size=0.025,
              half_angle=0.4363323129985824) -> np.ndarray:
    """``n`` random poses X_OE' in a cube (2 * half_size) and an rpy box (2 * half_angle, rad;
    default 25 deg) about the target End pose (DESIGN.md section 5: 50 mm cube, 50 deg)."""
    dp = rng.uniform(-half_size, half_size, (n, 3))
    drpy = rng.uniform(-half_angle, half_angle, (n, 3))
    return X_OE @ transform(rpy_to_rotation(drpy), dp)


def gii(xyz, branch: int, sc: Scenario, rng: np.random.Generator, n: int = 100) -> dict:
    """General Isotropy Index (paper Eq. 24): sigma_min over sigma_max across the 6x6 body
    Jacobians of ``n`` random poses about Oral, reached on the selected branch.

    Returns dict(gii, reached, poses) (gii over the reached poses; NaN if none is reached).
    """
    X_OEp = gii_poses(n, rng)
    X_BEp = invert(base_pose(xyz)) @ X_OEp
    q, ok = ik_closed_form(X_BEp, limits=sc.limits, X_FT=sc.X_FT)
    ok_b = ok[:, branch]
    if not np.any(ok_b):
        return {"gii": float("nan"), "reached": 0, "poses": n}
    J = kin.jacobian_body(q[ok_b, branch], sc.X_FT)
    s = np.linalg.svd(J, compute_uv=False)
    return {"gii": float(s.min() / s.max()), "reached": int(ok_b.sum()), "poses": n}
