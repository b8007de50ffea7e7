"""Benchmark of stage 2 (seed 000, paper Sec. 5.2-5.3): PSO placement time and rod safety.

Run: ``python -m implantplan.analyses.bench_placement [--fpsm FPSM.json --hole-mm X Y Z
--hole-axis DX DY DZ]
[--fpsm-rod-radius-mm R --fpsm-implant-length-mm D] [--rod-radius-mm 6] [--implant-length-mm 31]
[--repeats 5]``. Prints, side by side in one run:

1. PSO placement time on the paper's cylinder check (radius 50 mm, z 0..100 mm, 15 slices x
   15 control points, hole (0, -50, 50) mm, axis +Y; Eq. 14) and on the FPSM file given with
   ``--fpsm`` (site and axis in Center, mm; without ``--hole-mm`` a site on the wall at
   theta = 180 deg, 60 % up the slice range, axis into the cavity tilted towards the opening),
   against the paper's 0.299 s (C++, 76 iterations) and the 0.05 s target; with the result, the
   iterations, the evaluations and the distance to the exhaustive-grid optimum. The PSO is the
   project's numpy Eq. 20 loop around the compiled line-safety kernel (first call compiled or
   loaded from numba's cache before timing). pymoo's PSO is timed beside it when pymoo is
   installed, skipped with a message otherwise.
2. Rod safety (Eq. 13 for a rod of radius r against the shrunk model, Eq. 12) in evaluations
   per second: one batched call over 100,000 random rods (compiled kernel), the same batch
   through the vectorized numpy reference, and a per-rod Python loop calling
   ``Fpsm.line_safety`` once per rod; with the ratios (target >= 100,000 rods/s). The rod
   radius is ``--fpsm-rod-radius-mm`` when an FPSM is given, else ``--rod-radius-mm``.

3. The sound tool clearance beside FCL's exact capsule-vs-mesh collide on the same
   random rods of the real cavity, with Eq. 12 for reference and the whole tool's single-query
   latency (``--sound-rods``, ``--fcl-rods``; ``--no-sound`` skips it).

Timings on a shared 2-core machine are noisy: each figure is the median of ``--repeats`` runs.
"""

from __future__ import annotations

import argparse
import importlib.util
import time

import numpy as np

from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.placement.planner import (
    PlacementProblem,
    default_bounds,
    hole_frame,
    place_instrument,
    verify_by_grid,
)

MM = 1e-3
PAPER_PSO_SECONDS = 0.299  # Sec. 5.2, 76 iterations
TARGET_PSO_SECONDS = 0.05
TARGET_RODS_PER_SECOND = 100_000


