"""Sound clearance of the implanting tool against the FPSM (this project's correction of Eq. 12).

Seed 000 checks a rod of radius r by testing its axis against the model shrunk radially,
rho(theta) - r (Eq. 12), at the slice crossings only. Both steps are unsound: rho - r is not the
inward offset of a non-circular curve (in a slit-shaped section the wall can lie inside the rod's
radius while rho - r is positive), and the wall between two slices is never looked at. Here the
clearance of a capsule (axis segment, radius r) is a certified lower bound of its true distance to
the FPSM boundary, over the whole slab structure:

**The free region.** F = {z_0 <= z <= z_top, |xy| < rho(theta, z)} U {z > z_top}, with rho linear
in z between slices (Eq. 11). Its boundary is the lateral wall of every slab, the throat disc at
z_0 (below it is a collision, as in :meth:`Fpsm.d_safe`) and the part of the plane z = z_top
outside the top curve (above the mouth opening nothing is constrained). Leaving through the throat
or the side is therefore a collision; leaving through the opening is not.

**A certified distance field.** The signed distance f to that boundary (> 0 in F) is 1-Lipschitz.
It is bounded from below on a regular grid of spacing g over the model's bounding box: the
boundary is sampled densely (the slab walls on a (theta, w) grid, the throat disc and the top
annulus on (theta, radius) grids) with a *covering radius* e proven from the curves' derivative
bounds (every boundary point lies within e of a sample); a node at distance d from its nearest
sample then has f >= d - e inside F and f >= -d outside (where the nearest boundary point is at
most d away). Values beyond ``cap`` are clamped (a lower bound stays one).

**Between nodes** the trilinear interpolant I of the node bounds L_c satisfies, for a
1-Lipschitz f, f(q) >= sum_c w_c (L_c - |q - c|) >= I(q) - g sqrt(sum_a t_a (1 - t_a)), by
Jensen (sum_c w_c |q - c|^2 = g^2 sum_a t_a (1 - t_a) for the cell's fractional coordinates t_a);
each corner's cone L_c - |q - c| is a bound too, and the largest of the nine is used.
Tighter away from the wall: the distance d to the boundary set (unsigned) has d(q)^2 - |q|^2 =
min over boundary points b of (|b|^2 - 2 q . b), a minimum of affine functions, so concave;
with the trilinear weights (convex, sum_c w_c c = q) d(q)^2 >= sum_c w_c max(L_c, 0)^2 -
g^2 sum_a t_a (1 - t_a). It loses about g^2 sum t (1 - t) / (2 d) instead of g sqrt(sum t (1 -
t)) (0.05 mm instead of 0.87 mm at the cell centre for d = 7 mm, g = 1 mm), and is at least the
linear bound wherever that one is >= 0. Being a bound of the unsigned distance, it certifies
only that the axis never meets the boundary: the axis then stays on the side of its start, and
whether the start is in F is decided exactly (Eq. 10-11 at its height).

**Along the axis** two samples q_i, q_{i+1} at distance t with bounds b_i, b_{i+1} give
min over the segment between them of f >= (b_i + b_{i+1} - t) / 2 (both cones of slope 1). The
step is adaptive (sphere tracing): t = max(step, b_i - m) with m the smallest bound so far, so far
from the wall the march is quick and near it the spacing is ``step``.

**Above the grid** (z above z_top + 2 g), every boundary point has z <= z_top, so with q' the
point's projection onto z = z_top, |q - b|^2 >= (z - z_top)^2 + |q' - b|^2 and
f(q) >= sqrt((z - z_top)^2 + max(f(q'), 0)^2). Outside the box laterally or below it (at z <=
z_top) a point is outside F: the bound is -1 m (not certified, negative).

The capsule clearance is min over its axis of f minus r: > 0 certifies that the capsule is that far
from the boundary (so inside the free region); <= 0 means "not certified" (its magnitude is only a
penetration estimate). Eq. 12 stays available as ``method="paper"``.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from implantplan.systems import validate
from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import SPLINE_BASIS, TWO_PI, Fpsm, point_d_safe
from implantplan.systems.frames import rotations
from implantplan.systems.instrument import Instrument
from implantplan.systems.jit import numba

METHODS = ("sound", "paper")
OUTSIDE = -1.0  # the bound (m) outside the grid box at z <= z_top: a collision, not a distance
ROUNDING = 1e-9  # m taken off the square-root bound (rounding of the squared interpolation)


# -- curve bounds ------------------------------------------------------------------------------


def _segment_coefficients(rho: np.ndarray) -> np.ndarray:
    """(M, N, 4) cubic coefficients in t of every Catmull-Rom segment of every slice."""
    n = rho.shape[-1]
    idx = np.mod(np.arange(n)[:, None] + np.arange(-1, 3), n)  # (N, 4)
    return np.einsum("mka,ai->mki", rho[..., idx], SPLINE_BASIS)


def curve_bounds(rho) -> tuple[np.ndarray, np.ndarray]:
    """Exact max |rho(theta)| and max |d rho / d theta| of each slice (M,), from the segment
    cubics' critical points (``rho`` (M, N))."""
    c = _segment_coefficients(np.atleast_2d(np.asarray(rho, float)))
    n = c.shape[1]
    c0, c1, c2, c3 = c[..., 0], c[..., 1], c[..., 2], c[..., 3]
    # rho' in t: c1 + 2 c2 t + 3 c3 t^2; its roots are rho's critical points
    a, b, cc = 3 * c3, 2 * c2, c1
    disc = b * b - 4 * a * cc
    sq = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(np.abs(a) > 1e-300, (-b + sq) / (2 * a), -cc / np.where(b == 0, 1, b))
        r2 = np.where(np.abs(a) > 1e-300, (-b - sq) / (2 * a), -cc / np.where(b == 0, 1, b))
    cand = [np.zeros_like(c0), np.ones_like(c0)]
    for r in (r1, r2):
        cand.append(np.where((disc >= 0) & (r > 0) & (r < 1) & np.isfinite(r), r, 0.0))
    T = np.stack(cand, -1)
    val = c0[..., None] + T * (c1[..., None] + T * (c2[..., None] + T * c3[..., None]))
    max_rho = np.abs(val).max(axis=(-1, -2))
    # rho'' in t: 2 c2 + 6 c3 t; rho' extremes at t = 0, 1, -c2 / (3 c3)
    with np.errstate(divide="ignore", invalid="ignore"):
        tv = np.where(np.abs(c3) > 1e-300, -c2 / (3 * c3), 0.0)
    tv = np.where((tv > 0) & (tv < 1), tv, 0.0)
    T = np.stack([np.zeros_like(c0), np.ones_like(c0), tv], -1)
    der = c1[..., None] + T * (2 * c2[..., None] + 3 * c3[..., None] * T)
    max_der = np.abs(der).max(axis=(-1, -2)) * (n / TWO_PI)
    return max_rho, max_der


