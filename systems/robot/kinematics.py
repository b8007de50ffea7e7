"""AUBO-i10 kinematics: forward kinematics, Jacobians and the closed-form inverse (all 8 branches).

This module is the contract other tools use; keep the names ``fk``, ``jacobian_space``,
``jacobian_body``, ``ik``, ``IkResult``, ``joint_copies``.

Forward kinematics chains the URDF joint origins of DESIGN.md section 8 exactly (each joint turns
about +z of its child frame), so it agrees with Drake's MultibodyPlant built from
``models/aubo_i10/aubo_i10.urdf`` to rounding. The inverse uses the equivalent standard
Denavit-Hartenberg model (UR sign convention):

    d1 = 0.1632, a2 = -0.647, a3 = -0.6005, d4 = 0.2013, d5 = 0.1025, d6 = 0.094,
    alpha = (pi/2, 0, 0, pi/2, -pi/2, 0),
    theta = (q1, q2 - pi/2, -q3, q4 - pi/2, q5, q6 + pi)

(joint 3 turns the other way in the URDF). Joints 2, 3, 4 are parallel, so the inverse has the
classic UR closed form: the shoulder angle from the wrist centre (2 solutions), the wrist angle
theta5 from the flange position (2), theta6 from the orientation, then a planar 2-link problem for
theta2, theta3 (2) and theta4 from the sum theta2 + theta3 + theta4. That gives up to 8 solutions;
branch index = 4 * shoulder + 2 * wrist + elbow with each bit 0 for the '+' root, stable for a
pose as long as it moves continuously away from singularities.

At a wrist singularity (sin theta5 = 0) theta6 and theta4 are not separable: we set theta6 = 0 and
solve the rest, so the returned solution still reproduces the pose; ``singular`` marks it.

Jacobians (rows [angular; linear], Drake's spatial-velocity order):
``jacobian_space(q)`` = J such that [w_BT; v_BT] = J qdot, the angular velocity of the tool frame T
and the velocity of T's origin, both measured in and expressed in base_link B (Drake's
CalcJacobianSpatialVelocity with frame_A = frame_E = base_link, at T's origin). Note: this is the
"geometric" Jacobian, not Lynch & Park's space Jacobian (whose linear part is the velocity of the
point at the base origin). ``jacobian_body(q)`` is the same expressed in T.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from implantplan.systems import validate
from implantplan.systems.errors import InputError
from implantplan.systems.frames import invert, rpy_to_rotation, transform, wrap_angle
from implantplan.systems.jit import numba

PI = np.pi
JOINT_NAMES = (
    "shoulder_joint",
    "upperArm_joint",
    "foreArm_joint",
    "wrist1_joint",
    "wrist2_joint",
    "wrist3_joint",
)
LINK_NAMES = (
    "base_link",
    "shoulder_Link",
    "upperArm_Link",
    "foreArm_Link",
    "wrist1_Link",
    "wrist2_Link",
    "wrist3_Link",
)

# URDF joint origins (parent -> child), DESIGN.md section 8.
JOINT_XYZ = np.array(
    [
        [0.0, 0.0, 0.1632],
        [0.0, 0.2013, 0.0],
        [0.647, 0.0, 0.0],
        [0.6005, 0.0, 0.0],
        [0.0, 0.1025, 0.0],
        [0.0, -0.094, 0.0],
    ]
)
JOINT_RPY = np.array(
    [
        [0.0, 0.0, PI],
        [-PI / 2, -PI / 2, 0.0],
        [PI, 0.0, 0.0],
        [PI, 0.0, PI / 2],
        [-PI / 2, 0.0, 0.0],
        [PI / 2, 0.0, 0.0],
    ]
)
X_JOINT_ORIGINS = transform(rpy_to_rotation(JOINT_RPY), JOINT_XYZ)  # (6, 4, 4)

# Standard DH (UR convention) equivalent to the URDF chain.
DH_D1, DH_A2, DH_A3, DH_D4, DH_D5, DH_D6 = 0.1632, -0.647, -0.6005, 0.2013, 0.1025, 0.094

JOINT_LIMITS_175 = np.deg2rad(np.array([[-175.0] * 6, [175.0] * 6]))  # (2, 6): lower, upper
JOINT_LIMITS_360 = np.deg2rad(np.array([[-360.0] * 6, [360.0] * 6]))
VELOCITY_LIMITS = np.deg2rad(np.array([180.0, 180.0, 147.0, 180.0, 180.0, 180.0]))

# Why a branch is empty (IkResult.reason).
REASON_OK = 0
REASON_SHOULDER = 1  # the wrist centre is inside the cylinder of radius d4 about joint 1
REASON_WRIST = 2  # no theta5: the flange is too far from the shoulder plane
REASON_ELBOW = 3  # the planar 2-link arm cannot reach (too far or too close)
REASON_LIMITS = 4  # a solution exists but violates the joint limits
REASONS = {
    REASON_OK: "ok",
    REASON_SHOULDER: "out of reach: wrist centre within d4 of the shoulder axis",
    REASON_WRIST: "out of reach: no wrist angle places the flange",
    REASON_ELBOW: "out of reach: beyond (or inside) the elbow's reach",
    REASON_LIMITS: "violates the joint limits",
}


def joint_limits(limits: str | np.ndarray = "175") -> np.ndarray:
    """Joint limits (2, 6) in rad from ``"175"``, ``"360"`` or an explicit (2, 6) array."""
    if isinstance(limits, str):
        if limits == "175":
            return JOINT_LIMITS_175
        if limits == "360":
            return JOINT_LIMITS_360
        raise InputError("limits", f"expected '175' or '360', got {limits!r}")
    arr = np.asarray(limits, dtype=float)
    if arr.shape != (2, 6) or not np.all(arr[0] < arr[1]):
        raise InputError("limits", "expected a (2, 6) array of lower < upper bounds in rad")
    return arr


def joint_headroom(q, limits: str | np.ndarray = "175") -> np.ndarray:
    """Distance (rad) of each joint of ``q`` (..., 6) to its nearer limit, min(q - lower,
    upper - q) per joint (..., 6): negative outside the limits, NaN where ``q`` is NaN."""
    lo, hi = joint_limits(limits)
    q = np.asarray(q, dtype=float)
    return np.minimum(q - lo, hi - q)


def _check_q(q) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.ndim == 0 or q.shape[-1] != 6:
        raise InputError("q", f"expected joint vectors of shape (..., 6), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise InputError("q", "joint values must be finite (found NaN or inf)")
    return q


def _check_pose(X, field: str) -> np.ndarray:
    """Poses (..., 4, 4) checked by systems.validate.pose (the one pose validator)."""
    return validate.pose(X, field, batch=True)


def _tool(X_FT) -> np.ndarray | None:
    return None if X_FT is None else _check_pose(X_FT, "X_FT")


def joint_frames(q) -> np.ndarray:
    """Poses X_BJi (..., 6, 4, 4) of each joint's child frame (after its rotation) in base_link."""
    q = _check_q(q)
    c, s = np.cos(q), np.sin(q)
    X = np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4))
    frames = np.empty(q.shape[:-1] + (6, 4, 4))
    for i in range(6):
        X = X @ X_JOINT_ORIGINS[i]
        col0 = X[..., :, 0].copy()
        col1 = X[..., :, 1]
        ci, si = c[..., i, None], s[..., i, None]
        X[..., :, 0] = ci * col0 + si * col1  # right-multiply by Rz(q_i)
        X[..., :, 1] = -si * col0 + ci * col1
        frames[..., i, :, :] = X
    return frames


