"""Whole-tool checks: tool_clearance / ToolClearance.one / feed_clearance vs the ground truth."""

import sys

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from harness import _near_wall


def rot(axis, ang):
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def _poses_near_wall(G, rng, n, *, top_slices: int, wall_fraction, max_tilt_deg: float):
    """n Tool poses: origins near the wall in the top slabs, x (the rod) within max_tilt of +Z
    (out of the mouth), a random roll about it."""
    X = np.tile(np.eye(4), (n, 1, 1))
    p = _near_wall(G, rng, n, G.z[max(G.M - top_slices, 0)], G.ztop, wall_fraction)
    for k in range(n):
        cz = rng.uniform(np.cos(np.radians(max_tilt_deg)), 1)
        ph = rng.uniform(0, 2 * np.pi)
        s = np.sqrt(1 - cz * cz)
        x = np.array([s * np.cos(ph), s * np.sin(ph), cz])
        a = np.array([1.0, 0, 0]) if abs(x[0]) < 0.9 else np.array([0, 1.0, 0])
        y = a - a.dot(x) * x
        y /= np.linalg.norm(y)
        y = rot(x, rng.uniform(0, 2 * np.pi)) @ y
        X[k, :3, :3] = np.column_stack([x, y, np.cross(x, y)])
        X[k, :3, 3] = p[k]
    return X


def random_poses(G, rng, n):
    return _poses_near_wall(G, rng, n, top_slices=6, wall_fraction=(0.0, 0.95), max_tilt_deg=80)


def random_poses_feed(G, rng, n):
    return _poses_near_wall(G, rng, n, top_slices=5, wall_fraction=(0.0, 0.6), max_tilt_deg=35)


def capsules(X, tool):
    a, b, r = tool.capsules_T()
    A = np.einsum("ij,cj->ci", X[:3, :3], a) + X[:3, 3]
    B = np.einsum("ij,cj->ci", X[:3, :3], b) + X[:3, 3]
    return A, B, r


def truth_tool(G, X, tool):
    """rigorous upper bound of the true clearance (min over the 3 capsules); -r if axis leaves F."""
    A, B, r = capsules(X, tool)
    best = np.inf
    for c in range(3):
        q = G.query(A[c], B[c], axis_samples=200)
        v = -max(r[c], 1e-12) if q["axis_out"] else q["upper"] - r[c]
        if q["crosses"] and r[c] > G.eps:
            v = min(v, G.eps - r[c])
        best = min(best, v)
    return best
