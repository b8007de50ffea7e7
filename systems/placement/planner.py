"""Stage 2 of seed 000: automatic placement of the feeding target (Wang et al. 2023, Sec. 4).

Frames (Eq. 15-18). The Hole frame sits at the implant site ``t_ch`` with z = ``D_hz``, the hole
axis from the bone into the cavity, and x = ``D_hx`` in Center's YZ plane (Eq. 15-16):
    D_hx = (0, -s D_hz_z, |D_hz_y|) / sqrt(D_hz_y^2 + D_hz_z^2),   s = sign(D_hz_y),
which is Eq. 16 multiplied through (no division by D_hz_y). Departures, both for degenerate axes:
s = +1 when D_hz_y = 0 (the limit from D_hz_y > 0), and D_hx = Center z when D_hz is (anti)parallel
to Center x, where Eq. 16 is 0/0 (Center z is already perpendicular and points out of the mouth,
the side Eq. 16 prefers with D_hx_z >= 0). R_ch = (D_hx, D_hz x D_hx, D_hz) (Eq. 17).
The Tool frame is T_ct = T_ch T_ht with T_ht = (Rz(theta_T), [0, 0, d_T]) (Eq. 18).

Lines (Eq. 19). Both run along D = R_ch [cos theta_T, sin theta_T, 0] (Tool x), outward:
line1, the rod, from P1 = T_ct [r, 0, 0] against the model shrunk by r; line2, the path of the
implant tip, from P2 = T_ct [r, 0, -d12] against the unshrunk model. Both are rays that must leave
through the mouth opening (the rule in :meth:`systems.fpsm.model.Fpsm.line_safety`).

Objective (to be minimized), with n_i = m_i + 1 samples of line i and f_i = f_safe (Eq. 13):
    eq14: F = -(n1 sgn(f1) sqrt|f1| + n2 sgn(f2) sqrt|f2|) / (n1 + n2)   (units sqrt(m))
    eq21: F = -(n1 f1 + n2 f2) / (n1 + n2)                                (m)
    eq22: F = -(n1 sgn(f1) f1^2 + n2 sgn(f2) f2^2) / (n1 + n2)            (m^2)
Departure: Eq. 22 as printed squares away the sign of f, so a deep collision (large negative f)
would score as very safe and the PSO runs into it; we keep the sign, as Eq. 14 does. On
collision-free placements (both f > 0, e.g. the paper's cylinder check) it is Eq. 22 exactly.
A line with no sample (it lies wholly above the mouth opening) constrains nothing and has weight
0; F = 0 if neither line has one. The feeding target itself must be inside the cavity (the paper's
VF ends in a cylinder inside the mouth): when the Tool origin, P1 or P2 lies h above the top
slice the placement is infeasible and scored as a collision, f_safe = -lambda_min h for both
lines (so every line of a feasible placement is sampled at least at its start and at the top
slice) (a rule the paper does not need,
since its search never leaves the mouth; without it a target floating outside the mouth would
score F = 0, better than any colliding placement).

PSO (Eq. 20): v <- c0 v + r1 c1 (x_best_i - x) + r2 c2 (x_best_glb - x); x <- x + v, with r1, r2
uniform in [0, 1) drawn per particle and per coordinate. Positions that leave the bounds are
clipped onto them and that velocity component is zeroed (an absorbing wall). The paper gives no
inertia c0; we use 0.8, chosen by measurement with the paper's c1 = 0.3 and c2 = 0.4 (20 seeds
per case; "hit" = within 0.1 mm / 0.1 deg of the optimum): on the cylinder check every c0 in
0.5..0.8 hits 20/20, but on a flat-bottomed objective (an elliptic tube, see the tests) 0.5 hits
11/20, Clerc's constriction value 0.7298 17/20 (misses by up to 0.7 mm), 0.8 20/20 at about 200
iterations; 0.9 oscillates and stalls early (18/20 on the cylinder). A small inertia lets the
swarm collapse before it has found the bottom of a flat valley. The run stops when the global
best has not improved (strictly) for 40 iterations, as in the paper.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from implantplan.systems import seeds
from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import rot_z, transform, unit, wrap_angle
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.tool_clearance import (
    admissible_poses,
    feed_clearance,
    feed_depth,
    feed_poses,
    fixture_admits,
)
from implantplan.systems.safety import SafetySpec

OBJECTIVES = ("eq14", "eq21", "eq22")


# -- frames (Eq. 15-19) ------------------------------------------------------------------------


def hole_frame(hole_Center_m, axis_Center) -> np.ndarray:
    """X_CH (4, 4): the Hole frame in Center from the site and the hole axis (Eq. 15-17).

    Args:
        hole_Center_m: (3,) implant site t_ch in Center (m).
        axis_Center: (3,) hole axis D_hz in Center, from the bone into the cavity (normalized
            here; zero or non-finite is an InputError).
    """
    t = np.asarray(hole_Center_m, dtype=float)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise InputError("hole", f"expected 3 finite coordinates (m), got {t.tolist()}")
    z = unit(axis_Center, field="hole_axis")
    zy, zz = z[1], z[2]
    m = max(abs(zy), abs(zz))
    if m == 0.0:  # D_hz (anti)parallel to Center x: Eq. 16 is 0/0
        x = np.array([0.0, 0.0, 1.0])
    else:  # Eq. 16, exact for any (zy, zz) != 0; scaled by m first so tiny values keep |x| = 1
        s = 1.0 if zy >= 0 else -1.0
        v = np.array([0.0, -s * zz / m, abs(zy) / m])
        x = v / np.linalg.norm(v)
    R = np.stack([x, np.cross(z, x), z], axis=-1)  # Eq. 17
    return transform(R, t)


def tool_frames(X_CH: np.ndarray, d_T, theta_T) -> np.ndarray:
    """X_CT (..., 4, 4) for d_T (m) and theta_T (rad) broadcast together (Eq. 18)."""
    d_T, theta_T = np.broadcast_arrays(np.asarray(d_T, float), np.asarray(theta_T, float))
    R = X_CH[:3, :3] @ rot_z(theta_T)
    p = X_CH[:3, 3] + d_T[..., None] * X_CH[:3, 2]
    return transform(R, p)


@dataclass(frozen=True)
class FeedingLines:
    """Start points and the common direction of line1 (rod) and line2 (implant tip), Eq. 19."""

    tool: np.ndarray  # (K, 3) origin of Tool
    direction: np.ndarray  # (K, 3) unit D_line, Tool x
    start1: np.ndarray  # (K, 3) P1
    start2: np.ndarray  # (K, 3) P2


def feeding_lines(X_CH, d_T, theta_T, rod_radius: float, implant_length: float) -> FeedingLines:
    """Eq. 19 for a batch of (d_T, theta_T) (each (K,)), without building 4x4 matrices: the
    Tool-frame lines of :meth:`Instrument.lines_T` carried by X_CT = X_CH (Rz(theta), d_T z)."""
    d_T = np.atleast_1d(np.asarray(d_T, dtype=float))
    theta_T = np.atleast_1d(np.asarray(theta_T, dtype=float))
    R = X_CH[:3, :3]
    c, s = np.cos(theta_T)[:, None], np.sin(theta_T)[:, None]
    Tx = c * R[:, 0] + s * R[:, 1]  # Tool x (= D) and y in Center
    Ty = -s * R[:, 0] + c * R[:, 1]
    tool = X_CH[:3, 3] + d_T[:, None] * R[:, 2]
    starts, u = _lines_T(rod_radius, implant_length)
    p1, p2 = (tool + a[0] * Tx + a[1] * Ty + a[2] * R[:, 2] for a in starts)
    D = u[0] * Tx + u[1] * Ty + u[2] * R[:, 2]
    return FeedingLines(tool, D, p1, p2)


def _lines_T(rod_radius: float, implant_length: float):
    # Eq. 19 lives in Instrument.lines_T; a zero rod radius is allowed here (the paper's
    # line check), so build the geometry only for its lines
    return Instrument.paper(rod_radius=rod_radius, implant_length=implant_length).lines_T()


# -- objective (Eq. 13, 14, 21, 22) ------------------------------------------------------------


@dataclass(frozen=True)
class Evaluation:
    """Objective and its parts for K placements."""

    F: np.ndarray
    f_safe_line1: np.ndarray
    f_safe_line2: np.ndarray
    samples_line1: np.ndarray
    samples_line2: np.ndarray
    d_safe_min_line1: np.ndarray
    d_safe_min_line2: np.ndarray


def combine(f1, n1, f2, n2, objective: str = "eq14") -> np.ndarray:
    """F_safe from the two lines' f_safe and sample counts (Eq. 14, 21 or 22), batched."""
    f1, f2 = np.asarray(f1, float), np.asarray(f2, float)
    w1, w2 = np.asarray(n1, float), np.asarray(n2, float)
    if objective == "eq14":
        g = np.sign
        t1, t2 = g(f1) * np.sqrt(np.abs(f1)), g(f2) * np.sqrt(np.abs(f2))
    elif objective == "eq21":
        t1, t2 = f1, f2
    elif objective == "eq22":
        t1, t2 = f1 * np.abs(f1), f2 * np.abs(f2)  # signed squares, see the module notes
    else:
        raise InputError("objective", f"expected one of {', '.join(OBJECTIVES)}, got {objective!r}")
    num = w1 * np.where(w1 > 0, t1, 0.0) + w2 * np.where(w2 > 0, t2, 0.0)
    den = w1 + w2
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, -num / np.maximum(den, 1.0), 0.0)


