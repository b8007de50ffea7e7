"""A sound, tight lower bound of the instrument's clearance against the opened scan itself.

The exact reference is FCL against the scan (:class:`systems.placement.exact_clearance.
ExactCavity`: per solid, -r when its start is in tissue or its axis touches the mesh, else the
distance of the axis minus r for a capsule or sphere and the solid cylinder's own distance for a
cylinder). This module bounds that value from below with the distance grid of the same mesh
(:mod:`systems.placement.distance_grid`, a proven lower bound of the distance anywhere), by
branch and bound over the instrument's solids (:class:`systems.instrument.Instrument`, in the
Tool frame, posed by X_CTool):

- a capsule (or sphere) of radius r: pieces are sub-segments of its axis; a piece of half-length
  h about its midpoint q is at least D(q) - h from the mesh (1-Lipschitz), so the capsule piece
  at least D(q) - h - r;
- a cylinder (axis a-b, radius R, length L): pieces are annular sectors u in [u0, u1],
  rho in [rho0, rho1], phi in [phi0, phi1] of its cylinder coordinates; a piece lies in the ball
  about q = (u_m, (rho0 + rho1) / 2 at phi_m) whose radius is the largest distance from q to the
  four corners of the sector in its (rho, phi) plane (the farthest point of an annular sector of
  opening <= 2 pi from a point on its bisector is a corner: along each arc the distance grows
  with the angle from the bisector, along each radial edge it is convex), combined with the
  half-height (sqrt(c^2 + (h/2)^2)); the piece is at least D(q) minus that radius from the mesh.

A piece whose bound reaches the target (the claimed clearance, or the best upper estimate so far
when the value is asked) is done; otherwise it is split in two along its longest extent until its
ball is below the resolution (default 0.1 mm, plus 5 % of its bound). The result is the smallest
bound over the leaves (they cover the solid). Where that value is <= 0 the solid may touch, and
the reference may then be as low as -r: the bound reports -r (the reference's floor), so the
value is a lower bound of the reference everywhere, not only where free.

**The start** of each solid (its point a, as the reference tests it): the reference calls it in
tissue when the horizontal segment from the Center axis (0, 0, z_a) to a crosses the mesh. The
bound certifies that this segment keeps a positive distance from the mesh (the same branch and
bound, radius 0); otherwise the solid's bound is -r.

**Upper estimates** (for the "unsafe" verdict): at each piece's centre q (inside the solid, at
depth e from its surface) the solid is at most D_up(q) - e from the mesh (an exact node's value
plus the distance to it); where the solid is free that is an upper bound of the reference, and
where it is not the reference is <= 0. So for a claimed clearance c > 0, an upper estimate below
c proves that the reference is below c.

Verdicts for a claimed clearance c: ``SAFE`` (the bound >= c, FCL would agree), ``UNSAFE`` (an
upper estimate < c), ``UNDECIDED`` (resolved by FCL in :meth:`ScanClearance.verdict` when the
class holds an :class:`ExactCavity`).
"""

from __future__ import annotations

import dataclasses
import functools
import heapq
import time
from typing import TYPE_CHECKING

import numpy as np

from implantplan.systems.errors import InputError
from implantplan.systems.instrument import Instrument
from implantplan.systems.jit import kernel_array, numba
from implantplan.systems.placement.distance_grid import (
    DistanceGrid,
    distance_grid,
    lower_at,
    upper_at,
)
from implantplan.systems.safety import SafetySpec

SAFE, UNDECIDED, UNSAFE = 1, 0, -1
RESOLUTION = 0.1e-3  # m: a piece whose ball radius is below this is not split further
VALUE_CAP = 0.005  # m: clearances above this are not resolved further (reported >= about it)
RELATIVE = 0.05  # a piece whose bound is b is not split below res + RELATIVE * b (far pieces
# are resolved coarser: a clearance of 3 mm is not near the margin)
TOLERANCE = 0.05e-3  # m: a piece within this of the best upper estimate is not split further
PRUNE_SLACK = 1e-6  # m: FCL's own error; a pose is ruled out of a minimum only beyond it
STACK = 4096  # pieces held per solid; past it the solid is undecided (sound)
START_CLEARANCE = 1e-7  # m: the start segment must be at least this far from the mesh
if TYPE_CHECKING:
    from implantplan.systems.placement.exact_clearance import ExactCavity

KIND = {"capsule": 0, "sphere": 0, "cylinder": 1}


@numba.njit(cache=True)
def _frame(n):
    """Two unit vectors completing the unit vector n to an orthonormal frame."""
    if abs(n[0]) < 0.9:
        ax, ay, az = 1.0, 0.0, 0.0
    else:
        ax, ay, az = 0.0, 1.0, 0.0
    # e1 = n x a normalised, e2 = n x e1
    e1 = np.array([n[1] * az - n[2] * ay, n[2] * ax - n[0] * az, n[0] * ay - n[1] * ax])
    e1 /= np.sqrt(e1[0] ** 2 + e1[1] ** 2 + e1[2] ** 2)
    e2 = np.array([n[1] * e1[2] - n[2] * e1[1], n[2] * e1[0] - n[0] * e1[2],
                   n[0] * e1[1] - n[1] * e1[0]])
    return e1, e2


