"""Whole-tool checks: tool_clearance / ToolClearance.one / feed_clearance vs the ground truth."""

import sys
import time

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from harness import MM, MODELS, _near_wall, region

from implantplan.systems.tool_clearance import (
    ToolClearance,
    ToolGeometry,
    feed_clearance,
    tool_clearance,
)


def rot(axis, ang):
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def random_poses(G, rng, n):
    X = np.tile(np.eye(4), (n, 1, 1))
    p = _near_wall(G, rng, n, G.z[max(G.M - 6, 0)], G.ztop, (0.0, 0.95))
    for k in range(n):
        cz = rng.uniform(np.cos(np.radians(80)), 1)
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


def random_poses_feed(G, rng, n):
    X = np.tile(np.eye(4), (n, 1, 1))
    p = _near_wall(G, rng, n, G.z[max(G.M - 5, 0)], G.ztop, (0.0, 0.6))
    for k in range(n):
        cz = rng.uniform(np.cos(np.radians(35)), 1)
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


def run(name, n, seed=0, feed_n=None):
    rng = np.random.default_rng(seed)
    f = MODELS[name]()
    G = region(f)
    X = random_poses(G, rng, n)
    fs = 0
    worst = -np.inf
    safe = 0
    free = 0
    free_unsafe = 0
    mism = 0
    ex = None
    t = time.time()
    for k in range(n):
        tool = ToolGeometry(
            rod_radius=rng.uniform(0.5, 6) * MM,
            implant_length=rng.uniform(5, 31) * MM,
            rod_length=rng.uniform(20, 200) * MM,
            implant_radius=rng.uniform(0, 2) * MM,
            head_radius=rng.uniform(0.5, 7) * MM,
        )
        v = tool_clearance(f, X[k], tool)[0]
        one = ToolClearance(f, tool).one(X[k])
        if abs(one - v) > 1e-12:
            mism += 1
        tr = truth_tool(G, X[k], tool)
        safe += v > 0
        free += tr > G.eps
        free_unsafe += (tr > G.eps) and v <= 0
        if v > 0 and tr < -G.eps:
            fs += 1
            ex = (X[k].tolist(), tool, v, tr)
        if v > 0:
            worst = max(worst, v - tr)
    print(
        f"[tool] {name}: poses {n}, called safe {safe}, false-safe {fs}, "
        f"worst (sound - true) {worst / MM:.4f} mm, "
        f"free called unsafe {free_unsafe}/{free}, one()!=batch {mism} ({time.time() - t:.1f}s)",
        flush=True,
    )
    if ex:
        print("   FS example", ex)
    # feed: truth sampled every 0.25 mm along the feed up to the computed depth (+ the default rule)
    feed_n = feed_n if feed_n is not None else max(n // 10, 5)
    ffs = 0
    fsafe = 0
    t = time.time()
    fworst = -np.inf
    X = random_poses_feed(G, rng, feed_n)
    for k in range(feed_n):
        tool = ToolGeometry(
            rod_radius=rng.uniform(0.5, 3) * MM,
            implant_length=rng.uniform(3, 12) * MM,
            rod_length=0.1,
            implant_radius=rng.uniform(0, 1) * MM,
        )
        lat, ang = rng.uniform(0, 0.5) * MM, np.radians(rng.uniform(0, 2))
        v = feed_clearance(f, X[k], tool, lateral=lat, angle=ang)[0]
        if v <= 0:
            continue
        fsafe += 1
        x_dir = X[k][:3, 0]
        need = G.ztop + tool.head + tool.implant_length - X[k][2, 3]
        depth = min(max(need / x_dir[2], 0) if x_dir[2] > 1e-6 else 0.2, 0.2) + 0.03  # a bit beyond
        worst_k = np.inf
        for s in np.arange(0, depth, 0.0005):
            for _ in range(2):
                Y = X[k].copy()
                Y[:3, 3] += s * x_dir
                # admissible perturbation: rotate by <= ang about the implant start, shift <= lat
                piv = Y[:3, 3] + Y[:3, 0] * tool.rod_radius
                ax = rng.normal(size=3)
                R = rot(ax, rng.uniform(0, ang))
                Y[:3, :3] = R @ Y[:3, :3]
                Y[:3, 3] = piv + R @ (Y[:3, 3] - piv)
                off = rng.normal(size=3)
                off -= off.dot(Y[:3, 0]) * Y[:3, 0]
                Y[:3, 3] += off / (np.linalg.norm(off) + 1e-300) * rng.uniform(0, lat)
                worst_k = min(worst_k, truth_tool(G, Y, tool))
        fworst = max(fworst, v - worst_k)
        if worst_k < -G.eps:
            ffs += 1
            print("   FEED FS", X[k].tolist(), tool, lat, ang, v, worst_k)
    print(
        f"[feed] {name}: feeds {feed_n}, called safe {fsafe}, false-safe {ffs}, "
        f"worst (feed - true min) {fworst / MM:.4f} mm ({time.time() - t:.1f}s)",
        flush=True,
    )


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    for name in (
        sys.argv[2].split(",")
        if len(sys.argv) > 2
        else ["default", "cylinder", "slit", "nonconvex"]
    ):
        run(name, n, feed_n=int(sys.argv[3]) if len(sys.argv) > 3 else None)
