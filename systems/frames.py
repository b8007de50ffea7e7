"""Rigid transforms and rotations, batched over leading dimensions (DESIGN.md section 3, Frames).

Monogram notation: ``X_AB`` is the pose of frame B in frame A as a 4x4 homogeneous matrix,
``R_AB`` its rotation, ``p_AB`` its translation. All functions accept ``(..., 4, 4)`` /
``(..., 3, 3)`` / ``(..., 3)`` arrays.
"""

from __future__ import annotations

import math

import numpy as np

from implantplan.systems.errors import InputError


def transform(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Assemble ``X`` (..., 4, 4) from ``R`` (..., 3, 3) and ``p`` (..., 3)."""
    R = np.asarray(R, dtype=float)
    p = np.asarray(p, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], p.shape[:-1])
    X = np.zeros(shape + (4, 4))
    X[..., :3, :3] = R
    X[..., :3, 3] = p
    X[..., 3, 3] = 1.0
    return X


def invert(X: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (uses R^T, never a general 4x4 inverse)."""
    X = np.asarray(X, dtype=float)
    Rt = np.swapaxes(X[..., :3, :3], -1, -2)
    return transform(Rt, -np.einsum("...ij,...j->...i", Rt, X[..., :3, 3]))


def apply(X: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Transform points: ``p_A = X_AB @ p_B`` for points ``p`` (..., 3)."""
    X = np.asarray(X, dtype=float)
    return np.einsum("...ij,...j->...i", X[..., :3, :3], p) + X[..., :3, 3]


def rot_x(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape(a.shape + (3, 3))


def rot_y(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape(a.shape + (3, 3))


def rot_z(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(a.shape + (3, 3))


def rpy_to_rotation(rpy) -> np.ndarray:
    """URDF convention: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    rpy = np.asarray(rpy, dtype=float)
    return rot_z(rpy[..., 2]) @ rot_y(rpy[..., 1]) @ rot_x(rpy[..., 0])


def rotations(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of rotation vectors w (n, 3) (Rodrigues, vectorized; one
    vector in scalar arithmetic, the same formula: the control loop's case)."""
    if w.shape == (1, 3):
        return _rotation_one(float(w[0, 0]), float(w[0, 1]), float(w[0, 2]))[None]
    th = np.linalg.norm(w, axis=1)
    k = w / np.where(th > 0, th, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def _rotation_one(x: float, y: float, z: float) -> np.ndarray:
    """(3, 3) I + sin(th) K + (1 - cos(th)) K^2 of the rotation vector (x, y, z), K the unit
    axis' cross-product matrix (:func:`rotations` for one vector, no array overhead)."""
    th = math.sqrt(x * x + y * y + z * z)
    if th == 0.0:
        return np.eye(3)
    x, y, z = x / th, y / th, z / th
    s, c = math.sin(th), 1.0 - math.cos(th)
    return np.array([[1.0 - c * (y * y + z * z), c * x * y - s * z, c * x * z + s * y],
                     [c * x * y + s * z, 1.0 - c * (x * x + z * z), c * y * z - s * x],
                     [c * x * z - s * y, c * y * z + s * x, 1.0 - c * (x * x + y * y)]])


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices, robust near 0 and pi."""
    R = np.asarray(R, dtype=float)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    sin = np.linalg.norm(skew, axis=-1) / 2.0
    return np.arctan2(sin, cos)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vector (3,) of a rotation matrix (3, 3) whose angle is below pi - 1e-6 (the
    inverse of :func:`rotations` there): axis x angle, from the skew part sin(angle) axis and
    the angle atan2(sin, cos) of :func:`rotation_angle` (scalar arithmetic: one matrix is asked
    at every control step)."""
    R = np.asarray(R, dtype=float)
    s0, s1, s2 = 0.5 * (R[2, 1] - R[1, 2]), 0.5 * (R[0, 2] - R[2, 0]), 0.5 * (R[1, 0] - R[0, 1])
    sin = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    angle = math.atan2(sin, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0))
    if angle > np.pi - 1e-6:
        raise ValueError(f"rotation_vector: angle {angle} too close to pi")
    k = angle / sin if sin > 0.0 else 1.0
    return np.array([k * s0, k * s1, k * s2])


def wrap_angle(a) -> np.ndarray:
    """Angles (any shape, rad) wrapped into [-pi, pi): the one angle wrap of the project (joint
    differences, rod directions theta_T, yaw differences).

    a - 2 pi floor((a + pi) / 2 pi), and an angle already in [-pi, pi) comes back bit for bit (no
    rounding through a + pi or exp/atan2). The compiled IK kernel (systems.robot.kinematics) uses
    the
    same formula inside numba, then moves -pi to pi (its solutions are in (-pi, pi])."""
    a = np.asarray(a, dtype=float)
    r = a - 2.0 * np.pi * np.floor((a + np.pi) / (2.0 * np.pi))
    r = np.where(r >= np.pi, r - 2.0 * np.pi, np.where(r < -np.pi, r + 2.0 * np.pi, r))
    return np.where((a >= -np.pi) & (a < np.pi), a, r)


def unit(v, *, field: str = "vector") -> np.ndarray:
    """Normalize vectors (..., 3); a zero or non-finite vector is an InputError naming ``field``."""
    v = np.asarray(v, dtype=float)
    if v.shape[-1:] != (3,):
        raise InputError(field, f"expected 3 components, got shape {v.shape}")
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    if not np.all(np.isfinite(v)) or np.any(norm < 1e-12):
        raise InputError(field, "expected a finite, non-zero direction")
    return v / norm


def frame_from_z(origin, z_axis, *, x_hint=None, field: str = "z_axis") -> np.ndarray:
    """A right-handed frame with the given origin and z axis; x is ``x_hint`` made orthogonal to z
    (default: world x, or world y when z is within 1e-6 of parallel to x)."""
    z = unit(z_axis, field=field)
    hint = np.array([1.0, 0.0, 0.0]) if x_hint is None else unit(x_hint, field="x_hint")
    if abs(float(np.dot(hint, z))) > 1.0 - 1e-6:
        if x_hint is not None:
            raise InputError("x_hint", "must not be parallel to the z axis")
        hint = np.array([0.0, 1.0, 0.0])
    x = hint - np.dot(hint, z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return transform(np.stack([x, y, z], axis=-1), np.asarray(origin, dtype=float))
