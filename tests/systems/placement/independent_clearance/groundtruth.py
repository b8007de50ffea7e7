"""Independent ground truth for the FPSM free region (verifier's code, no implantplan geometry).

Only the FPSM's *data* (slice_z, rho) is taken from implantplan.  The curve is re-implemented
from DESIGN.md section 4 (Eq. 1-5): control radii rho_k at theta_k = 2 pi k / N, cubic Hermite
per segment with knot slopes v_k = N (rho_{k+1} - rho_{k-1}) / (4 pi); radius linear in z
between slices.

Free region (the tool_clearance docstring, checked against Fpsm.d_safe by the tests):
    F = {z_0 <= z <= z_top, hypot(x, y) < rho(theta, z)}  U  {z > z_top}
Boundary dF = slab walls + throat disc at z_0 + the annulus of the plane z_top outside the top
curve (triangulated out to R_OUT).

A capsule (segment a-b, radius r) is free iff its axis lies in F and dist(axis, dF) >= r.

* ``upper``: a *rigorous upper bound* of dist(axis, dF): an exact point on the axis and an exact
  point on dF (evaluated with the verifier's spline) -- FCL's witness points, mapped back onto
  the exact surface.  upper < r  ==> the capsule certainly touches / crosses dF.
* ``axis_out``: an axis sample that is certainly outside F (beyond ``tol``), or the FCL segment
  crosses the triangulated boundary farther than eps from its ends.
* ``d_fcl`` +- ``eps``: FCL distance to the triangulated surface, eps = proven-ish bound of the
  triangulation error (chord sagitta + bilinear twist), used for the conservatism statistics.
"""

from __future__ import annotations

import fcl
import numpy as np

TWO_PI = 2 * np.pi
R_OUT = 1.0  # outer radius of the triangulated top annulus (m)


# -- the curve, from the definition -----------------------------------------------------------


