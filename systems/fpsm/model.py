"""Finite-parameter surrogate model (FPSM) of the oral cavity (seed 000, Wang et al. 2023).

The curve of one slice (Eq. 1-5): N control radii rho_1..rho_N at theta_k = 2*pi*k/N
(k = 0..N-1 here, zero-based); on each segment a cubic that takes the control values at its ends
and the central-difference slope v_k = N*(rho_{k+1} - rho_{k-1})/(4*pi) (Eq. 2) at each knot.
That is a periodic cubic Hermite (Catmull-Rom) spline, so rho(theta) is *linear* in the control
radii: rho(theta) = B(theta) . rho, with at most four non-zero weights per angle. We evaluate it
through those weights instead of solving Eq. 3 each time (tests check both give the same curve).

With h = 2*pi/N and t = (theta - theta_k)/h on segment k, the Hermite form gives
    rho = h00 rho_k + h01 rho_{k+1} + h10 (rho_{k+1} - rho_{k-1})/2 + h11 (rho_{k+2} - rho_k)/2,
so the weights on (rho_{k-1}, rho_k, rho_{k+1}, rho_{k+2}) are
    (-h10/2, h00 - h11/2, h01 + h10/2, h11/2).

The area (Eq. 6) S = 1/2 int rho^2 dtheta is then the quadratic form S = 1/2 rho^T Q rho with the
constant circulant Q = int B(theta)^T B(theta) dtheta, computed exactly (:func:`area_matrix`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from implantplan.systems import validate
from implantplan.systems.errors import InputError
from implantplan.systems.files import read_json, write_json
from implantplan.systems.jit import kernel_array, numba

TWO_PI = 2.0 * np.pi

# Catmull-Rom weights on (rho_{k-1}, rho_k, rho_{k+1}, rho_{k+2}) as cubics in t, rows = weight,
# columns = coefficients of (1, t, t^2, t^3). From h00 = 1 - 3t^2 + 2t^3, h10 = t - 2t^2 + t^3,
# h01 = 3t^2 - 2t^3, h11 = -t^2 + t^3.
SPLINE_BASIS = np.array(
    [
        [0.0, -0.5, 1.0, -0.5],
        [1.0, 0.0, -2.5, 1.5],
        [0.0, 0.5, 2.0, -1.5],
        [0.0, 0.0, -0.5, 0.5],
    ]
)


def _check_n(n: int) -> int:
    n = int(n)
    if n < 3:
        raise ValueError(f"control_points: expected at least 3, got {n}")
    return n


def basis_weights(theta, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Non-zero basis weights of rho(theta) for N = ``n`` control radii.

    Args:
        theta: angles (rad), any shape; wrapped into [0, 2*pi).
        n: number of control radii N (>= 3).

    Returns:
        ``(index, weight)``, both of shape ``theta.shape + (4,)``: rho(theta) =
        sum(weight * rho[..., index]). Indices are in 0..n-1 (periodic).
    """
    n = _check_n(n)
    theta = np.asarray(theta, dtype=float)
    u = np.mod(theta, TWO_PI) * (n / TWO_PI)
    k = np.floor(u).astype(np.int64)
    k = np.minimum(k, n - 1)  # u can round up to exactly n
    t = u - k
    powers = np.stack([np.ones_like(t), t, t * t, t * t * t], axis=-1)
    weight = powers @ SPLINE_BASIS.T
    index = np.mod(k[..., None] + np.arange(-1, 3), n)
    return index, weight


def basis_matrix(theta, n: int) -> np.ndarray:
    """Dense basis B (len(theta), n) with rho(theta) = B @ rho for 1-D ``theta``."""
    theta = np.atleast_1d(np.asarray(theta, dtype=float))
    index, weight = basis_weights(theta, n)
    B = np.zeros((theta.size, n))
    rows = np.repeat(np.arange(theta.size), 4)
    np.add.at(B, (rows, index.reshape(-1)), weight.reshape(-1))
    return B


def evaluate(rho, theta) -> np.ndarray:
    """rho(theta) for control radii ``rho`` (..., N) at angles ``theta`` broadcastable to (...).

    The leading dimensions of ``rho`` and ``theta`` broadcast: one curve at many angles is
    ``evaluate(rho[None, :], theta)``; many curves each at its own angle is
    ``evaluate(rho_batch, theta_batch)``.
    """
    rho = np.asarray(rho, dtype=float)
    index, weight = basis_weights(theta, rho.shape[-1])
    shape = np.broadcast_shapes(rho.shape[:-1], index.shape[:-1])
    rho_b = np.broadcast_to(rho, shape + rho.shape[-1:])
    index = np.broadcast_to(index, shape + (4,))
    weight = np.broadcast_to(weight, shape + (4,))
    return np.sum(np.take_along_axis(rho_b, index, axis=-1) * weight, axis=-1)


