"""Seed 001's teleop experiments as cores over the feeding diagram (diagrams.teleop) and the arm's
kinematics (systems.kinematics): K scripted feeds of one case, and the error-mapping circle.

**Feeding** (seed 001 "Experimental validation"): K feeds with independent operator randomness
(systems.master_device.feeding_runs) on one diagram; joint travel = sum over joints of
integrated |qdot| (seed 001 Eq. 23).

**Error mapping**: a circle of radius 25 mm at 10 mm/s about the target, in the plane across the
feed (Oral Y-Z), tool orientation fixed, joints on the layout's branch by closed-form IK; the
executed joints carry an injected error, and the path error is the mean distance between executed
and desired TCP positions.

**Joint error model** (seeded; the paper only says "joint error"): per joint, a constant offset
N(0, (eps/2)^2) (calibration), a backlash of eps/4 against the direction of motion, and a smooth
servo error of RMS eps/4 (Gaussian noise smoothed over 0.5 s), with eps the scenario's joint error
radius (0.1 deg). The same R realizations are applied to every layout, so layouts differ only by
how their configurations map joint error to the tool.

The circle is followed on the layout's IK branch with the +-360 deg joint range (the production
variant, DESIGN.md section 8): near the target the wrist often sits close to +-175 deg, and the
probe is about how joint error maps to the tool, not about the stop.

Departure: the error-mapping test runs on the kinematics core, not in the Drake diagram: the
injected error is a joint-space perturbation of a commanded path, which is exactly forward
kinematics of the perturbed joints; the diagram adds nothing but cost there.
"""

from __future__ import annotations

import numpy as np

from implantplan.diagrams.teleop import TeleopCase, build_teleop, simulate
from implantplan.systems import kinematics as kin
from implantplan.systems import moprp
from implantplan.systems.frames import invert, transform
from implantplan.systems.master_device import Operator, feeding_runs

FINISH_SECONDS = 2.0  # simulated time after the script for the operator to finish by eye
TARGET_TOLERANCE = 0.001  # m: the feed "reaches the target" within this
CIRCLE_LIMITS = "360"  # the circle probes error mapping; a +-175 deg wrist stop must not cut it


def run_feeding(
    case: TeleopCase,
    *,
    runs: int = 10,
    seed: int = 0,
    mode: str = "kinematic",
    operator: Operator | None = None,
    meshcat=None,
    progress=None,
) -> dict:
    """K scripted feeds on one case; per-run figures and the overall realtime factor.

    ``progress``: anything with ``step(i, n, text)`` (analyses.progress.Progress), or None.
    """
    start = case.X_WE(case.q_start)[:3, 3]
    target = case.X_WTarget[:3, 3]
    motions = feeding_runs(start, target, runs=runs, seed=seed, operator=operator)
    out = []
    for i, motion in enumerate(motions):
        teleop = build_teleop(case, motion, mode=mode, meshcat=meshcat if i == 0 else None)
        run = simulate(teleop, motion.duration + FINISH_SECONDS, recording=meshcat is not None)
        err = float(np.linalg.norm(run.p_WE[-1] - target))
        out.append(
            {
                "joint_travel": run.joint_travel,
                "min_d_safe": float(np.min(run.min_d_safe)),
                "max_vf_violation": float(np.max(run.violation)),
                "collision_alarm": bool(np.any(run.alarm)),
                "final_error": err,
                "reached_target": err <= TARGET_TOLERANCE,
                "sim_seconds": run.sim_seconds,
                "wall_seconds": run.wall_seconds,
                "travel_curve": _travel_curve(run),
            }
        )
        if progress is not None:
            progress.step(i, len(motions), f"run travel {run.joint_travel:.3f} rad")
    sim = sum(r["sim_seconds"] for r in out)
    wall = sum(r["wall_seconds"] for r in out)
    return {"runs": out, "realtime_factor": sim / wall if wall > 0 else float("inf")}


def _travel_curve(run, points: int = 50) -> dict:
    """Cumulative joint travel against time, resampled (seed 001 Fig. 12c)."""
    cum = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(run.q, axis=0)).sum(axis=1))])
    t = np.linspace(run.t[0], run.t[-1], points)
    return {"t": t, "joint_travel": np.interp(t, run.t, cum)}


def circle_path(radius=0.025, speed=0.010, dt=0.01):
    """(t, offsets in Oral (n, 3)): one turn in the Oral Y-Z plane starting at +Y."""
    T = 2 * np.pi * radius / speed
    t = np.arange(int(np.ceil(T / dt)) + 1) * dt
    a = 2 * np.pi * t / T
    return t, np.stack([np.zeros_like(a), radius * np.cos(a), radius * np.sin(a)], axis=1)


def joint_error(q_path, t, eps: float, realizations: int, seed: int) -> np.ndarray:
    """Injected joint errors (R, n, 6) for a joint path (n, 6) (the model in the docstring)."""
    rng = np.random.default_rng(seed)
    n = t.size
    dt = float(t[1] - t[0])
    offset = rng.normal(0.0, eps / 2, (realizations, 1, 6))
    qdot = np.gradient(q_path, dt, axis=0)
    backlash = -(eps / 4) * np.tanh(qdot / 1e-4)[None]
    corr = max(int(round(0.5 / dt)), 1)
    kernel = np.exp(-0.5 * (np.arange(-3 * corr, 3 * corr + 1) / corr) ** 2)
    noise = rng.standard_normal((realizations, n + kernel.size - 1, 6))
    smooth = np.apply_along_axis(lambda x: np.convolve(x, kernel, mode="valid"), 1, noise)
    smooth *= (eps / 4) / np.sqrt(np.mean(smooth**2))
    return offset + backlash + smooth


def run_circle(sc_plant, xyz, branch: int, *, realizations=10, seed=0, radius=0.025, speed=0.01):
    """Path error of the circle on one layout; None where the branch cannot follow it."""
    t, d_O = circle_path(radius, speed)
    X_OE = moprp.R_OE
    X_BO = invert(moprp.base_pose(xyz))
    X_OEs = transform(np.broadcast_to(X_OE, (t.size, 3, 3)), d_O)
    r = kin.ik(X_BO @ X_OEs, limits=CIRCLE_LIMITS, X_FT=sc_plant.X_FT)
    if not np.all(r.valid[:, branch]):
        return None
    q = np.unwrap(r.q[:, branch], axis=0)
    if np.abs(np.diff(q, axis=0)).max() > np.deg2rad(5):
        return None  # the branch flips on the way: not a continuous path
    dq = joint_error(q, t, sc_plant.eps, realizations, seed)
    p_des = kin.fk(q, sc_plant.X_FT)[:, :3, 3]
    p_exe = kin.fk(q[None] + dq, sc_plant.X_FT)[..., :3, 3]
    dev = np.linalg.norm(p_exe - p_des[None], axis=-1)  # (R, n)
    return {
        "path_error_mean": float(dev.mean()),
        "path_error_max": float(dev.max()),
        "per_realization": dev.mean(axis=1),
        "joint_travel": float(np.abs(np.diff(q, axis=0)).sum()),
        "samples": int(t.size),
    }
