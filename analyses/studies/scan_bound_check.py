"""An independent check of the scan bound (:class:`systems.placement.scan_clearance.
ScanClearance`) against its exact reference, FCL against the same opened scan
(:meth:`systems.placement.exact_clearance.ExactCavity.tool_clearance`), on the bundled default
case, transformed copies of its cavity and both instruments.

Run: ``python -m implantplan.analyses.studies.scan_bound_check [--poses 10000] [--seed 0]
[--cavities default,mirror,scale0.9,scale1.1,rigid] [--plan DIR] [--out DIR]``; ``cohort-00``,
``cohort-01`` are other subjects (cases of the default case's synthetic cohort,
:func:`cohort_cavity`).

**Cavities.** ``default``: the default case's opened scan as the plan takes it (Center frame,
open cuts closed, cut at the mouth opening: :meth:`ExactCavity.from_scan`). Its copies, each a
new mesh with its own FCL model and its own distance grid (so the walls sit elsewhere between
the grid's nodes): ``mirror`` (reflected in Center's x = 0 plane, the mid-sagittal plane: Center
y is cranial, z out of the mouth; triangles re-wound so the normals stay outward), ``scale0.9``
and ``scale1.1`` (about the Center origin; the instrument is not scaled), ``rigid`` (rotated 4
deg about a fixed oblique axis through the Center origin and moved by (2, -3, 1.5) mm). Every
planned feeding target X_CT moves with its cavity (X' = A X F: A the similarity's rotation and
the moved point; F flips Tool y for the mirror, which keeps the frame right-handed and the
instrument, symmetric about its Tool x-z plane, the mirror image of itself), and the poses are
sampled afresh about the moved feed.

**Poses** per cavity and instrument (``--poses`` of them, :data:`ADVERSARIAL_SHARE` adversarial):

- ``random``: :func:`analyses.studies.instrument_check.sampled_poses` about each site's feed
  (backed out over the whole feed, up to 8 mm lateral, 12 deg tilt);
- ``margin_above`` / ``margin_below``: a random pose moved across the rod axis (a random
  direction in Tool y-z) until FCL's clearance crosses the margin (sphere tracing with the
  1-Lipschitz clearance, then bisection), the two ends of a bracket narrower than
  :data:`BAND` and both kept only where FCL puts them within :data:`BAND` of the margin;
- ``grazing_free`` / ``grazing_touch``: the same to clearance 0 (just free: 0 < FCL <=
  :data:`BAND`; just touching: FCL <= 0);
- ``midcell_axis`` / ``midcell_surface``: a margin or grazing pose translated (by at most half a
  cell diagonal) so that the point of the instrument nearest the scan (of its axis for a
  capsule or sphere, the bound's evaluation point; of its surface, or its axis, for a cylinder)
  sits at the centre of a cell of the grid level that holds exact values at that distance
  (0.5 mm cells nearer than 2.5 mm, 1 mm nearer than 8 mm, else 2 mm: distance_grid.py), where
  the grid's bound loses most;
- ``start_outside`` / ``start_inside``: a random pose moved horizontally (radially from the
  Center axis) until one solid's start point, as the reference tests it (the horizontal segment
  from the Center axis to it crosses the mesh), passes into tissue, bisected to 20 um: the last
  pose with the start in the cavity and the first with it in tissue.

**Measured** per cavity x instrument at the case's margin c: ``false_safe_verdict`` (fast_verdict
SAFE where FCL < c: must be 0), ``false_safe_value`` (lower bound > FCL + 1 um where FCL > 0, the
place FCL's value is a distance) and ``excess_anywhere`` (the same at every pose: the bound
claims to be below the reference's -r floor too), the largest excess, ``undecided``,
``false_unsafe`` (UNSAFE where FCL >= c: a wrong upper estimate, not a safety defect but a
defect), ``called_safe_share`` (of the poses FCL puts >= c + 0.2 mm clear, the share fast_verdict
calls SAFE; target >= 0.9), the median gap FCL - bound where 0 < FCL <= 5 mm (the bound resolves
values up to :data:`systems.placement.scan_clearance.VALUE_CAP`), ``fcl_below_its_floor`` (poses
where FCL's value is below -r, impossible by its definition: FCL's distance query returns -1
for a grazing cylinder its collide query calls free; left out of the excess), and the time per
pose of fast_verdict, of the bound's value and of FCL, side by side in one run, numba on one
thread (FCL runs on one). The false-safe counts are also given per pose kind.

Writes ``scan_bound_check.json`` to ``--out`` (a new folder) when given.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import igl
import numpy as np
import trimesh

from implantplan.analyses.progress import Progress
from implantplan.analyses.studies.instrument_check import sampled_poses
from implantplan.systems import seeds
from implantplan.systems.errors import InputError
from implantplan.systems.files import write_json
from implantplan.systems.frames import rotations
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.exact_clearance import ExactCavity
from implantplan.systems.placement.scan_clearance import (
    RELATIVE,
    RESOLUTION,
    SAFE,
    UNDECIDED,
    UNSAFE,
    ScanClearance,
)

MAX_POSES = 1_000_000  # per cavity x instrument
CAVITIES = ("default", "mirror", "scale0.9", "scale1.1", "rigid")
SUBJECTS = ("cohort-00", "cohort-01")  # other subjects: :func:`cohort_cavity`
INSTRUMENTS = ("paper", "actuator")
ADVERSARIAL_SHARE = 0.4
BAND = 0.05e-3  # m: the margin and grazing poses are within this of their level
FREE_BY = 0.2e-3  # m: "exactly free" is FCL >= margin + this
VALUE_TOL = 1e-6  # m: a lower bound above FCL by more than this is a false value
GAP_CAP = 5e-3  # m: the median gap is taken where 0 < FCL <= this (the bound's resolved range)
HANG_SLACK = 1e-3  # m: see :func:`nonterminating`
START_STEP = 20e-6  # m: the start poses' bracket
RIGID_AXIS = np.array([0.3, -0.5, 0.81])
RIGID_ANGLE = np.radians(4.0)
RIGID_SHIFT = np.array([2.0e-3, -3.0e-3, 1.5e-3])
# grid levels (distance_grid.py): the spacing whose nodes are exact nearer than the distance
LEVELS = ((2.5e-3, 1), (8e-3, 2), (np.inf, 4))


@dataclass
class Cavity:
    """One cavity of the check: its FCL model (Center frame) and its feeds (site, X_CT, depth
    per instrument name)."""

    name: str
    exact: ExactCavity
    feeds: list = field(default_factory=list)
    transform: np.ndarray | None = None  # A (4, 4) from the default cavity, None for it


# -- cavities ----------------------------------------------------------------------------------


def similarity(name: str) -> np.ndarray:
    """A (4, 4) of a copy (module notes)."""
    A = np.eye(4)
    if name == "mirror":
        A[0, 0] = -1.0
    elif name.startswith("scale"):
        A[:3, :3] *= float(name[5:])
    elif name == "rigid":
        A[:3, :3] = rotations((RIGID_ANGLE * RIGID_AXIS / np.linalg.norm(RIGID_AXIS))[None])[0]
        A[:3, 3] = RIGID_SHIFT
    else:
        raise InputError("cavity", f"unknown cavity {name!r}; expected one of {CAVITIES}")
    return A


def transform_mesh(mesh: trimesh.Trimesh, A: np.ndarray) -> trimesh.Trimesh:
    """``mesh`` moved by the similarity A, its triangles wound as before (a reflection reverses
    the winding: the faces are flipped back where their normals came out reversed)."""
    out = trimesh.Trimesh(np.asarray(mesh.vertices) @ A[:3, :3].T + A[:3, 3],
                          np.asarray(mesh.faces).copy(), process=False)
    Q = A[:3, :3] / np.cbrt(abs(np.linalg.det(A[:3, :3])))
    expected = np.asarray(mesh.face_normals) @ Q.T
    if np.mean(np.sum(np.asarray(out.face_normals) * expected, axis=1)) < 0:
        out = trimesh.Trimesh(out.vertices, out.faces[:, ::-1].copy(), process=False)
    return out


def transform_poses(X: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Tool poses (n, 4, 4) moved with the cavity: positions by A, orientations by A's rotation
    (its scale removed), Tool y flipped where A reflects (module notes)."""
    X = np.asarray(X, dtype=float).reshape(-1, 4, 4)
    L = A[:3, :3]
    Q = L / np.cbrt(abs(np.linalg.det(L)))
    F = np.diag([1.0, -1.0, 1.0]) if np.linalg.det(L) < 0 else np.eye(3)
    out = X.copy()
    out[:, :3, :3] = Q @ X[:, :3, :3] @ F
    out[:, :3, 3] = X[:, :3, 3] @ L.T + A[:3, 3]
    return out