# -- the certified field -----------------------------------------------------------------------


@dataclass(frozen=True)
class ClearanceField:
    """Lower bounds of the signed distance to the FPSM boundary on a grid (see module notes).

    Attributes:
        values: (nx, ny, nz) float64 node bounds (m), in the Center frame.
        origin: (3,) position of node (0, 0, 0) (m).
        spacing: grid spacing g (m).
        z_top: the top slice height (the mouth opening) (m).
        cover: proven covering radius e of the boundary samples (m).
        cap: node values are clamped to at most this (m).
        samples: number of boundary samples used.
    """

    values: np.ndarray
    origin: np.ndarray
    spacing: float
    z_top: float
    cover: float
    cap: float
    samples: int


@numba.njit(cache=True)
def _envelope_distance(X, Y, coarse, e_coarse, qx, qy, s, p0, best):
    """Smallest distance from q to the dense curve samples (X, Y) (P,), starting from the
    upper bound ``best``. Only samples within the angular window that a disc of radius best
    about q subtends (seen from the axis, q at radius s and nearest sample index p0) can be
    nearer; every ``coarse``-th sample stands for its run of samples on either side, all within
    ``e_coarse`` of it along the curve, and prunes the run when it is too far."""
    P = X.shape[0]
    half = coarse // 2
    if best < s:
        w = np.arcsin(best / s) * (P / TWO_PI) + coarse + 1
        c_lo = (p0 - int(w)) // coarse
        c_hi = (p0 + int(w)) // coarse + 1
    else:
        c_lo = 0
        c_hi = P // coarse + 1
    arg = p0
    for cc in range(c_lo, c_hi + 1):  # first pass: the coarse samples tighten the bound
        c = (cc * coarse) % P
        d = np.hypot(X[c] - qx, Y[c] - qy)
        if d < best:
            best = d
            arg = c
    for cc in range(c_lo, c_hi + 1):  # second pass: refine the runs that can hold a nearer one
        c = (cc * coarse) % P
        if np.hypot(X[c] - qx, Y[c] - qy) - e_coarse < best:
            for i in range(c - half, c + half + 1):
                ii = i % P
                di = np.hypot(X[ii] - qx, Y[ii] - qy)
                if di < best:
                    best = di
                    arg = ii
    return best, arg


@numba.njit(cache=True, parallel=True)
def _layer_distances(EX, EY, ER, cover, coarse, e_coarse, xs, ys, cap, out):
    """out[k, i, j]: lower bound of the horizontal distance from node (xs[i], ys[j]) to the
    complement of envelope k's interior (0 where the node may be outside it), clamped to cap;
    envelopes as dense polar samples (K, P) with radii ER at the angles 2 pi p / P and
    covering radius ``cover``."""
    K, P = ER.shape
    for i in numba.prange(xs.size):
        for j in range(ys.size):
            x = xs[i]
            y = ys[j]
            s = np.hypot(x, y)
            u = (np.arctan2(y + 0.0, x + 0.0) % TWO_PI) * (P / TWO_PI)
            p0 = int(u) % P
            p1 = (p0 + 1) % P
            near = p0  # nearest sample of the previous layer: a tight start for the next
            for k in range(K):
                rmin = ER[k, p0] if ER[k, p0] < ER[k, p1] else ER[k, p1]
                if s > rmin - 3.0 * cover:
                    # at or beyond the curve (within the samples' covering radius): the
                    # horizontal distance is at most a few covering radii, bound it by 0
                    out[k, i, j] = 0.0
                    continue
                best = min(
                    cap + cover,
                    np.hypot(EX[k, p0] - x, EY[k, p0] - y),
                    np.hypot(EX[k, near] - x, EY[k, near] - y),
                )
                best, near = _envelope_distance(
                    EX[k], EY[k], coarse, e_coarse, x, y, s, p0, best
                )
                out[k, i, j] = min(max(best - cover, 0.0), cap)


@numba.njit(cache=True)
def _combine_layers(H, layer_lo, layer_hi, zs, z0, inside, outside_depth, cap, out):
    """out[i, j, l] = min over layers k of sqrt(H[k,i,j]^2 + dv^2), dv the vertical gap from
    zs[l] to layer k's interval, and the throat disc's z - z0; nodes outside F get
    -outside_depth."""
    K = H.shape[0]
    for i in range(H.shape[1]):
        for j in range(H.shape[2]):
            for l in range(zs.size):
                if not inside[i, j, l]:
                    out[i, j, l] = -outside_depth[i, j, l]
                    continue
                z = zs[l]
                best = min(cap, z - z0)
                for k in range(K):
                    if z < layer_lo[k]:
                        dv = layer_lo[k] - z
                    elif z > layer_hi[k]:
                        dv = z - layer_hi[k]
                    else:
                        dv = 0.0
                    if dv >= best:
                        continue
                    h = H[k, i, j]
                    v = np.sqrt(h * h + dv * dv)
                    if v < best:
                        best = v
                out[i, j, l] = best


