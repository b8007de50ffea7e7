"""A synthetic CBCT the project makes from a mesh case (DESIGN.md section 12), so the CBCT path
is tested end to end on data that ships or is generated (no download).

Geometry: the case's scan, closed as the planner closes it (systems.fpsm.oral_mesh.
close_open_cuts), is the air/tissue boundary; the patient frame (LPS, mm) is the mesh frame, so
the case's ``center`` and sites stay as written. The volume is the cavity's bounding box plus a
margin of tissue, on a grid of ``voxel`` (0.2-0.4 mm is a clinical CBCT's; coarser for tests).

Air occupancy is exact along z: a ray up each voxel column (``supersample``^2 per voxel,
averaged, for the partial volume across x and y) (Embree, every hit) gives the column's inside
intervals [a_m, b_m]; the air fraction of a voxel [z - h/2, z + h/2] is (F(z + h/2) - F(z -
h/2)) / h with F(z) = sum_m clip(z - a_m, 0, b_m - a_m), so a surface crossing a voxel gives it
the partial-volume value a scanner records, and the iso-surface at the mid-value lands on the
wall to well under a voxel. Tissue classes by depth d below the air surface (Euclidean distance
transform, scipy): mucosa/soft tissue 0-2 mm, cortical bone 2-3.5 mm, cancellous bone deeper, in
the jaws: 2-22 mm under each column's cavity floor and over its roof (vertical depth; crude
anatomy, soft tissue elsewhere); teeth (enamel) in the tissue within 6 mm of the wall along the
dental arch band near the occlusal plane, except the tooth each planned implant replaces; the
alveolar ridge of each planned implant (:func:`alveolar_ridge`: bone 2.5 mm beyond the implant
all round, a crest across its axis under 1 mm or more of mucosa; the band alone follows the
scan's walls, and the default sites sit on a wall 38 deg off their implants' axes, where it left
a wedge of bone at the crest and none beside the apex past the cavity's edge: -0.35 mm of bone
around both, measured); the mandibular canal a tube of soft-tissue HU through the bone, 5 mm
under each implant's apex. Then
optionally a Gaussian blur (``psf_sigma``, voxels; off by default: it rounds creases and moves
the iso-surface there by up to 0.1 mm at 1 mm voxels, measured) and Gaussian noise
(``noise_hu``), seeded.

HU values (CBCT grey values calibrated to HU; typical published ranges): air -1000, soft tissue
40, cancellous bone 500, cortical bone 1500, enamel 2500, canal contents 40.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.oral_mesh import close_open_cuts

HU = {"air": -1000.0, "soft_tissue": 40.0, "cancellous": 500.0, "cortical": 1500.0,
      "enamel": 2500.0, "canal": 40.0}
MAX_VOXELS = 60_000_000  # float32 work arrays: about 1.5 GB at the bound
MUCOSA_MM, CORTEX_MM, BONE_MM, TOOTH_MM = 2.0, 3.5, 22.0, 6.0
TOOTH_GAP = 5.5e-3  # no tooth within this of an implant's entry along x: the missing tooth
# the alveolar ridge around each planned implant (alveolar_ridge): its wall beyond the implant
# (a molar ridge of 9 mm for a 4 mm implant), mucosa over its crest, how far the crest may slope
# around the implant, how far it reaches under the apex, its cortex, sectors around the axis
RIDGE_WALL_MM, RIDGE_MUCOSA_MM, RIDGE_SLOPE_MM, RIDGE_BELOW_APEX_MM = 2.5, 1.0, 1.5, 3.0
CORTEX_WALL_MM, RIDGE_SECTORS = 1.5, 24
IMPLANT_RADIUS = 2e-3


@dataclass(frozen=True)
class PhantomSpec:
    """What the phantom is made of: voxel size (m), tissue margin around the cavity (m), noise
    (HU, sigma), the canal radius (m) and depth below the cavity floor (m), the occlusal plane
    height (m, mesh z) and the arch band (|y| in m) where teeth are drawn; ``supersample``
    squared ray columns per voxel give the partial volume across x and y too."""

    voxel: float = 0.4e-3
    margin: float = 16e-3
    noise_hu: float = 20.0
    canal_radius: float = 1.2e-3
    canal_depth: float = 5e-3
    occlusal_z: float = 100e-3
    arch_band: tuple = (8e-3, 35e-3)
    tooth_half_height: float = 6e-3
    supersample: int = 2
    psf_sigma: float = 0.0  # a point spread (Gaussian sigma, voxels); 0: the partial volume only


@dataclass
class Phantom:
    """``hu`` [k, j, i] int16 HU; ``origin`` (m, LPS) of voxel (0, 0, 0); ``voxel`` (m);
    ``canals`` one (n, 3) polyline (m, LPS) per implant; ``canal_radius`` (m)."""

    hu: np.ndarray
    origin: np.ndarray
    voxel: float
    canals: list
    canal_radius: float


def grid_shape(bounds: np.ndarray, spec: PhantomSpec) -> tuple[int, int, int]:
    """(nk, nj, ni) of the phantom of a cavity with ``bounds`` (m)."""
    size = (bounds[1] - bounds[0]) + 2 * spec.margin
    ni, nj, nk = (np.ceil(size / spec.voxel).astype(int) + 1).tolist()
    return nk, nj, ni


def check_size(bounds: np.ndarray, spec: PhantomSpec, *, field: str = "--voxel-mm") -> None:
    shape = grid_shape(bounds, spec)
    n = int(np.prod(shape))
    if n > MAX_VOXELS:
        raise InputError(field, f"{spec.voxel * 1e3:g} mm voxels make {shape[2]} x {shape[1]} x "
                         f"{shape[0]} = {n:,} voxels, at most {MAX_VOXELS:,}; expected a "
                         "coarser voxel")


def column_air_fraction(mesh: trimesh.Trimesh, x: np.ndarray, y: np.ndarray,
                        z_edges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Air fraction of every voxel [j, i, k] (columns at x[i], y[j], z-extent between z_edges),
    and each column's first and last wall height (NaN without a hit), all m."""
    X, Y = np.meshgrid(x, y)  # [j, i]
    origins = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z_edges[0] - 1e-3)])
    dirs = np.tile([0.0, 0.0, 1.0], (X.size, 1))
    loc, ray, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=True)
    z = loc[:, 2]
    order = np.lexsort((z, ray))
    ray, z = ray[order], z[order]
    keep = np.ones(len(z), bool)  # hits on a shared edge come once per face: keep one
    keep[1:] = ~((ray[1:] == ray[:-1]) & (np.abs(z[1:] - z[:-1]) < 1e-9))
    ray, z = ray[keep], z[keep]
    counts = np.bincount(ray, minlength=X.size)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(len(z)) - start[ray]
    width = int(counts.max()) if len(counts) else 0
    width += width % 2
    H = np.full((X.size, max(width, 2)), np.nan)
    H[ray, rank] = z
    odd = counts % 2 == 1  # a grazing ray: its last hit has no partner; drop it
    H[np.flatnonzero(odd), counts[odd] - 1] = np.nan
    a, b = H[:, 0::2], H[:, 1::2]
    length = np.nan_to_num(b - a)
    a = np.nan_to_num(a)
    F = np.zeros((X.size, len(z_edges)))
    for m in range(a.shape[1]):
        F += np.clip(z_edges[None, :] - a[:, m:m + 1], 0.0, length[:, m:m + 1])
    frac = np.diff(F, axis=1) / np.diff(z_edges)[None, :]
    first = np.where(counts > 0, H[:, 0], np.nan)
    last = np.full(X.size, np.nan)
    last[counts > 1] = np.nanmax(H[counts > 1], axis=1)
    shape = X.shape
    return frac.reshape(*shape, -1), first.reshape(shape), last.reshape(shape)