def planned_cavity(case_path, name: str, progress: Progress) -> tuple[Cavity, float]:
    """A case's cavity and its feeds as ``implantplan plan`` places them (a site without a
    valid placement keeps its best feed), and the case's margin (m)."""
    from implantplan.analyses import pipeline
    from implantplan.analyses.case import load_case

    case = load_case(case_path)
    progress.say(f"{name}: fit and placement")
    fit = pipeline.fit_stage(case)
    placements = pipeline.placement_stage(case, fit, require_valid=False)
    return _cavity(name, case, fit, [(site.name, p.X_CT)
                                     for site, p in zip(case.sites, placements, strict=True)])


def _cavity(name: str, case, fit, targets) -> tuple[Cavity, float]:
    """The cavity of a fitted case with its feeds at the feeding targets ``targets`` ((site
    name, X_CT) per site), against the exact reference the placement verified against; the
    case's margin (m)."""
    from implantplan.systems.placement.tool_clearance import feed_depth

    feeds = []
    for site_name, X_CT in targets:
        X_CT = np.asarray(X_CT, dtype=float)
        depth = {n: float(feed_depth(fit.fpsm, X_CT, instrument(n))) for n in INSTRUMENTS}
        feeds.append((site_name, X_CT, depth))
    return (Cavity(name, fit.exact(case.mesh.close_open_cuts), feeds),
            float(case.safety.clearance_margin))


