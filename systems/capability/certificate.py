"""The certificate of a capability-map cell: one IK sample and first-order bounds on the IK.

A cell of a certified map is every pose the map's query sends to it: the mapped frame's origin
anywhere in the voxel's closed cube (half edge ``h``), its z axis anywhere in the region of the
sphere the query's lookup table gives to direction d (at most ``alpha[d]`` rad from d,
:func:`direction_radii`), and, for a sampled roll (tool off the flange axis), its roll within half
a roll step (``pi / R``) of the roll sample r. Roll is measured in the frame of d carried to the
pose's z by the shortest rotation (:func:`systems.capability.maps.roll_bins`), so a pose of the
cell differs from the cell's centre sample X0 = (voxel centre, F(d) Rz(2 pi r / R)) by a
translation of at most ``h`` per axis and a rotation of at most
``theta = alpha[d] + pi / R`` (the triangle inequality on SO(3)); with a free roll (flange,
``R = 1``) every roll belongs to the cell and moves q6 alone, exactly.

**Certified yes** (:func:`certify`): some closed-form branch b is valid and not wrist-singular at
X0 and, with J the geometric Jacobian of the mapped frame at q0 = q_b(X0) ([w; v], base_link) and
G = J^-1, the first-order displacement of every joint over the cell,

    dq_j = kappa * (h * sum_i |G[j, 3 + i]| + theta * |G[j, 0:3]|),

(the exact maximum of the linear model over the cube x the rotation ball, times the safety factor
``kappa`` for what the linear model leaves out) fits: each joint keeps ``slack + dq_j`` to its
limits, the wrist (q5) stays ``dq_5`` away from its singular values 0 and pi, the elbow keeps
its reach (cos q3, which the reach's end bounds by -1 and 1 and which is smooth there, moves by
at most ``|sin q3| dq_3`` and stays inside: q3's own room ``dq_3 <= |q3|`` is first-order in a
square root and let cells near the outer reach through, 22 in 400,000 poses at the actuator's
certified cells' corners), every ``dq_j`` is below ``DQ_MAX`` (the
linear model is trusted only for small motions), and the wrist centre (whose distance from joint
1's axis must exceed d4, the shoulder's condition) keeps that distance with the rigorous bound
``hd + |c| theta`` to spare (``hd`` the voxel's half diagonal, ``c`` the wrist centre in the
mapped frame). Every boundary of a branch's existence is a singular surface of J (elbow,
shoulder, wrist) or a joint limit, so a cell meeting none of them within the bounds is reached by
that branch throughout. For the flange "every roll" needs two such branches whose q6 stay apart by
more than the forbidden q6 arc (the 10 deg gap of +-175 deg limits) + twice the slack + both
``dq_6``: their forbidden roll windows are then disjoint (with +-360 deg one branch is enough).

The bound is first-order, not interval arithmetic: it is tested against exact IK on random and
boundary poses and at the corners of certified cells (:func:`systems.capability.maps.
corner_poses`; 0 false yes), and a certificate with a term dropped is tested to be caught. A
cell that fails is **undecided**, never "no": queries resolve it with closed-form IK at the pose.
A cell is **certified no** only where no pose can be reached at all (outside the reach sphere,
:func:`systems.capability.maps.candidate_voxels`).
"""

from __future__ import annotations

import numpy as np

from implantplan.systems.jit import numba
from implantplan.systems.robot.kinematics import DH_D4, DH_D6, X_JOINT_ORIGINS

KAPPA = 2.0  # safety factor on the first-order joint displacement over a cell
TRIES = 3  # Jacobians per cell at most (branches in order of their room; 8 for the flange's pairs)
DQ_MAX = 3.0  # rad: the largest first-order joint displacement over a cell that is trusted