def derivative(rho, theta) -> np.ndarray:
    """d rho / d theta, same broadcasting as :func:`evaluate`."""
    rho = np.asarray(rho, dtype=float)
    n = rho.shape[-1]
    theta = np.asarray(theta, dtype=float)
    u = np.mod(theta, TWO_PI) * (n / TWO_PI)
    k = np.minimum(np.floor(u).astype(np.int64), n - 1)
    t = u - k
    dpowers = np.stack([np.zeros_like(t), np.ones_like(t), 2 * t, 3 * t * t], axis=-1)
    weight = (dpowers @ SPLINE_BASIS.T) * (n / TWO_PI)
    index = np.mod(k[..., None] + np.arange(-1, 3), n)
    shape = np.broadcast_shapes(rho.shape[:-1], index.shape[:-1])
    rho_b = np.broadcast_to(rho, shape + (n,))
    return np.sum(
        np.take_along_axis(rho_b, np.broadcast_to(index, shape + (4,)), axis=-1)
        * np.broadcast_to(weight, shape + (4,)),
        axis=-1,
    )


@lru_cache(maxsize=64)
def _area_matrix_cached(n: int) -> np.ndarray:
    # Exact Gram matrix of the four local weights over t in [0, 1]:
    # G[a, b] = int_0^1 w_a(t) w_b(t) dt, with w_a(t) = sum_i SPLINE_BASIS[a, i] t^i.
    moments = 1.0 / (np.add.outer(np.arange(4), np.arange(4)) + 1.0)  # int t^(i+j) dt
    G = SPLINE_BASIS @ moments @ SPLINE_BASIS.T
    h = TWO_PI / n
    Q = np.zeros((n, n))
    for k in range(n):
        idx = np.mod(k + np.arange(-1, 3), n)
        np.add.at(Q, (idx[:, None], idx[None, :]), h * G)  # indices repeat when n == 3
    Q.setflags(write=False)
    return Q


def area_matrix(n: int) -> np.ndarray:
    """Constant circulant Q (n, n) with int_0^{2 pi} rho^2 dtheta = rho^T Q rho (exact)."""
    return _area_matrix_cached(_check_n(n))


def area(rho) -> np.ndarray:
    """Area enclosed by the curve (Eq. 6), S = 1/2 rho^T Q rho, batched over leading dims."""
    rho = np.asarray(rho, dtype=float)
    Q = area_matrix(rho.shape[-1])
    return 0.5 * np.einsum("...i,ij,...j->...", rho, Q, rho)


# ---------------------------------------------------------------------------------------------
# The surrogate model: M slices of such curves stacked along the Center frame's z axis.
# ---------------------------------------------------------------------------------------------