def default_cavity(progress: Progress, plan=None) -> tuple[Cavity, float]:
    """The bundled default case's cavity, feeds and margin (:func:`planned_cavity`); with
    ``plan``, a plan folder (``implantplan plan`` or ``demo``): its case's cavity and the feeds
    as that plan placed them (the fit again, the placements read, not searched again)."""
    from implantplan.analyses.case import default_case_path

    if plan is None:
        return planned_cavity(default_case_path(), "default", progress)
    from implantplan.analyses import pipeline
    from implantplan.analyses.case import load_case
    from implantplan.systems.files import read_json

    folder = Path(plan)
    data = read_json(folder / "plan.json", kind="plan", field="--plan")
    source = Path(data["case"]["source"])
    if not source.is_file():
        raise InputError("--plan", f"{folder}: the case file the plan names ({source}) is not "
                         "there")
    case = load_case(source)
    progress.say(f"default: fit of {source.name}, the placements of {folder}")
    return _cavity("default", case, pipeline.fit_stage(case),
                   [(s["name"], s["feeding_target"]["X_CT"]) for s in data["sites"]])


def cohort_cavity(name: str, progress: Progress) -> tuple[Cavity, float]:
    """``cohort-NN``: case NN of the synthetic cohort of the default case
    (:func:`analyses.cohort.make_cohort`, seed 0: the scan under a seeded similarity, the sites
    jittered, fitted and placed afresh), another subject in the project's sense."""
    import tempfile

    from implantplan.analyses.case import default_case_path
    from implantplan.analyses.cohort import load_cohort, make_cohort

    i = int(name.split("-")[1])
    with tempfile.TemporaryDirectory() as tmp:
        _, files = load_cohort(make_cohort(default_case_path(), Path(tmp), i + 1, seed=0))
        return planned_cavity(files[i], name, progress)


def copy_cavity(base: Cavity, name: str) -> Cavity:
    """A transformed copy of ``base`` (module notes): new mesh, new FCL model, moved feeds."""
    A = similarity(name)
    mesh = transform_mesh(base.exact.mesh, A)
    s = float(np.cbrt(abs(np.linalg.det(A[:3, :3]))))
    feeds = [(site, transform_poses(X, A)[0], {k: s * d for k, d in depth.items()})
             for site, X, depth in base.feeds]
    return Cavity(name, ExactCavity(mesh), feeds, A)


def instrument(name: str) -> Instrument:
    if name == "paper":
        return Instrument.paper()
    if name == "actuator":
        return Instrument.actuator()
    raise InputError("instrument", f"unknown instrument {name!r}; expected one of {INSTRUMENTS}")


# -- adversarial poses -------------------------------------------------------------------------


def _lateral(X: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) unit directions across each pose's rod axis (Tool y-z plane)."""
    phi = rng.uniform(0, 2 * np.pi, len(X))
    return np.cos(phi)[:, None] * X[:, :3, 1] + np.sin(phi)[:, None] * X[:, :3, 2]


