"""Teleoperated-feeding experiments of seed 001 ("Experimental validation") on the Drake diagram.

Commands::

    implantplan simulate feeding [--plan placement.json | --scenario lying|sitting]
        [--robot-placement placement.json] [--runs K] [--seed S] [--mode kinematic|dynamic]
        [--meshcat-html FILE] --out DIR
    implantplan simulate circle  [same case options] [--realizations R] --out DIR
    implantplan analyze layouts  [same case options] [--random N] [--runs K] --out DIR

**The case.** The instrument side (FPSM, feeding target X_CT, virtual fixture) comes from
``--plan`` (an ``implantplan instrument place`` result: its ``X_CT``, ``vf``, ``rod_radius``,
``implant_length`` and the FPSM it names in ``fpsm`` or ``inputs.fpsm``, a file or the model).
Without a plan the default case is seed 000's cylinder check (Sec. 5.3): a cylinder FPSM of
radius 50 mm from z = 0 to 100 mm (opening at 100 mm), hole (0, -50, 50) mm, axis +y, rod radius
6 mm, d12 31 mm, placed on the fly by systems.placement (d_T = 62.5 mm, theta_T = 0). The room
comes from the MOPRP scenario (``--scenario``, default lying): Oral (= the feeding target, seed
000's Tool frame) at the scenario's X_WO, so Center sits at X_WO X_CT^-1. The base layout comes
from ``--robot-placement`` (an ``implantplan robot place`` result: ``selected.base_xyz`` and
``selected.branch``); without it we pick a stand-in for MOPRP's choice: the knee point
(systems.moprp.knee_point) of the non-dominated set of 300 random feasible bases.

The arm starts at the pre-feed pose (the TCP backed out along the rod by the scenario's feed
length) on the layout's branch, and the scripted operator (systems.master_device) feeds it to
the target through the virtual fixture.

**Experiments.** (a) feeding: K feeds with independent operator randomness; joint travel = sum
over joints of integrated |qdot| (seed 001 Eq. 23). (b) error mapping: a circle of radius 25 mm
at 10 mm/s about the target, in the plane across the feed (Oral Y-Z), tool orientation fixed,
joints on the layout's branch by closed-form IK; the executed joints carry an injected error
(the model below), and the path error is the mean distance between executed and desired TCP
positions. (c) GII over 100 poses about Oral (systems.moprp.gii). (d) the selected layout against
N random feasible ones on (a)-(c): bars and distributions (seed 001 Figs. 11, 13, 14) and ranks.

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

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from implantplan.analyses.progress import Progress
from implantplan.diagrams import tools
from implantplan.diagrams.teleop import TeleopCase, build_teleop, simulate
from implantplan.systems import kinematics as kin
from implantplan.systems import moprp
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.files import read_json, write_json, write_text_atomic
from implantplan.systems.fpsm import Fpsm
from implantplan.systems.frames import invert, transform
from implantplan.systems.master_device import Operator, feeding_runs
from implantplan.systems.placement import place_instrument
from implantplan.systems.virtual_fixture import VirtualFixture

FINISH_SECONDS = 2.0  # simulated time after the script for the operator to finish by eye
TARGET_TOLERANCE = 0.001  # m: the feed "reaches the target" within this
CIRCLE_LIMITS = "360"  # the circle probes error mapping; a +-175 deg wrist stop must not cut it


# --------------------------------------------------------------------------------------------
# The case
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Instrument:
    """The instrument side of a case (Center frame, SI)."""

    fpsm: Fpsm
    X_CT: np.ndarray
    vf: VirtualFixture
    rod_radius: float
    implant_length: float
    source: str


def default_instrument(seed: int = 0) -> Instrument:
    """Seed 000's cylinder check placed on the fly (see the module docstring)."""
    fpsm = Fpsm.cylinder(0.05, 0.0, 0.1, slices=11)
    p = place_instrument(
        fpsm,
        [0.0, -0.05, 0.05],
        [0.0, 1.0, 0.0],
        rod_radius=tools.ROD_RADIUS,
        implant_length=tools.IMPLANT_LENGTH,
        seed=seed,
        verify=False,
    )
    if not p.valid:
        raise PlanningFailure(f"default instrument placement invalid: {p.reason}")
    return Instrument(
        fpsm, p.X_CT, p.vf, p.rod_radius, p.implant_length, "cylinder check (seed 000 Sec. 5.3)"
    )


