"""The tracked head frame's step, no faster than the arm can follow (DESIGN.md section 7).

The arm holds the tool in the *tracked* head frame H (diagrams.teleop.TrackedHeadFrame: the
tracker's predicted head displacement): differential IK is sent H X_des, the supervisor's
desired pose carried with the frame. The supervisor keeps every step of X_des within the command
limits, but nothing else bounds the frame's own step between two control steps. At a camera
sample the prediction corrects itself by a jump (a new sample's noise, extrapolated over the
sample's age when the head moves; measured in docs/measurements.md, the head-turn sweep), and
where that jump asks a joint for more than its velocity limit within one control step,
differential IK reaches only part of H X_des: it scales its whole step down (the direction
kept) and catches up at the next control step. The tool then moves other than its command in
the frame the supervisor, the fixture and the guard hold it in (two steps above the command
limits: an *arm jump* of the head-turn sweep, analyses.studies.head_turn).

:func:`frame_step` moves the frame from its last value towards the tracker's pose along the
screw between them (rotation about the desired TCP, translation of that point, one share s of
both) by the largest share s in [0, 1] for which differential IK's step to H_s X_des needs joint
rates within ``headroom`` x the joints' limits: its own linearization (the joint rates J^-1 V of
the pose difference V per period, J the TCP's Jacobian in World at the arm's joints), so
differential IK makes the step whole and the arm moves in the frame as the supervisor commanded.
Where the arm can follow the tracker's pose in one step (s = 1) the frame is that pose;
otherwise the frame reaches it over the next steps, as fast as the joints allow (without the
bound the arm would lag its command instead, by about as much). If the arm cannot make even the
command's own step with the frame held (s = 0 infeasible: near a singularity, or with the arm
still catching up), the frame holds and differential IK scales its step as it would anyway.
"""

from __future__ import annotations

import numpy as np

from implantplan.systems.frames import invert, rotation_vector, rotations

HEADROOM = 0.95  # share of the joints' velocity limits a frame step may ask for (the rest: what
# the joint rates of the step differential IK takes at its next update may differ by from these)


def pose_difference(X_a: np.ndarray, X_b: np.ndarray) -> np.ndarray:
    """(6,) [rotation vector of R_b R_a^T; p_b - p_a] in the poses' common frame: differential
    IK's error of X_a against the desired X_b (Drake's ComputePoseDiffInCommonFrame)."""
    out = np.empty(6)
    out[:3] = rotation_vector(X_b[:3, :3] @ X_a[:3, :3].T)
    out[3:] = X_b[:3, 3] - X_a[:3, 3]
    return out


def screw_share(H_prev: np.ndarray, H_goal: np.ndarray, p: np.ndarray, s: float) -> np.ndarray:
    """(4, 4) the share ``s`` of the step from ``H_prev`` to ``H_goal``: the step's rotation
    about the point ``p`` (World) times s, and p's translation times s (s = 1: ``H_goal``)."""
    D = H_goal @ invert(H_prev)
    p = np.asarray(p, dtype=float)
    step = np.eye(4)
    step[:3, :3] = rotations((s * rotation_vector(D[:3, :3]))[None])[0]
    step[:3, 3] = p + s * (D[:3, :3] @ p + D[:3, 3] - p) - step[:3, :3] @ p
    return step @ H_prev


def _largest_share(a: np.ndarray, b: np.ndarray, limit: np.ndarray) -> float:
    """The largest s in [0, 1] with |a + s b| <= limit (every joint), 0 if none."""
    if np.any(np.abs(a) > limit):
        return 0.0
    s = 1.0
    for ai, bi, li in zip(a, b, limit, strict=True):
        if bi > 0.0:
            s = min(s, (li - ai) / bi)
        elif bi < 0.0:
            s = min(s, (-li - ai) / bi)
    return max(0.0, s)


def frame_step(H_prev: np.ndarray, H_goal: np.ndarray, X_des: np.ndarray, X_now: np.ndarray,
               J_W: np.ndarray, qdot_max: np.ndarray, dt: float, *,
               headroom: float = HEADROOM) -> tuple[np.ndarray, float]:
    """(H (4, 4), share s) the frame for this control step (module notes): ``H_prev`` the last
    step's frame, ``H_goal`` the tracker's, ``X_des`` the supervisor's desired End pose in the
    head-fixed World, ``X_now`` the arm's End pose (World) at its joints, ``J_W`` (6, 6) the
    End's Jacobian [w; v] in World there, ``qdot_max`` (6,) the joints' velocity limits, ``dt``
    the control period."""
    lim = headroom * np.asarray(qdot_max, dtype=float)

    def rates(H):
        return np.linalg.solve(J_W, pose_difference(X_now, H @ X_des) / dt)

    r1 = rates(H_goal)
    if np.all(np.abs(r1) <= lim):
        return H_goal, 1.0
    p = (H_prev @ X_des)[:3, 3]
    r0 = rates(H_prev)
    s = _largest_share(r0, r1 - r0, lim)
    # the joint rates are nearly affine in s (the rotation vectors of small steps add); where
    # they are not quite, shorten the share by the rate's excess over the limit
    for _ in range(4):
        if s <= 0.0:
            break
        H = screw_share(H_prev, H_goal, p, s)
        excess = float(np.max(np.abs(rates(H)) / lim))
        if excess <= 1.0:
            return H, s
        s /= excess
    return H_prev, 0.0