def _moved(X: np.ndarray, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
    out = X.copy()
    out[:, :3, 3] += lam[:, None] * u
    return out


def level_poses(exact: ExactCavity, inst: Instrument, X0: np.ndarray, level: float,
                rng: np.random.Generator, *, reach: float = 0.02, iterations: int = 14):
    """Brackets of FCL's clearance about ``level`` along a random lateral move of each pose:
    (X_above (m, 4, 4), X_below (m, 4, 4), c_above, c_below) where c_above >= level > c_below
    and the bracket is narrower than :data:`BAND` (poses whose start is above the level and
    whose move reaches below it within ``reach``)."""
    u = _lateral(X0, rng)
    c = exact.tool_clearance(X0, inst)
    keep = c >= level
    X0, u, c = X0[keep], u[keep], c[keep]
    lo = np.zeros(len(X0))  # clearance >= level here
    c_lo = c.copy()
    hi = np.full(len(X0), np.nan)
    # sphere tracing: the clearance (while free) is 1-Lipschitz in the translation
    for _ in range(iterations):
        open_ = np.isnan(hi) & (lo < reach)
        if not open_.any():
            break
        step = np.maximum(c_lo[open_] - level, 0.5 * BAND) + 0.25e-3
        lam = lo[open_] + step
        cc = exact.tool_clearance(_moved(X0[open_], u[open_], lam), inst)
        idx = np.flatnonzero(open_)
        below = cc < level
        hi[idx[below]] = lam[below]
        lo[idx[~below]] = lam[~below]
        c_lo[idx[~below]] = cc[~below]
    ok = ~np.isnan(hi)
    X0, u, lo, hi, c_lo = X0[ok], u[ok], lo[ok], hi[ok], c_lo[ok]
    c_hi = np.full(len(X0), -np.inf)
    while len(X0) and np.any(hi - lo > BAND):
        w = hi - lo > BAND
        mid = 0.5 * (lo[w] + hi[w])
        cc = exact.tool_clearance(_moved(X0[w], u[w], mid), inst)
        idx = np.flatnonzero(w)
        up = cc >= level
        lo[idx[up]], c_lo[idx[up]] = mid[up], cc[up]
        hi[idx[~up]] = mid[~up]
    if len(X0):
        c_hi = exact.tool_clearance(_moved(X0, u, hi), inst)
    return _moved(X0, u, lo), _moved(X0, u, hi), c_lo, c_hi


def _nearest_points(exact: ExactCavity, inst: Instrument, X: np.ndarray):
    """Per pose, the sampled point of the instrument nearest the mesh and its distance: of
    the axis (capsule, sphere) and of the surface (cylinders; their axis as well)."""
    V = np.ascontiguousarray(exact.mesh.vertices, dtype=float)
    F = np.ascontiguousarray(exact.mesh.faces, dtype=np.int64)
    axis_pts, surf_pts, axis_r = [], [], []
    t = np.linspace(0.0, 1.0, 21)
    for s in inst.shapes:
        P = s.a + t[:, None] * (s.b - s.a)
        axis_pts.append(P)
        axis_r.append(np.full(len(P), s.radius))
        if s.kind == "cylinder":
            n = (s.b - s.a) / s.length
            e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(n, e1)
            phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)
            ring = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
            side = (P[::2, None, :] + s.radius * ring[None]).reshape(-1, 3)
            caps = [(e + rho * s.radius * ring) for e in (s.a, s.b) for rho in (0.5,)]
            surf_pts.append(np.vstack([side, *caps]))
    A_T, r_T = np.vstack(axis_pts), np.concatenate(axis_r)
    S_T = np.vstack(surf_pts) if surf_pts else np.zeros((0, 3))
    out = []
    for P_T, rad in ((A_T, r_T), (S_T, np.zeros(len(S_T)))):
        if len(P_T) == 0:
            out.append(None)
            continue
        W = np.einsum("kij,pj->kpi", X[:, :3, :3], P_T) + X[:, None, :3, 3]
        d = np.sqrt(np.maximum(igl.point_mesh_squared_distance(
            np.ascontiguousarray(W.reshape(-1, 3)), V, F)[0], 0.0)).reshape(len(X), -1)
        k = np.argmin(d - rad[None], axis=1)
        out.append((W[np.arange(len(X)), k], d[np.arange(len(X)), k]))
    return out