def _distinct_layer_distances(EX, EY, ER, cover, coarse, e_coarse, xs, ys, cap) -> np.ndarray:
    """:func:`_layer_distances` of every envelope (K, P), each distinct envelope computed once
    (a layer's distances depend on its envelope alone: the layers of a cylinder, or of slabs
    between equal slices, repeat one), the distinct ones in layer order."""
    _, first, inverse = np.unique(ER, axis=0, return_index=True, return_inverse=True)
    if first.size == ER.shape[0]:
        H = np.empty((ER.shape[0], xs.size, ys.size))
        _layer_distances(EX, EY, ER, cover, coarse, e_coarse, xs, ys, cap, H)
        return H
    keep = np.sort(first)  # the first layer of each distinct envelope, in layer order
    H = np.empty((keep.size, xs.size, ys.size))
    _layer_distances(np.ascontiguousarray(EX[keep]), np.ascontiguousarray(EY[keep]),
                     np.ascontiguousarray(ER[keep]), cover, coarse, e_coarse, xs, ys, cap, H)
    return H[np.searchsorted(keep, first)[inverse.reshape(-1)]]


def build_field(
    fpsm: Fpsm,
    *,
    spacing: float = 0.001,
    cap: float = 0.02,
    angles: int = 8192,
) -> ClearanceField:
    """The certified distance field of ``fpsm`` (module notes).

    Built by layers: for each grid cell layer [z_l, z_l+1] the *envelope* m(theta) = min of
    rho(theta, z) over the layer (rho is piecewise linear in z, so the minimum is at the layer's
    ends or a slice plane inside it) bounds every wall point of the layer from inside: its xy
    lies on or outside the envelope curve. The horizontal distance from a node's xy to that curve
    (dense polar samples with a proven covering radius) and the vertical gap to the layer give
    |q - b| >= sqrt(dh^2 + dv^2) for every wall point b of the layer; the node's bound is the
    minimum over layers, the throat disc (z - z_0) and the top annulus (the top curve at
    z_top), clamped to ``cap``. Outside F a node gets minus an upper bound of its depth (the
    radial step back to the wall at its height, and up to z_0 below the throat).

    Args:
        spacing: grid spacing g (m) in x, y and z.
        cap: node values are clamped to it (m); clearances are resolved up to cap - r.
        angles: dense samples per curve.
    """
    if not isinstance(fpsm, Fpsm):
        raise InputError("fpsm", "expected an Fpsm")
    for name, value in (("spacing", spacing), ("cap", cap)):
        if not np.isfinite(value) or value <= 0:
            raise InputError(name, f"expected a positive length (m), got {value}")
    z_lo, z_hi = fpsm.z_range
    th = np.arange(angles) * (TWO_PI / angles)
    max_rho, max_der = curve_bounds(fpsm.rho)
    # Every envelope is a minimum of curves rho(., z) (convex combinations of two slices): as a
    # plane curve theta -> m(theta) e_theta it is Lipschitz with constant hypot(max rho,
    # max rho'), so samples 2 pi / angles apart cover it within half of that step.
    lip = float(np.hypot(max_rho.max(), max_der.max()))
    cover = lip * (np.pi / angles)
    coarse = 16
    e_coarse = lip * (TWO_PI * (coarse // 2) / angles)
    nz = int(np.ceil((z_hi - z_lo) / spacing)) + 1
    pad_z = 3
    zs = z_hi - spacing * np.arange(nz + pad_z)[::-1]  # the top layer is exactly z_top
    dense = fpsm.radius_at(th[None, :], fpsm.slice_z[:, None])
    X, Y = dense * np.cos(th), dense * np.sin(th)
    pad = max(4 * spacing, 0.002)
    lo = np.array([X.min() - pad, Y.min() - pad])
    nxy = np.ceil((np.array([X.max(), Y.max()]) + pad - lo) / spacing).astype(int) + 1
    xs = lo[0] + spacing * np.arange(nxy[0])
    ys = lo[1] + spacing * np.arange(nxy[1])
    # envelopes of the cell layers inside [z_lo, z_hi], plus the top curve itself (annulus)
    zin = zs[zs >= z_lo - 1e-12]
    edges = []
    if zin[0] > z_lo + 1e-12:  # a partial cell just above z_lo
        edges.append((z_lo, zin[0]))
    edges += list(zip(zin[:-1], zin[1:], strict=True))
    ER = np.empty((len(edges) + 1, angles))
    for k, (a_, b_) in enumerate(edges):
        zz = np.array([a_, b_] + [z for z in fpsm.slice_z if a_ < z < b_])
        ER[k] = np.min(fpsm.radius_at(th[None, :], zz[:, None]), axis=0)
    ER[-1] = fpsm.radius_at(th, np.full(angles, z_hi))
    layer_lo = np.array([e[0] for e in edges] + [z_hi])
    layer_hi = np.array([e[1] for e in edges] + [z_hi])
    EX, EY = ER * np.cos(th), ER * np.sin(th)
    H = _distinct_layer_distances(EX, EY, ER, cover, coarse, e_coarse, xs, ys, cap)
    # membership and outside depths of the nodes
    Xn, Yn, Zn = np.meshgrid(xs, ys, zs, indexing="ij")
    theta = np.arctan2(Yn + 0.0, Xn + 0.0)
    r = np.hypot(Xn, Yn)
    rad = fpsm._radius(theta, np.clip(Zn, z_lo, z_hi))
    inside = (Zn >= z_lo) & (r < rad)
    out_r = np.maximum(r - rad, 0.0)
    depth = np.where(Zn >= z_lo, out_r, np.hypot(z_lo - Zn, out_r))
    values = np.empty(Xn.shape)
    _combine_layers(H, layer_lo, layer_hi, zs, z_lo, inside, depth, cap, values)
    values.setflags(write=False)
    origin = np.array([xs[0], ys[0], zs[0]])
    return ClearanceField(values, origin, float(spacing), float(z_hi), float(cover), float(cap),
                          int(ER.size))


_FIELDS: dict[int, tuple] = {}


def clearance_field(fpsm: Fpsm, **options) -> ClearanceField:
    """The field of ``fpsm``, built once per model object (and per options) and cached."""
    key = (id(fpsm), tuple(sorted(options.items())))
    hit = _FIELDS.get(key)
    if hit is not None:
        ref, rho, z, field = hit
        if ref() is fpsm and rho is fpsm.rho and z is fpsm.slice_z:
            return field
    field = build_field(fpsm, **options)
    _FIELDS[key] = (weakref.ref(fpsm, lambda _r, k=key: _FIELDS.pop(k, None)), fpsm.rho,
                    fpsm.slice_z, field)
    return field


def boundary_mesh(fpsm: Fpsm, *, angles: int = 4096, rings: int = 2, outer: float = 1.0):
    """The boundary of the free region F (module notes) as a triangle mesh in Center (m): the
    slab walls (``angles`` samples per curve, ``rings`` + 1 rows per slab: the wall is linear in z
    at each angle, so only the angular chords and the quads' twist depart from it), the throat
    disc at z_0 and the annulus of the plane z_top between the top curve and radius ``outer``.

    An exact reference of the distance to the FPSM boundary, to the triangulation's error
    (sub-micrometre at the default density on the bundled models): ``ExactCavity`` over it
    measures how far a rod's certified bound lies below its true FPSM clearance
    (analyses.studies.rod_check's breakdown). Not used by the bound itself.
    """
    import trimesh

    th = np.arange(angles) * (TWO_PI / angles)
    c, s = np.cos(th), np.sin(th)
    V, F = [], []
    nv = 0
    z = fpsm.slice_z
    for j in range(z.size - 1):
        zz = np.linspace(z[j], z[j + 1], rings + 1)
        R = fpsm.radius_at(th[None, :], zz[:, None])
        V.append(np.stack([R * c, R * s, np.broadcast_to(zz[:, None], R.shape)], -1)
                 .reshape(-1, 3))
        idx = nv + np.arange((rings + 1) * angles).reshape(rings + 1, angles)
        a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
        cc, d = idx[1:], np.roll(idx[1:], -1, axis=1)
        F += [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, cc], -1).reshape(-1, 3)]
        nv += (rings + 1) * angles
    for zc, top in ((z[0], False), (z[-1], True)):
        R = fpsm.radius_at(th, np.full(angles, zc))
        ring = nv + np.arange(angles)
        V.append(np.column_stack([R * c, R * s, np.full(angles, zc)]))
        nv += angles
        if top:
            V.append(np.column_stack([outer * c, outer * s, np.full(angles, zc)]))
            out = nv + np.arange(angles)
            nv += angles
            F += [np.stack([ring, out, np.roll(out, -1)], -1),
                  np.stack([ring, np.roll(out, -1), np.roll(ring, -1)], -1)]
        else:
            V.append(np.array([[0.0, 0.0, zc]]))
            F.append(np.stack([np.full(angles, nv), ring, np.roll(ring, -1)], -1))
            nv += 1
    return trimesh.Trimesh(np.concatenate(V), np.concatenate(F), process=False)