@dataclass(frozen=True)
class PlacementProblem:
    """Everything fixed during stage 2; :meth:`evaluate` is the batched objective."""

    fpsm: Fpsm
    X_CH: np.ndarray
    rod_radius: float
    implant_length: float
    objective: str = "eq14"
    lambda_avg: float = 0.5
    lambda_min: float = 0.5

    def evaluate(self, x: np.ndarray) -> Evaluation:
        """Objective for placements x (K, 2) = (d_T m, theta_T rad)."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        K = x.shape[0]
        lines = feeding_lines(self.X_CH, x[:, 0], x[:, 1], self.rod_radius, self.implant_length)
        starts = np.concatenate([lines.start1, lines.start2])
        dirs = np.concatenate([lines.direction, lines.direction])
        radius = np.concatenate([np.full(K, self.rod_radius), np.zeros(K)])  # Eq. 12 for line1
        ls = self.fpsm.line_safety_batch(
            starts, dirs, np.full(2 * K, np.inf), radius, self.lambda_avg, self.lambda_min
        )
        f1, f2 = ls.f_safe[:K], ls.f_safe[K:]
        n1, n2 = ls.samples[:K], ls.samples[K:]
        d1, d2 = ls.d_safe_min[:K], ls.d_safe_min[K:]
        # The feeding target must be inside the cavity: a Tool origin or line start above the
        # top slice (the mouth opening) is infeasible, scored as a collision as deep as it is
        # high.
        above = _height_above(lines, self.fpsm)
        out = above > 0
        if np.any(out):
            f1 = np.where(out, np.minimum(f1, -self.lambda_min * above), f1)
            f2 = np.where(out, np.minimum(f2, -self.lambda_min * above), f2)
            d1 = np.where(out, np.minimum(d1, -above), d1)
            d2 = np.where(out, np.minimum(d2, -above), d2)
            n1 = np.where(out, np.maximum(n1, 1), n1)
            n2 = np.where(out, np.maximum(n2, 1), n2)
        F = combine(f1, n1, f2, n2, self.objective)
        return Evaluation(F, f1, f2, n1, n2, d1, d2)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.evaluate(x).F


# -- PSO (Eq. 20) and the exhaustive grid ------------------------------------------------------


@dataclass(frozen=True)
class PsoResult:
    x: np.ndarray  # (D,) global best
    F: float
    history: np.ndarray  # (iterations + 1,) global best F after each iteration (0 = initial)
    iterations: int
    evaluations: int
    seconds: float
    stopped: str  # "stall" or "max_iterations"


def pso(
    func: Callable[[np.ndarray], np.ndarray],
    lower,
    upper,
    *,
    particles: int = 30,
    c0: float = 0.8,
    c1: float = 0.3,
    c2: float = 0.4,
    stall_iterations: int = 40,
    max_iterations: int = 1000,
    seed: int | np.random.Generator = 0,
) -> PsoResult:
    """Minimize ``func`` (batched: (P, D) -> (P,)) over the box [lower, upper] by Eq. 20.

    Initial positions uniform in the box, initial velocities uniform in +-(upper - lower)/2.
    Positions are clipped to the box and the clipped velocity components zeroed. Stops after
    ``stall_iterations`` iterations without a strict improvement of the global best, or after
    ``max_iterations``. Same seed, same result bit for bit, on every machine: the values of
    ``func`` are compared rounded to 27 bits (:func:`seeds.rounded`), so an "improvement" of a
    last bit (BLAS differs there between machines) neither resets the stall count nor moves
    the best (the optimum is found to that step, 2^-27 |F|; ``F`` and ``history`` are the
    values themselves).
    """
    t0 = time.perf_counter()
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    if lo.shape != hi.shape or lo.ndim != 1 or not np.all(np.isfinite(lo) & np.isfinite(hi)):
        raise InputError("bounds", "expected finite lower/upper bounds of equal length")
    if np.any(hi < lo):
        raise InputError("bounds", f"expected lower <= upper, got {lo.tolist()}, {hi.tolist()}")
    if particles < 1 or stall_iterations < 1 or max_iterations < 1:
        raise InputError("pso", "particles, stall_iterations and max_iterations must be >= 1")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    span = hi - lo
    x = lo + rng.random((particles, lo.size)) * span
    v = (rng.random((particles, lo.size)) - 0.5) * span
    value = np.asarray(func(x), dtype=float)
    f = seeds.rounded(value)  # compared rounded: the same on every machine
    p_best, f_best, value_best = x.copy(), f.copy(), value.copy()
    g = int(np.argmin(f_best))
    g_best, g_f, g_value = p_best[g].copy(), float(f_best[g]), float(value_best[g])
    history = [g_value]
    evaluations, stall, it = particles, 0, 0
    while it < max_iterations and stall < stall_iterations:
        it += 1
        r1 = rng.random(x.shape)
        r2 = rng.random(x.shape)
        v = c0 * v + r1 * c1 * (p_best - x) + r2 * c2 * (g_best - x)  # Eq. 20
        x = x + v
        out = (x < lo) | (x > hi)
        x = np.clip(x, lo, hi)
        v = np.where(out, 0.0, v)
        value = np.asarray(func(x), dtype=float)
        f = seeds.rounded(value)
        evaluations += particles
        better = f < f_best
        p_best[better], f_best[better], value_best[better] = x[better], f[better], value[better]
        g = int(np.argmin(f_best))
        if f_best[g] < g_f:
            g_best, g_f, g_value, stall = p_best[g].copy(), float(f_best[g]), \
                float(value_best[g]), 0
        else:
            stall += 1
        history.append(g_value)
    return PsoResult(
        x=g_best,
        F=g_value,
        history=np.array(history),
        iterations=it,
        evaluations=evaluations,
        seconds=time.perf_counter() - t0,
        stopped="stall" if stall >= stall_iterations else "max_iterations",
    )


@dataclass(frozen=True)
class GridResult:
    d_T: np.ndarray  # (A,) m
    theta_T: np.ndarray  # (B,) rad
    F: np.ndarray  # (A, B)
    x: np.ndarray  # (2,) best grid point
    best_F: float


def grid_search(func, lower, upper, shape=(201, 181), *, chunk: int = 50_000) -> GridResult:
    """Exhaustive evaluation on a (d_T, theta_T) grid including the bounds; ties go to the
    first in row-major order."""
    a = np.linspace(lower[0], upper[0], int(shape[0]))
    b = np.linspace(lower[1], upper[1], int(shape[1]))
    X = np.stack(np.meshgrid(a, b, indexing="ij"), axis=-1).reshape(-1, 2)
    F = np.concatenate([func(X[i : i + chunk]) for i in range(0, len(X), chunk)])
    k = int(np.argmin(F))
    return GridResult(a, b, F.reshape(a.size, b.size), X[k], float(F[k]))


def verify_by_grid(func, lower, upper, *, coarse=(201, 181), fine=(161, 161)) -> dict:
    """The paper's Fig. 18 check: a global grid, then a fine grid over +-2 coarse steps around
    its best point (clipped to the bounds). Returns both grids and the best point found."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    g1 = grid_search(func, lo, hi, coarse)
    step = (hi - lo) / (np.asarray(coarse) - 1)
    g2 = grid_search(func, np.maximum(g1.x - 2 * step, lo), np.minimum(g1.x + 2 * step, hi), fine)
    best = g2 if g2.best_F <= g1.best_F else g1
    return {"coarse": g1, "fine": g2, "x": best.x, "F": best.best_F}


