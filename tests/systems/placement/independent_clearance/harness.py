"""Models, adversarial rod families and the comparison against the verifier's ground truth."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from groundtruth import FreeRegion, spline, verdict  # noqa: E402

from implantplan.systems.fpsm.model import Fpsm  # noqa: E402  (data container only)
from implantplan.systems.placement.tool_clearance import rod_clearance  # noqa: E402  (under test)

MM = 1e-3
HERE = Path(__file__).resolve().parent
# set VERIFY12_CACHE=/path/fpsm.json to reuse a fitted default model between script runs
CACHE = Path(os.environ["VERIFY12_CACHE"]) if os.environ.get("VERIFY12_CACHE") else None


# -- models ------------------------------------------------------------------------------------


def default_fpsm() -> Fpsm:
    if CACHE is not None and CACHE.exists():
        return Fpsm.load(CACHE)
    from implantplan.analyses.case import default_case_path, load_case
    from implantplan.analyses.pipeline import fit_stage

    f = fit_stage(load_case(default_case_path())).fpsm
    if CACHE is not None:
        f.save(CACHE)
    return f


def cylinder_fpsm() -> Fpsm:
    return Fpsm.cylinder(0.05, 0.0, 0.1, 11)


def nonconvex_fpsm(seed=3) -> Fpsm:
    """Wild control radii, independent between neighbouring slices (spline kept > 2 mm)."""
    rng = np.random.default_rng(seed)
    z = np.array([0.0, 0.004, 0.009, 0.012, 0.02, 0.028, 0.0305, 0.04])
    while True:
        rho = rng.uniform(6 * MM, 40 * MM, (z.size, 12))
        th = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
        if spline(rho, th).min() > 2 * MM:
            return Fpsm(z, rho)


def slit_fpsm() -> Fpsm:
    """Slit-shaped (ellipse 40 x 4 mm) sections near the top, round below, rotating slits."""
    th = np.arange(16) * 2 * np.pi / 16
    rows = []
    z = np.linspace(0, 0.05, 6)
    for _j, (a, b, rot) in enumerate([(25, 25, 0), (30, 15, 0), (35, 8, 0.3), (40, 5, 0.0),
                                     (40, 4, 0.4), (38, 4, 1.2)]):
        a, b = a * MM, b * MM
        t = th - rot
        rows.append(a * b / np.sqrt((b * np.cos(t)) ** 2 + (a * np.sin(t)) ** 2))
    rho = np.array(rows)
    return Fpsm(z, rho)


MODELS = {"default": default_fpsm, "cylinder": cylinder_fpsm, "nonconvex": nonconvex_fpsm,
          "slit": slit_fpsm}


def region(f: Fpsm, angles=2048, zsteps=8) -> FreeRegion:
    return FreeRegion(np.array(f.slice_z), np.array(f.rho)).build_mesh(angles, zsteps)


# -- rod families ------------------------------------------------------------------------------


def _dirs(rng, n, max_tilt_deg, min_tilt_deg=0.0):
    cz = rng.uniform(np.cos(np.radians(max_tilt_deg)), np.cos(np.radians(min_tilt_deg)), n)
    ph = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - cz ** 2)
    return np.column_stack([s * np.cos(ph), s * np.sin(ph), cz])


def _radii(rng, n, lo=0.1, hi=8.0):
    return np.exp(rng.uniform(np.log(lo), np.log(hi), n)) * MM


def _near_wall(G: FreeRegion, rng, n, z_lo=None, z_hi=None, frac=(0.90, 0.999)):
    z_lo = G.z0 if z_lo is None else z_lo
    z_hi = G.ztop if z_hi is None else z_hi
    th = rng.uniform(0, 2 * np.pi, n)
    z = rng.uniform(z_lo, z_hi, n)
    rr = G.radius(th, np.clip(z, G.z0, G.ztop)) * rng.uniform(*frac, n)
    return np.column_stack([rr * np.cos(th), rr * np.sin(th), z])


def families(f: Fpsm, G: FreeRegion, n: int, seed=0) -> dict:
    """name -> (p0, p1, r) arrays, n rods each (some families are fixed-size)."""
    rng = np.random.default_rng(seed)
    z0, zt = G.z0, G.ztop
    out = {}
    # 1. near-wall starts, any upward-ish direction up to 80 deg, lengths 1-100 mm
    p0 = _near_wall(G, rng, n)
    u = _dirs(rng, n, 80)
    L = rng.uniform(1, 100, n)[:, None] * MM
    out["near_wall"] = (p0, p0 + L * u, _radii(rng, n))
    # 2. near wall, direction anywhere on the sphere (down, sideways), short 0.5-20 mm
    p0 = _near_wall(G, rng, n)
    u = _dirs(rng, n, 180)
    L = rng.uniform(0.5, 20, n)[:, None] * MM
    out["near_wall_any_dir"] = (p0, p0 + L * u, _radii(rng, n, 0.1, 3))
    # 3. top slabs (slit-shaped sections in 'slit'), tilted, exiting the opening or not
    ztop2 = G.z[-3] if G.M >= 3 else z0
    p0 = _near_wall(G, rng, n, ztop2, zt, (0.5, 0.999))
    u = _dirs(rng, n, 80)
    L = rng.uniform(2, 80, n)[:, None] * MM
    out["top_slabs"] = (p0, p0 + L * u, _radii(rng, n))
    # 4. steep tilts 60-80 deg crossing several slab boundaries
    p0 = _near_wall(G, rng, n, frac=(0.0, 0.95))
    u = _dirs(rng, n, 80, 60)
    L = rng.uniform(5, 60, n)[:, None] * MM
    out["steep_tilt"] = (p0, p0 + L * u, _radii(rng, n))
    # 5. very short segments (1 um - 1 mm) and points, near the wall
    p0 = _near_wall(G, rng, n, frac=(0.8, 0.999))
    u = _dirs(rng, n, 180)
    L = np.where(rng.random(n) < 0.2, 0.0, np.exp(rng.uniform(np.log(1e-6), np.log(1e-3), n)))
    out["short"] = (p0, p0 + L[:, None] * u, _radii(rng, n))
    # 6. lying exactly in a slice plane (horizontal), start near wall
    j = rng.integers(0, G.M, n)
    th = rng.uniform(0, 2 * np.pi, n)
    zz = G.z[j]
    rr = G.radius(th, zz) * rng.uniform(0.3, 0.99, n)
    p0 = np.column_stack([rr * np.cos(th), rr * np.sin(th), zz])
    ph = rng.uniform(0, 2 * np.pi, n)
    L = rng.uniform(0.5, 30, n) * MM
    p1 = p0 + L[:, None] * np.column_stack([np.cos(ph), np.sin(ph), np.zeros(n)])
    out["in_slice_plane"] = (p0, p1, _radii(rng, n, 0.1, 4))
    # 7. exit through the opening: long rods from the top region to far above, near the rim
    p0 = _near_wall(G, rng, n, zt - 0.01, zt + 0.01, (0.6, 1.05))
    p0[:, 2] = np.where(p0[:, 2] > zt, p0[:, 2], p0[:, 2])
    u = _dirs(rng, n, 85)
    out["through_opening"] = (p0, p0 + 0.2 * u, _radii(rng, n))
    # 8. entering below the lowest slice (throat)
    p0 = _near_wall(G, rng, n, z0, z0 + 0.004, (0.0, 0.9))
    u = _dirs(rng, n, 180, 95)  # pointing downward
    L = rng.uniform(0.1, 10, n)[:, None] * MM
    out["throat"] = (p0, p0 + L * u, _radii(rng, n, 0.1, 2))
    # 9. rods starting above the opening and going down into the mouth close to the rim
    th = rng.uniform(0, 2 * np.pi, n)
    rr = G.radius(th, np.full(n, zt)) * rng.uniform(0.7, 1.3, n)
    p0 = np.column_stack([rr * np.cos(th), rr * np.sin(th), zt + rng.uniform(0, 0.01, n)])
    u = -_dirs(rng, n, 60)
    L = rng.uniform(1, 30, n)[:, None] * MM
    out["down_from_above"] = (p0, p0 + L * u, _radii(rng, n))
    return out


# -- comparison --------------------------------------------------------------------------------


def evaluate(f: Fpsm, G: FreeRegion, p0, p1, r, *, truth_all=True):
    """Per-rod sound value, paper value and the ground-truth verdict."""
    sound = rod_clearance(f, p0, p1, r)
    paper = rod_clearance(f, p0, p1, r, method="paper")
    n = len(r)
    kind = np.empty(n, dtype=object)
    est = np.full(n, np.nan)
    upper = np.full(n, np.nan)
    for k in range(n):
        if not truth_all and sound[k] <= 0:
            kind[k] = "skipped"
            continue
        q = G.query(p0[k], p1[k])
        kind[k], est[k] = verdict(q, r[k], G.eps)
        upper[k] = (q["upper"] - r[k]) if not q["axis_out"] else -r[k]
    return {"sound": sound, "paper": paper, "kind": kind, "est": est, "upper": upper}


def summarize(res, eps):
    sound, kind = res["sound"], res["kind"]
    safe = sound > 0
    fs = safe & (kind == "collide")
    free = kind == "free"
    # bound violated: sound larger than the rigorous upper bound of the true clearance
    viol = res["sound"] - res["upper"]
    bad_bound = safe & np.isfinite(viol) & (viol > eps + 1e-9)
    out = {
        "n": int(len(sound)),
        "called_safe": int(safe.sum()),
        "exactly_free": int(free.sum()),
        "collide": int((kind == "collide").sum()),
        "ambiguous": int((kind == "ambiguous").sum()),
        "false_safe": int(fs.sum()),
        "bound_violations": int(bad_bound.sum()),
        "worst_violation_mm": float(np.nanmax(np.where(safe, viol, np.nan)) / MM)
        if safe.any() else None,
        "free_called_unsafe": float(np.mean(~safe[free])) if free.any() else None,
        "paper_false_safe": int(((res["paper"] > 0) & (kind == "collide")).sum()),
    }
    return out


def ratchet(f: Fpsm, G: FreeRegion, p0, p1, iters=22):
    """Radius ratchet: for each axis, the largest r (bisection) the sound method still calls
    safe, against the rigorous upper bound of the axis's true distance to dF.  Returns
    (r_star, axis_upper, axis_out); a false-safe is r_star > axis_upper (or axis_out with a
    safe r_star > 0, or a safe r = 0 on an axis that leaves F)."""
    n = len(p0)
    s0 = rod_clearance(f, p0, p1, np.zeros(n))
    lo = np.zeros(n)
    hi = np.full(n, 0.06)
    ok = s0 > 0
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        s = rod_clearance(f, p0, p1, mid)
        good = s > 0
        lo = np.where(good, mid, lo)
        hi = np.where(good, hi, mid)
    r_star = np.where(ok, lo, -1.0)
    up = np.full(n, np.nan)
    out = np.zeros(n, bool)
    for k in np.flatnonzero(ok):
        q = G.query(p0[k], p1[k])
        up[k] = q["upper"]
        out[k] = q["axis_out"]
    return r_star, up, out, s0