# -- compiled kernels --------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _trilinear(v000, v100, v010, v110, v001, v101, v011, v111, tx, ty, tz):
    """The trilinear interpolant of a cell's corner values at fractional coordinates t."""
    c00 = v000 + tx * (v100 - v000)
    c10 = v010 + tx * (v110 - v010)
    c01 = v001 + tx * (v101 - v001)
    c11 = v011 + tx * (v111 - v011)
    c0 = c00 + ty * (c10 - c00)
    c1 = c01 + ty * (c11 - c01)
    return c0 + tz * (c1 - c0)


@numba.njit(cache=True)
def _grid_bound(V, ox, oy, oz, g, x, y, z, refine):
    """Lower bound of f at a point inside the grid's index range, else NaN; ``refine`` adds
    the corner cones (tighter, slower)."""
    nx, ny, nz = V.shape
    fx = (x - ox) / g
    fy = (y - oy) / g
    fz = (z - oz) / g
    if not (fx >= 0.0 and fy >= 0.0 and fz >= 0.0):
        return np.nan
    i = int(fx)
    j = int(fy)
    k = int(fz)
    if i >= nx - 1:
        if fx > nx - 1:
            return np.nan
        i = nx - 2
    if j >= ny - 1:
        if fy > ny - 1:
            return np.nan
        j = ny - 2
    if k >= nz - 1:
        if fz > nz - 1:
            return np.nan
        k = nz - 2
    tx = fx - i
    ty = fy - j
    tz = fz - k
    v000, v100 = V[i, j, k], V[i + 1, j, k]
    v010, v110 = V[i, j + 1, k], V[i + 1, j + 1, k]
    v001, v101 = V[i, j, k + 1], V[i + 1, j, k + 1]
    v011, v111 = V[i, j + 1, k + 1], V[i + 1, j + 1, k + 1]
    spread = tx * (1.0 - tx) + ty * (1.0 - ty) + tz * (1.0 - tz)
    # the squared distance: d^2 - |q|^2 is concave, so d(q)^2 >= sum_c w_c L_c^2 - g^2 spread
    # (module notes); where the linear bound below is >= 0 this one is at least as large
    s000, s100 = max(v000, 0.0) ** 2, max(v100, 0.0) ** 2
    s010, s110 = max(v010, 0.0) ** 2, max(v110, 0.0) ** 2
    s001, s101 = max(v001, 0.0) ** 2, max(v101, 0.0) ** 2
    s011, s111 = max(v011, 0.0) ** 2, max(v111, 0.0) ** 2
    sq = _trilinear(s000, s100, s010, s110, s001, s101, s011, s111, tx, ty, tz) - g * g * spread
    if sq > ROUNDING * ROUNDING:
        best = np.sqrt(sq) - ROUNDING
    else:  # near or beyond the wall: the trilinear interpolant less its Jensen term
        val = _trilinear(v000, v100, v010, v110, v001, v101, v011, v111, tx, ty, tz)
        best = val - g * np.sqrt(spread)
    if not refine:
        return best
    # the cone bound of each corner, L_c - |q - c|, is valid too: keep the larger
    for a in range(2):
        dx2 = (tx - a) * (tx - a)
        for b in range(2):
            dxy2 = dx2 + (ty - b) * (ty - b)
            for c in range(2):
                cone = V[i + a, j + b, k + c] - g * np.sqrt(dxy2 + (tz - c) * (tz - c))
                if cone > best:
                    best = cone
    return best


# refine or not, as np.bool_ (a bool, not a literal: one compiled version of the bounds)
_REFINE, _COARSE = np.bool_(True), np.bool_(False)