# -- the public entry point --------------------------------------------------------------------


@dataclass
class Placement:
    """Result of stage 2 for one implant site (SI units; frames in Center)."""

    d_T: float
    theta_T: float
    F_safe: float
    f_safe_line1: float
    f_safe_line2: float
    d_safe_min_line1: float
    d_safe_min_line2: float
    samples_line1: int
    samples_line2: int
    valid: bool
    reason: str
    iterations: int
    evaluations: int
    seconds: float
    stopped: str
    history: np.ndarray
    X_CH: np.ndarray
    X_CT: np.ndarray
    line1: dict
    line2: dict
    objective: str
    rod_radius: float
    implant_length: float
    bounds: np.ndarray  # (2, 2): rows lower/upper of (d_T, theta_T)
    seed: int
    vf: object = None  # systems.placement.fixture.VirtualFixture
    grid: dict | None = None
    settings: dict = field(default_factory=dict)
    verification: dict = field(default_factory=dict)  # see verify_placement

    def to_dict(self) -> dict:
        out = {
            "d_T": self.d_T,
            "theta_T": self.theta_T,
            "F_safe": self.F_safe,
            "F_safe_units": {"eq14": "sqrt(m)", "eq21": "m", "eq22": "m^2"}[self.objective],
            "f_safe_line1": self.f_safe_line1,
            "f_safe_line2": self.f_safe_line2,
            "d_safe_min_line1": self.d_safe_min_line1,
            "d_safe_min_line2": self.d_safe_min_line2,
            "samples_line1": self.samples_line1,
            "samples_line2": self.samples_line2,
            "valid": self.valid,
            "reason": self.reason,
            "iterations": self.iterations,
            "evaluations": self.evaluations,
            "seconds": self.seconds,
            "stopped": self.stopped,
            "history": self.history,
            "frame": "Center",
            "X_CH": self.X_CH,
            "X_CT": self.X_CT,
            "line1": self.line1,
            "line2": self.line2,
            "objective": self.objective,
            "rod_radius": self.rod_radius,
            "implant_length": self.implant_length,
            "bounds": {"d_T": self.bounds[:, 0], "theta_T": self.bounds[:, 1]},
            "seed": self.seed,
            "settings": self.settings,
            "vf": None if self.vf is None else self.vf.to_dict(),
            "verification": self.verification,
            "fixture_tolerance": {
                "lateral": self.verification.get("lateral_tolerance"),
                "angle": self.verification.get("angle_tolerance"),
                "units": {"lateral": "m", "angle": "rad"},
            },
        }
        if self.grid is not None:
            out["grid_check"] = {k: v for k, v in self.grid.items() if k not in ("coarse", "fine")}
        return out