@numba.njit(cache=True)
def _segment_bound(G, lo, hi, ox, oy, oz, g, band, a, b, radius, target, res, stack):
    """(lower bound, upper estimate) of the distance of the capsule (axis a-b, radius) to the
    mesh: pieces split while their bound is below min(target, best upper) and above the
    resolution. ``stack`` (STACK, 2) is scratch."""
    d = b - a
    L = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    stack[0, 0] = 0.0
    stack[0, 1] = 1.0
    top = 1
    lower = np.inf
    upper = np.inf
    while top > 0:
        top -= 1
        t0 = stack[top, 0]
        t1 = stack[top, 1]
        tm = 0.5 * (t0 + t1)
        x = a[0] + tm * d[0]
        y = a[1] + tm * d[1]
        z = a[2] + tm * d[2]
        h = 0.5 * (t1 - t0) * L
        lb = lower_at(G, ox, oy, oz, g, band, lo, hi, x, y, z) - h - radius
        ub = upper_at(G, ox, oy, oz, g, band, lo, hi, x, y, z) - radius
        if ub < upper:
            upper = ub
            if upper <= 0.0:  # proven to touch: the solid's value is the reference's floor
                return 0.0, upper
        goal = target if target < upper - TOLERANCE else upper - TOLERANCE
        if lb >= goal or h <= res + RELATIVE * max(lb, 0.0) or top + 2 > stack.shape[0]:
            if lb < lower:
                lower = lb
            continue
        stack[top, 0] = t0
        stack[top, 1] = tm
        stack[top + 1, 0] = tm
        stack[top + 1, 1] = t1
        top += 2
    return lower, upper


@numba.njit(cache=True)
def _cylinder_bound(G, lo, hi, ox, oy, oz, g, band, a, b, R, target, res, stack):
    """(lower bound, upper estimate) of the distance of the solid cylinder (axis a-b, radius R)
    to the mesh by annular-sector pieces (module notes). ``stack`` (STACK, 6) is scratch."""
    d = b - a
    L = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    n = d / L
    e1, e2 = _frame(n)
    top = 0
    for q in range(4):
        stack[top, 0] = 0.0
        stack[top, 1] = L
        stack[top, 2] = 0.0
        stack[top, 3] = R
        stack[top, 4] = q * 0.5 * np.pi
        stack[top, 5] = (q + 1) * 0.5 * np.pi
        top += 1
    lower = np.inf
    upper = np.inf
    while top > 0:
        top -= 1
        u0, u1, r0, r1, p0, p1 = (stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3],
                                  stack[top, 4], stack[top, 5])
        um = 0.5 * (u0 + u1)
        rm = 0.5 * (r0 + r1)
        pm = 0.5 * (p0 + p1)
        # farthest corner of the annular sector from (rm, pm) in its plane
        c = 0.0
        for rr in (r0, r1):
            for pp in (p0, p1):
                dd = rm * rm + rr * rr - 2.0 * rm * rr * np.cos(pp - pm)
                if dd > c:
                    c = dd
        hh = 0.5 * (u1 - u0)
        rad = np.sqrt(c + hh * hh) * (1.0 + 1e-12) + 1e-15
        cp = np.cos(pm) * rm
        sp = np.sin(pm) * rm
        x = a[0] + um * n[0] + cp * e1[0] + sp * e2[0]
        y = a[1] + um * n[1] + cp * e1[1] + sp * e2[1]
        z = a[2] + um * n[2] + cp * e1[2] + sp * e2[2]
        lb = lower_at(G, ox, oy, oz, g, band, lo, hi, x, y, z) - rad
        depth = min(R - rm, um, L - um)
        ub = upper_at(G, ox, oy, oz, g, band, lo, hi, x, y, z) - depth
        if ub < upper:
            upper = ub
            if upper <= 0.0:  # proven to touch: the solid's value is the reference's floor
                return 0.0, upper
        goal = target if target < upper - TOLERANCE else upper - TOLERANCE
        if lb >= goal or rad <= res + RELATIVE * max(lb, 0.0) or top + 2 > stack.shape[0]:
            if lb < lower:
                lower = lb
            continue
        ext_u = u1 - u0
        ext_r = r1 - r0
        ext_p = r1 * (p1 - p0)
        for s in range(2):
            stack[top + s, 0] = u0
            stack[top + s, 1] = u1
            stack[top + s, 2] = r0
            stack[top + s, 3] = r1
            stack[top + s, 4] = p0
            stack[top + s, 5] = p1
        if ext_u >= ext_r and ext_u >= ext_p:
            stack[top, 1] = um
            stack[top + 1, 0] = um
        elif ext_r >= ext_p:
            stack[top, 3] = rm
            stack[top + 1, 2] = rm
        else:
            stack[top, 5] = pm
            stack[top + 1, 4] = pm
        top += 2
    return lower, upper