def direction_radii(directions: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(K,) the largest angle (rad) between direction d and any unit vector the lookup ``table``
    (:func:`systems.capability.maps.direction_table`) maps to d: over the table's cells, the
    angle from the cell's centre to its direction plus the cell's half diagonal
    (<= 0.71 pi / n_theta, cells uniform in polar angle and azimuth)."""
    n_z, n_phi = table.shape
    z = np.cos((np.arange(n_z) + 0.5) * np.pi / n_z)
    phi = -np.pi + (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    s = np.sqrt(1.0 - z * z)
    cells = np.stack([s[:, None] * np.cos(phi)[None], s[:, None] * np.sin(phi)[None],
                      np.repeat(z[:, None], n_phi, 1)], axis=-1).reshape(-1, 3)  # fmt: skip
    owner = table.reshape(-1).astype(np.int64)
    ang = np.arccos(np.clip(np.sum(cells * directions[owner], axis=1), -1.0, 1.0))
    out = np.zeros(len(directions))
    np.maximum.at(out, owner, ang + 0.71 * np.pi / n_z)
    return out


def wrist_centre_offset(X_FT: np.ndarray) -> np.ndarray:
    """c (3,): the wrist centre (flange origin - d6 * flange z, the point whose distance from
    joint 1's axis the shoulder needs > d4) in the mapped frame: p_w = p_T + R_T c."""
    R_FT, p_FT = X_FT[:3, :3], X_FT[:3, 3]
    return -R_FT.T @ p_FT - DH_D6 * R_FT.T @ np.array([0.0, 0.0, 1.0])


@numba.njit(cache=True)
def jacobian_inverse(q, X_FT, G):  # pragma: no cover - compiled
    """G (6, 6) = J(q)^-1 of the mapped frame (J: [w; v] of its origin in base_link); returns
    False when J is numerically singular."""
    T = np.eye(4)
    U = np.empty((4, 4))
    A = np.empty((6, 12))
    o = np.empty((6, 3))
    for i in range(6):
        X = X_JOINT_ORIGINS[i]
        for r in range(3):
            for k in range(4):
                U[r, k] = T[r, 0] * X[0, k] + T[r, 1] * X[1, k] + T[r, 2] * X[2, k]
            U[r, 3] += T[r, 3]
        c, s = np.cos(q[i]), np.sin(q[i])
        for r in range(3):
            T[r, 0] = c * U[r, 0] + s * U[r, 1]
            T[r, 1] = -s * U[r, 0] + c * U[r, 1]
            T[r, 2] = U[r, 2]
            T[r, 3] = U[r, 3]
            A[r, i] = U[r, 2]  # joint i turns about its child frame's z
            o[i, r] = U[r, 3]
    p = np.empty(3)
    for r in range(3):
        p[r] = T[r, 0] * X_FT[0, 3] + T[r, 1] * X_FT[1, 3] + T[r, 2] * X_FT[2, 3] + T[r, 3]
    for i in range(6):
        dx, dy, dz = p[0] - o[i, 0], p[1] - o[i, 1], p[2] - o[i, 2]
        A[3, i] = A[1, i] * dz - A[2, i] * dy
        A[4, i] = A[2, i] * dx - A[0, i] * dz
        A[5, i] = A[0, i] * dy - A[1, i] * dx
    for r in range(6):
        for k in range(6):
            A[r, 6 + k] = 1.0 if r == k else 0.0
    for col in range(6):  # Gauss-Jordan with partial pivoting on [J | I]
        piv = col
        for r in range(col + 1, 6):
            if abs(A[r, col]) > abs(A[piv, col]):
                piv = r
        if abs(A[piv, col]) < 1e-9:
            return False
        if piv != col:
            for k in range(col, 12):
                A[col, k], A[piv, k] = A[piv, k], A[col, k]
        inv = 1.0 / A[col, col]
        for k in range(col, 12):
            A[col, k] *= inv
        for r in range(6):
            if r != col and A[r, col] != 0.0:
                f = A[r, col]
                for k in range(col, 12):
                    A[r, k] -= f * A[col, k]
    for r in range(6):
        for k in range(6):
            G[r, k] = A[r, 6 + k]
    return True


@numba.njit(cache=True)
def _singular_room(x):  # pragma: no cover - compiled
    """Distance of an angle in (-pi, pi] from 0 and from pi."""
    a = abs(x)
    return min(a, np.pi - a)


@numba.njit(cache=True)
def _elbow_keeps(q3, dq3, reach):  # pragma: no cover - compiled
    """The elbow's reach holds over the cell: cos q3 (affine in the squared distance from
    joint 2's axis to joint 4's, smooth where the reach ends) moves by at most |sin q3| dq3 to
    first order and stays inside [-1, 1]. q3 itself is not linear there (a square root: the
    room 1 - cos q3 ~ q3^2 / 2), so ``|q3| >= dq3`` would spend the whole safety factor on that
    curvature (``reach`` False: that rule, tests only)."""
    if not reach:
        return _singular_room(q3) >= dq3
    return abs(np.sin(q3)) * dq3 <= 1.0 - abs(np.cos(q3))


@numba.njit(cache=True)
def joint_bounds(G, z0, h, tilt, roll, kappa, use_pos, use_rot, dq):  # pragma: no cover
    """dq (6,): kappa x the exact maximum over the cell of the linear model G [w; v]: v in the
    cube of half edge h (sum of |G[j, 3:]| h), w a tilt of the approach axis z0 up to ``tilt``
    (w perpendicular to z0: tilt |P g_j|) plus a roll about z0 up to ``roll`` (|g_j . z0| roll),
    g_j = G[j, 0:3]."""
    for j in range(6):
        sp = abs(G[j, 3]) + abs(G[j, 4]) + abs(G[j, 5]) if use_pos else 0.0
        sr = 0.0
        if use_rot:
            gz = G[j, 0] * z0[0] + G[j, 1] * z0[1] + G[j, 2] * z0[2]
            px, py, pz = G[j, 0] - gz * z0[0], G[j, 1] - gz * z0[1], G[j, 2] - gz * z0[2]
            sr = tilt * np.sqrt(px * px + py * py + pz * pz) + roll * abs(gz)
        dq[j] = kappa * (h * sp + sr)


@numba.njit(cache=True)
def _certify_kernel(q, ok, shoulder_ok, R_s, alpha, roll, h, X_FT, lo, hi, slack, kappa, dq_max,
                    gap, free_roll, tries, use_pos, use_rot, elbow_reach, out):  # pragma: no cover
    """out[n, d, r] for samples q (n, K, R, 8, 6), ok (n, K, R, 8), see :func:`certify`."""
    n_vox, n_dir, n_roll = ok.shape[0], ok.shape[1], ok.shape[2]
    n_joint = 5 if free_roll else 6
    pairs = free_roll and gap > 0.0
    G = np.empty((6, 6))
    dq = np.empty((8, 6))
    score = np.empty(8)
    good = np.empty(8, dtype=np.bool_)
    z0 = np.empty(3)
    for v in range(n_vox):
        for d in range(n_dir):
            for r in range(n_roll):
                out[v, d, r] = False
                if not shoulder_ok[v, d, r]:
                    continue
                for k in range(3):
                    z0[k] = R_s[d, r, k, 2]
                # branches in order of their smallest room (joint limits, elbow and wrist
                # singular values): at most ``tries`` Jacobians per cell
                for b in range(8):
                    good[b] = False
                    score[b] = -1.0
                    if ok[v, d, r, b]:
                        qb = q[v, d, r, b]
                        m = min(_singular_room(qb[2]), _singular_room(qb[4]))
                        for j in range(n_joint):
                            m = min(m, qb[j] - lo[j], hi[j] - qb[j])
                        score[b] = m
                n_good = 0
                for _t in range(tries):
                    b = np.argmax(score)
                    if score[b] <= slack or (n_good > 0 and not pairs):
                        break
                    score[b] = -1.0
                    qb = q[v, d, r, b]
                    if not jacobian_inverse(qb, X_FT, G):
                        continue
                    joint_bounds(G, z0, h, alpha[d], roll, kappa, use_pos, use_rot, dq[b])
                    fine = (_elbow_keeps(qb[2], dq[b, 2], elbow_reach)
                            and _singular_room(qb[4]) >= dq[b, 4])
                    for j in range(n_joint):
                        if (dq[b, j] > dq_max or qb[j] - dq[b, j] < lo[j] + slack
                                or qb[j] + dq[b, j] > hi[j] - slack):
                            fine = False
                    if fine:
                        good[b] = True
                        n_good += 1
                if not pairs:
                    out[v, d, r] = n_good > 0
                    continue
                found = False
                for a in range(8):
                    for b in range(a + 1, 8):
                        if found or not (good[a] and good[b]):
                            continue
                        diff = (q[v, d, r, a, 5] - q[v, d, r, b, 5]) % (2.0 * np.pi)
                        room = gap + 2.0 * slack + dq[a, 5] + dq[b, 5]
                        found = room <= diff <= 2.0 * np.pi - room
                out[v, d, r] = found


def certify(
    q: np.ndarray,
    ok: np.ndarray,
    R_s: np.ndarray,
    p_s: np.ndarray,
    *,
    alpha: np.ndarray,
    voxel: float,
    X_FT: np.ndarray,
    limits: np.ndarray,
    slack: float,
    rolls: int,
    kappa: float = KAPPA,
    dq_max: float = DQ_MAX,
    tries: int = TRIES,
    position_term: bool = True,
    rotation_term: bool = True,
    shoulder_term: bool = True,
    elbow_reach: bool = True,
) -> np.ndarray:
    """(n, K, R) bool: the cells certified reachable (module docstring).

    Args:
        q, ok: the 8 closed-form branches at each cell's centre sample, (n, K, R, 8, 6) and
            (n, K, R, 8) (valid within the limits, q6 relaxed for a free roll, not singular).
        R_s, p_s: the centre samples' rotations (K, R, 3, 3) and positions (n, 3).
        alpha: (K,) direction radii (:func:`direction_radii`).
        voxel: voxel edge (m).
        X_FT: the mapped frame in the flange frame.
        limits: (2, 6) joint limits (rad).
        slack: joint-limit margin (rad).
        rolls: R (1: the roll is free, flange-coaxial frame).
        kappa, dq_max: the safety factor and the largest trusted displacement.
        position_term, rotation_term, shoulder_term: False drops that bound (tests only: a
            certificate without it must be caught saying yes where exact IK says no).
        elbow_reach: False bounds the elbow by q3's own first-order room to 0 and pi (the rule
            before the reach's cos q3; tests only: it must be caught near the outer reach).
    """
    free = rolls == 1
    theta = np.asarray(alpha, float) + (0.0 if free else np.pi / rolls)
    hd = 0.5 * np.sqrt(3.0) * voxel
    c = wrist_centre_offset(X_FT)
    w = p_s[:, None, None, :] + (R_s @ c)[None]  # (n, K, R, 3) wrist centres of the samples
    rho = np.hypot(w[..., 0], w[..., 1])
    bound = (hd + np.linalg.norm(c) * theta[None, :, None]) if shoulder_term else 0.0
    shoulder_ok = rho - abs(DH_D4) > bound
    lim = np.asarray(limits, float)
    gap = 2.0 * np.pi - (lim[1, 5] - lim[0, 5]) if free else 0.0
    out = np.empty(ok.shape[:3], dtype=bool)
    _certify_kernel(
        np.ascontiguousarray(q), np.ascontiguousarray(ok), np.ascontiguousarray(shoulder_ok),
        np.ascontiguousarray(R_s), np.ascontiguousarray(alpha, dtype=float),
        0.0 if free else np.pi / rolls, 0.5 * voxel, np.ascontiguousarray(X_FT, dtype=float),
        np.ascontiguousarray(lim[0]), np.ascontiguousarray(lim[1]), float(slack), float(kappa),
        float(dq_max), float(gap), free, int(tries), position_term, rotation_term,
        elbow_reach, out,
    )  # fmt: skip
    return out
