"""A distance grid of the opened scan with a proven bound between nodes (DESIGN.md section 4).

The safety verdict of the instrument is taken against the scan itself, not against the FPSM.
This module stores the unsigned distance d(q) = min over the mesh's triangles of |q - b| on a
regular grid (Center frame, spacing g, default 0.5 mm) and bounds d anywhere from the nodes.

**Node values.** Exact: libigl's ``point_mesh_squared_distance`` (an AABB tree over the
triangles; it agrees with FCL's point-to-mesh distance to 1e-9 m, where trimesh's
``closest_point`` was off by up to 18 um here) at every node whose distance is below the *band*
(default 8 mm, wider than the head's radius). Far nodes are not queried: a coarse grid (spacing
4 g, exact too) bounds them by the interpolation bound below, which is a lower bound as well,
so every stored value is a lower bound L_c <= d(c), and a value below the band is exact
(a node whose coarse bound is below the band is queried). Values are stored in float32 rounded
towards -inf (``np.nextafter``), so they stay lower bounds.

**Between nodes (proof).** d is 1-Lipschitz (|d(p) - d(q)| <= |p - q|, a minimum of
1-Lipschitz functions), so for any node c, d(q) >= L_c - |q - c| (the *cone* bound). Tighter:
d(q)^2 - |q|^2 = min over mesh points b of (|b|^2 - 2 q . b) is a minimum of affine functions of
q, hence concave. With the trilinear weights w_c >= 0 of the cell's corners (sum w_c = 1,
sum w_c c = q), concavity gives sum_c w_c (d(c)^2 - |c|^2) <= d(q)^2 - |q|^2, i.e.
d(q)^2 >= sum_c w_c d(c)^2 - sum_c w_c |c - q|^2 = sum_c w_c d(c)^2 - g^2 sum_a t_a (1 - t_a)
(the identity sum_c w_c |c - q|^2 = g^2 sum_a t_a (1 - t_a) for the fractional coordinates t_a
holds coordinate by coordinate). With max(L_c, 0) <= d(c) in place of d(c) it stays a bound. The
grid's bound at q is the largest of the eight cone bounds and the square-root bound (it loses
about g^2 sum t (1 - t) / (2 d): 0.08 mm at a cell centre 1.2 mm from the wall, g = 0.5 mm).

**Outside the grid box** (the mesh's bounding box grown by the band on every side) a point is at
least its distance to the mesh's bounding box from every triangle; inside, that distance is a
bound too and the larger of the two is taken. **Above the box** (out of the mouth, where the
handle rises) the bound of the point's projection q' onto the box's top plane z_g carries up:
every mesh point b has b_z <= z_g, so |q - b|^2 >= (z - z_g)^2 + |q' - b|^2 and
d(q) >= sqrt((z - z_g)^2 + d(q')^2) (the mouth opening is wide, the box distance alone is not).

**Upper bounds** (for "unsafe" verdicts): d(q) <= d(c) + |q - c| for an exact node c (value
below the band), plus a rounding allowance.

:func:`distance_grid` builds one per mesh and keeps it (a weak cache keyed by the mesh object,
as the plan keeps its :class:`systems.placement.exact_clearance.ExactCavity`), and on disk in
the user's cache folder keyed by the mesh's content (``$IMPLANTPLAN_CACHE``, ``off`` for none).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import time
import weakref
from dataclasses import dataclass
from pathlib import Path

import igl
import numpy as np
import trimesh

from implantplan.systems.errors import InputError
from implantplan.systems.jit import numba

SPACING = 0.5e-3  # m, the grid spacing g
BAND = 8e-3  # m, nodes nearer than this to the mesh hold their exact distance
COARSE = 4  # the coarsest level's spacing in fine cells (exact everywhere)
EXACT_BANDS = (BAND, 2.5e-3)  # m: levels 2 g and g are exact nearer than these
MAX_NODES = 40_000_000  # 160 MB of float32; a larger grid is an input error
ROUNDING = 1e-9  # m added to upper bounds (float32 storage, igl's rounding)


@dataclass(frozen=True)
class DistanceGrid:
    """Lower bounds of the unsigned distance to a mesh on a grid (module notes).

    Attributes:
        values: (nx, ny, nz) float32 node bounds (m); a value below ``band`` is exact.
        origin: (3,) position of node (0, 0, 0) (m).
        spacing: g (m).
        band: nodes nearer than this are exact (m).
        box_lo, box_hi: (3,) the mesh's bounding box (m).
        exact_nodes: how many nodes were queried exactly.
        seconds: build time.
    """

    values: np.ndarray
    origin: np.ndarray
    spacing: float
    band: float
    box_lo: np.ndarray
    box_hi: np.ndarray
    exact_nodes: int
    seconds: float

    @property
    def nbytes(self) -> int:
        return int(self.values.nbytes)

    def args(self) -> tuple:
        """The arguments the compiled kernels take (values, origin, g, band, box)."""
        return (self.values, float(self.origin[0]), float(self.origin[1]), float(self.origin[2]),
                float(self.spacing), float(self.band), self.box_lo, self.box_hi)

    def lower(self, points) -> np.ndarray:
        """(n,) proven lower bounds of the distance (m) at points (n, 3) in the grid's frame."""
        P = np.ascontiguousarray(np.atleast_2d(np.asarray(points, dtype=float)))
        out = np.empty(len(P))
        _lower_many(*self.args(), P, out)
        return out

    def upper(self, points) -> np.ndarray:
        """(n,) upper bounds of the distance (m), inf where no exact node is near."""
        P = np.ascontiguousarray(np.atleast_2d(np.asarray(points, dtype=float)))
        out = np.empty(len(P))
        _upper_many(*self.args(), P, out)
        return out