@numba.njit(cache=True)
def pose_bound(G, lo, hi, ox, oy, oz, g, band, X, kind, A, B, r, target, res, s2, s6, decide):
    """(lower bound, upper estimate) of the reference clearance (m) of the instrument (solids
    ``kind`` (S,), starts A (S, 3), ends B (S, 3) in T, radii r (S,)) at pose X (4, 4) of T in
    Center, resolved against ``target`` (module notes). With ``decide`` (a verdict for the
    claimed clearance ``target`` > 0) it stops at the first upper estimate below the target and
    returns the reference's floor -max(r) as the lower bound."""
    lower = np.inf
    upper = np.inf
    for s in range(kind.shape[0]):
        a = np.empty(3)
        b = np.empty(3)
        for i in range(3):
            a[i] = X[i, 0] * A[s, 0] + X[i, 1] * A[s, 1] + X[i, 2] * A[s, 2] + X[i, 3]
            b[i] = X[i, 0] * B[s, 0] + X[i, 1] * B[s, 1] + X[i, 2] * B[s, 2] + X[i, 3]
        # the start's horizontal segment from the Center axis must stay off the mesh
        axis = np.array([0.0, 0.0, a[2]])
        st, _ = _segment_bound(G, lo, hi, ox, oy, oz, g, band, axis, a, 0.0, START_CLEARANCE,
                               res, s2)
        goal = target if target < upper else upper  # the min over solids is at most upper
        if kind[s] == 1:
            lb, ub = _cylinder_bound(G, lo, hi, ox, oy, oz, g, band, a, b, r[s], goal, res, s6)
        else:
            lb, ub = _segment_bound(G, lo, hi, ox, oy, oz, g, band, a, b, r[s], goal, res, s2)
        if not (st >= START_CLEARANCE and lb > 0.0):
            lb = -r[s]
        if lb < lower:
            lower = lb
        if ub < upper:
            upper = ub
        if decide and target > 0.0 and upper < target:
            return -r.max(), upper
    return lower, upper


@numba.njit(cache=True, parallel=True)
def _poses_kernel(G, lo, hi, ox, oy, oz, g, band, X, kind, A, B, r, target, res, decide, lower,
                  upper):
    for k in numba.prange(X.shape[0]):
        s2 = np.empty((STACK, 2))
        s6 = np.empty((STACK, 6))
        lower[k], upper[k] = pose_bound(G, lo, hi, ox, oy, oz, g, band, X[k], kind, A, B, r,
                                        target[k], res, s2, s6, decide)


def _grid_args(grid: DistanceGrid) -> tuple:
    v, ox, oy, oz, g, band, lo, hi = grid.args()
    return (v, np.ascontiguousarray(lo), np.ascontiguousarray(hi), ox, oy, oz, g, band)