def instrument_from_plan(path) -> Instrument:
    """Read an ``instrument place`` result (kind "placement") and the FPSM file it names."""
    path = Path(path)
    data = read_json(path, kind="placement", field="--plan")
    for key in ("X_CT", "vf"):
        if data.get(key) is None:
            raise InputError("--plan", f"{path}: missing {key!r}")
    ref = data.get("fpsm") or (data.get("inputs") or {}).get("fpsm")
    if isinstance(ref, dict):
        fpsm = Fpsm.from_dict(ref)
    elif isinstance(ref, str):
        fpsm_path = Path(ref)
        if not fpsm_path.is_absolute() and not fpsm_path.exists():
            fpsm_path = path.parent / fpsm_path
        fpsm = Fpsm.load(fpsm_path, field="--plan fpsm")
    else:
        raise InputError("--plan", f"{path}: expected 'fpsm' or 'inputs.fpsm' (file or model)")
    X_CT = np.asarray(data["X_CT"], dtype=float)
    if X_CT.shape != (4, 4):
        raise InputError("--plan", f"{path}: X_CT must be a 4x4 pose")
    return Instrument(
        fpsm,
        X_CT,
        VirtualFixture.from_dict(data["vf"]),
        float(data.get("rod_radius", tools.ROD_RADIUS)),
        float(data.get("implant_length", tools.IMPLANT_LENGTH)),
        str(path),
    )


def load_scenario(name: str):
    """The MOPRP scenario (feasibility uses its own actuator model) and the same scenario with
    the plant's TCP (diagrams.tools.X_FT), used for every kinematic quantity of the runs."""
    sc = moprp.load_scenario(name)
    return sc, dataclasses.replace(sc, X_FT=tools.X_FT())


def select_layout(sc, *, seed: int = 0, robot_placement=None, candidates: int = 300):
    """(base_xyz in Oral, branch, source): from a robot placement file, or the knee point of the
    non-dominated set of ``candidates`` random feasible bases."""
    if robot_placement is not None:
        data = read_json(robot_placement, kind="robot_placement", field="--robot-placement")
        sel = data.get("selected") or {}
        if "base_xyz" not in sel or "branch" not in sel:
            raise InputError("--robot-placement", "expected selected.base_xyz and .branch")
        return np.asarray(sel["base_xyz"], dtype=float), int(sel["branch"]), str(robot_placement)
    rng = np.random.default_rng(seed)
    xyz, F = moprp.random_feasible(sc, candidates, rng)
    if xyz.shape[0] == 0:
        raise PlanningFailure("no feasible base found in the scenario's bounds")
    dominated = np.array(
        [np.any(np.all(F <= f, axis=1) & np.any(F < f, axis=1)) for f in F]
    )
    front = np.flatnonzero(~dominated)
    k = front[moprp.knee_point(F[front])]
    ev = moprp.evaluate_bases(xyz[k : k + 1], sc, rng)
    return xyz[k], int(ev.branch[0]), f"knee of {xyz.shape[0]} random feasible bases"


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


# --------------------------------------------------------------------------------------------
# (a) feeding
# --------------------------------------------------------------------------------------------


def run_feeding(
    case: TeleopCase,
    *,
    runs: int = 10,
    seed: int = 0,
    mode: str = "kinematic",
    operator: Operator | None = None,
    meshcat=None,
    progress: Progress | None = None,
) -> dict:
    """K scripted feeds on one case; per-run figures and the overall realtime factor."""
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