def midcell_poses(scan: ScanClearance, exact: ExactCavity, inst: Instrument, X: np.ndarray):
    """(poses, kinds): each pose translated so that its nearest axis point (and, for an
    instrument with a cylinder, its nearest surface point) lies at a cell centre of the grid
    level exact at that distance (module notes)."""
    g, origin = scan.grid.spacing, scan.grid.origin
    poses, kinds = [], []
    for kind, found in zip(("midcell_axis", "midcell_surface"), _nearest_points(exact, inst, X),
                           strict=True):
        if found is None:
            continue
        p, d = found
        step = np.select([d < lim for lim, _ in LEVELS], [m * g for _, m in LEVELS])[:, None]
        centre = origin + step * (np.floor((p - origin) / step) + 0.5)
        Y = X.copy()
        Y[:, :3, 3] += centre - p
        poses.append(Y)
        kinds += [kind] * len(Y)
    return (np.concatenate(poses) if poses else np.zeros((0, 4, 4))), kinds


def start_poses(exact: ExactCavity, inst: Instrument, X0: np.ndarray,
                rng: np.random.Generator, *, reach: float = 0.03):
    """(outside, inside): each pose moved horizontally, radially from the Center axis at one
    random solid's start, to the last pose with that start in the cavity and the first with it
    in tissue (bracket :data:`START_STEP`); poses whose start is in the cavity and reaches
    tissue within ``reach``."""
    s = rng.integers(0, len(inst.shapes), len(X0))
    A_T = np.array([sh.a for sh in inst.shapes])[s]
    a = np.einsum("kij,kj->ki", X0[:, :3, :3], A_T) + X0[:, :3, 3]
    u = np.column_stack([a[:, :2], np.zeros(len(a))])
    r = np.linalg.norm(u, axis=1)
    ok = r > 1e-6
    ok &= ~exact.start_in_tissue(a)
    X0, a, u = X0[ok], a[ok], u[ok] / r[ok][:, None]

    lo = np.zeros(len(X0))
    hi = np.full(len(X0), np.nan)
    for lam in np.arange(1e-3, reach + 1e-9, 1e-3):
        open_ = np.isnan(hi)
        if not open_.any():
            break
        t = exact.start_in_tissue(a[open_] + lam * u[open_])
        idx = np.flatnonzero(open_)
        hi[idx[t]] = lam
        lo[idx[~t]] = lam
    ok = ~np.isnan(hi)
    X0, u, lo, hi, a = X0[ok], u[ok], lo[ok], hi[ok], a[ok]
    while len(X0) and np.any(hi - lo > START_STEP):
        w = hi - lo > START_STEP
        mid = 0.5 * (lo[w] + hi[w])
        t = exact.start_in_tissue(a[w] + mid[:, None] * u[w])
        idx = np.flatnonzero(w)
        hi[idx[t]] = mid[t]
        lo[idx[~t]] = mid[~t]
    return _moved(X0, u, lo), _moved(X0, u, hi)