@numba.njit(cache=True)
def _point_bound(V, ox, oy, oz, g, z_top, x, y, z, refine):
    """Lower bound of the signed distance f at any point (module notes)."""
    b = _grid_bound(V, ox, oy, oz, g, x, y, z, refine)
    if not np.isnan(b):
        return b
    if z > z_top:
        b0 = _grid_bound(V, ox, oy, oz, g, x, y, z_top, _REFINE)
        if np.isnan(b0) or b0 < 0.0:
            b0 = 0.0
        return np.sqrt((z - z_top) * (z - z_top) + b0 * b0)
    return OUTSIDE


@numba.njit(cache=True)
def _segment_min(V, ox, oy, oz, g, z_top, cap, step, rho, slice_z, level, ax, ay, az, bx, by,
                 bz, stop=-np.inf):
    """Lower bound of min f over the segment a-b (adaptive march, module notes): distances up
    to ``level`` are resolved to the step; where the bound is far above both the running
    minimum and ``level`` the march takes long steps (the interval bound stays >= either).
    Once the running minimum is below ``stop`` the march ends and returns it (then only "below
    ``stop``" is certain: the verdict-only path)."""
    dx = bx - ax
    dy = by - ay
    dz = bz - az
    length = np.sqrt(dx * dx + dy * dy + dz * dz)
    b_prev = _point_bound(V, ox, oy, oz, g, z_top, ax, ay, az, _REFINE)
    if b_prev <= OUTSIDE:
        return OUTSIDE
    if az <= z_top:
        # the squared-distance bound is one of the unsigned distance: the march certifies that
        # the axis never meets the boundary, so it stays on the side of its start; whether the
        # start is in F is decided exactly (the curve at its height, Eq. 10-11)
        d0 = point_d_safe(rho, slice_z, 0.0, ax, ay, az, 0.0)
        if not d0 > 0.0:
            return min(d0, 0.0)
    m = min(b_prev, cap)
    if length <= 0.0 or m < stop:
        return m
    ux = dx / length
    uy = dy / length
    uz = dz / length
    s = 0.0
    while s < length:
        t = max(step, b_prev - min(m, level))
        if s + t > length:
            t = length - s
        s += t
        x, y, z = ax + s * ux, ay + s * uy, az + s * uz
        b = _point_bound(V, ox, oy, oz, g, z_top, x, y, z, _COARSE)
        if 0.5 * (b_prev + b - t) < m or b < m:  # this sample may lower the minimum: refine
            b = _point_bound(V, ox, oy, oz, g, z_top, x, y, z, _REFINE)
        if b <= OUTSIDE:  # outside the model's box below the opening: a collision, stop
            return OUTSIDE
        lo = 0.5 * (b_prev + b - t)
        if lo < m:
            m = lo
        if b < m:
            m = b
        if m < stop:
            return m
        b_prev = b
    return m


@numba.njit(cache=True, parallel=True)
def _capsules_kernel(V, ox, oy, oz, g, z_top, cap, step, resolve, rho, slice_z, A, B, r, out,
                     verdict=-np.inf):
    """out[k] = the capsules' certified clearances; with a finite ``verdict`` the march of a
    capsule stops as soon as its clearance is certain to be <= verdict (out[k] is then only
    known to be <= verdict: the verdict-only path)."""
    for k in numba.prange(A.shape[0]):
        out[k] = (
            _segment_min(
                V, ox, oy, oz, g, z_top, cap, step, rho, slice_z, r[k] + resolve,
                A[k, 0], A[k, 1], A[k, 2], B[k, 0], B[k, 1], B[k, 2], r[k] + verdict,
            )
            - r[k]
        )


@numba.njit(cache=True)
def tool_clearance_at(V, ox, oy, oz, g, z_top, cap, step, resolve, rho, slice_z, X, a, b, r):
    """The tool's clearance at one pose X ((4, 4) or (3, 4), Tool in Center): the smallest of
    its capsules' (a, b (C, 3) in T, radii r (C,))."""
    best = np.inf
    for c in range(a.shape[0]):
        px = X[0, 3] + X[0, 0] * a[c, 0] + X[0, 1] * a[c, 1] + X[0, 2] * a[c, 2]
        py = X[1, 3] + X[1, 0] * a[c, 0] + X[1, 1] * a[c, 1] + X[1, 2] * a[c, 2]
        pz = X[2, 3] + X[2, 0] * a[c, 0] + X[2, 1] * a[c, 1] + X[2, 2] * a[c, 2]
        qx = X[0, 3] + X[0, 0] * b[c, 0] + X[0, 1] * b[c, 1] + X[0, 2] * b[c, 2]
        qy = X[1, 3] + X[1, 0] * b[c, 0] + X[1, 1] * b[c, 1] + X[1, 2] * b[c, 2]
        qz = X[2, 3] + X[2, 0] * b[c, 0] + X[2, 1] * b[c, 1] + X[2, 2] * b[c, 2]
        v = (
            _segment_min(
                V, ox, oy, oz, g, z_top, cap, step, rho, slice_z, r[c] + resolve, px, py, pz,
                qx, qy, qz,
            )
            - r[c]
        )
        if v < best:
            best = v
    return best


@numba.njit(cache=True)
def fpsm_at(args, X) -> float:
    """:func:`tool_clearance_at` at one pose X with ``args`` = :attr:`ToolClearance.at_args`
    (the loops' hook: the supervisor's slow path takes it as a compiled function)."""
    field, a, b, r = args
    return tool_clearance_at(*field, X, a, b, r)


@numba.njit(cache=True)
def _tool_kernel(V, ox, oy, oz, g, z_top, cap, step, resolve, rho, slice_z, X, a, b, r, out):
    """out[k] = min over the tool's capsules (a, b (C, 3) in T, radii r (C,)) at pose X[k]."""
    for k in range(X.shape[0]):
        out[k] = tool_clearance_at(V, ox, oy, oz, g, z_top, cap, step, resolve, rho, slice_z,
                                   X[k], a, b, r)


# -- public API --------------------------------------------------------------------------------


MAX_COORDINATE = 1.0e3  # m: any real point in Center is within a metre; beyond this the grid
# indices of the compiled kernels would overflow, so such input is an error, not a verdict