def _height_above(lines: FeedingLines, fpsm: Fpsm) -> np.ndarray:
    """(K,) height (m) of the highest of the Tool origin, P1 and P2 above the top slice."""
    z = np.maximum(np.maximum(lines.tool[:, 2], lines.start1[:, 2]), lines.start2[:, 2])
    return z - fpsm.z_range[1]


def verify_placement(
    fpsm: Fpsm,
    X_CT: np.ndarray,
    tool: Instrument,
    *,
    safety: SafetySpec | None = None,
    exact=None,
    depth_step: float = 0.002,
    region_budget: int | None = None,
    progress=None,
) -> dict:
    """Verify the whole admissible region of a placement: the tool at every lateral offset up
    to ``safety.lateral_tolerance`` and turn up to ``safety.angle_tolerance`` from the planned
    pose X_CT, at every depth of the feed (backed out along the rod axis until it is out of the
    mouth), against the clinical margin ``safety.clearance_margin`` (None: ``SafetySpec()``).

    1. Certified, against the scan when ``exact`` (a :class:`systems.placement.exact_clearance.
       ExactCavity`) is given: :func:`systems.placement.scan_clearance.feed_scan_clearance` (the
       scan bound of every solid over the feed and the whole region, FCL resolving the poses the
       bound leaves below the margin, and where the region's worst-case loss leaves it below,
       the region itself by branch and bound with FCL, at most ``region_budget`` queries, None:
       :data:`systems.placement.scan_clearance.REGION_BUDGET`, its progress lines to
       ``progress``, a Progress-like object with ``say``); without a mesh, against the FPSM:
       :func:`systems.placement.tool_clearance.feed_clearance` (a lower bound over the whole
       region, no sampling gaps). The FPSM's value is kept as ``clearance_certified_fpsm``.
    2. Exact, against the scan mesh when ``exact`` is given: FCL at the planned pose, 8 lateral
       offsets, 18 turns (tilts, roll, diagonals) and their combinations
       (:func:`systems.placement.tool_clearance.admissible_poses`) about each pose of the feed
       (every ``depth_step``); the smallest value (exact at the samples).

    Returns:
        dict (SI units) with ``clearance_certified``, ``certified_against`` ("scan" or
        "fpsm"), ``clearance_certified_fpsm``, ``clearance_exact_min`` (None without a mesh),
        the tolerances, the margin, ``reasons`` (empty when both are >= margin).
    """
    safety = SafetySpec() if safety is None else safety
    lateral, angle = safety.lateral_tolerance, safety.angle_tolerance
    margin = safety.clearance_margin
    X = np.asarray(X_CT, dtype=float).reshape(4, 4)
    depth = feed_depth(fpsm, X, tool)
    fpsm_value = float(feed_clearance(fpsm, X, tool, depth=depth, lateral=lateral,
                                      angle=angle)[0])
    certified, against, scan = fpsm_value, "fpsm", None
    if exact is not None:
        from implantplan.systems.placement.scan_clearance import (
            ScanClearance,
            feed_scan_clearance,
        )

        bound = ScanClearance(exact, tool)
        scan = feed_scan_clearance(bound, X, depth=depth, lateral=lateral, angle=angle,
                                   clearance=margin, resolve_region=True,
                                   region_budget=region_budget, progress=progress)
        certified, against = scan["value"], "scan"
    out = {
        "clearance_certified": certified,
        "certified_against": against,
        "clearance_certified_fpsm": fpsm_value,
        "scan_bound": scan,
        "clearance_exact_min": None,
        "exact_poses": 0,
        "clearance_margin": margin,
        "lateral_tolerance": float(lateral),
        "angle_tolerance": float(angle),
        "feed_depth": depth,
        "tool": tool.to_dict(),
        "method": "certified bound over the feed and the admissible region (against the scan: "
                  "its distance grid, FCL resolving the poses the bound leaves below the "
                  "margin; without a mesh, the FPSM bound); FCL exact against the scan at "
                  "sampled poses of that region",
        "units": "m, rad",
    }
    reasons = []
    region = f"(lateral {lateral * 1e3:.2f} mm, angle {np.degrees(angle):.2f} deg)"
    if not certified >= margin:
        reasons.append(
            f"the tool's certified clearance ({against}) over the feed and the fixture's "
            f"admissible region {region} is {certified * 1e3:.3f} mm, below the clinical margin "
            f"{margin * 1e3:.3f} mm"
        )
    if exact is not None:
        # FCL's minimum over the samples, asked only where the bound cannot rule a sample out
        feed = feed_poses(X, depth, depth_step)[0][0]
        samples = admissible_poses(feed, lateral, angle).reshape(1, -1, 4, 4)
        c, out["exact_fcl_queries"] = bound.exact_minimum(samples)
        out["clearance_exact_min"] = float(c[0])
        out["exact_poses"] = int(samples.shape[1])
        if not c[0] >= margin:
            reasons.append(
                f"the tool's exact clearance to the scan (FCL) over the feed and the admissible "
                f"region {region} is {c[0] * 1e3:.3f} mm, below the clinical margin "
                f"{margin * 1e3:.3f} mm"
            )
    out["reasons"] = reasons
    return out