# --------------------------------------------------------------------------------------------
# (b) error mapping: the circle
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# (d) layouts
# --------------------------------------------------------------------------------------------


def rank_of_first(values, *, higher_is_better=False) -> int:
    """1-based rank of entry 0 among ``values`` (ties count in its favour)."""
    v = np.asarray(values, dtype=float)
    better = v[1:] > v[0] if higher_is_better else v[1:] < v[0]
    return int(1 + np.sum(better))


def analyze_layouts(
    scenario: str,
    inst: Instrument,
    *,
    random_layouts: int = 20,
    runs: int = 10,
    seed: int = 0,
    robot_placement=None,
    realizations: int = 10,
    operator: Operator | None = None,
    progress: Progress | None = None,
) -> dict:
    """The selected layout against ``random_layouts`` random feasible ones on (a)-(c)."""
    sc, sc_plant = load_scenario(scenario)
    scene = _scene_name(sc)
    xyz_sel, b_sel, source = select_layout(sc, seed=seed, robot_placement=robot_placement)
    rng = np.random.default_rng(seed + 1)
    xyz_r, _ = moprp.random_feasible(sc, 4 * random_layouts, rng)
    ev = moprp.evaluate_bases(xyz_r, sc, rng)
    layouts = [("win", xyz_sel, b_sel)]
    for x, b in zip(xyz_r, ev.branch, strict=True):
        if len(layouts) > random_layouts:
            break
        if b >= 0 and layout_configurations(sc_plant, x, int(b)) is not None:
            if run_circle(sc_plant, x, int(b), realizations=1, seed=seed) is not None:
                layouts.append((str(len(layouts)), x, int(b)))
    entries = []
    for i, (label, x, b) in enumerate(layouts):
        case = make_case(scene, sc_plant, x, b, inst, label=label)
        feed = run_feeding(case, runs=runs, seed=seed, operator=operator)
        circle = run_circle(sc_plant, x, b, realizations=realizations, seed=seed)
        g = moprp.gii(x, b, sc_plant, np.random.default_rng(seed), n=100)
        travel = np.array([r["joint_travel"] for r in feed["runs"]])
        entries.append(
            {
                "label": label,
                "base_xyz": x,
                "branch": b,
                "joint_travel_runs": travel,
                "joint_travel_mean": float(travel.mean()),
                "path_error_realizations": None if circle is None else circle["per_realization"],
                "path_error_mean": np.nan if circle is None else circle["path_error_mean"],
                "gii": g["gii"],
                "gii_reached": g["reached"],
                "max_vf_violation": max(r["max_vf_violation"] for r in feed["runs"]),
                "collision_alarm": any(r["collision_alarm"] for r in feed["runs"]),
                "realtime_factor": feed["realtime_factor"],
            }
        )
        if progress is not None:
            progress.step(i, len(layouts), f"layout {label}")
    ranks = {
        "joint_travel": rank_of_first([e["joint_travel_mean"] for e in entries]),
        "path_error": rank_of_first([e["path_error_mean"] for e in entries]),
        "gii": rank_of_first([e["gii"] for e in entries], higher_is_better=True),
    }
    return {
        "scenario": scenario,
        "instrument": inst.source,
        "selected_source": source,
        "layouts": entries,
        "ranks": ranks,
        "of": len(entries),
        "runs_per_layout": runs,
        "operator": dataclasses.asdict(operator or Operator()),
        "seed": seed,
    }


# --------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------