def _slice_values(rho: np.ndarray, slice_index: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """rho_j(theta) for per-point slice indices j (any shape, same as ``theta``).

    The same Catmull-Rom weights as :func:`basis_weights`, written out (four gathers from the
    flat radii, no stacking) because this is the hot path of every safety query."""
    n = rho.shape[1]
    u = np.mod(theta, TWO_PI) * (n / TWO_PI)
    k = np.minimum(u.astype(np.int64), n - 1)  # u >= 0, so truncation is floor
    t = u - k
    t2 = t * t
    t3 = t2 * t
    base = slice_index * n
    flat = rho.reshape(-1)
    km1 = np.where(k == 0, n - 1, k - 1)
    k1 = np.where(k == n - 1, 0, k + 1)
    k2 = np.where(k1 == n - 1, 0, k1 + 1)
    return (
        flat[base + km1] * (-0.5 * t + t2 - 0.5 * t3)
        + flat[base + k] * (1.0 - 2.5 * t2 + 1.5 * t3)
        + flat[base + k1] * (0.5 * t + 2.0 * t2 - 1.5 * t3)
        + flat[base + k2] * (0.5 * t3 - 0.5 * t2)
    )


@numba.njit(cache=True)
def _rho_on_slice(rho, j, theta):
    """rho_j(theta), the Catmull-Rom weights of :func:`basis_weights` for one angle."""
    n = rho.shape[1]
    u = (theta % TWO_PI) * (n / TWO_PI)
    k = min(int(u), n - 1)
    t = u - k
    t2 = t * t
    t3 = t2 * t
    km1 = n - 1 if k == 0 else k - 1
    k1 = 0 if k == n - 1 else k + 1
    k2 = 0 if k1 == n - 1 else k1 + 1
    return (
        rho[j, km1] * (-0.5 * t + t2 - 0.5 * t3)
        + rho[j, k] * (1.0 - 2.5 * t2 + 1.5 * t3)
        + rho[j, k1] * (0.5 * t + 2.0 * t2 - 1.5 * t3)
        + rho[j, k2] * (0.5 * t3 - 0.5 * t2)
    )


@numba.njit(cache=True)
def point_d_safe(rho, slice_z, shrink, x, y, z, r):
    """Eq. 10-11 with the throat rule for one point inside or below the slices."""
    m = slice_z.size
    theta = np.arctan2(y + 0.0, x + 0.0)  # + 0.0 turns -0.0 into 0.0: angle 0 on the axis
    if m == 1:
        radius = _rho_on_slice(rho, np.int64(0), theta)  # an int64, not the literal 0
    else:
        j = np.searchsorted(slice_z, z, side="right") - 1
        j = min(max(j, 0), m - 2)
        w = (z - slice_z[j]) / (slice_z[j + 1] - slice_z[j])
        w = min(max(w, 0.0), 1.0)
        lo = _rho_on_slice(rho, j, theta)
        hi = _rho_on_slice(rho, j + 1, theta)
        radius = lo + w * (hi - lo)
    d = radius - r - np.hypot(x, y)
    if z < slice_z[0]:
        d = min(d, z - slice_z[0] - r - shrink)
    return d


@numba.njit(cache=True)
def line_kernel(
    p0, u, L, radius, rho, slice_z, shrink, R, lambda_avg, lambda_min, f, d_min, mean, count
):
    """Eq. 13 for K lines; the sampling rules of :meth:`Fpsm.line_safety`, one line at a time."""
    m = slice_z.size
    z_lo = slice_z[0]
    z_hi = slice_z[m - 1]
    tol = 1e-12
    for k in range(p0.shape[0]):
        x0, y0, z0 = p0[k, 0], p0[k, 1], p0[k, 2]
        ux, uy, uz = u[k, 0], u[k, 1], u[k, 2]
        r = radius[k]
        length = L[k]
        finite = np.isfinite(length)
        a = ux * ux + uy * uy
        b = x0 * ux + y0 * uy
        c = x0 * x0 + y0 * y0 - R * R
        s_cyl = (-b + np.sqrt(max(b * b - a * c, 0.0))) / a if a > 1e-30 else np.inf
        s_down = (z_lo - R - z0) / uz if uz < -1e-15 else np.inf
        s_top = (z_hi - z0) / uz if uz > 1e-15 else np.inf
        s_side = max(min(s_cyl, s_down), 0.0)
        leaves = (not finite) and s_side < s_top
        if leaves:
            length = s_side
        total = 0.0
        n = 0
        lowest = np.inf
        on_plane = False
        if abs(uz) > 1e-15:
            for j in range(m):
                s = (slice_z[j] - z0) / uz
                if s > tol and s <= length + tol:
                    if abs(s - length) <= tol:
                        on_plane = True
                    x = x0 + s * ux
                    y = y0 + s * uy
                    d = _rho_on_slice(rho, j, np.arctan2(y + 0.0, x + 0.0)) - r - np.hypot(x, y)
                    total += d
                    n += 1
                    lowest = min(lowest, d)
        if z0 <= z_hi:  # the start point T (above the opening it does not count)
            d = point_d_safe(rho, slice_z, shrink, x0, y0, z0, r)
            total += d
            n += 1
            lowest = min(lowest, d)
        if (finite or leaves) and not on_plane:
            x = x0 + length * ux
            y = y0 + length * uy
            z = z0 + length * uz
            if z <= z_hi:
                d = point_d_safe(rho, slice_z, shrink, x, y, z, r)
                if leaves:
                    d = min(d, 0.0)
                total += d
                n += 1
                lowest = min(lowest, d)
        count[k] = n
        d_min[k] = lowest
        if n == 0:
            mean[k] = np.inf
            f[k] = np.inf
        else:
            mean[k] = total / n
            if lowest > 0:  # Eq. 13
                f[k] = lambda_avg * mean[k] + lambda_min * lowest
            else:
                f[k] = lambda_min * lowest


@dataclass(frozen=True)
class LineSafety:
    """Safety of K lines/rods against the FPSM (Eq. 13), one entry per line.

    Attributes:
        f_safe: (K,) safety indicator of Eq. 13 (> 0: collision-free); +inf for a line with no
            sample inside the model (it lies wholly above the mouth opening).
        d_safe_min: (K,) smallest safe distance over the samples (m), +inf when no sample.
        d_safe_mean: (K,) mean safe distance over the samples (m), +inf when no sample.
        samples: (K,) number of samples: the m slice-plane crossings + the start point T (+ the
            far end, see :meth:`Fpsm.line_safety`); this is the paper's m + 1.
    """

    f_safe: np.ndarray
    d_safe_min: np.ndarray
    d_safe_mean: np.ndarray
    samples: np.ndarray


def _as_array(value, field: str, shape_tail: tuple[int, ...] | None = None) -> np.ndarray:
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(field, "expected numbers") from None
    if shape_tail is not None and arr.shape[arr.ndim - len(shape_tail) :] != shape_tail:
        raise InputError(
            field, f"expected shape (..., {', '.join(map(str, shape_tail))}), got {arr.shape}"
        )
    return arr


@dataclass
class Fpsm:
    """Finite-parameter surrogate model of the oral cavity (paper Sec. 3).

    M closed polar curves (slices) at heights ``slice_z`` along the z axis of the Center frame,
    each with N control radii (row of ``rho``). The +Z end is the mouth opening.

    Safe distance of a point P (Eq. 10-11): d_safe = rho(theta_P, z_P) - sqrt(x_P^2 + y_P^2),
    with rho linear in z between neighbouring slices (Eq. 11 interpolates the two projections'
    d_safe, whose radial parts are equal, so it is the radius that is interpolated). Outside the
    slice range (a rule the paper leaves open, DESIGN.md section 4):

    - below the bottom slice (throat side): collision, d_safe = min(d_safe on the bottom slice,
      z_P - z_0 - shrink) < 0, so it grows more negative the deeper the point is;
    - above the top slice (outside the mouth opening): no constraint, d_safe = +inf.

    A shrunk model (Eq. 12, :meth:`shrink`) may have radii <= 0 where the cavity is narrower than
    the rod; it records the amount in ``settings["shrink_m"]`` and validation checks that the
    unshrunk radii ``rho + shrink_m`` are positive.

    Attributes:
        slice_z: (M,) strictly increasing slice heights along Center z (m).
        rho: (M, N) control radii per slice (m), at angles 2*pi*k/N.
        X_WC: (4, 4) pose of the Center frame in the mesh's frame (m).
        settings: fit settings (method, N, samples, mesh path, units, margin, ...).
        diagnostics: fit diagnostics (per-slice coverage, penetration, time, ...).
    """

    slice_z: np.ndarray
    rho: np.ndarray
    X_WC: np.ndarray = field(default_factory=lambda: np.eye(4))
    settings: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)

    def __post_init__(self):
        z = _as_array(self.slice_z, "slice_z")
        rho = _as_array(self.rho, "rho")
        X = _as_array(self.X_WC, "X_WC")
        if z.ndim != 1 or z.size < 1:
            raise InputError("slice_z", f"expected a 1-D array of slice heights, got {z.shape}")
        if not np.all(np.isfinite(z)):
            raise InputError("slice_z", "expected finite heights")
        if np.any(np.diff(z) <= 0):
            raise InputError("slice_z", "expected strictly increasing heights")
        if rho.ndim != 2 or rho.shape[0] != z.size or rho.shape[1] < 3:
            raise InputError(
                "rho", f"expected shape (M={z.size}, N>=3) control radii, got {rho.shape}"
            )
        if not np.all(np.isfinite(rho)):
            raise InputError("rho", "expected finite radii")
        if not isinstance(self.settings, dict):
            raise InputError("settings", "expected a mapping")
        if not isinstance(self.diagnostics, dict):
            raise InputError("diagnostics", "expected a mapping")
        shrink = float(self.settings.get("shrink_m", 0.0))
        if not np.isfinite(shrink) or shrink < 0:
            raise InputError("settings.shrink_m", "expected a finite shrink >= 0 m")
        if np.any(rho + shrink <= 0):
            raise InputError("rho", "expected positive control radii (m)")
        validate.pose(X, "X_WC")
        self.slice_z, self.rho, self.X_WC = z, rho, X
        self.slice_z.setflags(write=False)
        self.rho.setflags(write=False)

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def cylinder(
        cls, radius: float, z_min: float, z_max: float, slices: int, control_points: int = 16
    ) -> Fpsm:
        """A circular cylinder of ``radius`` from ``z_min`` to ``z_max`` (m), for checks."""
        radius, z_min, z_max = float(radius), float(z_min), float(z_max)
        if not np.isfinite(radius) or radius <= 0:
            raise InputError("radius", f"expected a positive radius in m, got {radius}")
        if not (np.isfinite(z_min) and np.isfinite(z_max)) or z_max <= z_min:
            raise InputError("z_max", f"expected z_min < z_max, got {z_min}, {z_max}")
        if int(slices) != slices or slices < 2:
            raise InputError("slices", f"expected an integer >= 2, got {slices}")
        if int(control_points) != control_points or control_points < 3:
            raise InputError("control_points", f"expected an integer >= 3, got {control_points}")
        slices, control_points = int(slices), int(control_points)
        return cls(
            slice_z=np.linspace(z_min, z_max, slices),
            rho=np.full((slices, control_points), radius),
            settings={
                "method": "cylinder",
                "radius_m": radius,
                "z_range_m": [z_min, z_max],
                "slices": slices,
                "control_points": control_points,
                "units": "m",
            },
        )

    def shrink(self, r: float) -> Fpsm:
        """The model shrunk inward by ``r`` (Eq. 12: rho* = rho - r), for a rod of radius r.

        Radii may become <= 0 where the cavity is narrower than 2 r; they are kept (the safe
        distances there are simply negative), and ``settings["shrink_m"]`` adds up the shrink.
        """
        r = float(r)
        if not np.isfinite(r) or r < 0:
            raise InputError("r", f"expected a shrink radius >= 0 m, got {r}")
        settings = dict(self.settings)
        settings["shrink_m"] = float(settings.get("shrink_m", 0.0)) + r
        return Fpsm(
            self.slice_z.copy(), self.rho - r, self.X_WC.copy(), settings, dict(self.diagnostics)
        )

    # -- geometry -----------------------------------------------------------------------------

    @property
    def slices(self) -> int:
        return int(self.slice_z.size)

    @property
    def control_points(self) -> int:
        return int(self.rho.shape[1])

    @property
    def z_range(self) -> tuple[float, float]:
        return float(self.slice_z[0]), float(self.slice_z[-1])

    @property
    def max_radius(self) -> float:
        """An upper bound of rho(theta) over every slice (m): the curve stays within the convex
        hull of the Catmull-Rom weights, |rho(theta)| <= 1.25 max|rho_k| (weights' abs sum)."""
        return float(np.max(np.abs(self.rho)) * 1.25)

    def _locate(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lower slice index j and weight w in [0, 1] for heights inside the range."""
        m = self.slice_z.size
        if m == 1:
            return np.zeros(z.shape, dtype=np.int64), np.zeros(z.shape)
        j = np.clip(np.searchsorted(self.slice_z, z, side="right") - 1, 0, m - 2)
        z0, z1 = self.slice_z[j], self.slice_z[j + 1]
        w = np.clip((z - z0) / (z1 - z0), 0.0, 1.0)
        return j, w

    def _radius(self, theta: np.ndarray, z: np.ndarray) -> np.ndarray:
        j, w = self._locate(z)
        lo = _slice_values(self.rho, j, theta)
        if self.slice_z.size == 1:
            return lo
        hi = _slice_values(self.rho, j + 1, theta)
        return lo + w * (hi - lo)  # Eq. 11

    def radius_at(self, theta, z) -> np.ndarray:
        """rho(theta, z): the curve radius at polar angle ``theta`` (rad) and height ``z`` (m),
        linear in z between slices (Eq. 11); NaN outside [z_0, z_{M-1}] (no curve there).
        ``theta`` and ``z`` broadcast."""
        theta = _as_array(theta, "theta")
        z = _as_array(z, "z")
        theta, z = np.broadcast_arrays(theta, z)
        out = self._radius(theta, z)
        z_lo, z_hi = self.z_range
        return np.where((z >= z_lo) & (z <= z_hi), out, np.nan)

    def _d_safe(self, p: np.ndarray, radius: float = 0.0) -> np.ndarray:
        """Eq. 10-11 with the out-of-range rules, no input checks; ``radius`` shrinks (Eq. 12)."""
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        theta = np.arctan2(y + 0.0, x + 0.0)  # on the axis (x = y = +-0) the angle is 0
        d = self._radius(theta, z) - radius - np.hypot(x, y)
        z_lo, z_hi = self.z_range
        # throat side: collision; the shrink applies to the throat end too, so that
        # shrink(r).d_safe == d_safe - r holds everywhere
        throat = z - z_lo - radius - float(self.settings.get("shrink_m", 0.0))
        d = np.where(z < z_lo, np.minimum(d, throat), d)
        return np.where(z > z_hi, np.inf, d)  # above the mouth opening: unconstrained

    def d_safe(self, points_Center_m, *, radius: float = 0.0) -> np.ndarray:
        """Safe distance (m) of points given in the Center frame (Eq. 10-11), batched.

        Args:
            points_Center_m: (..., 3) points in Center (m).
            radius: shrink the model by this much first (Eq. 12), i.e. the safe distance of a
                sphere of that radius.

        Returns:
            (...,) d_safe: > 0 inside, <= 0 collision; below the bottom slice
            min(d_safe on the bottom slice, z - z_0) < 0; above the top slice +inf.
        """
        p = _as_array(points_Center_m, "points_Center_m", (3,))
        if not np.all(np.isfinite(p)):
            raise InputError("points_Center_m", "expected finite coordinates (m)")
        return self._d_safe(p, float(radius))

    def line_safety(
        self,
        start,
        direction,
        length=np.inf,
        *,
        radius: float = 0.0,
        lambda_avg: float = 0.5,
        lambda_min: float = 0.5,
    ) -> LineSafety:
        """Safety of K lines (or rods of ``radius``) starting at T = ``start`` (Eq. 13), batched.

        Samples along each line: its start point T, every crossing with a slice plane at
        0 < s <= length (s = distance from T), and a far-end point:

        - a finite ``length``: the end point T + length * u (unless it lies on a slice plane,
          then the crossing already samples it). The paper samples T and the crossings only;
          the end point closes the gap after the last crossing.
        - an infinite ray (default) must leave through the mouth opening (+Z end). One that
          leaves the model's bounding cylinder (radius :attr:`max_radius` about the axis, down
          to max_radius below the bottom slice) through its side or bottom before it reaches
          the top slice is cut there and gets a far-end sample at that exit point, <= 0 by
          construction (and clamped to <= 0): it counts as a collision, with crossings beyond
          the exit dropped so that the collision measure stays bounded for near-horizontal rays.
          A ray that leaves the curves through the side but stays within the bounding cylinder
          is caught by the crossings above its exit (outside the curves).

        Samples above the top slice are outside the mouth and do not count (d_safe = +inf).
        A rod of radius r is the line against the model shrunk by r (Eq. 12): ``radius=r``.

        Args:
            start: (K, 3) or (3,) start points T in Center (m).
            direction: (K, 3) or (3,) directions (normalized here; non-zero).
            length: scalar or (K,) length along the direction (m), > 0; inf for a ray.
            radius: rod radius r (m) >= 0.
            lambda_avg, lambda_min: weights of Eq. 13.

        Returns:
            :class:`LineSafety` with (K,) arrays.
        """
        p0 = _as_array(start, "start", (3,))
        u = _as_array(direction, "direction", (3,))
        p0, u = np.broadcast_arrays(np.atleast_2d(p0), np.atleast_2d(u))
        if p0.ndim != 2:
            raise InputError("start", "expected (K, 3) start points")
        if not np.all(np.isfinite(p0)):
            raise InputError("start", "expected finite coordinates (m)")
        norm = np.linalg.norm(u, axis=-1)
        if not np.all(np.isfinite(u)) or np.any(norm < 1e-12):
            raise InputError("direction", "expected finite, non-zero directions")
        L = np.broadcast_to(_as_array(length, "length"), norm.shape)
        if np.any(np.isnan(L)) or np.any(L <= 0):
            raise InputError("length", "expected lengths > 0 m (inf for a ray)")
        radius = float(radius)
        if not np.isfinite(radius) or radius < 0:
            raise InputError("radius", f"expected a rod radius >= 0 m, got {radius}")
        return self._line_safety(p0, u / norm[:, None], L, radius, lambda_avg, lambda_min)

    def line_safety_batch(
        self, start, unit_direction, length, radius, lambda_avg: float = 0.5,
        lambda_min: float = 0.5,
    ) -> LineSafety:
        """:meth:`line_safety` for batches the caller has already checked (the PSO's and the
        contour maps' hot path): ``start`` (K, 3) finite, ``unit_direction`` (K, 3) of unit
        length, ``length`` (K,) > 0 (inf for rays), ``radius`` a scalar or (K,) >= 0 (rods and
        lines mix in one call). No input checks; the compiled kernel."""
        return self._line_safety(start, unit_direction, length, radius, lambda_avg, lambda_min)

    def _line_safety(self, p0, u, L, radius, lambda_avg, lambda_min) -> LineSafety:
        """:meth:`line_safety` without input checks (compiled kernel); ``u`` unit (K, 3),
        ``L`` (K,), ``radius`` a scalar or (K,) (rods and lines mix in one call)."""
        K = p0.shape[0]
        p0 = kernel_array(p0)
        u = kernel_array(u)
        L = kernel_array(L, (K,))
        radius = kernel_array(radius, (K,))
        f = np.empty(K)
        d_min = np.empty(K)
        mean = np.empty(K)
        count = np.empty(K, dtype=np.int64)
        line_kernel(
            p0,
            u,
            L,
            radius,
            np.ascontiguousarray(self.rho),
            np.ascontiguousarray(self.slice_z),
            float(self.settings.get("shrink_m", 0.0)),
            self.max_radius,
            float(lambda_avg),
            float(lambda_min),
            f,
            d_min,
            mean,
            count,
        )
        return LineSafety(f_safe=f, d_safe_min=d_min, d_safe_mean=mean, samples=count)

    def _line_safety_numpy(self, p0, u, L, radius, lambda_avg, lambda_min) -> LineSafety:
        """The same as :meth:`_line_safety` in vectorized numpy (all samples of all lines in
        one gather): the reference the compiled kernel is tested and timed against."""
        K, M = p0.shape[0], self.slice_z.size
        z_lo, z_hi = self.z_range
        shrink = float(self.settings.get("shrink_m", 0.0))
        radius = np.asarray(radius, dtype=float)
        r_col = radius[:, None] if radius.ndim else radius
        uz = u[:, 2]
        tol = 1e-12
        moving = np.abs(uz) > 1e-15
        inv = 1.0 / np.where(moving, uz, 1.0)
        s = (self.slice_z[None, :] - p0[:, 2:3]) * inv[:, None]

        # Far end: a finite segment ends at T + L u. A ray that leaves the model's bounding
        # cylinder (radius max_radius, from max_radius below z_0 up to the top slice) through
        # its side or bottom before reaching the top slice ends there, with a sample that is
        # <= 0 by construction; one that reaches the top slice needs no far sample.
        finite = np.isfinite(L)
        R = self.max_radius
        a = u[:, 0] * u[:, 0] + u[:, 1] * u[:, 1]
        b = p0[:, 0] * u[:, 0] + p0[:, 1] * u[:, 1]
        c = p0[:, 0] * p0[:, 0] + p0[:, 1] * p0[:, 1] - R * R
        with np.errstate(divide="ignore", invalid="ignore"):
            s_cyl = np.where(a > 1e-30, (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a, np.inf)
            s_down = np.where(uz < -1e-15, (z_lo - R - p0[:, 2]) / uz, np.inf)
            s_top = np.where(uz > 1e-15, (z_hi - p0[:, 2]) / uz, np.inf)
        s_side = np.maximum(np.minimum(s_cyl, s_down), 0.0)
        leaves_side = ~finite & (s_side < s_top)
        L = np.where(leaves_side, s_side, L)
        cross = moving[:, None] & (s > tol) & (s <= L[:, None] + tol)
        on_plane = np.any(cross & (np.abs(s - L[:, None]) <= tol), axis=1)
        far_ok = (finite | leaves_side) & ~on_plane
        s_far = np.where(far_ok, L, 0.0)

        # Sample parameters along each line: M crossings, the start T, the far end.
        S = np.empty((K, M + 2))
        S[:, :M] = np.where(cross, s, 0.0)
        S[:, M] = 0.0
        S[:, M + 1] = s_far
        P = p0[:, None, :] + S[..., None] * u[:, None, :]
        x, y, z = P[..., 0], P[..., 1], P[..., 2]
        theta = np.arctan2(y + 0.0, x + 0.0)  # as the compiled kernel: angle 0 on the axis
        j_end, w_end = self._locate(z[:, M:])
        j_all = np.empty((K, M + 4), dtype=np.int64)
        j_all[:, :M] = np.arange(M)
        j_all[:, M : M + 2] = j_end
        j_all[:, M + 2 :] = np.minimum(j_end + 1, M - 1)
        vals = _slice_values(self.rho, j_all, np.concatenate([theta, theta[:, M:]], axis=1))
        rad = vals[:, : M + 2].copy()
        rad[:, M:] += w_end * (vals[:, M + 2 :] - vals[:, M : M + 2])  # Eq. 11
        d = rad - r_col - np.hypot(x, y)
        z_end = z[:, M:]
        throat = z_end - z_lo - r_col - shrink
        d_end = np.where(z_end < z_lo, np.minimum(d[:, M:], throat), d[:, M:])
        end_in = z_end <= z_hi  # above the mouth opening: no constraint
        start_in = end_in[:, 0]
        far_in = far_ok & end_in[:, 1]
        d_start = d_end[:, 0]
        # A ray that leaves through the side or throat is a collision even if rounding left
        # d_far > 0 at its exit point.
        d_far = np.where(leaves_side, np.minimum(d_end[:, 1], 0.0), d_end[:, 1])

        d_cross = d[:, :M]
        count = cross.sum(axis=1) + start_in + far_in
        total = (
            np.where(cross, d_cross, 0.0).sum(axis=1)
            + np.where(start_in, d_start, 0.0)
            + np.where(far_in, d_far, 0.0)
        )
        d_min = np.minimum(
            np.where(cross, d_cross, np.inf).min(axis=1, initial=np.inf),
            np.minimum(np.where(start_in, d_start, np.inf), np.where(far_in, d_far, np.inf)),
        )
        mean = np.where(count > 0, total / np.maximum(count, 1), np.inf)
        # Eq. 13
        f = np.where(d_min > 0, lambda_avg * mean + lambda_min * d_min, lambda_min * d_min)
        f = np.where(count > 0, f, np.inf)
        return LineSafety(f_safe=f, d_safe_min=d_min, d_safe_mean=mean, samples=count)

    # -- files --------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """JSON-ready mapping (SI units; the frame named explicitly)."""
        return {
            "units": "m",
            "frame": {
                "name": "Center",
                "parent": "mesh",
                "X_WC": self.X_WC.tolist(),
                "axis": "+z points out of the mouth; slices are planes z = const",
            },
            "slice_z": self.slice_z.tolist(),
            "rho": self.rho.tolist(),
            "settings": self.settings,
            "diagnostics": self.diagnostics,
        }

    @classmethod
    def from_dict(cls, data: dict) -> Fpsm:
        if not isinstance(data, dict):
            raise InputError("fpsm", "expected a JSON object")
        units = data.get("units", "m")
        if units != "m":
            raise InputError("fpsm.units", f"expected 'm', got {units!r}")
        for key in ("slice_z", "rho"):
            if key not in data:
                raise InputError(f"fpsm.{key}", "missing")
        frame = data.get("frame") or {}
        if not isinstance(frame, dict):
            raise InputError("fpsm.frame", "expected a mapping")
        X_WC = frame.get("X_WC", np.eye(4).tolist())
        if X_WC is None:
            raise InputError("fpsm.frame.X_WC", "expected a 4x4 pose")
        try:
            slice_z = np.array(data["slice_z"], dtype=float)
            rho = np.array(data["rho"], dtype=float)
            X_WC = np.array(X_WC, dtype=float)
        except (TypeError, ValueError):
            raise InputError("fpsm", "slice_z, rho and frame.X_WC must be numeric arrays") from None
        return cls(
            slice_z=slice_z,
            rho=rho,
            X_WC=X_WC,
            settings=dict(data.get("settings") or {}),
            diagnostics=dict(data.get("diagnostics") or {}),
        )

    def save(self, path) -> Path:
        """Write the model as JSON (kind "fpsm", schema_version), atomically."""
        return write_json(path, self.to_dict(), kind="fpsm")

    @classmethod
    def load(cls, path, *, field: str = "fpsm") -> Fpsm:
        """Read a model written by :meth:`save`; InputError naming ``field`` when it is bad."""
        data = read_json(path, kind="fpsm", field=field)
        try:
            return cls.from_dict(data)
        except InputError as exc:
            raise InputError(field, f"{path}: {exc}") from None