def _median(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def auto_site(fpsm: Fpsm) -> tuple[np.ndarray, np.ndarray]:
    """A site on the wall at theta = 180 deg, 60 % up the slices; axis inward, tilted to +Z."""
    z_lo, z_hi = fpsm.z_range
    z = z_lo + 0.6 * (z_hi - z_lo)
    r = float(fpsm.radius_at(np.pi, z))
    return np.array([-r, 0.0, z]), np.array([1.0, 0.0, 0.3])


def bench_case(name, fpsm, hole, axis, rod, d12, repeats) -> dict:
    kw = dict(rod_radius=rod, implant_length=d12, verify=False)
    place_instrument(fpsm, hole, axis, seed=0, **kw)  # warm-up (numba cache)
    runs = [place_instrument(fpsm, hole, axis, seed=s, **kw) for s in range(repeats)]
    seconds = np.array([p.seconds for p in runs])
    problem = PlacementProblem(fpsm, hole_frame(hole, axis), rod, d12)
    b = default_bounds(fpsm, d12)
    t = time.perf_counter()
    grid = verify_by_grid(problem, b[0], b[1])
    grid_s = time.perf_counter() - t
    p = runs[0]
    hits = sum(
        abs(q.d_T - grid["x"][0]) <= 0.1 * MM and abs(q.theta_T - grid["x"][1]) <= np.deg2rad(0.1)
        for q in runs
    )
    return {
        "case": name,
        "pso_s": float(np.median(seconds)),
        "iterations": int(np.median([q.iterations for q in runs])),
        "evaluations": int(np.median([q.evaluations for q in runs])),
        "d_T_mm": p.d_T / MM,
        "theta_T_deg": np.rad2deg(p.theta_T),
        "valid": p.valid,
        "grid_d_T_mm": grid["x"][0] / MM,
        "grid_theta_T_deg": np.rad2deg(grid["x"][1]),
        "hits": f"{hits}/{repeats}",
        "grid_s": grid_s,
    }


def bench_pymoo(fpsm, hole, axis, rod, d12) -> str:
    if importlib.util.find_spec("pymoo") is None:
        return "pymoo is not installed: its PSO is not timed (pip install pymoo to compare)"
    from pymoo.algorithms.soo.nonconvex.pso import PSO
    from pymoo.core.problem import Problem
    from pymoo.optimize import minimize

    problem = PlacementProblem(fpsm, hole_frame(hole, axis), rod, d12)
    b = default_bounds(fpsm, d12)

    class _P(Problem):
        def __init__(self):
            super().__init__(n_var=2, n_obj=1, xl=b[0], xu=b[1])

        def _evaluate(self, x, out, *args, **kwargs):
            out["F"] = problem(x)

    t = time.perf_counter()
    res = minimize(_P(), PSO(pop_size=30), ("n_gen", 100), seed=0, verbose=False)
    s = time.perf_counter() - t
    return (
        f"pymoo PSO (30 particles x 100 generations): {s:.3f} s, d_T = "
        f"{res.X[0] / MM:.3f} mm, theta_T = {np.rad2deg(res.X[1]):.3f} deg"
    )


def bench_rods(fpsm: Fpsm, rod: float, n: int, loop_n: int, repeats: int) -> dict:
    rng = np.random.default_rng(0)
    z_lo, z_hi = fpsm.z_range
    R = float(np.max(fpsm.rho))
    r = rng.uniform(0, 0.8 * R, n)
    a = rng.uniform(0, 2 * np.pi, n)
    start = np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(z_lo, z_hi, n)], axis=1)
    u = rng.normal(size=(n, 3)) + [0, 0, 1.5]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    L = np.full(n, np.inf)
    fpsm.line_safety(start[:10], u[:10], radius=rod)  # warm-up
    t_kernel, ls = _median(lambda: fpsm.line_safety(start, u, radius=rod), repeats)
    t_numpy, ref = _median(
        lambda: fpsm._line_safety_numpy(start, u, L, rod, 0.5, 0.5), max(1, repeats // 2)
    )
    agree = np.allclose(ls.f_safe, ref.f_safe, rtol=1e-12, atol=1e-14)
    m = min(loop_n, n)
    t = time.perf_counter()
    for k in range(m):
        fpsm.line_safety(start[k], u[k], radius=rod)
    t_loop = (time.perf_counter() - t) / m
    return {
        "rods": n,
        "kernel_per_s": n / t_kernel,
        "numpy_per_s": n / t_numpy,
        "loop_per_s": 1.0 / t_loop,
        "agree": agree,
        "safe_fraction": float(np.mean(ls.f_safe > 0)),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m implantplan.analyses.bench_placement", description=__doc__
    )
    ap.add_argument("--fpsm", default=None, help="an FPSM JSON to time beside the cylinder")
    ap.add_argument("--hole-mm", nargs=3, type=float, default=None, metavar=("X", "Y", "Z"))
    ap.add_argument("--hole-axis", nargs=3, type=float, default=None, metavar=("DX", "DY", "DZ"))
    ap.add_argument("--rod-radius-mm", type=float, default=6.0)
    ap.add_argument("--implant-length-mm", type=float, default=31.0)
    ap.add_argument("--fpsm-rod-radius-mm", type=float, default=None, help="for --fpsm only")
    ap.add_argument("--fpsm-implant-length-mm", type=float, default=None, help="for --fpsm only")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rods", type=int, default=100_000)
    ap.add_argument("--loop-rods", type=int, default=3_000)
    ap.add_argument("--sound-rods", type=int, default=100_000)
    ap.add_argument("--fcl-rods", type=int, default=20_000)
    ap.add_argument("--no-sound", action="store_true", help="skip the sound-vs-FCL section")
    args = ap.parse_args(argv)
    rod, d12 = args.rod_radius_mm * MM, args.implant_length_mm * MM

    cyl = Fpsm.cylinder(50 * MM, 0.0, 100 * MM, 15, 15)
    cases = [
        ("cylinder (Sec. 5.3)", cyl, np.array([0, -50, 50]) * MM, np.array([0, 1.0, 0]), rod, d12)
    ]
    custom = None
    if args.fpsm:
        custom = Fpsm.load(args.fpsm)
        hole, axis = auto_site(custom)
        if args.hole_mm is not None:
            hole = np.asarray(args.hole_mm) * MM
        if args.hole_axis is not None:
            axis = np.asarray(args.hole_axis, dtype=float)
        c_rod = rod if args.fpsm_rod_radius_mm is None else args.fpsm_rod_radius_mm * MM
        c_d12 = d12 if args.fpsm_implant_length_mm is None else args.fpsm_implant_length_mm * MM
        cases.append((f"{args.fpsm}", custom, hole, axis, c_rod, c_d12))

    print(f"== PSO placement (Eq. 14, 30 particles, median of {args.repeats} seeds) ==")
    head = (
        f"{'case':<28} {'rod_mm':>6} {'d12_mm':>6} {'pso_ms':>8} {'paper/pso':>9} "
        f"{'iters':>6} {'evals':>6} "
        f"{'d_T_mm':>8} {'theta_deg':>9} {'valid':>5} {'grid_d_T':>8} {'grid_th':>8} "
        f"{'hits':>5} {'grid_ms':>8}"
    )
    print(head)
    for name, f, hole, axis, c_rod, c_d12 in cases:
        r = bench_case(name, f, hole, axis, c_rod, c_d12, args.repeats)
        print(
            f"{name[-28:]:<28} {c_rod / MM:6.1f} {c_d12 / MM:6.1f} {r['pso_s'] * 1e3:8.1f} "
            f"{PAPER_PSO_SECONDS / r['pso_s']:9.1f} "
            f"{r['iterations']:6d} {r['evaluations']:6d} {r['d_T_mm']:8.3f} "
            f"{r['theta_T_deg']:9.3f} {str(r['valid']):>5} {r['grid_d_T_mm']:8.3f} "
            f"{r['grid_theta_T_deg']:8.3f} {r['hits']:>5} {r['grid_s'] * 1e3:8.1f}"
        )
    print(
        f"paper: {PAPER_PSO_SECONDS} s (C++, 76 iterations); target < {TARGET_PSO_SECONDS} s; "
        "hits = seeds within 0.1 mm / 0.1 deg of the grid optimum"
    )
    print(bench_pymoo(cyl, cases[0][2], cases[0][3], rod, d12))

    print("\n== rod safety (Eq. 12-13), evaluations per second ==")
    print(
        f"{'model':<28} {'rod_mm':>6} {'batched':>12} {'numpy':>12} {'py loop':>10} "
        f"{'batch/loop':>10} "
        f"{'numpy/loop':>10} {'agree':>5} {'safe':>5}"
    )
    models = [("cylinder 15x15", cyl, rod)]
    if custom is not None:
        models.append((args.fpsm, custom, cases[-1][4]))
    for name, f, m_rod in models:
        r = bench_rods(f, m_rod, args.rods, args.loop_rods, args.repeats)
        print(
            f"{name[-28:]:<28} {m_rod / MM:6.1f} {r['kernel_per_s']:12,.0f} "
            f"{r['numpy_per_s']:12,.0f} "
            f"{r['loop_per_s']:10,.0f} {r['kernel_per_s'] / r['loop_per_s']:10.1f} "
            f"{r['numpy_per_s'] / r['loop_per_s']:10.1f} {str(r['agree']):>5} "
            f"{r['safe_fraction']:5.2f}"
        )
    print(
        f"target >= {TARGET_RODS_PER_SECOND:,} rods/s (batched); batch of {args.rods:,} "
        f"random rods, loop over {args.loop_rods:,}"
    )
    if not args.no_sound:
        print(bench_sound(args.sound_rods, args.fcl_rods, args.repeats))
    return 0


TARGET_SOUND_PER_SECOND = 500_000
TARGET_SOUND_OVER_FCL = 20.0


def bench_sound(n: int, n_fcl: int, repeats: int) -> str:
    """The sound clearance beside FCL's exact capsule-vs-mesh collide on the same
    rods of the default case's real cavity (analyses.studies.rod_check's random rods), and the
    single-query latency of the whole tool (the 200 Hz / 1 kHz path)."""
    import os

    from implantplan.analyses.studies import rod_check
    from implantplan.systems.instrument import Instrument
    from implantplan.systems.placement.tool_clearance import ToolClearance, rod_clearance, rod_safe

    v = rod_check.make_variants(("real",))[0]
    p0, p1, r = rod_check.random_rods(v.fpsm, n, seed=0)
    t = time.perf_counter()
    rod_clearance(v.fpsm, p0[:2], p1[:2], r[:2])  # the field is built (and the kernel loaded)
    build = time.perf_counter() - t
    sound_s, c = _median(lambda: rod_clearance(v.fpsm, p0, p1, r), repeats)
    rod_safe(v.fpsm, p0[:2], p1[:2], r[:2])
    verdict_s, safe = _median(lambda: rod_safe(v.fpsm, p0, p1, r), repeats)
    if not np.array_equal(safe, c > 0):  # the same verdict, or the speed means nothing
        raise AssertionError("rod_safe disagrees with rod_clearance > 0")
    k = min(n_fcl, n)
    fcl_s, hit = _median(lambda: v.exact.capsule_collides(p0[:k], p1[:k], r[:k]), 1)
    paper_s, _ = _median(lambda: rod_clearance(v.fpsm, p0, p1, r, method="paper"), repeats)
    sound_rate, fcl_rate, paper_rate = n / sound_s, k / fcl_s, n / paper_s
    verdict_rate = n / verdict_s
    tc = ToolClearance(v.fpsm, Instrument.paper())
    X = np.eye(4)
    X[:3, 0] = [0, 0, 1]  # the rod out of the mouth (Center +z), the implant along -x
    X[:3, 2] = [-1, 0, 0]
    X[:3, 1] = np.cross(X[:3, 2], X[:3, 0])
    X[:3, 3] = [0, 0, 0.03]
    tc.one(X)
    one_s, _ = _median(lambda: [tc.one(X) for _ in range(1000)], repeats)
    safe_fcl = int(np.sum((c[:k] > 0) & hit))
    return "\n".join([
        "\n== sound tool clearance vs FCL exact collide, same rods ==",
        f"load average {os.getloadavg()[0]:.2f}; real cavity, {n:,} rods (radius 2-8 mm, "
        f"within 60 deg of the opening axis, half near the walls); FCL on the first {k:,}",
        f"field build (once per FPSM): {build:.2f} s",
        f"sound verdict (rod_safe, the timed target): {verdict_rate:12,.0f} rods/s (target >= "
        f"{TARGET_SOUND_PER_SECOND:,}); {verdict_rate / fcl_rate:.1f} x FCL (target >= "
        f"{TARGET_SOUND_OVER_FCL:g} x); the same verdicts as the signed bound",
        f"sound signed bound (rod_clearance): {sound_rate:12,.0f} rods/s; "
        f"{sound_rate / fcl_rate:.1f} x FCL",
        f"Eq. 12 batched: {paper_rate:11,.0f} rods/s",
        f"FCL collide:   {fcl_rate:12,.0f} rods/s (Coal, one call per rod)",
        f"whole tool, single query (ToolClearance.one): {one_s / 1000 * 1e6:.1f} us",
        f"rods called safe by the sound bound that FCL says collide: {safe_fcl} of {k:,}",
    ])


if __name__ == "__main__":
    raise SystemExit(main())