def _points(value, name: str) -> np.ndarray:
    try:
        p = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(name, "expected numbers (m)") from None
    if p.ndim not in (1, 2) or p.shape[-1:] != (3,) or not np.all(np.isfinite(p)):
        raise InputError(name, f"expected finite (n, 3) or (3,) points (m), got shape {p.shape}")
    if p.size and np.abs(p).max() > MAX_COORDINATE:
        raise InputError(name, f"expected points within {MAX_COORDINATE:g} m of the Center "
                         f"origin, got a coordinate of {np.abs(p).max():.3g} m")
    return p


MAX_FEED = 0.2  # longest feed (m) checked when the rod axis does not rise out of the mouth
RESOLVE = 0.005  # clearances up to this (m) are resolved to the step; larger ones: >= about it


def _field_args(field: ClearanceField, step: float | None, fpsm: Fpsm):
    o = field.origin
    st = field.spacing / 2 if step is None else float(step)
    if not np.isfinite(st) or st <= 0:
        raise InputError("step", f"expected a positive step (m), got {step}")
    return (field.values, float(o[0]), float(o[1]), float(o[2]), field.spacing, field.z_top,
            field.cap, st, RESOLVE, np.ascontiguousarray(fpsm.rho, dtype=float),
            np.ascontiguousarray(fpsm.slice_z, dtype=float))


def rod_clearance(
    fpsm: Fpsm, p0, p1, radius, *, method: str = "sound", step: float | None = None
) -> np.ndarray:
    """Clearance (m) of capsules (axis p0-p1, ``radius``) to the FPSM boundary, batched.

    Args:
        fpsm: the model (Center frame).
        p0, p1: (n, 3) or (3,) axis end points in Center (m); a long segment out of the mouth
            stands for a ray.
        radius: scalar or (n,) capsule radii (m), >= 0.
        method: ``"sound"`` (default): a certified lower bound of the distance (> 0: the
            capsule is free by at least that much; module notes); ``"paper"``: Eq. 12, the
            smallest safe distance of the axis against the model shrunk by r at the slice
            crossings and the end points (not a bound; for comparison).
        step: axis sampling step near the wall for ``sound`` (m), default half the grid
            spacing (each step costs at most half of it in the bound; a quarter cuts the
            rejected free rods by about a third at twice the cost).

    Returns:
        (n,) clearances (a (1,) array for a single capsule).
    """
    if method not in METHODS:
        raise InputError("method", f"expected one of {METHODS}, got {method!r}")
    A, B, r = _capsule_batch(p0, p1, radius)
    if method == "paper":
        d = B - A
        L = np.linalg.norm(d, axis=1)
        u = np.where(L[:, None] > 0, d / np.where(L > 0, L, 1.0)[:, None], [0.0, 0.0, 1.0])
        ls = fpsm.line_safety_batch(A, u, np.maximum(L, 1e-12), np.ascontiguousarray(r))
        out = ls.d_safe_min
        return out
    out = np.empty(A.shape[0])
    _capsules_kernel(*_field_args(clearance_field(fpsm), step, fpsm), A, B, r, out)
    return out


def rod_safe(fpsm: Fpsm, p0, p1, radius, *, clearance: float = 0.0,
             step: float | None = None) -> np.ndarray:
    """The verdict only: (n,) True where the sound clearance of :func:`rod_clearance` is above
    ``clearance`` (m), the same verdict as ``rod_clearance(...) > clearance``, faster: a
    capsule's march stops as soon as its bound is certain to be at or below ``clearance``."""
    A, B, r = _capsule_batch(p0, p1, radius)
    clearance = float(clearance)
    if not np.isfinite(clearance):
        raise InputError("clearance", f"expected a finite clearance (m), got {clearance}")
    out = np.empty(A.shape[0])
    _capsules_kernel(*_field_args(clearance_field(fpsm), step, fpsm), A, B, r, out, clearance)
    return out > clearance


def _capsule_batch(p0, p1, radius):
    """Checked, contiguous (n, 3) starts and ends and (n,) radii (m) of a batch of capsules."""
    A = np.atleast_2d(_points(p0, "p0"))
    B = np.atleast_2d(_points(p1, "p1"))
    try:
        A, B = np.broadcast_arrays(A, B)
    except ValueError:
        raise InputError("p1", f"expected as many end points as p0 ({A.shape[0]}) or one, got "
                         f"{B.shape[0]}") from None
    try:
        r = np.broadcast_to(np.asarray(radius, dtype=float), (A.shape[0],))
    except (TypeError, ValueError):
        raise InputError("radius", f"expected a radius (m) or one per capsule ({A.shape[0]}), "
                         f"got {radius!r}") from None
    if not np.all(np.isfinite(r)) or np.any(r < 0):
        raise InputError("radius", "expected radii >= 0 m")
    return np.ascontiguousarray(A), np.ascontiguousarray(B), np.ascontiguousarray(r)


def tool_capsules(X_CT: np.ndarray, tool: Instrument):
    a, b, r = tool.capsules_T()
    R, p = X_CT[:, :3, :3], X_CT[:, :3, 3]
    A = np.einsum("kij,cj->kci", R, a) + p[:, None, :]
    B = np.einsum("kij,cj->kci", R, b) + p[:, None, :]
    return A, B, r


def rigid_poses(X, name: str = "X_CTool") -> np.ndarray:
    """Rigid poses only: a scaled or sheared "pose" would shrink the tool and pass as safe."""
    X = validate.pose(X, name, batch=True).reshape(-1, 4, 4)
    if X.size and np.abs(X[:, :3, 3]).max() > MAX_COORDINATE:
        raise InputError(name, f"expected tool positions within {MAX_COORDINATE:g} m of the "
                         "Center origin")
    return X


@numba.njit(cache=True)
def is_rigid_pose(X) -> bool:
    """True when :func:`rigid_poses` accepts the one pose X (4, 4) (C-contiguous): the same test
    (finite, a proper rotation and the last row [0, 0, 0, 1] within ``validate.ROTATION_TOL``,
    the position within ``MAX_COORDINATE``), compiled for the control loops; they call
    :func:`rigid_poses` for its error when it is False."""
    err, finite = validate.rotation_error(X.reshape((1, 4, 4)))
    if not finite or err > validate.ROTATION_TOL:
        return False
    for j in range(4):
        if abs(X[3, j] - (1.0 if j == 3 else 0.0)) > validate.ROTATION_TOL:
            return False
    for i in range(3):
        if abs(X[i, 3]) > MAX_COORDINATE:
            return False
    return True