class ScanClearance:
    """The scan bound of one instrument against one cavity (module notes).

    Args:
        cavity: an :class:`systems.placement.exact_clearance.ExactCavity` (its mesh, Center
            frame, cut at the mouth opening; FCL resolves undecided verdicts) or a mesh
            (``trimesh.Trimesh``, then no FCL).
        instrument: the solids (default the paper's tool).
        resolution: smallest piece (m).
        grid: a prebuilt :class:`DistanceGrid` of the same mesh (default: built and kept).

    ``check(X)`` -> (n,) lower bounds (m) for (n, 4, 4) or (4, 4) poses; ``verdict(X, c)`` ->
    (n,) SAFE / UNSAFE / UNDECIDED; ``clearance(X, c)`` -> (n,) the bound where it decides and
    FCL's value where not; ``one(X)`` -> float for one (4, 4) pose.
    """

    def __init__(self, cavity, instrument: Instrument | None = None, *,
                 resolution: float = RESOLUTION, grid: DistanceGrid | None = None):
        import trimesh

        from implantplan.systems.placement.exact_clearance import ExactCavity

        if isinstance(cavity, ExactCavity):
            self.exact, mesh = cavity, cavity.mesh
        elif isinstance(cavity, trimesh.Trimesh):
            self.exact, mesh = None, cavity
        else:
            raise InputError("cavity", f"expected an ExactCavity or a mesh, got "
                             f"{type(cavity).__name__}")
        res = float(resolution)
        if not (np.isfinite(res) and res > 0):
            raise InputError("resolution", f"expected a positive length (m), got {resolution}")
        self.instrument = instrument or Instrument.paper()
        self.grid_mesh = mesh
        self.grid = grid if grid is not None else distance_grid(mesh)
        self.resolution = res
        self._g = _grid_args(self.grid)
        shapes = self.instrument.shapes
        self._kind = np.array([KIND[s.kind] for s in shapes], dtype=np.int64)
        self._A = np.ascontiguousarray([s.a for s in shapes], dtype=float)
        self._B = np.ascontiguousarray([s.b for s in shapes], dtype=float)
        self._r = np.ascontiguousarray([s.radius for s in shapes], dtype=float)
        self._s2 = np.empty((STACK, 2))
        self._s6 = np.empty((STACK, 6))

    def bounds(self, X_CTool, target=VALUE_CAP, *, decide: bool = False,
               resolution: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(lower bounds, upper estimates) (n,) (m), resolved against ``target`` (scalar or
        (n,)); ``decide``: a verdict for the claimed clearance ``target`` (stops at the first
        proof of "unsafe", the lower bound then the reference's floor); ``resolution``: the
        smallest piece (m), default the instance's."""
        from implantplan.systems.placement.tool_clearance import rigid_poses

        X = np.ascontiguousarray(rigid_poses(X_CTool))
        t = kernel_array(target, (X.shape[0],))
        if not np.all(np.isfinite(t)):
            raise InputError("clearance", "expected a finite claimed clearance (m)")
        lower, upper = np.empty(X.shape[0]), np.empty(X.shape[0])
        res = self.resolution if resolution is None else float(resolution)
        _poses_kernel(*self._g, X, self._kind, self._A, self._B, self._r, t, res,
                      bool(decide), lower, upper)
        return lower, upper

    @functools.cached_property
    def solids(self) -> tuple[ScanClearance, ...]:
        """One bound per solid of the instrument (the same cavity, grid and resolution)."""
        if len(self.instrument.shapes) == 1:
            return (self,)
        cavity = self.exact if self.exact is not None else self.grid_mesh
        return tuple(ScanClearance(cavity, dataclasses.replace(self.instrument, shapes=(s,)),
                                   resolution=self.resolution, grid=self.grid)
                     for s in self.instrument.shapes)

    def exact_minimum(self, X_CTool, *, check_start: bool = True) -> tuple[np.ndarray, int]:
        """(values (n,), FCL queries): FCL's clearance of the instrument
        (:meth:`ExactCavity.tool_clearance`) minimized over the S poses of each row of
        ``X_CTool`` (n, S, 4, 4), the same value as asking FCL at all n * S poses, with FCL
        asked only for the (solid, pose) pairs that may hold a row's minimum.

        Per solid the bound gives a lower bound L and an upper estimate U at every pose (a
        coarse pass, then the candidates refined against the row's level). A solid's FCL value
        is at most max(U, 0) (U bounds it where the solid is free, and where it is not the
        value is <= 0), so a row's minimum is at most m = min max(U, 0) over its solids and
        poses, and a pair whose L exceeds m (by more than :data:`PRUNE_SLACK`) cannot hold it.
        """
        from implantplan.systems.placement.tool_clearance import rigid_poses

        if self.exact is None:
            raise InputError("cavity", "the exact minimum needs the ExactCavity")
        X = np.asarray(X_CTool, dtype=float)
        if X.ndim != 4 or X.shape[2:] != (4, 4) or 0 in X.shape[:2]:
            raise InputError("X_CTool", f"expected (n, S, 4, 4) poses, got shape {X.shape}")
        n, S = X.shape[:2]
        P = rigid_poses(X.reshape(-1, 4, 4))
        subs = self.solids
        L = np.empty((len(subs), n * S))
        U = np.empty_like(L)
        coarse = max(COARSE_RESOLUTION, self.resolution)
        for k, sub in enumerate(subs):
            L[k], U[k] = sub.bounds(P, resolution=coarse)

        def candidates():
            level = np.maximum(U, 0.0).reshape(len(subs), n, S).min(axis=(0, 2))
            return L <= np.repeat(level, S)[None] + PRUNE_SLACK, np.repeat(level, S)

        cand, level = candidates()
        for k, sub in enumerate(subs):
            idx = np.flatnonzero(cand[k])
            if idx.size:
                lb, ub = sub.bounds(P[idx], np.minimum(level[idx], VALUE_CAP))
                L[k, idx] = np.maximum(L[k, idx], lb)
                U[k, idx] = np.minimum(U[k, idx], ub)
        cand, _ = candidates()
        out = np.full(n, np.inf)
        for k, sub in enumerate(subs):
            idx = np.flatnonzero(cand[k])
            if idx.size:
                v = self.exact.tool_clearance(P[idx], sub.instrument, check_start=check_start)
                np.minimum.at(out, idx // S, v)
        return out, int(cand.sum())

    def check(self, X_CTool) -> np.ndarray:
        """(n,) proven lower bounds (m) of the reference clearance (resolved up to
        :data:`VALUE_CAP`)."""
        return self.bounds(X_CTool)[0]

    def one(self, X_CTool: np.ndarray) -> float:
        """The lower bound (m) at one (4, 4) pose, without input checks."""
        X = np.ascontiguousarray(X_CTool, dtype=float)
        return float(pose_bound(*self._g, X, self._kind, self._A, self._B, self._r, VALUE_CAP,
                                self.resolution, self._s2, self._s6, False)[0])

    def fast_verdict(self, X_CTool, clearance: float) -> np.ndarray:
        """(n,) SAFE / UNSAFE / UNDECIDED for the claimed ``clearance`` (m) without FCL."""
        c = float(clearance)
        lower, upper = self.bounds(X_CTool, c, decide=True)
        out = np.full(lower.shape, UNDECIDED, dtype=np.int8)
        out[lower >= c] = SAFE
        if c > 0:
            out[(upper < c) & (lower < c)] = UNSAFE
        return out

    def verdict(self, X_CTool, clearance: float) -> np.ndarray:
        """(n,) True where the instrument keeps ``clearance`` (m): the fast verdict, FCL
        resolving the undecided poses (requires an ExactCavity)."""
        v = self.fast_verdict(X_CTool, clearance)
        und = v == UNDECIDED
        if und.any():
            if self.exact is None:
                raise InputError("cavity", "undecided poses need the ExactCavity to resolve")
            from implantplan.systems.placement.tool_clearance import rigid_poses

            X = rigid_poses(X_CTool)
            v[und] = np.where(self.exact.tool_clearance(X[und], self.instrument)
                              >= float(clearance), SAFE, UNSAFE)
        return v == SAFE

    def clearance(self, X_CTool, clearance: float) -> tuple[np.ndarray, np.ndarray]:
        """(values (n,), resolved (n,) bool): the scan bound where it decides the claimed
        ``clearance`` (m) (a lower bound of FCL's value), FCL's value at the undecided poses
        (``resolved`` True there)."""
        from implantplan.systems.placement.tool_clearance import rigid_poses

        X = rigid_poses(X_CTool)
        c = float(clearance)
        lower, upper = self.bounds(X, c, decide=True)
        und = (lower < c) & ~((upper < c) & (c > 0))
        vals = lower.copy()
        if und.any():
            if self.exact is None:
                raise InputError("cavity", "undecided poses need the ExactCavity to resolve")
            vals[und] = self.exact.tool_clearance(X[und], self.instrument)
        return vals, und


@numba.njit(cache=True)
def capped_at(args, X) -> float:
    """min(scan bound, cap) (m) at one pose X (4, 4); ``args`` is :attr:`CappedScanClearance.
    at_args`. The loops' hook (the supervisor's slow path takes it as a compiled function)."""
    G, lo, hi, ox, oy, oz, g, band, kind, A, B, r, cap, res, s2, s6 = args
    # np.bool_: a bool, not the literal False (numba would compile pose_bound once more for it)
    v = pose_bound(G, lo, hi, ox, oy, oz, g, band, X, kind, A, B, r, cap, res, s2, s6,
                   np.bool_(False))[0]
    return v if v < cap else cap


@numba.njit(cache=True)
def _capped_many(args, X, out):
    """out[k] = :func:`capped_at` at X[k] (serial: the loops call it with one pose, and a forked
    worker must not start the parallel kernels' OpenMP pool)."""
    for k in range(X.shape[0]):
        out[k] = capped_at(args, X[k])


class CappedScanClearance:
    """The scan bound resolved only up to ``cap`` (m): min(lower bound, cap), a lower bound of
    FCL's clearance capped at ``cap``, for the control loops (supervisor, estimator).

    A barrier needs the clearance only near its margin: above the cap the value is the cap
    (h = min(d, cap) is itself a barrier of the same safe set while cap > margin), and the
    branch and bound stops as soon as every piece is proven beyond it, so the cost per pose is
    that of the pieces near the cap (docs/measurements.md, "The supervisor on the scan").

    ``clear(X)`` -> (n,) for (n, 4, 4) or (4, 4) poses; ``one(X)`` -> float for one (4, 4)
    pose without checks; ``at(at_args, X)``: the compiled one-pose hook.
    """

    def __init__(self, scan: ScanClearance, cap: float):
        cap = float(cap)
        if not (np.isfinite(cap) and cap > 0):
            raise InputError("cap", f"expected a positive length (m), got {cap}")
        self.scan, self.cap = scan, cap
        self.instrument = scan.instrument
        self.at = capped_at
        self.at_args = (*scan._g, scan._kind, scan._A, scan._B, scan._r, cap, scan.resolution,
                        np.empty((STACK, 2)), np.empty((STACK, 6)))

    def __call__(self, X_CTool) -> np.ndarray:
        from implantplan.systems.placement.tool_clearance import rigid_poses

        X = np.ascontiguousarray(rigid_poses(X_CTool))
        out = np.empty(X.shape[0])
        _capped_many(self.at_args, X, out)
        return out

    def one(self, X_CTool: np.ndarray) -> float:
        return capped_at(self.at_args, np.ascontiguousarray(X_CTool, dtype=float))


REGION_BUDGET = 250_000  # FCL queries of one placement search's region resolution (~75 s)
REGION_BATCH = 64  # cells split per round of :func:`region_branch_and_bound` (one FCL batch)
REGION_PROGRESS_EVERY = 5.0  # s between the progress lines of :func:`region_branch_and_bound`


def _region_poses(P: np.ndarray, index: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(m, 4, 4) the poses at cell centres (m, 6) = (s, t_y, t_z, w) about feed poses P[index]
    (:func:`systems.placement.tool_clearance.moved_poses`: the TCP moved along the rod by s and
    across it by t, the frame turned by exp(w) at the TCP)."""
    from implantplan.systems.placement.tool_clearance import moved_poses

    return moved_poses(P[index], centre[:, :3], centre[:, 3:])


def region_branch_and_bound(scan: ScanClearance, P: np.ndarray, lower: np.ndarray, *,
                            half_step: float, lateral: float, angle: float, claim: float,
                            budget: int = REGION_BUDGET,
                            progress=None) -> tuple[np.ndarray, int, bool]:
    """Branch and bound over the fixture's region about feed poses, where the bound minus the
    region's worst-case loss leaves a pose below the claimed clearance; the scan bound and FCL
    at the cells' centres.

    The region about feed pose P_i (the cell): the feed offset s in [-half_step, half_step]
    along the rod, the TCP's lateral offset t in the disc |t| <= ``lateral`` across it, and a
    turn w (rotation vector) in the ball |w| <= ``angle`` at the TCP (the fixture holds the TCP
    within the lateral tolerance and the orientation within the angle: this set contains the
    fixture's region). A box cell of half-widths h about (s, t, w) moves no point of the solid
    by more than rho = |h_s,t| + |h_w| Q from where it is at the centre, Q the solid's largest
    distance from the TCP (:meth:`Instrument.origin_reach_T`): translations move every point by
    their length and |exp(w) q - exp(w') q| <= |w - w'| |q| (the right Jacobian of SO(3) has
    norm <= 1). So the cell keeps v - rho for any lower bound v of the clearance at its centre,
    and its parent's bound. At each new centre the scan bound (its lower bound and upper
    estimate, resolved against claim + rho) comes first; FCL is asked only where the lower bound
    leaves the cell below the claim and the upper estimate says FCL can lift it. Cells are split
    in two along the half-width that costs most (turns weighted by Q) while their bound is below
    ``claim``; cells wholly outside the disc or the ball are dropped.

    Stops when every cell reaches ``claim`` (proven), when a centre inside the region is closer
    than it (an upper estimate or FCL below it: disproved, the region holds such a pose), or
    after ``budget`` FCL queries (undecided: the bounds so far are returned, still sound).

    A long search (a small margin: minutes) says how far it is, every
    :data:`REGION_PROGRESS_EVERY` seconds, through ``progress`` (an
    :class:`analyses.progress.Progress`-like object with ``say``; None: silent): the FCL queries
    done of the budget, the cells still below the claim and the bound so far (the least cell's).
    The result does not depend on it.

    Args:
        scan: the :class:`ScanClearance` of one solid, with its ExactCavity.
        P: (n, 4, 4) feed poses; lower: (n,) each cell's lower bound so far (m).
        progress: where the progress lines go (None: nowhere).

    Returns:
        ((n,) the cells' lower bounds (m), FCL queries, decided: proven or disproved).
    """
    exact, solid = scan.exact, scan.instrument
    Q = float(solid.origin_reach_T()[0])
    n = P.shape[0]
    weight = np.array([1.0, 1.0, 1.0, Q, Q, Q])
    cells = CellLog(n)
    queries = 0
    first = True
    last_said = time.perf_counter()
    what = solid.shapes[0].name if len(solid.shapes) == 1 else solid.name
    while True:
        if (progress is not None and not first
                and time.perf_counter() - last_said >= REGION_PROGRESS_EVERY):
            last_said = time.perf_counter()
            progress.say(f"fixture region of the {what}: {queries:,} of {budget:,} FCL "
                         f"queries, {len(cells.open):,} cells below the claimed "
                         f"{claim * 1e3:.3f} mm, bound {cells.least() * 1e3:.3f} mm so far")
        if first:  # the feed poses themselves (centres of the root cells, in the region)
            c = np.zeros((n, 6))
            h = np.tile([half_step, lateral, lateral, angle, angle, angle], (n, 1))
            i, parent = np.arange(n), lower.astype(float)
        else:
            if not cells.open:
                break
            if queries >= budget:
                return cells.minimum(), queries, False
            pick = cells.pop_least(REGION_BATCH)
            hk = cells.half[pick]
            d = np.argmax(hk * weight, axis=1)
            rows = np.arange(pick.size)
            hk[rows, d] *= 0.5
            low_c, high_c = cells.centre[pick], cells.centre[pick]
            low_c[rows, d] -= hk[rows, d]
            high_c[rows, d] += hk[rows, d]
            c, h = np.concatenate([low_c, high_c]), np.concatenate([hk, hk])
            i, parent = np.tile(cells.index[pick], 2), np.tile(cells.lb[pick], 2)
            gap_t = np.linalg.norm(np.maximum(np.abs(c[:, 1:3]) - h[:, 1:3], 0.0), axis=1)
            gap_w = np.linalg.norm(np.maximum(np.abs(c[:, 3:]) - h[:, 3:], 0.0), axis=1)
            keep = (gap_t <= lateral) & (gap_w <= angle)
            c, h, i, parent = c[keep], h[keep], i[keep], parent[keep]
        rho = np.linalg.norm(h[:, :3], axis=1) + Q * np.linalg.norm(h[:, 3:], axis=1)
        X = _region_poses(P, i, c)
        v, up = scan.bounds(X, np.minimum(claim + rho, VALUE_CAP))
        ask = (v - rho < claim) & ~(up - rho < claim)
        if ask.any():
            v[ask] = np.maximum(v[ask], exact.tool_clearance(X[ask], solid))
            up[ask] = np.minimum(up[ask], v[ask])
            queries += int(ask.sum())
        cells.append(c, h, i, np.maximum(parent, v - rho), claim)
        first = False
        inside = (np.linalg.norm(c[:, 1:3], axis=1) <= lateral) & (
            np.linalg.norm(c[:, 3:], axis=1) <= angle) & (np.abs(c[:, 0]) <= half_step)
        if (up[inside] < claim).any():
            return cells.minimum(), queries, True
    return cells.minimum(), queries, True


class CellLog:
    """The cells of :func:`region_branch_and_bound`: an append-only log (centre, half-widths,
    feed pose index, lower bound) where a split cell is marked dead and its children appended,
    and a heap of the open cells (bound below the claim) keyed by (bound, position in the log).
    The live cells keep their order of creation, so the heap gives the cells a stable sort of
    the live bounds would (the least first, ties in creation order), in O(log N) a cell instead
    of a sort and a copy of every cell in every round."""

    def __init__(self, n: int):
        cap = max(8 * n, 1024)
        self.centre, self.half = np.empty((cap, 6)), np.empty((cap, 6))
        self.index, self.lb = np.empty(cap, dtype=np.int64), np.empty(cap)
        self.live = np.zeros(cap, dtype=bool)
        self.n, self.size = n, 0
        self.open: list[tuple[float, int]] = []

    def append(self, c, h, i, lb, claim: float) -> None:
        m, k = c.shape[0], self.size
        if k + m > self.lb.size:
            cap = max(2 * self.lb.size, k + m)
            for name in ("centre", "half", "index", "lb", "live"):
                old = getattr(self, name)
                new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
                new[:k] = old[:k]
                setattr(self, name, new)
        self.centre[k:k + m], self.half[k:k + m] = c, h
        self.index[k:k + m], self.lb[k:k + m] = i, lb
        self.live[k:k + m] = True
        self.size = k + m
        for j in np.flatnonzero(lb < claim):
            heapq.heappush(self.open, (float(lb[j]), k + int(j)))

    def pop_least(self, count: int) -> np.ndarray:
        """The positions of the ``count`` least open cells (in that order), marked dead."""
        pick = np.array([heapq.heappop(self.open)[1]
                         for _ in range(min(count, len(self.open)))], dtype=np.int64)
        self.live[pick] = False
        return pick

    def least(self) -> float:
        """The least bound of the live cells (an open one's while any is open)."""
        if self.open:
            return self.open[0][0]
        return float(self.lb[:self.size][self.live[:self.size]].min())

    def minimum(self) -> np.ndarray:
        alive = self.live[:self.size]
        return _cell_minimum(self.index[:self.size][alive], self.lb[:self.size][alive], self.n)


def _cell_minimum(index: np.ndarray, lb: np.ndarray, n: int) -> np.ndarray:
    out = np.full(n, np.inf)
    np.minimum.at(out, index, lb)
    return out


FEED_STEP = 0.1e-3  # m, pose spacing of :func:`feed_scan_clearance` (costs at most half of it)
COARSE_RESOLUTION = 0.5e-3  # m, the first pass of :func:`feed_scan_clearance`
NEAR_MINIMUM = 0.3e-3  # m: poses within this of the feed's least upper estimate are refined


def feed_scan_clearance(scan: ScanClearance, X_CTool, *, depth: float, lateral: float = 0.0,
                        angle: float = 0.0, clearance: float | None = None,
                        step: float = FEED_STEP, resolve_region: bool = False,
                        region_budget: int | None = None, progress=None) -> dict:
    """Certified clearance (m) of the instrument against the scan over its whole feed (the pose
    ``X_CTool`` (4, 4) backed out along the rod by 0..``depth``) and the fixture's admissible
    region (the rod axis within ``lateral`` of the planned line, the orientation within
    ``angle``).

    Per solid s and feed pose i the scan bound v_si (:meth:`ScanClearance.bounds`: a first
    pass at :data:`COARSE_RESOLUTION`, then the poses whose bound is within
    :data:`NEAR_MINIMUM` of the feed's least upper estimate refined at the scan's resolution
    against that level: the others cannot hold the minimum); where a
    pose's value minus the region's loss is below ``clearance`` (the margin; None: never) and
    the scan holds an ExactCavity, FCL's exact value of each solid replaces the bound
    (resolved). The region moves every point of solid s by at most lateral + angle * reach_s
    (:meth:`Instrument.shape_reach_T`), so c_i = min_s (v_si - loss_s); between poses at spacing
    t (a translation along the rod, 1-Lipschitz) the feed keeps min(c_i, (c_i + c_{i+1} - t) / 2).

    With ``resolve_region`` (and an ExactCavity and a ``clearance``), where that value is below
    the claim the worst-case loss is replaced by FCL over the region itself (at most
    ``region_budget`` FCL queries, None: :data:`REGION_BUDGET`): each solid's feed
    cells (pose i +- t / 2) whose bound v_si - loss_s - t / 2 is below the claim go through
    :func:`region_branch_and_bound` (branch and bound of the region, FCL at the cells' centres),
    for the solids whose turn about the TCP is the region's (origin reach = rod-axis reach:
    the head and the implant, not the long rod the fixture holds by its axis). The value is
    then the larger of the two sound bounds. ``progress`` gets that search's progress lines.

    Returns:
        dict: ``value`` (m), ``poses``, ``resolved_poses`` (poses FCL resolved), ``step``,
        ``solid`` (the solid at the minimum), ``region`` (None, or what the region's
        resolution did: ``cells`` resolved, ``fcl_queries``, ``decided``, ``value``).
    """
    from implantplan.systems.placement.tool_clearance import feed_poses

    for name, value in (("lateral", lateral), ("angle", angle)):
        if not np.isfinite(value) or value < 0:
            raise InputError(name, f"expected a tolerance >= 0, got {value}")
    P, t = feed_poses(X_CTool, depth, step)
    P = P.reshape(-1, 4, 4)
    inst = scan.instrument
    loss = lateral + angle * inst.shape_reach_T()
    V = np.empty((len(inst.shapes), P.shape[0]))
    U = np.empty_like(V)
    solids = scan.solids
    for k, sub in enumerate(solids):
        lb, ub = sub.bounds(P, resolution=max(COARSE_RESOLUTION, scan.resolution))
        level = min(ub.min() - loss[k] + NEAR_MINIMUM, VALUE_CAP)
        V[k], U[k] = lb - loss[k], ub - loss[k]
        refine = V[k] < level
        if refine.any():
            V[k, refine] = sub.bounds(P[refine], level + loss[k])[0] - loss[k]
    c_claim = -np.inf if clearance is None else float(clearance)
    # FCL can lift a pose above the claim only where no solid's upper estimate is below it
    low = (V.min(axis=0) < c_claim) & ~(U.min(axis=0) < c_claim)
    resolved = int(low.sum())
    if resolved and scan.exact is not None:
        for k, sub in enumerate(solids):
            V[k, low] = np.maximum(V[k, low],
                                   scan.exact.tool_clearance(P[low], sub.instrument) - loss[k])
    c = V.min(axis=0)
    value = float(c.min())
    if c.size > 1:
        value = min(value, float((0.5 * (c[:-1] + c[1:] - t)).min()))
    solid = inst.shapes[int(np.unravel_index(np.argmin(V), V.shape)[0])].name
    region = None
    if resolve_region and scan.exact is not None and value < c_claim and (lateral or angle):
        # each feed cell (pose +- t / 2) keeps v - loss - t / 2; FCL resolves the region where
        # that is below the claim
        cells = V - 0.5 * t
        turn_about_tcp = inst.turns_about_tcp()
        region = {"cells": 0, "fcl_queries": 0, "decided": True}
        for k, sub in enumerate(solids):
            low = np.flatnonzero(cells[k] < c_claim)
            if low.size == 0 or not turn_about_tcp[k]:
                continue
            budget = (REGION_BUDGET if region_budget is None else int(region_budget)) \
                - region["fcl_queries"]
            lb, q, decided = region_branch_and_bound(
                sub, P[low], cells[k, low], half_step=0.5 * t,
                lateral=lateral, angle=angle, claim=c_claim, budget=max(budget, 0),
                progress=progress)
            cells[k, low] = lb
            region["cells"] += int(low.size)
            region["fcl_queries"] += int(q)
            region["decided"] &= bool(decided)
        region["value"] = float(cells.min())
        if region["value"] > value:
            value = region["value"]
            solid = inst.shapes[int(np.unravel_index(np.argmin(cells), cells.shape)[0])].name
    return {"value": value, "poses": int(c.size), "resolved_poses": resolved if scan.exact
            is not None else 0, "step": float(t), "solid": solid, "region": region}


def registration_monte_carlo(
    exact: ExactCavity,
    X_CT,
    tool,
    *,
    depth: float,
    safety: SafetySpec | None = None,
    seed: int = 0,
    depth_step: float = 0.004,
    bound=None,
) -> dict:
    """The planned feed under registration error of the Center frame.

    Each of ``safety.registration_samples`` samples (None: ``SafetySpec()``) draws an error E
    of Center's pose (translation ~ N(0, sigma_translation^2) per axis, rotation vector
    ~ N(0, sigma_rotation^2) per axis, about Center's origin; the sigmas are
    ``safety.registration_sigma_*``): the robot executes the plan in the registered frame, so
    relative to the true anatomy the tool is at E^-1 X(s) for every depth s of the feed (the
    planned pose backed out along the rod axis, 0..``depth`` every ``depth_step``). The exact
    (FCL) clearance of the whole tool at those poses, minimized over the feed, is the sample's
    value, found with FCL where the scan bound ``bound`` (a
    :class:`systems.placement.scan_clearance.ScanClearance` of ``exact`` and ``tool``; None:
    built) cannot rule a pose out of a sample's minimum
    (:meth:`~systems.placement.scan_clearance.ScanClearance.exact_minimum`: the same values as
    FCL at every pose). Same seed, same result.

    Returns:
        dict: ``probability_clear`` (share of samples whose clearance stays > 0 along the whole
        feed), ``clearance_p01`` (1st percentile, m), ``clearance_median``, ``clearance_min``,
        the settings (SI units).
    """

    safety = SafetySpec() if safety is None else safety
    if not isinstance(safety, SafetySpec):
        raise InputError("safety", f"expected a SafetySpec, got {type(safety).__name__}")
    samples = int(safety.registration_samples)
    if samples < 1:
        raise InputError("safety.registration_samples",
                         f"expected at least 1 sample, got {samples}")
    sigma_translation = safety.registration_sigma_translation
    sigma_rotation = safety.registration_sigma_rotation
    from implantplan.systems.placement.exact_clearance import registration_errors
    from implantplan.systems.placement.tool_clearance import feed_poses

    E_inv = registration_errors(safety, np.random.default_rng(seed), samples)

    P, _ = feed_poses(X_CT, depth, depth_step)  # (1, S, 4, 4)
    poses = E_inv[:, None] @ P[0][None]  # (samples, S, 4, 4)
    if bound is None:
        bound = ScanClearance(exact, tool)
    elif bound.exact is not exact or bound.instrument != tool:
        raise InputError("bound", "expected the scan bound of this cavity and instrument")
    c, queries = bound.exact_minimum(poses)
    return {
        "samples": samples,
        "seed": int(seed),
        "sigma_translation": float(sigma_translation),
        "sigma_rotation": float(sigma_rotation),
        "depth": float(depth),
        "depth_step": float(depth_step),
        "fcl_queries": int(queries),
        "poses": int(poses.shape[0] * poses.shape[1]),
        "probability_clear": float(np.mean(c > 0)),
        "clearance_p01": float(np.percentile(c, 1)),
        "clearance_median": float(np.median(c)),
        "clearance_min": float(c.min()),
        "units": "m, rad",
        "reference": "exact (FCL) clearance of the whole tool to the scan, min over the feed",
    }
