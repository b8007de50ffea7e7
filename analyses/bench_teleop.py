"""Benchmark: the safety layer's cost per step and the feeding diagram's realtime factor.

Run: ``python -m implantplan.analyses.bench_teleop [--runs K] [--seed S] [--case default|cylinder]``

Prints, side by side in one run (targets: safety layer <= 50 us per 200 Hz step,
kinematic >= 20x real time, dynamic >= 5x):

- **the safety layer per 200 Hz step** (``timeit.repeat``, best of 7, over the poses and commands
  logged along a feed): the command limiter (its output and its update: two evaluations of the
  one-sample rule per step), the fixture's body law (one compiled call per step: the diagram
  caches it), the supervisor's update (one barrier query per step when the command meets the barrier
  condition) and the FPSM estimator (at 50 Hz: a quarter of its cost per step), each on its own
  with the inputs the diagram gave it; the same along an adversarial push towards the cheek
  with the fixture off (the supervisor alone stops it: its slow path near the wall; each sample
  alone, so without the gradient reuse of consecutive steps), and the supervisor's exclusive
  time per step inside the diagram on that push;
- the full diagram (master, fixture, supervisor, estimator, DiffIK 200 Hz, tool pose, loggers) on
  the case (``default``: site 36 of models/cases/default.yaml planned as ``implantplan plan``
  does; ``cylinder``: seed 000's cylinder check in the lying scenario), one scripted feed per
  run, in kinematic mode and in dynamic mode (plant at 1 ms under inverse dynamics control),
  after 0.5 s of one untimed feed on the same diagram (first calls, not the steady loop);
- the bare-loop reference: the same scene and DiffIK at 200 Hz with two trivial Python systems
  (a constant desired pose and a pass-through), no fixture, no estimator, no loggers;
- the cost share of each Python system in the kinematic run (exclusive time in its callbacks,
  measured by wrapping them), per call and per 200 Hz step;
- the load average at the start and at the end (the timings are wall clock).

Timings on a shared machine are noisy; the ratios in one run are what to compare.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
import timeit
from collections import defaultdict

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.inverse_kinematics import DifferentialInverseKinematicsIntegrator
from pydrake.systems.analysis import Simulator
from pydrake.systems.controllers import InverseDynamicsController
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import StateInterpolatorWithDiscreteDerivative

from implantplan.analyses.studies import adversarial
from implantplan.diagrams import feeding as S
from implantplan.diagrams import teleop as T
from implantplan.systems.teleop.adversarial_operator import Directions, adversarial_motion
from implantplan.systems.teleop.command_limits import CommandLimiter
from implantplan.systems.teleop.fixture_system import VirtualFixtureForceLaw
from implantplan.systems.teleop.fpsm_estimator import FpsmEstimator
from implantplan.systems.teleop.master_device import MasterDevice, feeding_runs
from implantplan.systems.teleop.supervisor import SafetySupervisor

CALLBACKS = {
    "MasterDevice": (MasterDevice, ("_calc_velocity", "_calc_offset", "_calc_handle")),
    "CommandLimiter": (CommandLimiter, ("_calc_limited", "_update", "_calc_status")),
    "VirtualFixtureForceLaw": (
        VirtualFixtureForceLaw,
        ("_calc_corrected", "_calc_violation", "_calc_angle", "_calc_force"),
    ),
    "SafetySupervisor": (
        SafetySupervisor, ("_update", "_calc_desired", "_calc_filtered", "_calc_barrier")
    ),
    "FpsmEstimator": (FpsmEstimator, ("_update", "_calc_cache", "_calc_safety", "_calc_alarm")),
    "ToolPose": (T.ToolPose, ("_calc_pose", "_calc_position")),
}


class ExclusiveTimer:
    """Wraps methods to add up their exclusive wall time (nested calls subtracted)."""

    def __init__(self):
        self.seconds = defaultdict(float)
        self.calls = defaultdict(int)
        self._stack: list[float] = []
        self._saved = []

    def patch(self):
        for name, (cls, methods) in CALLBACKS.items():
            for m in methods:
                original = getattr(cls, m)
                self._saved.append((cls, m, original))
                setattr(cls, m, self._wrap(name, original))

    def restore(self):
        for cls, m, original in self._saved:
            setattr(cls, m, original)
        self._saved.clear()

    def _wrap(self, name, fn):
        def wrapped(*args):
            t0 = time.perf_counter()
            self._stack.append(0.0)
            try:
                return fn(*args)
            finally:
                dt = time.perf_counter() - t0
                child = self._stack.pop()
                self.seconds[name] += dt - child
                self.calls[name] += 1
                if self._stack:
                    self._stack[-1] += dt

        return wrapped


class _ConstantPose(LeafSystem):
    def __init__(self, X):
        super().__init__()
        self._X = RigidTransform(X)
        self.DeclareAbstractOutputPort(
            "X", lambda: AbstractValue.Make(RigidTransform()), self._calc
        )

    def _calc(self, context, value):
        value.set_value(self._X)


class _PassThrough(LeafSystem):
    def __init__(self, n):
        super().__init__()
        self._u = self.DeclareVectorInputPort("u", n)
        self.DeclareVectorOutputPort("y", n, self._calc)
        self.DeclarePeriodicPublishEvent(0.005, 0.0, self._publish)

    def _calc(self, context, output):
        output.SetFromVector(self._u.Eval(context))

    def _publish(self, context):
        self._u.Eval(context)


def bare_loop(case: T.TeleopCase, mode: str, seconds: float) -> float:
    """Realtime factor of DiffIK 200 Hz + two trivial Python systems on the same scene."""
    builder = DiagramBuilder()
    plant, scene_graph = T.add_teleop_scene(builder, case, mode, 0.001)
    q0 = np.asarray(case.q_start, dtype=float)
    tcp = plant.GetFrameByName("tcp")
    diffik = builder.AddSystem(
        DifferentialInverseKinematicsIntegrator(
            plant, tcp, 0.005, T.diffik_parameters(plant, q0, 0.005)
        )
    )
    source = builder.AddSystem(_ConstantPose(case.X_WE(q0)))
    builder.Connect(source.get_output_port(), diffik.GetInputPort("X_AE_desired"))
    sink = builder.AddSystem(_PassThrough(6 if mode == "kinematic" else 12))
    keep = [plant]
    if mode == "kinematic":
        builder.Connect(diffik.GetOutputPort("joint_positions"), sink.get_input_port())
    else:
        arm = plant.GetModelInstanceByName("aubo")
        interp = builder.AddSystem(StateInterpolatorWithDiscreteDerivative(6, 0.005, True))
        ctrl = builder.AddSystem(InverseDynamicsController(plant, [900] * 6, [1] * 6, [60] * 6,
                                                           False))
        builder.Connect(diffik.GetOutputPort("joint_positions"), interp.get_input_port())
        builder.Connect(interp.get_output_port(), ctrl.get_input_port_desired_state())
        builder.Connect(plant.get_state_output_port(arm), ctrl.get_input_port_estimated_state())
        builder.Connect(ctrl.get_output_port_control(), plant.get_actuation_input_port())
        builder.Connect(plant.get_state_output_port(arm), sink.get_input_port())
    diagram = builder.Build()
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    diffik.GetInputPort("use_robot_state").FixValue(diffik.GetMyMutableContextFromRoot(ctx), False)
    diffik.SetPositions(diffik.GetMyMutableContextFromRoot(ctx), q0)
    if mode == "dynamic":
        plant.SetPositions(plant.GetMyMutableContextFromRoot(ctx), q0)
        interp.set_initial_position(interp.GetMyMutableContextFromRoot(ctx), q0)
    sim.Initialize()
    t0 = time.perf_counter()
    sim.AdvanceTo(seconds)
    del keep
    return seconds / (time.perf_counter() - t0)


def safety_layer_cost(teleop: T.Teleop, run: T.FeedRun, motion, *, samples: int = 100,
                      repeat: int = 7, estimator_period: float = 0.02) -> dict:
    """us per 200 Hz step of the fixture, the supervisor and the estimator, each alone on the
    inputs of ``samples`` logged steps of ``run`` (see the module docstring)."""
    case = teleop.case
    k = np.linspace(0, run.t.size - 2, samples).astype(int)
    X_WE = case.X_WE(run.q[k])
    V = np.zeros((samples, 6))
    V[:, 3:] = motion_velocity(motion, run.t[k])
    fixture, supervisor, estimator = teleop.vf, teleop.supervisor, teleop.estimator
    limiter = teleop.limiter
    ctx_f, ctx_s, ctx_e, ctx_l = [], [], [], []
    for i in range(samples):
        X = AbstractValue.Make(RigidTransform(X_WE[i]))
        c = limiter.CreateDefaultContext()
        limiter.GetInputPort("V_WE_command").FixValue(c, V[i])
        ctx_l.append(c)
        c = fixture.CreateDefaultContext()
        fixture.GetInputPort("V_WE_command").FixValue(c, V[i])
        fixture.GetInputPort("X_WE").FixValue(c, X)
        ctx_f.append(c)
        c = supervisor.CreateDefaultContext()
        supervisor.set_desired_pose(c, X_WE[i])
        supervisor.GetInputPort("V_WE_corrected").FixValue(c, fixture.law(ctx_f[-1])[:6])
        ctx_s.append(c)
        c = estimator.CreateDefaultContext()
        estimator.GetInputPort("X_WT").FixValue(c, X)
        ctx_e.append(c)
    ds = supervisor.AllocateDiscreteVariables()
    dl = limiter.AllocateDiscreteVariables()
    out_l = limiter.GetOutputPort("V_WE_limited").Allocate().get_value()

    def best(fn, contexts):
        fn(contexts[0])  # compiled once
        t = timeit.repeat(lambda: [fn(c) for c in contexts], number=1, repeat=repeat)
        return 1e6 * min(t) / len(contexts)

    lim = best(lambda c: (limiter._calc_limited(c, out_l), limiter._update(c, dl)), ctx_l)
    fix = best(fixture.law, ctx_f)
    sup = best(lambda c: supervisor._update(c, ds), ctx_s)
    est = best(estimator.estimate, ctx_e)
    per_step = teleop.period / estimator_period  # build_teleop's default: 50 Hz of 200 Hz
    return {"limiter": lim, "fixture": fix, "supervisor": sup, "estimator": est * per_step,
            "total": lim + fix + sup + est * per_step}


def motion_velocity(motion, t) -> np.ndarray:
    """The master's commanded velocity (World, identity mapping) at times t (zero-order hold)."""
    v = motion.velocity_M()
    return v[np.clip(np.floor(np.asarray(t) / motion.dt + 1e-9).astype(int), 0, len(v) - 1)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=2, help="feeds per mode (default 2)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--case", choices=("default", "cylinder"), default="default",
                        help="default: site 36 of the bundled case; cylinder: seed 000's check")
    parser.add_argument("--head-motion", help="also time the kinematic diagram with this head "
                        "motion on (breathing|swallow|startle|drift; target >= 5x)")
    args = parser.parse_args(argv)
    load = os.getloadavg()  # timings on a shared machine: printed with the load

    if args.case == "default":
        case = adversarial.default_case_sites()[0][0]
    else:
        sc, sc_plant = S.load_scenario("lying")
        xyz, branch, _ = S.knee_layout(sc, seed=args.seed)
        case = S.make_case("lying", sc_plant, xyz, branch, S.default_instrument(args.seed))
    start, target = case.X_WE(case.q_start)[:3, 3], case.X_WTarget[:3, 3]
    motions = feeding_runs(start, target, runs=args.runs, seed=args.seed)
    push = adversarial_motion("cheek_left", start, target,
                              Directions.of_case(case.X_WTarget, case.X_WCenter), seed=args.seed)

    rows = []
    diagrams = {}
    for mode in ("kinematic", "dynamic"):
        sim = wall = 0.0
        teleop = diagrams[mode] = T.build_teleop(case, mode=mode)
        # one untimed feed first: the kernels' first calls (loaded from numba's cache) and
        # Drake's first allocations are not the loop's steady cost
        T.simulate(teleop, 0.5, motion=motions[0])
        for m in motions:
            run = T.simulate(teleop, m.duration + S.FINISH_SECONDS, motion=m)
            sim += run.sim_seconds
            wall += run.wall_seconds
        if mode == "kinematic":
            kin_run = run
        seconds = sim / len(motions)
        rows.append((mode, sim / wall, bare_loop(case, mode, seconds)))
    if args.head_motion:  # the awake patient: tracker, guard, moving patient (kinematic only)
        from implantplan.systems.teleop.head_motion import HeadMotion, neck_of

        hm = HeadMotion.make(args.head_motion, seed=args.seed, pivot=case.X_WCenter[:3, 3],
                             neck=neck_of(case.X_WCenter))
        head = T.build_teleop(case, head_motion=hm)
        runs = [T.simulate(head, m.duration + S.FINISH_SECONDS, motion=m) for m in motions]
        rows.append((f"kin+{args.head_motion}", sum(r.sim_seconds for r in runs)
                     / sum(r.wall_seconds for r in runs), rows[0][2]))
    kin = diagrams["kinematic"]
    calm = safety_layer_cost(kin, kin_run, motions[-1])
    # the push with the fixture off, so that the supervisor's barrier does the stopping (its
    # slow path: gradient and projection) at the steps near the wall
    bare_fixture = T.build_teleop(case, vf_enabled=False)
    push_run = T.simulate(bare_fixture, push.duration + 0.5, motion=push)
    pushed = safety_layer_cost(bare_fixture, push_run, push)
    # the same logged steps with the FPSM's bound in the supervisor and the estimator instead
    # of the capped scan bound (the diagram without the plan's scan)
    fpsm_case = dataclasses.replace(case, scan=None)
    calm_fpsm = safety_layer_cost(T.build_teleop(fpsm_case), kin_run, motions[-1])
    pushed_fpsm = safety_layer_cost(T.build_teleop(fpsm_case, vf_enabled=False), push_run, push)
    # the cost shares: the same kinematic feeds again on a diagram built with wrapped callbacks
    # (the wrapping adds its own overhead, so the realtime factors above come from plain ones)
    timer = ExclusiveTimer()
    timer.patch()  # before building: the ports keep the methods they were given
    try:
        timed = T.build_teleop(case)
    finally:
        timer.restore()
    kin_sim = kin_wall = 0.0
    for m in motions:
        run = T.simulate(timed, m.duration + S.FINISH_SECONDS, motion=m)
        kin_sim += run.sim_seconds
        kin_wall += run.wall_seconds
    # the supervisor inside the diagram on the push (fixture off), its gradient reused at the wall
    push_timer = ExclusiveTimer()
    push_timer.patch()
    try:
        timed_push = T.build_teleop(case, vf_enabled=False)
    finally:
        push_timer.restore()
    steps = T.simulate(timed_push, push.duration + 0.5, motion=push).t.size
    in_loop = 1e6 * push_timer.seconds["SafetySupervisor"] / steps

    bound = "the capped scan bound" if case.scan is not None else "the FPSM bound"
    print(f"safety layer per 200 Hz step (us, best of 7 over 100 logged steps; {args.case} "
          f"case, {case.tool.name} instrument, {bound}; target <= 50 us)")
    print(f"{'feed':<22} {'limiter':>8} {'fixture':>8} {'supervisor':>11} {'estimator/4':>12} "
          f"{'total':>8}")
    for name, c in (("calm scripted feed", calm), ("cheek push, no fixture", pushed),
                    ("calm, FPSM bound", calm_fpsm), ("push, FPSM bound", pushed_fpsm)):
        print(f"{name:<22} {c['limiter']:>8.1f} {c['fixture']:>8.1f} {c['supervisor']:>11.1f} "
              f"{c['estimator']:>12.1f} {c['total']:>8.1f}")
    print(f"  in the loop on the push (its gradient reused over steps at the wall): supervisor "
          f"{in_loop:.1f} us per step")
    print(f"  (supervisor active at {100 * push_run.barrier[:, 2].mean():.0f}% of the push's "
          f"steps, {100 * kin_run.barrier[:, 2].mean():.0f}% of the calm feed's; min barrier "
          f"{1e3 * push_run.barrier[:, 0].min():.3f} mm on the push)")
    print()
    print(f"feeding diagram, {args.case} case, {args.runs} feed(s) per mode "
          f"(~{seconds:.1f} s simulated each)")
    print(f"{'mode':<10} {'full diagram':>14} {'bare loop':>11} {'full/bare':>10} {'target':>8}")
    for mode, full, bare in rows:
        target = ">= 20x" if mode == "kinematic" else ">= 5x"
        print(f"{mode:<10} {full:>13.1f}x {bare:>10.1f}x {full / bare:>10.2f} {target:>8}")
    print("before the safety layer (measured then): kinematic 7-9x, bare loop 58x")
    print()
    print(
        f"Python systems in the kinematic runs ({kin_sim:.1f} s simulated, "
        f"{kin_wall:.2f} s wall):"
    )
    steps = kin_sim / kin.period  # 200 Hz control steps
    print(f"{'system':<24} {'calls':>8} {'us/call':>9} {'us/step':>8} {'share of wall':>14}")
    total = 0.0
    for name in CALLBACKS:
        s, n = timer.seconds[name], timer.calls[name]
        total += s
        print(f"{name:<24} {n:>8d} {1e6 * s / max(n, 1):>9.1f} {1e6 * s / steps:>8.1f} "
              f"{100 * s / kin_wall:>13.1f}%")
    print(f"{'all Python systems':<24} {'':>8} {'':>9} {1e6 * total / steps:>8.1f} "
          f"{100 * total / kin_wall:>13.1f}%")
    print(f"load average (1, 5, 15 min) at the start {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, "
          "at the end {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