def fk(q, X_FT=None) -> np.ndarray:
    """Flange pose X_BF (..., 4, 4) in base_link, or the tool pose X_BT = X_BF X_FT if given."""
    X_BF = joint_frames(q)[..., 5, :, :]
    X_FT = _tool(X_FT)
    return X_BF if X_FT is None else X_BF @ X_FT


def jacobian_space(q, X_FT=None) -> np.ndarray:
    """6x6 Jacobian [w; v] of the flange (or tool) frame in base_link (see module docstring)."""
    frames = joint_frames(q)
    X_BT = frames[..., 5, :, :]
    X_FT = _tool(X_FT)
    if X_FT is not None:
        X_BT = X_BT @ X_FT
    z = frames[..., :, :3, 2]  # joint axes in B, (..., 6, 3)
    r = X_BT[..., None, :3, 3] - frames[..., :, :3, 3]
    J = np.empty(z.shape[:-2] + (6, 6))
    J[..., :3, :] = np.swapaxes(z, -1, -2)
    J[..., 3:, :] = np.swapaxes(np.cross(z, r), -1, -2)
    return J


def jacobian_body(q, X_FT=None) -> np.ndarray:
    """The same Jacobian expressed in the flange (or tool) frame."""
    q = _check_q(q)
    J = jacobian_space(q, X_FT)
    R_BT = fk(q, X_FT)[..., :3, :3]
    Rt = np.swapaxes(R_BT, -1, -2)
    return np.concatenate([Rt @ J[..., :3, :], Rt @ J[..., 3:, :]], axis=-2)


