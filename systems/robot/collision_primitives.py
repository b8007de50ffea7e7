"""Fast collision primitives, vectorized over many configurations: capsules (a segment swept by
a sphere) fixed in link frames and posed by the joint angles (:func:`arm_capsules`), and the
distances segment-segment, capsule-capsule and segment/capsule-box.

The arm's collision model is not here: it is systems.robot.arm_collision, generated from the plant's
own geometry. These functions serve the cart-vs-patient check of systems.robot.moprp, the compiled
kernels of systems.robot.arm_collision (:func:`seg_seg`, :func:`point_box`) and the
reconstruction of
the old hand-written capsule model that analyses/bench_moprp.py compares against.

Frames: link index 0 is ``base_link``; index i (1..6) is the child frame of joint i, i.e. the
frames returned by :func:`systems.robot.kinematics.joint_frames`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from implantplan.systems.errors import InputError
from implantplan.systems.jit import kernel_array, numba
from implantplan.systems.robot.kinematics import joint_frames


@dataclass(frozen=True)
class Capsule:
    """A capsule fixed in a link frame: segment p0-p1 (m, in the link frame) and radius (m)."""

    name: str
    link: int
    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    radius: float


def capsule_arrays(capsules) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(links (K,), local segments (K, 2, 3), radii (K,)) of a capsule list."""
    links = np.array([c.link for c in capsules], dtype=np.int64)
    seg = np.array([[c.p0, c.p1] for c in capsules], dtype=float)
    radii = np.array([c.radius for c in capsules], dtype=float)
    return links, seg, radii


def arm_capsules(q, capsules) -> tuple[np.ndarray, np.ndarray]:
    """Capsule segments fixed in the arm's link frames, posed in base_link.

    Args:
        q: (..., 6) joint vectors in rad.
        capsules: sequence of :class:`Capsule`.

    Returns:
        ``(segments, radii)``: segments (..., K, 2, 3) endpoints in base_link (m), radii (K,).
    """
    links, seg, radii = capsule_arrays(capsules)
    frames = joint_frames(q)  # (..., 6, 4, 4)
    lead = frames.shape[:-3]
    F = np.ascontiguousarray(frames.reshape(-1, 6, 4, 4))
    out = np.empty((F.shape[0], links.size, 2, 3))
    _place(F, links, seg, out)
    return out.reshape(lead + (links.size, 2, 3)), radii


@numba.njit(cache=True)
def _place(F, links, seg, out):  # pragma: no cover - compiled
    """out[n, k, a] = X_B,link(k) @ seg[k, a] (link 0 = base_link = identity)."""
    for n in range(F.shape[0]):
        for k in range(links.shape[0]):
            li = links[k]
            for a in range(2):
                x, y, z = seg[k, a, 0], seg[k, a, 1], seg[k, a, 2]
                if li == 0:
                    out[n, k, a, 0] = x
                    out[n, k, a, 1] = y
                    out[n, k, a, 2] = z
                else:
                    f = li - 1
                    for c in range(3):
                        out[n, k, a, c] = (F[n, f, c, 0] * x + F[n, f, c, 1] * y
                                           + F[n, f, c, 2] * z + F[n, f, c, 3])


@numba.njit(cache=True)
def seg_seg(ax, ay, az, bx, by, bz, cx, cy, cz, dx, dy, dz):  # pragma: no cover - compiled
    """Distance between segments AB and CD (Ericson, Real-Time Collision Detection 5.1.9)."""
    d1x, d1y, d1z = bx - ax, by - ay, bz - az
    d2x, d2y, d2z = dx - cx, dy - cy, dz - cz
    rx, ry, rz = ax - cx, ay - cy, az - cz
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    eps = 1e-18
    if a <= eps and e <= eps:
        s = 0.0
        t = 0.0
    elif a <= eps:
        s = 0.0
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = d1x * rx + d1y * ry + d1z * rz
        if e <= eps:
            t = 0.0
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = d1x * d2x + d1y * d2y + d1z * d2z
            denom = a * e - b * b
            if denom > eps * a * e:
                s = min(max((b * f - c * e) / denom, 0.0), 1.0)
            else:
                s = 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((b - c) / a, 0.0), 1.0)
    px = ax + d1x * s - (cx + d2x * t)
    py = ay + d1y * s - (cy + d2y * t)
    pz = az + d1z * s - (cz + d2z * t)
    return np.sqrt(px * px + py * py + pz * pz)


@numba.njit(cache=True)
def _seg_seg_batch(A, B, out):  # pragma: no cover - compiled
    for n in range(A.shape[0]):
        out[n] = seg_seg(
            A[n, 0, 0], A[n, 0, 1], A[n, 0, 2], A[n, 1, 0], A[n, 1, 1], A[n, 1, 2],
            B[n, 0, 0], B[n, 0, 1], B[n, 0, 2], B[n, 1, 0], B[n, 1, 1], B[n, 1, 2],
        )