def canal_polylines(apexes: np.ndarray, spec: PhantomSpec) -> list[np.ndarray]:
    """One canal per implant: a straight line along x (front to back, as the mandibular canal
    runs under the molars), 20 mm each way, ``canal_depth`` under the implant's apex."""
    xs = np.arange(-20e-3, 20e-3 + 1e-9, 2e-3)
    return [np.column_stack([a[0] + xs, np.full(len(xs), a[1]),
                             np.full(len(xs), a[2] - spec.canal_depth)]) for a in apexes]


def distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance of (n, 3) points to a polyline's segments."""
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    t = np.einsum("nsk,sk->ns", points[:, None, :] - a[None], ab) / np.einsum("sk,sk->s", ab, ab)
    t = np.clip(t, 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(points[:, None, :] - closest, axis=2), axis=1)


def alveolar_ridge(hu_t, tissue, depth, x, y, z, entry, apex, radius: float, *, teeth) -> dict:
    """Write the alveolar ridge of one planned implant into ``hu_t`` [k, j, i] (in place; see
    the module docstring): bone within ``radius + RIDGE_WALL_MM`` of the implant's axis, from
    ``RIDGE_BELOW_APEX_MM`` under the apex up to a crest across the axis (flat along each
    direction out of the axis), per sector of ``RIDGE_SECTORS`` around it the shallowest level
    whose ridge lies ``RIDGE_MUCOSA_MM`` or more under the air surface (and at most
    ``RIDGE_SLOPE_MM`` above the deepest sector's), continuous around the axis; the jaw
    band's bone above the crest inside the ridge's radius is soft tissue; cortical within
    ``CORTEX_WALL_MM`` of the ridge's sides and crest. Returns the crest depths (m, along the
    axis from the entry) per sector."""
    axis = (entry - apex) / np.linalg.norm(entry - apex)
    length = float(np.linalg.norm(entry - apex))
    R = radius + RIDGE_WALL_MM * 1e-3
    reach = np.maximum(np.abs(axis) * length, 0) + R + 2e-3
    lo, hi = np.minimum(entry, apex) - reach, np.maximum(entry, apex) + reach
    sl = [slice(np.searchsorted(c, lo[d]), np.searchsorted(c, hi[d], side="right"))
          for d, c in ((2, z), (1, y), (0, x))]
    K, J, I = np.meshgrid(z[sl[0]], y[sl[1]], x[sl[2]], indexing="ij")
    rel = np.stack([I - entry[0], J - entry[1], K - entry[2]], axis=-1)
    a = -(rel @ axis)  # depth along the axis below the entry
    lateral = rel + a[..., None] * axis
    rho = np.linalg.norm(lateral, axis=-1)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    phi = np.arctan2(lateral @ w, lateral @ u) % (2 * np.pi)
    width = 2 * np.pi / RIDGE_SECTORS
    sector = np.floor(phi / width).astype(int) % RIDGE_SECTORS
    inside = (rho <= R) & (a <= length + RIDGE_BELOW_APEX_MM * 1e-3)
    shallow = inside & (depth[sl[0], sl[1], sl[2]] < RIDGE_MUCOSA_MM * 1e-3) & (a <= length)
    h = float(x[1] - x[0])
    crest = np.zeros(RIDGE_SECTORS)
    np.maximum.at(crest, sector[shallow], a[shallow] + h)
    crest = np.maximum(crest, crest.max() - RIDGE_SLOPE_MM * 1e-3)
    # continuous around the axis (a step between sectors is a ledge a ray can run along): the
    # larger of each sector's and its neighbours', interpolated between the sectors' middles,
    # so no point lies higher than its own sector asks
    crest = np.maximum.reduce([np.roll(crest, -1), crest, np.roll(crest, 1)])
    middles = (np.arange(-1, RIDGE_SECTORS + 1) + 0.5) * width
    top = np.interp(phi, middles, np.concatenate([crest[-1:], crest, crest[:1]]))
    view = hu_t[sl[0], sl[1], sl[2]]
    bone_hu = (view == HU["cancellous"]) | (view == HU["cortical"])
    view[inside & (a < top) & bone_hu] = HU["soft_tissue"]  # no band bone above the crest
    ridge = inside & (a >= top) & tissue[sl[0], sl[1], sl[2]]
    cortex = (R - rho < CORTEX_WALL_MM * 1e-3) | (a - top < CORTEX_WALL_MM * 1e-3)
    view[ridge & ~cortex] = HU["cancellous"]
    view[ridge & cortex] = HU["cortical"]
    teeth[sl[0], sl[1], sl[2]] &= ~ridge
    return crest