def pose_set(cavity: Cavity, scan: ScanClearance, inst_name: str, n: int, margin: float,
             rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(poses (m, 4, 4), kinds (m,) str) of one cavity x instrument: ``n`` random poses spread
    over the feeds, less the adversarial share, and the adversarial ones (module notes)."""
    inst = scan.instrument
    n_adv = int(round(ADVERSARIAL_SHARE * n))
    n_rand = n - n_adv

    def about_feeds(m):
        per = np.full(len(cavity.feeds), m // len(cavity.feeds))
        per[: m % len(cavity.feeds)] += 1
        return np.concatenate([sampled_poses(X, depth[inst_name], int(k), rng)
                               for (_, X, depth), k in zip(cavity.feeds, per, strict=True)])

    poses, kinds = [about_feeds(n_rand)], ["random"] * n_rand
    have = 0
    # each base yields up to 2 (bracket ends) + midcell variants; overdraw, trim at the end
    tries = 0
    while have < n_adv and tries < 6:
        tries += 1
        need = n_adv - have
        m = max(need // 6, 4)
        adv, akind = [], []
        for level, names in ((margin, ("margin_above", "margin_below")),
                             (0.0, ("grazing_free", "grazing_touch"))):
            Xa, Xb, ca, cb = level_poses(cavity.exact, inst, about_feeds(m), level, rng)
            if level > 0:  # both ends within BAND of the margin
                keep = (np.abs(ca - level) <= BAND) & (np.abs(cb - level) <= BAND)
            else:  # just free and just touching
                keep = (ca > 0) & (ca <= BAND) & (cb <= 0)
            for Y, name in ((Xa[keep], names[0]), (Xb[keep], names[1])):
                adv.append(Y)
                akind += [name] * len(Y)
                if len(Y):
                    Z, zk = midcell_poses(scan, cavity.exact, inst, Y)
                    adv.append(Z)
                    akind += zk
        out_, in_ = start_poses(cavity.exact, inst, about_feeds(m), rng)
        adv += [out_, in_]
        akind += ["start_outside"] * len(out_) + ["start_inside"] * len(in_)
        A = np.concatenate(adv)
        take = rng.permutation(len(A))[:need]
        poses.append(A[take])
        kinds += [akind[i] for i in take]
        have += len(take)
    return np.concatenate(poses), np.array(kinds)


# -- the measurement ---------------------------------------------------------------------------


def nonterminating(exact: ExactCavity, inst: Instrument, X: np.ndarray) -> np.ndarray:
    """(n,) True where the bound may not return (the defect this check found; the reproducer
    is tests/analyses/test_scan_bound_check.py): a capsule or sphere splits its pieces while
    h > res + RELATIVE * lb, never true once lb = D(q) - h - r < -res / RELATIVE, so a solid of
    radius r > res / RELATIVE whose axis comes nearer than r - res / RELATIVE to the wall (and
    whose upper estimate does not prove the touch first) never returns. Flagged, by FCL's
    exact axis distance d: d < r - res / RELATIVE + :data:`HANG_SLACK` (the grid's loss there
    is about 0.1 mm); such a pose is at least 1 mm deep in tissue by FCL."""
    X = np.asarray(X, dtype=float).reshape(-1, 4, 4)
    out = np.zeros(len(X), dtype=bool)
    floor = RESOLUTION / RELATIVE
    for s in inst.shapes:
        if s.kind == "cylinder" or s.radius <= floor:
            continue  # a cylinder's lb >= -rad: its pieces always reach the resolution
        A = np.einsum("kij,j->ki", X[:, :3, :3], s.a) + X[:, :3, 3]
        B = np.einsum("kij,j->ki", X[:, :3, :3], s.b) + X[:, :3, 3]
        d = exact.capsule_clearance(A, B, 0.0, check_start=False)
        out |= d < s.radius - floor + HANG_SLACK
    return out



def measure(scan, exact: ExactCavity, inst: Instrument, X: np.ndarray, kinds: np.ndarray,
            margin: float) -> dict:
    """The check (module notes) of ``scan`` (anything with ``fast_verdict(X, c)`` and
    ``bounds(X)`` as :class:`ScanClearance` has them) against FCL at poses X (n, 4, 4)."""
    hang = nonterminating(exact, inst, X)
    X_all, kinds_all = X, kinds
    X, kinds = X[~hang], kinds[~hang]
    scan.fast_verdict(X[:1], margin)  # loaded before it is timed
    t0 = time.perf_counter()
    verdict = np.asarray(scan.fast_verdict(X, margin))
    t_verdict = time.perf_counter() - t0
    t0 = time.perf_counter()
    lower = np.asarray(scan.bounds(X)[0])
    t_value = time.perf_counter() - t0
    t0 = time.perf_counter()
    truth = exact.tool_clearance(X, inst)
    t_fcl = time.perf_counter() - t0
    false_verdict = (verdict == SAFE) & (truth < margin)
    # FCL's distance query answers -1 (its "in collision") for a few grazing cylinders its
    # collide query calls free: below the reference's own floor -r, not a value to compare
    sentinel = truth < -max(s.radius for s in inst.shapes) - VALUE_TOL
    excess = np.where(sentinel, -np.inf, lower - truth)
    false_value = (truth > 0) & (excess > VALUE_TOL)
    free = truth >= margin + FREE_BY
    gap_at = (truth > 0) & (truth <= GAP_CAP)
    n = len(X)
    worst = None
    bad = np.flatnonzero(false_verdict | (excess > VALUE_TOL))
    if bad.size:
        k = int(bad[np.argmax(excess[bad])])
        worst = {"pose_X_CTool": X[k].tolist(), "kind": str(kinds[k]),
                 "lower_bound_m": float(lower[k]), "fcl_m": float(truth[k]),
                 "verdict": int(verdict[k])}
    by_kind = {}
    for kind in sorted(set(kinds.tolist())):
        m = kinds == kind
        by_kind[kind] = {"poses": int(m.sum()), "false_safe_verdict": int(false_verdict[m].sum()),
                         "false_safe_value": int(false_value[m].sum()),
                         "undecided": int((verdict[m] == UNDECIDED).sum()),
                         "fcl_min_m": float(truth[m].min()), "fcl_max_m": float(truth[m].max())}
    skipped = {}
    if hang.any():
        c_hang = exact.tool_clearance(X_all[hang], inst)
        skipped = {"poses": int(hang.sum()), "fcl_max_m": float(c_hang.max()),
                   "by_kind": {k: int((kinds_all[hang] == k).sum())
                               for k in sorted(set(kinds_all[hang].tolist()))}}
    return {
        "poses": n,
        "not_evaluated_nonterminating": skipped,
        "false_safe_verdict": int(false_verdict.sum()),
        "false_safe_value": int(false_value.sum()),
        "excess_anywhere": int((excess > VALUE_TOL).sum()),
        "fcl_below_its_floor": int(sentinel.sum()),
        "fcl_below_its_floor_min_m": float(truth[sentinel].min()) if sentinel.any() else None,
        "largest_excess_m_where_free": float(excess[truth > 0].max()) if (truth > 0).any()
        else None,
        "largest_excess_m": float(excess.max()),
        "worst_pose": worst,
        "safe": int((verdict == SAFE).sum()),
        "undecided": int((verdict == UNDECIDED).sum()),
        "undecided_fcl_below_margin": int(((verdict == UNDECIDED) & (truth < margin)).sum()),
        "unsafe": int((verdict == UNSAFE).sum()),
        "false_unsafe": int(((verdict == UNSAFE) & (truth >= margin)).sum()),
        "fcl_below_margin": int((truth < margin).sum()),
        "fcl_free_by_margin_plus_0.2mm": int(free.sum()),
        "called_safe_share": float((verdict[free] == SAFE).mean()) if free.any() else None,
        "median_gap_m_where_free": float(np.median(truth[gap_at] - lower[gap_at]))
        if gap_at.any() else None,
        "us_per_pose": {"fast_verdict": 1e6 * t_verdict / n, "bound_value": 1e6 * t_value / n,
                        "fcl": 1e6 * t_fcl / n},
        "fcl_over_fast_verdict": t_fcl / t_verdict if t_verdict > 0 else None,
        "by_kind": by_kind,
    }


def study(*, poses: int = 10_000, seed: int = 0, cavities=CAVITIES, instruments=INSTRUMENTS,
          progress: Progress | None = None, threads: int | None = 1, plan=None) -> dict:
    """The check of every cavity x instrument (module notes); ``poses`` per pair. ``threads``:
    numba's threads for the bound (1: timed like FCL, on one core; None: as it is); ``plan``: a
    plan folder whose case and placements are the ``default`` cavity (:func:`default_cavity`)."""
    import numba

    check_poses(poses)
    check_seed(seed)
    for name in cavities:
        if name not in CAVITIES + SUBJECTS:
            raise InputError("--cavities", f"unknown cavity {name!r}; expected some of "
                             f"{CAVITIES + SUBJECTS}")
    for name in instruments:
        instrument(name)
    progress = progress or Progress("scan-bound-check", quiet=True)
    before = numba.get_num_threads()
    if threads is not None:
        numba.set_num_threads(min(int(threads), numba.config.NUMBA_NUM_THREADS))
    try:
        base, margin = None, None
        if any(name in CAVITIES for name in cavities):
            base, margin = default_cavity(progress, plan)
        rows = []
        for ci, name in enumerate(cavities):
            if name in SUBJECTS:
                cav, margin = cohort_cavity(name, progress)
            else:
                cav = base if name == "default" else copy_cavity(base, name)
            for ii, iname in enumerate(instruments):
                inst = instrument(iname)
                t0 = time.perf_counter()
                scan = ScanClearance(cav.exact, inst)
                grid_s = time.perf_counter() - t0
                progress.say(f"{name} x {iname}: drawing {poses} poses")
                X, kinds = pose_set(cav, scan, iname, poses, margin,
                                    seeds.rng(seed, 100 * ci + ii))
                progress.say(f"{name} x {iname}: bound vs FCL on {len(X)} poses")
                row = {"cavity": name, "instrument": iname, "grid_seconds": grid_s,
                       **measure(scan, cav.exact, inst, X, kinds, margin)}
                rows.append(row)
                progress.say(table_line(row))
    finally:
        numba.set_num_threads(before)
    return {"case": "default", "cavities": list(cavities), "seed": int(seed), "margin_m": margin,
            "poses_per_pair": int(poses), "poses_total": int(sum(r["poses"] for r in rows)),
            "numba_threads": threads, "band_m": BAND, "free_by_m": FREE_BY,
            "value_tolerance_m": VALUE_TOL, "adversarial_share": ADVERSARIAL_SHARE,
            "rows": rows}


def check_poses(poses) -> int:
    if isinstance(poses, bool) or not isinstance(poses, (int, np.integer)) or not (
            1 <= poses <= MAX_POSES):
        raise InputError("--poses", f"expected an integer 1..{MAX_POSES}, got {poses!r}")
    return int(poses)


def check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError("--seed", f"expected an integer >= 0, got {seed!r}")
    return int(seed)


HEADER = (f"{'cavity':9s} {'instrument':9s} {'poses':>7s} {'f-safe':>6s} {'f-value':>7s} "
          f"{'excess mm':>9s} {'no-return':>9s} {'undec':>6s} {'f-unsafe':>8s} "
          f"{'called safe':>11s} "
          f"{'gap mm':>6s} {'verdict us':>10s} {'FCL us':>8s} {'FCL/bound':>9s}")


def table_line(r: dict) -> str:
    share = "n/a" if r["called_safe_share"] is None else f"{100 * r['called_safe_share']:.1f}%"
    gap = "n/a" if r["median_gap_m_where_free"] is None else \
        f"{1e3 * r['median_gap_m_where_free']:.3f}"
    t = r["us_per_pose"]
    skipped = r["not_evaluated_nonterminating"].get("poses", 0)
    ratio = "n/a" if r["fcl_over_fast_verdict"] is None else f"{r['fcl_over_fast_verdict']:.2f}"
    return (f"{r['cavity']:9s} {r['instrument']:9s} {r['poses']:7d} "
            f"{r['false_safe_verdict']:6d} {r['false_safe_value']:7d} "
            f"{1e3 * r['largest_excess_m']:+9.3f} {skipped:9d} {r['undecided']:6d} "
            f"{r['false_unsafe']:8d} "
            f"{share:>11s} {gap:>6s} {t['fast_verdict']:10.1f} {t['fcl']:8.1f} {ratio:>9s}")


def _arguments(argv):
    ap = argparse.ArgumentParser(prog="python -m implantplan.analyses.studies.scan_bound_check",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", default="10000",
                    help=f"poses per cavity x instrument (1..{MAX_POSES}; default 10000)")
    ap.add_argument("--seed", default="0", help="seed (integer >= 0; default 0)")
    ap.add_argument("--cavities", default=",".join(CAVITIES),
                    help=f"comma-separated, some of {', '.join(CAVITIES + SUBJECTS)} "
                         "(default: the default case and its 4 copies)")
    ap.add_argument("--out", type=Path, default=None,
                    help="a new folder for scan_bound_check.json")
    ap.add_argument("--plan", type=Path, default=None,
                    help="a plan folder (implantplan plan/demo): its case and placements are the "
                         "'default' cavity (default: the bundled case, placed again)")
    return ap.parse_args(argv)


def _integer(text: str, name: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise InputError(name, f"expected an integer, got {text!r}") from None


def main(argv=None) -> int:
    args = _arguments(argv)
    try:
        poses = check_poses(_integer(args.poses, "--poses"))
        seed = check_seed(_integer(args.seed, "--seed"))
        if args.out is not None and args.out.exists():
            raise InputError("--out", f"{args.out} exists; expected a new folder")
        cavities = tuple(c.strip() for c in args.cavities.split(",") if c.strip())
        if not cavities:
            raise InputError("--cavities", "expected at least one cavity")
        res = study(poses=poses, seed=seed, cavities=cavities,
                    progress=Progress("scan-bound-check"), plan=args.plan)
        if args.out is not None:
            try:
                args.out.mkdir(parents=True)
                write_json(args.out / "scan_bound_check.json", res)
            except OSError as exc:
                raise InputError("--out", f"{args.out}: cannot write ({exc})") from None
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"margin {1e3 * res['margin_m']:g} mm, {res['poses_total']} poses, numba threads "
          f"{res['numba_threads']}")
    print(HEADER)
    for r in res["rows"]:
        print(table_line(r))
    bad = sum(r["false_safe_verdict"] + r["false_safe_value"] for r in res["rows"])
    return 3 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