def segment_distance(seg_a, seg_b) -> np.ndarray:
    """Distance between segments, broadcast over leading dimensions.

    Args:
        seg_a, seg_b: (..., 2, 3) segment endpoints (m); a point is a segment with equal ends.

    Returns:
        (...) the smallest distance between the two segments.
    """
    seg_a = np.asarray(seg_a, dtype=float)
    seg_b = np.asarray(seg_b, dtype=float)
    shape = np.broadcast_shapes(seg_a.shape, seg_b.shape)
    if shape[-2:] != (2, 3):
        raise InputError("segments", f"expected (..., 2, 3) endpoint arrays, got {shape}")
    A = np.ascontiguousarray(np.broadcast_to(seg_a, shape).reshape(-1, 2, 3))
    B = np.ascontiguousarray(np.broadcast_to(seg_b, shape).reshape(-1, 2, 3))
    out = np.empty(A.shape[0])
    _seg_seg_batch(A, B, out)
    return out.reshape(shape[:-2])


def capsule_clearance(seg_a, r_a, seg_b, r_b) -> np.ndarray:
    """Signed clearance between capsules: segment distance minus both radii (< 0: overlap)."""
    return segment_distance(seg_a, seg_b) - np.asarray(r_a) - np.asarray(r_b)


@numba.njit(cache=True)
def point_box(px, py, pz, hx, hy, hz):  # pragma: no cover - compiled
    """Distance from a point (box frame) to an axis-aligned box of half sizes h (0 inside)."""
    qx = max(abs(px) - hx, 0.0)
    qy = max(abs(py) - hy, 0.0)
    qz = max(abs(pz) - hz, 0.0)
    return np.sqrt(qx * qx + qy * qy + qz * qz)


@numba.njit(cache=True)
def _segment_box(ax, ay, az, dx, dy, dz, hx, hy, hz, iterations):  # pragma: no cover - compiled
    """Distance from the segment a + t d, t in [0, 1] (box frame) to an axis-aligned box of half
    sizes h: the point-box distance is convex along the segment, so a golden-section search on t
    finds its minimum (``iterations`` steps shrink the bracket by 0.618 each), then the ends."""
    g = 0.6180339887498949
    lo, hi = 0.0, 1.0
    t1 = hi - g * (hi - lo)
    t2 = lo + g * (hi - lo)
    f1 = point_box(ax + t1 * dx, ay + t1 * dy, az + t1 * dz, hx, hy, hz)
    f2 = point_box(ax + t2 * dx, ay + t2 * dy, az + t2 * dz, hx, hy, hz)
    for _ in range(iterations):
        if f1 <= f2:
            hi = t2
            t2 = t1
            f2 = f1
            t1 = hi - g * (hi - lo)
            f1 = point_box(ax + t1 * dx, ay + t1 * dy, az + t1 * dz, hx, hy, hz)
        else:
            lo = t1
            t1 = t2
            f1 = f2
            t2 = lo + g * (hi - lo)
            f2 = point_box(ax + t2 * dx, ay + t2 * dy, az + t2 * dz, hx, hy, hz)
    best = min(f1, f2)
    best = min(best, point_box(ax, ay, az, hx, hy, hz))
    return min(best, point_box(ax + dx, ay + dy, az + dz, hx, hy, hz))


@numba.njit(cache=True)
def _seg_box_batch(S, H, out):  # pragma: no cover - compiled
    """Segment-to-box distance: the point-box distance is convex along the segment, so a
    golden-section search on t in [0, 1] finds its minimum (to ~1e-9 of the segment length)."""
    for n in range(S.shape[0]):
        ax, ay, az = S[n, 0, 0], S[n, 0, 1], S[n, 0, 2]
        dx, dy, dz = S[n, 1, 0] - ax, S[n, 1, 1] - ay, S[n, 1, 2] - az
        out[n] = _segment_box(ax, ay, az, dx, dy, dz, H[n, 0], H[n, 1], H[n, 2], 45)


def segment_box_distance(seg, X_AB, half_size) -> np.ndarray:
    """Distance from segments to boxes (0 when they touch or overlap), broadcast.

    Args:
        seg: (..., 2, 3) segment endpoints in frame A (m).
        X_AB: (..., 4, 4) pose of the box centre frame B in A (box axes = B's axes).
        half_size: (..., 3) half extents of the box along B's axes (m).

    Returns:
        (...) distances (m).
    """
    seg = np.asarray(seg, dtype=float)
    X_AB = np.asarray(X_AB, dtype=float)
    half = np.asarray(half_size, dtype=float)
    local = np.matmul(seg - X_AB[..., None, :3, 3], X_AB[..., :3, :3])  # rows: R^T (x - p)
    shape = np.broadcast_shapes(local.shape, half.shape[:-1] + (2, 3))
    S = np.ascontiguousarray(np.broadcast_to(local, shape).reshape(-1, 2, 3))
    H = np.ascontiguousarray(np.broadcast_to(half, shape[:-2] + (3,)).reshape(-1, 3))
    out = np.empty(S.shape[0])
    _seg_box_batch(S, H, out)
    return out.reshape(shape[:-2])