def make_phantom(scan: trimesh.Trimesh, spec: PhantomSpec, *, seed, implants=None,
                 implant_radii=None, close_cuts: bool = True) -> Phantom:
    """The synthetic CBCT of a cavity mesh (m, mesh frame = LPS); see the module docstring.
    ``implants`` (entries, apexes: (n, 3) each, m, mesh frame as scanned) places a canal under
    each implant's apex, its alveolar ridge around it (``implant_radii``, m; default 2 mm) and
    leaves its tooth out (the tooth the implant replaces)."""
    from scipy import ndimage

    mesh = close_open_cuts(scan)[0] if close_cuts else scan
    bounds = np.asarray(mesh.bounds)
    check_size(bounds, spec)
    nk, nj, ni = grid_shape(bounds, spec)
    h = spec.voxel
    origin = bounds[0] - spec.margin
    x, y, z = (origin[d] + h * np.arange(n) for d, n in enumerate((ni, nj, nk)))
    z_edges = np.concatenate([z - h / 2, [z[-1] + h / 2]])
    n = spec.supersample
    sub = (np.arange(n) + 0.5) / n - 0.5  # sub-column offsets (voxels) for partial volume in x, y
    xs = (x[:, None] + h * sub[None]).ravel()
    ys = (y[:, None] + h * sub[None]).ravel()
    frac, first, last = column_air_fraction(mesh, xs, ys, z_edges)
    frac = frac.reshape(nj, n, ni, n, nk).mean(axis=(1, 3))
    first = np.fmin.reduce(first.reshape(nj, n, ni, n), axis=(1, 3))  # the cavity's floor
    last = np.fmax.reduce(last.reshape(nj, n, ni, n), axis=(1, 3))  # and roof, per column
    frac = np.ascontiguousarray(frac.transpose(2, 0, 1), dtype=np.float32)  # [k, j, i]
    tissue = frac < 0.5
    depth = ndimage.distance_transform_edt(tissue, sampling=h).astype(np.float32)
    zz = z[:, None, None]
    # the jaws: under the floor and over the roof of each column, past the mucosa (vertical
    # depth, so a ridge's bone reaches under a sloping wall as a jaw's does)
    below = (first[None] - zz >= MUCOSA_MM * 1e-3) & (first[None] - zz < BONE_MM * 1e-3)
    above = (zz - last[None] >= MUCOSA_MM * 1e-3) & (zz - last[None] < BONE_MM * 1e-3)
    jaws = tissue & (below | above) & (depth >= MUCOSA_MM * 1e-3)
    hu_t = np.full(frac.shape, HU["soft_tissue"], dtype=np.float32)
    hu_t[jaws] = HU["cancellous"]
    hu_t[jaws & (depth < CORTEX_MM * 1e-3)] = HU["cortical"]
    band = (np.abs(y) >= spec.arch_band[0]) & (np.abs(y) <= spec.arch_band[1])
    teeth = (band[None, :, None] & (np.abs(zz - spec.occlusal_z) < spec.tooth_half_height)
             & tissue & (depth < TOOTH_MM * 1e-3))
    entries, apexes = (np.zeros((0, 3)), np.zeros((0, 3))) if implants is None else \
        (np.asarray(implants[0], float), np.asarray(implants[1], float))
    for e in entries:  # the missing tooth at each implant site
        teeth &= ~((np.abs(x - e[0]) < TOOTH_GAP)[None, None, :]
                   & (np.sign(y) == np.sign(e[1]))[None, :, None])
    hu_t[teeth] = HU["enamel"]
    radii = np.full(len(entries), IMPLANT_RADIUS) if implant_radii is None else \
        np.asarray(implant_radii, float)
    for e, a, r in zip(entries, apexes, radii, strict=True):
        alveolar_ridge(hu_t, tissue, depth, x, y, z, e, a, r, teeth=teeth)
    canals = canal_polylines(apexes, spec)
    for c in canals:
        lo = np.searchsorted(x, c[:, 0].min() - 2 * spec.canal_radius)
        hi = np.searchsorted(x, c[:, 0].max() + 2 * spec.canal_radius)
        jl = np.searchsorted(y, c[:, 1].min() - 2 * spec.canal_radius)
        jh = np.searchsorted(y, c[:, 1].max() + 2 * spec.canal_radius)
        kl = np.searchsorted(z, c[:, 2].min() - 2 * spec.canal_radius)
        kh = np.searchsorted(z, c[:, 2].max() + 2 * spec.canal_radius)
        K, J, I = np.meshgrid(np.arange(kl, kh), np.arange(jl, jh), np.arange(lo, hi),
                              indexing="ij")
        pts = np.column_stack([x[I.ravel()], y[J.ravel()], z[K.ravel()]])
        inside = distance_to_polyline(pts, c) <= spec.canal_radius
        hu_t[K.ravel()[inside], J.ravel()[inside], I.ravel()[inside]] = HU["canal"]
    hu = frac * HU["air"] + (1.0 - frac) * hu_t
    if spec.psf_sigma > 0:
        hu = ndimage.gaussian_filter(hu, sigma=spec.psf_sigma)
    rng = np.random.default_rng(seed)
    hu += rng.normal(0.0, spec.noise_hu, hu.shape).astype(np.float32)
    hu = np.clip(np.rint(hu), -1024, 3071).astype(np.int16)
    return Phantom(hu, origin, h, canals, spec.canal_radius)
