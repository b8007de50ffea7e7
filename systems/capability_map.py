"""Capability map of the AUBO-i10 (+ tool): voxels x approach directions (seed 004 Sec. 3).

The workspace is cut into cubic voxels (edge ``voxel`` m) over the box that bounds the arm's reach;
each voxel centre gets ``K`` approach directions on the unit sphere (golden spiral). A (voxel,
direction) pair is *reachable* when the closed-form IK (:func:`systems.kinematics.ik`, all 8
branches) finds a solution within the joint limits for the mapped frame (flange or tool) placed at
the voxel centre with its +z axis along the direction. The reachability index of a voxel is the
fraction of its directions that are reachable (Sec. 3: "number of reachable orientations in that
voxel with respect to all the discretized orientations"), in [0, 1].

Roll about the approach axis (the rotation of the mapped frame about its own z):

* Flange (no tool, or a tool whose z axis lies on the flange z axis): roll is **provably free up to
  the joint-6 limit**, so it is not sampled. A roll gamma about the flange z is a rotation about
  joint 6's axis, so (q1..q5, q6) reaches X iff (q1..q5, q6 + gamma) reaches X Rz(gamma): q1..q5 do
  not depend on the roll. With +-360 deg limits every q6 + gamma has a 2*pi copy within limits, so
  a (position, direction) reachable at one roll is reachable at every roll. With +-175 deg the
  forbidden q6 arc is the w = 10 deg gap around 180 deg: a branch valid for q1..q5 reaches all rolls
  except a 10 deg window. The map therefore stores ``reachable`` = "some roll" (IK with q6 relaxed),
  and ``all_rolls`` = "every roll": true iff two valid branches' q6 differ by at least w on the
  circle (then their forbidden windows are disjoint; if all valid q6 lie within w of each other
  their windows share a roll). Exact for the flange, no sampling.
* A tool whose z axis is not the flange z axis (e.g. the contra-angle implanting actuator, implant
  axis perpendicular to the rod): roll is **not** free (it moves q1..q5), so ``rolls`` values are
  sampled evenly in [0, 2*pi); ``reachable`` = any sample reachable, ``all_rolls`` = all samples.

Queries (:meth:`CapabilityMap.query`) take a batch of poses in base_link and return, per pose,
whether the voxel holding its position has the direction nearest to the pose's z axis reachable,
and that voxel's index; a compiled kernel does >2 M queries/s. Nearest direction uses a lookup
table over (polar angle, azimuth) cells (cell centre -> nearest spiral direction), at least 128 x
256 cells: a cell's half-diagonal is <= 0.71 pi / 128 = 0.017 rad, ~20x below the direction
spacing even at K = 200, so only poses that close to a Voronoi border can get the neighbour.

The map is built in independent voxel blocks through any ``concurrent.futures.Executor``
(:func:`build`; a ``ProcessPoolExecutor`` by default): :func:`build_block` is a pure top-level
function of picklable inputs, so the same blocks could go to a cluster executor unchanged.

Storage: HDF5 (h5py) with the parameters and ``schema_version`` as attributes; only voxels with at
least one reachable direction are stored (packed bits), with a dense int32 grid -> row table.

Departures from the paper: directions only (roll proved free or sampled as above), as the DLR
maps do for symmetric tools; the paper does not state its rotational grid.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass, field

import h5py
import numba
import numpy as np

from implantplan.systems import validate
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_atomic
from implantplan.systems.frames import invert
from implantplan.systems.kinematics import (
    DH_A2,
    DH_A3,
    DH_D1,
    DH_D4,
    DH_D5,
    DH_D6,
    ik,
    joint_limits,
)

KIND = "capability_map"
SCHEMA_VERSION = 1
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
SHOULDER = np.array([0.0, 0.0, DH_D1])  # joint 2 axis meets joint 1 axis here (base_link)
ARM_REACH = abs(DH_A2) + abs(DH_A3) + abs(DH_D4) + abs(DH_D5) + abs(DH_D6)  # bound from SHOULDER


# ---------------------------------------------------------------------------------------------
# Directions
# ---------------------------------------------------------------------------------------------


def golden_spiral(k: int) -> np.ndarray:
    """``k`` near-uniform unit vectors (k, 3): z_i = 1 - (2i + 1)/k, azimuth i * golden angle."""
    if int(k) != k or k < 1:
        raise InputError("directions", f"expected a positive integer, got {k!r}")
    i = np.arange(int(k), dtype=float)
    z = 1.0 - (2.0 * i + 1.0) / k
    s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * GOLDEN_ANGLE
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)


def frames_from_z(d: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) whose z column is the unit vector ``d`` (x fixed by a rule)."""
    d = np.asarray(d, dtype=float)
    hint = np.where(np.abs(d[..., 0:1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    x = hint - np.sum(hint * d, axis=-1, keepdims=True) * d
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(d, x)
    return np.stack([x, y, d], axis=-1)


def direction_table(directions: np.ndarray, n_theta: int | None = None) -> np.ndarray:
    """Nearest-direction lookup (n_theta, 2 n_theta) int16 over cells uniform in polar angle and
    azimuth (cell half-diagonal <= 0.71 pi / n_theta everywhere, poles included)."""
    k = len(directions)
    n_z = int(min(512, max(128, 24 * np.sqrt(k)))) if n_theta is None else int(n_theta)
    n_phi = 2 * n_z
    z = np.cos((np.arange(n_z) + 0.5) * np.pi / n_z)
    phi = -np.pi + (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    s = np.sqrt(1.0 - z * z)
    cells = np.stack(
        [
            s[:, None] * np.cos(phi)[None],
            s[:, None] * np.sin(phi)[None],
            np.repeat(z[:, None], n_phi, 1),
        ],
        axis=-1,
    ).reshape(-1, 3)
    table = np.empty(len(cells), dtype=np.int16)
    for start in range(0, len(cells), 8192):
        table[start : start + 8192] = np.argmax(cells[start : start + 8192] @ directions.T, axis=1)
    return table.reshape(n_z, n_phi)


# ---------------------------------------------------------------------------------------------
# Parameters and grid
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MapParams:
    """What a map was built from. Two maps answer alike iff their params are equal.

    Attributes:
        voxel: voxel edge in m.
        directions: number of golden-spiral approach directions K.
        limits: "175" or "360" (joint limits of the arm).
        X_FT: 4x4 pose of the mapped frame in the flange frame (identity = flange).
        tool: name of the mapped frame ("flange" or a tool name), for humans.
        rolls: roll samples about the approach axis; 1 when roll is free (flange-coaxial frame).
        self_collision: a branch also has to be free of self-collision (arm capsules of
            :mod:`systems.collision_primitives` on links two or more apart must not overlap).
    """

    voxel: float
    directions: int
    limits: str = "175"
    X_FT: tuple = tuple(np.eye(4).ravel())
    tool: str = "flange"
    rolls: int = 1
    self_collision: bool = False

    def X_FT_matrix(self) -> np.ndarray:
        return np.asarray(self.X_FT, dtype=float).reshape(4, 4)

    def as_dict(self) -> dict:
        return {
            "voxel": float(self.voxel),
            "directions": int(self.directions),
            "limits": str(self.limits),
            "X_FT": [float(v) for v in self.X_FT],
            "tool": str(self.tool),
            "rolls": int(self.rolls),
            "self_collision": bool(self.self_collision),
        }

    def key(self) -> str:
        """Stable hash of the parameters (used to key derived RASSCMAPs)."""
        text = json.dumps(self.as_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def roll_is_free(X_FT: np.ndarray, tol: float = 1e-9) -> bool:
    """True when the mapped frame's z axis lies on the flange z axis (roll = joint 6 rotation)."""
    X_FT = np.asarray(X_FT, dtype=float)
    z = X_FT[:3, 2]
    p = X_FT[:3, 3]
    return bool(abs(abs(z[2]) - 1.0) < tol and np.hypot(p[0], p[1]) < tol)


def make_params(
    voxel: float,
    directions: int,
    *,
    limits: str = "175",
    X_FT: np.ndarray | None = None,
    tool: str = "flange",
    rolls: int | None = None,
    self_collision: bool = False,
) -> MapParams:
    """Validated :class:`MapParams`; ``rolls`` defaults to 1 if roll is free, else 12."""
    if not np.isfinite(voxel) or not 0.005 <= voxel <= 0.5:
        raise InputError("voxel", f"expected a voxel edge in [5 mm, 500 mm], got {voxel!r} m")
    if int(directions) != directions or not 1 <= directions <= 32000:
        raise InputError("directions", f"expected an integer in [1, 32000], got {directions!r}")
    if limits not in ("175", "360"):
        raise InputError("limits", f"expected '175' or '360', got {limits!r}")
    X = np.eye(4) if X_FT is None else validate.pose(X_FT, "X_FT")
    free = roll_is_free(X)
    if rolls is None:
        rolls = 1 if free else 12
    if int(rolls) != rolls or rolls < 1:
        raise InputError("rolls", f"expected a positive integer, got {rolls!r}")
    if free and rolls != 1:
        raise InputError("rolls", "roll about the flange axis is free (joint 6); use rolls = 1")
    return MapParams(
        float(voxel),
        int(directions),
        limits,
        tuple(X.ravel()),
        tool,
        int(rolls),
        bool(self_collision),
    )


NEIGHBOURS = np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3)
"""(27, 3) cell offsets of a voxel's 3x3x3 neighbourhood (itself included), in C order."""


@dataclass(frozen=True)
class Grid:
    """Axis-aligned voxel grid in base_link: voxel (i, j, k) has centre origin + (ijk + 0.5) v."""

    origin: np.ndarray
    voxel: float
    shape: tuple

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def centres(self, ids: np.ndarray) -> np.ndarray:
        ijk = np.stack(np.unravel_index(ids, self.shape), axis=-1)
        return self.origin + (ijk + 0.5) * self.voxel

    def cells(self, p: np.ndarray) -> np.ndarray:
        """Integer cells (..., 3) holding positions p (..., 3); may lie outside the grid."""
        return np.floor((np.asarray(p, dtype=float) - self.origin) / self.voxel).astype(np.int64)

    def neighbourhood(self, p: np.ndarray) -> np.ndarray:
        """Linear ids (..., 27) of the 3x3x3 voxels around each position p (..., 3) (the
        voxel holding p and its 26 neighbours, :data:`NEIGHBOURS` order); -1 outside the grid."""
        c = self.cells(p)[..., None, :] + NEIGHBOURS
        shape = np.asarray(self.shape)
        inside = np.all((c >= 0) & (c < shape), axis=-1)
        ids = np.ravel_multi_index(np.moveaxis(np.clip(c, 0, shape - 1), -1, 0), self.shape)
        return np.where(inside, ids, -1)


def reach_radius(params: MapParams) -> float:
    """Upper bound of |p - SHOULDER| for the mapped frame's origin (triangle inequality)."""
    return ARM_REACH + float(np.linalg.norm(params.X_FT_matrix()[:3, 3]))


def make_grid(params: MapParams) -> Grid:
    """The grid over the cube that bounds the reach sphere about the shoulder point."""
    R = reach_radius(params)
    n = int(np.ceil(2.0 * R / params.voxel)) + 1
    origin = SHOULDER - 0.5 * n * params.voxel
    return Grid(origin=origin, voxel=params.voxel, shape=(n, n, n))


def candidate_voxels(params: MapParams, grid: Grid) -> np.ndarray:
    """Linear ids of voxels whose centre may be reachable (inside the reach sphere + half diag)."""
    ids = np.arange(grid.size)
    c = grid.centres(ids)
    keep = (
        np.linalg.norm(c - SHOULDER, axis=1) <= reach_radius(params) + 0.5 * np.sqrt(3) * grid.voxel
    )
    return ids[keep]


# ---------------------------------------------------------------------------------------------
# Building
# ---------------------------------------------------------------------------------------------


def _relaxed_limits(limits: str) -> np.ndarray:
    lim = joint_limits(limits).copy()
    lim[0, 5], lim[1, 5] = -2.0 * np.pi, 2.0 * np.pi
    return lim


def self_collision_free(q: np.ndarray) -> np.ndarray:
    """(..., 6) joint vectors -> (...) bool: no overlap between arm capsules (DESIGN.md 8
    primitives, :data:`systems.collision_primitives.ARM_CAPSULES`) on links two or more apart.
    The arm capsules are symmetric about the joint-6 axis, so q6 never matters (roll stays free)."""
    from implantplan.systems.collision_primitives import (
        ARM_CAPSULES,
        arm_capsules,
        capsule_clearance,
    )

    links = np.array([c.link for c in ARM_CAPSULES])
    ia, ib = np.nonzero(links[None, :] - links[:, None] >= 2)
    seg, r = arm_capsules(q)
    clr = capsule_clearance(seg[..., ia, :, :], r[ia], seg[..., ib, :, :], r[ib])
    return np.all(clr > 0.0, axis=-1)


def _collision_filter(params: MapParams, res) -> np.ndarray:
    """IkResult.valid with self-colliding branches removed when the params ask for it."""
    if not params.self_collision:
        return res.valid
    valid = res.valid.copy()
    if valid.any():
        valid[valid] = self_collision_free(res.q[valid])
    return valid


def reach_at(
    params: MapParams, centres: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Reachability of the mapped frame at ``centres`` (n, 3) x ``directions`` (k, 3).

    Returns:
        ``(reachable, all_rolls)``: bool (n, k) each; see the module docstring for the roll.
    """
    centres = np.asarray(centres, dtype=float)
    R_dir = frames_from_z(directions)  # (k, 3, 3)
    n, k = len(centres), len(directions)
    X_FT = params.X_FT_matrix()
    if params.rolls == 1:
        X = np.zeros((n, k, 4, 4))
        X[..., :3, :3] = R_dir[None]
        X[..., :3, 3] = centres[:, None]
        X[..., 3, 3] = 1.0
        X_BF = X @ invert(X_FT) if not np.allclose(X_FT, np.eye(4)) else X
        res = ik(X_BF, limits=_relaxed_limits(params.limits))
        valid = _collision_filter(params, res)
        reachable = valid.any(-1)
        lim = joint_limits(params.limits)
        gap = 2.0 * np.pi - (lim[1, 5] - lim[0, 5])
        if gap <= 0.0:
            return reachable, reachable.copy()
        q6 = np.where(valid, res.q[..., 5], np.nan)  # (n, k, 8)
        d = np.abs(q6[..., :, None] - q6[..., None, :])
        d = np.minimum(d, 2.0 * np.pi - d)
        spread = np.nanmax(np.where(np.isnan(d), -1.0, d), axis=(-1, -2))
        return reachable, reachable & (spread >= gap)
    gammas = 2.0 * np.pi * np.arange(params.rolls) / params.rolls
    c, s = np.cos(gammas), np.sin(gammas)
    Rz = np.zeros((params.rolls, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    X = np.zeros((n, k, params.rolls, 4, 4))
    X[..., :3, :3] = (R_dir[:, None] @ Rz[None])[None]
    X[..., :3, 3] = centres[:, None, None]
    X[..., 3, 3] = 1.0
    res = ik(X, limits=params.limits, X_FT=X_FT)
    per_roll = _collision_filter(params, res).any(-1)
    return per_roll.any(-1), per_roll.all(-1)


def build_block(
    params: MapParams, voxel_ids: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One independent unit of work: reachability of the given voxels (picklable in and out).

    Returns:
        ``(voxel_ids, reachable_bits, all_roll_bits)``: bits packed along the direction axis
        (np.packbits, big-endian), only for voxels with >= 1 reachable direction.
    """
    grid = make_grid(params)
    dirs = golden_spiral(params.directions)
    reach, allr = reach_at(params, grid.centres(np.asarray(voxel_ids)), dirs)
    keep = reach.any(axis=1)
    return (
        np.asarray(voxel_ids)[keep].astype(np.int64),
        np.packbits(reach[keep], axis=1),
        np.packbits(allr[keep], axis=1),
    )


def _blocks(ids: np.ndarray, per_block: int) -> list[np.ndarray]:
    return [ids[i : i + per_block] for i in range(0, len(ids), per_block)]


def build(
    params: MapParams,
    *,
    executor: Executor | None = None,
    workers: int | None = None,
    poses_per_block: int = 60_000,
    progress: Callable[[int, int], None] | None = None,
) -> CapabilityMap:
    """Build the map in independent voxel blocks.

    Args:
        params: from :func:`make_params`.
        executor: any ``concurrent.futures.Executor`` (a cluster one works unchanged); by default
            a ``ProcessPoolExecutor(workers)``; ``workers=1`` runs in this process.
        workers: process count for the default executor (default: os.cpu_count()).
        poses_per_block: IK poses per block (memory ~ 450 B per pose).
        progress: ``progress(done_blocks, n_blocks)`` callback.
    """
    grid = make_grid(params)
    ids = candidate_voxels(params, grid)
    per = max(1, poses_per_block // (params.directions * params.rolls))
    blocks = _blocks(ids, per)
    results = []
    if executor is None and (workers == 1 or len(blocks) == 1):
        for i, b in enumerate(blocks):
            results.append(build_block(params, b))
            if progress:
                progress(i + 1, len(blocks))
    else:
        own = executor is None
        ex = executor or ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1)
        try:
            futures = [ex.submit(build_block, params, b) for b in blocks]
            for i, f in enumerate(futures):
                results.append(f.result())
                if progress:
                    progress(i + 1, len(blocks))
        finally:
            if own:
                ex.shutdown()
    vox = np.concatenate([r[0] for r in results]) if results else np.zeros(0, np.int64)
    nbytes = (params.directions + 7) // 8
    reach = np.concatenate([r[1] for r in results]) if results else np.zeros((0, nbytes), np.uint8)
    allr = np.concatenate([r[2] for r in results]) if results else np.zeros((0, nbytes), np.uint8)
    return CapabilityMap(params, grid, vox, reach, allr)


# ---------------------------------------------------------------------------------------------
# The map and its queries
# ---------------------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def direction_of(zx, zy, zz, table):  # pragma: no cover - compiled
    """Map direction index for a vector (any length > 0) from the lookup table."""
    n_z, n_phi = table.shape
    norm = np.sqrt(zx * zx + zy * zy + zz * zz)
    c = min(1.0, max(-1.0, zz / norm))
    iz = min(max(int(np.arccos(c) / np.pi * n_z), 0), n_z - 1)
    ip = int((np.arctan2(zy, zx) + np.pi) / (2.0 * np.pi) * n_phi)
    ip = min(max(ip, 0), n_phi - 1)
    return table[iz, ip]


@numba.njit(cache=True, inline="always")
def lookup(px, py, pz, zx, zy, zz, origin, voxel, shape, row_of, table, bits):  # pragma: no cover
    """(row, reachable) of one position + approach direction; row -1 outside stored voxels."""
    i = int(np.floor((px - origin[0]) / voxel))
    j = int(np.floor((py - origin[1]) / voxel))
    k = int(np.floor((pz - origin[2]) / voxel))
    if i < 0 or j < 0 or k < 0 or i >= shape[0] or j >= shape[1] or k >= shape[2]:
        return -1, False
    row = row_of[(i * shape[1] + j) * shape[2] + k]
    if row < 0:
        return -1, False
    d = direction_of(zx, zy, zz, table)
    return row, (bits[row, d >> 3] >> (7 - (d & 7))) & 1 == 1


@numba.njit(cache=True)
def _query_kernel(p, zax, origin, voxel, shape, row_of, table, bits, index, reach_out, index_out):
    for n in range(p.shape[0]):  # pragma: no cover - compiled
        row, ok = lookup(
            p[n, 0], p[n, 1], p[n, 2], zax[n, 0], zax[n, 1], zax[n, 2],
            origin, voxel, shape, row_of, table, bits,
        )  # fmt: skip
        reach_out[n] = ok
        index_out[n] = index[row] if row >= 0 else 0.0


@numba.njit(cache=True)
def _index_kernel(p, X, origin, voxel, shape, row_of, index, out):  # pragma: no cover - compiled
    for b in range(X.shape[0]):
        for n in range(p.shape[0]):
            x, y, z = p[n, 0], p[n, 1], p[n, 2]
            px = X[b, 0, 0] * x + X[b, 0, 1] * y + X[b, 0, 2] * z + X[b, 0, 3]
            py = X[b, 1, 0] * x + X[b, 1, 1] * y + X[b, 1, 2] * z + X[b, 1, 3]
            pz = X[b, 2, 0] * x + X[b, 2, 1] * y + X[b, 2, 2] * z + X[b, 2, 3]
            i = int(np.floor((px - origin[0]) / voxel))
            j = int(np.floor((py - origin[1]) / voxel))
            k = int(np.floor((pz - origin[2]) / voxel))
            out[b, n] = 0.0
            if i < 0 or j < 0 or k < 0 or i >= shape[0] or j >= shape[1] or k >= shape[2]:
                continue
            row = row_of[(i * shape[1] + j) * shape[2] + k]
            if row >= 0:
                out[b, n] = index[row]


@dataclass
class CapabilityMap:
    """A built map: params, grid, the stored voxels and their direction bits.

    Attributes:
        params: :class:`MapParams`.
        grid: :class:`Grid`.
        voxel_ids: (m,) linear ids of voxels with >= 1 reachable direction.
        reach_bits: (m, ceil(K/8)) uint8 packed reachable bits ("some roll").
        all_roll_bits: (m, ceil(K/8)) uint8 packed bits "reachable at every roll".
    """

    params: MapParams
    grid: Grid
    voxel_ids: np.ndarray
    reach_bits: np.ndarray
    all_roll_bits: np.ndarray
    directions: np.ndarray = field(init=False, repr=False)
    index: np.ndarray = field(init=False, repr=False)
    _row_of: np.ndarray = field(init=False, repr=False)
    _table: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        k = self.params.directions
        self.directions = golden_spiral(k)
        counts = np.unpackbits(self.reach_bits, axis=1, count=k).sum(axis=1)
        self.index = (counts / k).astype(np.float64)
        self._row_of = np.full(self.grid.size, -1, dtype=np.int32)
        self._row_of[self.voxel_ids] = np.arange(len(self.voxel_ids), dtype=np.int32)
        self._table = direction_table(self.directions)

    # -- queries ------------------------------------------------------------------------------
    def kernel_args(self) -> tuple:
        """(origin, voxel, shape, row_of, table, bits): the arguments of :func:`lookup`, for
        compiled callers (e.g. the RASSCMAP's Algorithm 2)."""
        return (
            np.asarray(self.grid.origin, float), float(self.grid.voxel),
            np.asarray(self.grid.shape, np.int64), self._row_of, self._table, self.reach_bits,
        )  # fmt: skip

    def query_points(self, p: np.ndarray, z_axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(reachable, index) for positions (n, 3) and approach directions (n, 3) in base_link."""
        p = np.ascontiguousarray(np.asarray(p, dtype=float).reshape(-1, 3))
        z = np.ascontiguousarray(np.asarray(z_axis, dtype=float).reshape(-1, 3))
        if len(p) != len(z):
            raise InputError("poses", "positions and directions differ in count")
        reach = np.empty(len(p), dtype=bool)
        index = np.empty(len(p), dtype=np.float64)
        _query_kernel(p, z, *self.kernel_args(), self.index, reach, index)
        return reach, index

    def query(self, X_BP: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(reachable, index) for poses (..., 4, 4) in base_link; the pose's z is the approach."""
        X = np.asarray(X_BP, dtype=float)
        if X.ndim < 2 or X.shape[-2:] != (4, 4):
            raise InputError("poses", f"expected poses of shape (..., 4, 4), got {X.shape}")
        if not np.all(np.isfinite(X)):
            raise InputError("poses", "poses must be finite (found NaN or inf)")
        shape = X.shape[:-2]
        flat = X.reshape(-1, 4, 4)
        reach, index = self.query_points(flat[:, :3, 3], flat[:, :3, 2])
        return reach.reshape(shape), index.reshape(shape)

    def nearest_direction(self, v: np.ndarray) -> np.ndarray:
        """Index of the map direction nearest to each vector (n, 3) (the query's lookup table)."""
        v = np.asarray(v, dtype=float).reshape(-1, 3)
        v = v / np.linalg.norm(v, axis=1, keepdims=True)
        n_z, n_phi = self._table.shape
        iz = np.arccos(np.clip(v[:, 2], -1.0, 1.0)) / np.pi * n_z
        iz = np.clip(iz.astype(np.int64), 0, n_z - 1)
        phi = np.arctan2(v[:, 1], v[:, 0])
        ip = np.clip(((phi + np.pi) / (2.0 * np.pi) * n_phi).astype(np.int64), 0, n_phi - 1)
        return self._table[iz, ip].astype(np.int64)

    def voxel_index(self, p: np.ndarray, X_BW: np.ndarray | None = None) -> np.ndarray:
        """Reachability index of the voxel holding each position (0 outside the map).

        Args:
            p: (n, 3) positions in base_link, or in frame W when ``X_BW`` is given.
            X_BW: optional (nb, 4, 4) poses of W in base_link (one per base): the result is then
                (nb, n), the index of every point seen from every base (no (nb, n, 3) temporary).
        """
        p = np.ascontiguousarray(np.asarray(p, dtype=float).reshape(-1, 3))
        X = np.eye(4)[None] if X_BW is None else np.asarray(X_BW, dtype=float).reshape(-1, 4, 4)
        out = np.empty((len(X), len(p)))
        origin, voxel, shape, row_of = self.kernel_args()[:4]
        _index_kernel(p, np.ascontiguousarray(X), origin, voxel, shape, row_of, self.index, out)
        return out[0] if X_BW is None else out

    def neighbourhood_index(self, p: np.ndarray) -> np.ndarray:
        """Mean reachability index (...,) of the 27 voxels around each position p (..., 3) in
        base_link (:meth:`Grid.neighbourhood`; voxels outside the grid or the map count 0): how
        well the map tolerates the position moved by a voxel. The one neighbourhood query (the
        plan's capability check, RASSCMAP's tie-break)."""
        ids = self.grid.neighbourhood(p)
        rows = np.where(ids >= 0, self._row_of[np.maximum(ids, 0)], -1)
        return np.where(rows >= 0, self.index[np.maximum(rows, 0)], 0.0).mean(axis=-1)

    def centres(self) -> np.ndarray:
        """Centres (m, 3) of the stored voxels."""
        return self.grid.centres(self.voxel_ids)

    def reach_rows(self, rows: np.ndarray | None = None) -> np.ndarray:
        """Unpacked reachable bits (m, K) (or of the given rows)."""
        bits = self.reach_bits if rows is None else self.reach_bits[rows]
        return np.unpackbits(bits, axis=1, count=self.params.directions).astype(bool)

    def stats(self) -> dict:
        """Counts for reports: stored voxels, mean index, share of pairs reachable at all rolls."""
        k = self.params.directions
        reach = np.unpackbits(self.reach_bits, axis=1, count=k).sum()
        allr = np.unpackbits(self.all_roll_bits, axis=1, count=k).sum()
        return {
            "voxels_reachable": int(len(self.voxel_ids)),
            "mean_index": float(self.index.mean()) if len(self.index) else 0.0,
            "pairs_reachable": int(reach),
            "pairs_all_rolls": int(allr),
        }

    # -- files --------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write HDF5 atomically with params + schema_version as attributes."""

        def writer(tmp):
            with h5py.File(tmp, "w") as f:
                f.attrs["schema_version"] = SCHEMA_VERSION
                f.attrs["kind"] = KIND
                f.attrs["params"] = json.dumps(self.params.as_dict(), sort_keys=True)
                f.attrs["grid_origin"] = np.asarray(self.grid.origin, float)
                f.attrs["grid_shape"] = np.asarray(self.grid.shape, np.int64)
                f.attrs["voxel"] = float(self.grid.voxel)
                kw = {"compression": "gzip", "compression_opts": 4} if len(self.voxel_ids) else {}
                f.create_dataset("voxel_ids", data=self.voxel_ids, **kw)
                f.create_dataset("reach_bits", data=self.reach_bits, **kw)
                f.create_dataset("all_roll_bits", data=self.all_roll_bits, **kw)
                f.create_dataset("index", data=self.index.astype(np.float32), **kw)

        write_atomic(path, writer)


def load(path: str | os.PathLike, *, expect: dict | None = None) -> CapabilityMap:
    """Read a map written by :meth:`CapabilityMap.save`, checking kind, schema and parameters.

    Args:
        path: HDF5 file.
        expect: optional subset of parameters (keys of :meth:`MapParams.as_dict`) that must match.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError("map", f"file {path!r} does not exist")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError("map", f"{path} is not an HDF5 file ({exc})") from None
    with f:
        if f.attrs.get("kind") != KIND:
            raise InputError("map", f"{path} is a {f.attrs.get('kind')!r} file, expected {KIND!r}")
        version = int(f.attrs.get("schema_version", -1))
        if version != SCHEMA_VERSION:
            raise InputError(
                "map", f"{path} has schema_version {version}; this version reads {SCHEMA_VERSION}"
            )
        raw = json.loads(f.attrs["params"])
        params = MapParams(
            voxel=float(raw["voxel"]),
            directions=int(raw["directions"]),
            limits=str(raw["limits"]),
            X_FT=tuple(float(v) for v in raw["X_FT"]),
            tool=str(raw["tool"]),
            rolls=int(raw["rolls"]),
            self_collision=bool(raw.get("self_collision", False)),
        )
        grid = make_grid(params)
        if (
            tuple(f.attrs["grid_shape"]) != grid.shape
            or not np.allclose(f.attrs["grid_origin"], grid.origin)
            or float(f.attrs["voxel"]) != grid.voxel
        ):
            raise InputError("map", f"{path}: stored grid does not match its parameters")
        for name, value in (expect or {}).items():
            stored = params.as_dict().get(name)
            if stored is None or not _same(stored, value):
                raise InputError(
                    "map", f"{path} was built with {name}={stored!r}, expected {value!r}"
                )
        vox = f["voxel_ids"][()]
        reach = f["reach_bits"][()]
        allr = f["all_roll_bits"][()]
    nbytes = (params.directions + 7) // 8
    if reach.shape != (len(vox), nbytes) or allr.shape != reach.shape:
        raise InputError("map", f"{path}: bit arrays do not match {params.directions} directions")
    if len(vox) and (vox.min() < 0 or vox.max() >= grid.size):
        raise InputError("map", f"{path}: voxel ids outside the grid")
    return CapabilityMap(params, grid, vox.astype(np.int64), reach, allr)


def _same(a, b) -> bool:
    if isinstance(a, (list, tuple)) or isinstance(b, (list, tuple, np.ndarray)):
        return np.allclose(np.asarray(a, float), np.asarray(b, float))
    if isinstance(a, float) or isinstance(b, float):
        return bool(np.isclose(float(a), float(b)))
    return str(a) == str(b)


# ---------------------------------------------------------------------------------------------
# Accuracy against direct IK
# ---------------------------------------------------------------------------------------------


def random_poses(n: int, *, seed: int, radius: float | None = None, center=SHOULDER) -> np.ndarray:
    """``n`` random poses (n, 4, 4): position uniform in the ball (default: the arm's reach about
    the shoulder), rotation uniform on SO(3) (unit quaternions). Same seed -> same poses."""
    rng = np.random.default_rng(seed)
    radius = ARM_REACH if radius is None else radius
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    p = np.asarray(center) + v * radius * rng.random(n)[:, None] ** (1.0 / 3.0)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(n, 3, 3)  # fmt: skip
    X = np.zeros((n, 4, 4))
    X[:, :3, :3], X[:, :3, 3], X[:, 3, 3] = R, p, 1.0
    return X


def accuracy(cmap: CapabilityMap, poses: np.ndarray, *, exact_roll: bool = True) -> dict:
    """TP/FP/FN/TN of the map's answers against direct IK on ``poses`` (n, 4, 4), as the field
    reports them (fractions of all poses).

    Args:
        exact_roll: ground truth is IK of the exact pose (its roll included, true joint limits);
            False: ground truth is "some roll" (the map's own question), which isolates the
            discretization error.

    Returns:
        n, TP, FP, FN, TN, correct (fractions of all poses), truth_reachable, and the share of
        poses in partially reachable voxels (0 < index < 1) with the correct rate among them (the
        hard cases: poses in full or empty voxels are mostly answered right by construction).
    """
    p = cmap.params
    reach_map, index = cmap.query(poses)
    if exact_roll:
        truth = _collision_filter(p, ik(poses, limits=p.limits, X_FT=p.X_FT_matrix())).any(-1)
    else:
        truth, _ = _some_roll_truth(p, poses)
    n = len(poses)
    tp = np.sum(reach_map & truth)
    fp = np.sum(reach_map & ~truth)
    fn = np.sum(~reach_map & truth)
    tn = n - tp - fp - fn
    edge = (index > 0.0) & (index < 1.0)  # voxels where some directions are reachable, some not
    n_edge = int(edge.sum())
    edge_ok = float(np.mean(reach_map[edge] == truth[edge])) if n_edge else 1.0
    return {
        "n": int(n), "TP": float(tp / n), "FP": float(fp / n), "FN": float(fn / n),
        "TN": float(tn / n), "correct": float((tp + tn) / n),
        "truth_reachable": float(truth.mean()),
        "partial_voxel_share": float(n_edge / n), "partial_voxel_correct": edge_ok,
    }  # fmt: skip


def _some_roll_truth(params: MapParams, poses: np.ndarray):
    if params.rolls == 1:
        X_FT = params.X_FT_matrix()
        X_BF = poses @ invert(X_FT)
        res = ik(X_BF, limits=_relaxed_limits(params.limits))
        return _collision_filter(params, res).any(-1), None
    # sampled roll: the truth for "some roll" is approximated by a 4x finer roll sampling
    fine = make_params(
        params.voxel, params.directions, limits=params.limits, X_FT=params.X_FT_matrix(),
        tool=params.tool, rolls=4 * params.rolls,
    )  # fmt: skip
    gammas = 2.0 * np.pi * np.arange(fine.rolls) / fine.rolls
    c, s = np.cos(gammas), np.sin(gammas)
    Rz = np.zeros((fine.rolls, 4, 4))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2], Rz[:, 3, 3] = c, -s, s, c, 1, 1
    X = poses[:, None] @ Rz[None]
    res = ik(X, limits=params.limits, X_FT=params.X_FT_matrix())
    return _collision_filter(params, res).any(-1).any(-1), None


def blocks_of(params: MapParams, poses_per_block: int = 60_000) -> Sequence[np.ndarray]:
    """The voxel-id blocks :func:`build` hands to the executor (for external schedulers)."""
    grid = make_grid(params)
    per = max(1, poses_per_block // (params.directions * params.rolls))
    return _blocks(candidate_voxels(params, grid), per)