SEARCH_GRID = (101, 91)  # (d_T, theta_T) points of the coarse grid of :func:`search_for_instrument`
SEARCH_FINE = (0.25e-3, np.radians(1.0))  # m, rad: the fine grid's largest spacing
SEARCH_FINE_MAX = 161  # points per axis of the fine grid at most
SEARCH_FEED_STEP = 0.5e-3  # m, the screen's pose spacing along the feed (costs <= half)
SEARCH_SCREEN = 400  # feeds screened at most
SEARCH_COARSE = 0.5e-3  # m, the scan bound's resolution in the screen's upper estimates
SEARCH_VERIFY = 8  # full verifications at most (each screened candidate that passes gets one)
EXACT_BEST_STEP = 1e-3  # m, the feed's pose spacing of :func:`exact_best` (a refusal's reference)
EXACT_REGION_EVERY = 2  # :func:`exact_best` samples the region about every 2nd feed pose
EXACT_VERIFY = 3  # candidates FCL's samples keep at the margin that get the full verification


def _grid_points(lo, hi, shape) -> np.ndarray:
    a = np.linspace(lo[0], hi[0], int(shape[0]))
    b = np.linspace(lo[1], hi[1], int(shape[1]))
    return np.stack(np.meshgrid(a, b, indexing="ij"), axis=-1).reshape(-1, 2)


def _feasibility(problem: PlacementProblem, X: np.ndarray) -> tuple[Evaluation, np.ndarray]:
    """The evaluation at placements X (K, 2) and the feeding target's height above the mouth
    opening (K,): what :func:`_invalid_reasons` and :func:`_lines_ok` judge."""
    ev = problem.evaluate(X)
    lines = feeding_lines(problem.X_CH, X[:, 0], X[:, 1], problem.rod_radius,
                          problem.implant_length)
    return ev, _height_above(lines, problem.fpsm)


def _lines_ok(problem: PlacementProblem, X: np.ndarray):
    """The objective at placements X (K, 2) and whether each keeps :func:`_invalid_reasons`'s
    rules (both FPSM lines collision-free, the feeding target in the mouth)."""
    ev, h = _feasibility(problem, X)
    return ev.F, (ev.f_safe_line1 > 0) & (ev.f_safe_line2 > 0) & (h <= 0)


def search_for_instrument(problem: PlacementProblem, bounds: np.ndarray, tool: Instrument,
                          safety: SafetySpec, exact, *,
                          progress=None) -> tuple[np.ndarray | None, dict | None, dict]:
    """The best placement whose whole instrument clears the scan, when the FPSM optimum's does
    not (the PSO objective is the paper's: it sees the rod and the implant's path, not the
    instrument's head).

    1. Candidates: the :data:`SEARCH_GRID` points of ``bounds`` whose FPSM lines are
       collision-free with the feeding target in the mouth (:func:`_invalid_reasons`'s rules),
       then a fine grid (spacing at most :data:`SEARCH_FINE`) over their bounding box, with the
       same rules.
    2. At the target pose, each solid's scan bound less its share of the fixture's region
       (lateral + angle * reach) must reach the margin: the target is one pose of the feed, so a
       candidate failing there cannot pass (a necessary test, batched).
    3. In order of the objective F (best first), at most :data:`SEARCH_SCREEN` feeds are
       screened by :func:`systems.placement.scan_clearance.feed_scan_clearance` every
       :data:`SEARCH_FEED_STEP` (the verification's certified bound at a coarser spacing); the
       first :data:`SEARCH_VERIFY` that pass get the full :func:`verify_placement` (the plan's
       verdict), and the first it accepts is the placement.

    Returns:
        (x (2,) or None, its verification or None, the search record: ``grid``, ``fine``,
        ``candidates``, ``clear_at_target``, ``screened``, ``verified``, ``F`` and ``F_loss``
        (F minus the best F of all candidates) of the choice).
    """
    from implantplan.systems.placement import scan_clearance
    from implantplan.systems.placement.scan_clearance import (
        FEED_STEP,
        ScanClearance,
        feed_scan_clearance,
    )

    lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    Xc = _grid_points(lo, hi, SEARCH_GRID)
    _, ok = _lines_ok(problem, Xc)
    record = {"grid": list(SEARCH_GRID), "fine": None, "candidates": 0, "clear_at_target": 0,
              "screened": 0, "verified": 0, "feed_step": SEARCH_FEED_STEP, "F": None,
              "F_loss": None}
    if not ok.any():
        return None, None, record
    step = (hi - lo) / (np.asarray(SEARCH_GRID) - 1)
    flo = np.maximum(Xc[ok].min(axis=0) - step, lo)
    fhi = np.minimum(Xc[ok].max(axis=0) + step, hi)
    shape = np.clip(np.ceil((fhi - flo) / np.asarray(SEARCH_FINE)).astype(int) + 1, 2,
                    SEARCH_FINE_MAX)
    X = np.concatenate([Xc[ok], _grid_points(flo, fhi, shape)])
    F, ok = _lines_ok(problem, X)
    X, F = X[ok], F[ok]
    record["fine"] = {"shape": shape.tolist(), "d_T": [float(flo[0]), float(fhi[0])],
                      "theta_T": [float(flo[1]), float(fhi[1])]}
    record["candidates"] = int(X.shape[0])
    scan = ScanClearance(exact, tool)
    margin = safety.clearance_margin
    loss = safety.lateral_tolerance + safety.angle_tolerance * tool.shape_reach_T()
    X_CT = tool_frames(problem.X_CH, X[:, 0], X[:, 1])
    clear = np.ones(X.shape[0], dtype=bool)
    subs = scan.solids
    for k, sub in enumerate(subs):
        clear &= sub.bounds(X_CT, margin + loss[k])[0] - loss[k] >= margin
    record["clear_at_target"] = int(clear.sum())
    order = np.flatnonzero(clear)[np.argsort(F[clear], kind="stable")]
    for k in order[:SEARCH_SCREEN]:
        record["screened"] += 1
        depth = feed_depth(problem.fpsm, X_CT[k], tool)
        # an upper estimate below the margin at a feed pose (the verification's poses are within
        # half its step of it) rules the candidate out before the certified screen
        P = feed_poses(X_CT[k], depth, SEARCH_FEED_STEP)[0].reshape(-1, 4, 4)
        if any((sub.bounds(P, margin + loss[j], resolution=SEARCH_COARSE)[1] - loss[j]).min()
               + 0.5 * FEED_STEP < margin for j, sub in enumerate(subs)):
            continue
        screen = feed_scan_clearance(scan, X_CT[k], depth=depth,
                                     lateral=safety.lateral_tolerance,
                                     angle=safety.angle_tolerance, clearance=margin,
                                     step=SEARCH_FEED_STEP)
        if not screen["value"] >= margin:
            continue
        record["verified"] += 1
        ver = verify_placement(problem.fpsm, X_CT[k], tool, safety=safety, exact=exact,
                               progress=progress)
        if not ver["reasons"]:
            record["F"] = float(F[k])
            record["F_loss"] = float(F[k] - F.min())
            return X[k].copy(), ver, record
        if record["verified"] >= SEARCH_VERIFY:
            break
    if X.shape[0] == 0:
        return None, None, record
    best = exact_best(problem, X, tool, safety, scan)
    record["exact_best"] = best
    # FCL finds room the bound did not certify: the plan's verdict (the region resolved with
    # FCL) for the candidates FCL's samples rank best, at most EXACT_VERIFY
    budget = scan_clearance.REGION_BUDGET  # shared by the candidates (read at call time)
    for rank, (k, value) in enumerate(best["ranked"][:EXACT_VERIFY]):
        if value < margin or budget <= 0:
            break
        ver = verify_placement(problem.fpsm, X_CT[k], tool, safety=safety, exact=exact,
                               region_budget=budget, progress=progress)
        budget -= ((ver["scan_bound"] or {}).get("region") or {}).get("fcl_queries", 0)
        record["verified"] += 1
        if rank == 0:
            best["certified"] = ver["clearance_certified"]
            best["region"] = (ver["scan_bound"] or {}).get("region")
        if not ver["reasons"]:
            record["F"] = float(F[k])
            record["F_loss"] = float(F[k] - F.min())
            record["exact_rank"] = rank
            return X[k].copy(), ver, record
    return None, None, record


