"""RASSCMAP: surgery-specific capability maps and setup optimization (seed 004 Sec. 3-4).

Everything in world W (z up) unless a name says otherwise; a robot base pose is X_WB; the
capability map (:mod:`systems.capability_map`) answers in base_link B.

**Unconstrained access** (Sec. 3.1, Fig. 4). The body part is approximated by a cylinder whose
cross-section is a circular arc of arc length ``a`` and chord ``c``: solve a = r*theta and
c = 2 r sin(theta/2) for the radius r and the arc angle theta (:func:`arc_radius`; the equation
c/a = sin(theta/2)/(theta/2) has one root in (0, 2*pi) for 0 < c < a, found by Brent's method).
Points: n = floor(theta / d_r) + 1 rotations Theta_i evenly from pi/2 - theta/2 to pi/2 + theta/2,
x = r cos Theta_i, y = r sin Theta_i - r cos(theta/2) (so the chord lies on y = 0), z from 0 to l in
steps d_t; one layer per voxel of depth, each layer's radius grown by the voxel size. These points
are given in the body-part frame P (x across the body, y up out of the table, z along the body),
transformed to W by X_WP and to the robot by X_BW; each point's capability is the CMAP index of its
voxel. c_s = mean over the points.

**Constrained access** (Sec. 3.2, Algorithms 1 and 2). A trocar at X_WA (z into the patient) is the
remote centre of motion. Algorithm 1 (:func:`pivot_voxels`): directions d = R_WA Rx(alpha)
Ry(beta) e_z with |alpha|, |beta| <= 90 deg in steps d_R (the hemisphere), tip depths rho = l_c + s,
s = v, 2v, ..., depth (l_c = cannula length, v = voxel size). With the instrument joints at zero the
tip is at p_A + rho d and the robot's mapped frame (where the shaft starts) at
p_A - (l_s + l_i - rho) d with approach d; a tip voxel is a *pivot voxel* when the CMAP has that
(position, direction). Algorithm 2 (:func:`add_orientations`): at each pivot voxel centre v_s with
D = |v_s - p_A| the instrument bends by delta in [0, 90 deg] (pitch/yaw joints +-90 deg) in any
plane psi about u = (v_s - p_A)/D (the robot's roll turns the bend plane). The law of sines in the
triangle trocar - instrument joint - tip gives the shaft's angle to u, phi = asin(l_i sin(delta) /
D), the instrument's angle to u, delta - phi, and the trocar-joint distance
|AJ| = D sin(delta - phi) / sin(delta). A sample counts when the joint is past the cannula
(|AJ| >= l_c, or delta = 0), the shaft is within the hemisphere and the CMAP has the shaft's start
point with the shaft direction; its instrument direction is then added (nearest golden-spiral
direction) to the voxel. A voxel's index = its directions / K; c_s = the sum of the indices over
all hemisphere voxels / their number (unreached voxels count 0, as in the unconstrained map).
Departure: the paper sweeps pitch and yaw; we sweep the bend (delta, psi) directly - the same cone
of instrument directions, sampled evenly in angle.

**Cost** (Sec. 4.2, DESIGN.md 6) of a setup (base pose, access point) for m task poses:

    f = 0                                  if any task pose is unreachable (r_t,i = 0),
    f = ( (1/m) sum_i c_t,i + c_s ) / 2    otherwise,

with c_t,i the capability index of the voxel holding task pose i and r_t,i its reachability
(unconstrained: the CMAP bit of the pose's approach direction; constrained: the RASSCMAP bit).
Ties (common: with this 6-axis arm about half of the map has index 1, so f saturates at 1) go to
the larger :func:`task_margin` (mean index of the 27 voxels around each task position: tolerance
to a base placed a voxel off), then to the candidate deepest inside the tied set (farthest from
any worse candidate), then to the lower id. This tie-break is our addition (the paper's GA
returns one of the tied optima at random).

**Optimization**: :func:`optimize` with ``method="exhaustive"`` evaluates every candidate (exact),
``"ga"`` runs :func:`genetic_search` (a small vectorized GA over the discrete candidate grid:
tournament selection, uniform crossover, +-1-step/random-reset mutation, elitism; seeded), and
``"auto"`` takes the exhaustive search when there are at most ``exhaustive_limit`` candidates.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numba
import numpy as np
from scipy.optimize import brentq

from implantplan.systems.capability_map import CapabilityMap, direction_of, golden_spiral, lookup
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.files import read_yaml, write_atomic
from implantplan.systems.frames import (
    invert,
    rot_x,
    rot_y,
    rot_z,
    rpy_to_rotation,
    transform,
    wrap_angle,
)

SCHEMA_VERSION = 1
STORE_VERSION = 1  # bump when the RASSCMAP algorithm changes (invalidates stored maps)


# ---------------------------------------------------------------------------------------------
# Unconstrained access (Sec. 3.1)
# ---------------------------------------------------------------------------------------------


def arc_radius(a: float, c: float, *, field: str = "body") -> tuple[float, float]:
    """Radius r and arc angle theta (rad) of a circular arc with arc length a and chord c.

    Solves a = r*theta, c = 2 r sin(theta/2) (Sec. 3.1): c/a = sin(theta/2)/(theta/2), a
    decreasing function of theta on (0, 2*pi), so there is one root for 0 < c < a.
    """
    if not (np.isfinite(a) and np.isfinite(c) and a > 0 and c > 0):
        raise InputError(field, f"arc_length and chord must be positive, got a={a!r}, c={c!r}")
    if c >= a:
        raise InputError(
            f"{field}.chord", f"the chord ({c} m) must be shorter than the arc ({a} m)"
        )
    ratio = c / a

    def g(t):
        return np.sin(t / 2.0) / (t / 2.0) - ratio

    theta = brentq(g, 1e-9, 2.0 * np.pi - 1e-12, xtol=1e-14, rtol=1e-14)
    return a / theta, theta


def surface_points(
    a: float, c: float, length: float, *, d_r: float, d_t: float, voxel: float, depth: float
) -> np.ndarray:
    """Points (n, 3) of the unconstrained RASSCMAP in the body frame P (see module docstring)."""
    for name, v in (("length", length), ("d_r", d_r), ("d_t", d_t), ("voxel", voxel)):
        if not (np.isfinite(v) and v > 0):
            raise InputError(name, f"expected a positive number, got {v!r}")
    if not (np.isfinite(depth) and depth >= 0):
        raise InputError("map_depth", f"expected a number >= 0, got {depth!r}")
    r, theta = arc_radius(a, c)
    n_rot = int(np.floor(theta / d_r + 1e-9)) + 1
    Theta = np.pi / 2 - theta / 2 + np.linspace(0.0, theta, n_rot)
    z = np.arange(0.0, length + 1e-9, d_t)
    layers = int(np.floor(depth / voxel + 1e-9)) + 1
    y0 = -r * np.cos(theta / 2.0)  # circle centre below the chord
    pts = []
    for k in range(layers):
        rk = r + k * voxel
        xy = np.stack([rk * np.cos(Theta), y0 + rk * np.sin(Theta)], axis=-1)
        g = np.concatenate([np.repeat(xy, len(z), 0), np.tile(z, len(xy))[:, None]], axis=1)
        pts.append(g)
    return np.concatenate(pts)


# ---------------------------------------------------------------------------------------------
# Constrained access (Sec. 3.2, Algorithms 1-2)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Trocar:
    """Access constraints: cannula length, map depth beyond it, RCM rotation limits."""

    cannula_length: float = 0.05
    depth: float = 0.15
    alpha_max: float = np.pi / 2
    beta_max: float = np.pi / 2


@dataclass(frozen=True)
class Instrument:
    """Shaft length l_s (from the robot's mapped frame) and instrument length l_i (joint to tip)."""

    shaft_length: float = 0.40
    instrument_length: float = 0.02
    joint_limit: float = np.pi / 2


def _lattice(p: np.ndarray, origin: np.ndarray, voxel: float) -> np.ndarray:
    return np.round((p - origin) / voxel).astype(np.int64)


def _codes(keys: np.ndarray) -> np.ndarray:
    k = keys + (1 << 20)
    return (k[..., 0] << 42) | (k[..., 1] << 21) | k[..., 2]


def hemisphere_samples(X_WA: np.ndarray, trocar: Trocar, voxel: float, d_rot: float):
    """Algorithm 1's search space in W: tip positions (n, 3), shaft directions (n, 3) and the
    tip's distance rho (n,) from the trocar point."""
    a = np.arange(-trocar.alpha_max, trocar.alpha_max + 1e-9, d_rot)
    b = np.arange(-trocar.beta_max, trocar.beta_max + 1e-9, d_rot)
    A, B = np.meshgrid(a, b, indexing="ij")
    R = rot_x(A.ravel()) @ rot_y(B.ravel())  # (n_dir, 3, 3)
    d = X_WA[:3, :3] @ R[:, :, 2].T  # (3, n_dir)
    d = d.T
    s = np.arange(voxel, trocar.depth + 1e-9, voxel)
    rho = trocar.cannula_length + s
    tips = X_WA[:3, 3] + rho[:, None, None] * d[None]  # (n_rho, n_dir, 3)
    dirs = np.broadcast_to(d[None], tips.shape)
    return tips.reshape(-1, 3), dirs.reshape(-1, 3), np.repeat(rho, len(d))


@dataclass
class Rasscmap:
    """A constrained-access RASSCMAP: voxel centres in W, per-voxel direction bits, capability.

    (An unconstrained RASSCMAP needs no object: it is the CMAP index at the body points,
    :func:`unconstrained_index`, and task poses query the CMAP directly.)

    Attributes:
        centres: (n, 3) voxel centres in W.
        reach: (n, K) bool, instrument (or tool) directions reachable in the voxel.
        index: (n,) capability in [0, 1].
        voxel: voxel edge (m); origin: lattice origin in W (the trocar point).
        kind: "constrained".
        timings: seconds of Algorithm 1 (t_t) and 2 (t_R).
    """

    centres: np.ndarray
    reach: np.ndarray
    index: np.ndarray
    voxel: float
    origin: np.ndarray
    kind: str
    timings: dict = field(default_factory=dict)

    @property
    def c_s(self) -> float:
        """Average capability of the map (Sec. 4.2)."""
        return float(self.index.mean()) if len(self.index) else 0.0

    def query(self, X_WT: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(reachable, index) of task poses (m, 4, 4) on this map's voxels and directions."""
        m = len(X_WT)
        if len(self.centres) == 0:
            return np.zeros(m, bool), np.zeros(m)
        mine = _codes(_lattice(self.centres, self.origin, self.voxel))
        order = np.argsort(mine)
        sorted_codes = mine[order]
        codes = _codes(_lattice(X_WT[:, :3, 3], self.origin, self.voxel))
        pos = np.clip(np.searchsorted(sorted_codes, codes), 0, len(mine) - 1)
        found = sorted_codes[pos] == codes
        rows = order[pos]
        dir_idx = np.argmax(X_WT[:, :3, 2] @ directions.T, axis=1)
        reach = found & self.reach[rows, dir_idx]
        index = np.where(found, self.index[rows], 0.0)
        return reach, index


def pivot_voxels(
    cmap: CapabilityMap,
    X_WB: np.ndarray,
    X_WA: np.ndarray,
    trocar: Trocar,
    instrument: Instrument,
    voxel: float,
    d_rot: float,
):
    """Algorithm 1: the hemisphere's voxels and which are pivots (reachable, instrument straight).

    Returns:
        ``(keys, pivot)``: integer lattice keys (n, 3) of every hemisphere voxel (origin p_A) and a
        bool (n,) marking pivot voxels.
    """
    tips, d, rho = hemisphere_samples(X_WA, trocar, voxel, d_rot)
    L = instrument.shaft_length + instrument.instrument_length
    p_ee = tips - L * d
    X_BW = invert(X_WB)
    reach, _ = cmap.query_points(p_ee @ X_BW[:3, :3].T + X_BW[:3, 3], d @ X_BW[:3, :3].T)
    keys = _lattice(tips, X_WA[:3, 3], voxel)
    codes = _codes(keys)
    uniq, first, inv = np.unique(codes, return_index=True, return_inverse=True)
    pivot = np.zeros(len(uniq), bool)
    np.logical_or.at(pivot, inv.ravel(), reach)
    return keys[first], pivot


def bend_samples(d_rot: float, joint_limit: float) -> tuple[np.ndarray, np.ndarray]:
    """(delta, psi) samples of the instrument bend: delta 0..limit, psi around (one at delta 0)."""
    deltas = np.arange(0.0, joint_limit + 1e-9, d_rot)
    psis = np.arange(0.0, 2 * np.pi - 1e-9, d_rot)
    D, P = np.meshgrid(deltas[1:], psis, indexing="ij")
    return np.concatenate([[0.0], D.ravel()]), np.concatenate([[0.0], P.ravel()])


@numba.njit(cache=True)
def _bend_kernel(
    centres,
    p_A,
    z_A,
    cos_min,
    delta,
    sin_d,
    cos_d,
    cos_psi,
    sin_psi,
    l_i,
    l_s,
    l_c,
    R_BW,
    t_BW,
    origin,
    voxel,
    shape,
    row_of,
    table,
    bits,
    out,
):  # pragma: no cover - compiled
    """Algorithm 2 for every pivot centre x bend sample; marks out[pivot, direction]."""
    for m in range(centres.shape[0]):
        vx, vy, vz = centres[m, 0] - p_A[0], centres[m, 1] - p_A[1], centres[m, 2] - p_A[2]
        D = np.sqrt(vx * vx + vy * vy + vz * vz)
        if D <= l_i:
            continue
        ux, uy, uz = vx / D, vy / D, vz / D
        hx, hy, hz = (1.0, 0.0, 0.0) if abs(ux) < 0.9 else (0.0, 1.0, 0.0)
        dot = hx * ux + hy * uy + hz * uz
        ax, ay, az = hx - dot * ux, hy - dot * uy, hz - dot * uz
        na = np.sqrt(ax * ax + ay * ay + az * az)
        ax, ay, az = ax / na, ay / na, az / na
        bx, by, bz = uy * az - uz * ay, uz * ax - ux * az, ux * ay - uy * ax  # e2 = u x e1
        for s in range(delta.shape[0]):
            d, sd, cd = delta[s], sin_d[s], cos_d[s]
            sphi = l_i * sd / D  # law of sines: sin(phi) / l_i = sin(pi - delta) / D
            if sphi > 1.0:
                continue
            cphi = np.sqrt(1.0 - sphi * sphi)
            sg = sd * cphi - cd * sphi  # sin(delta - phi): instrument angle to u
            cg = cd * cphi + sd * sphi
            if d > 0.0:
                AJ = D * sg / sd  # |trocar - joint|
                if AJ < l_c:
                    continue  # the instrument joint is still inside the cannula
            else:
                AJ = D - l_i
            cp, sp = cos_psi[s], sin_psi[s]
            wx, wy, wz = cp * ax + sp * bx, cp * ay + sp * by, cp * az + sp * bz
            sx, sy, sz = cphi * ux - sphi * wx, cphi * uy - sphi * wy, cphi * uz - sphi * wz
            if sx * z_A[0] + sy * z_A[1] + sz * z_A[2] < cos_min - 1e-12:
                continue  # shaft outside the trocar's rotation limits
            t = AJ - l_s  # shaft start (robot's mapped frame) = p_A + (AJ - l_s) z_s
            ex, ey, ez = p_A[0] + t * sx, p_A[1] + t * sy, p_A[2] + t * sz
            px = R_BW[0, 0] * ex + R_BW[0, 1] * ey + R_BW[0, 2] * ez + t_BW[0]
            py = R_BW[1, 0] * ex + R_BW[1, 1] * ey + R_BW[1, 2] * ez + t_BW[1]
            pz = R_BW[2, 0] * ex + R_BW[2, 1] * ey + R_BW[2, 2] * ez + t_BW[2]
            qx = R_BW[0, 0] * sx + R_BW[0, 1] * sy + R_BW[0, 2] * sz
            qy = R_BW[1, 0] * sx + R_BW[1, 1] * sy + R_BW[1, 2] * sz
            qz = R_BW[2, 0] * sx + R_BW[2, 1] * sy + R_BW[2, 2] * sz
            row, ok = lookup(px, py, pz, qx, qy, qz, origin, voxel, shape, row_of, table, bits)
            if ok:
                k = direction_of(cg * ux + sg * wx, cg * uy + sg * wy, cg * uz + sg * wz, table)
                out[m, k] = True


def add_orientations(
    cmap: CapabilityMap,
    X_WB: np.ndarray,
    X_WA: np.ndarray,
    centres: np.ndarray,
    trocar: Trocar,
    instrument: Instrument,
    d_rot: float,
) -> np.ndarray:
    """Algorithm 2: instrument directions (n, K) bool reachable at each pivot centre (n, 3).

    For each centre and bend (delta, psi) (:func:`bend_samples`): shaft angle phi to u by the law
    of sines, joint past the cannula, shaft within the trocar limits, CMAP lookup of the shaft's
    start point and direction in base_link, then the instrument direction's bin is set.
    """
    out = np.zeros((len(centres), cmap.params.directions), bool)
    if len(centres) == 0:
        return out
    delta, psi = bend_samples(d_rot, instrument.joint_limit)
    X_BW = invert(X_WB)
    cos_min = np.cos(min(trocar.alpha_max, trocar.beta_max, np.pi / 2))
    _bend_kernel(
        np.ascontiguousarray(centres, dtype=float), X_WA[:3, 3].copy(), X_WA[:3, 2].copy(),
        float(cos_min), delta, np.sin(delta), np.cos(delta), np.cos(psi), np.sin(psi),
        float(instrument.instrument_length),
        float(instrument.shaft_length), float(trocar.cannula_length),
        np.ascontiguousarray(X_BW[:3, :3]), X_BW[:3, 3].copy(), *cmap.kernel_args(), out,
    )  # fmt: skip
    return out


def constrained_map(
    cmap: CapabilityMap,
    X_WB: np.ndarray,
    X_WA: np.ndarray,
    trocar: Trocar,
    instrument: Instrument,
    *,
    voxel: float,
    d_rot: float,
) -> Rasscmap:
    """RASSCMAP for a constrained access point (Algorithms 1 + 2); voxels = the hemisphere."""
    t0 = time.perf_counter()
    keys, pivot = pivot_voxels(cmap, X_WB, X_WA, trocar, instrument, voxel, d_rot)
    t1 = time.perf_counter()
    directions = golden_spiral(cmap.params.directions)
    centres = X_WA[:3, 3] + keys * voxel
    reach = np.zeros((len(keys), len(directions)), bool)
    reach[pivot] = add_orientations(cmap, X_WB, X_WA, centres[pivot], trocar, instrument, d_rot)
    t2 = time.perf_counter()
    index = reach.mean(axis=1)
    return Rasscmap(
        centres, reach, index, voxel, X_WA[:3, 3].copy(), "constrained",
        {"t_t": t1 - t0, "t_R": t2 - t1, "n_voxels": int(len(keys)), "n_pivots": int(pivot.sum())},
    )  # fmt: skip


def unconstrained_index(cmap: CapabilityMap, X_WB: np.ndarray, points_W: np.ndarray) -> np.ndarray:
    """CMAP index at body-surface points for a batch of bases: X_WB (nb, 4, 4) -> (nb, n)."""
    return cmap.voxel_index(points_W, invert(np.asarray(X_WB).reshape(-1, 4, 4)))


NEIGHBOURS = np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3)


def task_margin(cmap: CapabilityMap, X_BT: np.ndarray) -> np.ndarray:
    """Tie-break score: mean CMAP index over the 27 voxels around each task position, averaged
    over the task poses (nb, m, 4, 4) -> (nb,). High = the setup tolerates a base placed a voxel
    off. (Our addition: with a 6-axis arm half the map has index 1, so Sec. 4.2's cost ties.)"""
    p = X_BT[..., None, :3, 3] + cmap.params.voxel * NEIGHBOURS
    idx = cmap.voxel_index(p.reshape(-1, 3)).reshape(p.shape[:-1])
    return idx.mean(axis=(-1, -2))


# ---------------------------------------------------------------------------------------------
# Inputs (Listings 1-3)
# ---------------------------------------------------------------------------------------------


def _num(d: dict, key: str, where: str, *, positive=True, default=None) -> float:
    if key not in d:
        if default is not None:
            return float(default)
        raise InputError(f"{where}.{key}", "missing (expected a number)")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise InputError(f"{where}.{key}", f"expected a number, got {v!r}")
    if positive and v <= 0:
        raise InputError(f"{where}.{key}", f"expected a positive number, got {v!r}")
    if not positive and v < 0:
        raise InputError(f"{where}.{key}", f"expected a number >= 0, got {v!r}")
    return float(v)


def _vec(v, where: str, n: int = 3) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise InputError(where, f"expected a list of {n} numbers, got {v!r}")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not np.isfinite(x):
            raise InputError(where, f"expected a list of {n} numbers, got {v!r}")
        out.append(float(x))
    return np.array(out)


def parse_pose(d, where: str) -> np.ndarray:
    """``{xyz: [m, m, m], rpy_deg: [deg, deg, deg]}`` -> 4x4 (rpy_deg optional, default 0)."""
    if not isinstance(d, dict) or "xyz" not in d:
        raise InputError(where, "expected a mapping with 'xyz' (m) and optional 'rpy_deg'")
    unknown = set(d) - {"xyz", "rpy_deg", "id"}
    if unknown:
        raise InputError(where, f"unknown keys {sorted(unknown)} (expected xyz, rpy_deg)")
    p = _vec(d["xyz"], f"{where}.xyz")
    rpy = np.deg2rad(_vec(d.get("rpy_deg", [0, 0, 0]), f"{where}.rpy_deg"))
    return transform(rpy_to_rotation(rpy), p)


def _mapping(data: dict, key: str, where: str) -> dict:
    v = data.get(key)
    if not isinstance(v, dict):
        raise InputError(f"{where}.{key}" if where else key, "missing or not a mapping")
    return v


@dataclass
class Patient:
    """Listing 1: id, body-part pose, voxel size, map depth, access (points or body measures)."""

    id: str
    X_WP: np.ndarray
    voxel: float
    depth: float
    access: str
    d_rot: float
    d_trans: float
    body: dict | None = None
    access_points: list = field(default_factory=list)  # [(id, X_WA)]
    trocar: Trocar | None = None
    instrument: Instrument | None = None


def load_patient(path) -> Patient:
    """Read and validate a patient YAML (Listing 1)."""
    data = _mapping(read_yaml(path, field="patient"), "patient", "")
    w = "patient"
    pid = str(data.get("id", ""))
    if not pid:
        raise InputError("patient.id", "missing (expected a non-empty id)")
    X_WP = parse_pose(data.get("pose"), "patient.pose")
    voxel = _num(data, "voxel_size", w)
    depth = _num(data, "map_depth", w, positive=False)
    d_rot = np.deg2rad(_num(data, "rotation_step_deg", w, default=5.0))
    d_trans = _num(data, "translation_step", w, default=0.05)
    access = data.get("access")
    if access not in ("unconstrained", "constrained"):
        raise InputError(
            "patient.access", f"expected 'unconstrained' or 'constrained', got {access!r}"
        )
    pat = Patient(pid, X_WP, voxel, depth, access, d_rot, d_trans)
    if access == "unconstrained":
        body = _mapping(data, "body", w)
        a = _num(body, "arc_length", "patient.body")
        c = _num(body, "chord", "patient.body")
        ln = _num(body, "length", "patient.body")
        arc_radius(a, c, field="patient.body")
        pat.body = {"arc_length": a, "chord": c, "length": ln}
    else:
        aps = data.get("access_points")
        if not isinstance(aps, list) or not aps:
            raise InputError("patient.access_points", "expected a non-empty list of poses")
        for i, ap in enumerate(aps):
            X = parse_pose(ap, f"patient.access_points[{i}]")
            pat.access_points.append((str(ap.get("id", f"AP{i + 1}")), X))
        tr = data.get("trocar", {})
        if not isinstance(tr, dict):
            raise InputError("patient.trocar", "expected a mapping")
        pat.trocar = Trocar(
            cannula_length=_num(
                tr, "cannula_length", "patient.trocar", positive=False, default=0.05
            ),
            depth=depth,
            alpha_max=np.deg2rad(_num(tr, "alpha_max_deg", "patient.trocar", default=90.0)),
            beta_max=np.deg2rad(_num(tr, "beta_max_deg", "patient.trocar", default=90.0)),
        )
        if pat.trocar.alpha_max > np.pi / 2 + 1e-12 or pat.trocar.beta_max > np.pi / 2 + 1e-12:
            raise InputError("patient.trocar", "alpha_max_deg and beta_max_deg must be <= 90")
        ins = data.get("instrument", {})
        if not isinstance(ins, dict):
            raise InputError("patient.instrument", "expected a mapping")
        pat.instrument = Instrument(
            shaft_length=_num(ins, "shaft_length", "patient.instrument", default=0.40),
            instrument_length=_num(ins, "instrument_length", "patient.instrument", default=0.02),
            joint_limit=np.deg2rad(
                _num(ins, "joint_limit_deg", "patient.instrument", default=90.0)
            ),
        )
        if pat.instrument.joint_limit > np.pi / 2 + 1e-12:
            raise InputError("patient.instrument.joint_limit_deg", "must be <= 90")
    return pat


@dataclass
class Task:
    """Listing 2: task id and task poses in W (z = approach direction of the mapped frame)."""

    id: str
    poses: np.ndarray


def load_task(path) -> Task:
    """Read a task YAML (Listing 2): ``poses`` (list of xyz/rpy_deg) and/or ``boxes`` (grids)."""
    data = _mapping(read_yaml(path, field="task"), "task", "")
    tid = str(data.get("id", ""))
    if not tid:
        raise InputError("task.id", "missing (expected a non-empty id)")
    poses = []
    for i, p in enumerate(data.get("poses", []) or []):
        poses.append(parse_pose(p, f"task.poses[{i}]"))
    for i, b in enumerate(data.get("boxes", []) or []):
        w = f"task.boxes[{i}]"
        if not isinstance(b, dict):
            raise InputError(w, "expected a mapping with min, max, counts, rpy_deg")
        lo, hi = _vec(b.get("min"), f"{w}.min"), _vec(b.get("max"), f"{w}.max")
        counts = b.get("counts")
        if not (
            isinstance(counts, list)
            and len(counts) == 3
            and all(isinstance(c, int) and c >= 1 for c in counts)
        ):
            raise InputError(f"{w}.counts", f"expected 3 positive integers, got {counts!r}")
        if np.any(hi < lo):
            raise InputError(w, "max must be >= min on every axis")
        R = rpy_to_rotation(np.deg2rad(_vec(b.get("rpy_deg", [0, 0, 0]), f"{w}.rpy_deg")))
        axes = [np.linspace(lo[k], hi[k], counts[k]) for k in range(3)]
        g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        poses.extend(transform(np.broadcast_to(R, (len(g), 3, 3)), g))
    if not poses:
        raise InputError("task.poses", "expected at least one task pose (poses or boxes)")
    return Task(tid, np.stack(poses))


@dataclass
class BaseRange:
    """One range of base poses (Listing 3): x, y, z (m) and yaw (rad) intervals."""

    lo: np.ndarray  # (4,) x, y, z, yaw
    hi: np.ndarray
    step: np.ndarray  # (4,) translation, translation, translation, rotation

    def axes(self) -> list[np.ndarray]:
        return [
            self.lo[k]
            + self.step[k]
            * np.arange(int(np.floor((self.hi[k] - self.lo[k]) / self.step[k] + 1e-9)) + 1)
            for k in range(4)
        ]

    @property
    def dims(self) -> tuple[int, int, int, int]:
        return tuple(len(a) for a in self.axes())


@dataclass
class Robot:
    """Listing 3: robot name, CMAP path, base pose ranges, store, optional map build params."""

    name: str
    map_path: Path
    ranges: list
    store: Path | None = None
    build: dict | None = None
    limits: str | None = None


def load_robot(path) -> Robot:
    """Read and validate a robot YAML (Listing 3); relative paths are relative to the file."""
    path = Path(path)
    data = _mapping(read_yaml(path, field="robot"), "robot", "")
    name = str(data.get("name", ""))
    if not name:
        raise InputError("robot.name", "missing (expected the robot's name)")
    if not isinstance(data.get("map"), str):
        raise InputError("robot.map", "missing (expected the path of the capability map .h5)")
    map_path = (path.parent / data["map"]).resolve()
    t_step = _num(data, "translation_step", "robot", default=0.05)
    r_step = np.deg2rad(_num(data, "rotation_step_deg", "robot", default=5.0))
    ranges = []
    raw = data.get("base_ranges")
    if not isinstance(raw, list) or not raw:
        raise InputError("robot.base_ranges", "expected a non-empty list of ranges")
    for i, r in enumerate(raw):
        w = f"robot.base_ranges[{i}]"
        if not isinstance(r, dict):
            raise InputError(w, "expected a mapping with x, y, z ([min, max] m) and yaw_deg")
        lo, hi = [], []
        for key, scale in (("x", 1.0), ("y", 1.0), ("z", 1.0), ("yaw_deg", np.pi / 180)):
            v = r.get(key, [0.0, 0.0])
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                v = [v, v]
            pair = _vec(v, f"{w}.{key}", 2) * scale
            if pair[1] < pair[0]:
                raise InputError(f"{w}.{key}", f"expected [min, max] with min <= max, got {v!r}")
            lo.append(pair[0])
            hi.append(pair[1])
        ranges.append(BaseRange(np.array(lo), np.array(hi), np.array([t_step] * 3 + [r_step])))
    store = data.get("store")
    build = data.get("build")
    if build is not None and not isinstance(build, dict):
        raise InputError("robot.build", "expected a mapping (voxel_mm, directions, limits)")
    limits = data.get("limits")
    if limits is not None and str(limits) not in ("175", "360"):
        raise InputError("robot.limits", f"expected '175' or '360', got {limits!r}")
    return Robot(
        name, map_path, ranges, (path.parent / store).resolve() if store else None, build,
        None if limits is None else str(limits),
    )  # fmt: skip


def base_candidates(ranges: list) -> tuple[np.ndarray, np.ndarray]:
    """All base poses X_WB (n, 4, 4) and their grid coordinates (n, 5): range, ix, iy, iz, iyaw."""
    poses, coords = [], []
    for ri, r in enumerate(ranges):
        ax = r.axes()
        grid = np.stack(np.meshgrid(*[np.arange(len(a)) for a in ax], indexing="ij"), -1).reshape(
            -1, 4
        )
        vals = np.stack([ax[k][grid[:, k]] for k in range(4)], axis=-1)
        poses.append(transform(rot_z(vals[:, 3]), vals[:, :3]))
        coords.append(np.concatenate([np.full((len(grid), 1), ri), grid], axis=1))
    return np.concatenate(poses), np.concatenate(coords)


# ---------------------------------------------------------------------------------------------
# Keyed store of computed RASSCMAPs
# ---------------------------------------------------------------------------------------------


class RasscmapStore:
    """On-disk store of RASSCMAPs keyed by everything they depend on (reused across runs).

    The key hashes the CMAP's parameter key, the map kind, its geometric inputs (access pose,
    trocar, instrument, voxel, rotation step) and the base pose, plus ``STORE_VERSION``. One HDF5
    file per key under ``root/ab/<key>.h5``, written atomically. Constrained maps only: an
    unconstrained RASSCMAP is a CMAP lookup of ~25 us per base, cheaper than opening a file.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(**parts) -> str:
        def norm(v):
            if isinstance(v, np.ndarray):
                return np.round(v.astype(float), 9).tolist()
            if isinstance(v, (Trocar, Instrument)):
                return {k: round(float(x), 9) for k, x in v.__dict__.items()}
            if isinstance(v, float):
                return round(v, 9)
            return v

        text = json.dumps(
            {"v": STORE_VERSION, **{k: norm(v) for k, v in parts.items()}}, sort_keys=True
        )
        return hashlib.sha256(text.encode()).hexdigest()[:24]

    def path(self, key: str) -> Path:
        return self.root / key[:2] / f"{key}.h5"

    def get(self, key: str) -> Rasscmap | None:
        p = self.path(key)
        if not p.is_file():
            self.misses += 1
            return None
        try:
            with h5py.File(p, "r") as f:
                if int(f.attrs.get("schema_version", -1)) != SCHEMA_VERSION:
                    self.misses += 1
                    return None
                K = int(f.attrs["directions"])
                r = Rasscmap(
                    f["centres"][()], np.unpackbits(f["reach"][()], axis=1, count=K).astype(bool),
                    f["index"][()], float(f.attrs["voxel"]),
                    f["origin"][()] if "origin" in f else None, str(f.attrs["kind"]),
                    json.loads(f.attrs["timings"]),
                )  # fmt: skip
        except (OSError, KeyError):
            self.misses += 1
            return None
        self.hits += 1
        return r

    def put(self, key: str, r: Rasscmap) -> None:
        def writer(tmp):
            with h5py.File(tmp, "w") as f:
                f.attrs["schema_version"] = SCHEMA_VERSION
                f.attrs["kind"] = r.kind
                f.attrs["voxel"] = r.voxel
                f.attrs["directions"] = r.reach.shape[1]
                f.attrs["timings"] = json.dumps(r.timings)
                f.create_dataset("centres", data=r.centres)
                f.create_dataset("reach", data=np.packbits(r.reach, axis=1))
                f.create_dataset("index", data=r.index)
                if r.origin is not None:
                    f.create_dataset("origin", data=r.origin)

        write_atomic(self.path(key), writer)


# ---------------------------------------------------------------------------------------------
# Setup optimization (Sec. 4.2)
# ---------------------------------------------------------------------------------------------


def setup_cost(reach: np.ndarray, c_t: np.ndarray, c_s: np.ndarray) -> np.ndarray:
    """Sec. 4.2 cost over candidates: 0 if any task pose unreachable, else (mean c_t + c_s) / 2.

    Args:
        reach: (n, m) bool per candidate and task pose; c_t: (n, m) indices; c_s: (n,).
    """
    return np.where(reach.all(axis=1), 0.5 * (c_t.mean(axis=1) + c_s), 0.0)


class SetupProblem:
    """Candidates = base poses x access points; ``evaluate(ids)`` gives their costs (cached)."""

    def __init__(
        self,
        cmap: CapabilityMap,
        patient: Patient,
        task: Task,
        robot: Robot,
        *,
        store: RasscmapStore | None = None,
    ):
        self.cmap, self.patient, self.task, self.robot, self.store = (
            cmap,
            patient,
            task,
            robot,
            store,
        )
        self.bases, self.base_coords = base_candidates(robot.ranges)
        self.n_access = len(patient.access_points) if patient.access == "constrained" else 1
        self.n = len(self.bases) * self.n_access
        self.cost = np.full(self.n, np.nan)
        self.c_s = np.full(self.n, np.nan)
        self.all_reached = np.zeros(self.n, bool)
        self.mean_c_t = np.full(self.n, np.nan)
        self.margin = np.zeros(self.n)
        self.directions = golden_spiral(cmap.params.directions)
        self.evaluations = 0
        self.eval_seconds = 0.0  # time spent in evaluate (the rest of a search is bookkeeping)
        if patient.access == "unconstrained":
            b = patient.body
            pts_P = surface_points(
                b["arc_length"], b["chord"], b["length"], d_r=patient.d_rot,
                d_t=patient.d_trans, voxel=patient.voxel, depth=patient.depth,
            )  # fmt: skip
            self.points_W = pts_P @ patient.X_WP[:3, :3].T + patient.X_WP[:3, 3]

    def split(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ids = np.asarray(ids)
        return ids // self.n_access, ids % self.n_access

    def rasscmap(self, base: int, access: int) -> Rasscmap:
        """The constrained RASSCMAP of one candidate, from the store when there."""
        p = self.patient
        aid, X_WA = p.access_points[access]
        key = RasscmapStore.key(
            kind="constrained", cmap=self.cmap.params.key(), X_WB=self.bases[base], X_WA=X_WA,
            trocar=p.trocar, instrument=p.instrument, voxel=p.voxel, d_rot=p.d_rot,
        )  # fmt: skip
        if self.store is not None:
            r = self.store.get(key)
            if r is not None:
                return r
        r = constrained_map(
            self.cmap, self.bases[base], X_WA, p.trocar, p.instrument, voxel=p.voxel, d_rot=p.d_rot
        )
        if self.store is not None:
            self.store.put(key, r)
        return r

    def evaluate(self, ids: np.ndarray) -> np.ndarray:
        """Costs of candidates ``ids`` (computing only those not cached)."""
        t0 = time.perf_counter()
        ids = np.unique(np.asarray(ids, dtype=np.int64))
        todo = ids[np.isnan(self.cost[ids])]
        if len(todo):
            self.evaluations += len(todo)
            b, a = self.split(todo)
            m = len(self.task.poses)
            if self.patient.access == "unconstrained":
                X_BW = invert(self.bases[b])
                X_BT = X_BW[:, None] @ self.task.poses[None]
                reach, c_t = self.cmap.query(X_BT)
                c_s = unconstrained_index(self.cmap, self.bases[b], self.points_W).mean(axis=1)
                self.margin[todo] = task_margin(self.cmap, X_BT)
            else:
                reach = np.zeros((len(todo), m), bool)
                c_t = np.zeros((len(todo), m))
                c_s = np.zeros(len(todo))
                for i, (bi, ai) in enumerate(zip(b, a, strict=True)):
                    r = self.rasscmap(int(bi), int(ai))
                    reach[i], c_t[i] = r.query(self.task.poses, self.directions)
                    c_s[i] = r.c_s
            self.cost[todo] = setup_cost(reach, c_t, c_s)
            self.c_s[todo] = c_s
            self.all_reached[todo] = reach.all(axis=1)
            self.mean_c_t[todo] = c_t.mean(axis=1)
        self.eval_seconds += time.perf_counter() - t0
        return self.cost[np.asarray(ids)]

    # genome = (range, ix, iy, iz, iyaw, access); bounds per range
    def genome_bounds(self) -> np.ndarray:
        """(n_ranges, 6) exclusive upper bound of each gene per range."""
        return np.array(
            [[len(self.robot.ranges), *r.dims, self.n_access] for r in self.robot.ranges]
        )

    def genome_to_id(self, g: np.ndarray) -> np.ndarray:
        offsets = np.concatenate([[0], np.cumsum([np.prod(r.dims) for r in self.robot.ranges])])
        dims = np.array([r.dims for r in self.robot.ranges])  # (n_ranges, 4)
        d = dims[g[:, 0]]
        lin = ((g[:, 1] * d[:, 1] + g[:, 2]) * d[:, 2] + g[:, 3]) * d[:, 3] + g[:, 4]
        return (offsets[g[:, 0]] + lin) * self.n_access + g[:, 5]


@dataclass
class SetupResult:
    """Outcome of a search: best / worst candidate ids, their costs, how it was found."""

    best: int
    worst: int
    cost: float
    worst_cost: float
    method: str
    seconds: float
    evaluations: int
    generations: int = 0


YAW_LENGTH = 0.5  # m: a yaw difference counts as its arc at half a metre (tie-break distance)


def setup_distance(problem: SetupProblem, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance between candidates' bases (m): position, plus yaw as an arc at YAW_LENGTH;
    candidates at different access points are infinitely apart. Shapes (na,), (nb,) -> (na, nb)."""
    ba, aa = problem.split(a)
    bb, ab = problem.split(b)
    Pa, Pb = problem.bases[ba], problem.bases[bb]
    dp = np.linalg.norm(Pa[:, None, :3, 3] - Pb[None, :, :3, 3], axis=-1)
    ya = np.arctan2(Pa[:, 1, 0], Pa[:, 0, 0])
    yb = np.arctan2(Pb[:, 1, 0], Pb[:, 0, 0])
    dy = np.abs(wrap_angle(ya[:, None] - yb[None, :]))
    d = np.hypot(dp, YAW_LENGTH * dy)
    return np.where(aa[:, None] == ab[None, :], d, np.inf)


def _best_worst(problem: SetupProblem, ids: np.ndarray) -> tuple[int, int]:
    """Best and worst of the evaluated candidates ``ids``.

    Best: highest cost; ties -> highest :func:`task_margin`; remaining ties -> the candidate
    deepest inside the tied set (largest :func:`setup_distance` to any evaluated candidate of
    lower cost or margin: the most tolerant to a misplaced base); then the lowest id.
    Worst: lowest cost; ties -> lowest margin, then lowest id.
    """
    ids = np.asarray(ids)
    cost, margin = problem.cost[ids], problem.margin[ids]
    order = np.lexsort((ids, -margin, -cost))
    top = (cost == cost[order[0]]) & (margin == margin[order[0]])
    best = ids[order[0]]
    if top.sum() > 1 and (~top).any():
        tied, rest = ids[top], ids[~top]
        depth = np.full(len(tied), np.inf)
        for i in range(0, len(rest), 2048):
            depth = np.minimum(depth, setup_distance(problem, tied, rest[i : i + 2048]).min(axis=1))
        best = tied[np.lexsort((tied, -depth))[0]]
    worst = ids[np.lexsort((ids, margin, cost))[0]]
    return int(best), int(worst)


def exhaustive_search(problem: SetupProblem) -> SetupResult:
    """Evaluate every candidate (exact); ties are broken as in :func:`_best_worst`."""
    t0 = time.perf_counter()
    problem.evaluate(np.arange(problem.n))
    best, worst = _best_worst(problem, np.arange(problem.n))
    cost = problem.cost
    return SetupResult(best, worst, float(cost[best]), float(cost[worst]), "exhaustive",
                       time.perf_counter() - t0, problem.evaluations)  # fmt: skip


def genetic_search(
    problem: SetupProblem,
    *,
    seed: int,
    population: int = 50,
    generations: int = 60,
    patience: int = 12,
    elite: int = 2,
    mutation: float | None = None,
) -> SetupResult:
    """A small vectorized GA over the discrete setup grid (Sec. 4.2).

    Genome = (range, ix, iy, iz, iyaw, access). Tournament selection (size 2), uniform crossover,
    mutation per gene with probability ``mutation`` (default 1/6): +-1 grid step (clipped) or, one
    time in four, a uniform reset; the ``elite`` best survive. Stops after ``generations`` or when
    the best cost has not improved for ``patience`` generations. Same seed -> same result.
    The worst setup reported is the worst the GA evaluated (the paper's "additive inverse" run
    would need a second GA; the exhaustive search gives the exact worst).
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    bounds = problem.genome_bounds()
    n_genes = bounds.shape[1]
    mutation = 1.0 / n_genes if mutation is None else mutation

    def clip(g):
        g[:, 0] = np.clip(g[:, 0], 0, len(bounds) - 1)
        hi = bounds[g[:, 0]] - 1
        hi[:, 0] = len(bounds) - 1
        return np.clip(g, 0, hi)

    def random_genomes(n):
        r = rng.integers(0, len(bounds), n)
        return clip(
            np.concatenate(
                [r[:, None], (rng.random((n, n_genes - 1)) * bounds[r][:, 1:]).astype(np.int64)], 1
            )
        )

    def costs_of(g):
        ids = problem.genome_to_id(g)
        problem.evaluate(ids)
        return problem.cost[ids].copy()

    pop = random_genomes(population)
    fit = costs_of(pop)
    best_cost, stall, ran = fit.max(), 0, 0
    for gen in range(1, generations + 1):
        ran = gen
        a, b = rng.integers(0, population, (2, population))
        parents = pop[np.where(fit[a] >= fit[b], a, b)]
        mates = parents[rng.permutation(population)]
        child = np.where(rng.random(parents.shape) < 0.5, parents, mates)
        child[:, 1:] = np.where(
            rng.random((population, n_genes - 1)) < 0.5, parents[:, 1:], mates[:, 1:]
        )
        child = clip(child)
        mut = rng.random(child.shape) < mutation
        step = rng.choice(np.array([-1, 1]), child.shape)
        reset = rng.random(child.shape) < 0.25
        rnd = (rng.random(child.shape) * bounds[child[:, 0]]).astype(np.int64)
        rnd[:, 0] = rng.integers(0, len(bounds), population)
        child = np.where(mut & reset, rnd, np.where(mut, child + step, child))
        child = clip(child)
        costs = costs_of(child)
        order = np.argsort(-fit)
        child[:elite] = pop[order[:elite]]
        costs[:elite] = fit[order[:elite]]
        pop, fit = child, costs
        if fit.max() > best_cost + 1e-15:
            best_cost, stall = fit.max(), 0
        else:
            stall += 1
            if stall >= patience:
                break
    seen = np.flatnonzero(~np.isnan(problem.cost))
    best, worst = _best_worst(problem, seen)
    return SetupResult(best, worst, float(problem.cost[best]), float(problem.cost[worst]), "ga",
                       time.perf_counter() - t0, problem.evaluations, ran)  # fmt: skip


def optimize(
    problem: SetupProblem, *, method: str = "auto", seed: int = 0, exhaustive_limit: int = 20000
) -> SetupResult:
    """Best setup by ``"exhaustive"``, ``"ga"`` or ``"auto"`` (exhaustive when n <= limit).

    Raises:
        PlanningFailure: no candidate reaches every task pose (all costs 0).
    """
    if method not in ("auto", "exhaustive", "ga"):
        raise InputError("method", f"expected auto, exhaustive or ga, got {method!r}")
    if method == "exhaustive" or (method == "auto" and problem.n <= exhaustive_limit):
        res = exhaustive_search(problem)
    else:
        res = genetic_search(problem, seed=seed)
    if res.cost <= 0.0:
        raise PlanningFailure(
            f"no base pose (of {res.evaluations} evaluated) reaches all "
            f"{len(problem.task.poses)} task poses"
        )
    return res
