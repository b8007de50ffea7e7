"""Capability map of the AUBO-i10 (+ tool): voxels x approach directions (seed 004 Sec. 3).

The workspace is cut into cubic voxels (edge ``voxel`` m) over the box that bounds the arm's reach;
each voxel gets ``K`` approach directions on the unit sphere (golden spiral). The reachability
index of a voxel is the fraction of its directions that are reachable (Sec. 3: "number of
reachable orientations in that voxel with respect to all the discretized orientations"), in [0, 1].

Answers (``MapParams.cell``) -- a map is a safety verdict, so what it says must be what exact IK
(:func:`systems.robot.kinematics.ik`, all 8 branches, the joint limits) at the pose itself says.
A query's cell (the voxel holding the position x the direction bin of its z axis x, for a
sampled roll, the roll bin) is **certified yes**, **certified no** or **undecided**, and
:meth:`CapabilityMap.answer` resolves undecided cells with closed-form IK at the pose (~2 us),
saying which it was (:data:`SOURCES`):

* ``"certified"`` (the default): the paper's IK samples at the voxel centres (below) and, from
  the same samples, a certificate per (voxel, direction, roll bin): one IK branch reaches the
  whole cell with room to its joint limits and singular values over first-order bounds on the
  IK (:mod:`systems.capability.certificate`). Measured (``analyses/bench_capmap.py
  --certificate-only``): 0 false yes; about two thirds of the IK-reachable poses of the oral
  region fall in certified cells, the rest are resolved by IK; the build takes about 1.5x the
  centre map's. Certified no: outside the grid or the reach sphere (rigorous).
* ``"centre"`` (the paper's map alone): IK at the voxel centre with +z along the bin's direction,
  some roll. Its bits are *not* a verdict: a lookup maps every pose in the voxel and in the bin's
  region of the sphere to that one sample. Measured (5 cm x 100, 20,000 uniform poses): 221
  false-safe (1.1 %), almost all at the workspace boundary (the elbow's reach, the shoulder
  cylinder), a few at joint limits, one kind a sampled map can never see: the 10 deg band of q5
  about +-180 deg (and of q1, q3) is a hole smaller than the sample spacing. Its answers are all
  resolved by IK.

The reachability index (the paper's: the share of a voxel's directions reachable at its centre,
some roll) comes from the centre samples in both kinds, so it is the same number.

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

Queries (:meth:`CapabilityMap.answer`, :meth:`CapabilityMap.query`) take a batch of poses in
base_link and return, per pose, the exact answer (and where it came from) and the voxel's index;
the paper's centre-sampled bit of the voxel and the direction nearest to the pose's z axis is
:meth:`CapabilityMap.query_points` (a compiled kernel, >2 M queries/s). Nearest direction uses a
lookup table over (polar angle, azimuth) cells (cell centre -> nearest spiral direction), at
least 128 x 256 cells: a cell's half-diagonal is <= 0.71 pi / 128 = 0.017 rad, ~20x below the
direction spacing even at K = 200, so only poses that close to a Voronoi border can get the
neighbour (the certificate's direction radii include it).

The map is built in independent voxel blocks through any ``concurrent.futures.Executor``
(:func:`build`; a ``ProcessPoolExecutor`` by default, a Dask client's from
:mod:`systems.capability.scaleout` for a cluster): :func:`build_block` is a pure top-level function
of
picklable inputs. A :class:`BlockStore` keeps finished blocks on disk as they arrive, so an
interrupted build resumes with only the missing blocks; blocks are joined in block order, so the
map does not depend on the engine, the completion order or the resumption.

Storage: HDF5 (h5py) with the parameters and ``schema_version`` as attributes; only voxels with at
least one reachable direction are stored (packed bits), with a dense int32 grid -> row table.
Schema 3 adds ``yes_bits`` (certified cells per direction x roll bin); schema 1 and 2 files are
refused with a message naming the file (rebuild them).

Departures from the paper: directions only (roll proved free or sampled as above), as the DLR
maps do for symmetric tools; the paper does not state its rotational grid.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from implantplan.systems import validate
from implantplan.systems.capability import certificate
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_atomic, write_json
from implantplan.systems.frames import invert
from implantplan.systems.jit import numba
from implantplan.systems.robot.kinematics import (
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
SCHEMA_VERSION = 3  # 3: per-(direction, roll) certified-yes bits beside the paper's bits
SLACK = float(np.radians(1.0))  # joint-limit margin of certified maps (rad)
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
YES, NO, UNDECIDED = np.int8(1), np.int8(-1), np.int8(0)  # a cell's verdict (CapabilityMap.verdict)
SOURCES = {1: "certified reachable", -1: "certified unreachable", 0: "resolved by IK"}
"""What an answer of :meth:`CapabilityMap.answer` rests on, by its ``source`` code."""
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


def roll_bins(R: np.ndarray, d: np.ndarray, rolls: int) -> np.ndarray:
    """Roll bin (n,) of rotations R (n, 3, 3) whose z axes the query gave directions d (n, 3):
    the roll of R about its z, measured from F(d) (:func:`frames_from_z`) carried to R's z by the
    shortest rotation (so it is continuous over d's region of the sphere), rounded to the
    nearest of the ``rolls`` samples 2 pi r / R."""
    if rolls == 1:
        return np.zeros(len(R), dtype=np.int64)
    z, x = R[:, :, 2], R[:, :, 0]
    xd = frames_from_z(d)[:, :, 0]
    a = np.cross(d, z)
    c = np.sum(d * z, axis=1, keepdims=True)
    x_ref = xd + np.cross(a, xd) + np.cross(a, np.cross(a, xd)) / (1.0 + c)  # Rodrigues, d -> z
    y_ref = np.cross(z, x_ref)
    gamma = np.arctan2(np.sum(x * y_ref, axis=1), np.sum(x * x_ref, axis=1))
    return np.rint(gamma * rolls / (2.0 * np.pi)).astype(np.int64) % rolls


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
            :mod:`systems.robot.collision_primitives` on links two or more apart must not overlap).
        cell: ``"certified"`` (default): the paper's centre-sampled bits plus a certificate per
            (voxel, direction, roll bin) (:mod:`systems.capability.certificate`, with ``slack``
            to spare at every joint limit); ``"centre"``: the paper's bits only (IK at the
            voxel centre and the direction, "some roll"); either way undecided cells are
            resolved by IK when queried (module docstring).
        slack: joint-limit margin in rad of the certificate (0 for ``"centre"``).
    """

    voxel: float
    directions: int
    limits: str = "175"
    X_FT: tuple = tuple(np.eye(4).ravel())
    tool: str = "flange"
    rolls: int = 1
    self_collision: bool = False
    cell: str = "certified"
    slack: float = SLACK

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
            "cell": str(self.cell),
            "slack": float(self.slack),
        }

    def describe(self) -> str:
        """One line for people: which map this is (what an index or an answer came from)."""
        return (f"{self.cell} map: {self.tool}, {self.voxel * 1e3:g} mm voxels, "
                f"{self.directions} directions x {self.rolls} roll(s), +-{self.limits} deg")

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
    cell: str = "certified",
    slack: float | None = None,
) -> MapParams:
    """Validated :class:`MapParams`; ``rolls`` defaults to 1 if roll is free, else 12;
    ``slack`` (rad) defaults to :data:`SLACK` for certified maps and is 0 for centre maps."""
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
    if cell not in ("certified", "centre"):
        raise InputError("cell", f"expected 'certified' or 'centre', got {cell!r}")
    if slack is None:
        slack = SLACK if cell == "certified" else 0.0
    if not np.isfinite(slack) or not 0.0 <= slack <= np.radians(10.0):
        raise InputError("slack", f"expected a margin in [0, 10 deg], got {slack!r} rad")
    if cell == "centre" and slack != 0.0:
        raise InputError("slack", "a centre-sampled map has no margin; use slack = 0")
    return MapParams(
        float(voxel),
        int(directions),
        limits,
        tuple(X.ravel()),
        tool,
        int(rolls),
        bool(self_collision),
        cell,
        float(slack),
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


def _limits_with_slack(limits: str, slack: float = 0.0) -> np.ndarray:
    """Joint limits (2, 6) narrowed by ``slack`` rad on both sides (the certified build's
    margin; joints whose range exceeds 2*pi keep a copy of every angle anyway)."""
    lim = joint_limits(limits).copy()
    lim[0] += slack
    lim[1] -= slack
    return lim


def relaxed_limits(limits: str, slack: float = 0.0) -> np.ndarray:
    lim = _limits_with_slack(limits, slack)
    lim[0, 5], lim[1, 5] = -2.0 * np.pi, 2.0 * np.pi
    return lim


def self_collision_free(q: np.ndarray) -> np.ndarray:
    """(..., 6) joint vectors -> (...) bool: no overlap between the bare arm's collision shapes
    (the URDF geometry through the conservative model of systems.robot.arm_collision, every pair the
    plant's SceneGraph does not filter: links two or more apart). Past joint 6 there is only the
    round wrist3 disc, so q6 moves the verdict only through the disc's enclosing boxes, at
    contact."""
    from implantplan.systems.robot.arm_collision import model_for

    q = np.asarray(q, dtype=float)
    d, _ = model_for(None, tool=False).clearance(q.reshape(-1, 6))
    return (d[:, 0] > 0.0).reshape(q.shape[:-1])


def _collision_filter(params: MapParams, res) -> np.ndarray:
    """IkResult.valid with self-colliding branches removed when the params ask for it."""
    if not params.self_collision:
        return res.valid
    valid = res.valid.copy()
    if valid.any():
        valid[valid] = self_collision_free(res.q[valid])
    return valid


def roll_frames(directions: np.ndarray, rolls: int) -> np.ndarray:
    """(K, R, 3, 3) the centre samples' rotations: F(d) Rz(2 pi r / R) (:func:`frames_from_z`)."""
    gammas = 2.0 * np.pi * np.arange(rolls) / rolls
    c, s = np.cos(gammas), np.sin(gammas)
    Rz = np.zeros((rolls, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    return frames_from_z(directions)[:, None] @ Rz[None]


def centre_samples(params: MapParams, centres: np.ndarray, directions: np.ndarray, *,
                   slack: float = 0.0):
    """IK (all 8 branches) at the cells' centre samples: positions ``centres`` (n, 3) x
    ``directions`` (k, 3) x the roll samples. Returns ``(R_s (k, R, 3, 3), res (IkResult over
    (n, k, R)), valid (n, k, R, 8))``; a free roll (R = 1) relaxes q6 (some roll), ``valid``
    drops self-colliding branches when the params ask, ``slack`` narrows the limits."""
    centres = np.asarray(centres, dtype=float)
    R_s = roll_frames(directions, params.rolls)
    n, k, r = len(centres), len(directions), params.rolls
    X = np.zeros((n, k, r, 4, 4))
    X[..., :3, :3] = R_s[None]
    X[..., :3, 3] = centres[:, None, None]
    X[..., 3, 3] = 1.0
    lim = relaxed_limits(params.limits, slack) if r == 1 else _limits_with_slack(params.limits,
                                                                                slack)
    X_FT = params.X_FT_matrix()
    res = ik(X, limits=lim, X_FT=None if np.allclose(X_FT, np.eye(4)) else X_FT)
    return R_s, res, _collision_filter(params, res)


def _roll_answers(params: MapParams, res, valid: np.ndarray, slack: float = 0.0):
    """(reachable, all_rolls) (n, k) of centre samples: some roll / every roll (module
    docstring: exact for a free roll, over the samples otherwise)."""
    if params.rolls > 1:
        per_roll = valid.any(-1)
        return per_roll.any(-1), per_roll.all(-1)
    valid, q6 = valid[:, :, 0], res.q[:, :, 0, :, 5]
    reachable = valid.any(-1)
    lim = _limits_with_slack(params.limits, slack)
    gap = 2.0 * np.pi - (lim[1, 5] - lim[0, 5])
    if gap <= 0.0:
        return reachable, reachable.copy()
    q6 = np.where(valid, q6, np.nan)  # (n, k, 8)
    d = np.abs(q6[..., :, None] - q6[..., None, :])
    d = np.minimum(d, 2.0 * np.pi - d)
    spread = np.nanmax(np.where(np.isnan(d), -1.0, d), axis=(-1, -2))
    return reachable, reachable & (spread >= gap)


def reach_at(
    params: MapParams, centres: np.ndarray, directions: np.ndarray, *, slack: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Reachability of the mapped frame at ``centres`` (n, 3) x ``directions`` (k, 3).

    Args:
        slack: joint-limit margin in rad: a branch counts only if every joint lies at least this
            far inside its limits (the q6 gap of the flange grows by 2 slack).

    Returns:
        ``(reachable, all_rolls)``: bool (n, k) each; see the module docstring for the roll.
    """
    _, res, valid = centre_samples(params, centres, directions, slack=slack)
    return _roll_answers(params, res, valid, slack)


@functools.lru_cache(maxsize=8)
def direction_radii(k: int) -> np.ndarray:
    """(K,) the largest angle between each of the ``k`` golden-spiral directions and the z axes
    the query gives it (:func:`systems.capability.certificate.direction_radii` over
    :func:`direction_table`); cached, read-only."""
    dirs = golden_spiral(k)
    out = certificate.direction_radii(dirs, direction_table(dirs))
    out.flags.writeable = False
    return out


def build_block(params: MapParams, voxel_ids: np.ndarray, *, certify_options: dict | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One independent unit of work: the cells of the given voxels (picklable in and out).

    IK at every cell's centre sample gives the paper's bits (some roll, every roll; the
    reachability index) and, for a certified map, the certificate of each (direction, roll) cell
    from the same samples (:mod:`systems.capability.certificate`). A map that checks
    self-collision certifies nothing (the certificate does not bound the arm's clearance): its
    cells are all resolved by IK.

    Args:
        certify_options: keyword arguments passed on to
            :func:`systems.capability.certificate.certify` (tests: a term dropped).

    Returns:
        ``(voxel_ids, reachable_bits, all_roll_bits, yes_bits)``: bits packed along the
        direction axis (np.packbits, big-endian; ``yes_bits`` along direction x roll, d * R + r),
        only for voxels with >= 1 reachable direction.
    """
    grid = make_grid(params)
    dirs = golden_spiral(params.directions)
    voxel_ids = np.asarray(voxel_ids, dtype=np.int64)
    centres = grid.centres(voxel_ids)
    R_s, res, valid = centre_samples(params, centres, dirs)
    reach, allr = _roll_answers(params, res, valid)
    keep = reach.any(axis=1)
    k, r = params.directions, params.rolls
    if params.cell == "certified" and not params.self_collision and keep.any():
        yes = certificate.certify(
            res.q[keep], (valid & ~res.singular)[keep], R_s, centres[keep],
            alpha=direction_radii(params.directions), voxel=params.voxel, X_FT=params.X_FT_matrix(),
            limits=joint_limits(params.limits), slack=params.slack, rolls=r,
            **(certify_options or {}),
        )  # fmt: skip
    else:
        yes = np.zeros((int(keep.sum()), k, r), dtype=bool)
    return (
        voxel_ids[keep].astype(np.int64),
        np.packbits(reach[keep], axis=1),
        np.packbits(allr[keep], axis=1),
        np.packbits(yes.reshape(len(yes), k * r), axis=1),
    )


def _blocks(ids: np.ndarray, per_block: int) -> list[np.ndarray]:
    return [ids[i : i + per_block] for i in range(0, len(ids), per_block)]


class BlockStore:
    """Finished blocks of one build on disk, so an interrupted build resumes where it stopped.

    The folder (``<out>.blocks-<key>`` beside the map file, :meth:`beside`) is keyed by the map
    parameters and the block size, so blocks of a different map never mix in. Each block is an
    ``.npz`` (voxel ids and the three packed bit arrays of :func:`build_block`) written atomically;
    a block file that does not read back as the block it names counts as missing. ``manifest.json``
    records what the blocks are of. Counters: ``reused`` (read back), ``written`` (this run).
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        params: MapParams,
        blocks: Sequence[np.ndarray],
        *,
        poses_per_block: int,
    ):
        self.folder = Path(folder)
        self.params = params
        self.blocks = blocks
        self.poses_per_block = int(poses_per_block)
        self.reused = 0
        self.written = 0

    @staticmethod
    def key(params: MapParams, poses_per_block: int) -> str:
        text = json.dumps(
            {
                "params": params.as_dict(),
                "poses_per_block": int(poses_per_block),
                "schema_version": SCHEMA_VERSION,
            },
            sort_keys=True,
        )
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    @classmethod
    def beside(
        cls, out: str | os.PathLike, params: MapParams, *, poses_per_block: int = 60_000
    ) -> BlockStore:
        """The store of a build whose map goes to ``out``."""
        out = Path(out)
        folder = out.with_name(f"{out.name}.blocks-{cls.key(params, poses_per_block)}")
        return cls(
            folder, params, blocks_of(params, poses_per_block), poses_per_block=poses_per_block
        )

    def _path(self, i: int):
        return self.folder / f"block-{i:06d}.npz"

    def finished(self) -> list[int]:
        """Indices of the blocks on disk (present files; validity is checked on :meth:`read`)."""
        if not self.folder.is_dir():
            return []
        return [i for i in range(len(self.blocks)) if self._path(i).is_file()]

    def open(self) -> None:
        """Create the folder and its manifest (kept if already there)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        manifest = self.folder / "manifest.json"
        if not manifest.is_file():
            write_json(
                manifest,
                {
                    "params": self.params.as_dict(),
                    "blocks": len(self.blocks),
                    "poses_per_block": self.poses_per_block,
                },
                kind="capability_map_blocks",
            )

    def read(self, i: int):
        """Block ``i`` as :func:`build_block` returned it, or None if missing or not that block."""
        nbytes = (self.params.directions + 7) // 8
        ybytes = (self.params.directions * self.params.rolls + 7) // 8
        try:
            with np.load(self._path(i), allow_pickle=False) as z:
                vox, reach, allr = z["voxel_ids"], z["reach_bits"], z["all_roll_bits"]
                yes = z["yes_bits"]
        except (OSError, KeyError, ValueError):
            return None
        if (
            vox.ndim != 1
            or reach.shape != (len(vox), nbytes)
            or allr.shape != reach.shape
            or yes.shape != (len(vox), ybytes)
            or not np.all(np.isin(vox, self.blocks[i]))
        ):
            return None
        self.reused += 1
        return vox.astype(np.int64), reach, allr, yes

    def write(self, i: int, result) -> None:
        vox, reach, allr, yes = result

        def writer(tmp):
            with open(tmp, "wb") as f:
                np.savez(f, voxel_ids=vox, reach_bits=reach, all_roll_bits=allr, yes_bits=yes)

        write_atomic(self._path(i), writer)
        self.written += 1

    def remove_partial(self) -> None:
        """Delete temporary files of blocks being written when the build stopped (a signal
        that lands between creating the temporary file and its cleanup leaves one)."""
        if self.folder.is_dir():
            for tmp in self.folder.glob(".block-*"):
                tmp.unlink(missing_ok=True)

    def remove(self) -> None:
        """Delete the folder (after the map file is written)."""
        shutil.rmtree(self.folder, ignore_errors=True)


def build(
    params: MapParams,
    *,
    executor: Executor | None = None,
    workers: int | None = None,
    poses_per_block: int = 60_000,
    progress: Callable[[int, int], None] | None = None,
    store: BlockStore | None = None,
) -> CapabilityMap:
    """Build the map in independent voxel blocks.

    Args:
        params: from :func:`make_params`.
        executor: any ``concurrent.futures.Executor`` (e.g. a Dask client's,
            :mod:`systems.capability.scaleout`); by default a ``ProcessPoolExecutor(workers)``;
            ``workers=1`` runs in this process.
        workers: process count for the default executor (default: os.cpu_count()).
        poses_per_block: IK poses per block (memory ~ 450 B per pose).
        progress: ``progress(done_blocks, n_blocks)`` callback, blocks read from ``store``
            included (called once with them before any is computed).
        store: a :class:`BlockStore` of these blocks: blocks already in it are read, not
            computed; every computed block is written to it as soon as it arrives (in completion
            order). The result does not depend on the order: blocks are joined in block order.
    """
    grid = make_grid(params)
    ids = candidate_voxels(params, grid)
    per = max(1, poses_per_block // (params.directions * params.rolls))
    blocks = _blocks(ids, per)
    results: list = [None] * len(blocks)
    if store is not None:
        if len(store.blocks) != len(blocks) or store.poses_per_block != poses_per_block:
            raise InputError("store", f"{store.folder} holds blocks of another partition")
        store.open()
        store.remove_partial()  # of a build killed before its cleanup ran
        for i in store.finished():
            results[i] = store.read(i)
    todo = [i for i, r in enumerate(results) if r is None]
    done = len(blocks) - len(todo)
    if progress and done:
        progress(done, len(blocks))

    def finish(i, r):
        nonlocal done
        results[i] = r
        if store is not None:
            store.write(i, r)
        done += 1
        if progress:
            progress(done, len(blocks))

    try:
        if executor is None and (workers == 1 or len(todo) <= 1):
            for i in todo:
                finish(i, build_block(params, blocks[i]))
        else:
            own = executor is None
            ex = executor or ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1)
            futures = {ex.submit(build_block, params, blocks[i]): i for i in todo}
            try:
                for f in as_completed(futures):
                    finish(futures[f], f.result())
            finally:
                from implantplan.systems.capability.scaleout import cancel_pending

                cancel_pending(futures, ex)
                if own:
                    ex.shutdown()
    except BaseException:  # Ctrl-C, SIGTERM, a failed block: the finished blocks stay
        if store is not None:
            store.remove_partial()
        raise
    if not results:
        return empty_map(params)
    return CapabilityMap(params, grid, *(np.concatenate([r[i] for r in results]) for i in range(4)))


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


def _poses(X_BP) -> np.ndarray:
    X = np.asarray(X_BP, dtype=float)
    if X.ndim < 2 or X.shape[-2:] != (4, 4):
        raise InputError("poses", f"expected poses of shape (..., 4, 4), got {X.shape}")
    if not np.all(np.isfinite(X)):
        raise InputError("poses", "poses must be finite (found NaN or inf)")
    return X


def empty_map(params: MapParams) -> CapabilityMap:
    """A map of ``params`` with no voxel stored (every answer resolved by IK, or "no" outside
    the reach sphere)."""
    k, r = params.directions, params.rolls
    z = np.zeros((0, (k + 7) // 8), np.uint8)
    return CapabilityMap(params, make_grid(params), np.zeros(0, np.int64), z, z.copy(),
                         np.zeros((0, (k * r + 7) // 8), np.uint8))


@dataclass
class CapabilityMap:
    """A built map: params, grid, the stored voxels and their bits.

    Attributes:
        params: :class:`MapParams`.
        grid: :class:`Grid`.
        voxel_ids: (m,) linear ids of voxels with >= 1 reachable direction at the centre.
        reach_bits: (m, ceil(K/8)) uint8 packed bits "reachable at the voxel centre, some roll"
            (the paper's centre-sampled map: the reachability index and RASSCMAP's c_s).
        all_roll_bits: (m, ceil(K/8)) uint8 packed bits "reachable at the centre at every roll".
        yes_bits: (m, ceil(K R/8)) uint8 packed bits, direction-major (d * R + r): the cell
            (voxel, direction d, roll bin r) is certified reachable throughout
            (:mod:`systems.capability.certificate`; a free roll: every roll). None: no cell is
            certified (all zero).
    """

    params: MapParams
    grid: Grid
    voxel_ids: np.ndarray
    reach_bits: np.ndarray
    all_roll_bits: np.ndarray
    yes_bits: np.ndarray | None = None
    directions: np.ndarray = field(init=False, repr=False)
    index: np.ndarray = field(init=False, repr=False)
    _row_of: np.ndarray = field(init=False, repr=False)
    _table: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        k = self.params.directions
        if self.yes_bits is None:
            width = (k * self.params.rolls + 7) // 8
            self.yes_bits = np.zeros((len(self.voxel_ids), width), dtype=np.uint8)
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
        """(reachable, index) for positions (n, 3) and approach directions (n, 3) in base_link from
        the centre-sampled bits (the paper's map, some roll; not a verdict: :meth:`answer` is)."""
        p = np.ascontiguousarray(np.asarray(p, dtype=float).reshape(-1, 3))
        z = np.ascontiguousarray(np.asarray(z_axis, dtype=float).reshape(-1, 3))
        if len(p) != len(z):
            raise InputError("poses", "positions and directions differ in count")
        reach = np.empty(len(p), dtype=bool)
        index = np.empty(len(p), dtype=np.float64)
        _query_kernel(p, z, *self.kernel_args(), self.index, reach, index)
        return reach, index

    def verdict(self, X_BP: np.ndarray) -> np.ndarray:
        """The map's own answer (n,) int8 for poses (n, 4, 4) in base_link: :data:`YES` (the
        pose's cell is certified reachable), :data:`NO` (no pose there can be reached: outside
        the grid or the reach sphere) or :data:`UNDECIDED`; no IK is run."""
        X = _poses(X_BP).reshape(-1, 4, 4)
        p = X[:, :3, 3]
        out = np.full(len(X), UNDECIDED, dtype=np.int8)
        c = self.grid.cells(p)
        inside = np.all((c >= 0) & (c < np.asarray(self.grid.shape)), axis=1)
        far = (np.linalg.norm(p - SHOULDER, axis=1) > reach_radius(self.params)) | ~inside
        out[far] = NO
        ids = np.ravel_multi_index(np.clip(c, 0, np.asarray(self.grid.shape) - 1).T,
                                   self.grid.shape)
        rows = np.where(inside, self._row_of[ids], -1)
        have = np.flatnonzero(rows >= 0)
        if have.size:
            d = self.nearest_direction(X[have, :3, 2])
            r = roll_bins(X[have, :3, :3], self.directions[d], self.params.rolls)
            bit = d * self.params.rolls + r
            row = rows[have]
            yes = (self.yes_bits[row, bit >> 3] >> (7 - (bit & 7))) & 1 == 1
            out[have[yes]] = YES
        return out.reshape(np.shape(X_BP)[:-2])

    def answer(self, X_BP: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The exact answer for poses (..., 4, 4) in base_link, and where it came from.

        Returns:
            ``(reachable, source, index)``: reachable (bool); source (int8) :data:`YES` or
            :data:`NO` (certified by the map) or :data:`UNDECIDED` (the cell is undecided, the
            answer is closed-form IK at the pose, :func:`exact_reachable`); index: the
            centre-sampled reachability index of the pose's voxel (the paper's, 0 outside).
        """
        X = _poses(X_BP)
        shape = X.shape[:-2]
        flat = X.reshape(-1, 4, 4)
        source = self.verdict(flat)
        reach = source == YES
        todo = np.flatnonzero(source == UNDECIDED)
        if todo.size:
            reach[todo] = exact_reachable(self.params, flat[todo])
        _, index = self.query_points(flat[:, :3, 3], flat[:, :3, 2])
        return reach.reshape(shape), source.reshape(shape), index.reshape(shape)

    def query(self, X_BP: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(reachable, index) for poses (..., 4, 4) in base_link, the pose's z the approach:
        the exact answer (certified cells as the map says, undecided ones by IK at the pose)
        and the voxel's reachability index (:meth:`answer`)."""
        reach, _, index = self.answer(X_BP)
        return reach, index

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
        """Counts for reports: stored voxels, mean index, (voxel, direction) pairs reachable at
        the centre (some roll, every roll), certified cells (voxel, direction, roll bin) and
        the cells of the stored voxels."""
        k, r = self.params.directions, self.params.rolls
        reach = np.unpackbits(self.reach_bits, axis=1, count=k).sum()
        allr = np.unpackbits(self.all_roll_bits, axis=1, count=k).sum()
        yes = np.unpackbits(self.yes_bits, axis=1, count=k * r).sum()
        return {
            "voxels_reachable": int(len(self.voxel_ids)),
            "mean_index": float(self.index.mean()) if len(self.index) else 0.0,
            "pairs_reachable": int(reach),
            "pairs_all_rolls": int(allr),
            "cells_certified": int(yes),
            "cells_stored": int(len(self.voxel_ids) * k * r),
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
                f.create_dataset("yes_bits", data=self.yes_bits, **kw)
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
        if version == 1:
            raise InputError(
                "map",
                f"{path} is a schema_version 1 map: sampled at voxel centres only, it can say "
                "reachable where exact IK fails; rebuild it with `implantplan capmap build` "
                f"(this version reads {SCHEMA_VERSION}, certified cells)",
            )
        if version == 2:
            raise InputError(
                "map",
                f"{path} is a schema_version 2 map: its certificate is for every roll at once "
                "(it certifies almost no cell of an off-axis tool) and its index is not the "
                "paper's; rebuild it with `implantplan capmap build` (this version reads "
                f"{SCHEMA_VERSION}: per-roll certified cells, undecided ones resolved by IK)",
            )
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
            cell=str(raw["cell"]),
            slack=float(raw["slack"]),
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
        yes = f["yes_bits"][()] if "yes_bits" in f else None
    nbytes = (params.directions + 7) // 8
    ybytes = (params.directions * params.rolls + 7) // 8
    if (reach.shape != (len(vox), nbytes) or allr.shape != reach.shape or yes is None
            or yes.shape != (len(vox), ybytes)):
        raise InputError("map", f"{path}: bit arrays do not match {params.directions} directions"
                         f" x {params.rolls} roll(s)")
    if len(vox) and (vox.min() < 0 or vox.max() >= grid.size):
        raise InputError("map", f"{path}: voxel ids outside the grid")
    return CapabilityMap(params, grid, vox.astype(np.int64), reach, allr, yes)


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


def region_poses(X_targets: np.ndarray, n: int, *, seed: int, margin: float = 0.03,
                 cone: float = np.radians(45.0)) -> np.ndarray:
    """``n`` poses (n, 4, 4) uniform over a task region: positions uniform in the axis-aligned
    box bounding the targets' origins grown by ``margin`` (m), z axes uniform in the cone of
    half angle ``cone`` (rad) about the targets' mean z axis, rolls uniform in [0, 2 pi). For
    the oral region: the feeding targets of a plan, in the robot's base frame. Same seed -> same
    poses."""
    X_targets = np.asarray(X_targets, dtype=float).reshape(-1, 4, 4)
    rng = np.random.default_rng(seed)
    lo = X_targets[:, :3, 3].min(axis=0) - margin
    hi = X_targets[:, :3, 3].max(axis=0) + margin
    axis = X_targets[:, :3, 2].mean(axis=0)
    axis /= np.linalg.norm(axis)
    c = rng.uniform(np.cos(cone), 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    s = np.sqrt(1.0 - c * c)
    z = np.stack([s * np.cos(phi), s * np.sin(phi), c], axis=1) @ frames_from_z(axis).T
    g = rng.uniform(0.0, 2.0 * np.pi, n)
    Rz = np.zeros((n, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = (
        np.cos(g), -np.sin(g), np.sin(g), np.cos(g), 1.0)  # fmt: skip
    X = np.zeros((n, 4, 4))
    X[:, :3, :3] = frames_from_z(z) @ Rz
    X[:, :3, 3] = rng.uniform(lo, hi, (n, 3))
    X[:, 3, 3] = 1.0
    return X


def regional_map(params: MapParams, p: np.ndarray, *, pad: int = 1,
                 certify_options: dict | None = None) -> CapabilityMap:
    """The map of ``params`` over the voxels holding the positions ``p`` (n, 3) and ``pad``
    voxels around them (built in this process, one block: the plan's capability check and the
    oral-region measurements need the map where the tasks are, not the whole workspace)."""
    grid = make_grid(params)
    c = np.unique(grid.cells(np.asarray(p, dtype=float).reshape(-1, 3)), axis=0)
    r = np.arange(-pad, pad + 1)
    offs = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    c = np.unique((c[:, None] + offs[None]).reshape(-1, 3), axis=0)
    c = c[np.all((c >= 0) & (c < np.asarray(grid.shape)), axis=1)]
    ids = np.ravel_multi_index(c.T, grid.shape)
    return CapabilityMap(params, grid, *build_block(params, ids, certify_options=certify_options))


def accuracy(cmap: CapabilityMap, poses: np.ndarray, *, exact_roll: bool = True) -> dict:
    """The map against direct IK on ``poses`` (n, 4, 4), as the field reports it.

    Args:
        exact_roll: True: the map's answer (:meth:`CapabilityMap.answer`: certified cells, the
            undecided ones by IK at the pose) against IK of the exact pose (its roll, true joint
            limits), with the certificate's own counts; False: the centre-sampled bits (the
            paper's map, :meth:`CapabilityMap.query_points`) against "some roll" (the paper's
            question), which isolates the discretization error.

    Returns:
        n, TP, FP, FN, TN, correct (fractions of all poses), truth_reachable, false_safe (count
        of FP), rejected_reachable (FN / reachable), the share of poses in partially reachable
        voxels (0 < index < 1) with the correct rate among them; with ``exact_roll`` also
        certified_yes / certified_no / resolved_by_ik (shares of the poses), false_yes /
        false_no (counts: a certified verdict exact IK contradicts) and coverage (the share of
        the IK-reachable poses whose cell is certified reachable).
    """
    p = cmap.params
    if exact_roll:
        truth = exact_reachable(p, poses)
        reach_map, source, index = cmap.answer(poses)
    else:
        truth, _ = some_roll_truth(p, poses)
        reach_map, index = cmap.query_points(poses[:, :3, 3], poses[:, :3, 2])
    n = len(poses)
    tp = np.sum(reach_map & truth)
    fp = np.sum(reach_map & ~truth)
    fn = np.sum(~reach_map & truth)
    tn = n - tp - fp - fn
    edge = (index > 0.0) & (index < 1.0)  # voxels where some directions are reachable, some not
    n_edge = int(edge.sum())
    edge_ok = float(np.mean(reach_map[edge] == truth[edge])) if n_edge else 1.0
    out = {
        "n": int(n), "TP": float(tp / n), "FP": float(fp / n), "FN": float(fn / n),
        "TN": float(tn / n), "correct": float((tp + tn) / n),
        "truth_reachable": float(truth.mean()),
        "partial_voxel_share": float(n_edge / n), "partial_voxel_correct": edge_ok,
        "false_safe": int(fp), "rejected_reachable": float(fn / max(tp + fn, 1)),
    }  # fmt: skip
    if exact_roll:
        yes, no = source == YES, source == NO
        out.update({
            "certified_yes": float(yes.mean()), "certified_no": float(no.mean()),
            "resolved_by_ik": float(np.mean(source == UNDECIDED)),
            "false_yes": int(np.sum(yes & ~truth)), "false_no": int(np.sum(no & truth)),
            "coverage": float(np.sum(yes & truth) / max(int(truth.sum()), 1)),
        })  # fmt: skip
    return out


def exact_reachable(params: MapParams, poses: np.ndarray) -> np.ndarray:
    """The exact reference (n,) bool: closed-form IK at the pose itself (its roll, the true joint
    limits, self-collision when the map checks it) has a branch."""
    res = ik(poses, limits=params.limits, X_FT=params.X_FT_matrix())
    return _collision_filter(params, res).any(-1)


BOUNDARY_ROUND = 100_000  # pairs per round of boundary_poses (memory: 13 MB of poses each)
BOUNDARY_RATE_FLOOR = 10_000
BOUNDARY_GIVE_UP = 2_000_000  # pairs drawn without one on the boundary: there is none


def boundary_poses(
    params: MapParams,
    n: int,
    *,
    seed: int,
    step: float | None = None,
    angle: float = 0.35,
    center=SHOULDER,
    radius: float | None = None,
) -> np.ndarray:
    """``n`` poses (n, 4, 4) within ~1e-7 (m, rad) of the exact reachability boundary, about half
    on each side: the hardest cases for a map. Pairs of a random pose (:func:`random_poses` over
    the reach ball) and a neighbour (position moved ~``step``, default one voxel, rotation turned
    up to ``angle`` rad about a random axis) that exact IK (:func:`exact_reachable`) answers
    differently are bisected along the straight path between them (24 halvings); both ends of
    the final bracket are kept. ``center``/``radius``: the ball the random poses are drawn from
    (default: the reach ball). Same seed -> same poses."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    step = params.voxel if step is None else float(step)
    radius = reach_radius(params) if radius is None else radius
    out, have, drawn, kept = [], 0, 0, 0
    while have < n:
        if have == 0 and drawn >= BOUNDARY_GIVE_UP:
            raise InputError("center", f"no reachability boundary found in the ball of radius "
                             f"{radius} m about {np.round(center, 4).tolist()} "
                             f"({drawn:,} pairs drawn)")
        # pairs for the poses still missing at the share of pairs kept so far (at most one in
        # BOUNDARY_RATE_FLOOR assumed before any is kept), in rounds of at most BOUNDARY_ROUND
        rate = max(kept / drawn, 1.0 / BOUNDARY_RATE_FLOOR) if drawn else 1.0 / 8
        m = int(min(max(1.2 * (n - have) / (2 * rate), 2000), BOUNDARY_ROUND))
        A = random_poses(m, seed=int(rng.integers(2**31)), radius=radius, center=center)
        axis = rng.normal(size=(m, 3))
        w = axis / np.linalg.norm(axis, axis=1, keepdims=True) * angle * rng.random((m, 1))
        dp = rng.normal(size=(m, 3)) * step

        def at(t, A=A, w=w, dp=dp):
            X = A.copy()
            X[:, :3, :3] = A[:, :3, :3] @ Rotation.from_rotvec(w * t[:, None]).as_matrix()
            X[:, :3, 3] += dp * t[:, None]
            return X

        ra = exact_reachable(params, A)
        keep = ra != exact_reachable(params, at(np.ones(m)))
        A, w, dp, ra = A[keep], w[keep], dp[keep], ra[keep]
        drawn, kept = drawn + m, kept + len(A)
        lo, hi = np.zeros(len(A)), np.ones(len(A))
        for _ in range(24):
            mid = 0.5 * (lo + hi)
            same = exact_reachable(params, at(mid, A, w, dp)) == ra
            lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
        out.append(np.stack([at(lo, A, w, dp), at(hi, A, w, dp)], axis=1).reshape(-1, 4, 4))
        have += 2 * len(A)
    return np.concatenate(out)[:n]


def corner_poses(cmap: CapabilityMap, n: int, *, seed: int, far: float = 0.8) -> np.ndarray:
    """``n`` poses (n, 4, 4) at the far ends of the map's certified-yes cells, where a
    first-order certificate errs first: a certified (voxel, direction, roll bin) drawn at random,
    the position at a corner of the voxel (70 %) or anywhere in it, the z axis on the edge of
    the direction's region of the query's lookup (found by bisection along a random great circle
    from d; ``far`` of the poses there, the rest inside), the roll at an edge of its bin (80 %,
    per :func:`roll_bins`) or anywhere in it. Every pose is one the map's own lookup sends to a
    certified cell (a few on a lookup border may land in the neighbouring cell: the map's
    :meth:`CapabilityMap.verdict` says which). Empty when nothing is certified. Same seed, same
    poses."""
    rng = np.random.default_rng(seed)
    k, r_n = cmap.params.directions, cmap.params.rolls
    yes = np.unpackbits(cmap.yes_bits, axis=1, count=k * r_n).reshape(-1, k, r_n)
    rows, ds, rs = np.nonzero(yes)
    if rows.size == 0:
        return np.zeros((0, 4, 4))
    pick = rng.integers(rows.size, size=n)
    row, d, r = rows[pick], ds[pick], rs[pick]
    h = 0.5 * cmap.params.voxel * (1.0 - 1e-9)
    c = cmap.centres()[row]
    corner = c + h * rng.choice([-1.0, 1.0], size=(n, 3))
    p = np.where(rng.random((n, 1)) < 0.7, corner, c + rng.uniform(-h, h, (n, 3)))
    D = cmap.directions[d]
    u = rng.normal(size=(n, 3))
    u -= np.sum(u * D, axis=1, keepdims=True) * D
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    lo, hi = np.zeros(n), np.full(n, np.pi / 2)
    for _ in range(30):  # the largest angle along u whose z the lookup still sends to d
        mid = 0.5 * (lo + hi)
        z = np.cos(mid)[:, None] * D + np.sin(mid)[:, None] * u
        same = cmap.nearest_direction(z) == d
        lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
    t = np.where(rng.random(n) < far, lo, lo * rng.random(n))
    z = np.cos(t)[:, None] * D + np.sin(t)[:, None] * u
    x_d = frames_from_z(D)[:, :, 0]  # roll_bins' reference: F(d) carried from d to z
    a = np.cross(D, z)
    x_ref = x_d + np.cross(a, x_d) + np.cross(a, np.cross(a, x_d)) / (
        1.0 + np.sum(D * z, axis=1, keepdims=True))
    y_ref = np.cross(z, x_ref)
    edge = rng.choice([-0.4999, 0.4999], size=n)
    g = 2.0 * np.pi * (r + np.where(rng.random(n) < 0.8, edge, rng.uniform(-0.5, 0.5, n))) / r_n
    x = np.cos(g)[:, None] * x_ref + np.sin(g)[:, None] * y_ref
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    X = np.zeros((n, 4, 4))
    X[:, :3, :3] = np.stack([x, np.cross(z, x), z], axis=-1)
    X[:, :3, 3], X[:, 3, 3] = p, 1.0
    return X


def some_roll_truth(params: MapParams, poses: np.ndarray):
    if params.rolls == 1:
        X_FT = params.X_FT_matrix()
        X_BF = poses @ invert(X_FT)
        res = ik(X_BF, limits=relaxed_limits(params.limits))
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