@numba.njit(cache=True)
def _planar(r, px, py, pz, c1, s1, c5, s5, t6):  # pragma: no cover - compiled
    """Frame 4 seen from frame 1 given theta1, theta5, theta6: (x14, y14, theta234, cos theta3)."""
    a2, a3, d1, d5, d6 = DH_A2, DH_A3, DH_D1, DH_D5, DH_D6
    c6, s6 = np.cos(t6), np.sin(t6)
    # R46 = R45 R56 and p46 (frame 6 in frame 4)
    m00, m01, m02 = c5 * c6, -c5 * s6, -s5
    m10, m11, m12 = s5 * c6, -s5 * s6, c5
    m20, m21, m22 = -s6, -c6, 0.0
    q0, q1, q2 = -s5 * d6, c5 * d6, d5
    # R04 = R06 R46^T (the columns needed)
    a00 = r[0, 0] * m00 + r[0, 1] * m01 + r[0, 2] * m02
    a10 = r[1, 0] * m00 + r[1, 1] * m01 + r[1, 2] * m02
    a20 = r[2, 0] * m00 + r[2, 1] * m01 + r[2, 2] * m02
    a01 = r[0, 0] * m10 + r[0, 1] * m11 + r[0, 2] * m12
    a11 = r[1, 0] * m10 + r[1, 1] * m11 + r[1, 2] * m12
    a21 = r[2, 0] * m10 + r[2, 1] * m11 + r[2, 2] * m12
    a02 = r[0, 0] * m20 + r[0, 1] * m21 + r[0, 2] * m22
    a12 = r[1, 0] * m20 + r[1, 1] * m21 + r[1, 2] * m22
    a22 = r[2, 0] * m20 + r[2, 1] * m21 + r[2, 2] * m22
    # p04 = p06 - R04 p46, relative to frame 1's origin
    ex = px - (a00 * q0 + a01 * q1 + a02 * q2)
    ey = py - (a10 * q0 + a11 * q1 + a12 * q2)
    ez = pz - (a20 * q0 + a21 * q1 + a22 * q2) - d1
    # into frame 1: R01^T v = (c1 vx + s1 vy, vz, s1 vx - c1 vy)
    x14 = c1 * ex + s1 * ey
    y14 = ez
    t234 = np.arctan2(a20, c1 * a00 + s1 * a10)
    c3v = (x14 * x14 + y14 * y14 - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
    return x14, y14, t234, c3v


@numba.njit(cache=True)
def _best_singular_t6(r, px, py, pz, c1, s1, c5, s5):  # pragma: no cover - compiled
    """theta6 minimizing |cos theta3| at a wrist singularity: 64-point scan + golden section."""
    best, t_best = 1e300, 0.0
    for m in range(64):
        t = 2.0 * PI * m / 64.0
        v = abs(_planar(r, px, py, pz, c1, s1, c5, s5, t)[3])
        if v < best:
            best, t_best = v, t
    lo, hi = t_best - 2.0 * PI / 64.0, t_best + 2.0 * PI / 64.0
    g = 0.6180339887498949
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa = abs(_planar(r, px, py, pz, c1, s1, c5, s5, a)[3])
    fb = abs(_planar(r, px, py, pz, c1, s1, c5, s5, b)[3])
    for _ in range(60):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = abs(_planar(r, px, py, pz, c1, s1, c5, s5, a)[3])
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = abs(_planar(r, px, py, pz, c1, s1, c5, s5, b)[3])
    return 0.5 * (lo + hi)


@numba.njit(cache=True)
def _assemble(q_row, t1, t2, t3, t4, t5, t6):  # pragma: no cover - compiled
    """DH angles -> joint vector (offsets and joint 3's sign, DESIGN.md 8), wrapped to (-pi, pi]."""
    q_row[0] = t1
    q_row[1] = t2 + PI / 2
    q_row[2] = -t3
    q_row[3] = t4 + PI / 2
    q_row[4] = t5
    q_row[5] = t6 - PI
    for j in range(6):
        v = q_row[j] - 2.0 * PI * np.floor((q_row[j] + PI) / (2.0 * PI))
        if v <= -PI:
            v += 2.0 * PI
        q_row[j] = v


@numba.njit(cache=True)
def _within_limits(q_row, lo, hi):  # pragma: no cover - compiled
    """Move each joint to its 2*pi copy within [lo, hi] (in place); False if one has none."""
    for j in range(6):
        v = q_row[j]
        if lo[j] <= v <= hi[j]:
            continue
        if lo[j] <= v + 2.0 * PI <= hi[j]:
            q_row[j] = v + 2.0 * PI
        elif lo[j] <= v - 2.0 * PI <= hi[j]:
            q_row[j] = v - 2.0 * PI
        else:
            return False
    return True


@numba.njit(cache=True)
def _singular_retry(R, p, q, code, singular, lo, hi):  # pragma: no cover - compiled
    """At a wrist singularity theta6 is free (joints 4 and 6 aligned): a branch whose q6 = 0
    solution breaks a joint limit is solved again over 720 values of theta6, keeping the
    solution within the limits with the smallest |q6| (the pose is reproduced for any theta6)."""
    a2, a3 = DH_A2, DH_A3
    row = np.empty(6)
    for n in range(q.shape[0]):
        r = R[n]
        px, py, pz = p[n, 0], p[n, 1], p[n, 2]
        for b in range(8):
            if not (singular[n, b] and code[n, b] == REASON_LIMITS):
                continue
            t1, t5 = q[n, b, 0], q[n, b, 4]
            c1, s1, c5, s5 = np.cos(t1), np.sin(t1), np.cos(t5), np.sin(t5)
            best = 1e300
            for m in range(720):
                t6 = -PI + 2.0 * PI * (m + 1) / 720.0
                x14, y14, t234, c3v = _planar(r, px, py, pz, c1, s1, c5, s5, t6)
                if abs(c3v) > 1.0 + 1e-9:
                    continue
                t3 = np.arccos(max(-1.0, min(1.0, c3v)))
                if b % 2 == 1:
                    t3 = -t3
                t2 = np.arctan2(y14, x14) - np.arctan2(a3 * np.sin(t3), a2 + a3 * np.cos(t3))
                _assemble(row, t1, t2, t3, t234 - t2 - t3, t5, t6)
                if _within_limits(row, lo, hi) and abs(row[5]) < best:
                    best = abs(row[5])
                    q[n, b, :] = row
                    code[n, b] = REASON_OK


@numba.njit(cache=True, fastmath=False)
def _ik_kernel(R, p, q_out, code_out, singular_out):  # pragma: no cover - compiled
    """Closed-form UR inverse on flattened poses: R (n,3,3), p (n,3) of the flange in base."""
    a2, a3, d4, d6 = DH_A2, DH_A3, DH_D4, DH_D6
    eps = 1e-12
    for n in range(R.shape[0]):
        r00, r01 = R[n, 0, 0], R[n, 0, 1]
        r10, r11, r12 = R[n, 1, 0], R[n, 1, 1], R[n, 1, 2]
        r02 = R[n, 0, 2]
        px, py, pz = p[n, 0], p[n, 1], p[n, 2]
        r = R[n]
        # wrist centre p05 = p06 - d6 * z6
        wx, wy = px - d6 * r02, py - d6 * r12
        rw = np.sqrt(wx * wx + wy * wy)
        for b in range(8):
            code_out[n, b] = 0
            singular_out[n, b] = False
        if rw < abs(d4) * (1.0 + 1e-15) - eps or rw < eps:
            for b in range(8):
                code_out[n, b] = 1
                for j in range(6):
                    q_out[n, b, j] = 0.0
            continue
        cphi = min(1.0, d4 / rw)
        phi = np.arccos(cphi)
        psi = np.arctan2(wy, wx)
        for ish in range(2):
            t1 = psi + (phi if ish == 0 else -phi) + PI / 2
            c1, s1 = np.cos(t1), np.sin(t1)
            c5v = (px * s1 - py * c1 - d4) / d6
            if abs(c5v) > 1.0 + 1e-9:
                for b in range(4 * ish, 4 * ish + 4):
                    code_out[n, b] = 2
                    for j in range(6):
                        q_out[n, b, j] = 0.0
                continue
            # theta5 from the orientation, accurate at every angle (acos loses half the digits
            # near 0 and pi): s5 (sin t6, cos t6) = (A, B), cos t5 = z6 . (s1, -c1, 0), which
            # equals c5v for any pose whose theta1 was solved from its wrist centre.
            A = -r01 * s1 + r11 * c1
            B = r00 * s1 - r10 * c1
            s5abs = np.sqrt(A * A + B * B)
            c5 = r02 * s1 - r12 * c1
            for iw in range(2):
                s5 = s5abs if iw == 0 else -s5abs
                t5 = np.arctan2(s5, c5)
                sing = s5abs < 1e-10  # fixed theta6 errs ~2|s5| rad; atan2 above errs ~1e-32/s5^2 m
                if sing:
                    # theta6 is free with theta4 (joints 4 and 6 aligned): prefer q6 = 0; if the
                    # elbow cannot reach with it, take the theta6 that minimizes |cos theta3|
                    # (the most comfortable elbow; a fully stretched pose has one such theta6).
                    t6 = PI
                    x14, y14, t234, c3v = _planar(r, px, py, pz, c1, s1, c5, s5, t6)
                    if abs(c3v) > 1.0 + 1e-9:
                        t6 = _best_singular_t6(r, px, py, pz, c1, s1, c5, s5)
                        x14, y14, t234, c3v = _planar(r, px, py, pz, c1, s1, c5, s5, t6)
                else:
                    t6 = np.arctan2(A / s5, B / s5)
                    x14, y14, t234, c3v = _planar(r, px, py, pz, c1, s1, c5, s5, t6)
                base = 4 * ish + 2 * iw
                if abs(c3v) > 1.0 + 1e-9:
                    for b in range(base, base + 2):
                        code_out[n, b] = 3
                        for j in range(6):
                            q_out[n, b, j] = 0.0
                    continue
                c3v = max(-1.0, min(1.0, c3v))
                t3abs = np.arccos(c3v)
                for ie in range(2):
                    t3 = t3abs if ie == 0 else -t3abs
                    s3 = np.sin(t3)
                    t2 = np.arctan2(y14, x14) - np.arctan2(a3 * s3, a2 + a3 * np.cos(t3))
                    b = base + ie
                    _assemble(q_out[n, b], t1, t2, t3, t234 - t2 - t3, t5, t6)
                    singular_out[n, b] = sing


@dataclass
class IkResult:
    """All 8 closed-form branches of a batch of poses.

    Attributes:
        q: (..., 8, 6) joint solutions in rad, each wrapped into (-pi, pi]; entries of empty
            branches are 0.
        valid: (..., 8) bool, the branch exists and lies within the joint limits.
        reason: (..., 8) int code, see ``REASONS`` (0 = ok).
        singular: (..., 8) bool, wrist singular (theta5 = 0 or pi; theta6 set to 0).
    """

    q: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    singular: np.ndarray

    def reasons(self) -> np.ndarray:
        """Human-readable reason per branch."""
        return np.vectorize(REASONS.__getitem__, otypes=[object])(self.reason)


def ik(X_BT, *, limits: str | np.ndarray = "175", X_FT=None) -> IkResult:
    """Closed-form inverse kinematics, all 8 branches, batched over leading dimensions.

    Args:
        X_BT: (..., 4, 4) target poses of the flange (or of the tool frame when ``X_FT`` is
            given) in base_link.
        limits: ``"175"``, ``"360"`` or a (2, 6) array. Solutions are reported wrapped into
            (-pi, pi]; with wider limits the extra 2*pi copies are available from
            :func:`joint_copies`, never lost.
        X_FT: pose of the tool frame in the flange frame, or None for the flange.

    Returns:
        IkResult with q (..., 8, 6), valid, reason and singular (..., 8).
    """
    X = _check_pose(X_BT, "X_BT")
    lim = joint_limits(limits)
    X_FT = _tool(X_FT)
    if X_FT is not None:
        X = X @ invert(X_FT)
    shape = X.shape[:-2]
    flat = X.reshape(-1, 4, 4)
    R = np.ascontiguousarray(flat[:, :3, :3])
    p = np.ascontiguousarray(flat[:, :3, 3])
    n = flat.shape[0]
    q = np.empty((n, 8, 6))
    code = np.empty((n, 8), dtype=np.int8)
    singular = np.empty((n, 8), dtype=bool)
    _ik_kernel(R, p, q, code, singular)
    _apply_limits(q, code, lim[0], lim[1])
    _singular_retry(R, p, q, code, singular, lim[0], lim[1])
    valid = code == REASON_OK
    return IkResult(
        q=q.reshape(shape + (8, 6)),
        valid=valid.reshape(shape + (8,)),
        reason=code.reshape(shape + (8,)),
        singular=singular.reshape(shape + (8,)),
    )


@numba.njit(cache=True)
def _apply_limits(q, code, lo, hi):  # pragma: no cover - compiled
    """Move each solution (in (-pi, pi]) to its copy within limits nearest 0, or mark it
    REASON_LIMITS when neither it nor a 2*pi copy is within (q, code modified in place)."""
    for n in range(q.shape[0]):
        for b in range(8):
            if code[n, b] == REASON_OK and not _within_limits(q[n, b], lo, hi):
                code[n, b] = REASON_LIMITS


def joint_copies(q, *, limits: str | np.ndarray = "360") -> tuple[np.ndarray, np.ndarray]:
    """All joint vectors equal to ``q`` modulo 2*pi per joint that lie within the limits.

    Args:
        q: (..., 6) joint vectors.
        limits: as in :func:`ik`.

    Returns:
        ``(copies, mask)``: copies (..., 3**6, 6) candidate vectors (each joint shifted by -2pi,
        0, +2pi) and mask (..., 3**6) True where every joint is within the limits. With ±360 deg
        limits each joint has two copies, so a branch yields up to 64 configurations.
    """
    q = _check_q(q)
    lim = joint_limits(limits)
    shifts = np.array(np.meshgrid(*([[-2 * PI, 0.0, 2 * PI]] * 6), indexing="ij")).reshape(6, -1).T
    copies = q[..., None, :] + shifts
    mask = np.all((copies >= lim[0]) & (copies <= lim[1]), axis=-1)
    return copies, mask


def wrapped_distance(qa, qb) -> np.ndarray:
    """Joint-space distance with each joint difference wrapped (systems.frames.wrap_angle)."""
    d = wrap_angle(np.asarray(qa, dtype=float) - np.asarray(qb, dtype=float))
    return np.linalg.norm(d, axis=-1)


def pose_error(X_a, X_b) -> tuple[np.ndarray, np.ndarray]:
    """(position error m, rotation error rad) between pose batches."""
    from implantplan.systems.frames import rotation_angle

    dp = np.linalg.norm(X_a[..., :3, 3] - X_b[..., :3, 3], axis=-1)
    dR = rotation_angle(np.swapaxes(X_a[..., :3, :3], -1, -2) @ X_b[..., :3, :3])
    return dp, dR
