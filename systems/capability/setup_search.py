"""Setup optimization with RASSCMAPs (seed 004 Sec. 4.2): the cost of a setup (base pose, access
point) and the search over the candidate grid.

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

import time
from dataclasses import dataclass

import numpy as np

from implantplan.systems.capability.maps import CapabilityMap, golden_spiral
from implantplan.systems.capability.rasscmap import (
    Rasscmap,
    constrained_map,
    surface_points,
    task_margin,
    unconstrained_index,
)
from implantplan.systems.capability.rasscmap_inputs import Patient, Robot, Task, base_candidates
from implantplan.systems.capability.store import RasscmapStore
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.frames import invert, wrap_angle


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