def plot_layouts(result: dict, out_dir) -> list[Path]:
    """Bars of the means and distributions per layout (seed 001 Figs. 11, 13, 14)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    entries = result["layouts"]
    labels = [e["label"] for e in entries]
    colors = ["tab:red"] + ["tab:gray"] * (len(entries) - 1)
    paths = []
    specs = [
        ("path_error", "path_error_mean", "path_error_realizations", 1000.0,
         "mean path error (mm)", "Error mapping: circle r 25 mm at 10 mm/s (cf. seed 001 Fig. 11)"),
        ("joint_travel", "joint_travel_mean", "joint_travel_runs", 1.0,
         "joint travel (rad)", "Joint variation over the feeds (cf. seed 001 Fig. 13)"),
    ]
    for name, mean_key, dist_key, scale, ylabel, title in specs:
        fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        means = np.array([e[mean_key] for e in entries], dtype=float) * scale
        ax1.bar(range(len(entries)), means, color=colors)
        ax1.set_ylabel(ylabel)
        ax1.set_title(title + f"  rank of 'win': {result['ranks'][name]}/{len(entries)}")
        data = [
            np.asarray(e[dist_key], dtype=float) * scale if e[dist_key] is not None else []
            for e in entries
        ]
        ax2.boxplot(data, positions=range(len(entries)))
        ax2.set_ylabel(ylabel)
        ax2.set_xticks(range(len(entries)), labels)
        ax2.set_xlabel("layout ('win' = selected)")
        fig.tight_layout()
        path = out_dir / f"layouts_{name}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    fig, ax = plt.subplots(figsize=(9, 3.5))
    ax.bar(range(len(entries)), [e["gii"] for e in entries], color=colors)
    ax.set_xticks(range(len(entries)), labels)
    ax.set_ylabel("GII")
    ax.set_title(
        f"GII over 100 poses (cf. seed 001 Fig. 14)  rank of 'win': "
        f"{result['ranks']['gii']}/{len(entries)}"
    )
    fig.tight_layout()
    path = out_dir / "layouts_gii.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    paths.append(path)
    return paths


def plot_feeding(result: dict, out_dir) -> Path:
    """Cumulative joint travel of every run (seed 001 Fig. 12c)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for i, r in enumerate(result["runs"]):
        c = r["travel_curve"]
        ax.plot(c["t"], c["joint_travel"], lw=1, label=f"run {i}" if i < 10 else None)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("cumulative joint travel (rad)")
    ax.set_title("Joint swing during the feeds")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    path = Path(out_dir) / "feeding_travel.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_circle(sc_plant, xyz, branch, result, out_dir, seed=0) -> Path:
    """Desired and executed circle (first realization), magnified error (seed 001 Fig. 10)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, d_O = circle_path()
    X_OEs = transform(np.broadcast_to(moprp.R_OE, (t.size, 3, 3)), d_O)
    X_BO = invert(moprp.base_pose(xyz))
    r = kin.ik(X_BO @ X_OEs, limits=CIRCLE_LIMITS, X_FT=sc_plant.X_FT)
    q = np.unwrap(r.q[:, branch], axis=0)
    dq = joint_error(q, t, sc_plant.eps, 1, seed)[0]
    X_OB = moprp.base_pose(xyz)
    p_des = (X_OB @ kin.fk(q, sc_plant.X_FT))[:, :3, 3]
    p_exe = (X_OB @ kin.fk(q + dq, sc_plant.X_FT))[:, :3, 3]
    gain = 20.0
    p_mag = p_des + gain * (p_exe - p_des)
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.plot(1000 * p_des[:, 1], 1000 * p_des[:, 2], "k-", label="desired")
    ax.plot(1000 * p_mag[:, 1], 1000 * p_mag[:, 2], "r-", lw=1, label=f"executed (error x{gain:g})")
    ax.set_aspect("equal")
    ax.set_xlabel("Oral Y (mm)")
    ax.set_ylabel("Oral Z (mm)")
    ax.set_title(f"mean path error {1000 * result['path_error_mean']:.3f} mm")
    ax.legend()
    fig.tight_layout()
    path = Path(out_dir) / "circle.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------


def _case_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plan", type=Path, help="instrument placement JSON (instrument place)")
    p.add_argument(
        "--scenario", default="lying", help="MOPRP scenario: lying, sitting (default lying)"
    )
    p.add_argument(
        "--robot-placement", type=Path, help="robot placement JSON (robot place) for the layout"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def _operator_options(p: argparse.ArgumentParser) -> None:
    d = Operator()
    p.add_argument("--tremor-mm", type=float, default=1000 * d.tremor,
                   help=f"operator tremor amplitude, ~9 Hz (default {1000 * d.tremor:g} mm)")
    p.add_argument("--drift-mm", type=float, default=1000 * d.drift,
                   help=f"operator lateral drift RMS (default {1000 * d.drift:g} mm)")


def _operator(args) -> Operator:
    return dataclasses.replace(Operator(), tremor=args.tremor_mm / 1000, drift=args.drift_mm / 1000)


def register(subparsers) -> None:
    sim = subparsers.add_parser("simulate", help="teleoperated-feeding simulations (seed 001)")
    sub = sim.add_subparsers(dest="simulate_command", required=True, metavar="EXPERIMENT")
    p = sub.add_parser("feeding", help="K scripted feeds through the virtual fixture")
    _case_options(p)
    p.add_argument("--runs", type=int, default=10, help="feeds (default 10, the paper's)")
    p.add_argument("--mode", default="kinematic", choices=("kinematic", "dynamic"))
    p.add_argument("--meshcat-html", type=Path, help="write a static HTML replay of run 0")
    _operator_options(p)
    p.set_defaults(func=cmd_feeding)
    p = sub.add_parser("circle", help="circle r 25 mm at 10 mm/s with injected joint error")
    _case_options(p)
    p.add_argument("--realizations", type=int, default=10, help="joint error draws (default 10)")
    p.set_defaults(func=cmd_circle)

    ana = subparsers.add_parser("analyze", help="offline analyses of layouts")
    sub = ana.add_subparsers(dest="analyze_command", required=True, metavar="ANALYSIS")
    p = sub.add_parser("layouts", help="selected layout vs random feasible ones (Figs. 11, 13, 14)")
    _case_options(p)
    p.add_argument("--random", type=int, default=20, help="random layouts (default 20)")
    p.add_argument("--runs", type=int, default=10, help="feeds per layout (default 10)")
    p.add_argument("--realizations", type=int, default=10, help="joint error draws (default 10)")
    _operator_options(p)
    p.set_defaults(func=cmd_layouts)


def _check_count(value: int, name: str, lo: int = 1) -> None:
    if value < lo:
        raise InputError(name, f"expected an integer >= {lo}, got {value}")


def _setup(args):
    if args.scenario not in moprp.BUNDLED and not Path(args.scenario).is_file():
        raise InputError(
            "--scenario", f"expected lying, sitting or a YAML file, got {args.scenario!r}"
        )
    inst = instrument_from_plan(args.plan) if args.plan else default_instrument(args.seed)
    sc, sc_plant = load_scenario(args.scenario)
    return inst, sc, sc_plant


def _scene_name(sc) -> str:
    return sc.posture if sc.posture in ("lying", "sitting") else "arm"


def cmd_feeding(args) -> int:
    _check_count(args.runs, "--runs")
    progress = Progress("simulate feeding", quiet=args.quiet)
    inst, sc, sc_plant = _setup(args)
    xyz, branch, source = select_layout(sc, seed=args.seed, robot_placement=args.robot_placement)
    progress.say(f"layout {np.round(1000 * xyz).tolist()} mm branch {branch} ({source})")
    case = make_case(_scene_name(sc), sc_plant, xyz, branch, inst, label="selected")
    meshcat = None
    if args.meshcat_html is not None:
        from pydrake.geometry import Meshcat

        meshcat = Meshcat()
    t0 = time.perf_counter()
    operator = _operator(args)
    result = run_feeding(
        case,
        runs=args.runs,
        seed=args.seed,
        mode=args.mode,
        operator=operator,
        meshcat=meshcat,
        progress=progress,
    )
    if meshcat is not None:
        write_text_atomic(args.meshcat_html, meshcat.StaticHtml())
    runs = result["runs"]
    data = {
        "scenario": args.scenario,
        "mode": args.mode,
        "seed": args.seed,
        "instrument": inst.source,
        "layout": {"base_xyz": xyz, "branch": branch, "source": source},
        "X_WBase": case.X_WBase,
        "X_WTarget": case.X_WTarget,
        "operator": dataclasses.asdict(operator),
        "runs": runs,
        "realtime_factor": result["realtime_factor"],
        "summary": {
            "joint_travel_mean": float(np.mean([r["joint_travel"] for r in runs])),
            "joint_travel_std": float(np.std([r["joint_travel"] for r in runs])),
            "max_vf_violation": max(r["max_vf_violation"] for r in runs),
            "min_d_safe": min(r["min_d_safe"] for r in runs),
            "any_alarm": any(r["collision_alarm"] for r in runs),
            "all_reached_target": all(r["reached_target"] for r in runs),
        },
        "wall_seconds_total": time.perf_counter() - t0,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "feeding.json", data, kind="feeding")
    plot_feeding(result, args.out)
    s = data["summary"]
    print(
        f"feeding: {len(runs)} runs, joint travel {s['joint_travel_mean']:.3f} "
        f"+- {s['joint_travel_std']:.3f} rad, max VF violation "
        f"{1000 * s['max_vf_violation']:.3f} mm, min d_safe {1000 * s['min_d_safe']:.1f} mm, "
        f"alarm {s['any_alarm']}, realtime factor {result['realtime_factor']:.1f}x"
    )
    return 0


def cmd_circle(args) -> int:
    _check_count(args.realizations, "--realizations")
    progress = Progress("simulate circle", quiet=args.quiet)
    _, sc, sc_plant = _setup(args)
    xyz, branch, source = select_layout(sc, seed=args.seed, robot_placement=args.robot_placement)
    progress.say(f"layout {np.round(1000 * xyz).tolist()} mm branch {branch} ({source})")
    result = run_circle(sc_plant, xyz, branch, realizations=args.realizations, seed=args.seed)
    if result is None:
        raise PlanningFailure(f"branch {branch} cannot follow the circle continuously")
    data = {
        "scenario": args.scenario,
        "seed": args.seed,
        "layout": {"base_xyz": xyz, "branch": branch, "source": source},
        "circle": {"radius": 0.025, "speed": 0.010, "plane": "Oral Y-Z"},
        "joint_error_eps": sc_plant.eps,
        **result,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "circle.json", data, kind="circle")
    plot_circle(sc_plant, xyz, branch, result, args.out, seed=args.seed)
    print(
        f"circle: mean path error {1000 * result['path_error_mean']:.4f} mm, max "
        f"{1000 * result['path_error_max']:.4f} mm over {args.realizations} joint error draws"
    )
    return 0


def cmd_layouts(args) -> int:
    _check_count(args.random, "--random")
    _check_count(args.runs, "--runs")
    _check_count(args.realizations, "--realizations")
    progress = Progress("analyze layouts", quiet=args.quiet)
    inst, sc, _ = _setup(args)
    result = analyze_layouts(
        args.scenario,
        inst,
        random_layouts=args.random,
        runs=args.runs,
        seed=args.seed,
        robot_placement=args.robot_placement,
        realizations=args.realizations,
        operator=_operator(args),
        progress=progress,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "layouts.json", result, kind="layouts")
    plot_layouts(result, args.out)
    r = result["ranks"]
    n = result["of"]
    print(
        f"layouts: selected ranks joint travel {r['joint_travel']}/{n}, path error "
        f"{r['path_error']}/{n}, GII {r['gii']}/{n}"
    )
    return 0