@numba.njit(cache=True)
def _min_caps(SA, rA, SB, rB, I, J, out):  # pragma: no cover - compiled
    for n in range(SA.shape[0]):
        best = np.inf
        for m in range(I.shape[0]):
            i, j = I[m], J[m]
            d = seg_seg(
                SA[n, i, 0, 0], SA[n, i, 0, 1], SA[n, i, 0, 2],
                SA[n, i, 1, 0], SA[n, i, 1, 1], SA[n, i, 1, 2],
                SB[n, j, 0, 0], SB[n, j, 0, 1], SB[n, j, 0, 2],
                SB[n, j, 1, 0], SB[n, j, 1, 1], SB[n, j, 1, 2],
            ) - rA[i] - rB[j]
            if d < best:
                best = d
        out[n] = best


def min_capsule_clearance(seg_a, r_a, seg_b, r_b, pairs=None) -> np.ndarray:
    """Smallest clearance over capsule pairs, per configuration, without broadcast copies.

    Args:
        seg_a: (N, A, 2, 3) capsule segments; r_a: (A,) radii.
        seg_b: (N, B, 2, 3) capsule segments; r_b: (B,) radii.
        pairs: (M, 2) index pairs (i into A, j into B); None = all A x B pairs.

    Returns:
        (N,) min over pairs of (segment distance - r_i - r_j) in m (+inf when M = 0).
    """
    SA = np.ascontiguousarray(seg_a, dtype=float)
    SB = np.ascontiguousarray(seg_b, dtype=float)
    rA = np.ascontiguousarray(r_a, dtype=float)
    rB = np.ascontiguousarray(r_b, dtype=float)
    if SA.ndim != 4 or SB.ndim != 4 or SA.shape[0] != SB.shape[0]:
        raise InputError("segments", f"expected (N, A, 2, 3) and (N, B, 2, 3), got "
                         f"{SA.shape} and {SB.shape}")
    if pairs is None:
        I, J = np.meshgrid(np.arange(SA.shape[1]), np.arange(SB.shape[1]), indexing="ij")
        I, J = I.ravel(), J.ravel()
    else:
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        I, J = pairs[:, 0], pairs[:, 1]
    out = np.empty(SA.shape[0])
    _min_caps(SA, rA, SB, rB, np.ascontiguousarray(I, dtype=np.int64),
              np.ascontiguousarray(J, dtype=np.int64), out)
    return out


@numba.njit(cache=True)
def _min_boxes(S, r, R, P, H, out):  # pragma: no cover - compiled
    for n in range(S.shape[0]):
        best = np.inf
        for b in range(R.shape[0]):
            hx, hy, hz = H[b, 0], H[b, 1], H[b, 2]
            for k in range(S.shape[1]):
                # endpoints in the box frame: R^T (x - p)
                ux = S[n, k, 0, 0] - P[n, b, 0]
                uy = S[n, k, 0, 1] - P[n, b, 1]
                uz = S[n, k, 0, 2] - P[n, b, 2]
                vx = S[n, k, 1, 0] - S[n, k, 0, 0]
                vy = S[n, k, 1, 1] - S[n, k, 0, 1]
                vz = S[n, k, 1, 2] - S[n, k, 0, 2]
                ax = R[b, 0, 0] * ux + R[b, 1, 0] * uy + R[b, 2, 0] * uz
                ay = R[b, 0, 1] * ux + R[b, 1, 1] * uy + R[b, 2, 1] * uz
                az = R[b, 0, 2] * ux + R[b, 1, 2] * uy + R[b, 2, 2] * uz
                dx = R[b, 0, 0] * vx + R[b, 1, 0] * vy + R[b, 2, 0] * vz
                dy = R[b, 0, 1] * vx + R[b, 1, 1] * vy + R[b, 2, 1] * vz
                dz = R[b, 0, 2] * vx + R[b, 1, 2] * vy + R[b, 2, 2] * vz
                d = _segment_box(ax, ay, az, dx, dy, dz, hx, hy, hz, 32) - r[k]
                if d < best:
                    best = d
        out[n] = best


def min_box_clearance(seg, r, R_box, p_box, half_size) -> np.ndarray:
    """Smallest clearance between capsules and boxes, per configuration.

    Args:
        seg: (N, A, 2, 3) capsule segments in frame F; r: (A,) radii.
        R_box: (Bx, 3, 3) box orientations in F (shared by all N).
        p_box: (N, Bx, 3) box centres in F (per configuration: the base moves).
        half_size: (Bx, 3) half extents.

    Returns:
        (N,) min over capsules and boxes of (segment-box distance - r) in m (+inf if none).
    """
    S = kernel_array(seg)
    P = kernel_array(p_box, (S.shape[0],) + np.shape(p_box)[-2:])
    out = np.empty(S.shape[0])
    _min_boxes(S, kernel_array(r), kernel_array(R_box), P, kernel_array(half_size), out)
    return out