def refusal(tool: Instrument, safety: SafetySpec, search: dict) -> str:
    """Why no placement passes, measured: the search's counts and :func:`exact_best`'s FCL
    reference, which tells the site's geometry (FCL finds no candidate keeping the margin) from
    the certified bound's slack (FCL's samples keep it, the bound cannot prove it)."""
    text = (f"no placement clears the scan by the margin with the whole instrument ({tool.name})"
            f" over the feed and the fixture's region ({search['candidates']} grid placements "
            f"with collision-free FPSM lines, {search['clear_at_target']} clear at the target, "
            f"{search['screened']} feeds screened)")
    best = search.get("exact_best")
    if not best:
        return text
    margin = safety.clearance_margin
    where = (f"d_T {best['d_T'] * 1e3:.1f} mm, theta_T {np.degrees(best['theta_T']):.1f} deg, "
             f"limited by the {best['limiting_solid']}")
    text += (f"; FCL at sampled poses of every candidate's feed and region: the best keeps at "
             f"most {best['value'] * 1e3:.3f} mm ({where})")
    if best["value"] < margin:
        return text + (f", below the margin {margin * 1e3:.3f} mm: the site's geometry refuses "
                       f"this instrument and safety spec, not the bound")
    region = best.get("region") or {}
    tried = (f", the fixture's region resolved with FCL until its budget of "
             f"{region['fcl_queries']} queries" if region and not region["decided"] else "")
    return text + (f", but the certified bound there is {best['certified'] * 1e3:.3f} mm{tried}: "
                   f"not proven to keep the margin {margin * 1e3:.3f} mm (the true clearance "
                   f"lies between the two)")


def exact_best(problem: PlacementProblem, X: np.ndarray, tool: Instrument, safety: SafetySpec,
               scan) -> dict:
    """The reference for a refusal: FCL's clearance of the whole instrument (``scan``, a
    :class:`systems.placement.scan_clearance.ScanClearance` with its ExactCavity) over each
    candidate placement's feed (poses every :data:`EXACT_BEST_STEP`) and, where the feed alone
    keeps the margin, over the fixture's region about every :data:`EXACT_REGION_EVERY`-th feed
    pose too (:func:`admissible_poses`, as :func:`verify_placement` samples it, less the
    samples the fixture does not admit, :func:`fixture_admits`: a pose outside its region
    could read below the region's minimum); the best over the candidates X (K, 2).

    FCL at sampled poses is each candidate's clearance or more, so a best below the margin
    proves that no candidate keeps it, whatever bound the search used: the refusal is the site's
    geometry with this instrument and safety spec, not the bound's slack.

    Returns:
        dict (SI units): ``value`` (the best), ``index`` (into X), ``d_T``, ``theta_T``,
        ``feed_only`` (the best over the feed alone), ``limiting_solid`` (the instrument's solid
        that holds the best candidate's minimum), ``per_solid``, ``candidates``,
        ``region_checked`` (candidates whose region FCL sampled: in order of their feed's value
        until no later one can enter the best :data:`EXACT_VERIFY`), ``fcl_queries``,
        ``ranked`` ((index, value) of those, best first).
    """
    margin = safety.clearance_margin
    lateral, angle = safety.lateral_tolerance, safety.angle_tolerance
    X_CT = tool_frames(problem.X_CH, X[:, 0], X[:, 1])
    depths = [feed_depth(problem.fpsm, x, tool) for x in X_CT]
    feeds = [feed_poses(x, d, EXACT_BEST_STEP)[0][0] for x, d in zip(X_CT, depths, strict=True)]
    S = max(f.shape[0] for f in feeds)
    P = np.stack([np.concatenate([f, np.repeat(f[-1:], S - f.shape[0], axis=0)])
                  for f in feeds])  # each feed padded with its last pose: one (K, S) batch
    feed_only, queries = scan.exact_minimum(P)
    value = feed_only.copy()  # an upper bound of each candidate's clearance; exact where seen
    region = {}
    for k in np.argsort(-feed_only, kind="stable"):
        # the region's value is at most the feed's: once the EXACT_VERIFY-th best region value
        # found reaches the next feed value (or the margin is out of reach), no later candidate
        # can enter the ranking
        found = sorted((value[j] for j in region), reverse=True)
        if feed_only[k] < margin or (len(found) >= EXACT_VERIFY
                                     and feed_only[k] <= found[EXACT_VERIFY - 1]):
            break
        # the samples the fixture admits: FCL's minimum over them bounds the region's above
        feed = feeds[k][::EXACT_REGION_EVERY]
        R = admissible_poses(feed, lateral, angle)
        region[k] = R[fixture_admits(R, feed, problem.fpsm.z_range[1], lateral)][None]
        v, q = scan.exact_minimum(region[k])
        value[k], queries = float(v[0]), queries + q
    ranked = sorted(region, key=lambda k: -value[k])
    b = int(ranked[0] if region else np.argmax(value))
    poses = region.get(b, P[b:b + 1])
    per_solid = [float(sub.exact_minimum(poses)[0][0]) for sub in scan.solids]
    return {"value": float(value[b]), "index": b, "d_T": float(X[b, 0]),
            "theta_T": float(X[b, 1]), "feed_only": float(feed_only.max()),
            "limiting_solid": tool.shapes[int(np.argmin(per_solid))].name,
            "per_solid": dict(zip((s.name for s in tool.shapes), per_solid, strict=True)),
            "candidates": int(X.shape[0]), "region_checked": len(region),
            "fcl_queries": int(queries),
            "ranked": [(int(k), float(value[k])) for k in ranked],
            "step": EXACT_BEST_STEP, "units": "m, rad"}