def spline(rho_rows: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """rho(theta) for each row of control radii (M, N), theta broadcast to (M, ...) or (...)."""
    rho_rows = np.atleast_2d(np.asarray(rho_rows, float))
    M, N = rho_rows.shape
    h = TWO_PI / N
    th = np.mod(np.asarray(theta, float), TWO_PI)
    k = np.floor(th / h).astype(int)
    k = np.clip(k, 0, N - 1)
    t = th / h - k
    kk = [np.mod(k + o, N) for o in (-1, 0, 1, 2)]
    # broadcast rows
    rows = np.arange(M).reshape((M,) + (1,) * th.ndim) if th.ndim and th.shape[0] != M else None
    if rows is None:
        if th.ndim == 0:
            rows = np.arange(M)
        else:
            rows = np.arange(M).reshape((M,) + (1,) * (th.ndim - 1))
    g = [rho_rows[rows, q] for q in kk]
    p0, p1 = g[1], g[2]
    v0 = N * (g[2] - g[0]) / (4 * np.pi)  # Eq. 2 slope d rho / d theta at knot k
    v1 = N * (g[3] - g[1]) / (4 * np.pi)
    m0, m1 = v0 * h, v1 * h
    t2, t3 = t * t, t * t * t
    return ((2 * t3 - 3 * t2 + 1) * p0 + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * p1
            + (t3 - t2) * m1)


class FreeRegion:
    def __init__(self, slice_z, rho):
        self.z = np.asarray(slice_z, float).copy()
        self.rho = np.atleast_2d(np.asarray(rho, float)).copy()
        self.M, self.N = self.rho.shape
        self.z0, self.ztop = float(self.z[0]), float(self.z[-1])

    def radius(self, theta, z):
        """rho(theta, z) for z inside [z0, ztop] (arrays of equal shape), NaN outside."""
        theta = np.asarray(theta, float)
        z = np.asarray(z, float)
        theta, z = np.broadcast_arrays(theta, z)
        out = np.full(theta.shape, np.nan)
        ok = (z >= self.z0) & (z <= self.ztop)
        if self.M == 1:
            out[ok] = spline(self.rho[0:1], theta[ok][None])[0]
            return out
        j = np.clip(np.searchsorted(self.z, z[ok], side="right") - 1, 0, self.M - 2)
        w = (z[ok] - self.z[j]) / (self.z[j + 1] - self.z[j])
        th = theta[ok]
        hi = self._rows(j + 1, th)
        lo = self._rows(j, th)
        out[ok] = (1 - w) * lo + w * hi
        return out

    def _rows(self, j, th):
        # evaluate slice j[i] at th[i] (vectorized, per-point slice)
        N = self.N
        h = TWO_PI / N
        t_ = np.mod(th, TWO_PI)
        k = np.clip(np.floor(t_ / h).astype(int), 0, N - 1)
        t = t_ / h - k
        g = [self.rho[j, np.mod(k + o, N)] for o in (-1, 0, 1, 2)]
        m0 = (g[2] - g[0]) / 2
        m1 = (g[3] - g[1]) / 2
        t2, t3 = t * t, t * t * t
        return ((2 * t3 - 3 * t2 + 1) * g[1] + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * g[2]
                + (t3 - t2) * m1)

    def signed_radial(self, P):
        """rho(theta, z) - hypot(x, y) inside the slice range; -inf-ish (z - z0) below;
        +inf above z_top.  > 0: in F."""
        P = np.asarray(P, float)
        x, y, z = P[..., 0], P[..., 1], P[..., 2]
        th = np.arctan2(y + 0.0, x + 0.0)
        rr = np.hypot(x, y)
        zc = np.clip(z, self.z0, self.ztop)
        d = self.radius(th, zc) - rr
        d = np.where(z < self.z0, np.minimum(d, z - self.z0), d)
        return np.where(z > self.ztop, np.inf, d)

    def surface_point(self, theta, z):
        """Exact wall point at (theta, z), z in [z0, ztop]."""
        r = self.radius(theta, z)
        return np.stack([r * np.cos(theta), r * np.sin(theta), z], -1)

    # -- triangulated boundary ------------------------------------------------------------------

    def build_mesh(self, angles=2048, zsteps=8):
        P = angles
        th = np.arange(P) * (TWO_PI / P)
        V, F, _kinds = [], [], []
        nv = 0
        eps = 0.0
        # lateral walls
        for j in range(self.M - 1):
            zz = np.linspace(self.z[j], self.z[j + 1], zsteps + 1)
            if j > 0:
                zz = zz  # rows shared not needed; duplicates fine
            R = self.radius(np.broadcast_to(th, (zsteps + 1, P)),
                            np.broadcast_to(zz[:, None], (zsteps + 1, P)))
            X = np.stack([R * np.cos(th), R * np.sin(th), np.broadcast_to(zz[:, None], R.shape)],
                         -1)
            idx = nv + np.arange((zsteps + 1) * P).reshape(zsteps + 1, P)
            a = idx[:-1, :]
            b = np.roll(idx[:-1, :], -1, axis=1)
            c = idx[1:, :]
            d = np.roll(idx[1:, :], -1, axis=1)
            F.append(np.stack([a, b, d], -1).reshape(-1, 3))
            F.append(np.stack([a, d, c], -1).reshape(-1, 3))
            V.append(X.reshape(-1, 3))
            nv += X.shape[0] * X.shape[1]
            # error: sagitta at mid angle (x1.5) + |twist| / 4
            thm = th + 0.5 * TWO_PI / P
            Rm = self.radius(np.broadcast_to(thm, R.shape), np.broadcast_to(zz[:, None], R.shape))
            Xm = np.stack([Rm * np.cos(thm), Rm * np.sin(thm)], -1)
            chord = 0.5 * (X[..., :2] + np.roll(X[..., :2], -1, axis=1))
            sag = np.linalg.norm(Xm - chord, axis=-1).max()
            tw = X[:-1] - np.roll(X[:-1], -1, axis=1) - X[1:] + np.roll(X[1:], -1, axis=1)
            twist = np.linalg.norm(tw, axis=-1).max()
            eps = max(eps, 1.5 * sag + 0.25 * twist)
        # throat disc (fan) and top annulus
        for zc, top in ((self.z0, False), (self.ztop, True)):
            R = self.radius(th, np.full(P, zc))
            C = np.stack([R * np.cos(th), R * np.sin(th), np.full(P, zc)], -1)
            ic = nv + np.arange(P)
            V.append(C)
            nv += P
            if not top:
                V.append(np.array([[0.0, 0.0, zc]]))
                o = nv
                nv += 1
                F.append(np.stack([np.full(P, o), ic, np.roll(ic, -1)], -1))
            else:
                Ocirc = np.stack([R_OUT * np.cos(th), R_OUT * np.sin(th), np.full(P, zc)], -1)
                io = nv + np.arange(P)
                V.append(Ocirc)
                nv += P
                F.append(np.stack([ic, io, np.roll(io, -1)], -1))
                F.append(np.stack([ic, np.roll(io, -1), np.roll(ic, -1)], -1))
            thm = th + 0.5 * TWO_PI / P
            Rm = self.radius(thm, np.full(P, zc))
            Xm = np.stack([Rm * np.cos(thm), Rm * np.sin(thm)], -1)
            chord = 0.5 * (C[:, :2] + np.roll(C[:, :2], -1, axis=0))
            eps = max(eps, 1.5 * np.linalg.norm(Xm - chord, axis=-1).max())
        V = np.ascontiguousarray(np.concatenate(V), float)
        F = np.ascontiguousarray(np.concatenate(F), np.int32)
        self.V, self.F, self.eps = V, F, float(eps) + 1e-7  # + FCL/GJK tolerance
        m = fcl.BVHModel()
        m.beginModel(len(V), len(F))
        m.addSubModel(V, F)
        m.endModel()
        self.obj = fcl.CollisionObject(m, fcl.Transform())
        return self

    # -- queries --------------------------------------------------------------------------------

    def _seg_obj(self, a, b):
        d = b - a
        L = float(np.linalg.norm(d))
        if L < 1e-10:
            return fcl.CollisionObject(fcl.Sphere(1e-10), fcl.Transform(np.eye(3), a))
        u = d / L
        e = np.array([1.0, 0, 0]) if abs(u[0]) < 0.9 else np.array([0, 1.0, 0])
        x = e - e.dot(u) * u
        x /= np.linalg.norm(x)
        R = np.column_stack([x, np.cross(u, x), u])
        return fcl.CollisionObject(fcl.Capsule(1e-10, L), fcl.Transform(R, 0.5 * (a + b)))

    def _exact_on_surface(self, q):
        """Map a point q of the triangulated boundary to an exact boundary point nearby."""
        x, y, z = q
        th = np.arctan2(y, x)
        if abs(z - self.ztop) < 1e-9:
            rr = np.hypot(x, y)
            rt = self.radius(np.array([th]), np.array([self.ztop]))[0]
            if rr >= rt:  # annulus: q itself is on the exact (planar) annulus if outside curve
                return np.array([x, y, self.ztop])
            return self.surface_point(np.array([th]), np.array([self.ztop]))[0]
        if abs(z - self.z0) < 1e-9:
            rr = np.hypot(x, y)
            rt = self.radius(np.array([th]), np.array([self.z0]))[0]
            if rr <= rt:
                return np.array([x, y, self.z0])
            return self.surface_point(np.array([th]), np.array([self.z0]))[0]
        zc = min(max(z, self.z0), self.ztop)
        return self.surface_point(np.array([th]), np.array([zc]))[0]

    def query(self, a, b, axis_samples=400, tol=1e-7):
        """dict(d_fcl, upper, axis_out, crosses) for the segment a-b (metres)."""
        a = np.asarray(a, float)
        b = np.asarray(b, float)
        obj = self._seg_obj(a, b)
        req = fcl.DistanceRequest(enable_nearest_points=True)
        res = fcl.DistanceResult()
        d = fcl.distance(obj, self.obj, req, res)
        cres = fcl.CollisionResult()
        crosses = fcl.collide(obj, self.obj, fcl.CollisionRequest(), cres) > 0
        # exact axis samples: outside test
        s = np.linspace(0, 1, axis_samples)
        P = a + s[:, None] * (b - a)
        sr = self.signed_radial(P)
        axis_out = bool(np.any(sr < -tol))
        upper = np.inf
        if d >= 0 and not crosses:
            ab = b - a
            L2 = ab.dot(ab)

            def segdist(p):
                tt = 0.0 if L2 == 0 else np.clip((p - a).dot(ab) / L2, 0, 1)
                return float(np.linalg.norm(a + tt * ab - p))

            # python-fcl's witness order / frame varies by shape: the mesh witness is the one
            # whose distance to the segment matches d
            cands = [np.asarray(p, float) for p in res.nearest_points]
            pb = min(cands, key=lambda p: abs(segdist(p) - d))
            e = self._exact_on_surface(pb)
            upper = segdist(e)
        else:
            d = 0.0
            # a crossing point within the segment: certified collision for r > eps; the exact
            # sample test above decides r = 0
            upper = self.eps
        # also exact samples near the boundary: min pairwise for the KD-free upper bound
        return {"d_fcl": float(d), "upper": upper, "axis_out": axis_out, "crosses": crosses,
                "min_radial": float(np.min(sr))}


def verdict(q, r, eps):
    """('collide' | 'free' | 'ambiguous', true-clearance estimate) for a query result."""
    est = (q["d_fcl"] - r) if not q["axis_out"] else -max(r, 1e-12)
    if q["axis_out"] or q["upper"] < r - 1e-12 or (q["crosses"] and r > eps):
        return "collide", min(est, q["upper"] - r)
    if (not q["crosses"]) and q["d_fcl"] - eps >= r:
        return "free", est
    return "ambiguous", est
