"""The conical virtual fixture (VF) that guards the feed (seed 000 Sec. 2.2, its ref. [12]).

Geometry. The fixture's axis is line1 of the placement (through the feeding target T = Tool
origin, direction D out of the mouth). With s the axial coordinate from T along D and rho the
distance from the axis, the *axis region* is
    s >= 0 (when ``cap`` is set: the tool may not pass the target) and rho <= R(s),
where R is the profile: the lateral tolerance ``lateral_tolerance`` (delta) from s = 0 to the
entry point at the mouth opening (s_entry, where line1 crosses the top slice plane), then a chain
of conical segments of given lengths and half-angles, each widening the radius by
length * tan(half_angle) (the funnel outside the mouth), and beyond the last segment a cylinder
of the final radius.

What the fixture bounds: the tool *body* (DESIGN.md section 4). The paper's cylinder "of the
tool's radius" (``cylinder_radius`` = r) keeps the tool on the line, so the constrained points
are on the tool's axis, not its surface:

- the TCP (the head centre, on the rod axis) must lie in the axis region;
- while the TCP is inside the mouth (s_TCP < s_entry) the rod axis where it crosses the entry
  plane s = s_entry must lie within delta too. The rod axis is a straight segment and its lateral
  offset from line1 is affine in s, so the whole in-mouth part of the rod is then within delta
  of line1 (the maximum of a convex function on a segment sits at an end): the rod body stays in
  the cylinder of radius r + delta about line1;
- the tool's orientation stays within ``angle_tolerance`` (beta) of the planned Tool frame
  ``R_ref`` (the geodesic angle, tilt and roll; without ``R_ref`` the tilt of the rod from D).

Previously (and in the paper's figures) the last cylinder had the rod's radius and constrained
the TCP point only, which lets the rod axis sit r off line1, into tissue.

Queries are batched over points: the signed distance to the axis region's boundary is computed
exactly in the meridian half-plane (s, rho) as the distance to the profile polyline, negative
inside; its gradient is the outward normal (one compiled kernel, :func:`_signed_batch`, serves
the numpy API and the body law).

Admittance law (:meth:`VirtualFixture.correct_twist`, :func:`body_law`). The commanded spatial
velocity V = [w; v] of the tool (w its angular velocity, v the TCP's velocity) is filtered:

1. orientation: with phi the rotation vector from R_ref to the tool (|phi| the angle error) the
   rate d|phi|/dt ~ w . phi/|phi| is limited to what reaches beta within one period, and a tool
   beyond beta gets the return rate -g (|phi| - beta) (stiffness on the violation through the
   damping: g = k / b, 1/s);
2. position: each constrained point P_i (outward normal n_i, signed distance d_i) moves with
   v + w x (P_i - p); its outward speed is limited to -d_i / dt inside and to -g d_i outside
   (the return). v is the least-squares change of the command meeting both half-space limits
   (closed form for two constraints), so motion along the axis and along the boundary passes.

The force a haptic master renders is the spring-damper on the violation,
F = sum_i -(k d_i + b max(v_i . n_i, 0)) n_i over the points outside (zero inside).
Departure from ref. [12]: its segment sizes are not published; the defaults here (a 30 mm cone of
15 deg then a 50 mm cone of 30 deg outside the mouth) are ours and are stored in the plan, as are
delta (0.5 mm) and beta (0.5 deg: 0.27 mm at the 31 mm implant tip).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from implantplan.systems.errors import InputError
from implantplan.systems.jit import numba
from implantplan.systems.safety import DEFAULT as SAFETY

# delta (m) and beta (rad): the fixture's admissible region, the safety spec's (one default each;
# the planner builds every fixture with its case's spec, the region it verified)
LATERAL_TOLERANCE = SAFETY.lateral_tolerance
ANGLE_TOLERANCE = SAFETY.angle_tolerance
_FAR = 1e3  # m: the last radius continues this far (and the uncapped cylinder back past T)


def _perpendicular(u: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e = a - np.dot(a, u) * u
    return e / np.linalg.norm(e)


# -- compiled kernels -------------------------------------------------------------------------


@numba.njit(cache=True)
def _profile_signed(s, rho, ps, pr, cap):
    """Signed distance of the meridian point (s, rho) to the region {rho <= R(s), s >= 0 if
    cap} whose boundary is the polyline (ps, pr) (the cap disc / backward cylinder included),
    and its outward normal (ns, nr) in the meridian plane."""
    best, bqs, bqr, bk = np.inf, 0.0, 0.0, 0
    for k in range(ps.size - 1):
        ds, dr = ps[k + 1] - ps[k], pr[k + 1] - pr[k]
        qs, qr = s - ps[k], rho - pr[k]
        seg2 = ds * ds + dr * dr
        t = (qs * ds + qr * dr) / seg2 if seg2 > 0.0 else 0.0
        t = min(max(t, 0.0), 1.0)
        qs -= t * ds
        qr -= t * dr
        d2 = qs * qs + qr * qr
        if d2 < best:
            best, bqs, bqr, bk = d2, qs, qr, k
    # R(s) on the profile proper: constant beyond both ends (ps[0] is 0 with the cap)
    lo = 1 if cap else 0
    if s <= ps[lo + 1]:
        R = pr[lo + 1] if cap else pr[lo]
    else:
        R = pr[ps.size - 1]
        for k in range(lo + 1, ps.size - 1):
            if s <= ps[k + 1]:
                w = (s - ps[k]) / (ps[k + 1] - ps[k])
                R = pr[k] + w * (pr[k + 1] - pr[k])
                break
    inside = rho <= R and (s >= 0.0 or not cap)
    sign = -1.0 if inside else 1.0
    dist = np.sqrt(best)
    if dist < 1e-15:  # on the boundary: the edge's outward normal (edge turned by +90 deg)
        es, er = ps[bk + 1] - ps[bk], pr[bk + 1] - pr[bk]
        el = np.sqrt(es * es + er * er)
        return sign * dist, -er / el, es / el
    return sign * dist, sign * bqs / dist, sign * bqr / dist


@numba.njit(cache=True)
def _point_signed(p, origin, D, e1, ps, pr, cap, out_n):
    """Signed distance of a 3D point; writes the outward unit normal into ``out_n``."""
    r0, r1, r2 = p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]
    s = r0 * D[0] + r1 * D[1] + r2 * D[2]
    a0, a1, a2 = r0 - s * D[0], r1 - s * D[1], r2 - s * D[2]
    rho = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    if rho > 1e-15:
        a0, a1, a2 = a0 / rho, a1 / rho, a2 / rho
    else:
        a0, a1, a2 = e1[0], e1[1], e1[2]
    d, ns, nr = _profile_signed(s, rho, ps, pr, cap)
    out_n[0] = ns * D[0] + nr * a0
    out_n[1] = ns * D[1] + nr * a1
    out_n[2] = ns * D[2] + nr * a2
    return d


@numba.njit(cache=True)
def _lateral(p, origin, D, e1, out_n):
    """Distance of a point from the axis; writes the radial unit vector into ``out_n``."""
    r0, r1, r2 = p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]
    s = r0 * D[0] + r1 * D[1] + r2 * D[2]
    a0, a1, a2 = r0 - s * D[0], r1 - s * D[1], r2 - s * D[2]
    rho = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    if rho > 1e-15:
        out_n[0], out_n[1], out_n[2] = a0 / rho, a1 / rho, a2 / rho
    else:
        out_n[0], out_n[1], out_n[2] = e1[0], e1[1], e1[2]
    return rho


@numba.njit(cache=True)
def _signed_batch(P, origin, D, e1, ps, pr, cap, d, n):
    for i in range(P.shape[0]):
        d[i] = _point_signed(P[i], origin, D, e1, ps, pr, cap, n[i])


@numba.njit(cache=True)
def _rotation_error(R, R_ref, has_ref, D, phi):
    """Rotation vector phi (Center) from the planned orientation to the tool's; returns |phi|.
    Without a reference: the tilt of the tool x axis (the rod) from D."""
    if has_ref:
        # R_err = R R_ref^T; phi = angle * axis from its skew part (angles well below pi here)
        E = np.zeros((3, 3))
        for i in range(3):
            for j in range(3):
                E[i, j] = R[i, 0] * R_ref[j, 0] + R[i, 1] * R_ref[j, 1] + R[i, 2] * R_ref[j, 2]
        w0, w1, w2 = E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]
        c = 0.5 * (E[0, 0] + E[1, 1] + E[2, 2] - 1.0)
    else:
        a0, a1, a2 = R[0, 0], R[1, 0], R[2, 0]
        w0 = 2.0 * (D[1] * a2 - D[2] * a1)  # 2 (D x a) = 2 sin(angle) axis
        w1 = 2.0 * (D[2] * a0 - D[0] * a2)
        w2 = 2.0 * (D[0] * a1 - D[1] * a0)
        c = D[0] * a0 + D[1] * a1 + D[2] * a2
    sn = 0.5 * np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    angle = np.arctan2(sn, c)
    f = angle / (2.0 * sn) if sn > 1e-15 else 0.5
    phi[0], phi[1], phi[2] = f * w0, f * w1, f * w2
    return angle


@numba.njit(cache=True)
def _limit(d, dt, gain, tol):
    """Largest outward rate allowed for a signed distance d (the return rate when outside)."""
    if d > 0.0:
        return -gain * d
    if dt > 0.0:
        return -d / dt
    return np.inf if d < -tol else 0.0


@numba.njit(cache=True)
def _dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@numba.njit(cache=True)
def _project(v, n, c, m):
    """The least-squares change of v (3) meeting n_i . x <= c_i for the first m (<= 3) rows:
    the exact projection on the intersection of the half-spaces, by trying each set of active
    constraints (at most 7; Cramer's rule on their Gram matrix) and keeping the nearest
    feasible candidate."""
    feasible = True
    for i in range(m):
        if _dot3(n[i], v) > c[i]:
            feasible = False
    if feasible:
        return v.copy()
    best = v.copy()
    best_d2 = np.inf
    idx = np.empty(3, dtype=np.int64)
    G = np.empty((3, 3))
    r = np.empty(3)
    lam = np.empty(3)
    x = np.empty(3)
    for mask in range(1, 1 << m):
        q = 0
        skip = False
        for i in range(m):
            if mask & (1 << i):
                idx[q] = i
                q += 1
                skip = skip or not np.isfinite(c[i])  # never active
        if skip:
            continue
        for a in range(q):
            r[a] = _dot3(n[idx[a]], v) - c[idx[a]]
            for bb in range(q):
                G[a, bb] = _dot3(n[idx[a]], n[idx[bb]])
        if q == 1:
            lam[0] = r[0] / G[0, 0]
        elif q == 2:
            det = G[0, 0] * G[1, 1] - G[0, 1] * G[1, 0]
            if abs(det) < 1e-12:
                continue
            lam[0] = (r[0] * G[1, 1] - G[0, 1] * r[1]) / det
            lam[1] = (G[0, 0] * r[1] - G[1, 0] * r[0]) / det
        else:
            c00 = G[1, 1] * G[2, 2] - G[1, 2] * G[2, 1]
            c01 = G[1, 2] * G[2, 0] - G[1, 0] * G[2, 2]
            c02 = G[1, 0] * G[2, 1] - G[1, 1] * G[2, 0]
            det = G[0, 0] * c00 + G[0, 1] * c01 + G[0, 2] * c02
            if abs(det) < 1e-12:
                continue
            # inverse by cofactors (G is symmetric)
            c11 = G[0, 0] * G[2, 2] - G[0, 2] * G[2, 0]
            c12 = G[0, 1] * G[2, 0] - G[0, 0] * G[2, 1]
            c22 = G[0, 0] * G[1, 1] - G[0, 1] * G[1, 0]
            lam[0] = (c00 * r[0] + c01 * r[1] + c02 * r[2]) / det
            lam[1] = (c01 * r[0] + c11 * r[1] + c12 * r[2]) / det
            lam[2] = (c02 * r[0] + c12 * r[1] + c22 * r[2]) / det
        neg = False
        for a in range(q):
            neg = neg or lam[a] < -1e-12
        if neg:
            continue
        for j in range(3):
            x[j] = v[j]
            for a in range(q):
                x[j] -= lam[a] * n[idx[a], j]
        ok = True
        for i in range(m):
            if _dot3(n[i], x) > c[i] + 1e-12:
                ok = False
        d2 = (x[0] - v[0]) ** 2 + (x[1] - v[1]) ** 2 + (x[2] - v[2]) ** 2
        if ok and d2 < best_d2:
            best[:] = x
            best_d2 = d2
    if best_d2 == np.inf:  # degenerate (parallel) constraints: cyclic projections
        for _ in range(50):
            for i in range(m):
                g = _dot3(n[i], best) - c[i]
                if g > 0.0:
                    best -= g * n[i]
    return best


@numba.njit(cache=True)
def _crossing(p, a, origin, D, s_entry, out_q):
    """The point where the axis p + t a crosses the entry plane s = s_entry (False: none, the
    TCP is at or outside the entry or the axis runs along the plane)."""
    s0 = (p[0] - origin[0]) * D[0] + (p[1] - origin[1]) * D[1] + (p[2] - origin[2]) * D[2]
    aD = a[0] * D[0] + a[1] * D[1] + a[2] * D[2]
    if s0 >= s_entry or aD <= 1e-6:
        return False
    t = (s_entry - s0) / aD
    for j in range(3):
        out_q[j] = p[j] + t * a[j]
    return True


@numba.njit(cache=True)
def _disc_step(e, u, R):
    """Largest t in [0, 1] with |e + t u| <= R (e, u lateral vectors); 0 if even t = 0 is
    outside."""
    eu = _dot3(e, u)
    uu = _dot3(u, u)
    ee = _dot3(e, e)
    if ee + 2.0 * eu + uu <= R * R:
        return 1.0
    if uu < 1e-300:
        return 1.0
    disc = eu * eu - uu * (ee - R * R)
    if disc < 0.0:
        return 0.0
    return min(max((-eu + np.sqrt(disc)) / uu, 0.0), 1.0)


@numba.njit(cache=True)
def _lateral_safeguard(p, v, a1, dt, origin, D, pr_lat, ps_lat, s_entry, crossing, d_now, target,
                       delta):
    """The linearized walls are curved (a disc about line1): limit the lateral part of v so that
    the TCP and the rod's entry crossing, one period ahead, are within the allowed radius
    (plus the return target when outside). The TCP: its radial step is cut to the radius, then
    its tangential step scaled to end on the circle; the crossing (affine in a common scale
    of the lateral part): the root of a quadratic. The axial part is kept."""
    vD = _dot3(v, D)
    v_par = vD * D
    v_perp = v - v_par
    p_par = p + v_par * dt
    s1 = _dot3(p_par - origin, D)
    # the TCP: lateral offset of p_par, allowed radius R(s) of the lateral profile there
    rel = p_par - origin
    e = rel - _dot3(rel, D) * D
    R = pr_lat[pr_lat.size - 1]
    for kk in range(ps_lat.size - 1):
        if s1 <= ps_lat[kk + 1]:
            span = ps_lat[kk + 1] - ps_lat[kk]
            wgt = (s1 - ps_lat[kk]) / span if span > 0.0 else 0.0
            R = pr_lat[kk] + wgt * (pr_lat[kk + 1] - pr_lat[kk])
            break
    # the TCP's lateral step: keep its radial part unless it alone overshoots, then scale the
    # tangential part so that the step ends within the radius
    R_tcp = R + target[0]
    rho = np.sqrt(_dot3(e, e))
    if rho > 1e-15:
        e_hat = e / rho
        v_r = _dot3(v_perp, e_hat)
        v_t = v_perp - v_r * e_hat
        if rho + v_r * dt > R_tcp:
            v_r = (R_tcp - rho) / dt
        rr = rho + v_r * dt
        tt = np.sqrt(_dot3(v_t, v_t)) * dt
        if rr * rr + tt * tt > R_tcp * R_tcp:
            v_t *= np.sqrt(max(R_tcp * R_tcp - rr * rr, 0.0)) / tt
        v_perp = v_r * e_hat + v_t
    else:
        speed = np.sqrt(_dot3(v_perp, v_perp)) * dt
        if speed > R_tcp:
            v_perp *= R_tcp / speed
    u = v_perp * dt
    t = 1.0
    if crossing:
        q0 = np.empty(3)
        q1 = np.empty(3)
        if _crossing(p_par, a1, origin, D, s_entry, q0) and _crossing(
            p_par + u, a1, origin, D, s_entry, q1
        ):
            r0 = q0 - origin
            e0 = r0 - _dot3(r0, D) * D
            r1 = q1 - origin
            e1q = r1 - _dot3(r1, D) * D
            t = min(t, _disc_step(e0, e1q - e0, delta + target[2]))
    return v_par + t * v_perp


_NO_CAP = np.bool_(False)  # a bool, not the literal False: one compiled _point_signed


@numba.njit(cache=True)
def _body_law(p, R, V, origin, D, e1, ps, pr, cap, ps_lat, pr_lat, s_entry, R_ref, has_ref,
              beta, dt, gain, k, b, tol, out):
    """The body law for one tool pose (p TCP, R tool axes, V = [w; v], all in Center).

    ``out`` (12): corrected [w; v], position violation (m), angle violation (rad), F (3), the
    angle error (rad). The constraints: the TCP against the lateral profile, the TCP against
    the cap (s >= 0), the rod's crossing of the entry plane against delta (its lateral offset;
    the crossing slides with the plane, so its axial motion does not count). With a period dt
    each is linearized about the pose predicted one period ahead and the projection repeated
    (three passes: a Newton iteration on the curved walls, exact for the planar cap); without
    one, about the current pose.
    """
    n = np.zeros((3, 3))
    c = np.zeros(3)
    nrm = np.empty(3)
    phi = np.empty(3)
    q = np.empty(3)
    delta = pr_lat[1]  # the profile's inner radius
    w = V[:3].copy()
    v_cmd = V[3:].copy()
    # 1. orientation
    angle = _rotation_error(R, R_ref, has_ref, D, phi)
    e_ang = angle - beta
    if angle > 1e-12:
        nw = phi / angle
        rate = w[0] * nw[0] + w[1] * nw[1] + w[2] * nw[2]
        allowed = _limit(e_ang, dt, gain, tol)
        if rate > allowed:
            w -= (rate - allowed) * nw
    # 2. where the constraints stand now: violation, targets one period ahead, the force
    a_now = R[:, 0].copy()
    viol = max(_point_signed(p, origin, D, e1, ps, pr, cap, nrm), 0.0)
    F = np.zeros(3)
    d_now = np.zeros(3)
    d_now[0] = _point_signed(p, origin, D, e1, ps_lat, pr_lat, _NO_CAP, nrm)
    n[0] = nrm
    s0 = (p[0] - origin[0]) * D[0] + (p[1] - origin[1]) * D[1] + (p[2] - origin[2]) * D[2]
    d_now[1] = -s0 if cap else -np.inf
    n[1] = -D
    crossing = _crossing(p, a_now, origin, D, s_entry, q)
    lever = q - p
    d_now[2] = _lateral(q, origin, D, e1, nrm) - delta if crossing else -np.inf
    n[2] = nrm
    if crossing:
        viol = max(viol, d_now[2])
    for i in range(3):
        # the spring-damper on the violation, with the commanded velocity, outside or on the
        # wall (within tol): the law keeps the commanded pose inside, so a tool held at the
        # fixture's limit sits on the wall to rounding, and pushing out is what it resists
        if d_now[i] > -tol:
            ni = n[i]
            r = lever if i == 2 else np.zeros(3)
            vp0 = V[3] + V[1] * r[2] - V[2] * r[1]
            vp1 = V[4] + V[2] * r[0] - V[0] * r[2]
            vp2 = V[5] + V[0] * r[1] - V[1] * r[0]
            vn = ni[0] * vp0 + ni[1] * vp1 + ni[2] * vp2
            F -= (k * max(d_now[i], 0.0) + b * max(vn, 0.0)) * ni
    # 3. the translational part
    if dt <= 0.0:  # no period: stop outward motion at or over the walls, about the pose now
        for i in range(3):
            ni = n[i]
            r = lever if i == 2 else np.zeros(3)
            wr0, wr1, wr2 = w[1] * r[2] - w[2] * r[1], w[2] * r[0] - w[0] * r[2], \
                w[0] * r[1] - w[1] * r[0]
            c[i] = _limit(d_now[i], dt, gain, tol) - (ni[0] * wr0 + ni[1] * wr1 + ni[2] * wr2)
        v = _project(v_cmd, n, c, 3)
    else:
        target = np.where(d_now > 0.0, d_now * (1.0 - gain * dt), 0.0)
        # A rotation swings the rod's entry crossing sideways; if the translation cannot make
        # up for it (the TCP at its own wall), the rotation is halved (and at last dropped).
        for attempt in range(4):
            if attempt == 3:
                w[:] = 0.0
            # the axis one period ahead under the rotation
            a1 = a_now + dt * np.array([w[1] * a_now[2] - w[2] * a_now[1],
                                        w[2] * a_now[0] - w[0] * a_now[2],
                                        w[0] * a_now[1] - w[1] * a_now[0]])
            v_lin = np.zeros(3)
            v = v_cmd.copy()
            for _ in range(2):
                pp = p + v_lin * dt
                d_pred = _point_signed(pp, origin, D, e1, ps_lat, pr_lat, _NO_CAP, nrm)
                n[0] = nrm
                c[0] = (target[0] - d_pred) / dt + _dot3(nrm, v_lin)
                c[1] = (target[1] + s0) / dt if cap else np.inf  # -D . v <= (target + s0) / dt
                c[2] = np.inf
                if crossing and _crossing(pp, a1, origin, D, s_entry, q):
                    d_pred = _lateral(q, origin, D, e1, nrm) - delta
                    n[2] = nrm
                    c[2] = (target[2] - d_pred) / dt + _dot3(nrm, v_lin)
                v = _project(v_cmd, n, c, 3)
                v_lin = v
            v = _lateral_safeguard(p, v, a1, dt, origin, D, pr_lat, ps_lat, s_entry, crossing,
                                   d_now, target, delta)
            if not (crossing and _crossing(p + v * dt, a1, origin, D, s_entry, q)):
                break
            if _lateral(q, origin, D, e1, nrm) - delta <= max(target[2], d_now[2]) + 1e-9:
                break
            w *= 0.5
    out[:3] = w
    out[3:6] = v
    out[6] = viol
    out[7] = max(e_ang, 0.0)
    out[8:11] = F
    out[11] = angle


@numba.njit(cache=True)
def _body_batch(p, R, V, origin, D, e1, ps, pr, cap, ps_lat, pr_lat, s_entry, R_ref, has_ref,
                beta, dt, gain, k, b, tol, out):
    for i in range(p.shape[0]):
        _body_law(p[i], R[i], V[i], origin, D, e1, ps, pr, cap, ps_lat, pr_lat, s_entry, R_ref,
                  has_ref, beta, dt, gain, k, b, tol, out[i])


@numba.njit(cache=True)
def body_law_world(X_WE, V_W, X_CW, R_ET, origin, D, e1, ps, pr, cap, ps_lat, pr_lat,
                    s_entry, R_ref, has_ref, beta, dt, gain, k, b, tol, out):
    """:func:`_body_law` for a measured pose X_WE and a command in World (the LeafSystem's
    single query): the tool frame is E rotated by R_ET (same origin); out[:6] and F in World."""
    p = np.empty(3)
    R = np.empty((3, 3))
    V = np.empty(6)
    for i in range(3):
        p[i] = X_CW[i, 3]
        V[i] = 0.0
        V[3 + i] = 0.0
        for j in range(3):
            p[i] += X_CW[i, j] * X_WE[j, 3]
            V[i] += X_CW[i, j] * V_W[j]
            V[3 + i] += X_CW[i, j] * V_W[3 + j]
            acc = 0.0
            for m in range(3):
                RE = 0.0
                for q in range(3):
                    RE += X_WE[m, q] * R_ET[q, j]
                acc += X_CW[i, m] * RE
            R[i, j] = acc
    _body_law(p, R, V, origin, D, e1, ps, pr, cap, ps_lat, pr_lat, s_entry, R_ref, has_ref, beta,
              dt, gain, k, b, tol, out)
    res = out[:11].copy()
    for i in range(3):  # back to World: R_WC = R_CW^T
        out[i] = X_CW[0, i] * res[0] + X_CW[1, i] * res[1] + X_CW[2, i] * res[2]
        out[3 + i] = X_CW[0, i] * res[3] + X_CW[1, i] * res[4] + X_CW[2, i] * res[5]
        out[8 + i] = X_CW[0, i] * res[8] + X_CW[1, i] * res[9] + X_CW[2, i] * res[10]


@dataclass(frozen=True)
class BodyLaw:
    """The body law's result for K tool poses (Center frame, SI); fields (K, ...).

    Attributes:
        V: (K, 6) corrected [w; v].
        violation: (K,) how far the constrained axis points are outside the axis region (m).
        angle_violation: (K,) orientation error beyond beta (rad).
        angle: (K,) orientation error (rad).
        force: (K, 3) the spring-damper force on the violation (N).
    """

    V: np.ndarray
    violation: np.ndarray
    angle_violation: np.ndarray
    angle: np.ndarray
    force: np.ndarray


@dataclass
class VirtualFixture:
    """A chain of cones ending in a cylinder on the feeding axis (all lengths in m, Center frame).

    Attributes:
        origin: (3,) feeding target T on the axis (s = 0).
        direction: (3,) unit axis D, pointing out of the mouth.
        entry_distance: s of the entry point at the mouth opening (m).
        cylinder_radius: the tool's (rod's) radius r (m): the tool body stays within r + delta
            of line1 inside the mouth.
        segment_lengths: (S,) axial lengths of the cones beyond the entry, inner to outer (m).
        half_angles: (S,) half-angles of those cones (rad), in [0, pi/2).
        cap: forbid s < 0 (passing the target).
        lateral_tolerance: delta (m): how far the tool axis may deviate from line1 inside the
            mouth (the profile's inner radius; the cones widen from it).
        angle_tolerance: beta (rad): how far the tool's orientation may deviate.
        R_ref: (3, 3) planned Tool axes in Center (x along D), or None: then only the tilt of
            the rod from D is bounded (no roll reference).
    """

    origin: np.ndarray
    direction: np.ndarray
    entry_distance: float
    cylinder_radius: float
    segment_lengths: np.ndarray
    half_angles: np.ndarray
    cap: bool = True
    lateral_tolerance: float = LATERAL_TOLERANCE
    angle_tolerance: float = ANGLE_TOLERANCE
    R_ref: np.ndarray | None = None

    def __post_init__(self):
        self.origin = np.asarray(self.origin, dtype=float).reshape(3)
        d = np.asarray(self.direction, dtype=float).reshape(3)
        n = np.linalg.norm(d)
        if not np.all(np.isfinite(self.origin)):
            raise InputError("vf.origin", "expected 3 finite coordinates (m)")
        if not np.isfinite(n) or n < 1e-12:
            raise InputError("vf.direction", "expected a finite, non-zero direction")
        self.direction = d / n
        self.segment_lengths = np.atleast_1d(np.asarray(self.segment_lengths, dtype=float))
        self.half_angles = np.atleast_1d(np.asarray(self.half_angles, dtype=float))
        if self.segment_lengths.shape != self.half_angles.shape or self.segment_lengths.ndim != 1:
            raise InputError("vf.segment_lengths", "expected one half-angle per segment")
        if np.any(~np.isfinite(self.segment_lengths)) or np.any(self.segment_lengths <= 0):
            raise InputError("vf.segment_lengths", "expected lengths > 0 m")
        if np.any(~np.isfinite(self.half_angles)) or np.any(
            (self.half_angles < 0) | (self.half_angles >= np.pi / 2)
        ):
            raise InputError("vf.half_angles", "expected half-angles in [0, pi/2) rad")
        for name, lo in (("entry_distance", 0.0), ("cylinder_radius", 0.0),
                         ("lateral_tolerance", 0.0), ("angle_tolerance", 0.0)):
            value = float(getattr(self, name))
            if not np.isfinite(value) or value < lo:
                raise InputError(f"vf.{name}", f"expected a finite value >= {lo:g} (SI units)")
            setattr(self, name, value)
        if self.angle_tolerance >= np.pi / 2:
            raise InputError("vf.angle_tolerance", "expected an angle below pi/2 rad")
        if self.R_ref is not None:
            R = np.asarray(self.R_ref, dtype=float)
            if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or (
                np.linalg.det(R) < 0
            ):
                raise InputError("vf.R_ref", "expected a 3x3 rotation matrix (or null)")
            if R[:, 0] @ self.direction < 1.0 - 1e-6:
                raise InputError("vf.R_ref", "expected its x axis along the fixture direction")
            self.R_ref = R
        self.cap = bool(self.cap)
        self._e1 = _perpendicular(self.direction)
        s, r = self.profile()
        far = s[-1] + _FAR  # the last radius continues as a cylinder
        self._s = np.concatenate([s, [far]])
        self._r = np.concatenate([r, [r[-1]]])
        # the lateral boundary alone (the law constrains the cap separately)
        self._s_lat = np.concatenate([[-_FAR], self._s])
        self._r_lat = np.concatenate([[r[0]], self._r])
        if self.cap:  # the cap disc at s = 0 from the axis to the cylinder
            self._s = np.concatenate([[0.0], self._s])
            self._r = np.concatenate([[0.0], self._r])
        else:  # the cylinder continues past the target
            self._s = np.concatenate([[-_FAR], self._s])
            self._r = np.concatenate([[r[0]], self._r])
        self._R_ref = np.eye(3) if self.R_ref is None else self.R_ref

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def from_placement(
        cls,
        placement,
        fpsm,
        *,
        cylinder_radius: float | None = None,
        segment_lengths=(0.03, 0.05),
        half_angles_deg=(15.0, 30.0),
        cap: bool = True,
        lateral_tolerance: float = LATERAL_TOLERANCE,
        angle_tolerance: float = ANGLE_TOLERANCE,
    ) -> VirtualFixture:
        """The VF of a placement: axis = line1 through the Tool origin, entry where line1
        crosses the model's top slice plane (the mouth opening; 0 if it never does), tool radius
        = the rod radius unless given, the planned orientation = the Tool frame X_CT."""
        X_CT = np.asarray(placement.X_CT, dtype=float)
        origin = X_CT[:3, 3]
        direction = X_CT[:3, 0]  # Tool x is along line1 (Eq. 19)
        z_top = fpsm.z_range[1]
        entry = (z_top - origin[2]) / direction[2] if direction[2] > 1e-12 else 0.0
        r = placement.rod_radius if cylinder_radius is None else cylinder_radius
        return cls(
            origin=origin,
            direction=direction,
            entry_distance=max(float(entry), 0.0),
            cylinder_radius=r,
            segment_lengths=segment_lengths,
            half_angles=np.deg2rad(np.asarray(half_angles_deg, dtype=float)),
            cap=cap,
            lateral_tolerance=lateral_tolerance,
            angle_tolerance=angle_tolerance,
            R_ref=X_CT[:3, :3],
        )

    def profile(self) -> tuple[np.ndarray, np.ndarray]:
        """Profile vertices (s, R(s)) of the axis region from the target out to the end of
        the last cone (R starts at delta)."""
        s = np.concatenate(
            [[0.0, self.entry_distance], self.entry_distance + np.cumsum(self.segment_lengths)]
        )
        widen = np.cumsum(self.segment_lengths * np.tan(self.half_angles))
        r = np.concatenate([[self.lateral_tolerance] * 2, self.lateral_tolerance + widen])
        return s, r

    @property
    def entry_point(self) -> np.ndarray:
        return self.origin + self.entry_distance * self.direction

    def radius_at(self, s) -> np.ndarray:
        """Allowed axis radius R(s) (m); NaN where s < 0 and the cap is set."""
        s = np.asarray(s, dtype=float)
        prof_s, prof_r = self.profile()
        r = np.interp(s, prof_s, prof_r)  # constant beyond both ends
        return np.where((s < 0) & self.cap, np.nan, r)

    # -- point queries (the axis region) ----------------------------------------------------

    def _signed(self, p: np.ndarray):
        """Signed distance (..., ) and outward unit normal (..., 3)."""
        flat = np.ascontiguousarray(p.reshape(-1, 3))
        d = np.empty(flat.shape[0])
        n = np.empty_like(flat)
        _signed_batch(flat, self.origin, self.direction, self._e1, self._s, self._r, self.cap,
                      d, n)
        return d.reshape(p.shape[:-1]), n.reshape(p.shape)

    def distance(self, points) -> np.ndarray:
        """Signed distance (m) of axis points (..., 3) to the axis region's boundary, < 0
        inside."""
        return self._signed(self._points(points))[0]

    def violation(self, points) -> np.ndarray:
        """How far (m) axis points are outside the axis region, >= 0."""
        return np.maximum(self.distance(points), 0.0)

    def normal(self, points) -> np.ndarray:
        """Outward unit normal of the nearest boundary, (..., 3)."""
        return self._signed(self._points(points))[1]

    def force(self, points, velocities, *, stiffness: float, damping: float = 0.0) -> np.ndarray:
        """Restoring force (N) on axis points by the admittance law: -(k * violation + b *
        max(v.n, 0)) n for points outside, zero inside. ``stiffness`` N/m, ``damping`` N s/m."""
        p = self._points(points)
        v = np.asarray(velocities, dtype=float)
        d, n = self._signed(p)
        out = d > 0
        vn = np.maximum(np.sum(v * n, axis=-1), 0.0)
        mag = np.where(out, stiffness * np.maximum(d, 0.0) + damping * vn, 0.0)
        return -mag[..., None] * n

    def correct_velocity(
        self,
        points,
        v_cmd,
        *,
        dt: float | None = None,
        return_gain: float = 10.0,
        tolerance: float = 1e-9,
    ) -> np.ndarray:
        """Filter commanded velocities (m/s) of single axis points so they stay in the region.

        Motion along the boundary (and along the axis) passes. The outward normal component is
        limited to what reaches the boundary in one step ``dt`` (if given), or removed at or over
        the boundary (within ``tolerance``); a point outside also gets a return velocity
        ``-return_gain * violation * n`` (1/s). The tool body uses :meth:`correct_twist`.
        """
        p = self._points(points)
        v = np.array(np.broadcast_to(np.asarray(v_cmd, dtype=float), p.shape))
        d, n = self._signed(p)
        vn = np.sum(v * n, axis=-1)
        if dt is None:
            allowed = np.where(d < -tolerance, np.inf, 0.0)
        else:
            allowed = np.maximum(-d, 0.0) / float(dt)
        excess = np.maximum(vn - allowed, 0.0)
        v = v - excess[..., None] * n
        return v - (return_gain * np.maximum(d, 0.0))[..., None] * n

    # -- the tool body ------------------------------------------------------------------------

    def kernel_args(self) -> tuple:
        """The fixed arguments of the compiled body law (for adapters that call it directly)."""
        return (self.origin, self.direction, self._e1, self._s, self._r, self.cap,
                self._s_lat, self._r_lat, self.entry_distance, self._R_ref, self.R_ref is not None,
                self.angle_tolerance)

    def correct_twist(
        self,
        p_CT,
        R_CT,
        V_C=None,
        *,
        dt: float | None = None,
        return_gain: float = 10.0,
        stiffness: float = 0.0,
        damping: float = 0.0,
        tolerance: float = 1e-9,
    ) -> BodyLaw:
        """The body law (module docstring) for K tool poses, batched.

        Args:
            p_CT: (K, 3) or (3,) TCP positions in Center (m).
            R_CT: (K, 3, 3) or (3, 3) tool axes in Center (x along the rod, out of the mouth).
            V_C: (K, 6) or (6,) commanded [w; v] in Center (rad/s, m/s); zero if None.
            dt: the control period (s): outward motion is limited to reaching the boundary in
                one period; None: removed at or over the boundary (within ``tolerance``).
            return_gain: k / b (1/s), the rate at which a violation is taken back.
            stiffness, damping: k (N/m), b (N s/m) of the reported force.
        """
        p = self._points(p_CT).reshape(-1, 3)
        R = np.asarray(R_CT, dtype=float).reshape(-1, 3, 3)
        V = np.zeros((1, 6)) if V_C is None else np.asarray(V_C, dtype=float).reshape(-1, 6)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(V))):
            raise InputError("R_CT/V_C", "expected finite rotations and velocities")
        K = max(p.shape[0], R.shape[0], V.shape[0])
        try:
            p = np.ascontiguousarray(np.broadcast_to(p, (K, 3)))
            R = np.ascontiguousarray(np.broadcast_to(R, (K, 3, 3)))
            V = np.ascontiguousarray(np.broadcast_to(V, (K, 6)))
        except ValueError:
            raise InputError("p_CT/R_CT/V_C", "expected the same number of poses") from None
        out = np.empty((p.shape[0], 12))
        _body_batch(p, R, V, *self.kernel_args(), -1.0 if dt is None else float(dt),
                    float(return_gain), float(stiffness), float(damping), float(tolerance), out)
        return BodyLaw(V=out[:, :6], violation=out[:, 6], angle_violation=out[:, 7],
                       angle=out[:, 11], force=out[:, 8:11])

    def body_violation(self, X_CT) -> tuple[np.ndarray, np.ndarray]:
        """(position violation (m), angle violation (rad)) of K tool poses (K, 4, 4) in Center:
        the offline check of a logged run at every pose."""
        X = np.asarray(X_CT, dtype=float).reshape(-1, 4, 4)
        law = self.correct_twist(X[:, :3, 3], X[:, :3, :3])
        return law.violation, law.angle_violation

    @staticmethod
    def _points(points) -> np.ndarray:
        p = np.asarray(points, dtype=float)
        if p.shape[-1:] != (3,) or not np.all(np.isfinite(p)):
            raise InputError("points", "expected finite points of shape (..., 3) in m")
        return p

    # -- files --------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "frame": "Center",
            "origin": self.origin.tolist(),
            "direction": self.direction.tolist(),
            "entry_distance": self.entry_distance,
            "entry_point": self.entry_point.tolist(),
            "cylinder_radius": self.cylinder_radius,
            "segment_lengths": self.segment_lengths.tolist(),
            "half_angles": self.half_angles.tolist(),
            "cap": self.cap,
            "bounds": "tool axis",
            "lateral_tolerance": self.lateral_tolerance,
            "angle_tolerance": self.angle_tolerance,
            "R_ref": None if self.R_ref is None else self.R_ref.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict) -> VirtualFixture:
        """Read :meth:`to_dict`; files written before the body fixture (no
        ``lateral_tolerance``) get the defaults delta = 0.5 mm, beta = 0.5 deg, no R_ref."""
        if not isinstance(data, dict):
            raise InputError("vf", "expected a mapping")
        keys = (
            "origin",
            "direction",
            "entry_distance",
            "cylinder_radius",
            "segment_lengths",
            "half_angles",
        )
        missing = [k for k in keys if k not in data]
        if missing:
            raise InputError("vf", f"missing {', '.join(missing)}")
        return cls(
            **{k: data[k] for k in keys},
            cap=data.get("cap", True),
            lateral_tolerance=data.get("lateral_tolerance", LATERAL_TOLERANCE),
            angle_tolerance=data.get("angle_tolerance", ANGLE_TOLERANCE),
            R_ref=data.get("R_ref"),
        )