def _invalid_reasons(problem: PlacementProblem, x: np.ndarray) -> list[str]:
    """Why the placement x is not acceptable (empty when both lines are collision-free)."""
    ev, hs = _feasibility(problem, np.asarray(x, dtype=float)[None])
    f1, f2 = float(ev.f_safe_line1[0]), float(ev.f_safe_line2[0])
    h = float(hs[0])
    reasons = []
    if h > 0:
        reasons.append(
            f"the feeding target (tool origin, rod start or implant tip) is {h * 1e3:.3f} mm "
            "above the mouth opening (top slice)"
        )
    if not f1 > 0:
        reasons.append(f"line1 (rod) collides: f_safe = {f1 * 1e3:.3f} mm <= 0")
    if not f2 > 0:
        reasons.append(f"line2 (implant tip path) collides: f_safe = {f2 * 1e3:.3f} mm <= 0")
    return reasons


def default_bounds(fpsm: Fpsm, implant_length: float) -> np.ndarray:
    """d_T from d12 (the implant tip at the hole) to d12 + twice the largest control radius;
    theta_T over a full turn [-pi, pi]."""
    return np.array(
        [
            [implant_length, -np.pi],
            [implant_length + 2.0 * float(np.max(np.abs(fpsm.rho))), np.pi],
        ]
    )


def _check_scalar(value, name: str, *, positive: bool = False) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(name, f"expected a number, got {value!r}") from None
    if not np.isfinite(value) or value < 0 or (positive and value == 0):
        raise InputError(name, f"expected a finite value {'>' if positive else '>='} 0 m")
    return value