def _round_down(v: np.ndarray) -> np.ndarray:
    f = v.astype(np.float32)
    return np.where(f.astype(np.float64) > v, np.nextafter(f, np.float32(-np.inf)), f)


def _exact(V, F, P) -> np.ndarray:
    if len(P) == 0:
        return np.zeros(0)
    sq = igl.point_mesh_squared_distance(np.ascontiguousarray(P), V, F)[0]
    return np.sqrt(np.maximum(sq, 0.0))


def build_grid(mesh: trimesh.Trimesh, *, spacing: float = SPACING, band: float = BAND,
               max_nodes: int = MAX_NODES) -> DistanceGrid:
    """The grid of ``mesh`` (module notes): exact values within ``band`` of it."""
    t0 = time.perf_counter()
    g, band = float(spacing), float(band)
    if not (np.isfinite(g) and g > 0):
        raise InputError("spacing", f"expected a positive grid spacing (m), got {spacing}")
    if not (np.isfinite(band) and band > 0):
        raise InputError("band", f"expected a positive band (m), got {band}")
    if len(mesh.faces) == 0:
        raise InputError("mesh", "expected a mesh with triangles")
    V = np.ascontiguousarray(mesh.vertices, dtype=float)
    F = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    gc = COARSE * g
    n_c = np.ceil((hi - lo + 2 * band) / gc).astype(int) + 1
    shape = (n_c - 1) * COARSE + 1
    if int(np.prod(shape)) > max_nodes:
        raise InputError("spacing", f"a grid of {int(np.prod(shape))} nodes at {g * 1e3:g} mm "
                         f"exceeds the limit of {max_nodes}; expected a coarser spacing")
    origin = lo - band
    # levels: spacing 4 g exact everywhere, 2 g exact within EXACT_BANDS[0], g within
    # EXACT_BANDS[1]; every other node holds the coarser level's proven bound
    fine, exact_nodes = None, 0
    for level, step in enumerate((COARSE, COARSE // 2, 1)):
        n_l = (n_c - 1) * (COARSE // step) + 1
        gl = g * step
        if fine is None:
            axes = [origin[a] + gl * np.arange(n_l[a]) for a in range(3)]
            P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
            fine = _exact(V, F, P).reshape(tuple(n_l))
            exact_nodes += P.shape[0]
            continue
        coarse = _round_down(fine)
        fine = np.empty(tuple(n_l))
        _coarse_fill(coarse, origin, 2 * gl, band, lo, hi, gl, fine)
        limit = min(band, EXACT_BANDS[level - 1])
        near = fine < limit
        near[::2, ::2, ::2] = False  # the coarser level's nodes: already exact or bounded
        idx = np.nonzero(near)
        fine[idx] = _exact(V, F, origin + gl * np.stack(idx, -1))
        fine[::2, ::2, ::2] = np.maximum(fine[::2, ::2, ::2], coarse)
        exact_nodes += idx[0].size
    values = _round_down(fine)
    return DistanceGrid(values, origin, g, min(band, EXACT_BANDS[-1]), lo, hi, exact_nodes,
                        time.perf_counter() - t0)


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
CACHE_ENV = "IMPLANTPLAN_CACHE"  # a folder for built grids; "off": none (default ~/.cache)
CACHE_VERSION = 1  # with this module's text, part of the cache key


def cache_folder() -> Path | None:
    """Where built grids are kept across processes: ``$IMPLANTPLAN_CACHE``, else
    ``$XDG_CACHE_HOME/implantplan`` or ``~/.cache/implantplan``; None when the variable is
    ``off``."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() == "off" else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "implantplan"


def _cache_file(mesh: trimesh.Trimesh, options: dict) -> Path | None:
    folder = cache_folder()
    if folder is None:
        return None
    h = hashlib.sha256()
    h.update(f"distance_grid {CACHE_VERSION} {sorted(options.items())!r}".encode())
    h.update(Path(__file__).read_bytes())  # any change of this module is a new grid
    h.update(np.ascontiguousarray(mesh.vertices, dtype=float).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return folder / f"distance_grid_{h.hexdigest()[:32]}.npz"


def _load(path: Path) -> DistanceGrid | None:
    try:
        with np.load(path) as z:
            return DistanceGrid(z["values"].astype(np.float32, copy=False), z["origin"],
                                float(z["spacing"]), float(z["band"]), z["box_lo"],
                                z["box_hi"], int(z["exact_nodes"]), float(z["seconds"]))
    except (OSError, KeyError, ValueError):  # absent, partial or foreign: build it again
        return None


def _save(path: Path, grid: DistanceGrid) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.part")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, values=grid.values, origin=grid.origin, spacing=grid.spacing,
                     band=grid.band, box_lo=grid.box_lo, box_hi=grid.box_hi,
                     exact_nodes=grid.exact_nodes, seconds=grid.seconds)
        os.replace(tmp, path)  # atomic: a parallel reader sees the whole file or none
    except OSError:  # a read-only home: the grid is rebuilt next time
        with contextlib.suppress(OSError, UnboundLocalError):
            os.unlink(tmp)


def distance_grid(mesh: trimesh.Trimesh, **options) -> DistanceGrid:
    """:func:`build_grid` of ``mesh``, kept while the mesh object lives (per options) and on
    disk across processes (:func:`cache_folder`, keyed by the mesh's vertices and faces, the
    options and :data:`CACHE_VERSION`)."""
    per_mesh = _CACHE.setdefault(mesh, {})
    key = tuple(sorted(options.items()))
    if key not in per_mesh:
        path = _cache_file(mesh, options)
        grid = _load(path) if path is not None and path.exists() else None
        if grid is None:
            grid = build_grid(mesh, **options)
            if path is not None:
                _save(path, grid)
        per_mesh[key] = grid
    return per_mesh[key]


# -- compiled bounds ---------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def box_distance(lo, hi, x, y, z):
    """Distance (m) from (x, y, z) to the box [lo, hi] (0 inside): a lower bound of the distance
    to anything inside it."""
    dx = max(lo[0] - x, 0.0, x - hi[0])
    dy = max(lo[1] - y, 0.0, y - hi[1])
    dz = max(lo[2] - z, 0.0, z - hi[2])
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@numba.njit(cache=True, inline="always")
def _cell(V, ox, oy, oz, g, x, y, z):
    """(inside, i, j, k, fx, fy, fz): the grid coordinates of (x, y, z), its cell's lower corner
    and whether it lies in the grid."""
    nx, ny, nz = V.shape
    fx = (x - ox) / g
    fy = (y - oy) / g
    fz = (z - oz) / g
    inside = (fx >= 0.0 and fy >= 0.0 and fz >= 0.0 and fx <= nx - 1 and fy <= ny - 1
              and fz <= nz - 1)
    i = min(int(fx), nx - 2) if inside else 0
    j = min(int(fy), ny - 2) if inside else 0
    k = min(int(fz), nz - 2) if inside else 0
    return inside, i, j, k, fx, fy, fz


@numba.njit(cache=True)
def _cell_lower(V, ox, oy, oz, g, lo, hi, x, y, z):
    """The bound at (x, y, z) from the grid's cell and the bounding box (module notes)."""
    best = box_distance(lo, hi, x, y, z)
    inside, i, j, k, fx, fy, fz = _cell(V, ox, oy, oz, g, x, y, z)
    if not inside:
        return best
    tx = fx - i
    ty = fy - j
    tz = fz - k
    acc = 0.0
    for c in range(8):
        a = c & 1
        b = (c >> 1) & 1
        e = (c >> 2) & 1
        L = np.float64(V[i + a, j + b, k + e])
        dx = (tx - a) * g
        dy = (ty - b) * g
        dz = (tz - e) * g
        cone = L - np.sqrt(dx * dx + dy * dy + dz * dz)
        if cone > best:
            best = cone
        w = (tx if a else 1.0 - tx) * (ty if b else 1.0 - ty) * (tz if e else 1.0 - tz)
        Lp = L if L > 0.0 else 0.0
        acc += w * Lp * Lp
    acc -= g * g * (tx * (1.0 - tx) + ty * (1.0 - ty) + tz * (1.0 - tz))
    if acc > 0.0:
        s = np.sqrt(acc) * (1.0 - 1e-12) - ROUNDING
        if s > best:
            best = s
    return best


@numba.njit(cache=True)
def lower_at(V, ox, oy, oz, g, band, lo, hi, x, y, z):
    """Proven lower bound of the distance at (x, y, z) (module notes). Above the grid's top
    plane z_g (every mesh point has b_z <= z_g): (z - b_z)^2 >= (z - z_g)^2 + (z_g - b_z)^2,
    so d(q)^2 >= (z - z_g)^2 + d(q')^2 with q' the point's projection onto that plane."""
    zg = oz + g * (V.shape[2] - 1)
    if z <= zg:
        return _cell_lower(V, ox, oy, oz, g, lo, hi, x, y, z)
    below = _cell_lower(V, ox, oy, oz, g, lo, hi, x, y, oz + g * (V.shape[2] - 1 - 1e-9))
    if below < 0.0:
        below = 0.0
    up = np.sqrt((z - zg) * (z - zg) + below * below) * (1.0 - 1e-12)
    box = box_distance(lo, hi, x, y, z)
    return up if up > box else box


@numba.njit(cache=True)
def upper_at(V, ox, oy, oz, g, band, lo, hi, x, y, z):
    """Upper bound of the distance at (x, y, z) from the cell's exact corners (inf if none)."""
    inside, i, j, k, fx, fy, fz = _cell(V, ox, oy, oz, g, x, y, z)
    if not inside:
        return np.inf
    best = np.inf
    for c in range(8):
        a = c & 1
        b = (c >> 1) & 1
        e = (c >> 2) & 1
        L = np.float64(V[i + a, j + b, k + e])
        if L < band:
            dx = (fx - i - a) * g
            dy = (fy - j - b) * g
            dz = (fz - k - e) * g
            u = L + np.sqrt(dx * dx + dy * dy + dz * dz) + ROUNDING + 1e-7 * L
            if u < best:
                best = u
    return best


@numba.njit(cache=True, parallel=True)
def _coarse_fill(Dc, origin, gc, band, lo, hi, g, out):
    """out[i, j, k] = the coarse grid's lower bound at fine node (i, j, k)."""
    nx, ny, nz = out.shape
    for i in numba.prange(nx):
        for j in range(ny):
            for k in range(nz):
                out[i, j, k] = lower_at(Dc, origin[0], origin[1], origin[2], gc, band, lo, hi,
                                        origin[0] + g * i, origin[1] + g * j, origin[2] + g * k)


@numba.njit(cache=True)
def _lower_many(V, ox, oy, oz, g, band, lo, hi, P, out):
    for n in range(P.shape[0]):
        out[n] = lower_at(V, ox, oy, oz, g, band, lo, hi, P[n, 0], P[n, 1], P[n, 2])


@numba.njit(cache=True)
def _upper_many(V, ox, oy, oz, g, band, lo, hi, P, out):
    for n in range(P.shape[0]):
        out[n] = upper_at(V, ox, oy, oz, g, band, lo, hi, P[n, 0], P[n, 1], P[n, 2])
