"""Control-barrier safety supervisor of the instrument against the tissue (DESIGN.md section 7).

The barrier is the clearance h(X) of the whole instrument (every solid: rod, head, implant) at
its pose X, a certified lower bound of its distance to the tissue, prepared once: with the
plan's scan, the scan bound resolved up to a cap above the margin
(:class:`~implantplan.systems.placement.scan_clearance.CappedScanClearance`: h = min(bound, cap),
the verdict the plan certifies its feed with); without it, the sound FPSM clearance
(:class:`~implantplan.systems.placement.tool_clearance.ToolClearance`);
and the safe set is h >= margin. A commanded tool twist V = [w; v] (w the angular velocity, v
the TCP's velocity, both in Center) is filtered so that

    dh/dt = grad h . V >= b,   b = min(-alpha (h - margin), 0)

(control-barrier style, Ames et al.): far from the wall any approach slower than
alpha (h - margin) passes; at the margin no approach is left; below it (which the filter itself
never causes) the command may not approach further but is not turned into a retreat, so the
supervisor never amplifies a command. The fixture's return law brings the tool back.

Discrete time (period dt). The commanded next pose X + dt V costs one clearance query; only a
command that fails the condition enters one compiled kernel (no allocation per step) for the 12
poses perturbed along the twist's coordinates (translations by +-eps_p, rotations about the TCP
by +-eps_w: the central-difference gradient g of h with respect to the twist), the projection
and the scale tries:

0. the twist is clipped to the command limits' speeds (systems.teleop.command_limits.clip_twist:
   one scale, direction kept; a non-finite twist is zero), whatever sent it (the operator's
   command through the fixture, the fixture's return law, the head guard's retreat): every step
   of the desired pose is then short enough that the tool between two steps keeps the barrier
   of its ends less half a step (systems.teleop.command_limits, between control steps);
1. if h(X + dt V) >= h + dt b - 10 nm (the discrete barrier condition holds for the command
   itself, no linearization) or h is +inf (the tool is outside the mouth), V passes untouched;
2. otherwise V is projected on the half-space g . V' >= 0.9 b (aiming at 90% of the allowed
   approach: room for the linearization error of a non-smooth h) in the metric
   |V|_M^2 = L^2 |w|^2 + |v|^2 (L = ``length_scale``: a rotation is "costly" in proportion to
   the lever it swings): V' = V + lambda M^-1 g, lambda = (0.9 b - g . V) / (g^T M^-1 g) >= 0.
   The half-space contains 0 (b <= 0), so the projection is non-expansive: |V'|_M <= |V|_M;
3. h being a minimum over the tool's parts (not smooth), the projected command is checked on
   h itself at X + dt V' and, only if that fails, at s = 3/4, 1/2, 1/4 of it in turn: the
   largest s that meets the discrete condition is taken, s = 0 (stop) if none does.
   Stopping always meets it, so the guarantee does not rest on the gradient: the LeafSystem
   reuses one gradient over up to 4 consecutive steps at the wall.
   Above the margin, this check of the projected command allows h to fall ``JUMP`` (0.05 mm)
   further than the rate, never below the margin: h_next >= max(margin, h + dt b - JUMP).
   The scan bound is not continuous in the pose (its branch and bound stops splitting a piece
   within 0.05 mm of its best upper estimate, so the tree, and the bound, change by a step
   where a piece crosses that test; measured: drops of up to 34 um within 1 um of travel
   along the feed's narrow section), and the strict check parks the tool exactly on the upper
   side of such a step: every move, however short, then falls by the step, which dt alpha
   (h - margin) does not allow until h - margin >= 10 x the step (0.2-0.34 mm). Under a moving
   head, whose margin the head guard grows by 1.1-1.8 mm, that froze the feed for a second at
   the narrowest part of site 46 (feeds that ended short of the target). The raw command keeps
   the strict condition (step 1) and the projection still aims at 0.9 b; the relaxation only
   lets the shaped command across the bound's steps. The safe set is unchanged: every step
   ends at h >= margin (or no lower than it started, below the margin).

h being a certified lower bound of the exact clearance, h >= margin - a few tenths of a
millimetre at every step thus bounds the exact distance of the instrument to the tissue (the
scan's, or the FPSM's without the scan). The estimator's alarm stays as the second line of defence.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from pydrake.common.eigen_geometry import AngleAxis
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem

from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import invert
from implantplan.systems.instrument import Instrument
from implantplan.systems.jit import numba
from implantplan.systems.placement.scan_clearance import TOLERANCE as SPLIT_TOLERANCE
from implantplan.systems.placement.scan_clearance import capped_at
from implantplan.systems.placement.tool_clearance import ToolClearance, fpsm_at
from implantplan.systems.safety import DEFAULT as SAFETY
from implantplan.systems.safety import SafetySpec
from implantplan.systems.teleop.command_limits import CommandLimits, clip_twist
from implantplan.systems.teleop.fixture_system import step_pose

AIM = 0.9  # the projection aims at this share of the allowed approach rate
SCALES = np.array([1.0, 0.75, 0.5, 0.25])  # tried on h itself after the projection
GRADIENT_REUSE = 4  # consecutive steps at the wall that share one finite-difference gradient
TOLERANCE = 1e-8  # m: rounding allowed in the discrete barrier condition per step
JUMP = SPLIT_TOLERANCE  # m: how much further than the rate the projected command's check lets
# h fall above the margin, never below it (module docstring, step 3: the scan bound's own steps)
FAR = 1.0e3  # stand-in for +inf (the tool wholly outside the mouth) on the output ports (m)
_IDENTITY = np.eye(3)  # the rotation of a step without angular velocity (read only)
_IDENTITY.flags.writeable = False


def clearance(fpsm: Fpsm, X_CT: np.ndarray, tool: Instrument) -> np.ndarray:
    """The barrier h (m) at K poses ``X_CT`` (K, 4, 4) of the Tool frame in Center: the sound
    FPSM clearance of the whole tool body (systems.placement.tool_clearance, a certified lower
    bound of its
    distance to the FPSM boundary). The supervisor holds a prepared :class:`ToolClearance`."""
    return ToolClearance(fpsm, tool)(X_CT)


@dataclass(frozen=True)
class Barrier:
    """Settings of the barrier filter (SI units).

    Attributes:
        margin: the clinical margin h must keep (m); the safety spec's (``clearance_mm``).
        alpha: the barrier's rate (1/s): an approach slower than alpha (h - margin) passes;
            the safety spec's (``barrier_rate_per_s``).
        length_scale: L (m) of the twist metric L^2 |w|^2 + |v|^2.
        eps_p, eps_w: finite-difference steps of the gradient (m, rad).
    """

    margin: float = SAFETY.clearance_margin
    alpha: float = SAFETY.barrier_rate
    length_scale: float = 10.0
    eps_p: float = 1e-4
    eps_w: float = 1e-3

    def __post_init__(self):
        for name in ("margin", "alpha", "length_scale", "eps_p", "eps_w"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0 or (name != "margin" and value == 0):
                raise InputError(f"barrier.{name}", f"expected a finite value > 0, got {value}")

    @classmethod
    def from_spec(cls, spec: SafetySpec, **options) -> Barrier:
        """The barrier of a safety spec: its margin and rate (``options``: the other fields)."""
        return cls(margin=spec.clearance_margin, alpha=spec.barrier_rate, **options)


def stepped_poses(X_CT: np.ndarray, V: np.ndarray, dt) -> np.ndarray:
    """(K, 4, 4) poses after dt under twists V (K, 6) = [w; v] (w about the TCP; exact
    rotation by Drake's AngleAxis, through :func:`systems.teleop.fixture_system.step_pose`)."""
    dt = np.broadcast_to(np.asarray(dt, dtype=float), (X_CT.shape[0],))
    out = X_CT.copy()
    for i in range(X_CT.shape[0]):
        p, R = step_pose(X_CT[i, :3, 3], X_CT[i, :3, :3], V[i], float(dt[i]))
        out[i, :3, 3], out[i, :3, :3] = p, R
    return out


@numba.njit(cache=True)
def _project(V, h, g, margin, alpha, length_scale, out) -> bool:
    """Step 2 for one command: out = V projected on g . V' >= b (b = min(-alpha (h - margin),
    0)) in the metric L^2 |w|^2 + |v|^2; True when the command was changed."""
    finite = np.isfinite(h)
    for i in range(6):
        out[i] = V[i]
        if not np.isfinite(g[i]):
            finite = False
    if not finite:
        return False
    b = min(-alpha * (h - margin), 0.0)
    inv_l2 = 1.0 / (length_scale * length_scale)
    gMg = 0.0
    gV = 0.0
    for i in range(6):
        gMg += g[i] * g[i] * (inv_l2 if i < 3 else 1.0)
        gV += g[i] * V[i]
    if not (gV < b and gMg > 0.0):
        return False
    lam = (b - gV) / gMg
    for i in range(6):
        out[i] = V[i] + lam * g[i] * (inv_l2 if i < 3 else 1.0)
    return True


def barrier_filter(V, h, g, *, margin: float, alpha: float, length_scale: float):
    """The projection of step 2 for K commands (the compiled kernel of the supervisor's step,
    one command at a time).

    Args:
        V: (K, 6) commanded twists [w; v]; h: (K,) barrier values (m; +inf: no constraint);
        g: (K, 6) gradients of h with respect to the twist.

    Returns:
        (V' (K, 6), b (K,) the required rate, active (K,) bool: the command was changed).
    """
    V = np.ascontiguousarray(V, dtype=float).reshape(-1, 6)
    h = np.asarray(h, dtype=float).reshape(-1)
    g = np.ascontiguousarray(g, dtype=float).reshape(-1, 6)
    finite = np.isfinite(h) & np.all(np.isfinite(g), axis=1)
    b = np.where(finite, np.minimum(-alpha * (np.where(finite, h, 0.0) - margin), 0.0), -np.inf)
    out = np.empty_like(V)
    active = np.zeros(V.shape[0], dtype=bool)
    for k in range(V.shape[0]):
        active[k] = _project(V[k], float(h[k]), g[k], float(margin), float(alpha),
                             float(length_scale), out[k])
    return out, b, active


def barrier_holds(h, h_next, barrier: Barrier, dt: float) -> np.ndarray:
    """The discrete barrier condition h_next >= h + dt b (b = min(-alpha (h - margin), 0)),
    within ``TOLERANCE``; always true where h is +inf (outside the mouth)."""
    h = np.asarray(h, dtype=float)
    with np.errstate(invalid="ignore"):
        b = np.minimum(-barrier.alpha * (h - barrier.margin), 0.0)
        return ~np.isfinite(h) | (np.asarray(h_next) >= h + dt * b - TOLERANCE)


@numba.njit(cache=True)
def step_pose_into(X, V, dt, out):
    """out = X one period dt on under the twist V = [w; v] (Center): p + v dt, exp([w] dt) R
    (Rodrigues' formula: Drake's AngleAxis rotation, to rounding)."""
    wx, wy, wz = V[0], V[1], V[2]
    n = np.sqrt(wx * wx + wy * wy + wz * wz)
    angle = n * dt
    for i in range(3):
        out[i, 3] = X[i, 3] + V[3 + i] * dt
        out[3, i] = 0.0
    out[3, 3] = 1.0
    if angle == 0.0:
        for i in range(3):
            for j in range(3):
                out[i, j] = X[i, j]
        return
    kx, ky, kz = wx / n, wy / n, wz / n
    c, s = np.cos(angle), np.sin(angle)
    C = 1.0 - c
    r00, r01, r02 = c + kx * kx * C, kx * ky * C - kz * s, kx * kz * C + ky * s
    r10, r11, r12 = ky * kx * C + kz * s, c + ky * ky * C, ky * kz * C - kx * s
    r20, r21, r22 = kz * kx * C - ky * s, kz * ky * C + kx * s, c + kz * kz * C
    for j in range(3):
        x0, x1, x2 = X[0, j], X[1, j], X[2, j]
        out[0, j] = r00 * x0 + r01 * x1 + r02 * x2
        out[1, j] = r10 * x0 + r11 * x1 + r12 * x2
        out[2, j] = r20 * x0 + r21 * x1 + r22 * x2


@numba.njit(inline="always")
def _filter_step(h_at, h_args,
                 X, V, h, g, have_g, dt, margin, alpha, length_scale, eps_p, eps_w, scales,
                 V_out, X_next, g_out, work):
    """Steps 2-3 of the module docstring for one pose X (4, 4) and twist V (6,) in Center whose
    command failed the discrete condition at barrier h: the gradient (12 perturbed poses, unless
    ``have_g``: then ``g`` is used), the projection, the scales tried on h itself. Writes V_out,
    X_next, g_out (the gradient used); returns (h at X_next, |V_out|_M / |V|_M). ``work`` is a
    (4, 4) buffer; ``h_at(h_args, X)`` is the barrier's compiled one-pose hook (the clearance's
    ``at`` and ``at_args``)."""
    if have_g:
        for i in range(6):
            g_out[i] = g[i]
    else:
        e = np.zeros(6)
        for i in range(3):
            for sign in (1.0, -1.0):
                e[:] = 0.0
                e[i] = sign
                step_pose_into(X, e, eps_w, work)  # rotated about the TCP by sign eps_w about x_i
                hr = h_at(h_args, work)
                e[i] = 0.0
                e[3 + i] = sign
                step_pose_into(X, e, eps_p, work)  # moved by sign eps_p along x_i
                hp = h_at(h_args, work)
                if sign > 0.0:
                    g_out[i], g_out[3 + i] = hr, hp
                else:
                    g_out[i] = (g_out[i] - hr) / (2.0 * eps_w)
                    g_out[3 + i] = (g_out[3 + i] - hp) / (2.0 * eps_p)
        for i in range(6):
            if not np.isfinite(g_out[i]):  # out of the mouth: no limit
                g_out[i] = 0.0
    # aim at 90% of the allowed approach: room for the linearization of a non-smooth h
    Vp = np.empty(6)
    _project(V, h, g_out, margin, AIM * alpha, length_scale, Vp)
    limit = h + dt * min(-alpha * (h - margin), 0.0)
    if h >= margin:  # across the bound's own steps, never below the margin (step 3)
        limit = min(limit, max(margin, limit - JUMP))
    limit -= TOLERANCE
    h_next = h
    chosen = 0.0
    Vs = np.empty(6)
    for k in range(scales.size):
        for i in range(6):
            Vs[i] = scales[k] * Vp[i]
        step_pose_into(X, Vs, dt, work)
        hs = h_at(h_args, work)
        if hs >= limit:
            chosen, h_next = scales[k], hs
            X_next[:, :] = work
            break
    if chosen == 0.0:  # stopping always meets the condition
        X_next[:, :] = X
    l2 = length_scale * length_scale
    num = 0.0
    den = 0.0
    for i in range(6):
        V_out[i] = chosen * Vp[i]
        m = l2 if i < 3 else 1.0
        num += V_out[i] * V_out[i] * m
        den += V[i] * V[i] * m
    return h_next, (np.sqrt(num / den) if den > 0.0 else 1.0)


@numba.njit(cache=True)
def _filter_step_fpsm(h_args, X, V, h, g, have_g, dt, margin, alpha, length_scale, eps_p,
                      eps_w, scales, V_out, X_next, g_out, work):
    """:func:`_filter_step` on the FPSM bound (an entry point with its hook fixed: numba
    caches it on disk, which it does not for a hook passed in from Python)."""
    return _filter_step(fpsm_at, h_args, X, V, h, g, have_g, dt, margin, alpha, length_scale,
                        eps_p, eps_w, scales, V_out, X_next, g_out, work)


@numba.njit(cache=True)
def _filter_step_scan(h_args, X, V, h, g, have_g, dt, margin, alpha, length_scale, eps_p,
                      eps_w, scales, V_out, X_next, g_out, work):
    """:func:`_filter_step` on the capped scan bound (as :func:`_filter_step_fpsm`)."""
    return _filter_step(capped_at, h_args, X, V, h, g, have_g, dt, margin, alpha, length_scale,
                        eps_p, eps_w, scales, V_out, X_next, g_out, work)


_FILTER_STEPS = {fpsm_at: _filter_step_fpsm, capped_at: _filter_step_scan}


def _filter_step_of(clear):
    """The compiled slow path for a prepared clearance (by its hook ``at``)."""
    try:
        return _FILTER_STEPS[clear.at]
    except (KeyError, AttributeError):
        raise InputError("clearance", "expected a ToolClearance or a CappedScanClearance "
                         f"(a compiled hook the supervisor knows), got "
                         f"{type(clear).__name__}") from None


@dataclass(frozen=True)
class Supervised:
    """One supervisor step for K poses (Center frame, SI); fields (K, ...).

    Attributes:
        V: (K, 6) the filtered twist.
        X_next: (K, 4, 4) the pose one period ahead under V.
        h: (K,) barrier value at the pose (m, +inf outside the mouth).
        h_next: (K,) barrier value at X_next.
        scale: (K,) |V|_M / |V_command|_M (1: untouched, 0: stopped).
        active: (K,) the command was changed.
        g: (K, 6) the gradient used where active (NaN elsewhere).
    """

    V: np.ndarray
    X_next: np.ndarray
    h: np.ndarray
    h_next: np.ndarray
    scale: np.ndarray
    active: np.ndarray
    g: np.ndarray


def supervise(clear: ToolClearance, X_CT, V_C, barrier: Barrier, dt: float, *,
              h=None, g=None, limits: CommandLimits | None = None) -> Supervised:
    """Steps 0-3 of the module docstring for K tool poses ``X_CT`` (K, 4, 4) in Center and
    commanded twists ``V_C`` (K, 6) in Center, over a period ``dt`` (s). ``h`` (K,): the
    barrier at the poses if known (the supervisor keeps it from its previous step); ``g``
    (K, 6): a gradient to use instead of the finite differences (the supervisor reuses one over
    a few consecutive steps at the wall; it only shapes the projection, which step 3 checks on h
    itself); ``limits``: clip the twists to these speed limits first (step 0; None: no clip).
    ``scale`` is then relative to the clipped twist."""
    X = np.asarray(X_CT, dtype=float).reshape(-1, 4, 4)
    V = np.asarray(V_C, dtype=float).reshape(-1, 6)
    K = X.shape[0]
    if V.shape[0] != K:
        raise InputError("V_C", f"expected one twist per pose ({K}), got {V.shape[0]}")
    if limits is not None:
        V = np.array([clip_twist(Vk, limits) for Vk in V]).reshape(-1, 6)
    X_cmd = np.empty_like(X)
    for k in range(K):  # the compiled step (Drake's AngleAxis rejects a twist of ~1e-160)
        step_pose_into(np.ascontiguousarray(X[k]), np.ascontiguousarray(V[k]), float(dt), X_cmd[k])
    if h is None:
        H = clear(np.concatenate([X, X_cmd]))
        h, h_cmd = H[:K], H[K:]
    else:
        h, h_cmd = np.asarray(h, dtype=float).reshape(K), clear(X_cmd)
    ok = barrier_holds(h, h_cmd, barrier, dt)
    V_out, X_next, h_next = V.copy(), X_cmd, h_cmd.copy()
    scale = np.ones(K)
    g_out = np.full((K, 6), np.nan)
    work = np.empty((4, 4))
    have_g = g is not None
    g_in = (np.ascontiguousarray(g, dtype=float).reshape(K, 6) if have_g else np.zeros((K, 6)))
    step = _filter_step_of(clear)
    for k in np.flatnonzero(~ok):
        Xk = np.ascontiguousarray(X[k])
        g_k = np.empty(6)
        Xn = np.empty((4, 4))
        h_next[k], scale[k] = step(
            clear.at_args, Xk, np.ascontiguousarray(V[k]), float(h[k]), g_in[k], have_g,
            float(dt), barrier.margin, barrier.alpha, barrier.length_scale, barrier.eps_p,
            barrier.eps_w, SCALES, V_out[k], Xn, g_k, work)
        X_next[k], g_out[k] = Xn, g_k
    return Supervised(V=V_out, X_next=X_next, h=h, h_next=h_next, scale=scale, active=~ok,
                      g=g_out)


@numba.njit(cache=True)
def _world_pose_of_E(new, X_WC, X_TE):
    """new[21:33] = the World pose of E (p_WE, R_WE row-major) from the Tool pose in Center in
    new[0:12] (p_CT, R_CT row-major); E's origin is the Tool's."""
    for i in range(3):
        pw = X_WC[i, 3]
        for j in range(3):
            pw += X_WC[i, j] * new[j]
        new[21 + i] = pw
        for j in range(3):
            acc = 0.0
            for k in range(3):
                RWk = 0.0
                for m in range(3):
                    RWk += X_WC[i, m] * new[3 + 3 * m + k]
                acc += RWk * X_TE[k, j]
            new[24 + 3 * i + j] = acc


@numba.njit(cache=True)
def _advance(x, V_W, dR, dt, R_CW, X_WC, X_TE, new, X1):
    """The supervisor's state one period on under the twist V_W (World) left as it is: the Tool
    pose in Center (p + v dt, dR R), the twist, scale 1, not active, the World pose of E; X1 the
    new Tool pose in Center (4, 4). ``new[18]`` (h) is left to the caller."""
    for i in range(3):
        v = 0.0
        for j in range(3):
            v += R_CW[i, j] * V_W[3 + j]
        new[i] = x[i] + v * dt
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += dR[i, k] * x[3 + 3 * k + j]
            new[3 + 3 * i + j] = acc
    for i in range(6):
        new[12 + i] = V_W[i]
    new[19], new[20] = 1.0, 0.0
    _world_pose_of_E(new, X_WC, X_TE)
    for i in range(3):
        X1[i, 3] = new[i]
        for j in range(3):
            X1[i, j] = new[3 + 3 * i + j]
    X1[3, 0], X1[3, 1], X1[3, 2], X1[3, 3] = 0.0, 0.0, 0.0, 1.0


@numba.njit(cache=True)
def _commit(X, V, scale, R_CW, X_WC, X_TE, new):
    """The supervisor's state after a filtered step: the Tool pose X (4, 4) in Center, the
    filtered twist V (Center) in World, the scale, active, the World pose of E (``new[0:21]``
    but h, and ``new[21:33]``)."""
    for i in range(3):
        new[i] = X[i, 3]
        for j in range(3):
            new[3 + 3 * i + j] = X[i, j]
    for i in range(3):  # R_WC = R_CW^T
        w = 0.0
        v = 0.0
        for j in range(3):
            w += R_CW[j, i] * V[j]
            v += R_CW[j, i] * V[3 + j]
        new[12 + i], new[15 + i] = w, v
    new[19], new[20] = scale, 1.0
    _world_pose_of_E(new, X_WC, X_TE)


@numba.njit(inline="always")
def _advance_checked(h_at, h_args, x, V_W, dR, dt, R_CW, X_WC, X_TE, margin, alpha, new, X1):
    """The update's common path in one call: :func:`_advance`, the barrier h at the commanded
    next pose X1 and the discrete barrier condition (on floats, as :func:`barrier_holds`).
    True: the command passes, ``new`` is the whole next state (h capped at ``FAR``, no gradient
    kept); False: it fails the condition, ``new[18]`` holds h at X1 and the caller takes the
    slow path (steps 2-3)."""
    _advance(x, V_W, dR, dt, R_CW, X_WC, X_TE, new, X1)
    h = h_at(h_args, X1)
    h0 = x[18]
    if h0 < FAR:  # the barrier at the pose itself, kept from the previous update
        a = -alpha * (h0 - margin)
        b = 0.0 if 0.0 < a else a  # min(a, 0.0) as Python's min takes it
        if not h >= h0 + dt * b - TOLERANCE:
            new[18] = h
            return False
    new[18] = FAR if FAR < h else h
    for i in range(33, 39):  # not at the wall this step: the next slow step computes afresh
        new[i] = 0.0
    new[39] = GRADIENT_REUSE
    return True


@numba.njit(cache=True)
def _advance_checked_fpsm(h_args, x, V_W, dR, dt, R_CW, X_WC, X_TE, margin, alpha, new, X1):
    """:func:`_advance_checked` on the FPSM bound (as :func:`_filter_step_fpsm`)."""
    return _advance_checked(fpsm_at, h_args, x, V_W, dR, dt, R_CW, X_WC, X_TE, margin, alpha,
                            new, X1)


@numba.njit(cache=True)
def _advance_checked_scan(h_args, x, V_W, dR, dt, R_CW, X_WC, X_TE, margin, alpha, new, X1):
    """:func:`_advance_checked` on the capped scan bound (as :func:`_filter_step_scan`)."""
    return _advance_checked(capped_at, h_args, x, V_W, dR, dt, R_CW, X_WC, X_TE, margin, alpha,
                            new, X1)


_ADVANCE_CHECKED = {fpsm_at: _advance_checked_fpsm, capped_at: _advance_checked_scan}


class SafetySupervisor(LeafSystem):
    """Filters the fixture's corrected twist with the FPSM barrier; integrates the desired pose.

    .. pydrake_system::

        name: SafetySupervisor
        input_ports:
        - V_WE_corrected
        output_ports:
        - X_WE_desired
        - V_WE_filtered
        - barrier

    ``V_WE_corrected`` (6): the twist to filter, [w; v] in World (the fixture's output).
    ``X_WE_desired`` (abstract RigidTransform): the desired tool pose, integrated every period
    from the filtered twist (discrete state, kept as the Tool pose in Center), for differential
    IK; the barrier is evaluated at it (the pose the command drives the tool to).
    ``V_WE_filtered`` (6): the filtered twist of the last update, in World. ``barrier`` (3): [h
    at the desired pose (m; 1e3 for +inf, the tool outside the mouth), scale
    (|V_filtered|_M / |V_corrected|_M), active (1.0 when the command was changed at the last
    update)].

    Each update costs one clearance query (the commanded next pose: the barrier at the pose
    itself is kept from the previous update); only a command that fails the discrete barrier
    condition pays for the gradient (12 poses) and the check of the projection (4 poses). A
    released update costs none: h is left out of the state (NaN) and computed at the desired
    pose when the ``barrier`` port is evaluated, or by the first update after the release.

    Args:
        fpsm: the surrogate model (Center frame).
        X_WCenter: (4, 4) pose of Center in World.
        X_WE_initial: (4, 4) initial desired pose.
        tool: the tool for :class:`ToolClearance`, in its Tool frame.
        R_ET: (3, 3) the Tool axes in E (identity if None); the Tool origin is E's.
        barrier: the filter's settings.
        period: update period (s).
        enabled: False integrates the command unfiltered (experiments without the supervisor).
        margin_input: declare a vector input port ``margin_extra`` (1, m) added to the
            barrier's margin at every update (the awake patient: tracking lag and error).
        limits: the speed limits every integrated step keeps (step 0; CommandLimits() if
            None), with the supervisor on or off.
        release_input: declare a vector input port ``barrier_release`` (1): while it is > 0.5
            the command is integrated without the barrier (speed limits kept), as with
            ``enabled`` False: the implant's insertion into the bone (systems.teleop.insertion),
            which the FPSM, the cavity's free space, calls a collision.
        clearance: the barrier's clearance of ``tool``, prepared (``__call__``, ``one``, the
            compiled hook ``at`` / ``at_args``): the scan bound capped above the margin
            (:class:`systems.placement.scan_clearance.CappedScanClearance`) when the plan has
            the scan; None: the FPSM bound (:class:`ToolClearance`).
    """

    def __init__(
        self,
        fpsm: Fpsm,
        X_WCenter,
        X_WE_initial,
        tool: Instrument,
        *,
        R_ET=None,
        barrier: Barrier | None = None,
        period: float = 0.005,
        enabled: bool = True,
        margin_input: bool = False,
        limits: CommandLimits | None = None,
        release_input: bool = False,
        clearance=None,
    ):
        super().__init__()
        if not np.isfinite(period) or period <= 0:
            raise InputError("period", f"expected a period > 0 s, got {period}")
        self.limits = limits or CommandLimits()
        self._clear = ToolClearance(fpsm, tool) if clearance is None else clearance
        self._filter_step = _filter_step_of(self._clear)
        self._advance_checked = _ADVANCE_CHECKED[self._clear.at]
        if clearance is not None and clearance.instrument != tool:
            raise InputError("clearance", f"bounds the instrument {clearance.instrument.name!r},"
                             f" not the supervisor's {tool.name!r}")
        self._barrier = barrier or Barrier()
        self._period = float(period)
        self._enabled = bool(enabled)
        self._X_WC = np.asarray(X_WCenter, dtype=float)
        self._X_CW = invert(self._X_WC)
        self._R_CW = np.ascontiguousarray(self._X_CW[:3, :3])
        self._X_WC = np.ascontiguousarray(self._X_WC)
        R_ET = np.eye(3) if R_ET is None else np.asarray(R_ET, dtype=float)
        self._X_ET = np.eye(4)
        self._X_ET[:3, :3] = R_ET
        self._X_TE = invert(self._X_ET)
        # buffers of the compiled slow path (no allocation per step)
        self._X0, self._Xn, self._work, self._X1 = np.eye(4), np.eye(4), np.eye(4), np.eye(4)
        self._Xh = np.eye(4)  # the pose of :meth:`_h_of_state`
        self._Vc, self._Vo, self._g = np.zeros(6), np.zeros(6), np.zeros(6)
        self._V_in = self.DeclareVectorInputPort("V_WE_corrected", 6)
        self._margin_in = self.DeclareVectorInputPort("margin_extra", 1) if margin_input else None
        self._release = (self.DeclareVectorInputPort("barrier_release", 1) if release_input
                         else None)
        # state: [p_CT (3), R_CT row-major (9), V filtered in World (6), h, scale, active,
        #         p_WE (3), R_WE row-major (9), gradient (6), its age in steps]
        self.DeclareDiscreteState(self._state_of(np.asarray(X_WE_initial, dtype=float)))
        self.DeclarePeriodicDiscreteUpdateEvent(self._period, 0.0, self._update)
        self._X_des = self.DeclareAbstractOutputPort(
            "X_WE_desired",
            lambda: AbstractValue.Make(RigidTransform()),
            self._calc_desired,
            prerequisites_of_calc={self.xd_ticket()},
        )
        self._V_out = self.DeclareVectorOutputPort(
            "V_WE_filtered", 6, self._calc_filtered, prerequisites_of_calc={self.xd_ticket()}
        )
        self._h = self.DeclareVectorOutputPort(
            "barrier", 3, self._calc_barrier, prerequisites_of_calc={self.xd_ticket()}
        )

    @property
    def barrier(self) -> Barrier:
        """The barrier's settings this supervisor enforces (margin, rate)."""
        return self._barrier

    def _state_of(self, X_WE) -> np.ndarray:
        X_CT = self._X_CW @ X_WE @ self._X_ET
        h = self._clear(X_CT[None])[0]
        return np.concatenate([X_CT[:3, 3], X_CT[:3, :3].ravel(), np.zeros(6),
                               [min(h, FAR), 1.0, 0.0], X_WE[:3, 3], X_WE[:3, :3].ravel(),
                               np.zeros(6), [GRADIENT_REUSE]])

    def _update(self, context, discrete_state):
        x = context.get_discrete_state(0).get_value()
        V_W = clip_twist(self._V_in.Eval(context), self.limits)  # step 0
        new = discrete_state.get_mutable_value(0)  # the next state, written in place
        if V_W[0] == 0.0 and V_W[1] == 0.0 and V_W[2] == 0.0:  # no rotation: the common case
            w_C, dR = None, _IDENTITY
        else:  # the rotation of one period (Drake's AngleAxis; the operator's command has none)
            w_C = self._R_CW @ V_W[:3]
            angle = float(np.linalg.norm(w_C)) * self._period
            dR = _IDENTITY if angle == 0.0 else RotationMatrix(
                AngleAxis(angle, w_C * (self._period / angle))).matrix()
        released = self._release is not None and self._release.Eval(context)[0] > 0.5
        X1 = self._X1
        if not released and np.isnan(x[18]):  # back from a release: h where the pose is now
            x = x.copy()
            x[18] = self._h_of_state(x)
        if self._enabled and not released:
            bar = self._barrier
            margin = bar.margin
            if self._margin_in is not None:  # the awake patient: tracking lag and error
                margin = margin + float(self._margin_in.Eval(context)[0])
                if not 0.0 <= margin < np.inf:
                    replace(bar, margin=margin)  # raises the barrier's own error
            if self._advance_checked(self._clear.at_args, x, V_W, dR, self._period, self._R_CW,
                                     self._X_WC, self._X_TE, margin, bar.alpha, new, X1):
                return
            # the slow path: the command fails the discrete barrier condition
            h0 = float(x[18])
            X0 = self._X0
            X0[:3, :3], X0[:3, 3] = x[3:12].reshape(3, 3), x[:3]
            V = self._Vc
            V[:3] = self._R_CW @ V_W[:3] if w_C is None else w_C
            V[3:] = self._R_CW @ V_W[3:]
            age = int(x[39])
            have_g = age < GRADIENT_REUSE
            h, scale = self._filter_step(
                self._clear.at_args, X0, V,
                h0, x[33:39], have_g, self._period, margin, bar.alpha,
                bar.length_scale, bar.eps_p, bar.eps_w, SCALES, self._Vo, self._Xn,
                self._g, self._work)
            new[33:39] = self._g
            new[39] = age + 1 if have_g else 1
            _commit(self._Xn, self._Vo, scale, self._R_CW, self._X_WC, self._X_TE, new)
            new[18] = min(h, FAR)
            return
        _advance(x, V_W, dR, self._period, self._R_CW, self._X_WC, self._X_TE, new, X1)
        # released: h at the new pose is not needed to integrate; the barrier port computes it
        # if asked (NaN: not computed yet), the first update after the release before using it
        new[18] = np.nan if released else min(x[18], FAR)
        new[33:39], new[39] = 0.0, GRADIENT_REUSE  # not at the wall

    def _h_of_state(self, x) -> float:
        """min(h, FAR) at the desired pose of state ``x`` (its Tool pose in Center)."""
        X = self._Xh
        X[:3, :3], X[:3, 3] = x[3:12].reshape(3, 3), x[:3]
        return min(self._clear.one(X), FAR)

    def _calc_desired(self, context, value):
        x = context.get_discrete_state(0).get_value()
        value.set_value(RigidTransform(RotationMatrix(x[24:33].reshape(3, 3)), x[21:24]))

    def _calc_filtered(self, context, output: BasicVector):
        output.set_value(context.get_discrete_state(0).get_value()[12:18])

    def _calc_barrier(self, context, output: BasicVector):
        x = context.get_discrete_state(0).get_value()
        if np.isnan(x[18]):  # released: h computed on demand (the update skips it)
            output.set_value(np.array([self._h_of_state(x), x[19], x[20]]))
        else:
            output.set_value(x[18:21])

    def set_desired_pose(self, context, X_WE) -> None:
        """Reset the desired pose (e.g. to the tool's pose at the start of a run)."""
        context.SetDiscreteState(0, self._state_of(np.asarray(X_WE, dtype=float)))
