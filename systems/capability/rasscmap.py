"""RASSCMAP maths: surgery-specific capability maps (seed 004 Sec. 3, Algorithms 1-2).

Everything in world W (z up) unless a name says otherwise; a robot base pose is X_WB; the
capability map (:mod:`systems.capability.maps`) answers in base_link B.

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

The inputs (patient, task, robot YAML) are systems.capability.rasscmap_inputs', the keyed store of
built
maps systems.capability.store's, the cost and the setup search systems.capability.setup_search's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq

from implantplan.systems.capability.maps import CapabilityMap, direction_of, golden_spiral, lookup
from implantplan.systems.errors import InputError
from implantplan.systems.frames import (
    invert,
    rot_x,
    rot_y,
)
from implantplan.systems.jit import numba

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


def task_margin(cmap: CapabilityMap, X_BT: np.ndarray) -> np.ndarray:
    """Tie-break score: mean CMAP index over the 27 voxels around each task position
    (CapabilityMap.neighbourhood_index), averaged over the task poses (nb, m, 4, 4) -> (nb,).
    High = the setup tolerates a base placed a voxel off. (Our addition: with a 6-axis arm half
    the map has index 1, so Sec. 4.2's cost ties.)"""
    return cmap.neighbourhood_index(X_BT[..., :3, 3]).mean(axis=-1)


# ---------------------------------------------------------------------------------------------
# Inputs (Listings 1-3)
# ---------------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------------
# Keyed store of computed RASSCMAPs
# ---------------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------------
# Setup optimization (Sec. 4.2)
# ---------------------------------------------------------------------------------------------