def tool_clearance(
    fpsm: Fpsm,
    X_CTool,
    tool: Instrument | None = None,
    *,
    method: str = "sound",
    step: float | None = None,
) -> np.ndarray:
    """Clearance (m) of the whole tool body (rod, head, implant) at poses of the Tool frame in
    Center, the smallest of its three capsules' (:func:`rod_clearance`).

    Args:
        X_CTool: (n, 4, 4) or (4, 4) poses of T in Center.
        tool: the geometry (default :class:`Instrument`).
        method: ``"sound"`` (default, certified lower bound) or ``"paper"`` (Eq. 12).

    Returns:
        (n,) signed clearance (> 0 free; for ``sound`` a certified lower bound).
    """
    tool = tool or Instrument.paper()
    X = rigid_poses(X_CTool)
    A, B, r = tool_capsules(X, tool)
    if method == "paper":
        K = X.shape[0]
        out = rod_clearance(
            fpsm, A.reshape(-1, 3), B.reshape(-1, 3), np.tile(r, K), method="paper"
        )
        return out.reshape(K, -1).min(axis=1)
    if method not in METHODS:
        raise InputError("method", f"expected one of {METHODS}, got {method!r}")
    return ToolClearance(fpsm, tool, step=step)(X)


class ToolClearance:
    """:func:`tool_clearance` for one model and tool with the per-call overhead cut down to the
    compiled kernel: the path for the 200 Hz / 1 kHz loops.

    ``ToolClearance(fpsm, tool)(X_CTool)`` -> (n,) certified clearances (m) for (n, 4, 4) or
    (4, 4) poses of T in Center; :meth:`one` takes one (4, 4) pose (no checks) -> float;
    ``at(at_args, X)`` is the compiled one-pose hook (as
    :class:`systems.placement.scan_clearance.CappedScanClearance`'s).
    """

    def __init__(self, fpsm: Fpsm, tool: Instrument | None = None, *, step=None):
        self.fpsm = fpsm
        self.tool = tool or Instrument.paper()
        self.field = clearance_field(fpsm)
        self._args = _field_args(self.field, step, fpsm)
        a, b, r = self.tool.capsules_T()
        self._a, self._b, self._r = a, b, np.ascontiguousarray(r, dtype=float)
        self.at, self.at_args = fpsm_at, (self._args, self._a, self._b, self._r)
        self.instrument = self.tool

    def __call__(self, X_CTool) -> np.ndarray:
        X = np.ascontiguousarray(rigid_poses(X_CTool))
        out = np.empty(X.shape[0])
        _tool_kernel(*self._args, X, self._a, self._b, self._r, out)
        return out

    def one(self, X_CTool: np.ndarray) -> float:
        """Clearance (m) at one (4, 4) pose, without input checks."""
        return tool_clearance_at(*self._args, np.ascontiguousarray(X_CTool, dtype=float), self._a,
                         self._b, self._r)


def feed_poses(X_CTool, depth: float, step: float) -> tuple[np.ndarray, float]:
    """Poses of the tool backed out along its rod axis (Tool +x) by 0..``depth`` (m) in steps
    of at most ``step``: (n, S, 4, 4) and the actual spacing (m)."""
    X = rigid_poses(X_CTool)
    depth, step = float(depth), float(step)
    if not np.isfinite(depth) or depth < 0:
        raise InputError("depth", f"expected a feed depth >= 0 m, got {depth}")
    if not np.isfinite(step) or step <= 0:
        raise InputError("step", f"expected a positive step (m), got {step}")
    S = max(int(np.ceil(depth / step)), 1) + 1
    s = np.linspace(0.0, depth, S)
    P = np.repeat(X[:, None], S, axis=1).copy()
    P[..., :3, 3] += s[None, :, None] * X[:, None, :3, 0]
    return P, (depth / (S - 1) if S > 1 else 0.0)


def feed_depth(fpsm: Fpsm, X_CTool, tool: Instrument) -> float:
    """How far (m) the tools at poses X must back out along their rod axis (Tool +x) until the
    tool origin is above the mouth opening by the head and the implant length (the largest over
    the poses; MAX_FEED when an axis does not rise out of the mouth)."""
    X = rigid_poses(X_CTool)
    need = fpsm.z_range[1] + tool.head + tool.implant_length - X[:, 2, 3]
    rise = X[:, 2, 0]  # Center z of the rod axis: the feed direction out of the mouth
    with np.errstate(divide="ignore", invalid="ignore"):
        s_out = np.where(need <= 0, 0.0, need / np.where(rise > 1e-6, rise, np.nan))
    depth = float(np.nanmax(np.where(np.isnan(s_out), MAX_FEED, s_out), initial=0.0))
    return min(depth, MAX_FEED)


def _turn_axes(directions: int) -> np.ndarray:
    """Unit rotation axes (Tool) sampling the fixture's turns: ``directions`` in the y-z plane
    (tilts of the rod), +-x (roll about the rod) and the 8 cube diagonals."""
    a = np.arange(directions) * (2 * np.pi / directions)
    ring = np.column_stack([np.zeros(directions), np.cos(a), np.sin(a)])
    diag = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
    return np.concatenate([ring, [[1.0, 0, 0], [-1.0, 0, 0]], diag / np.sqrt(3.0)])