def place_instrument(
    fpsm: Fpsm,
    hole_Center_m,
    axis_Center,
    *,
    rod_radius: float,
    implant_length: float,
    objective: str = "eq14",
    bounds=None,
    seed: int = 0,
    particles: int = 30,
    c0: float = 0.8,
    c1: float = 0.3,
    c2: float = 0.4,
    stall_iterations: int = 40,
    max_iterations: int = 1000,
    lambda_avg: float = 0.5,
    lambda_min: float = 0.5,
    hole_tolerance: float = 0.005,
    restarts: int = 3,
    verify: bool = True,
    vf_options: dict | None = None,
    tool: Instrument | None = None,
    safety: SafetySpec | None = None,
    exact=None,
    progress=None,
) -> Placement:
    """Place the feeding target for one implant site by PSO (paper Sec. 4.3).

    Args:
        fpsm: the surrogate model (Center frame).
        hole_Center_m: (3,) implant site t_ch in Center (m); it must lie within the slice range
            and no more than ``hole_tolerance`` outside the model (the site is on the jaw
            surface, which the fitted model stays just inside of).
        axis_Center: (3,) hole axis D_hz, from the bone into the cavity.
        rod_radius: radius r of the handle rod (m), line1 is checked against the model shrunk
            by r (Eq. 12).
        implant_length: d12 (m).
        objective: "eq14" (default), "eq21" or "eq22".
        bounds: ((d_T_min, theta_min), (d_T_max, theta_max)) in (m, rad); default
            :func:`default_bounds`.
        seed: PSO seed.
        restarts: further PSO runs (seeds spawned from ``seed``) while the optimum is not
            collision-free; the best optimum of all runs is kept. 0 = the paper's single run.
        verify: also run the exhaustive grid check (:func:`verify_by_grid`).
        vf_options: keyword arguments for :meth:`VirtualFixture.from_placement` (its
            tolerances default to ``safety``'s).
        tool: the tool body checked by the verification (default: the paper's model with
            ``rod_radius`` and ``implant_length``, :class:`Instrument`).
        safety: the fixture's admissible region (lateral and angle tolerances) and the
            clinical margin: a placement whose verified clearance over that region is below the
            margin is invalid (:func:`verify_placement`). None: ``SafetySpec()``.
        exact: an :class:`systems.placement.exact_clearance.ExactCavity` of the scan for the exact
            check (None: only the certified FPSM bound).
        progress: a Progress-like object (``say``) for the progress lines of a long
            verification (the fixture's region resolved with FCL); None: silent.

    Returns:
        :class:`Placement` (``seconds`` is the PSO time of all runs; loading the compiled
        safety kernel, about 0.1-0.3 s once per process, happens before the clock starts);
        ``valid`` is False (with ``reason``) when a line is unsafe at the
        optimum (f_safe <= 0), which callers report as a planning failure.
    """
    from implantplan.systems.placement.fixture import VirtualFixture

    if not isinstance(fpsm, Fpsm):
        raise InputError("fpsm", "expected an Fpsm")
    if objective not in OBJECTIVES:
        raise InputError("objective", f"expected one of {', '.join(OBJECTIVES)}, got {objective!r}")
    rod_radius = _check_scalar(rod_radius, "rod_radius")
    implant_length = _check_scalar(implant_length, "implant_length", positive=True)
    hole_tolerance = _check_scalar(hole_tolerance, "hole_tolerance")
    if int(restarts) != restarts or restarts < 0:
        raise InputError("restarts", f"expected an integer >= 0, got {restarts!r}")
    restarts = int(restarts)
    if tool is None:
        tool = Instrument.paper(rod_radius=rod_radius, implant_length=implant_length)
    safety = SafetySpec() if safety is None else safety
    if not isinstance(safety, SafetySpec):
        raise InputError("safety", f"expected a SafetySpec, got {type(safety).__name__}")
    X_CH = hole_frame(hole_Center_m, axis_Center)
    t = X_CH[:3, 3]
    z_lo, z_hi = fpsm.z_range
    if not (z_lo <= t[2] <= z_hi):
        raise InputError(
            "hole",
            f"z = {t[2] * 1e3:.3f} mm is outside the model's slices "
            f"[{z_lo * 1e3:.3f}, {z_hi * 1e3:.3f}] mm (Center frame)",
        )
    d_hole = float(fpsm.d_safe(t)[()])
    if d_hole < -hole_tolerance:
        raise InputError(
            "hole",
            f"lies {-d_hole * 1e3:.3f} mm outside the model (tolerance "
            f"{hole_tolerance * 1e3:.3f} mm); expected a site on the cavity wall",
        )
    if bounds is None:
        bounds = default_bounds(fpsm, implant_length)
    bounds = np.asarray(bounds, dtype=float)
    if bounds.shape != (2, 2) or not np.all(np.isfinite(bounds)) or np.any(bounds[1] < bounds[0]):
        raise InputError(
            "bounds", "expected ((d_T_min, theta_min), (d_T_max, theta_max)) with min <= max"
        )

    problem = PlacementProblem(
        fpsm, X_CH, rod_radius, implant_length, objective, lambda_avg, lambda_min
    )
    # The paper runs the PSO once. A swarm can stall on an infeasible plateau (seen on the
    # bundled cavity: one seed ended with the tool above the mouth while a collision-free
    # optimum existed), so when its optimum is not collision-free we run it again with seeds
    # spawned from ``seed`` (at most ``restarts`` more runs) and keep the best optimum.
    problem.evaluate(np.asarray(bounds[0])[None])  # loads the compiled kernel before timing
    entropy = int(seed) if isinstance(seed, (int, np.integer)) else 0
    seeds = np.random.SeedSequence(entropy).spawn(restarts)
    runs, total_it, total_ev, total_s = 0, 0, 0, 0.0
    best = None
    for attempt in range(restarts + 1):
        res = pso(
            problem,
            bounds[0],
            bounds[1],
            particles=particles,
            c0=c0,
            c1=c1,
            c2=c2,
            stall_iterations=stall_iterations,
            max_iterations=max_iterations,
            seed=seed if attempt == 0 else np.random.default_rng(seeds[attempt - 1]),
        )
        runs += 1
        total_it += res.iterations
        total_ev += res.evaluations
        total_s += res.seconds
        if best is None or res.F < best.F:
            best = res
        reasons = _invalid_reasons(problem, best.x)
        if not reasons:
            break
    res = best
    x = res.x
    verification = verify_placement(fpsm, tool_frames(X_CH, x[0], x[1]), tool, safety=safety,
                                    exact=exact, progress=progress)
    search = None
    if (reasons or verification["reasons"]) and exact is not None:
        # the FPSM optimum fails for the instrument (its head, the region): the best grid
        # placement that the scan certifies for the whole instrument
        found, ver, search = search_for_instrument(problem, bounds, tool, safety, exact,
                                                   progress=progress)
        search["rejected_optimum"] = {"d_T": float(x[0]), "theta_T": float(x[1]),
                                      "reason": "; ".join(reasons + verification["reasons"])}
        if found is not None:
            x, verification, reasons = found, ver, []
        else:
            reasons = [refusal(tool, safety, search)] + [
                f"at the FPSM optimum: {r}" for r in reasons + verification["reasons"]]
    verification["instrument_search"] = search
    ev = problem.evaluate(x[None])
    f1, f2 = float(ev.f_safe_line1[0]), float(ev.f_safe_line2[0])
    lines = feeding_lines(X_CH, x[0], x[1], rod_radius, implant_length)
    X_CT = tool_frames(X_CH, x[0], x[1])
    grid = None
    if verify:
        g = verify_by_grid(problem, bounds[0], bounds[1])
        grid = {
            **g,
            "d_T": float(g["x"][0]),
            "theta_T": float(g["x"][1]),
            "distance_d_T": float(abs(g["x"][0] - res.x[0])),
            # angles wrap: -pi and pi are the same rod direction
            "distance_theta_T": float(abs(wrap_angle(g["x"][1] - res.x[1]))),
            "F_pso_minus_grid": float(res.F - g["F"]),
        }
    if search is None or search["F"] is not None:  # a refusal has named the optimum's reasons
        reasons = reasons + verification["reasons"]
    placement = Placement(
        d_T=float(x[0]),
        theta_T=float(x[1]),
        F_safe=float(ev.F[0]),
        f_safe_line1=f1,
        f_safe_line2=f2,
        d_safe_min_line1=float(ev.d_safe_min_line1[0]),
        d_safe_min_line2=float(ev.d_safe_min_line2[0]),
        samples_line1=int(ev.samples_line1[0]),
        samples_line2=int(ev.samples_line2[0]),
        valid=not reasons,
        reason="; ".join(reasons),
        iterations=total_it,
        evaluations=total_ev,
        seconds=total_s,
        stopped=res.stopped,
        history=res.history,
        X_CH=X_CH,
        X_CT=X_CT,
        line1={"start": lines.start1[0], "direction": lines.direction[0], "radius": rod_radius},
        line2={"start": lines.start2[0], "direction": lines.direction[0], "radius": 0.0},
        objective=objective,
        rod_radius=rod_radius,
        implant_length=implant_length,
        bounds=bounds,
        seed=entropy if isinstance(seed, (int, np.integer)) else -1,
        grid=grid,
        settings={
            "particles": particles,
            "c0": c0,
            "c1": c1,
            "c2": c2,
            "stall_iterations": stall_iterations,
            "max_iterations": max_iterations,
            "lambda_avg": lambda_avg,
            "lambda_min": lambda_min,
            "hole_tolerance": hole_tolerance,
            "restarts": restarts,
            "pso_runs": runs,
            "iterations_last_run": res.iterations,
            "bounds_rule": "positions clipped to the bounds, clipped velocity zeroed",
        },
        verification=verification,
    )
    # the fixture guards the region the verification checked: the spec's tolerances
    vf_options = {"lateral_tolerance": safety.lateral_tolerance,
                  "angle_tolerance": safety.angle_tolerance, **(vf_options or {})}
    placement.vf = VirtualFixture.from_placement(placement, fpsm, **vf_options)
    return placement
