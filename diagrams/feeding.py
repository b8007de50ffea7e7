"""Seed 001's teleop experiments as cores over the feeding diagram (diagrams.teleop) and the arm's
kinematics (systems.robot.kinematics): K scripted feeds of one case, and the error-mapping circle.

**Feeding** (seed 001 "Experimental validation"): K feeds with independent operator randomness
(systems.teleop.master_device.feeding_runs) on one diagram; joint travel = sum over joints of
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

import dataclasses
from dataclasses import dataclass

import numpy as np

from implantplan.diagrams.teleop import TeleopCase, build_teleop, simulate
from implantplan.systems import actuator
from implantplan.systems.errors import PlanningFailure
from implantplan.systems.fpsm.model import Fpsm
from implantplan.systems.frames import invert, transform
from implantplan.systems.placement.fixture import VirtualFixture
from implantplan.systems.placement.planner import place_instrument
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp
from implantplan.systems.robot.nsga2 import non_dominated_sort
from implantplan.systems.teleop.master_device import Operator, feeding_runs

# -- the case ----------------------------------------------------------------------------------


@dataclass
class Instrument:
    """The instrument side of a case (Center frame, SI)."""

    fpsm: Fpsm
    X_CT: np.ndarray
    vf: VirtualFixture
    rod_radius: float
    implant_length: float
    source: str


def default_instrument(seed: int = 0) -> Instrument:
    """Seed 000's cylinder check (Sec. 5.3) placed on the fly: a cylinder FPSM of radius 50 mm from
    z = 0 to 100 mm, hole (0, -50, 50) mm, axis +y, rod radius 6 mm, d12 31 mm
    (systems.placement.planner
    finds d_T = 62.5 mm, theta_T = 0)."""
    fpsm = Fpsm.cylinder(0.05, 0.0, 0.1, slices=11)
    p = place_instrument(
        fpsm,
        [0.0, -0.05, 0.05],
        [0.0, 1.0, 0.0],
        rod_radius=actuator.ROD_RADIUS,
        implant_length=actuator.IMPLANT_LENGTH,
        seed=seed,
        verify=False,
    )
    if not p.valid:
        raise PlanningFailure(f"default instrument placement invalid: {p.reason}")
    return Instrument(
        fpsm, p.X_CT, p.vf, p.rod_radius, p.implant_length, "cylinder check (seed 000 Sec. 5.3)"
    )


def load_scenario(name: str):
    """The MOPRP scenario (feasibility uses its own actuator model) and the same scenario with
    the plant's TCP (systems.actuator.X_FT), used for every kinematic quantity of the runs."""
    sc = moprp.load_scenario(name)
    return sc, dataclasses.replace(sc, X_FT=actuator.X_FT())


def layout_configurations(sc_plant, xyz, branch: int):
    """(q_pre, q_target) on ``branch`` with the plant's TCP, or None if not reachable."""
    X = moprp.feed_poses(xyz, sc_plant.feed_length, 2)
    r = kin.ik(X, limits=sc_plant.limits, X_FT=sc_plant.X_FT)
    if not np.all(r.valid[:, branch]):
        return None
    return r.q[0, branch], r.q[1, branch]


def make_case(scenario: str, sc_plant, xyz, branch: int, inst: Instrument, label="") -> TeleopCase:
    qs = layout_configurations(sc_plant, xyz, branch)
    if qs is None:
        raise PlanningFailure(
            f"layout {np.round(np.asarray(xyz) * 1000).tolist()} mm: branch {branch} does not "
            "reach the pre-feed and target poses with the actuator's TCP"
        )
    X_WO = sc_plant.X_WO
    return TeleopCase(
        scenario=scenario,
        X_WBase=X_WO @ moprp.base_pose(xyz),
        q_start=qs[0],
        X_WCenter=X_WO @ invert(inst.X_CT),
        fpsm=inst.fpsm,
        vf=inst.vf,
        X_WTarget=X_WO,
        rod_radius=inst.rod_radius,
        implant_length=inst.implant_length,
        limits=sc_plant.limits,
        label=label,
    )


def knee_layout(sc, *, seed: int = 0, candidates: int = 300):
    """(base_xyz in Oral, branch, source): a stand-in for MOPRP's choice, the knee point
    (systems.robot.moprp.knee_point) of the non-dominated set of ``candidates`` random feasible
    bases."""
    rng = np.random.default_rng(seed)
    xyz, F = moprp.random_feasible(sc, candidates, rng)
    if xyz.shape[0] == 0:
        raise PlanningFailure("no feasible base found in the scenario's bounds")
    front = np.flatnonzero(non_dominated_sort(F) == 0)
    k = front[moprp.knee_point(F[front])]
    ev = moprp.evaluate_bases(xyz[k : k + 1], sc, rng)
    return xyz[k], int(ev.branch[0]), f"knee of {xyz.shape[0]} random feasible bases"


# -- the runs ------------------------------------------------------------------------------------


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
    head_motion=None,
) -> dict:
    """K scripted feeds on one case; per-run figures and the overall realtime factor. The runs
    share one diagram (a motion is a context parameter); with ``meshcat`` the first run is shown
    and recorded on a second diagram that has the visualizer.

    ``progress``: anything with ``step(i, n, text)`` (analyses.progress.Progress), or None.
    ``head_motion``: a systems.teleop.head_motion.HeadMotion (the awake patient, every run; the arm
    follows the tracked mouth): the errors are then relative to the moving head, and each run
    says whether the head guard stopped it.
    """
    start = case.X_WE(case.q_start)[:3, 3]
    target = case.X_WTarget[:3, 3]
    motions = feeding_runs(start, target, runs=runs, seed=seed, operator=operator)
    head = {} if head_motion is None else {"head_motion": head_motion}
    teleop = build_teleop(case, mode=mode, **head)  # one diagram for every run; each its motion
    shown = build_teleop(case, mode=mode, meshcat=meshcat, **head) if meshcat is not None else (
        teleop)
    target_C = (invert(case.X_WCenter) @ case.X_WTarget)[:3, 3]
    out = []
    for i, motion in enumerate(motions):
        run = simulate(shown if i == 0 else teleop, motion.duration + FINISH_SECONDS,
                       motion=motion, recording=i == 0 and meshcat is not None)
        err = float(np.linalg.norm(run.p_WE[-1] - target)) if head_motion is None else float(
            np.linalg.norm(run.X_CT[-1, :3, 3] - target_C))  # relative to the moving head
        extra = {} if run.guard is None else {
            "head_guard_stopped": bool(run.guard[-1, 0] > 0.5),
            "head_guard_time": float(run.guard[-1, 2]),
            "max_margin_extra": float(np.max(run.margin_extra)),
        }
        out.append(
            {
                **extra,
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