def admissible_poses(X_CTool, lateral: float, angle: float, *, directions: int = 8) -> np.ndarray:
    """Sample poses of the fixture's admissible region about planned poses (n, 4, 4) or (4, 4):
    every combination of the tool origin moved by ``lateral`` across the rod axis (none, or one
    of ``directions`` directions in Tool y-z) and the pose turned by ``angle`` at its origin
    (none, or about one of :func:`_turn_axes`: tilts, roll and diagonals), the region being
    both at once: (n, (1 + directions) (11 + directions), 4, 4), each planned pose first. For
    the exact (FCL) check: every sample is in the region, so FCL's minimum over them bounds the
    region's from above (along a feed, sample about each feed pose: a turned pose fed along its
    own axis would leave the region); the certified bounds cover the whole region without
    sampling."""
    X = rigid_poses(X_CTool)
    R, p = X[:, :3, :3], X[:, :3, 3]
    a = np.arange(directions) * (2 * np.pi / directions)
    shift = lateral * np.column_stack([np.zeros(directions + 1),
                                       np.concatenate([[0.0], np.cos(a)]),
                                       np.concatenate([[0.0], np.sin(a)])])  # (m, 3) in Tool
    axes = np.concatenate([np.zeros((1, 3)), _turn_axes(directions)])
    turn = rotations(angle * axes)  # (t, 3, 3) in Tool
    m, t = len(shift), len(turn)
    out = np.repeat(X[:, None], m * t, axis=1)
    out[:, :, :3, :3] = np.einsum("nij,tjk->ntik", R, np.repeat(turn, m, axis=0))
    out[:, :, :3, 3] = p[:, None] + np.einsum("nij,tj->nti", R, np.tile(shift, (t, 1)))
    return out


def fixture_admits(samples, planned, z_top: float, lateral: float) -> np.ndarray:
    """(n, M) whether the fixture admits each sample (n, M, 4, 4) of the region about planned
    poses (n, 4, 4) on line1 (the planned rod axis): besides the TCP, the fixture holds the rod
    axis where it crosses the mouth opening (z = ``z_top``) within ``lateral`` of line1 while
    the TCP is below it (systems.placement.fixture). A turn at the TCP on top of the full
    lateral offset can move that point farther (the turn times the TCP's depth along the rod):
    such a sample is outside the fixture's region."""
    S = np.asarray(samples, dtype=float)
    X = rigid_poses(planned)
    p, x = S[..., :3, 3], S[..., :3, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(x[..., 2] > 1e-9, (z_top - p[..., 2]) / x[..., 2], 0.0)
    s = np.maximum(s, 0.0)  # a TCP above the opening: only the TCP is held
    e = p + s[..., None] * x - X[:, None, :3, 3]
    x0 = X[:, None, :3, 0]
    off = np.linalg.norm(e - np.sum(e * x0, axis=-1, keepdims=True) * x0, axis=-1)
    return off <= lateral * (1 + 1e-9) + 1e-12


def random_region_poses(feed, lateral: float, angle: float, n: int,
                        rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) uniform random poses of the fixture's region about a feed (S, 4, 4) poses
    along the rod: a feed pose drawn at random and moved along the rod by up to half the
    feed's spacing, the TCP moved uniformly in the disc of ``lateral`` across the rod and the
    frame turned uniformly in the ball of ``angle`` at the TCP (the region of
    :func:`systems.placement.scan_clearance.region_branch_and_bound`; the in-mouth rod axis may
    leave the lateral disc at these samples, which the fixture does not allow). For independent
    checks of the certified region against FCL."""
    feed = rigid_poses(feed)
    S = feed.shape[0]
    half = 0.5 * np.linalg.norm(feed[1, :3, 3] - feed[0, :3, 3]) if S > 1 else 0.0
    r, a = lateral * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
    shift = np.c_[rng.uniform(-half, half, n), r * np.cos(a), r * np.sin(a)]
    w = rng.normal(size=(n, 3))
    w *= (angle * np.cbrt(rng.uniform(0, 1, n)) / np.linalg.norm(w, axis=1))[:, None]
    return moved_poses(feed[rng.integers(0, S, n)], shift, w)


def moved_poses(X0: np.ndarray, shift: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(n, 4, 4) poses X0 (n, 4, 4) with the TCP moved by R0 ``shift`` (n, 3) (Tool: x along
    the rod, y-z across it) and the frame turned by exp(``w``) (n, 3) at the TCP: a pose of the
    fixture's region about X0."""
    out = X0.copy()
    out[:, :3, :3] = X0[:, :3, :3] @ rotations(w)
    out[:, :3, 3] = X0[:, :3, 3] + np.einsum("nij,nj->ni", X0[:, :3, :3], shift)
    return out


def feed_clearance(
    fpsm: Fpsm,
    X_CTool,
    tool: Instrument | None = None,
    *,
    depth: float | None = None,
    step: float = 0.001,
    lateral: float = 0.0,
    angle: float = 0.0,
) -> np.ndarray:
    """Certified clearance (m) of the tool over its whole feed and admissible region, batched.

    The feed moves the tool along its rod axis from outside the mouth to the target pose; the
    poses are the target backed out by s in [0, depth] (default: until the head is above the
    mouth opening). Clearance is 1-Lipschitz in s (a translation moves every point by |ds|), so
    sampled poses c_i at spacing t give min over the feed >= min_i (c_i + c_{i+1} - t) / 2.

    The admissible region of the fixture: the tool axis within ``lateral`` (m) of the
    planned line and its orientation within ``angle`` (rad) of the planned one, at every depth.
    Every body point then lies within ``lateral + angle * reach`` of its planned position, with
    reach its distance from the rod axis (0 on the rod, the head radius, the implant length), so
    each capsule's clearance drops by at most that (rigorous, no sampling needed).

    Returns:
        (n,) the certified minimum over the region (m).
    """
    tool = tool or Instrument.paper()
    X = rigid_poses(X_CTool)
    for name, value in (("lateral", lateral), ("angle", angle)):
        if not np.isfinite(value) or value < 0:
            raise InputError(name, f"expected a tolerance >= 0, got {value}")
    if depth is None:
        depth = feed_depth(fpsm, X, tool)
    P, t = feed_poses(X, depth, step)
    n, S = P.shape[:2]
    A, B, r = tool_capsules(P.reshape(-1, 4, 4), tool)
    field = clearance_field(fpsm)
    C = A.shape[1]
    vals = np.empty(n * S * C)
    _capsules_kernel(*_field_args(field, None, fpsm), np.ascontiguousarray(A.reshape(-1, 3)),
                     np.ascontiguousarray(B.reshape(-1, 3)), np.tile(r, n * S), vals)
    vals = vals.reshape(n, S, C)
    loss = lateral + angle * tool.reach_T()
    vals = vals - loss[None, None, :]
    c = vals.min(axis=2)
    if S > 1:
        inter = 0.5 * (c[:, :-1] + c[:, 1:] - t)
        return np.minimum(c.min(axis=1), inter.min(axis=1))
    return c[:, 0]
